//! `prepare`: image pyramid, features, feature gradients, patch tables and texture weights.

use super::{FeatureKind, FlowConfig, Layout, LevelGeom, PatchData, PrepScratch, PreparedFrame, PreparedLevel};
use duv_core::PlaneF32;
use rayon::prelude::*;

/// Noise standard deviation factor per pyramid level of the `[1 3 3 1] / 8` filter applied
/// along both axes to white noise: `sqrt(20 / 64)^2`.
pub(crate) const NOISE_FACTOR_PER_LEVEL: f32 = 0.3125;

pub(crate) fn prepare<const C: usize>(
    cfg: &FlowConfig,
    layout: &Layout,
    geoms: &[LevelGeom],
    image: &PlaneF32,
    frame: &mut PreparedFrame,
    scratch: &mut PrepScratch,
) {
    frame.levels[0].image.copy_from_slice(&image.data);
    for l in 1..frame.levels.len() {
        let (prev, cur) = frame.levels.split_at_mut(l);
        let p = &prev[l - 1];
        downsample(&p.image, p.w, p.h, &mut cur[0].image, &mut scratch.a);
    }
    for (lev, geom) in frame.levels.iter_mut().zip(geoms).skip(layout.finest_level) {
        features::<C>(cfg, lev, scratch);
        gradients::<C>(lev);
        patch_table::<C>(geom, lev, cfg.patch_size);
    }
    let finest = layout.finest_level;
    texture(cfg, finest, &frame.levels[finest], &mut frame.texture_x, &mut frame.texture_y, scratch);
}

/// Halves an image with the separable `[1 3 3 1] / 8` filter, so that destination pixel `i`
/// is centred on source coordinate `2 i + 0.5` (borders replicated).
pub(crate) fn downsample(src: &[f32], sw: usize, sh: usize, dst: &mut [f32], tmp: &mut [f32]) {
    let (dw, dh) = (sw / 2, sh / 2);
    let tmp = &mut tmp[..dw * sh];
    tmp.par_chunks_mut(dw).enumerate().for_each(|(y, row)| {
        let s = &src[y * sw..(y + 1) * sw];
        for (x, o) in row.iter_mut().enumerate() {
            let c = 2 * x;
            let a = s[c.saturating_sub(1)];
            let e = s[(c + 2).min(sw - 1)];
            *o = (a + 3.0 * (s[c] + s[c + 1]) + e) * 0.125;
        }
    });
    let tmp = &*tmp;
    dst[..dw * dh].par_chunks_mut(dw).enumerate().for_each(|(y, row)| {
        let c = 2 * y;
        let r0 = &tmp[c.saturating_sub(1) * dw..][..dw];
        let r1 = &tmp[c * dw..][..dw];
        let r2 = &tmp[(c + 1) * dw..][..dw];
        let r3 = &tmp[(c + 2).min(sh - 1) * dw..][..dw];
        for x in 0..dw {
            row[x] = (r0[x] + 3.0 * (r1[x] + r2[x]) + r3[x]) * 0.125;
        }
    });
}

fn features<const C: usize>(cfg: &FlowConfig, lev: &mut PreparedLevel, scratch: &mut PrepScratch) {
    let (w, h) = (lev.w, lev.h);
    let n = w * h;
    match cfg.feature {
        FeatureKind::Intensity => lev.feat[..n].copy_from_slice(&lev.image),
        FeatureKind::LocalNormalized => local_normalize(
            &lev.image,
            w,
            h,
            cfg.normalize_radius,
            cfg.normalize_eps,
            &mut lev.feat[..n],
            &mut scratch.b,
            &mut scratch.c,
        ),
        FeatureKind::SoftCensus => {
            let lni = &mut scratch.d[..n];
            local_normalize(
                &lev.image,
                w,
                h,
                cfg.normalize_radius,
                cfg.normalize_eps,
                lni,
                &mut scratch.b,
                &mut scratch.c,
            );
            soft_census::<C>(lni, w, h, cfg.census_eps, &mut lev.feat);
        }
    }
}

/// `(I - mean) / sqrt(var + eps^2)` over a `(2 r + 1)^2` box (borders replicated).
#[allow(clippy::too_many_arguments)]
pub(crate) fn local_normalize(
    img: &[f32],
    w: usize,
    h: usize,
    r: usize,
    eps: f32,
    out: &mut [f32],
    sum: &mut [f32],
    sq: &mut [f32],
) {
    let (sum, sq) = (&mut sum[..w * h], &mut sq[..w * h]);
    // Centre intensities around 0.5 so that E[I^2] - E[I]^2 keeps its precision in f32.
    sum.par_chunks_mut(w).zip(sq.par_chunks_mut(w)).enumerate().for_each(|(y, (rs, rq))| {
        let row = &img[y * w..(y + 1) * w];
        for x in 0..w {
            let (mut s, mut q) = (0.0f32, 0.0f32);
            for k in x as isize - r as isize..=(x + r) as isize {
                let v = row[k.clamp(0, w as isize - 1) as usize] - 0.5;
                s += v;
                q += v * v;
            }
            rs[x] = s;
            rq[x] = q;
        }
    });
    let (sum, sq) = (&*sum, &*sq);
    let inv_n = 1.0 / ((2 * r + 1) * (2 * r + 1)) as f32;
    let eps2 = eps * eps;
    out[..w * h].par_chunks_mut(w).enumerate().for_each(|(y, ro)| {
        let row = &img[y * w..(y + 1) * w];
        for x in 0..w {
            let (mut s, mut q) = (0.0f32, 0.0f32);
            for k in y as isize - r as isize..=(y + r) as isize {
                let i = k.clamp(0, h as isize - 1) as usize * w + x;
                s += sum[i];
                q += sq[i];
            }
            let mean = s * inv_n;
            let var = (q * inv_n - mean * mean).max(0.0);
            ro[x] = (row[x] - 0.5 - mean) / (var + eps2).sqrt();
        }
    });
}

/// Soft census in four directions (two pixels to the right, below, below-right, below-left):
/// `d / sqrt(d^2 + eps^2)` with `d` the difference of the neighbour to the centre.
fn soft_census<const C: usize>(lni: &[f32], w: usize, h: usize, eps: f32, feat: &mut [f32]) {
    const OFFSETS: [(isize, isize); 4] = [(2, 0), (0, 2), (2, 2), (-2, 2)];
    let eps2 = eps * eps;
    feat[..w * h * C].par_chunks_mut(w * C).enumerate().for_each(|(y, row)| {
        for x in 0..w {
            let centre = lni[y * w + x];
            for (c, &(ox, oy)) in OFFSETS.iter().enumerate().take(C) {
                let xx = (x as isize + ox).clamp(0, w as isize - 1) as usize;
                let yy = (y as isize + oy).clamp(0, h as isize - 1) as usize;
                let d = lni[yy * w + xx] - centre;
                row[x * C + c] = d / (d * d + eps2).sqrt();
            }
        }
    });
}

/// Central differences of every feature channel (one-sided halves at the borders).
fn gradients<const C: usize>(lev: &mut PreparedLevel) {
    let (w, h) = (lev.w, lev.h);
    let feat = &lev.feat;
    lev.grad_x[..w * h * C]
        .par_chunks_mut(w * C)
        .zip(lev.grad_y[..w * h * C].par_chunks_mut(w * C))
        .enumerate()
        .for_each(|(y, (rx, ry))| {
            let (ym, yp) = (y.saturating_sub(1), (y + 1).min(h - 1));
            for x in 0..w {
                let (xm, xp) = (x.saturating_sub(1), (x + 1).min(w - 1));
                for c in 0..C {
                    rx[x * C + c] = 0.5 * (feat[(y * w + xp) * C + c] - feat[(y * w + xm) * C + c]);
                    ry[x * C + c] = 0.5 * (feat[(yp * w + x) * C + c] - feat[(ym * w + x) * C + c]);
                }
            }
        });
}

/// Inverse Hessian and mean gradients of every source patch of the level's grid.
fn patch_table<const C: usize>(geom: &LevelGeom, lev: &mut PreparedLevel, p: usize) {
    let nx = geom.patch_x.len();
    let w = lev.w;
    let (grad_x, grad_y) = (&lev.grad_x, &lev.grad_y);
    let n = (p * p) as f32;
    lev.patches.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
        let py = geom.patch_y[j];
        for (i, pd) in row.iter_mut().enumerate() {
            let px = geom.patch_x[i];
            let mut sg = [[0.0f32; 2]; C];
            let (mut hxx, mut hxy, mut hyy) = (0.0f32, 0.0f32, 0.0f32);
            for yy in py..py + p {
                let gxs = &grad_x[(yy * w + px) * C..(yy * w + px + p) * C];
                let gys = &grad_y[(yy * w + px) * C..(yy * w + px + p) * C];
                for (px_gx, px_gy) in gxs.chunks_exact(C).zip(gys.chunks_exact(C)) {
                    for c in 0..C {
                        let (gx, gy) = (px_gx[c], px_gy[c]);
                        sg[c][0] += gx;
                        sg[c][1] += gy;
                        hxx += gx * gx;
                        hxy += gx * gy;
                        hyy += gy * gy;
                    }
                }
            }
            let mut mean_grad = [0.0f32; 8];
            for c in 0..C {
                let (mx, my) = (sg[c][0] / n, sg[c][1] / n);
                mean_grad[2 * c] = mx;
                mean_grad[2 * c + 1] = my;
                hxx -= n * mx * mx;
                hxy -= n * mx * my;
                hyy -= n * my * my;
            }
            *pd = PatchData { hinv: regularised_inverse(hxx, hxy, hyy, n), mean_grad };
        }
    });
}

/// Inverse of `[[a, b], [b, c]] + lambda I` with `lambda = 1e-3 trace`; zero for a flat patch.
fn regularised_inverse(a: f32, b: f32, c: f32, n: f32) -> [f32; 3] {
    let tr = a + c;
    if tr.is_nan() || tr <= 1e-9 * n {
        return [0.0; 3];
    }
    let lambda = 1e-3 * tr;
    let (a, c) = (a + lambda, c + lambda);
    let det = a * c - b * b;
    if det.is_nan() || det <= 0.0 {
        return [0.0; 3];
    }
    [c / det, -b / det, a / det]
}

/// Per-axis texture weights of the finest level from the intensity structure tensor.
fn texture(cfg: &FlowConfig, level: usize, lev: &PreparedLevel, tx: &mut [f32], ty: &mut [f32], s: &mut PrepScratch) {
    let (w, h) = (lev.w, lev.h);
    let n = w * h;
    let img = &lev.image;
    let (gxx, gxy, gyy) = (&mut s.a[..n], &mut s.b[..n], &mut s.c[..n]);
    gxx.par_chunks_mut(w).zip(gxy.par_chunks_mut(w)).zip(gyy.par_chunks_mut(w)).enumerate().for_each(
        |(y, ((rxx, rxy), ryy))| {
            let (ym, yp) = (y.saturating_sub(1), (y + 1).min(h - 1));
            for x in 0..w {
                let (xm, xp) = (x.saturating_sub(1), (x + 1).min(w - 1));
                let gx = 0.5 * (img[y * w + xp] - img[y * w + xm]);
                let gy = 0.5 * (img[yp * w + x] - img[ym * w + x]);
                rxx[x] = gx * gx;
                rxy[x] = gx * gy;
                ryy[x] = gy * gy;
            }
        },
    );
    let r = cfg.texture_radius;
    let (gxx, gxy, gyy) = (&*gxx, &*gxy, &*gyy);
    let (hxx, hxy, hyy) = (&mut s.d[..n], &mut s.e[..n], &mut s.f[..n]);
    hxx.par_chunks_mut(w).zip(hxy.par_chunks_mut(w)).zip(hyy.par_chunks_mut(w)).enumerate().for_each(
        |(y, ((rxx, rxy), ryy))| {
            for x in 0..w {
                let (mut a, mut b, mut c) = (0.0f32, 0.0f32, 0.0f32);
                for k in x as isize - r as isize..=(x + r) as isize {
                    let i = y * w + k.clamp(0, w as isize - 1) as usize;
                    a += gxx[i];
                    b += gxy[i];
                    c += gyy[i];
                }
                rxx[x] = a;
                rxy[x] = b;
                ryy[x] = c;
            }
        },
    );
    let (hxx, hxy, hyy) = (&*hxx, &*hxy, &*hyy);
    let sigma = cfg.noise_sigma * NOISE_FACTOR_PER_LEVEL.powi(level as i32);
    let inv_var = 1.0 / (sigma * sigma);
    let count = ((2 * r + 1) * (2 * r + 1)) as f32;
    // Information pure noise would show (central differences: gradient variance sigma^2 / 2),
    // plus two of its standard deviations.
    let floor = 0.5 * count + 2.0 * (0.5 * count).sqrt();
    let sigma_level_px = cfg.texture_sigma_px / (1usize << level) as f32;
    let lambda0 = 1.0 / (sigma_level_px * sigma_level_px);
    tx[..n].par_chunks_mut(w).zip(ty[..n].par_chunks_mut(w)).enumerate().for_each(|(y, (rx, ry))| {
        for x in 0..w {
            let (mut a, mut b, mut c) = (0.0f32, 0.0f32, 0.0f32);
            for k in y as isize - r as isize..=(y + r) as isize {
                let i = k.clamp(0, h as isize - 1) as usize * w + x;
                a += hxx[i];
                b += hxy[i];
                c += hyy[i];
            }
            let (a, b, c) = (a * inv_var, b * inv_var, c * inv_var);
            let lx = (a - b * b / (c + 1e-6) - floor).max(0.0);
            let ly = (c - b * b / (a + 1e-6) - floor).max(0.0);
            rx[x] = lx / (lx + lambda0);
            ry[x] = ly / (ly + lambda0);
        }
    });
}
