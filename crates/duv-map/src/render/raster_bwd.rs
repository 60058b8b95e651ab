//! Stage 6, `map.raster_bwd`: per-pixel back-to-front gradient of the blend (one GPU
//! workgroup per tile, one thread per pixel), then a per-Gaussian reduction.
//!
//! # Gradients of one pixel
//! With `w_n = T_n alpha_n`, `v_nc = c_nc exp(-sigma_att,c t_n) - c_med,c exp(-sigma_bs,c t_n)`,
//! `W = sum w_n`, `D`, `V` the blended depth and variance, and upstream gradients `gC`, `gR`,
//! `gD`, `gV`, `gA` on colour, restored colour, depth, depth variance and alpha:
//!
//! ```text
//! q_n       = sum_c (gC_c v_nc + gR_c c_nc) + (gD (d_n - D) + gV ((d_n - D)^2 - V)) / W + gA
//! dL/dalpha_n = T_n q_n - S_n / (1 - alpha_n),   S_n = sum_{m > n} w_m q_m
//! dL/dc_nc  = w_n (gC_c exp(-sigma_att,c t_n) + gR_c)
//! dL/dt_n   = w_n sum_c gC_c (sigma_bs,c c_med,c exp(-sigma_bs,c t_n) - sigma_att,c c_nc exp(-sigma_att,c t_n))
//! dL/dd_n   = w_n (gD + 2 gV (d_n - D)) / W
//! dL/dc_med,c   = gC_c (1 - sum_n w_n exp(-sigma_bs,c t_n))
//! dL/dsigma_att,c = -gC_c sum_n w_n c_nc t_n exp(-sigma_att,c t_n)
//! dL/dsigma_bs,c  =  gC_c c_med,c sum_n w_n t_n exp(-sigma_bs,c t_n)
//! ```
//!
//! `T_n` is recovered back to front from the stored `T_{N+1}` by `T_n = T_{n+1} / (1 - alpha_n)`.
//! Through `alpha = o exp(-q/2)` (unless clamped at 0.99), `q = d^T conic d`, `d = pixel - mean2d`,
//! and `t_n = z_n |ray|`, these become the splat gradients of [`SplatGrad`].
//!
//! # Accumulation without atomics
//! One [`SplatGrad`] per sorted intersection, summed over the pixels of its tile; then
//! [`reduce_isect_grads`] sums each Gaussian's intersections (found through the inverse sort
//! permutation), one task per Gaussian. The result is deterministic. Here each tile row owns
//! the slice of the sorted intersection list its tiles cover; the kernel
//! (`kernels/rasterize_backward.wgsl`, one workgroup per tile) sums the tile's 256 pixels for
//! each intersection in workgroup memory in a fixed order (row by row) instead of pixel by
//! pixel, so the two agree to rounding.

use std::ops::Range;

use rayon::prelude::*;

use super::math::Real;
use super::project::ProjectedSplat;
use super::raster_fwd::{depth_value, depth_value_dz, medium_at, splat_alpha, PixelMedium, PixelRay, RasterInputs};
use super::{DepthMode, MediumPlanes, RenderOutput, RenderUpstream};

/// Upper bound on the exponent of the densification scale `exp(sigma_med t)`.
pub const MAX_DENSIFY_EXPONENT: f64 = 60.0;

/// Upstream gradients at one pixel: `dL/d` colour, restored colour, depth, depth variance
/// and alpha.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelUpstream<T> {
    pub colour: [T; 3],
    pub restored: [T; 3],
    pub depth: T,
    pub depth_var: T,
    pub alpha: T,
}

/// What the backward pass reads back from the forward pass at one pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelState<T> {
    pub depth: T,
    pub depth_var: T,
    pub alpha: T,
    pub final_t: T,
}

/// Gradient of the loss with respect to one projected splat (summed over pixels), plus the
/// densification statistics.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SplatGrad<T> {
    pub mean2d: [T; 2],
    /// With respect to `(a, b, c)` of the conic `[[a, b], [b, c]]` (`b` counted once).
    pub conic: [T; 3],
    /// With respect to the opacity after the sigmoid.
    pub opacity: T,
    pub colour: [T; 3],
    /// With respect to the camera depth of the mean (through `t_n` and `d_n`).
    pub z: T,
    /// `sum_pixels dL/dmean2d * exp(sigma_med t)`, detached scale (paper §3.3).
    pub mean2d_densify: [T; 2],
    /// Pixels the splat contributed to.
    pub pixels: u32,
}

impl<T: Real> SplatGrad<T> {
    #[inline(always)]
    pub fn add(&mut self, o: &SplatGrad<T>) {
        for i in 0..2 {
            self.mean2d[i] += o.mean2d[i];
            self.mean2d_densify[i] += o.mean2d_densify[i];
        }
        for i in 0..3 {
            self.conic[i] += o.conic[i];
            self.colour[i] += o.colour[i];
        }
        self.opacity += o.opacity;
        self.z += o.z;
        self.pixels += o.pixels;
    }
}

/// Back-propagates one pixel through the splats blended in `range` (`start .. end` of the
/// forward pass), back to front. Calls `sink(k, grad)` for every blended splat and returns
/// the gradient with respect to the pixel's medium parameters.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn backprop_pixel<T: Real>(
    range: Range<usize>,
    splat_at: impl Fn(usize) -> ProjectedSplat<T>,
    ray: &PixelRay<T>,
    medium: &PixelMedium<T>,
    mode: DepthMode,
    state: &PixelState<T>,
    up: &PixelUpstream<T>,
    mut sink: impl FnMut(usize, &SplatGrad<T>),
) -> PixelMedium<T> {
    let mut grad = PixelMedium { c_med: up.colour, sigma_att: [T::ZERO; 3], sigma_bs: [T::ZERO; 3] };
    let mut t = state.final_t;
    let mut behind = T::ZERO;
    let inv_w = if state.alpha > T::ZERO { T::ONE / state.alpha } else { T::ZERO };
    let sigma_med = (medium.sigma_att[0] + medium.sigma_att[1] + medium.sigma_att[2]) / T::from_f64(3.0);
    let (two, max_exp) = (T::from_f64(2.0), T::from_f64(MAX_DENSIFY_EXPONENT));
    for k in range.rev() {
        let s = splat_at(k);
        let Some(a) = splat_alpha(&s, ray.x, ray.y) else { continue };
        let one_minus = T::ONE - a.alpha;
        t /= one_minus;
        let w = t * a.alpha;
        let range_m = s.z * ray.ray_norm;
        let mut out = SplatGrad { pixels: 1, ..SplatGrad::default() };
        let mut value = T::ZERO;
        let mut g_range = T::ZERO;
        for c in 0..3 {
            let e_att = (-medium.sigma_att[c] * range_m).exp();
            let e_bs = (-medium.sigma_bs[c] * range_m).exp();
            let col = s.colour[c];
            value += up.colour[c] * (col * e_att - medium.c_med[c] * e_bs) + up.restored[c] * col;
            out.colour[c] = w * (up.colour[c] * e_att + up.restored[c]);
            g_range += w * up.colour[c] * (medium.sigma_bs[c] * medium.c_med[c] * e_bs - medium.sigma_att[c] * col * e_att);
            grad.c_med[c] -= up.colour[c] * w * e_bs;
            grad.sigma_att[c] -= up.colour[c] * w * col * range_m * e_att;
            grad.sigma_bs[c] += up.colour[c] * w * medium.c_med[c] * range_m * e_bs;
        }
        let d = depth_value(s.z, mode);
        let dd = d - state.depth;
        value += (up.depth * dd + up.depth_var * (dd * dd - state.depth_var)) * inv_w + up.alpha;
        let g_d = w * (up.depth + two * up.depth_var * dd) * inv_w;
        out.z = g_range * ray.ray_norm + g_d * depth_value_dz(s.z, mode);
        let g_alpha = t * value - behind / one_minus;
        behind += w * value;
        if !a.clamped {
            out.opacity = g_alpha * a.gauss;
            let g_q = T::from_f64(-0.5) * a.alpha * g_alpha;
            out.conic = [g_q * a.dx * a.dx, g_q * two * a.dx * a.dy, g_q * a.dy * a.dy];
            out.mean2d = [-two * g_q * (s.conic[0] * a.dx + s.conic[1] * a.dy), -two * g_q * (s.conic[1] * a.dx + s.conic[2] * a.dy)];
            let scale = (sigma_med * range_m).min(max_exp).exp();
            out.mean2d_densify = [out.mean2d[0] * scale, out.mean2d[1] * scale];
        }
        sink(k, &out);
    }
    grad
}

/// Shared read-only context of the tile-row recursion.
struct BwdCtx<'a> {
    inp: &'a RasterInputs<'a>,
    medium: &'a MediumPlanes,
    fwd: &'a RenderOutput,
    up: &'a RenderUpstream,
}

/// Stage 6a over the image: every tile row accumulates into its own slice of `partials`
/// (indexed by sorted intersection, zeroed here) and writes the medium gradients of its
/// pixels (overwritten).
pub fn rasterize_backward(
    inp: &RasterInputs<'_>,
    medium: &MediumPlanes,
    fwd: &RenderOutput,
    up: &RenderUpstream,
    partials: &mut [SplatGrad<f32>],
    medium_grads: &mut MediumPlanes,
) {
    let g = inp.grid;
    let n = inp.tile_offsets[g.tiles_x * g.tiles_y] as usize;
    let ctx = BwdCtx { inp, medium, fwd, up };
    bwd_rows(
        &ctx,
        0,
        g.tiles_y,
        &mut partials[..n],
        &mut medium_grads.c_med.data,
        &mut medium_grads.sigma_att.data,
        &mut medium_grads.sigma_bs.data,
    );
}

/// Splits tile rows `r0..r1` in two (each half's intersections and pixel bands are
/// contiguous) until one row is left.
fn bwd_rows(ctx: &BwdCtx<'_>, r0: usize, r1: usize, partials: &mut [SplatGrad<f32>], gc: &mut [f32], ga: &mut [f32], gb: &mut [f32]) {
    let g = ctx.inp.grid;
    if r1 - r0 > 1 {
        let mid = r0 + (r1 - r0) / 2;
        let offsets = ctx.inp.tile_offsets;
        let at_isect = (offsets[mid * g.tiles_x] - offsets[r0 * g.tiles_x]) as usize;
        let at_px = (mid - r0) * g.tile_size * g.width * 3;
        let (p0, p1) = partials.split_at_mut(at_isect);
        let (c0, c1) = gc.split_at_mut(at_px);
        let (a0, a1) = ga.split_at_mut(at_px);
        let (b0, b1) = gb.split_at_mut(at_px);
        rayon::join(|| bwd_rows(ctx, r0, mid, p0, c0, a0, b0), || bwd_rows(ctx, mid, r1, p1, c1, a1, b1));
        return;
    }
    let ty = r0;
    let inp = ctx.inp;
    partials.fill(SplatGrad::default());
    let base = inp.tile_offsets[ty * g.tiles_x] as usize;
    let y0 = ty * g.tile_size;
    let rows = gc.len() / (g.width * 3);
    for tx in 0..g.tiles_x {
        let range = inp.tile_range(ty * g.tiles_x + tx);
        let x_end = ((tx + 1) * g.tile_size).min(g.width);
        for ly in 0..rows {
            let y = y0 + ly;
            for x in tx * g.tile_size..x_end {
                let i = y * g.width + x;
                // Clamped to the tile's range, so an output from another render cannot index
                // outside the intersection buffers.
                let end = (ctx.fwd.isect_end[i] as usize).clamp(range.start, range.end);
                let state = PixelState {
                    depth: ctx.fwd.depth.data[i],
                    depth_var: ctx.fwd.depth_var.data[i],
                    alpha: ctx.fwd.alpha.data[i],
                    final_t: ctx.fwd.final_t.data[i],
                };
                let up = ctx.up.pixel(i);
                let m = medium_at(ctx.medium, i);
                let grad = backprop_pixel(
                    range.start..end,
                    |k| inp.splats[inp.sorted_gaussian[k] as usize],
                    &inp.ray(x, y),
                    &m,
                    inp.depth_mode,
                    &state,
                    &up,
                    |k, sg| partials[k - base].add(sg),
                );
                let local = (ly * g.width + x) * 3;
                gc[local..local + 3].copy_from_slice(&grad.c_med);
                ga[local..local + 3].copy_from_slice(&grad.sigma_att);
                gb[local..local + 3].copy_from_slice(&grad.sigma_bs);
            }
        }
    }
}

/// Stage 6b, one task per Gaussian: sums the per-intersection partials of Gaussian `g`
/// (its pre-sort slots `isect_offsets[g] .. isect_offsets[g + 1]`, moved by the sort to
/// `slot_to_sorted[slot]`) into `out[g]`.
pub fn reduce_isect_grads(isect_offsets: &[u32], slot_to_sorted: &[u32], partials: &[SplatGrad<f32>], out: &mut [SplatGrad<f32>]) {
    let n = isect_offsets.len() - 1;
    out[..n].par_iter_mut().enumerate().with_min_len(256).for_each(|(g, o)| {
        let mut acc = SplatGrad::default();
        for s in isect_offsets[g]..isect_offsets[g + 1] {
            acc.add(&partials[slot_to_sorted[s as usize] as usize]);
        }
        *o = acc;
    });
}
