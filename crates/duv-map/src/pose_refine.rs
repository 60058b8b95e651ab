//! Photometric pose refinement of a keyframe against the map (`duv refine --refine-poses`).
//!
//! The map rendered from a keyframe's current pose gives a colour and an inverse depth per
//! pixel. If the pose is off, the keyframe's own image is that render seen from somewhere
//! else: each rendered pixel `x` with inverse depth `d` back-projects to `X = K^-1 (x, 1) / d`
//! in the current camera, and lands at `pi(T X)` in the true one, `T = true_from_current`.
//! The refinement finds `T` by Gauss-Newton on the grey-level residuals
//! `r(x) = (1 + a) I(pi(T X)) + b - R(x)` (with a gain and offset `a`, `b` of the image against
//! the render estimated alongside; Huber weights, a 3-level image pyramid, coarse to fine; a
//! left-multiplied twist, `dX'/dxi = [I | -[X']x]`), as direct image alignment does (DSO,
//! LSD-SLAM), with the map render in the place of the reference keyframe. The corrected pose
//! is `world_from_current * T^-1`.
//!
//! Pixels count only where the render is opaque (`alpha >= min_alpha`), its depth is a single
//! surface (relative standard deviation of the blended inverse depth at most
//! `max_rel_depth_std`: occlusion boundaries mix two) and the image has a gradient. A result
//! is used only when the cost fell and the step is within `max_step_m` / `max_step_deg`:
//! this corrects small misregistrations between keyframes the map was built from, it does not
//! relocalise. Everything is f64; it runs offshore, not per frame.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use duv_core::pose::{hat, rotation_angle, se3_exp};
use duv_core::frame::LUMA_WEIGHTS;
use duv_core::{ImageRgb8, ImageRgbF32, PinholeCamera, PlaneF32, Se3};

/// Why a keyframe's pose could not be refined. The pose is then left as it was.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PoseRefineError {
    #[error("pose refinement config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
    #[error("pose refinement: {what} is {width}x{height}, the camera {camera_width}x{camera_height}")]
    Size { what: &'static str, width: usize, height: usize, camera_width: usize, camera_height: usize },
    #[error("pose refinement: {found} usable pixels (opaque render, one surface, image gradient), at least {needed} needed")]
    TooFewPixels { found: usize, needed: usize },
}

/// Settings of the refinement. Defaults live in [`PoseRefineConfig::default`] and nowhere else.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseRefineConfig {
    /// Pyramid levels (1 = full resolution only), 1..=6.
    pub levels: usize,
    /// Gauss-Newton iterations per level.
    pub iterations: usize,
    /// Huber threshold of the grey-level residual, [0, 1] units.
    pub huber: f64,
    /// Render pixels below this accumulated opacity are not used.
    pub min_alpha: f32,
    /// Render pixels whose blended inverse depth has a relative standard deviation above this
    /// are not used (they mix surfaces).
    pub max_rel_depth_std: f32,
    /// Fewest usable full-resolution pixels.
    pub min_pixels: usize,
    /// Largest accepted correction, metres (map units) and degrees.
    pub max_step_m: f64,
    pub max_step_deg: f64,
    /// Prior on the pose, in full-resolution pixels: the refined pose may move from the input
    /// pose (the tracker's) by about this much image motion at the scene's median depth
    /// (translation `prior_px * z / f`, rotation `prior_px / f`). Alternating pose and map
    /// steps otherwise drift along the directions the photometric error hardly sees (the map
    /// follows the poses). 0 disables it.
    pub prior_px: f64,
    /// Grey-level noise of the photometric residuals, [0, 1] units (weighs them against the prior).
    pub photometric_sigma: f64,
}

impl Default for PoseRefineConfig {
    fn default() -> Self {
        PoseRefineConfig { levels: 3, iterations: 8, huber: 0.03, min_alpha: 0.9, max_rel_depth_std: 0.1, min_pixels: 500, max_step_m: 0.2, max_step_deg: 5.0, prior_px: 0.1, photometric_sigma: 0.02 }
    }
}

impl PoseRefineConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), PoseRefineError> {
        let bad = |field: &'static str, value: f64, why: &'static str| Err(PoseRefineError::InvalidConfig { field, value, why });
        if !(1..=6).contains(&self.levels) {
            return bad("levels", self.levels as f64, "must be in 1..=6");
        }
        if self.iterations == 0 || self.iterations > 100 {
            return bad("iterations", self.iterations as f64, "must be in 1..=100");
        }
        for (field, v) in [
            ("huber", self.huber),
            ("min_alpha", self.min_alpha as f64),
            ("max_rel_depth_std", self.max_rel_depth_std as f64),
            ("max_step_m", self.max_step_m),
            ("max_step_deg", self.max_step_deg),
            ("photometric_sigma", self.photometric_sigma),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, v, "must be finite and positive");
            }
        }
        if !(self.prior_px.is_finite() && self.prior_px >= 0.0) {
            return bad("prior_px", self.prior_px, "must be finite and >= 0");
        }
        Ok(())
    }
}

/// What the refinement of one keyframe found.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PoseCorrection {
    /// `true_from_current`: the corrected pose is `world_from_current * true_from_current^-1`.
    #[serde(skip)]
    pub true_from_current: Se3,
    /// Robust cost per used pixel at full resolution, before and after.
    pub cost_before: f64,
    pub cost_after: f64,
    /// Full-resolution pixels used (before the last iteration).
    pub pixels: usize,
    /// Size of the correction, metres (map units) and degrees.
    pub step_m: f64,
    pub step_deg: f64,
    /// Whether the correction is meant to be applied (cost fell, step within the limits).
    pub accepted: bool,
}

impl PoseCorrection {
    /// The corrected camera pose.
    pub fn apply(&self, world_from_cam: &Se3) -> Se3 {
        world_from_cam * self.true_from_current.inverse()
    }
}

/// One pyramid level: grey keyframe image, its gradients, the grey render and its inverse
/// depth (0 = unusable), and the camera.
struct Level {
    cam: PinholeCamera,
    image: Vec<f64>,
    grad_x: Vec<f64>,
    grad_y: Vec<f64>,
    render: Vec<f64>,
    inv_depth: Vec<f64>,
}

impl Level {
    fn width(&self) -> usize {
        self.cam.width
    }
    fn height(&self) -> usize {
        self.cam.height
    }

    /// Bilinear sample of `plane` at `(x, y)`; `None` within one pixel of the border.
    fn sample(&self, plane: &[f64], x: f64, y: f64) -> Option<f64> {
        let (w, h) = (self.width(), self.height());
        if !(x >= 1.0 && y >= 1.0 && x < (w - 2) as f64 && y < (h - 2) as f64) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let p = |xx: usize, yy: usize| plane[yy * w + xx];
        let top = p(x0, y0) + fx * (p(x0 + 1, y0) - p(x0, y0));
        let bot = p(x0, y0 + 1) + fx * (p(x0 + 1, y0 + 1) - p(x0, y0 + 1));
        Some(top + fy * (bot - top))
    }

    /// The next coarser level: 2x2 means; a coarse inverse depth only where all four are usable.
    fn halve(&self) -> Level {
        let (w, h) = (self.width() / 2, self.height() / 2);
        let fw = self.width();
        let mean = |p: &[f64], x: usize, y: usize| 0.25 * (p[2 * y * fw + 2 * x] + p[2 * y * fw + 2 * x + 1] + p[(2 * y + 1) * fw + 2 * x] + p[(2 * y + 1) * fw + 2 * x + 1]);
        let mut image = vec![0.0; w * h];
        let mut render = vec![0.0; w * h];
        let mut inv_depth = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                image[y * w + x] = mean(&self.image, x, y);
                render[y * w + x] = mean(&self.render, x, y);
                let ds = [0, 1, fw, fw + 1].map(|o| self.inv_depth[2 * y * fw + 2 * x + o]);
                inv_depth[y * w + x] = if ds.iter().all(|&d| d > 0.0) { 0.25 * ds.iter().sum::<f64>() } else { 0.0 };
            }
        }
        let c = &self.cam;
        let cam = PinholeCamera { fx: c.fx / 2.0, fy: c.fy / 2.0, cx: (c.cx + 0.5) / 2.0 - 0.5, cy: (c.cy + 0.5) / 2.0 - 0.5, width: w, height: h, distortion: None };
        Level::new(cam, image, render, inv_depth)
    }

    fn new(cam: PinholeCamera, image: Vec<f64>, render: Vec<f64>, inv_depth: Vec<f64>) -> Level {
        let (w, h) = (cam.width, cam.height);
        let mut grad_x = vec![0.0; w * h];
        let mut grad_y = vec![0.0; w * h];
        for y in 1..h.saturating_sub(1) {
            for x in 1..w.saturating_sub(1) {
                let i = y * w + x;
                grad_x[i] = 0.5 * (image[i + 1] - image[i - 1]);
                grad_y[i] = 0.5 * (image[i + w] - image[i - w]);
            }
        }
        Level { cam, image, grad_x, grad_y, render, inv_depth }
    }
}

/// Residual `I(pi(T X)) - R(x)` of render pixel `(x, y)` with inverse depth `d` under
/// `T = true_from_current`, its Jacobian in the left-multiplied twist `(v, omega)`, and the
/// sampled image value. `None` when the point leaves the image or goes behind the camera.
fn residual_and_jacobian(level: &Level, x: usize, y: usize, d: f64, true_from_current: &Se3) -> Option<(f64, Vector6<f64>, f64)> {
    let c = &level.cam;
    let p = Vector3::new((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy, 1.0) / d;
    let q = true_from_current * nalgebra::Point3::from(p);
    if q.z <= 1e-6 {
        return None;
    }
    let (u, v) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
    let i = level.sample(&level.image, u, v)?;
    let (gx, gy) = (level.sample(&level.grad_x, u, v)?, level.sample(&level.grad_y, u, v)?);
    let r = i - level.render[y * level.width() + x];
    let iz = 1.0 / q.z;
    // d(u, v)/dq, then dq/dxi = [I | -[q]x].
    let du = Vector3::new(c.fx * iz, 0.0, -c.fx * q.x * iz * iz);
    let dv = Vector3::new(0.0, c.fy * iz, -c.fy * q.y * iz * iz);
    let g = gx * du + gy * dv;
    let rot: Matrix3<f64> = -hat(&q.coords);
    let w = rot.transpose() * g;
    Some((r, Vector6::new(g.x, g.y, g.z, w.x, w.y, w.z), i))
}

fn huber_weight(r: f64, k: f64) -> f64 {
    let a = r.abs();
    if a <= k {
        1.0
    } else {
        k / a
    }
}

fn huber_cost(r: f64, k: f64) -> f64 {
    let a = r.abs();
    if a <= k {
        0.5 * r * r
    } else {
        k * (a - 0.5 * k)
    }
}

/// Residual, Jacobian and sampled image value (as [`residual_and_jacobian`]) of every usable
/// render pixel of a level that lands in the image under `t`.
fn residuals<'a>(level: &'a Level, t: &'a Se3) -> impl Iterator<Item = (f64, Vector6<f64>, f64)> + 'a {
    let w = level.width();
    level.inv_depth.iter().enumerate().filter(|(_, &d)| d > 0.0).filter_map(move |(i, &d)| residual_and_jacobian(level, i % w, i / w, d, t))
}

/// Gain and offset `(a, b)` of the image against the render under `t`:
/// `(1 + a) I(pi(T X)) + b ~ R(x)` in least squares. A render a grey level brighter or darker
/// than the image (the medium's colours not quite right) would otherwise pull the pose along
/// the image's mean gradient.
fn fit_brightness(level: &Level, t: &Se3) -> (f64, f64) {
    let (mut n, mut si, mut sii, mut sr, mut sir) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (r, _, i) in residuals(level, t) {
        let rd = i - r; // the render value
        n += 1.0;
        si += i;
        sii += i * i;
        sr += rd;
        sir += i * rd;
    }
    let det = n * sii - si * si;
    if n < 2.0 || det.abs() < 1e-12 {
        return (0.0, 0.0);
    }
    let gain = (n * sir - si * sr) / det;
    ((gain - 1.0), (sr - gain * si) / n)
}

/// Robust cost per usable pixel of a level under `t` and brightness `(a, b)` (and the count).
fn level_cost(level: &Level, t: &Se3, (a, b): (f64, f64), k: f64) -> (f64, usize) {
    let (mut sum, mut n) = (0.0, 0);
    for (r, _, i) in residuals(level, t) {
        sum += huber_cost(r + a * i + b, k);
        n += 1;
    }
    (if n > 0 { sum / n as f64 } else { f64::INFINITY }, n)
}

/// Aligns a keyframe image to the map's render from the keyframe's current pose (colour,
/// blended inverse depth and its variance, accumulated alpha, all at the camera's size).
/// `current_from_input` is where the current pose stands against the input pose the prior
/// holds it to (identity on the first refinement).
#[allow(clippy::too_many_arguments)]
pub fn align_to_render(
    current_from_input: &Se3,
    image: &ImageRgb8,
    render_colour: &ImageRgbF32,
    render_inv_depth: &PlaneF32,
    render_inv_depth_var: &PlaneF32,
    render_alpha: &PlaneF32,
    camera: &PinholeCamera,
    cfg: &PoseRefineConfig,
) -> Result<PoseCorrection, PoseRefineError> {
    cfg.validate()?;
    let (w, h) = (camera.width, camera.height);
    let check = |what: &'static str, width: usize, height: usize| {
        if width != w || height != h {
            Err(PoseRefineError::Size { what, width, height, camera_width: w, camera_height: h })
        } else {
            Ok(())
        }
    };
    check("image", image.width, image.height)?;
    check("render", render_colour.width, render_colour.height)?;
    check("render depth", render_inv_depth.width, render_inv_depth.height)?;
    check("render depth variance", render_inv_depth_var.width, render_inv_depth_var.height)?;
    check("render alpha", render_alpha.width, render_alpha.height)?;
    let grey_u8: Vec<f64> = image.data.chunks_exact(3).map(|p| (0..3).map(|c| LUMA_WEIGHTS[c] as f64 * p[c] as f64).sum::<f64>() / 255.0).collect();
    let grey_render: Vec<f64> = render_colour.data.chunks_exact(3).map(|p| (0..3).map(|c| LUMA_WEIGHTS[c] as f64 * p[c] as f64).sum::<f64>()).collect();
    let mut inv_depth = vec![0.0; w * h];
    let mut usable = 0;
    for (i, d) in inv_depth.iter_mut().enumerate() {
        let (dd, var, a) = (render_inv_depth.data[i], render_inv_depth_var.data[i], render_alpha.data[i]);
        if a >= cfg.min_alpha && dd > 0.0 && dd.is_finite() && var.is_finite() && var.max(0.0).sqrt() <= cfg.max_rel_depth_std * dd {
            *d = dd as f64;
            usable += 1;
        }
    }
    if usable < cfg.min_pixels {
        return Err(PoseRefineError::TooFewPixels { found: usable, needed: cfg.min_pixels });
    }
    let mut cam = *camera;
    cam.distortion = None;
    let mut levels = vec![Level::new(cam, grey_u8, grey_render, inv_depth)];
    while levels.len() < cfg.levels && levels.last().is_some_and(|l| l.width() >= 32 && l.height() >= 32) {
        let next = levels.last().map(Level::halve);
        levels.extend(next);
    }
    let k = cfg.huber;
    let (cost_before, pixels) = level_cost(&levels[0], &Se3::identity(), fit_brightness(&levels[0], &Se3::identity()), k);
    // The prior's information: image motion of `prior_px` at the median depth, per axis.
    let prior = if cfg.prior_px > 0.0 {
        let mut ds: Vec<f64> = levels[0].inv_depth.iter().copied().filter(|&d| d > 0.0).collect();
        let mid = ds.len() / 2;
        let z = 1.0 / *ds.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
        let f = 0.5 * (camera.fx + camera.fy);
        let (st, sr) = (cfg.prior_px * z / f, cfg.prior_px / f);
        Some((Vector6::new(1.0 / (st * st), 1.0 / (st * st), 1.0 / (st * st), 1.0 / (sr * sr), 1.0 / (sr * sr), 1.0 / (sr * sr)), duv_core::pose::se3_log(current_from_input)))
    } else {
        None
    };
    let inv_var = 1.0 / (cfg.photometric_sigma * cfg.photometric_sigma);
    let mut t = Se3::identity();
    let mut gain_offset = fit_brightness(levels.last().unwrap_or(&levels[0]), &t);
    for level in levels.iter().rev() {
        for _ in 0..cfg.iterations {
            // Unknowns: the twist, then the image's gain and offset.
            let mut hm = SMatrix::<f64, 8, 8>::zeros();
            let mut b = SVector::<f64, 8>::zeros();
            let (ga, gb) = gain_offset;
            for (r, j, i) in residuals(level, &t) {
                let r = r + ga * i + gb;
                let js = j * (1.0 + ga);
                let jf = SVector::<f64, 8>::from_iterator(js.iter().copied().chain([i, 1.0]));
                let wgt = huber_weight(r, k) * inv_var;
                hm += wgt * jf * jf.transpose();
                b += wgt * r * jf;
            }
            // The prior on the deviation from the input pose, `log(T) + log(current_from_input)`
            // to first order.
            if let Some((info, offset)) = &prior {
                let dev = duv_core::pose::se3_log(&t) + offset;
                for i in 0..6 {
                    hm[(i, i)] += info[i];
                    b[i] += info[i] * dev[i];
                }
            }
            // A little Levenberg damping keeps weakly observed directions still.
            for i in 0..8 {
                hm[(i, i)] *= 1.0 + 1e-4;
            }
            let Some(step) = hm.cholesky().map(|c| c.solve(&(-b))) else { break };
            if !step.iter().all(|v| v.is_finite()) {
                break;
            }
            let twist = Vector6::from_iterator(step.iter().take(6).copied());
            t = se3_exp(&twist) * t;
            gain_offset = (ga + step[6], gb + step[7]);
            if twist.norm() < 1e-7 {
                break;
            }
        }
    }
    let (cost_after, _) = level_cost(&levels[0], &t, fit_brightness(&levels[0], &t), k);
    let step_m = t.translation.vector.norm();
    let step_deg = rotation_angle(&t.rotation).to_degrees();
    let accepted = cost_after < cost_before && step_m <= cfg.max_step_m && step_deg <= cfg.max_step_deg;
    Ok(PoseCorrection { true_from_current: t, cost_before, cost_after, pixels, step_m, step_deg, accepted })
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};

    /// A smooth level (sinusoids, periods of 100-150 px) with a slanted-plane inverse depth.
    fn smooth_level() -> Level {
        let (w, h) = (96, 72);
        let cam = PinholeCamera { fx: 80.0, fy: 80.0, cx: 47.5, cy: 35.5, width: w, height: h, distortion: None };
        let f = |x: f64, y: f64| 0.5 + 0.2 * (x / 16.0).sin() * (y / 18.0).cos() + 0.1 * ((x + y) / 24.0).sin();
        let image: Vec<f64> = (0..w * h).map(|i| f((i % w) as f64, (i / w) as f64)).collect();
        let render: Vec<f64> = (0..w * h).map(|i| f((i % w) as f64 + 0.7, (i / w) as f64 - 0.4)).collect();
        let inv_depth: Vec<f64> = (0..w * h).map(|i| 0.4 + 0.002 * (i / w) as f64).collect();
        Level::new(cam, image, render, inv_depth)
    }

    #[test]
    fn the_jacobian_matches_central_differences() {
        let level = smooth_level();
        let t0 = se3_exp(&Vector6::new(0.01, -0.02, 0.015, 0.004, -0.003, 0.002));
        let eps = 1e-6;
        let mut worst: f64 = 0.0;
        for &(x, y) in &[(30usize, 20usize), (50, 40), (60, 30), (40, 50)] {
            let d = level.inv_depth[y * level.width() + x];
            let (_, j, _) = residual_and_jacobian(&level, x, y, d, &t0).unwrap();
            for k in 0..6 {
                let mut e = Vector6::zeros();
                e[k] = eps;
                let rp = residual_and_jacobian(&level, x, y, d, &(se3_exp(&e) * t0)).unwrap().0;
                let rm = residual_and_jacobian(&level, x, y, d, &(se3_exp(&-e) * t0)).unwrap().0;
                let fd = (rp - rm) / (2.0 * eps);
                // The Jacobian samples the central-difference gradient images, the residual the
                // bilinear image itself: on a smooth image they agree to a few per cent.
                let err = (j[k] - fd).abs() / (fd.abs().max(j.norm() * 0.05));
                worst = worst.max(err);
            }
        }
        eprintln!("worst relative Jacobian error {worst:.4}");
        assert!(worst < 0.05, "worst relative Jacobian error {worst}");
    }

    /// Frame 0 and frame `k` of a generated survey (no vignetting): the keyframe is frame `k`,
    /// the "render" frame 0 with its true inverse depth. The correction must be `k_from_0`.
    #[test]
    fn the_motion_between_two_generated_frames_is_recovered() {
        let mut cfg = SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Survey);
        cfg.frames = 4;
        cfg.width = 160;
        cfg.height = 120;
        cfg.vignetting = 0.0;
        let r = SimRenderer::new(&cfg).unwrap();
        let (a, b) = (r.render(0), r.render(3));
        let cam = *r.camera();
        let mut inv = PlaneF32::new(cam.width, cam.height);
        for (d, &z) in inv.data.iter_mut().zip(&a.depth_m.data) {
            *d = if z > 0.0 { 1.0 / z } else { 0.0 };
        }
        let var = PlaneF32::new(cam.width, cam.height);
        let mut alpha = PlaneF32::new(cam.width, cam.height);
        alpha.data.fill(1.0);
        let truth = r.poses()[3].world_from_cam.inv_mul(&r.poses()[0].world_from_cam);
        let cfg = PoseRefineConfig { prior_px: 0.0, ..PoseRefineConfig::default() };
        let c = align_to_render(&Se3::identity(), &b.rgb, &a.rgb.to_rgb_f32(), &inv, &var, &alpha, &cam, &cfg).unwrap();
        let err = c.true_from_current.inv_mul(&truth);
        let (motion_m, err_m) = (truth.translation.vector.norm(), err.translation.vector.norm());
        let err_deg = rotation_angle(&err.rotation).to_degrees();
        eprintln!("motion {motion_m:.4} m {:.3} deg; error {err_m:.5} m {err_deg:.4} deg; cost {:.6} -> {:.6}", rotation_angle(&truth.rotation).to_degrees(), c.cost_before, c.cost_after);
        assert!(c.accepted);
        assert!(motion_m > 0.02, "the frames should be apart ({motion_m} m)");
        assert!(err_m < 0.1 * motion_m, "translation error {err_m} m of {motion_m} m");
        assert!(err_deg < 0.1, "rotation error {err_deg} deg");
    }

    #[test]
    fn bad_input_is_an_error_that_names_it() {
        let cam = PinholeCamera { fx: 80.0, fy: 80.0, cx: 47.5, cy: 35.5, width: 96, height: 72, distortion: None };
        let img = ImageRgb8::new(96, 72);
        let colour = ImageRgbF32::new(96, 72);
        let p = PlaneF32::new(96, 72);
        let small = PlaneF32::new(48, 36);
        let e = align_to_render(&Se3::identity(), &img, &colour, &small, &p, &p, &cam, &PoseRefineConfig::default()).unwrap_err();
        assert!(e.to_string().contains("render depth is 48x36"), "{e}");
        // An empty render (alpha 0) has no usable pixel.
        let e = align_to_render(&Se3::identity(), &img, &colour, &p, &p, &p, &cam, &PoseRefineConfig::default()).unwrap_err();
        assert_eq!(e, PoseRefineError::TooFewPixels { found: 0, needed: 500 });
        let bad = PoseRefineConfig { huber: f64::NAN, ..PoseRefineConfig::default() };
        assert!(align_to_render(&Se3::identity(), &img, &colour, &p, &p, &p, &cam, &bad).unwrap_err().to_string().contains("huber"));
    }
}
