//! Inverse search of the patch grid and densification into a per-pixel field.

use super::{bilinear_at, bilinear_cell, bilinear_n, FlowConfig, LevelFlow, LevelGeom, PreparedLevel, SeedView};
use rayon::prelude::*;

/// Sums of one patch evaluation at a translation.
#[derive(Clone, Copy)]
struct PatchEval<const C: usize> {
    /// `sum g_c r_c` over pixels and channels (gradient of the source, residual dst - src).
    b: [f32; 2],
    /// Per-channel residual sums (for removing the means).
    sum_r: [f32; C],
    /// Sum of squared residuals.
    sum_r2: f32,
}

impl<const C: usize> PatchEval<C> {
    /// Sum of squared mean-removed residuals.
    fn ssd(&self, n: f32) -> f32 {
        let mut s = self.sum_r2;
        for c in 0..C {
            s -= self.sum_r[c] * self.sum_r[c] / n;
        }
        s
    }
}

/// Lanes of the accumulators of the patch loops (independent partial sums vectorise).
const LANES: usize = 8;

/// Residual sums of the source patch at `(px, py)` against the destination warped by `(u, v)`.
#[inline]
fn eval_patch<const C: usize>(
    src: &PreparedLevel,
    dst: &PreparedLevel,
    px: usize,
    py: usize,
    p: usize,
    u: f32,
    v: f32,
) -> PatchEval<C> {
    let w = src.w;
    let (fu, fv) = (u.floor(), v.floor());
    let (ax, ay) = (u - fu, v - fv);
    // Bounds in f32, so that no flow value (huge, infinite) can overflow an index.
    let (x0, y0) = (px as f32 + fu, py as f32 + fv);
    let mut e = PatchEval { b: [0.0; 2], sum_r: [0.0; C], sum_r2: 0.0 };
    if x0 >= 0.0 && y0 >= 0.0 && x0 + (p as f32) < dst.w as f32 && y0 + (p as f32) < dst.h as f32 {
        // Interior: one set of bilinear weights for the whole patch, lane-wise partial sums.
        let (x0, y0) = (x0 as usize, y0 as usize);
        let (w00, w10, w01, w11) = ((1.0 - ax) * (1.0 - ay), ax * (1.0 - ay), (1.0 - ax) * ay, ax * ay);
        let n = p * C;
        let (mut bx, mut by, mut s2, mut sr) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        for j in 0..p {
            let s0 = ((py + j) * w + px) * C;
            let d0 = ((y0 + j) * w + x0) * C;
            let d1 = d0 + w * C;
            let (t, gx, gy) = (&src.feat[s0..s0 + n], &src.grad_x[s0..s0 + n], &src.grad_y[s0..s0 + n]);
            let (a0, a1) = (&dst.feat[d0..d0 + n], &dst.feat[d0 + C..d0 + C + n]);
            let (b0, b1) = (&dst.feat[d1..d1 + n], &dst.feat[d1 + C..d1 + C + n]);
            let full = n / LANES * LANES;
            for o in (0..full).step_by(LANES) {
                let lane = |sl: &[f32]| -> [f32; LANES] { sl[o..o + LANES].try_into().unwrap_or([0.0; LANES]) };
                let (t, gx, gy, a0, a1, b0, b1) = (lane(t), lane(gx), lane(gy), lane(a0), lane(a1), lane(b0), lane(b1));
                for l in 0..LANES {
                    let r = w00 * a0[l] + w10 * a1[l] + w01 * b0[l] + w11 * b1[l] - t[l];
                    bx[l] += gx[l] * r;
                    by[l] += gy[l] * r;
                    s2[l] += r * r;
                    sr[l] += r;
                }
            }
            for k in full..n {
                let r = w00 * a0[k] + w10 * a1[k] + w01 * b0[k] + w11 * b1[k] - t[k];
                let l = k % LANES;
                bx[l] += gx[k] * r;
                by[l] += gy[k] * r;
                s2[l] += r * r;
                sr[l] += r;
            }
        }
        // Lane l holds channel l % C as long as every row starts a lane group on a channel
        // boundary, which holds because LANES is a multiple of C.
        e.b = [bx.iter().sum(), by.iter().sum()];
        e.sum_r2 = s2.iter().sum();
        for (l, v) in sr.iter().enumerate() {
            e.sum_r[l % C] += v;
        }
    } else {
        // Partly outside: clamp every sample to the image.
        for j in 0..p {
            for i in 0..p {
                let (x, y) = (px + i, py + j);
                let (cx, cy, fx, fy) = bilinear_cell(dst.w, dst.h, x as f32 + u, y as f32 + v);
                let warped = bilinear_n::<C>(&dst.feat, dst.w, cx, cy, fx, fy);
                let base = y * w + x;
                for (c, wc) in warped.iter().enumerate() {
                    let k = base * C + c;
                    let r = wc - src.feat[k];
                    e.b[0] += src.grad_x[k] * r;
                    e.b[1] += src.grad_y[k] * r;
                    e.sum_r[c] += r;
                    e.sum_r2 += r * r;
                }
            }
        }
    }
    e
}

/// Moves every patch of the level's grid from its initial flow (the dense `init` field at the
/// patch centre, or the seed where that fits better) by inverse-compositional Gauss-Newton.
#[allow(clippy::too_many_arguments)]
pub(crate) fn search_patches<const C: usize>(
    cfg: &FlowConfig,
    geom: &LevelGeom,
    src: &PreparedLevel,
    dst: &PreparedLevel,
    init: &LevelFlow,
    seed: SeedView<'_>,
    level: usize,
    out: &mut [[f32; 2]],
) {
    let p = cfg.patch_size;
    let n = (p * p) as f32;
    let nx = geom.patch_x.len();
    let half = 0.5 * (p as f32 - 1.0);
    let min_step2 = cfg.patch_min_step_px * cfg.patch_min_step_px;
    let max_move2 = (p * p) as f32;
    out.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
        let py = geom.patch_y[j];
        let cy = py as f32 + half;
        for (i, o) in row.iter_mut().enumerate() {
            let px = geom.patch_x[i];
            let cx = px as f32 + half;
            let (x0, y0, ax, ay) = bilinear_cell(geom.w, geom.h, cx, cy);
            let mut u = [bilinear_at(&init.dx, geom.w, x0, y0, ax, ay), bilinear_at(&init.dy, geom.w, x0, y0, ax, ay)];
            let mut e = eval_patch::<C>(src, dst, px, py, p, u[0], u[1]);
            let mut ssd = e.ssd(n);
            if let Some((su, sv)) = seed.at(level, cx, cy) {
                let es = eval_patch::<C>(src, dst, px, py, p, su, sv);
                let s = es.ssd(n);
                if s < ssd {
                    (u, e, ssd) = ([su, sv], es, s);
                }
            }
            let pd = &src.patches[j * nx + i];
            let hinv = pd.hinv;
            let start = u;
            let mut best = (u, ssd);
            if hinv != [0.0; 3] {
                for _ in 0..cfg.patch_iterations {
                    let (mut bx, mut by) = (e.b[0], e.b[1]);
                    for c in 0..C {
                        bx -= pd.mean_grad[2 * c] * e.sum_r[c];
                        by -= pd.mean_grad[2 * c + 1] * e.sum_r[c];
                    }
                    let du = hinv[0] * bx + hinv[1] * by;
                    let dv = hinv[1] * bx + hinv[2] * by;
                    u = [u[0] - du, u[1] - dv];
                    let (mx, my) = (u[0] - start[0], u[1] - start[1]);
                    let moved2 = mx * mx + my * my;
                    if moved2.is_nan() || moved2 > max_move2 {
                        break;
                    }
                    e = eval_patch::<C>(src, dst, px, py, p, u[0], u[1]);
                    let s = e.ssd(n);
                    if s < best.1 {
                        best = (u, s);
                    }
                    if du * du + dv * dv < min_step2 {
                        break;
                    }
                }
            }
            *o = best.0;
        }
    });
}

/// Per pixel, the mean of the covering patches' flows weighted by the inverse residual.
/// Each row gathers from the patch rows covering it, one patch segment at a time (constant
/// bilinear weights along a segment), into row accumulators: rows are independent.
pub(crate) fn densify<const C: usize>(
    cfg: &FlowConfig,
    geom: &LevelGeom,
    src: &PreparedLevel,
    dst: &PreparedLevel,
    patch_flow: &[[f32; 2]],
    flow: &mut LevelFlow,
    weight_sum: &mut [f32],
) {
    let (w, h) = (geom.w, geom.h);
    let p = geom.patch;
    let nx = geom.patch_x.len();
    let eps = cfg.densify_eps;
    let inv_c = 1.0 / C as f32;
    flow.dx
        .par_chunks_mut(w)
        .zip(flow.dy.par_chunks_mut(w))
        .zip(weight_sum[..w * h].par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, ((rx, ry), rw))| {
            rx.fill(0.0);
            ry.fill(0.0);
            rw.fill(0.0);
            let (j0, j1) = geom.cover_y[y];
            let t_row = &src.feat[y * w * C..(y + 1) * w * C];
            for j in j0 as usize..=j1 as usize {
                for (i, &[u, v]) in patch_flow[j * nx..(j + 1) * nx].iter().enumerate() {
                    let px = geom.patch_x[i];
                    let (fu, fv) = (u.floor(), v.floor());
                    let (x0, yy) = (px as f32 + fu, y as f32 + fv);
                    let (rx, ry, rw) = (&mut rx[px..px + p], &mut ry[px..px + p], &mut rw[px..px + p]);
                    let t = &t_row[px * C..(px + p) * C];
                    if x0 >= 0.0 && yy >= 0.0 && x0 + (p as f32) < w as f32 && yy + 1.0 < h as f32 {
                        let (ax, ay) = (u - fu, v - fv);
                        let (w00, w10, w01, w11) = ((1.0 - ax) * (1.0 - ay), ax * (1.0 - ay), (1.0 - ax) * ay, ax * ay);
                        let d0 = ((yy as usize) * w + x0 as usize) * C;
                        let d1 = d0 + w * C;
                        let (a0, a1) = (&dst.feat[d0..d0 + p * C], &dst.feat[d0 + C..d0 + C + p * C]);
                        let (b0, b1) = (&dst.feat[d1..d1 + p * C], &dst.feat[d1 + C..d1 + C + p * C]);
                        for l in 0..p {
                            let mut r2 = 0.0f32;
                            for c in 0..C {
                                let k = l * C + c;
                                let r = w00 * a0[k] + w10 * a1[k] + w01 * b0[k] + w11 * b1[k] - t[k];
                                r2 += r * r;
                            }
                            let wt = 1.0 / (r2 * inv_c).sqrt().max(eps);
                            rw[l] += wt;
                            rx[l] += wt * u;
                            ry[l] += wt * v;
                        }
                    } else {
                        for l in 0..p {
                            let (cx, cy, fx, fy) = bilinear_cell(w, h, (px + l) as f32 + u, y as f32 + v);
                            let warped = bilinear_n::<C>(&dst.feat, w, cx, cy, fx, fy);
                            let mut r2 = 0.0f32;
                            for c in 0..C {
                                let r = warped[c] - t[l * C + c];
                                r2 += r * r;
                            }
                            let wt = 1.0 / (r2 * inv_c).sqrt().max(eps);
                            rw[l] += wt;
                            rx[l] += wt * u;
                            ry[l] += wt * v;
                        }
                    }
                }
            }
            for x in 0..w {
                let inv = 1.0 / rw[x];
                rx[x] *= inv;
                ry[x] *= inv;
            }
        });
}
