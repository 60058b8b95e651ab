//! Dense bundle adjustment over a keyframe window (paper §3.1, Eq. 1-4).
//!
//! # Problem (Eq. 1)
//! Keyframe `k` has a pose `world_from_cam_k` and a low-resolution inverse depth map `d_k`
//! (e.g. 40x30 for a 320x240 input at 1/8, with the [`PinholeCamera`] scaled to match). An
//! edge `(i, j)` gives, for every pixel `p` of keyframe `i`, a target position `p*_ij` in
//! keyframe `j` (the flow-corrected correspondence, low-res pixel units) and per-coordinate
//! confidences `(w_x, w_y) >= 0`, the diagonal of `Sigma_ij^-1`. The residual is
//!
//! ```text
//! r_ij(p) = p*_ij(p) - Pi(cam_j_from_cam_i * Pi^-1(p, d_i(p)))
//! cost    = sum_ij sum_p rho(|r|_W) + 1/2 w_prior sum_k sum_p (d_k(p) - d0_k(p))^2
//! ```
//!
//! with `|r|_W = sqrt(w_x r_x^2 + w_y r_y^2)` the whitened residual and `rho` the Huber
//! function with threshold [`BaConfig::huber_threshold`] (`rho(s) = s^2/2` below it).
//! Points are carried homogeneously, `(x_n, y_n, 1, d)`, as in DROID-SLAM, so pixels at
//! infinity (`d -> 0`) stay well conditioned.
//!
//! # Unknowns and perturbation convention
//! A 6-dof twist `xi = [v; omega]` (translation first, as [`se3_exp`](duv_core::pose::se3_exp))
//! per free pose, applied on the **right** of the camera-to-world pose, i.e. in the camera's
//! own frame: `world_from_cam <- world_from_cam * exp(xi)`. (Equivalently a left update of
//! `cam_from_world` by `exp(-xi)`; the paper's Eq. 2 writes the update on the left of the
//! world-to-camera pose.) One additive increment per inverse depth pixel of every keyframe,
//! clamped below at [`BaConfig::min_inv_depth`] so depths stay positive. Pose covariances are
//! expressed in the same right-perturbation tangent space.
//!
//! # Gauge and scale
//! The first [`BaConfig::fixed_poses`] keyframes (default 1) are held fixed: this removes the
//! 6-dof rigid gauge. Monocular scale (scaling every translation about the fixed camera and
//! every inverse depth by the inverse factor) is unobservable with a single fixed pose. It is
//! handled by a weak quadratic prior pulling each inverse depth towards its value when the
//! keyframe was loaded, weight [`BaConfig::depth_prior_weight`], plus the LM damping. The
//! prior is a genuine term of the cost, so the full Hessian is positive definite, the Schur
//! complement is invertible without damping, and the covariance (Eq. 4) is finite, with a
//! large variance along the scale direction. At the default weight (1e-4, far below what one
//! observation contributes) the prior barely pulls: the scale stays close to where the
//! loaded poses and depths put it, and a solve from poorly scaled initial poses can settle a
//! few percent off (the tracker re-anchors it window after window, as DROID-SLAM does). With
//! `fixed_poses >= 2` (and a non-zero baseline between the fixed poses) the scale is fixed by
//! the gauge instead.
//!
//! # Solver (Eq. 3)
//! Damped Gauss-Newton (Levenberg-Marquardt): the normal equations `H [dxi; dd] = [b_p; b_d]`
//! (with `H = J^T W J`, `b = J^T W r`, `J = d(prediction)/d(state)`) are damped as
//! `H_ii <- H_ii (1 + lambda)` on the whole diagonal, reduced onto the poses with the Schur
//! complement `S = H_pp - H_pd H_dd^-1 H_dp`, `g = b_p - H_pd H_dd^-1 b_d`, solved by a dense
//! Cholesky factorisation (faer), and the depth increments recovered by back-substitution,
//! `dd = H_dd^-1 (b_d - H_dp dxi)`. A step is accepted when it lowers the cost (lambda
//! shrinks, down to 1e-12), rejected otherwise (lambda grows, to at least 1e-6); a reduced
//! system that is not positive definite counts as a rejection. Pixels whose undamped `H_dd`
//! (prior included) is below [`BaConfig::min_depth_hessian`] are frozen: no increment, no
//! Schur contribution, infinite variance. With the default non-zero prior weight no pixel is
//! ever frozen.
//!
//! # Uncertainty (Eq. 4)
//! From the undamped system at the current estimate (robust weights included):
//! `Sigma_P = S^-1` and, per pixel, `var_d = 1/H_dd + (1/H_dd)^2 b^T S^-1 b`, with `b` the
//! pixel's column of `H_pd` (one 6-block per free pose the pixel couples to: its own
//! keyframe's pose and the pose of every keyframe its edges point to). `S^-1` is computed
//! once; each pixel then costs one small quadratic form over the poses it couples to.
//!
//! # Memory
//! [`BaWorkspace`] is sized once from a [`BaCapacity`]; loading a window, solving and computing
//! covariances never allocate afterwards (proven by `tests/ba_alloc.rs`).

mod covariance;
mod linearize;
mod motion_only;
mod schur;
mod solve;
mod workspace;

pub use linearize::{huber_cost, huber_weight, reproject, Reprojection, MIN_PROJECTED_Z};
pub use motion_only::{solve_motion_only, MotionOnlyObservation, MotionOnlyReport};
pub use solve::{BaReport, Termination};
pub use workspace::BaWorkspace;

#[cfg(doc)]
use duv_core::PinholeCamera;

/// Which fixed capacity of a [`BaWorkspace`] a request exceeded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Capacity {
    Keyframes,
    PixelsPerKeyframe,
    Edges,
}

impl std::fmt::Display for Capacity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Capacity::Keyframes => "keyframes",
            Capacity::PixelsPerKeyframe => "pixels per keyframe",
            Capacity::Edges => "edges",
        })
    }
}

/// Why a bundle adjustment could not be set up or solved. Bad input is reported here, never
/// by a panic.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BaError {
    #[error("BA capacity exceeded: {requested} {capacity} requested, workspace holds {limit}")]
    CapacityExceeded { capacity: Capacity, limit: usize, requested: usize },
    #[error("BA window is empty: no keyframes loaded")]
    EmptyWindow,
    #[error("BA window has no edges")]
    NoEdges,
    #[error("no camera set: call BaWorkspace::begin first")]
    NotStarted,
    #[error("BA camera must be undistorted (use PinholeCamera::undistorted on rectified images)")]
    DistortedCamera,
    #[error("BA camera is invalid: {0}")]
    BadCamera(#[from] duv_core::CameraModelError),
    #[error("keyframe {keyframe} is not in the window ({keyframes} loaded)")]
    NoSuchKeyframe { keyframe: usize, keyframes: usize },
    #[error("motion-only BA: the frame's initial pose has a non-finite value")]
    NonFiniteFramePose,
    #[error("keyframe {keyframe}: pose has a non-finite value")]
    NonFinitePose { keyframe: usize },
    #[error("keyframe {keyframe}: inverse depth map is {width}x{height}, camera is {expected_width}x{expected_height}")]
    DepthSizeMismatch { keyframe: usize, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("keyframe {keyframe}, pixel {pixel}: inverse depth {value} is not finite and positive")]
    BadInverseDepth { keyframe: usize, pixel: usize, value: f32 },
    #[error("edge {edge}: {width}x{height} measurements, camera is {expected_width}x{expected_height}")]
    MeasurementSizeMismatch { edge: usize, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("edge {edge} ({from} -> {to}) refers to a keyframe that is not loaded ({keyframes} loaded)")]
    EdgeToMissingKeyframe { edge: usize, from: usize, to: usize, keyframes: usize },
    #[error("edge {edge} connects keyframe {keyframe} to itself")]
    SelfEdge { edge: usize, keyframe: usize },
    #[error("edge {edge}, pixel {pixel}: target ({x}, {y}) is not finite")]
    NonFiniteTarget { edge: usize, pixel: usize, x: f32, y: f32 },
    #[error("edge {edge}, pixel {pixel}: weight ({wx}, {wy}) must be finite and >= 0")]
    BadWeight { edge: usize, pixel: usize, wx: f32, wy: f32 },
    #[error("keyframe {keyframe} is a free pose but no edge touches it")]
    UnconstrainedPose { keyframe: usize },
    #[error("reduced pose system ({dim}x{dim}) is not positive definite (pivot {pivot}) at damping {damping}")]
    SingularSystem { dim: usize, pivot: usize, damping: f64 },
    #[error("BA config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
    #[error("motion-only BA: no usable measurement")]
    NoMeasurements,
    #[error("keyframe {keyframe}: inverse depth variance map is {width}x{height}, camera is {expected_width}x{expected_height}")]
    VarianceSizeMismatch { keyframe: usize, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("keyframe {keyframe}, pixel {pixel}: inverse depth variance {value} is NaN or negative")]
    BadVariance { keyframe: usize, pixel: usize, value: f32 },
    #[error("keyframe {keyframe}: variance of unit weight {value} must be finite and positive")]
    BadVarianceOfUnitWeight { keyframe: usize, value: f32 },
}

/// Fixed sizes of a [`BaWorkspace`], chosen once from the board (BA window, depth resolution).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BaCapacity {
    /// Keyframes in the window, fixed ones included.
    pub max_keyframes: usize,
    /// Pixels of one low-resolution inverse depth map (width x height).
    pub max_pixels_per_keyframe: usize,
    /// Directed edges (i, j) in the window.
    pub max_edges: usize,
}

/// Parameters of the window solve; also used by [`solve_motion_only`]. Defaults live in
/// [`BaConfig::default`] and nowhere else.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BaConfig {
    /// Gauss-Newton / LM iterations (solve attempts, accepted or not) per `solve` call.
    pub max_iterations: usize,
    /// Number of leading keyframes held fixed (gauge); at least 1.
    pub fixed_poses: usize,
    /// Huber threshold on the whitened residual norm `sqrt(w_x r_x^2 + w_y r_y^2)`, in sigmas
    /// when the weights are inverse variances (about low-res pixels for confidences in [0, 1]).
    pub huber_threshold: f64,
    /// Initial Levenberg-Marquardt damping lambda (diagonal scaled by `1 + lambda`).
    pub initial_damping: f64,
    /// Factor applied to lambda after a rejected step (> 1).
    pub damping_increase: f64,
    /// Factor applied to lambda after an accepted step (in (0, 1]).
    pub damping_decrease: f64,
    /// Lambda above which the solve stops (no step lowers the cost any more).
    pub max_damping: f64,
    /// Weight of the prior pulling each inverse depth to its loaded value, per (1/m)^2; fixes
    /// monocular scale and keeps unobserved pixels defined. 0 disables it.
    pub depth_prior_weight: f64,
    /// Pixels whose undamped depth Hessian is below this are frozen (no update, infinite variance).
    pub min_depth_hessian: f64,
    /// Inverse depth floor after an update, 1/m (keeps depths positive and finite).
    pub min_inv_depth: f64,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub cost_tolerance: f64,
    /// Stop when every pose twist component and every relative inverse depth change is below this.
    pub step_tolerance: f64,
}

impl Default for BaConfig {
    fn default() -> Self {
        BaConfig {
            max_iterations: 10,
            fixed_poses: 1,
            huber_threshold: 1.5,
            initial_damping: 1e-4,
            damping_increase: 10.0,
            damping_decrease: 0.1,
            max_damping: 1e8,
            depth_prior_weight: 1e-4,
            min_depth_hessian: 1e-9,
            min_inv_depth: 1e-3,
            cost_tolerance: 1e-9,
            step_tolerance: 1e-8,
        }
    }
}

impl BaConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), BaError> {
        let bad = |field: &'static str, value: f64, why: &'static str| Err(BaError::InvalidConfig { field, value, why });
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        if self.max_iterations == 0 {
            return bad("max_iterations", 0.0, "must be at least 1");
        }
        if self.fixed_poses == 0 {
            return bad("fixed_poses", 0.0, "must be at least 1 (the gauge)");
        }
        if !positive(self.huber_threshold) {
            return bad("huber_threshold", self.huber_threshold, "must be finite and > 0");
        }
        if !non_negative(self.initial_damping) {
            return bad("initial_damping", self.initial_damping, "must be finite and >= 0");
        }
        if !(self.damping_increase.is_finite() && self.damping_increase > 1.0) {
            return bad("damping_increase", self.damping_increase, "must be finite and > 1");
        }
        if !(self.damping_decrease > 0.0 && self.damping_decrease <= 1.0) {
            return bad("damping_decrease", self.damping_decrease, "must be in (0, 1]");
        }
        if !(positive(self.max_damping) && self.max_damping >= self.initial_damping) {
            return bad("max_damping", self.max_damping, "must be finite, > 0 and >= initial_damping");
        }
        if !non_negative(self.depth_prior_weight) {
            return bad("depth_prior_weight", self.depth_prior_weight, "must be finite and >= 0");
        }
        if !positive(self.min_depth_hessian) {
            return bad("min_depth_hessian", self.min_depth_hessian, "must be finite and > 0");
        }
        if !positive(self.min_inv_depth) {
            return bad("min_inv_depth", self.min_inv_depth, "must be finite and > 0");
        }
        if !non_negative(self.cost_tolerance) {
            return bad("cost_tolerance", self.cost_tolerance, "must be finite and >= 0");
        }
        if !non_negative(self.step_tolerance) {
            return bad("step_tolerance", self.step_tolerance, "must be finite and >= 0");
        }
        Ok(())
    }
}

/// Intrinsics at the depth-map resolution, checked to be undistorted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
}

impl Intrinsics {
    pub fn from_camera(camera: &duv_core::PinholeCamera) -> Result<Self, BaError> {
        camera.validate()?;
        if camera.distortion.is_some() {
            return Err(BaError::DistortedCamera);
        }
        Ok(Intrinsics { fx: camera.fx, fy: camera.fy, cx: camera.cx, cy: camera.cy, width: camera.width, height: camera.height })
    }

    /// Normalised-plane coordinates `(x_n, y_n)` of pixel index `p` (row-major).
    #[inline]
    pub fn ray(&self, p: usize) -> [f64; 2] {
        let (u, v) = ((p % self.width) as f64, (p / self.width) as f64);
        [(u - self.cx) / self.fx, (v - self.cy) / self.fy]
    }
}
