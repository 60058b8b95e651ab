//! [`BaWorkspace`]: every buffer of the window solve, allocated once from a [`BaCapacity`].
//! Loading a window (`begin`, `add_keyframe`, `add_edge`), `solve`, `compute_covariance` and
//! the accessors only write into these buffers; nothing allocates after `new`.

use faer::dyn_stack::{MemBuffer, StackReq};
use faer::linalg::cholesky::llt;
use faer::Par;
use nalgebra::{Matrix6, Vector6};

use super::{BaCapacity, BaConfig, BaError, Capacity, Intrinsics};
use duv_core::{Image, PinholeCamera, PlaneF32, Se3};

/// Marks a (keyframe, pose) pair without a coupling slot.
pub(crate) const NO_SLOT: usize = usize::MAX;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Edge {
    pub from: usize,
    pub to: usize,
}

/// The loaded problem: camera, state, measurements. Depth-like arrays are indexed
/// `keyframe * n_pixels + pixel`; measurements `(edge * n_pixels + pixel) * 2 + axis`.
pub(crate) struct Window {
    pub started: bool,
    pub intr: Intrinsics,
    pub n_keyframes: usize,
    pub n_pixels: usize,
    pub n_edges: usize,
    /// Normalised-plane coordinates of every pixel.
    pub rays: Vec<[f64; 2]>,
    pub world_from_cam: Vec<Se3>,
    pub inv_depth: Vec<f64>,
    /// Inverse depth as loaded: the anchor of the depth prior.
    pub prior_inv_depth: Vec<f64>,
    pub edges: Vec<Edge>,
    pub target_xy: Vec<f64>,
    pub weight_xy: Vec<f64>,
}

impl Window {
    #[inline]
    pub fn intrinsics(&self) -> Intrinsics {
        self.intr
    }
}

/// A free pose that a keyframe's depths couple to, and where that coupling column lives.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Coupling {
    /// Index of the pose among the free poses (block row of the reduced system).
    pub free: usize,
    /// Slot of the 6 x n_pixels block of `H_pd`.
    pub slot: usize,
}

/// Sparsity of `H_pd`: the depths of keyframe `k` couple to the pose of `k` and to the pose
/// of every `j` with an edge `(k, j)`; each such free pose gets one slot.
pub(crate) struct Structure {
    pub fixed: usize,
    pub n_free: usize,
    pub n_slots: usize,
    stride: usize,
    slot_of: Vec<usize>,
    couplings: Vec<Coupling>,
    coupling_start: Vec<usize>,
}

impl Structure {
    #[inline]
    pub fn free_index(&self, k: usize) -> Option<usize> {
        (k >= self.fixed).then(|| k - self.fixed)
    }
    #[inline]
    pub fn slot(&self, keyframe: usize, pose: usize) -> usize {
        self.slot_of[keyframe * self.stride + pose]
    }
    #[inline]
    pub fn couplings_of(&self, k: usize) -> &[Coupling] {
        &self.couplings[self.coupling_start[k]..self.coupling_start[k + 1]]
    }

    fn build(&mut self, win: &Window, fixed_poses: usize) {
        let n = win.n_keyframes;
        self.fixed = fixed_poses.min(n);
        self.n_free = n - self.fixed;
        self.slot_of[..self.stride * self.stride].fill(NO_SLOT);
        let mut len = 0;
        for k in 0..n {
            self.coupling_start[k] = len;
            let has_edges = win.edges[..win.n_edges].iter().any(|e| e.from == k);
            let poses = std::iter::once(k).filter(|_| has_edges).chain(win.edges[..win.n_edges].iter().filter(|e| e.from == k).map(|e| e.to));
            for m in poses {
                if let Some(free) = self.free_index(m) {
                    if self.slot_of[k * self.stride + m] == NO_SLOT {
                        self.slot_of[k * self.stride + m] = len;
                        self.couplings[len] = Coupling { free, slot: len };
                        len += 1;
                    }
                }
            }
        }
        self.coupling_start[n] = len;
        self.n_slots = len;
    }
}

/// The undamped normal equations at the current state.
pub(crate) struct System {
    /// Dense `6 n_free` square, column-major.
    pub h_pp: Vec<f64>,
    pub b_p: Vec<f64>,
    /// `(slot * n_pixels + pixel) * 6 + row`.
    pub h_pd: Vec<f64>,
    pub h_dd: Vec<f64>,
    pub b_d: Vec<f64>,
    /// `sum rho'(s) (w_x r_x^2 + w_y r_y^2)` over the flow residuals (Huber-weighted, prior
    /// excluded): the numerator of the variance of unit weight.
    pub weighted_sq_residual: f64,
    /// Residual components with a non-zero weight.
    pub residuals: usize,
    /// Inverse depths with at least one flow observation.
    pub observed_depths: usize,
}

/// The reduced (Schur) system, the step, and faer's scratch memory.
pub(crate) struct Reduced {
    /// Damped Schur complement, overwritten by its Cholesky factor.
    pub s: Vec<f64>,
    /// Reduced right-hand side, overwritten by the pose step.
    pub rhs: Vec<f64>,
    /// `1 / H_dd` (damped as the last reduction asked), 0 for frozen pixels.
    pub inv_hdd: Vec<f64>,
    /// Pose step, `6 n_free`, block per free pose.
    pub step_pose: Vec<f64>,
    pub step_inv_depth: Vec<f64>,
    pub scratch: MemBuffer,
}

/// Trial state of a damped step.
pub(crate) struct Trial {
    pub world_from_cam: Vec<Se3>,
    pub inv_depth: Vec<f64>,
}

/// Outputs of `compute_covariance`.
pub(crate) struct Covariance {
    pub valid: bool,
    /// `S^-1`, `6 n_free` square, column-major, symmetric.
    pub pose: Vec<f64>,
    pub inv_depth_var: Vec<f64>,
    /// Variance of unit weight at the estimate (`None`: no more residuals than unknowns).
    pub unit_variance: Option<f64>,
}

/// Fixed-memory dense bundle adjustment over a keyframe window. See the [module
/// docs](super) for the model; a typical use per window:
///
/// ```no_run
/// # use duv_track::ba::{BaCapacity, BaConfig, BaWorkspace};
/// # use duv_core::{Image, PinholeCamera, PlaneF32, Se3};
/// # fn demo(camera: &PinholeCamera, poses: &[Se3], depths: &[PlaneF32], target: &Image<f32, 2>, weight: &Image<f32, 2>) -> Result<(), duv_track::ba::BaError> {
/// let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 8, max_pixels_per_keyframe: 40 * 30, max_edges: 24 });
/// ws.begin(camera)?;
/// for (pose, depth) in poses.iter().zip(depths) {
///     ws.add_keyframe(pose, depth)?;
/// }
/// ws.add_edge(1, 0, target, weight)?;
/// let report = ws.solve(&BaConfig::default())?;
/// ws.compute_covariance(&BaConfig::default())?;
/// let world_from_cam_1 = ws.world_from_cam(1);
/// # Ok(()) }
/// ```
pub struct BaWorkspace {
    pub(crate) capacity: BaCapacity,
    pub(crate) win: Window,
    pub(crate) st: Structure,
    pub(crate) sys: System,
    pub(crate) red: Reduced,
    pub(crate) trial: Trial,
    pub(crate) cov: Covariance,
    /// The config the current linearisation was built with, and the cost there; `None` when
    /// the state or the window changed since.
    pub(crate) linearized: Option<(BaConfig, f64)>,
    /// Whether `red.step_*` holds a step for the current linearisation.
    pub(crate) step_valid: bool,
}

impl std::fmt::Debug for BaWorkspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BaWorkspace")
            .field("capacity", &self.capacity)
            .field("keyframes", &self.win.n_keyframes)
            .field("pixels", &self.win.n_pixels)
            .field("edges", &self.win.n_edges)
            .finish_non_exhaustive()
    }
}

impl BaWorkspace {
    /// Allocates every buffer for the given capacities (the only allocation of the solver).
    pub fn new(capacity: BaCapacity) -> Self {
        let BaCapacity { max_keyframes: nk, max_pixels_per_keyframe: np, max_edges: ne } = capacity;
        let dim = 6 * nk;
        let max_slots = nk + ne;
        let scratch = StackReq::any_of(&[
            llt::factor::cholesky_in_place_scratch::<f64>(dim, Par::Seq, Default::default()),
            llt::solve::solve_in_place_scratch::<f64>(dim, 1, Par::Seq),
            llt::inverse::inverse_scratch::<f64>(dim, Par::Seq),
        ]);
        let intr = Intrinsics { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0, width: 0, height: 0 };
        BaWorkspace {
            capacity,
            win: Window {
                started: false,
                intr,
                n_keyframes: 0,
                n_pixels: 0,
                n_edges: 0,
                rays: vec![[0.0; 2]; np],
                world_from_cam: vec![Se3::identity(); nk],
                inv_depth: vec![0.0; nk * np],
                prior_inv_depth: vec![0.0; nk * np],
                edges: vec![Edge::default(); ne],
                target_xy: vec![0.0; ne * np * 2],
                weight_xy: vec![0.0; ne * np * 2],
            },
            st: Structure {
                fixed: 0,
                n_free: 0,
                n_slots: 0,
                stride: nk,
                slot_of: vec![NO_SLOT; nk * nk],
                couplings: vec![Coupling::default(); max_slots],
                coupling_start: vec![0; nk + 1],
            },
            sys: System {
                h_pp: vec![0.0; dim * dim],
                b_p: vec![0.0; dim],
                h_pd: vec![0.0; max_slots * np * 6],
                h_dd: vec![0.0; nk * np],
                b_d: vec![0.0; nk * np],
                weighted_sq_residual: 0.0,
                residuals: 0,
                observed_depths: 0,
            },
            red: Reduced {
                s: vec![0.0; dim * dim],
                rhs: vec![0.0; dim],
                inv_hdd: vec![0.0; nk * np],
                step_pose: vec![0.0; dim],
                step_inv_depth: vec![0.0; nk * np],
                scratch: MemBuffer::new(scratch),
            },
            trial: Trial { world_from_cam: vec![Se3::identity(); nk], inv_depth: vec![0.0; nk * np] },
            cov: Covariance { valid: false, pose: vec![0.0; dim * dim], inv_depth_var: vec![0.0; nk * np], unit_variance: None },
            linearized: None,
            step_valid: false,
        }
    }

    pub fn capacity(&self) -> BaCapacity {
        self.capacity
    }

    /// Starts a new window for a camera at the depth-map resolution (undistorted pinhole);
    /// drops any loaded keyframes and edges.
    pub fn begin(&mut self, camera: &PinholeCamera) -> Result<(), BaError> {
        let intr = Intrinsics::from_camera(camera)?;
        let n_pixels = intr.width * intr.height;
        if n_pixels > self.capacity.max_pixels_per_keyframe {
            return Err(BaError::CapacityExceeded {
                capacity: Capacity::PixelsPerKeyframe,
                limit: self.capacity.max_pixels_per_keyframe,
                requested: n_pixels,
            });
        }
        let win = &mut self.win;
        win.intr = intr;
        win.n_pixels = n_pixels;
        win.n_keyframes = 0;
        win.n_edges = 0;
        for (p, ray) in win.rays[..n_pixels].iter_mut().enumerate() {
            *ray = intr.ray(p);
        }
        win.started = true;
        self.invalidate();
        Ok(())
    }

    /// Adds keyframe number `num_keyframes()` with its pose and inverse depth map (1/m, at
    /// the camera's resolution, every value finite and > 0). The loaded depths are also the
    /// anchor of the depth prior.
    pub fn add_keyframe(&mut self, world_from_cam: &Se3, inv_depth: &PlaneF32) -> Result<usize, BaError> {
        let win = &mut self.win;
        if !win.started {
            return Err(BaError::NotStarted);
        }
        let k = win.n_keyframes;
        if k >= self.capacity.max_keyframes {
            return Err(BaError::CapacityExceeded { capacity: Capacity::Keyframes, limit: self.capacity.max_keyframes, requested: k + 1 });
        }
        let (w, h) = (win.intr.width, win.intr.height);
        if inv_depth.width != w || inv_depth.height != h || inv_depth.data.len() != w * h {
            return Err(BaError::DepthSizeMismatch { keyframe: k, width: inv_depth.width, height: inv_depth.height, expected_width: w, expected_height: h });
        }
        let finite_pose = world_from_cam.translation.vector.iter().chain(world_from_cam.rotation.coords.iter()).all(|v| v.is_finite());
        if !finite_pose {
            return Err(BaError::NonFinitePose { keyframe: k });
        }
        if let Some(pixel) = inv_depth.data.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(BaError::BadInverseDepth { keyframe: k, pixel, value: inv_depth.data[pixel] });
        }
        let n = win.n_pixels;
        for (dst, src) in win.inv_depth[k * n..(k + 1) * n].iter_mut().zip(&inv_depth.data) {
            *dst = *src as f64;
        }
        win.prior_inv_depth[k * n..(k + 1) * n].copy_from_slice(&win.inv_depth[k * n..(k + 1) * n]);
        win.world_from_cam[k] = *world_from_cam;
        win.n_keyframes += 1;
        self.invalidate();
        Ok(k)
    }

    /// Adds an edge: for every pixel of keyframe `from`, its target position `(x, y)` in
    /// keyframe `to` (low-res pixels, channel 0 = x) and the confidences `(w_x, w_y)` of the
    /// two coordinates (diagonal inverse covariance; 0 drops the coordinate). Both keyframes
    /// must already be loaded; targets finite, weights finite and >= 0.
    pub fn add_edge(&mut self, from: usize, to: usize, target_xy: &Image<f32, 2>, weight_xy: &Image<f32, 2>) -> Result<usize, BaError> {
        let win = &mut self.win;
        if !win.started {
            return Err(BaError::NotStarted);
        }
        let e = win.n_edges;
        if e >= self.capacity.max_edges {
            return Err(BaError::CapacityExceeded { capacity: Capacity::Edges, limit: self.capacity.max_edges, requested: e + 1 });
        }
        if from >= win.n_keyframes || to >= win.n_keyframes {
            return Err(BaError::EdgeToMissingKeyframe { edge: e, from, to, keyframes: win.n_keyframes });
        }
        if from == to {
            return Err(BaError::SelfEdge { edge: e, keyframe: from });
        }
        let (w, h) = (win.intr.width, win.intr.height);
        for m in [target_xy, weight_xy] {
            if m.width != w || m.height != h || m.data.len() != 2 * w * h {
                return Err(BaError::MeasurementSizeMismatch { edge: e, width: m.width, height: m.height, expected_width: w, expected_height: h });
            }
        }
        for (pixel, (t, wt)) in target_xy.data.chunks_exact(2).zip(weight_xy.data.chunks_exact(2)).enumerate() {
            if !(t[0].is_finite() && t[1].is_finite()) {
                return Err(BaError::NonFiniteTarget { edge: e, pixel, x: t[0], y: t[1] });
            }
            if !(wt[0].is_finite() && wt[1].is_finite() && wt[0] >= 0.0 && wt[1] >= 0.0) {
                return Err(BaError::BadWeight { edge: e, pixel, wx: wt[0], wy: wt[1] });
            }
        }
        let n2 = 2 * win.n_pixels;
        for (dst, src) in win.target_xy[e * n2..(e + 1) * n2].iter_mut().zip(&target_xy.data) {
            *dst = *src as f64;
        }
        for (dst, src) in win.weight_xy[e * n2..(e + 1) * n2].iter_mut().zip(&weight_xy.data) {
            *dst = *src as f64;
        }
        win.edges[e] = Edge { from, to };
        win.n_edges += 1;
        self.invalidate();
        Ok(e)
    }

    pub fn num_keyframes(&self) -> usize {
        self.win.n_keyframes
    }

    pub fn num_edges(&self) -> usize {
        self.win.n_edges
    }

    /// Current estimate of keyframe `k`'s pose.
    pub fn world_from_cam(&self, k: usize) -> Option<Se3> {
        (k < self.win.n_keyframes).then(|| self.win.world_from_cam[k])
    }

    /// Current inverse depth map of keyframe `k` (row-major, 1/m).
    pub fn inv_depth(&self, k: usize) -> Option<&[f64]> {
        let n = self.win.n_pixels;
        (k < self.win.n_keyframes).then(|| &self.win.inv_depth[k * n..(k + 1) * n])
    }

    /// Copies keyframe `k`'s inverse depth into `out`, which must have the camera's size.
    pub fn write_inv_depth(&self, k: usize, out: &mut PlaneF32) -> Result<(), BaError> {
        let src = self.inv_depth(k).ok_or(BaError::NoSuchKeyframe { keyframe: k, keyframes: self.win.n_keyframes })?;
        write_plane(k, src, &self.win.intr, out)
    }

    /// Sets the pose of keyframe `k` (e.g. to restart from a known state); the depth prior
    /// anchor is unchanged.
    pub fn set_world_from_cam(&mut self, k: usize, world_from_cam: &Se3) -> Result<(), BaError> {
        if k >= self.win.n_keyframes {
            return Err(BaError::NoSuchKeyframe { keyframe: k, keyframes: self.win.n_keyframes });
        }
        self.win.world_from_cam[k] = *world_from_cam;
        self.invalidate();
        Ok(())
    }

    /// Posterior covariance (6x6, right-perturbation tangent space `[v; omega]`) of keyframe
    /// `k`'s pose from the last [`compute_covariance`](Self::compute_covariance); `None` for
    /// fixed poses, unknown keyframes, or when no covariance is current.
    pub fn pose_covariance(&self, k: usize) -> Option<Matrix6<f64>> {
        self.pose_cross_covariance(k, k)
    }

    /// Cross-covariance block `Cov(xi_a, xi_b)` of two free poses.
    pub fn pose_cross_covariance(&self, a: usize, b: usize) -> Option<Matrix6<f64>> {
        if !self.cov.valid || a >= self.win.n_keyframes || b >= self.win.n_keyframes {
            return None;
        }
        let (fa, fb) = (self.st.free_index(a)?, self.st.free_index(b)?);
        let dim = 6 * self.st.n_free;
        Some(Matrix6::from_fn(|r, c| self.cov.pose[(6 * fb + c) * dim + 6 * fa + r]))
    }

    /// Marginal variance of every inverse depth of keyframe `k` ((1/m)^2, row-major) from the
    /// last `compute_covariance`; `f64::INFINITY` for frozen pixels.
    pub fn inv_depth_variance(&self, k: usize) -> Option<&[f64]> {
        let n = self.win.n_pixels;
        (self.cov.valid && k < self.win.n_keyframes).then(|| &self.cov.inv_depth_var[k * n..(k + 1) * n])
    }

    /// The a posteriori variance of unit weight from the last
    /// [`compute_covariance`](Self::compute_covariance): the Huber-weighted squared whitened
    /// flow residuals over their redundancy, `sum rho'(s) (w_x r_x^2 + w_y r_y^2) / (m - n)`
    /// (`m` residual components with weight, `n` free pose coordinates plus observed inverse
    /// depths). With weights that are exact inverse variances it is near 1; with weights that
    /// are relative confidences (the flow's) the covariance times it is in measured units.
    /// `None` when no covariance is current or the window has no redundancy.
    pub fn unit_variance(&self) -> Option<f64> {
        if self.cov.valid { self.cov.unit_variance } else { None }
    }

    /// Copies keyframe `k`'s inverse depth variance into `out` (which must have the camera's size).
    pub fn write_inv_depth_variance(&self, k: usize, out: &mut PlaneF32) -> Result<(), BaError> {
        let src = self.inv_depth_variance(k).ok_or(BaError::NoSuchKeyframe { keyframe: k, keyframes: self.win.n_keyframes })?;
        write_plane(k, src, &self.win.intr, out)
    }

    /// The pose step of keyframe `k` from the last [`compute_step`](Self::compute_step).
    pub fn step_pose(&self, k: usize) -> Option<Vector6<f64>> {
        if !self.step_valid || k >= self.win.n_keyframes {
            return None;
        }
        let f = self.st.free_index(k)?;
        Some(Vector6::from_column_slice(&self.red.step_pose[6 * f..6 * f + 6]))
    }

    /// The inverse depth step of keyframe `k` from the last `compute_step`.
    pub fn step_inv_depth(&self, k: usize) -> Option<&[f64]> {
        let n = self.win.n_pixels;
        (self.step_valid && k < self.win.n_keyframes).then(|| &self.red.step_inv_depth[k * n..(k + 1) * n])
    }

    /// Checks the window and the config and builds the coupling structure.
    pub(crate) fn prepare(&mut self, config: &BaConfig) -> Result<(), BaError> {
        config.validate()?;
        let win = &self.win;
        if !win.started {
            return Err(BaError::NotStarted);
        }
        if win.n_keyframes == 0 {
            return Err(BaError::EmptyWindow);
        }
        if win.n_edges == 0 {
            return Err(BaError::NoEdges);
        }
        for k in config.fixed_poses.min(win.n_keyframes)..win.n_keyframes {
            if !win.edges[..win.n_edges].iter().any(|e| e.from == k || e.to == k) {
                return Err(BaError::UnconstrainedPose { keyframe: k });
            }
        }
        self.st.build(win, config.fixed_poses);
        Ok(())
    }

    /// Marks the linearisation, step and covariance stale.
    pub(crate) fn invalidate(&mut self) {
        self.linearized = None;
        self.step_valid = false;
        self.cov.valid = false;
    }
}

fn write_plane(k: usize, src: &[f64], intr: &Intrinsics, out: &mut PlaneF32) -> Result<(), BaError> {
    if out.width != intr.width || out.height != intr.height || out.data.len() != src.len() {
        return Err(BaError::DepthSizeMismatch { keyframe: k, width: out.width, height: out.height, expected_width: intr.width, expected_height: intr.height });
    }
    for (dst, v) in out.data.iter_mut().zip(src) {
        *dst = *v as f32;
    }
    Ok(())
}
