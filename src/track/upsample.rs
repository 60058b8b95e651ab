//! Joint bilateral upsampling (Kopf et al. 2007) of a keyframe's depth-grid maps to the input
//! resolution, guided by the keyframe's image: each full-resolution pixel averages the 4x4
//! nearest depth-grid pixels with a spatial Gaussian (depth-grid pixels) times a range Gaussian
//! on the difference between its intensity and the block mean of the neighbour's cell. Depth
//! edges that coincide with image edges stay sharp; the learned upsampler of DROID-SLAM is
//! not available here.

use crate::core::PlaneF32;
use rayon::prelude::*;

/// Upsamples `low` maps (`cell` input pixels per low pixel) into `out` maps (full size), with
/// `guide` (full-resolution 8-bit grey) and `guide_low` (block means at the low grid, [0, 1]).
/// `low` and `out` hold one or more planes upsampled with the same weights.
#[allow(clippy::too_many_arguments)]
pub(crate) fn joint_bilateral(
    guide: &[u8],
    guide_low: &PlaneF32,
    cell: usize,
    sigma_px: f32,
    sigma_intensity: f32,
    low: &[&PlaneF32],
    out: &mut [&mut PlaneF32],
) {
    let (lw, lh) = (guide_low.width, guide_low.height);
    let w = out[0].width;
    let inv_s = -0.5 / (sigma_px * sigma_px);
    let inv_r = -0.5 / (sigma_intensity * sigma_intensity);
    let c = cell as f32;
    let off = 0.5 * (c - 1.0);
    let n_planes = low.len();
    // Rows in parallel: split every output plane by rows, zipped through one index.
    let rows: Vec<_> = (0..out[0].height).collect();
    let mut planes: Vec<&mut [f32]> = out.iter_mut().map(|p| p.data.as_mut_slice()).collect();
    let chunks: Vec<Vec<&mut [f32]>> = {
        let mut per_row: Vec<Vec<&mut [f32]>> = rows.iter().map(|_| Vec::with_capacity(n_planes)).collect();
        for plane in planes.iter_mut() {
            for (y, row) in plane.chunks_mut(w).enumerate() {
                per_row[y].push(row);
            }
        }
        per_row
    };
    chunks.into_par_iter().enumerate().for_each(|(y, mut rows_out)| {
        let ly = (y as f32 - off) / c;
        let y0 = (ly.floor() as isize - 1).clamp(0, lh as isize - 1) as usize;
        let y1 = (ly.floor() as isize + 2).clamp(0, lh as isize - 1) as usize;
        for x in 0..w {
            let lx = (x as f32 - off) / c;
            let x0 = (lx.floor() as isize - 1).clamp(0, lw as isize - 1) as usize;
            let x1 = (lx.floor() as isize + 2).clamp(0, lw as isize - 1) as usize;
            let g = guide[y * w + x] as f32 / 255.0;
            let mut wsum = 0.0f32;
            let mut acc = [0.0f32; 4];
            for qy in y0..=y1 {
                for qx in x0..=x1 {
                    let (dx, dy) = (qx as f32 - lx, qy as f32 - ly);
                    let dg = guide_low.data[qy * lw + qx] - g;
                    let wgt = ((dx * dx + dy * dy) * inv_s + dg * dg * inv_r).exp();
                    wsum += wgt;
                    for (k, plane) in low.iter().enumerate().take(4) {
                        acc[k] += wgt * plane.data[qy * lw + qx];
                    }
                }
            }
            let inv = if wsum > 0.0 { 1.0 / wsum } else { 0.0 };
            for (k, row) in rows_out.iter_mut().enumerate().take(4) {
                row[x] = acc[k] * inv;
            }
        }
    });
}
