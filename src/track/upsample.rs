//! Joint bilateral upsampling (Kopf et al. 2007) of a keyframe's depth-grid maps to the input
//! resolution, guided by the keyframe's image: each full-resolution pixel averages the 4x4
//! nearest depth-grid pixels with a spatial Gaussian (depth-grid pixels) times a range Gaussian
//! on the difference between its intensity and the block mean of the neighbour's cell. Depth
//! edges that coincide with image edges stay sharp; the learned upsampler of DROID-SLAM is
//! not available here.

use crate::core::PlaneF32;
use rayon::prelude::*;

/// Upsamples `low` (one plane, and optionally a second with the same weights) at `cell` input
/// pixels per low pixel into `out` / `out2` (full size), with `guide` (full-resolution 8-bit
/// grey) and `guide_low` (block means at the low grid, [0, 1]). When the second plane is the
/// first's variance, `spread_gain` times the weighted spread of the first plane's neighbours
/// is added to it (interpolation uncertainty). Allocation-free.
#[allow(clippy::too_many_arguments)]
pub(crate) fn joint_bilateral(
    guide: &[u8],
    guide_low: &PlaneF32,
    cell: usize,
    sigma_px: f32,
    sigma_intensity: f32,
    spread_gain: f32,
    low: &PlaneF32,
    out: &mut PlaneF32,
    second: Option<(&PlaneF32, &mut PlaneF32)>,
) {
    let (lw, lh) = (guide_low.width, guide_low.height);
    let w = out.width;
    let inv_s = -0.5 / (sigma_px * sigma_px);
    let inv_r = -0.5 / (sigma_intensity * sigma_intensity);
    let c = cell as f32;
    let off = 0.5 * (c - 1.0);
    let row = |y: usize, row1: &mut [f32], mut row2: Option<&mut [f32]>, low2: Option<&PlaneF32>| {
        let ly = (y as f32 - off) / c;
        let y0 = (ly.floor() as isize - 1).clamp(0, lh as isize - 1) as usize;
        let y1 = (ly.floor() as isize + 2).clamp(0, lh as isize - 1) as usize;
        for x in 0..w {
            let lx = (x as f32 - off) / c;
            let x0 = (lx.floor() as isize - 1).clamp(0, lw as isize - 1) as usize;
            let x1 = (lx.floor() as isize + 2).clamp(0, lw as isize - 1) as usize;
            let g = guide[y * w + x] as f32 / 255.0;
            let (mut wsum, mut a1, mut s1, mut a2) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
            for qy in y0..=y1 {
                for qx in x0..=x1 {
                    let (dx, dy) = (qx as f32 - lx, qy as f32 - ly);
                    let q = qy * lw + qx;
                    let dg = guide_low.data[q] - g;
                    let wgt = ((dx * dx + dy * dy) * inv_s + dg * dg * inv_r).exp();
                    let v = low.data[q];
                    wsum += wgt;
                    a1 += wgt * v;
                    s1 += wgt * v * v;
                    if let Some(l2) = low2 {
                        a2 += wgt * l2.data[q];
                    }
                }
            }
            let inv = if wsum > 0.0 { 1.0 / wsum } else { 0.0 };
            let mean = a1 * inv;
            row1[x] = mean;
            if let Some(r2) = row2.as_deref_mut() {
                // The second plane is the variance of the first: add the interpolation's own
                // uncertainty, the weighted spread of the neighbours it mixed.
                let spread = (s1 * inv - mean * mean).max(0.0);
                r2[x] = (a2 * inv + spread_gain * spread).min(f32::MAX);
            }
        }
    };
    match second {
        Some((low2, out2)) => out.data.par_chunks_mut(w).zip(out2.data.par_chunks_mut(w)).enumerate().for_each(|(y, (r1, r2))| row(y, r1, Some(r2), Some(low2))),
        None => out.data.par_chunks_mut(w).enumerate().for_each(|(y, r1)| row(y, r1, None, None)),
    }
}

/// Multiplies a full-resolution inverse-depth variance by `1 + (border_cells / d)^2`, `d` the
/// pixel's distance to the nearest image border in depth-grid cells (pixel centres, so at
/// least half an input pixel). Eq. 4 is the noise the flow weights propagate; near the border
/// the flow is also biased (patches clipped by the border, pooled cells partly out of view, fewer
/// keyframes seeing the point), which the Hessian cannot see. `border_cells` 0 leaves the
/// variance as it is; saturated values (`f32::MAX`, no information) stay saturated.
pub(crate) fn border_variance(variance: &mut PlaneF32, cell: usize, border_cells: f32) {
    if border_cells <= 0.0 {
        return;
    }
    let (w, h) = (variance.width, variance.height);
    let c = cell as f32;
    variance.data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let dy = y.min(h - 1 - y);
        for (x, v) in row.iter_mut().enumerate() {
            let d = (x.min(w - 1 - x).min(dy) as f32 + 0.5) / c;
            let r = border_cells / d;
            *v = (*v * (1.0 + r * r)).min(f32::MAX);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn border_variance_grows_towards_the_border_and_leaves_the_centre() {
        let (w, h, cell) = (64, 48, 8);
        let mut v = PlaneF32::new(w, h);
        v.data.fill(1e-4);
        v.data[0] = f32::MAX;
        border_variance(&mut v, cell, 4.0);
        assert_eq!(v.data[0], f32::MAX);
        // Second column: 1.5 px = 0.1875 cells from the border -> 1 + (4 / 0.1875)^2.
        let expect = 1e-4 * (1.0 + (4.0f32 / (1.5 / 8.0)).powi(2));
        assert!((v.data[24 * w + 1] / expect - 1.0).abs() < 1e-5, "{} vs {expect}", v.data[24 * w + 1]);
        // Monotone towards the centre along a row, and symmetric.
        let row = &v.data[24 * w..25 * w];
        assert!(row[..w / 2].windows(2).all(|p| p[0] >= p[1]));
        assert!((0..w).all(|x| row[x] == row[w - 1 - x]));
        // The centre (3 cells in) is inflated by 1 + (4 / 3)^2 at most there, never lowered.
        assert!(v.data.iter().all(|x| *x >= 1e-4));
        let mut off = PlaneF32::new(w, h);
        off.data.fill(2.0);
        border_variance(&mut off, cell, 0.0);
        assert!(off.data.iter().all(|x| *x == 2.0));
    }
}
