//! Per-pixel confidence (texture x photometric x forward-backward x in-view), pooling to the
//! BA's grid, and the per-edge summary.

use super::{bilinear_at, bilinear_cell, bilinear_n, FlowConfig, FlowResult, FlowScreen, FlowStats, PreparedFrame, PreparedLevel};
use rayon::prelude::*;

/// Finest-level weights, forward-backward error and residual of `out.flow` (and
/// `out.backward`). The texture term is the lower of the source's at the pixel and the
/// destination's at the target: both ends of a match need texture.
pub(crate) fn weights<const C: usize>(
    cfg: &FlowConfig,
    fb_on: bool,
    finest: usize,
    src: &PreparedLevel,
    dst: &PreparedLevel,
    src_frame: &PreparedFrame,
    dst_frame: &PreparedFrame,
    out: &mut FlowResult,
) {
    let (w, h) = (src.w, src.h);
    let cell = (1usize << finest) as f32;
    let fb_sigma = cfg.fb_sigma_px / cell;
    let fb_max = cfg.fb_max_px / cell;
    let inv_res2 = 1.0 / (cfg.residual_sigma * cfg.residual_sigma);
    let inv_fb2 = 1.0 / (fb_sigma * fb_sigma);
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    let FlowResult { flow, backward, weight_x, weight_y, fb_error, residual, .. } = out;
    let (fdx, fdy, bdx, bdy) = (&flow.dx.data, &flow.dy.data, &backward.dx.data, &backward.dy.data);
    let (tex_x, tex_y) = (&src_frame.texture_x, &src_frame.texture_y);
    let (dtex_x, dtex_y) = (&dst_frame.texture_x, &dst_frame.texture_y);
    weight_x
        .data
        .par_chunks_mut(w)
        .zip(weight_y.data.par_chunks_mut(w))
        .zip(fb_error.data.par_chunks_mut(w))
        .zip(residual.data.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (((rwx, rwy), rfb), rres))| {
            for x in 0..w {
                let i = y * w + x;
                let (u, v) = (fdx[i], fdy[i]);
                let (tx, ty) = (x as f32 + u, y as f32 + v);
                if !(tx >= 0.0 && tx <= xmax && ty >= 0.0 && ty <= ymax) {
                    rwx[x] = 0.0;
                    rwy[x] = 0.0;
                    rfb[x] = f32::INFINITY;
                    rres[x] = f32::INFINITY;
                    continue;
                }
                let (cx, cy, ax, ay) = bilinear_cell(w, h, tx, ty);
                let res = residual2::<C>(src, dst, i, (cx, cy, ax, ay)).sqrt();
                // Per axis: under the aperture problem the ambiguous axis may disagree while
                // the determined one is right.
                let (ex, ey) = if fb_on {
                    (u + bilinear_at(bdx, w, cx, cy, ax, ay), v + bilinear_at(bdy, w, cx, cy, ax, ay))
                } else {
                    (0.0, 0.0)
                };
                let w_fb = |e: f32| if e.abs() > fb_max { 0.0 } else { 1.0 / (1.0 + e * e * inv_fb2) };
                let w_photo = 1.0 / (1.0 + res * res * inv_res2);
                let tx = tex_x[i].min(bilinear_at(dtex_x, w, cx, cy, ax, ay));
                let ty = tex_y[i].min(bilinear_at(dtex_y, w, cx, cy, ax, ay));
                rwx[x] = tx * w_photo * w_fb(ex);
                rwy[x] = ty * w_photo * w_fb(ey);
                rfb[x] = (ex * ex + ey * ey).sqrt();
                rres[x] = res;
            }
        });
}

/// Mean squared feature difference between source pixel `i` and the destination at a
/// bilinear cell from [`bilinear_cell`] (the photometric residual, squared).
#[inline(always)]
fn residual2<const C: usize>(src: &PreparedLevel, dst: &PreparedLevel, i: usize, at: (usize, usize, f32, f32)) -> f32 {
    let (cx, cy, ax, ay) = at;
    let fd = bilinear_n::<C>(&dst.feat, src.w, cx, cy, ax, ay);
    let mut rr = 0.0f32;
    for (f, t) in fd.iter().zip(&src.feat[i * C..(i + 1) * C]) {
        rr += (f - t) * (f - t);
    }
    rr / C as f32
}

/// The summary of [`FlowEstimator::screen`](super::FlowEstimator::screen): forward flow
/// `fwd` and backward flow `bwd` at `level`, weighted per pixel as [`weights`] does without
/// the texture term (one weight for both axes, from the larger forward-backward error of the
/// two), averaged over each output-grid cell.
pub(crate) fn screen<const C: usize>(
    cfg: &FlowConfig,
    level: usize,
    src: &PreparedLevel,
    dst: &PreparedLevel,
    fwd: (&[f32], &[f32]),
    bwd: (&[f32], &[f32]),
    confident_weight: f32,
) -> FlowScreen {
    let (w, h) = (src.w, src.h);
    let cell = (1usize << level) as f32;
    let b = cfg.output_factor >> level;
    let (pw, ph) = (w / b, h / b);
    let fb_sigma = cfg.fb_sigma_px / cell;
    let fb_max = cfg.fb_max_px / cell;
    let inv_res2 = 1.0 / (cfg.residual_sigma * cfg.residual_sigma);
    let inv_fb2 = 1.0 / (fb_sigma * fb_sigma);
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    let count = (b * b) as f32;
    // Per pooled row: (confident cells, sum of weights, sum of weight x magnitude).
    let (n_conf, sw, swm) = (0..ph)
        .into_par_iter()
        .map(|py| {
            let (mut n_conf, mut sw, mut swm) = (0usize, 0.0f64, 0.0f64);
            for px in 0..pw {
                let mut cell_w = 0.0f32;
                for y in py * b..(py + 1) * b {
                    for x in px * b..(px + 1) * b {
                        let i = y * w + x;
                        let (u, v) = (fwd.0[i], fwd.1[i]);
                        let (tx, ty) = (x as f32 + u, y as f32 + v);
                        if !(tx >= 0.0 && tx <= xmax && ty >= 0.0 && ty <= ymax) {
                            continue;
                        }
                        let (cx, cy, ax, ay) = bilinear_cell(w, h, tx, ty);
                        let res2 = residual2::<C>(src, dst, i, (cx, cy, ax, ay));
                        let ex = u + bilinear_at(bwd.0, w, cx, cy, ax, ay);
                        let ey = v + bilinear_at(bwd.1, w, cx, cy, ax, ay);
                        let e = ex.abs().max(ey.abs());
                        if e > fb_max {
                            continue;
                        }
                        let wgt = 1.0 / (1.0 + res2 * inv_res2) / (1.0 + e * e * inv_fb2);
                        cell_w += wgt;
                        sw += wgt as f64;
                        swm += (wgt * u.hypot(v) * cell) as f64;
                    }
                }
                n_conf += (cell_w / count > confident_weight) as usize;
            }
            (n_conf, sw, swm)
        })
        .reduce(|| (0, 0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    FlowScreen {
        level,
        confident_fraction: n_conf as f32 / (pw * ph).max(1) as f32,
        mean_flow_input_px: if sw > 1e-12 { (swm / sw) as f32 } else { 0.0 },
    }
}

/// Pools the finest flow and weights to `output_factor` cells: per axis, the weight-averaged
/// flow (plain average where the cell has no weight), and the mean weight divided by
/// `1 + spread^2 / pool_spread^2`.
pub(crate) fn pool(cfg: &FlowConfig, finest: usize, out: &mut FlowResult) {
    let cell = 1usize << finest;
    let b = cfg.output_factor / cell;
    let fw = out.flow.width();
    let pw = out.pooled.flow.width();
    let spread_level_px = cfg.pool_spread_px / cell as f32;
    let inv_spread2 = 1.0 / (spread_level_px * spread_level_px);
    let count = (b * b) as f32;
    let to_pooled = 1.0 / b as f32;
    let (fdx, fdy, wxs, wys) = (&out.flow.dx.data, &out.flow.dy.data, &out.weight_x.data, &out.weight_y.data);
    let pooled = &mut out.pooled;
    pooled
        .flow
        .dx
        .data
        .par_chunks_mut(pw)
        .zip(pooled.flow.dy.data.par_chunks_mut(pw))
        .zip(pooled.weight_x.data.par_chunks_mut(pw))
        .zip(pooled.weight_y.data.par_chunks_mut(pw))
        .enumerate()
        .for_each(|(py, (((rdx, rdy), rwx), rwy))| {
            for px in 0..pw {
                let mut s = [0.0f32; 8];
                for j in 0..b {
                    let row = (py * b + j) * fw + px * b;
                    for i in row..row + b {
                        let (u, v, wx, wy) = (fdx[i], fdy[i], wxs[i], wys[i]);
                        s[0] += wx;
                        s[1] += wx * u;
                        s[2] += wx * u * u;
                        s[3] += wy;
                        s[4] += wy * v;
                        s[5] += wy * v * v;
                        s[6] += u;
                        s[7] += v;
                    }
                }
                let (mu, var_u) = weighted_mean_var(s[0], s[1], s[2], s[6] / count);
                let (mv, var_v) = weighted_mean_var(s[3], s[4], s[5], s[7] / count);
                rdx[px] = mu * to_pooled;
                rdy[px] = mv * to_pooled;
                rwx[px] = s[0] / count / (1.0 + var_u * inv_spread2);
                rwy[px] = s[3] / count / (1.0 + var_v * inv_spread2);
            }
        });
}

/// Weighted mean and variance from `sum w`, `sum w x`, `sum w x^2`; `fallback` mean (and zero
/// variance) when the weights vanish.
fn weighted_mean_var(sw: f32, swx: f32, swx2: f32, fallback: f32) -> (f32, f32) {
    if sw > 1e-12 {
        let m = swx / sw;
        (m, (swx2 / sw - m * m).max(0.0))
    } else {
        (fallback, 0.0)
    }
}

pub(crate) fn stats(out: &FlowResult, start_level: usize) -> FlowStats {
    let n = out.weight_x.data.len();
    let cell = out.flow.cell_px as f32;
    let (mut sw, mut swm, mut in_view) = (0.0f64, 0.0f64, 0usize);
    for i in 0..n {
        let wgt = 0.5 * (out.weight_x.data[i] + out.weight_y.data[i]) as f64;
        let (u, v) = (out.flow.dx.data[i], out.flow.dy.data[i]);
        if wgt > 0.0 {
            sw += wgt;
            swm += wgt * ((u as f64).hypot(v as f64) * cell as f64);
        }
        in_view += out.residual.data[i].is_finite() as usize;
    }
    FlowStats {
        start_level,
        mean_weight: (sw / n.max(1) as f64) as f32,
        in_view_fraction: in_view as f32 / n.max(1) as f32,
        mean_flow_input_px: if sw > 1e-12 { (swm / sw) as f32 } else { 0.0 },
    }
}
