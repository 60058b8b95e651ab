//! Variational refinement of a level's dense flow: feature constancy plus smoothness, both
//! Charbonnier, linearised around the current field and solved by red-black block SOR.
//!
//! Energy per pixel, in the unknown flow `U = (u, v)` around the linearisation point `U0`:
//! `w_d (r + g . (U - U0))^2 + alpha sum_n w_n |U - U_n|^2`, `r` the feature residual at the
//! target of `U0`, `g` the mean of the source gradient and the warped destination gradient,
//! `w_d` and `w_n` the Charbonnier (lagged) weights. A pixel's four neighbours have the other
//! colour of a checkerboard, so each half-sweep solves the 2x2 block of every pixel of one
//! colour independently: no dependency chain along a row, and rows run in parallel.

use super::{bilinear_cell, bilinear_n, FlowConfig, LevelFlow, LevelGeom, PreparedLevel, RefineScratch};
use rayon::prelude::*;

/// Over-relaxation factor of the SOR sweeps.
const SOR_OMEGA: f32 = 1.6;

pub(crate) fn refine<const C: usize>(
    cfg: &FlowConfig,
    geom: &LevelGeom,
    src: &PreparedLevel,
    dst: &PreparedLevel,
    flow: &mut LevelFlow,
    rs: &mut RefineScratch,
) {
    if cfg.refine_outer == 0 || cfg.refine_iterations == 0 {
        return;
    }
    let (w, h) = (geom.w, geom.h);
    let hw = w.div_ceil(2);
    let n = w * h;
    let RefineScratch { coeff, cells, u, v, .. } = rs;
    let coeff = &mut coeff[..n];
    for _ in 0..cfg.refine_outer {
        linearise::<C>(cfg, w, h, src, dst, flow, coeff);
        for colour in 0..2 {
            build_cells(
                coeff,
                w,
                h,
                cfg.refine_smoothness,
                colour,
                flow,
                &mut cells[colour][..h * hw],
                &mut u[colour][..h * hw],
                &mut v[colour][..h * hw],
            );
        }
        for _ in 0..cfg.refine_iterations {
            for (colour, cells) in cells.iter().enumerate() {
                let (mine_u, other_u) = split_colours(u, colour);
                let (mine_v, other_v) = split_colours(v, colour);
                sweep(w, h, colour, &cells[..h * hw], &mut mine_u[..h * hw], &mut mine_v[..h * hw], other_u, other_v);
            }
        }
        for colour in 0..2 {
            let (cu, cv) = (&u[colour], &v[colour]);
            flow.dx.par_chunks_mut(w).zip(flow.dy.par_chunks_mut(w)).enumerate().for_each(|(y, (rx, ry))| {
                let px = (y + colour) % 2;
                for k in 0..hw {
                    let x = 2 * k + px;
                    if x < w {
                        rx[x] = cu[y * hw + k];
                        ry[x] = cv[y * hw + k];
                    }
                }
            });
        }
    }
}

/// The arrays of colour `colour` (mutable) and of the other colour.
fn split_colours(a: &mut [Vec<f32>; 2], colour: usize) -> (&mut [f32], &[f32]) {
    let (first, second) = a.split_at_mut(1);
    if colour == 0 {
        (&mut first[0], &second[0])
    } else {
        (&mut second[0], &first[0])
    }
}

/// Per pixel `[a11, a12, a22, c1, c2, s, 0, 0]`: the data term's normal equations
/// `A U + c = 0` (with the data weight folded in) and the smoothness weight `s` in (0, 1].
fn linearise<const C: usize>(
    cfg: &FlowConfig,
    w: usize,
    h: usize,
    src: &PreparedLevel,
    dst: &PreparedLevel,
    flow: &LevelFlow,
    coeff: &mut [[f32; 8]],
) {
    let (eps_d, eps_s) = (cfg.refine_data_eps, cfg.refine_smooth_eps);
    let (dx, dy) = (&flow.dx, &flow.dy);
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    coeff.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, k) in row.iter_mut().enumerate() {
            let i = y * w + x;
            let (u0, v0) = (dx[i], dy[i]);
            let (tx, ty) = (x as f32 + u0, y as f32 + v0);
            let (mut a11, mut a12, mut a22, mut b1, mut b2) = (0.0f32, 0.0f32, 0.0f32, 0.0f32, 0.0f32);
            if tx >= 0.0 && tx <= xmax && ty >= 0.0 && ty <= ymax {
                let (cx, cy, fx, fy) = bilinear_cell(w, h, tx, ty);
                let fd = bilinear_n::<C>(&dst.feat, w, cx, cy, fx, fy);
                let gdx = bilinear_n::<C>(&dst.grad_x, w, cx, cy, fx, fy);
                let gdy = bilinear_n::<C>(&dst.grad_y, w, cx, cy, fx, fy);
                let mut rr = 0.0f32;
                for c in 0..C {
                    let r = fd[c] - src.feat[i * C + c];
                    let gx = 0.5 * (gdx[c] + src.grad_x[i * C + c]);
                    let gy = 0.5 * (gdy[c] + src.grad_y[i * C + c]);
                    a11 += gx * gx;
                    a12 += gx * gy;
                    a22 += gy * gy;
                    b1 += gx * r;
                    b2 += gy * r;
                    rr += r * r;
                }
                let wd = eps_d / (rr / C as f32 + eps_d * eps_d).sqrt() / C as f32;
                (a11, a12, a22, b1, b2) = (a11 * wd, a12 * wd, a22 * wd, b1 * wd, b2 * wd);
            }
            let (ux, vx) = if x + 1 < w { (dx[i + 1] - u0, dy[i + 1] - v0) } else { (0.0, 0.0) };
            let (uy, vy) = if y + 1 < h { (dx[i + w] - u0, dy[i + w] - v0) } else { (0.0, 0.0) };
            let s = eps_s / (ux * ux + uy * uy + vx * vx + vy * vy + eps_s * eps_s).sqrt();
            *k = [a11, a12, a22, b1 - a11 * u0 - a12 * v0, b2 - a12 * u0 - a22 * v0, s, 0.0, 0.0];
        }
    });
}

/// Cells of one colour: `[w_left, w_right, w_up, w_down, i11, i12, i22, c1, c2, active]`,
/// `i` the inverse of the block `A + (sum w) I`, and their flow taken from `flow`.
#[allow(clippy::too_many_arguments)]
fn build_cells(
    coeff: &[[f32; 8]],
    w: usize,
    h: usize,
    alpha: f32,
    colour: usize,
    flow: &LevelFlow,
    cells: &mut [[f32; 10]],
    u: &mut [f32],
    v: &mut [f32],
) {
    let hw = w.div_ceil(2);
    cells.par_chunks_mut(hw).zip(u.par_chunks_mut(hw)).zip(v.par_chunks_mut(hw)).enumerate().for_each(
        |(y, ((rc, ru), rv))| {
            let px = (y + colour) % 2;
            for k in 0..hw {
                let x = 2 * k + px;
                if x >= w {
                    rc[k] = [0.0; 10];
                    ru[k] = 0.0;
                    rv[k] = 0.0;
                    continue;
                }
                let i = y * w + x;
                let c = &coeff[i];
                let s = c[5];
                let edge = |ok: bool, j: usize| if ok { alpha * 0.5 * (s + coeff[j][5]) } else { 0.0 };
                let wl = edge(x > 0, i.wrapping_sub(1));
                let wr = edge(x + 1 < w, i + 1);
                let wu = edge(y > 0, i.wrapping_sub(w));
                let wd = edge(y + 1 < h, i + w);
                let sw = wl + wr + wu + wd;
                let (m11, m12, m22) = (c[0] + sw, c[1], c[2] + sw);
                let det = m11 * m22 - m12 * m12;
                rc[k] = if det > 1e-12 * (m11 + m22).max(1e-30).powi(2) && det > 0.0 {
                    [wl, wr, wu, wd, m22 / det, -m12 / det, m11 / det, c[3], c[4], 1.0]
                } else {
                    [0.0; 10]
                };
                ru[k] = flow.dx[i];
                rv[k] = flow.dy[i];
            }
        },
    );
}

/// One SOR half-sweep over the cells of `colour`; the other colour's flow is read only.
#[allow(clippy::too_many_arguments)]
fn sweep(
    w: usize,
    h: usize,
    colour: usize,
    cells: &[[f32; 10]],
    mu: &mut [f32],
    mv: &mut [f32],
    ou: &[f32],
    ov: &[f32],
) {
    let hw = w.div_ceil(2);
    mu.par_chunks_mut(hw).zip(mv.par_chunks_mut(hw)).enumerate().for_each(|(y, (ru, rv))| {
        let px = (y + colour) % 2;
        // Rows of the other colour: this one, above and below (clamped; border weights are 0).
        let row = |yy: usize| yy * hw..(yy + 1) * hw;
        let (su_row, sv_row) = (&ou[row(y)], &ov[row(y)]);
        let (uu, uv) = (&ou[row(y.saturating_sub(1))], &ov[row(y.saturating_sub(1))]);
        let (du, dv) = (&ou[row((y + 1).min(h - 1))], &ov[row((y + 1).min(h - 1))]);
        let cells = &cells[y * hw..(y + 1) * hw];
        for k in 0..hw {
            let c = &cells[k];
            // Left and right neighbours in the other colour's row: x = 2k + px, so x - 1 and
            // x + 1 sit at k - 1 and k (px = 0) or at k and k + 1 (px = 1); border weights are 0.
            let (l, r) = if px == 0 { (k.saturating_sub(1), k) } else { (k, (k + 1).min(hw - 1)) };
            let su = c[0] * su_row[l] + c[1] * su_row[r] + c[2] * uu[k] + c[3] * du[k] - c[7];
            let sv = c[0] * sv_row[l] + c[1] * sv_row[r] + c[2] * uv[k] + c[3] * dv[k] - c[8];
            let un = c[4] * su + c[5] * sv;
            let vn = c[5] * su + c[6] * sv;
            let a = SOR_OMEGA * c[9];
            ru[k] += a * (un - ru[k]);
            rv[k] += a * (vn - rv[k]);
        }
    });
}
