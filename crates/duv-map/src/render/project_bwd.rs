//! Stage 7, `map.project_bwd` (one GPU thread per Gaussian): splat gradients back to the
//! Gaussian parameters, through the conic inverse, the EWA projection `J Sigma_c J^T`, the
//! covariance `R S S^T R^T`, the quaternion normalisation, the perspective mean, the SH colour
//! (clamp and view direction) and the sigmoid opacity. The camera pose gets no gradient.

use rayon::prelude::*;

use super::math::{mat3_mul, mat3_mul_at, mat3_t_vec, quat_to_mat3_backward, sigmoid, Real, Mat3};
use super::project::{projection_tape, ProjectionSetup};
use super::raster_bwd::SplatGrad;
use crate::gaussians::{GaussianGrads, GaussianParam, Gaussians, SH_C0, SH_C1};

/// Gradient with respect to the parameters of one Gaussian given the gradient of its splat;
/// `None` when the Gaussian is culled by the projection (it has no gradient then).
pub fn project_splat_backward<T: Real>(p: &GaussianParam<T>, s: &ProjectionSetup<T>, g: &SplatGrad<T>) -> Option<GaussianParam<T>> {
    let tape = projection_tape(p, s)?;
    let two = T::from_f64(2.0);
    let [ca, cb, cc] = tape.cov2d;
    let det2 = tape.det * tape.det;
    let [ga, gb, gc] = g.conic;
    // Conic (C/det, -B/det, A/det) back to Sigma_2d = [[A, B], [B, C]].
    let d_a = (-ga * cc * cc + gb * cb * cc - gc * cb * cb) / det2;
    let d_b = (two * ga * cb * cc - gb * (ca * cc + cb * cb) + two * gc * ca * cb) / det2;
    let d_c = (-ga * cb * cb + gb * cb * ca - gc * ca * ca) / det2;
    // As a symmetric matrix gradient (dL = tr(G^T dSigma)).
    let g2 = [[d_a, d_b / two], [d_b / two, d_c]];
    let j = &tape.j;
    let w = &tape.sigma_c;
    // dL/dJ = 2 G2 J W; dL/dW = J^T G2 J.
    let mut jw = [[T::ZERO; 3]; 2];
    for r in 0..2 {
        for c in 0..3 {
            jw[r][c] = j[r][0] * w[0][c] + j[r][1] * w[1][c] + j[r][2] * w[2][c];
        }
    }
    let mut g_j = [[T::ZERO; 3]; 2];
    for r in 0..2 {
        for c in 0..3 {
            g_j[r][c] = two * (g2[r][0] * jw[0][c] + g2[r][1] * jw[1][c]);
        }
    }
    let mut g_w: Mat3<T> = [[T::ZERO; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            g_w[r][c] = j[0][r] * (g2[0][0] * j[0][c] + g2[0][1] * j[1][c]) + j[1][r] * (g2[1][0] * j[0][c] + g2[1][1] * j[1][c]);
        }
    }
    // W = R Sigma_w R^T -> dL/dSigma_w = R^T gW R; Sigma_w = M M^T -> dL/dM = 2 gSigma_w M.
    let r_cw = &s.cam_from_world_rot;
    let g_sigma_w = mat3_mul(&mat3_mul_at(r_cw, &g_w), r_cw);
    let g_m = mat3_mul(&g_sigma_w, &tape.m).map(|row| row.map(|v| two * v));
    // M = Rq diag(scale).
    let mut g_rq: Mat3<T> = [[T::ZERO; 3]; 3];
    let mut g_log_scale = [T::ZERO; 3];
    for col in 0..3 {
        let mut g_scale = T::ZERO;
        for row in 0..3 {
            g_rq[row][col] = g_m[row][col] * tape.scale[col];
            g_scale += g_m[row][col] * tape.rq[row][col];
        }
        g_log_scale[col] = g_scale * tape.scale[col];
    }
    let g_qn = quat_to_mat3_backward(&tape.qn, &g_rq);
    let dot = g_qn[0] * tape.qn[0] + g_qn[1] * tape.qn[1] + g_qn[2] * tape.qn[2] + g_qn[3] * tape.qn[3];
    let g_rotation: [T; 4] = std::array::from_fn(|i| (g_qn[i] - tape.qn[i] * dot) / tape.q_norm);

    // Camera-frame mean: the Jacobian, the projected mean, and the direct depth gradient.
    let [x, y, z] = tape.mean_c;
    let (fx, fy) = (s.fx, s.fy);
    let z2 = z * z;
    let mut g_mean_c = [T::ZERO; 3];
    g_mean_c[2] += -g_j[0][0] * fx / z2 - g_j[1][1] * fy / z2;
    // J[0][2] = -fx txz / z with txz = x/z inside the clamp, a constant outside it.
    for (axis, f) in [(0usize, fx), (1usize, fy)] {
        let g = g_j[axis][2];
        if tape.inside[axis] {
            g_mean_c[axis] += -g * f / z2;
            g_mean_c[2] += two * g * f * tape.txz[axis] / z2;
        } else {
            g_mean_c[2] += g * f * tape.txz[axis] / z2;
        }
    }
    g_mean_c[0] += g.mean2d[0] * fx / z;
    g_mean_c[1] += g.mean2d[1] * fy / z;
    g_mean_c[2] += -(g.mean2d[0] * fx * x + g.mean2d[1] * fy * y) / z2 + g.z;
    let mut g_mean = mat3_t_vec(r_cw, &g_mean_c);

    // SH colour, clamped at 0.
    let (c0, c1) = (T::from_f64(SH_C0), T::from_f64(SH_C1));
    let mut g_f_dc = [T::ZERO; 3];
    let mut g_f_rest = [T::ZERO; 9];
    let mut g_dir = [T::ZERO; 3];
    let dir = tape.dir;
    for c in 0..3 {
        if tape.colour_raw[c] < T::ZERO {
            continue;
        }
        let gcol = g.colour[c];
        g_f_dc[c] = c0 * gcol;
        g_f_rest[c] = -c1 * dir[1] * gcol;
        g_f_rest[3 + c] = c1 * dir[2] * gcol;
        g_f_rest[6 + c] = -c1 * dir[0] * gcol;
        g_dir[0] += -c1 * p.f_rest[6 + c] * gcol;
        g_dir[1] += -c1 * p.f_rest[c] * gcol;
        g_dir[2] += c1 * p.f_rest[3 + c] * gcol;
    }
    let proj = g_dir[0] * dir[0] + g_dir[1] * dir[1] + g_dir[2] * dir[2];
    for i in 0..3 {
        g_mean[i] += (g_dir[i] - dir[i] * proj) / tape.dist;
    }

    let o = sigmoid(p.opacity_logit);
    Some(GaussianParam {
        mean: g_mean,
        log_scale: g_log_scale,
        rotation: g_rotation,
        opacity_logit: g.opacity * o * (T::ONE - o),
        f_dc: g_f_dc,
        f_rest: g_f_rest,
    })
}

/// Stage 7 over all Gaussians: adds each Gaussian's parameter gradient into `grads`, and its
/// densification statistics (norm of the scaled screen-space gradient, pixel count, one view).
pub fn project_backward(gaussians: &Gaussians, setup: &ProjectionSetup<f32>, splat_grads: &[SplatGrad<f32>], grads: &mut GaussianGrads) {
    let n = gaussians.len();
    let parts = grads.parts_mut();
    (
        parts.mean.par_chunks_mut(3),
        parts.log_scale.par_chunks_mut(3),
        parts.rotation.par_chunks_mut(4),
        parts.opacity_logit.par_iter_mut(),
        parts.f_dc.par_chunks_mut(3),
        parts.f_rest.par_chunks_mut(9),
        parts.densify_grad_norm.par_iter_mut(),
        parts.pixels_touched.par_iter_mut(),
        parts.views.par_iter_mut(),
        splat_grads[..n].par_iter(),
    )
        .into_par_iter()
        .enumerate()
        .with_min_len(256)
        .for_each(|(i, (mean, log_scale, rotation, opacity_logit, f_dc, f_rest, norm, pixels, views, sg))| {
            if sg.pixels == 0 {
                return;
            }
            if let Some(gp) = project_splat_backward(&gaussians.get(i), setup, sg) {
                let add = |dst: &mut [f32], src: &[f32]| dst.iter_mut().zip(src).for_each(|(d, s)| *d += s);
                add(mean, &gp.mean);
                add(log_scale, &gp.log_scale);
                add(rotation, &gp.rotation);
                *opacity_logit += gp.opacity_logit;
                add(f_dc, &gp.f_dc);
                add(f_rest, &gp.f_rest);
            }
            *norm += (sg.mean2d_densify[0] * sg.mean2d_densify[0] + sg.mean2d_densify[1] * sg.mean2d_densify[1]).sqrt();
            *pixels += sg.pixels;
            *views += 1;
        });
}
