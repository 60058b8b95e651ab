//! Stage 5, `map.raster_fwd`: per-pixel front-to-back blending with the underwater medium
//! (one GPU workgroup per tile, one thread per pixel). The per-pixel loop, [`blend_pixel`],
//! is generic so the f64 reference runs the very same arithmetic.

use std::ops::Range;

use rayon::prelude::*;

use super::math::Real;
use super::project::ProjectedSplat;
use super::{DepthMode, MediumPlanes, RenderOutput, TileGrid, ALPHA_MAX, ALPHA_MIN, T_MIN};

/// Medium parameters along one pixel's ray, per channel R, G, B: the veiling (backscatter)
/// colour `c_med` and the attenuation coefficients of the direct signal `sigma_att` and of
/// the backscatter `sigma_bs`, both per metre of range.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelMedium<T> {
    pub c_med: [T; 3],
    pub sigma_att: [T; 3],
    pub sigma_bs: [T; 3],
}

/// A pixel centre and the length of its ray through the normalised image plane,
/// `|(xn, yn, 1)|`: range along the ray `t = z * ray_norm` for camera depth `z`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelRay<T> {
    pub x: T,
    pub y: T,
    pub ray_norm: T,
}

impl<T: Real> PixelRay<T> {
    #[inline(always)]
    pub fn new(x: usize, y: usize, fx: T, fy: T, cx: T, cy: T) -> Self {
        let (x, y) = (T::from_f64(x as f64), T::from_f64(y as f64));
        let xn = (x - cx) / fx;
        let yn = (y - cy) / fy;
        PixelRay { x, y, ray_norm: (xn * xn + yn * yn + T::ONE).sqrt() }
    }
}

/// Everything the forward pass yields for one pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelForward<T> {
    /// `C = c_med + sum_n w_n (c_n exp(-sigma_att t_n) - c_med exp(-sigma_bs t_n))`.
    pub colour: [T; 3],
    /// `sum_n w_n c_n`: the scene without the medium.
    pub restored: [T; 3],
    /// `sum_n w_n d_n / sum_n w_n` (0 when nothing was blended).
    pub depth: T,
    /// `sum_n w_n (d_n - depth)^2 / sum_n w_n`.
    pub depth_var: T,
    /// `sum_n w_n`.
    pub alpha: T,
    /// Object transmittance behind the last blended Gaussian, `T_{N+1}`.
    pub final_t: T,
    /// One past the last blended intersection (its start if none was blended).
    pub end: usize,
}

/// Alpha of a splat at a pixel, and what its derivatives need.
#[derive(Clone, Copy, Debug)]
pub(crate) struct AlphaEval<T> {
    pub alpha: T,
    /// `exp(-q/2)`.
    pub gauss: T,
    pub dx: T,
    pub dy: T,
    /// True when `opacity * gauss` was clamped to [`ALPHA_MAX`].
    pub clamped: bool,
}

/// Alpha of a splat at a pixel; `None` below [`ALPHA_MIN`]. A splat whose `q` is clearly
/// beyond `q_max` is rejected before the exponential (the exact test decides near the edge, so
/// the pre-test never changes the result).
#[inline(always)]
pub(crate) fn splat_alpha<T: Real>(s: &ProjectedSplat<T>, x: T, y: T) -> Option<AlphaEval<T>> {
    let dx = x - s.mean2d[0];
    let dy = y - s.mean2d[1];
    let q = s.conic[0] * dx * dx + T::from_f64(2.0) * s.conic[1] * dx * dy + s.conic[2] * dy * dy;
    if q > s.q_max * T::from_f64(1.0001) + T::from_f64(1e-3) {
        return None;
    }
    let gauss = (T::from_f64(-0.5) * q).exp();
    let raw = s.opacity * gauss;
    if raw < T::from_f64(ALPHA_MIN) {
        return None;
    }
    let max = T::from_f64(ALPHA_MAX);
    let clamped = raw > max;
    Some(AlphaEval { alpha: if clamped { max } else { raw }, gauss, dx, dy, clamped })
}

/// The per-Gaussian depth that is blended: `1/z` or `z`.
#[inline(always)]
pub fn depth_value<T: Real>(z: T, mode: DepthMode) -> T {
    match mode {
        DepthMode::InverseDepth => T::ONE / z,
        DepthMode::Depth => z,
    }
}

/// `d depth_value / dz`.
#[inline(always)]
pub(crate) fn depth_value_dz<T: Real>(z: T, mode: DepthMode) -> T {
    match mode {
        DepthMode::InverseDepth => -T::ONE / (z * z),
        DepthMode::Depth => T::ONE,
    }
}

/// Blends the depth-ordered splats `splat_at(k)`, `k` in `range`, at one pixel: alpha below
/// 1/255 is skipped; blending stops (without the splat) when the transmittance would drop
/// below 1e-4, as in 3DGS. The depth mean and variance use West's weighted update (stable in
/// f32).
#[inline(always)]
pub fn blend_pixel<T: Real>(
    range: Range<usize>,
    splat_at: impl Fn(usize) -> ProjectedSplat<T>,
    ray: &PixelRay<T>,
    medium: &PixelMedium<T>,
    mode: DepthMode,
) -> PixelForward<T> {
    let mut t = T::ONE;
    let mut colour = [T::ZERO; 3];
    let mut restored = [T::ZERO; 3];
    let (mut w_sum, mut mean, mut m2) = (T::ZERO, T::ZERO, T::ZERO);
    let mut end = range.start;
    let t_min = T::from_f64(T_MIN);
    for k in range {
        let s = splat_at(k);
        let Some(a) = splat_alpha(&s, ray.x, ray.y) else { continue };
        let next_t = t * (T::ONE - a.alpha);
        if next_t < t_min {
            break;
        }
        let w = a.alpha * t;
        let range_m = s.z * ray.ray_norm;
        for c in 0..3 {
            let direct = s.colour[c] * (-medium.sigma_att[c] * range_m).exp();
            let veiled = medium.c_med[c] * (-medium.sigma_bs[c] * range_m).exp();
            colour[c] += w * (direct - veiled);
            restored[c] += w * s.colour[c];
        }
        let d = depth_value(s.z, mode);
        let w_new = w_sum + w;
        let delta = d - mean;
        mean += delta * w / w_new;
        m2 += w * delta * (d - mean);
        w_sum = w_new;
        t = next_t;
        end = k + 1;
    }
    for (c, m) in colour.iter_mut().zip(&medium.c_med) {
        *c += *m;
    }
    let blended = w_sum > T::ZERO;
    PixelForward {
        colour,
        restored,
        depth: if blended { mean } else { T::ZERO },
        depth_var: if blended { m2 / w_sum } else { T::ZERO },
        alpha: w_sum,
        final_t: t,
        end,
    }
}

/// Read-only inputs of both rasterisers.
#[derive(Clone, Copy)]
pub struct RasterInputs<'a> {
    pub splats: &'a [ProjectedSplat<f32>],
    /// Gaussian id of each sorted intersection.
    pub sorted_gaussian: &'a [u32],
    /// CSR ranges of sorted intersections per tile (`num_tiles + 1` entries).
    pub tile_offsets: &'a [u32],
    pub grid: TileGrid,
    /// Intrinsics `fx, fy, cx, cy`.
    pub intrinsics: [f32; 4],
    pub depth_mode: DepthMode,
}

impl RasterInputs<'_> {
    #[inline(always)]
    pub(crate) fn ray(&self, x: usize, y: usize) -> PixelRay<f32> {
        let [fx, fy, cx, cy] = self.intrinsics;
        PixelRay::new(x, y, fx, fy, cx, cy)
    }

    #[inline(always)]
    pub(crate) fn tile_range(&self, tile: usize) -> Range<usize> {
        self.tile_offsets[tile] as usize..self.tile_offsets[tile + 1] as usize
    }
}

#[inline(always)]
pub(crate) fn medium_at(medium: &MediumPlanes, i: usize) -> PixelMedium<f32> {
    let p = |d: &[f32]| [d[i * 3], d[i * 3 + 1], d[i * 3 + 2]];
    PixelMedium { c_med: p(&medium.c_med.data), sigma_att: p(&medium.sigma_att.data), sigma_bs: p(&medium.sigma_bs.data) }
}

/// Stage 5 over the image: parallel over tile rows (a row of tiles is a contiguous band of
/// every output image), then tile by tile, pixel by pixel.
pub fn rasterize_forward(inp: &RasterInputs<'_>, medium: &MediumPlanes, out: &mut RenderOutput) {
    let g = inp.grid;
    let band = g.tile_size * g.width;
    (
        out.colour.data.par_chunks_mut(band * 3),
        out.restored.data.par_chunks_mut(band * 3),
        out.depth.data.par_chunks_mut(band),
        out.depth_var.data.par_chunks_mut(band),
        out.alpha.data.par_chunks_mut(band),
        out.final_t.data.par_chunks_mut(band),
        out.isect_end.par_chunks_mut(band),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(ty, (colour, restored, depth, depth_var, alpha, final_t, isect_end))| {
            let rows = depth.len() / g.width;
            for tx in 0..g.tiles_x {
                let range = inp.tile_range(ty * g.tiles_x + tx);
                let x_end = ((tx + 1) * g.tile_size).min(g.width);
                for ly in 0..rows {
                    let y = ty * g.tile_size + ly;
                    for x in tx * g.tile_size..x_end {
                        let local = ly * g.width + x;
                        let m = medium_at(medium, y * g.width + x);
                        let px =
                            blend_pixel(range.clone(), |k| inp.splats[inp.sorted_gaussian[k] as usize], &inp.ray(x, y), &m, inp.depth_mode);
                        colour[local * 3..local * 3 + 3].copy_from_slice(&px.colour);
                        restored[local * 3..local * 3 + 3].copy_from_slice(&px.restored);
                        depth[local] = px.depth;
                        depth_var[local] = px.depth_var;
                        alpha[local] = px.alpha;
                        final_t[local] = px.final_t;
                        isect_end[local] = px.end as u32;
                    }
                }
            }
        });
}
