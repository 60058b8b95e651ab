//! Reprojection with analytic Jacobians, the robust weight, and the accumulation of the
//! normal equations (H_pp, H_pd, H_dd, b_p, b_d) over every edge of the window.

use nalgebra::{Matrix2x6, Matrix3, Matrix6, Vector2, Vector3, Vector6};

use super::workspace::{Structure, System, Window, NO_SLOT};
use super::{BaConfig, Intrinsics};
use duv_core::{PinholeCamera, Se3};

/// A residual is used only when the reprojected homogeneous point has `z >= MIN_PROJECTED_Z`.
/// With points carried as `(x_n, y_n, 1, d)` that `z` is `depth_in_j / depth_in_i`, so this
/// drops points behind (or nearly at) camera `j` relative to their distance from camera `i`.
pub const MIN_PROJECTED_Z: f64 = 0.05;

/// A pixel of keyframe `i` reprojected into keyframe `j`, with its Jacobians.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reprojection {
    /// Predicted position in keyframe `j`, pixels.
    pub uv: Vector2<f64>,
    /// d uv / d xi_i for `world_from_cam_i <- world_from_cam_i * exp(xi_i)`, `xi = [v; omega]`.
    pub d_uv_d_pose_i: Matrix2x6<f64>,
    /// d uv / d xi_j for `world_from_cam_j <- world_from_cam_j * exp(xi_j)`.
    pub d_uv_d_pose_j: Matrix2x6<f64>,
    /// d uv / d d_i(p), the pixel's inverse depth (1/m).
    pub d_uv_d_inv_depth: Vector2<f64>,
}

/// Reprojects pixel `uv_in_i` of keyframe `i` with inverse depth `inv_depth` into keyframe `j`
/// (`cam_j_from_cam_i = world_from_cam_j^-1 * world_from_cam_i`), with analytic Jacobians.
/// Uses the pinhole intrinsics only (BA runs on undistorted images). `None` when the point
/// falls behind camera `j` (see [`MIN_PROJECTED_Z`]).
pub fn reproject(camera: &PinholeCamera, uv_in_i: Vector2<f64>, inv_depth: f64, cam_j_from_cam_i: &Se3) -> Option<Reprojection> {
    let intr = Intrinsics { fx: camera.fx, fy: camera.fy, cx: camera.cx, cy: camera.cy, width: camera.width, height: camera.height };
    let ray = [(uv_in_i.x - intr.cx) / intr.fx, (uv_in_i.y - intr.cy) / intr.fy];
    let rot = cam_j_from_cam_i.rotation.to_rotation_matrix().into_inner();
    reproject_ray(&intr, ray, inv_depth, &rot, &cam_j_from_cam_i.translation.vector)
}

/// The homogeneous point `P = R q + t d` in camera `j` (`q = (x_n, y_n, 1)`), if in front.
#[inline]
fn transform(ray: [f64; 2], inv_depth: f64, rot: &Matrix3<f64>, t: &Vector3<f64>) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let q = Vector3::new(ray[0], ray[1], 1.0);
    let p = rot * q + t * inv_depth;
    (p.z >= MIN_PROJECTED_Z).then_some((q, p))
}

/// Projection only (cost evaluation).
#[inline]
pub(crate) fn predict(intr: &Intrinsics, ray: [f64; 2], inv_depth: f64, rot: &Matrix3<f64>, t: &Vector3<f64>) -> Option<[f64; 2]> {
    let (_, p) = transform(ray, inv_depth, rot, t)?;
    let iz = 1.0 / p.z;
    Some([intr.fx * p.x * iz + intr.cx, intr.fy * p.y * iz + intr.cy])
}

/// Image motion of the ray's projection per unit of its inverse depth, `d uv / d d`.
#[inline]
pub(crate) fn d_uv_d_inv_depth(intr: &Intrinsics, ray: [f64; 2], inv_depth: f64, rot: &Matrix3<f64>, t: &Vector3<f64>) -> Option<Vector2<f64>> {
    let (_, p) = transform(ray, inv_depth, rot, t)?;
    let iz = 1.0 / p.z;
    Some(Vector2::new(intr.fx * iz * (t.x - p.x * iz * t.z), intr.fy * iz * (t.y - p.y * iz * t.z)))
}

/// Projection and Jacobians of a normalised ray of keyframe `i`.
///
/// With `P = R q + t d` (homogeneous, `W = d`): a right perturbation of pose `i` moves the
/// point in camera `i` by `exp(xi_i) (q, d) ~ (q + omega x q + v d, d)`, so
/// `dP/dxi_i = [d R, -R [q]x]`; one of pose `j` acts as `exp(-xi_j)` on the point in camera
/// `j`, so `dP/dxi_j = [-d I, [P]x]`; and `dP/dd = t`. Each is chained with the 2x3
/// projection Jacobian.
#[inline]
pub(crate) fn reproject_ray(intr: &Intrinsics, ray: [f64; 2], inv_depth: f64, rot: &Matrix3<f64>, t: &Vector3<f64>) -> Option<Reprojection> {
    let (q, p) = transform(ray, inv_depth, rot, t)?;
    let iz = 1.0 / p.z;
    let uv = Vector2::new(intr.fx * p.x * iz + intr.cx, intr.fy * p.y * iz + intr.cy);
    // Rows of d(uv)/dP.
    let a = Vector3::new(intr.fx * iz, 0.0, -intr.fx * p.x * iz * iz);
    let b = Vector3::new(0.0, intr.fy * iz, -intr.fy * p.y * iz * iz);
    let d = inv_depth;
    // Row r of dP/dxi_i chained: r^T [d R, -R [q]x] = [d (R^T r)^T, (q x R^T r)^T].
    let ra = rot.transpose() * a;
    let rb = rot.transpose() * b;
    let (qa, qb) = (q.cross(&ra), q.cross(&rb));
    // Row r of dP/dxi_j chained: r^T [-d I, [P]x] = [-d r^T, (r x P)^T].
    let (pa, pb) = (a.cross(&p), b.cross(&p));
    let d_uv_d_pose_i = Matrix2x6::new(
        d * ra.x, d * ra.y, d * ra.z, qa.x, qa.y, qa.z, //
        d * rb.x, d * rb.y, d * rb.z, qb.x, qb.y, qb.z,
    );
    let d_uv_d_pose_j = Matrix2x6::new(
        -d * a.x, -d * a.y, -d * a.z, pa.x, pa.y, pa.z, //
        -d * b.x, -d * b.y, -d * b.z, pb.x, pb.y, pb.z,
    );
    let d_uv_d_inv_depth = Vector2::new(a.dot(t), b.dot(t));
    Some(Reprojection { uv, d_uv_d_pose_i, d_uv_d_pose_j, d_uv_d_inv_depth })
}

/// Huber IRLS weight for a whitened residual norm `s >= 0`: 1 inside the threshold, `k / s`
/// outside.
#[inline]
pub fn huber_weight(s: f64, k: f64) -> f64 {
    if s <= k {
        1.0
    } else {
        k / s
    }
}

/// Huber cost `rho(s)`: `s^2 / 2` inside the threshold, `k (s - k / 2)` outside.
#[inline]
pub fn huber_cost(s: f64, k: f64) -> f64 {
    if s <= k {
        0.5 * s * s
    } else {
        k * (s - 0.5 * k)
    }
}

/// `cam_j_from_cam_i` as a rotation matrix and translation.
#[inline]
pub(crate) fn relative(world_from_cam_i: &Se3, world_from_cam_j: &Se3) -> (Matrix3<f64>, Vector3<f64>) {
    let rel = world_from_cam_j.inv_mul(world_from_cam_i);
    (rel.rotation.to_rotation_matrix().into_inner(), rel.translation.vector)
}

/// Robust cost of the window at the given state (poses, inverse depths), prior included.
pub(crate) fn window_cost(win: &Window, world_from_cam: &[Se3], inv_depth: &[f64], config: &BaConfig) -> f64 {
    let intr = win.intrinsics();
    let n_pix = win.n_pixels;
    let k = config.huber_threshold;
    let mut cost = 0.0;
    for (e, edge) in win.edges[..win.n_edges].iter().enumerate() {
        let (rot, t) = relative(&world_from_cam[edge.from], &world_from_cam[edge.to]);
        let depth = &inv_depth[edge.from * n_pix..(edge.from + 1) * n_pix];
        let target = &win.target_xy[e * 2 * n_pix..(e + 1) * 2 * n_pix];
        let weight = &win.weight_xy[e * 2 * n_pix..(e + 1) * 2 * n_pix];
        for p in 0..n_pix {
            let (wx, wy) = (weight[2 * p], weight[2 * p + 1]);
            if wx == 0.0 && wy == 0.0 {
                continue;
            }
            let Some(uv) = predict(&intr, win.rays[p], depth[p], &rot, &t) else { continue };
            let (rx, ry) = (target[2 * p] - uv[0], target[2 * p + 1] - uv[1]);
            cost += huber_cost((wx * rx * rx + wy * ry * ry).sqrt(), k);
        }
    }
    cost + prior_cost(win, inv_depth, config)
}

fn prior_cost(win: &Window, inv_depth: &[f64], config: &BaConfig) -> f64 {
    if config.depth_prior_weight == 0.0 {
        return 0.0;
    }
    let n = win.n_keyframes * win.n_pixels;
    let sq: f64 = inv_depth[..n].iter().zip(&win.prior_inv_depth[..n]).map(|(d, d0)| (d - d0) * (d - d0)).sum();
    0.5 * config.depth_prior_weight * sq
}

/// Builds the undamped normal equations at the window's current state into `sys`; returns
/// the cost there. `H_pp` is dense over the free poses (`6 n_free` square, column-major);
/// `H_pd` holds one 6-vector per (coupling slot, pixel); `H_dd` and `b_d` one value per pixel.
pub(crate) fn linearize(win: &Window, st: &Structure, config: &BaConfig, sys: &mut System) -> f64 {
    let intr = win.intrinsics();
    let n_pix = win.n_pixels;
    let n_depth = win.n_keyframes * n_pix;
    let dim = 6 * st.n_free;
    let k = config.huber_threshold;
    sys.h_pp[..dim * dim].fill(0.0);
    sys.b_p[..dim].fill(0.0);
    sys.h_pd[..st.n_slots * n_pix * 6].fill(0.0);
    sys.h_dd[..n_depth].fill(0.0);
    sys.b_d[..n_depth].fill(0.0);
    let (mut chi2, mut residuals, mut observed) = (0.0, 0usize, 0usize);
    let mut cost = 0.0;
    for (e, edge) in win.edges[..win.n_edges].iter().enumerate() {
        let (i, j) = (edge.from, edge.to);
        let (rot, t) = relative(&win.world_from_cam[i], &win.world_from_cam[j]);
        let (free_i, free_j) = (st.free_index(i), st.free_index(j));
        let slot_ii = st.slot(i, i);
        let slot_ij = st.slot(i, j);
        let depth = &win.inv_depth[i * n_pix..(i + 1) * n_pix];
        let target = &win.target_xy[e * 2 * n_pix..(e + 1) * 2 * n_pix];
        let weight = &win.weight_xy[e * 2 * n_pix..(e + 1) * 2 * n_pix];
        let (mut h_ii, mut h_ij, mut h_jj) = (Matrix6::<f64>::zeros(), Matrix6::<f64>::zeros(), Matrix6::<f64>::zeros());
        let (mut b_i, mut b_j) = (Vector6::<f64>::zeros(), Vector6::<f64>::zeros());
        for p in 0..n_pix {
            let (wx, wy) = (weight[2 * p], weight[2 * p + 1]);
            if wx == 0.0 && wy == 0.0 {
                continue;
            }
            let Some(rp) = reproject_ray(&intr, win.rays[p], depth[p], &rot, &t) else { continue };
            let (rx, ry) = (target[2 * p] - rp.uv.x, target[2 * p + 1] - rp.uv.y);
            let s = (wx * rx * rx + wy * ry * ry).sqrt();
            cost += huber_cost(s, k);
            let rw = huber_weight(s, k);
            chi2 += rw * s * s;
            residuals += (wx > 0.0) as usize + (wy > 0.0) as usize;
            let (wx, wy) = (rw * wx, rw * wy);
            let (ji, jj, jd) = (&rp.d_uv_d_pose_i, &rp.d_uv_d_pose_j, &rp.d_uv_d_inv_depth);
            // Rows of W J and W r.
            let (wrx, wry) = (wx * rx, wy * ry);
            let di = n_pix * i + p;
            observed += (sys.h_dd[di] == 0.0) as usize;
            sys.h_dd[di] += wx * jd.x * jd.x + wy * jd.y * jd.y;
            sys.b_d[di] += jd.x * wrx + jd.y * wry;
            if free_i.is_some() {
                let ji0: Vector6<f64> = ji.row(0).transpose();
                let ji1: Vector6<f64> = ji.row(1).transpose();
                h_ii.ger(wx, &ji0, &ji0, 1.0);
                h_ii.ger(wy, &ji1, &ji1, 1.0);
                b_i += ji0 * wrx + ji1 * wry;
                let c = &mut sys.h_pd[(slot_ii * n_pix + p) * 6..(slot_ii * n_pix + p + 1) * 6];
                for (r, cr) in c.iter_mut().enumerate() {
                    *cr += ji0[r] * (wx * jd.x) + ji1[r] * (wy * jd.y);
                }
                if free_j.is_some() {
                    let jj0: Vector6<f64> = jj.row(0).transpose();
                    let jj1: Vector6<f64> = jj.row(1).transpose();
                    h_ij.ger(wx, &ji0, &jj0, 1.0);
                    h_ij.ger(wy, &ji1, &jj1, 1.0);
                }
            }
            if free_j.is_some() {
                let jj0: Vector6<f64> = jj.row(0).transpose();
                let jj1: Vector6<f64> = jj.row(1).transpose();
                h_jj.ger(wx, &jj0, &jj0, 1.0);
                h_jj.ger(wy, &jj1, &jj1, 1.0);
                b_j += jj0 * wrx + jj1 * wry;
                let c = &mut sys.h_pd[(slot_ij * n_pix + p) * 6..(slot_ij * n_pix + p + 1) * 6];
                for (r, cr) in c.iter_mut().enumerate() {
                    *cr += jj0[r] * (wx * jd.x) + jj1[r] * (wy * jd.y);
                }
            }
        }
        // Scatter the edge's pose blocks into the dense H_pp.
        if let Some(fi) = free_i {
            add_block(&mut sys.h_pp, dim, fi, fi, &h_ii);
            add_vec(&mut sys.b_p, fi, &b_i);
        }
        if let Some(fj) = free_j {
            add_block(&mut sys.h_pp, dim, fj, fj, &h_jj);
            add_vec(&mut sys.b_p, fj, &b_j);
        }
        if let (Some(fi), Some(fj)) = (free_i, free_j) {
            add_block(&mut sys.h_pp, dim, fi, fj, &h_ij);
            add_block(&mut sys.h_pp, dim, fj, fi, &h_ij.transpose());
        }
        debug_assert!(free_i.is_none() || slot_ii != NO_SLOT);
        debug_assert!(free_j.is_none() || slot_ij != NO_SLOT);
    }
    sys.weighted_sq_residual = chi2;
    sys.residuals = residuals;
    sys.observed_depths = observed;
    let w_prior = config.depth_prior_weight;
    if w_prior > 0.0 {
        for q in 0..n_depth {
            sys.h_dd[q] += w_prior;
            sys.b_d[q] += w_prior * (win.prior_inv_depth[q] - win.inv_depth[q]);
        }
    }
    cost + prior_cost(win, &win.inv_depth, config)
}

/// `m[block (bi, bj)] += block` for a column-major `dim x dim` matrix of 6x6 blocks.
#[inline]
pub(crate) fn add_block(m: &mut [f64], dim: usize, bi: usize, bj: usize, block: &Matrix6<f64>) {
    for c in 0..6 {
        let col = &mut m[(6 * bj + c) * dim + 6 * bi..(6 * bj + c) * dim + 6 * bi + 6];
        for (r, v) in col.iter_mut().enumerate() {
            *v += block[(r, c)];
        }
    }
}

#[inline]
fn add_vec(v: &mut [f64], bi: usize, x: &Vector6<f64>) {
    for r in 0..6 {
        v[6 * bi + r] += x[r];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::pose::hat as skew;

    #[test]
    fn closed_form_rows_match_matrix_form() {
        // The row-wise closed forms used above against the plain matrix products.
        let intr = Intrinsics { fx: 30.0, fy: 31.0, cx: 19.5, cy: 14.5, width: 40, height: 30 };
        let rot = duv_core::pose::so3_exp(&Vector3::new(0.05, -0.1, 0.02)).to_rotation_matrix().into_inner();
        let t = Vector3::new(0.2, -0.05, 0.1);
        let ray = [0.13, -0.21];
        let d = 0.4;
        let rp = reproject_ray(&intr, ray, d, &rot, &t).unwrap();
        let q = Vector3::new(ray[0], ray[1], 1.0);
        let p = rot * q + t * d;
        let jp = nalgebra::Matrix2x3::new(intr.fx / p.z, 0.0, -intr.fx * p.x / (p.z * p.z), 0.0, intr.fy / p.z, -intr.fy * p.y / (p.z * p.z));
        let mut dpi = nalgebra::Matrix3x6::zeros();
        dpi.fixed_view_mut::<3, 3>(0, 0).copy_from(&(rot * d));
        dpi.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-rot * skew(&q)));
        let mut dpj = nalgebra::Matrix3x6::zeros();
        dpj.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-Matrix3::identity() * d));
        dpj.fixed_view_mut::<3, 3>(0, 3).copy_from(&skew(&p));
        assert!((jp * dpi - rp.d_uv_d_pose_i).abs().max() < 1e-12);
        assert!((jp * dpj - rp.d_uv_d_pose_j).abs().max() < 1e-12);
        assert!((jp * t - rp.d_uv_d_inv_depth).abs().max() < 1e-12);
    }
}
