//! Stage 1, `map.project` (one GPU thread per Gaussian): world-frame Gaussians to 2D splats
//! with the EWA affine approximation, the SH colour for the view, and the tile rectangle each
//! splat can reach.
//!
//! For a Gaussian with mean `mu_w`, `Sigma_w = M M^T`, `M = R(q / |q|) diag(exp(log_scale))`:
//! `mu_c = R_cw mu_w + t_cw`, `Sigma_c = R_cw Sigma_w R_cw^T`,
//! `J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]` with `tx/z`, `ty/z` clamped to the
//! field of view plus 15% of the image size on each side (3DGS: `1.3 tan(fov/2)` for a
//! centred principal point), `Sigma_2d = J Sigma_c J^T + blur I`, conic `Sigma_2d^-1`,
//! `mean2d = (fx x/z + cx, fy y/z + cy)`. Culled (no tiles): `z < near_z_m`, a singular
//! `Sigma_2d`, opacity `< 1/255`, or no pixel centre inside the splat's reach.
//!
//! Reach: alpha `= o exp(-q/2) >= 1/255` exactly where `q <= k^2`, `k^2 = 2 ln(255 o)`, and the
//! axis-aligned box of that ellipse is `|dx| <= k sqrt(Sigma_2d.xx)`, `|dy| <= k sqrt(Sigma_2d.yy)`
//! (exact, as gsplat's opacity-aware radius). So tile culling never drops a pixel that alpha
//! blending would keep, and the tiled renderer equals the untiled reference.

use rayon::prelude::*;

use super::math::{mat3_mul, mat3_mul_bt, mat3_vec, quat_to_mat3, sigmoid, Real, Mat3};
use super::{RenderConfig, RenderError, TileGrid, ALPHA_MIN};
use duv_core::{PinholeCamera, Se3};
use crate::gaussians::{sh_colour_raw, GaussianParam, Gaussians};

/// What the rasteriser needs of one projected Gaussian (AoS, 44 bytes in f32).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProjectedSplat<T> {
    /// Centre in pixels (pixel centres at integer coordinates).
    pub mean2d: [T; 2],
    /// `Sigma_2d^-1` as `(a, b, c)` = `[[a, b], [b, c]]`, 1/px^2.
    pub conic: [T; 3],
    /// Camera-frame depth of the mean, metres.
    pub z: T,
    /// Opacity after the sigmoid.
    pub opacity: T,
    /// View-dependent colour, clamped at 0.
    pub colour: [T; 3],
    /// Alpha reaches 1/255 only where `q = d^T conic d <= q_max = 2 ln(255 opacity)`: a
    /// culling bound for the rasteriser (not differentiated).
    pub q_max: T,
}

/// Camera, pose and projection settings in the working precision.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectionSetup<T> {
    pub cam_from_world_rot: Mat3<T>,
    pub cam_from_world_trans: [T; 3],
    /// Camera centre in the world frame (origin of the SH view directions).
    pub cam_centre_in_world: [T; 3],
    pub fx: T,
    pub fy: T,
    pub cx: T,
    pub cy: T,
    pub width: usize,
    pub height: usize,
    /// Clamp range of `x/z` inside the Jacobian, `(lo, hi)`.
    pub lim_x: [T; 2],
    pub lim_y: [T; 2],
    pub near_z: T,
    pub blur: T,
}

impl<T: Real> ProjectionSetup<T> {
    /// Validates the camera (undistorted pinhole) and the pose and converts them.
    pub fn new(camera: &PinholeCamera, cam_from_world: &Se3, config: &RenderConfig) -> Result<Self, RenderError> {
        camera.validate()?;
        if camera.distortion.is_some() {
            return Err(RenderError::DistortedCamera);
        }
        config.validate()?;
        let m = cam_from_world.to_homogeneous();
        if !m.iter().all(|v| v.is_finite()) {
            return Err(RenderError::NonFinitePose);
        }
        let rot: Mat3<T> = std::array::from_fn(|i| std::array::from_fn(|j| T::from_f64(m[(i, j)])));
        let trans: [T; 3] = std::array::from_fn(|i| T::from_f64(m[(i, 3)]));
        let centre = cam_from_world.inverse().translation.vector;
        let (w, h) = (camera.width as f64, camera.height as f64);
        let margin_x = 0.15 * w / camera.fx;
        let margin_y = 0.15 * h / camera.fy;
        Ok(ProjectionSetup {
            cam_from_world_rot: rot,
            cam_from_world_trans: trans,
            cam_centre_in_world: [T::from_f64(centre.x), T::from_f64(centre.y), T::from_f64(centre.z)],
            fx: T::from_f64(camera.fx),
            fy: T::from_f64(camera.fy),
            cx: T::from_f64(camera.cx),
            cy: T::from_f64(camera.cy),
            width: camera.width,
            height: camera.height,
            lim_x: [T::from_f64(-camera.cx / camera.fx - margin_x), T::from_f64((w - camera.cx) / camera.fx + margin_x)],
            lim_y: [T::from_f64(-camera.cy / camera.fy - margin_y), T::from_f64((h - camera.cy) / camera.fy + margin_y)],
            near_z: T::from_f64(config.near_z_m as f64),
            blur: T::from_f64(config.cov2d_blur_px2 as f64),
        })
    }
}

/// Forward intermediates of one projection, shared by the forward and the backward pass.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ProjectionTape<T> {
    pub qn: [T; 4],
    pub q_norm: T,
    pub rq: Mat3<T>,
    pub scale: [T; 3],
    pub m: Mat3<T>,
    pub mean_c: [T; 3],
    pub sigma_c: Mat3<T>,
    /// `x/z`, `y/z` after the clamp, and whether each was inside the clamp range.
    pub txz: [T; 2],
    pub inside: [bool; 2],
    pub j: [[T; 3]; 2],
    /// `Sigma_2d` as `(A, B, C)`.
    pub cov2d: [T; 3],
    pub det: T,
    /// Unit view direction (world) and the distance it was normalised by.
    pub dir: [T; 3],
    pub dist: T,
    pub colour_raw: [T; 3],
}

/// Projects one Gaussian; `None` when culled for depth, a singular 2D covariance or an
/// opacity below 1/255. Returns the splat and its reach `(k sqrt(Sxx), k sqrt(Syy))` in pixels.
#[inline]
#[allow(clippy::neg_cmp_op_on_partial_ord)] // written so that NaN fails every test
pub fn project_splat<T: Real>(p: &GaussianParam<T>, s: &ProjectionSetup<T>) -> Option<(ProjectedSplat<T>, [T; 2])> {
    let tape = projection_tape(p, s)?;
    let opacity = sigmoid(p.opacity_logit);
    if !(opacity >= T::from_f64(ALPHA_MIN)) {
        return None;
    }
    let [a, b, c] = tape.cov2d;
    let det = tape.det;
    let q_max = (T::from_f64(2.0) * (T::from_f64(255.0) * opacity).ln()).max(T::ZERO);
    let k = q_max.sqrt();
    let splat = ProjectedSplat {
        mean2d: [s.fx * tape.mean_c[0] / tape.mean_c[2] + s.cx, s.fy * tape.mean_c[1] / tape.mean_c[2] + s.cy],
        conic: [c / det, -b / det, a / det],
        z: tape.mean_c[2],
        opacity,
        colour: tape.colour_raw.map(|v| v.max(T::ZERO)),
        q_max,
    };
    let reach = [k * a.sqrt(), k * c.sqrt()];
    let finite = splat.mean2d.iter().chain(&splat.conic).chain(&reach).all(|v| v.is_finite());
    finite.then_some((splat, reach))
}

/// The forward computation up to the 2D covariance; `None` behind the near plane or when
/// `Sigma_2d` is not positive definite.
#[inline(always)]
#[allow(clippy::neg_cmp_op_on_partial_ord)] // written so that NaN fails every test
pub(crate) fn projection_tape<T: Real>(p: &GaussianParam<T>, s: &ProjectionSetup<T>) -> Option<ProjectionTape<T>> {
    let q = p.rotation;
    let q_norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if !(q_norm > T::ZERO) {
        return None;
    }
    let qn = q.map(|v| v / q_norm);
    let rq = quat_to_mat3(&qn);
    let scale = p.log_scale.map(|v| v.exp());
    let m: Mat3<T> = std::array::from_fn(|i| std::array::from_fn(|j| rq[i][j] * scale[j]));
    let sigma_w = mat3_mul_bt(&m, &m);
    let r = &s.cam_from_world_rot;
    let mut mean_c = mat3_vec(r, &p.mean);
    for (m, t) in mean_c.iter_mut().zip(&s.cam_from_world_trans) {
        *m += *t;
    }
    let z = mean_c[2];
    if !(z >= s.near_z) {
        return None;
    }
    let sigma_c = mat3_mul_bt(&mat3_mul(r, &sigma_w), r);
    let (rx, ry) = (mean_c[0] / z, mean_c[1] / z);
    let txz = [rx.max(s.lim_x[0]).min(s.lim_x[1]), ry.max(s.lim_y[0]).min(s.lim_y[1])];
    let inside = [rx >= s.lim_x[0] && rx <= s.lim_x[1], ry >= s.lim_y[0] && ry <= s.lim_y[1]];
    let j = [[s.fx / z, T::ZERO, -s.fx * txz[0] / z], [T::ZERO, s.fy / z, -s.fy * txz[1] / z]];
    // Sigma_2d = J Sigma_c J^T.
    let mut js = [[T::ZERO; 3]; 2];
    for a in 0..2 {
        for bb in 0..3 {
            js[a][bb] = j[a][0] * sigma_c[0][bb] + j[a][1] * sigma_c[1][bb] + j[a][2] * sigma_c[2][bb];
        }
    }
    let dot = |a: usize, b: usize| js[a][0] * j[b][0] + js[a][1] * j[b][1] + js[a][2] * j[b][2];
    let cov2d = [dot(0, 0) + s.blur, dot(0, 1), dot(1, 1) + s.blur];
    let det = cov2d[0] * cov2d[2] - cov2d[1] * cov2d[1];
    if !(det > T::ZERO) {
        return None;
    }
    let v = [p.mean[0] - s.cam_centre_in_world[0], p.mean[1] - s.cam_centre_in_world[1], p.mean[2] - s.cam_centre_in_world[2]];
    let dist = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let dir = v.map(|x| x / dist);
    let colour_raw = sh_colour_raw(&p.f_dc, &p.f_rest, &dir);
    Some(ProjectionTape { qn, q_norm, rq, scale, m, mean_c, sigma_c, txz, inside, j, cov2d, det, dir, dist, colour_raw })
}

/// Tiles `[x0, x1) x [y0, y1)` a splat may touch; empty when culled.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TileRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl TileRect {
    pub fn count(&self) -> u32 {
        (self.x1 - self.x0) * (self.y1 - self.y0)
    }
}

/// The tiles holding a pixel centre within the splat's reach (with a small safety margin
/// against f32 rounding: extra tiles cost time, never change the image).
#[inline]
pub fn tile_rect(mean2d: [f32; 2], reach: [f32; 2], grid: &TileGrid) -> TileRect {
    let axis = |m: f32, r: f32, n: usize| -> Option<(u32, u32)> {
        let r = r * 1.0001 + 1e-3;
        let lo = (m - r).ceil().max(0.0);
        let hi = (m + r).floor().min(n as f32 - 1.0);
        (lo <= hi).then_some((lo as u32, hi as u32))
    };
    match (axis(mean2d[0], reach[0], grid.width), axis(mean2d[1], reach[1], grid.height)) {
        (Some((px0, px1)), Some((py0, py1))) => {
            let t = grid.tile_size as u32;
            TileRect { x0: px0 / t, y0: py0 / t, x1: px1 / t + 1, y1: py1 / t + 1 }
        }
        _ => TileRect::default(),
    }
}

/// Stage 1 over all Gaussians, one task per Gaussian: writes each splat, its tile rectangle
/// and its tile count (0 when culled). Inputs must be finite (checked by the caller).
pub fn project_gaussians(
    gaussians: &Gaussians,
    setup: &ProjectionSetup<f32>,
    grid: &TileGrid,
    splats: &mut [ProjectedSplat<f32>],
    rects: &mut [TileRect],
    tiles_touched: &mut [u32],
) {
    let n = gaussians.len();
    (&mut splats[..n], &mut rects[..n], &mut tiles_touched[..n]).into_par_iter().enumerate().with_min_len(256).for_each(
        |(i, (splat, rect, count))| {
            let p = gaussians.get(i);
            match project_splat(&p, setup) {
                Some((s, reach)) => {
                    *splat = s;
                    *rect = tile_rect(s.mean2d, reach, grid);
                }
                None => {
                    *splat = ProjectedSplat::default();
                    *rect = TileRect::default();
                }
            }
            *count = rect.count();
        },
    );
}
