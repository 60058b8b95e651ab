//! Joint bilateral upsampling (Kopf et al. 2007) of a keyframe's depth-grid maps to the input
//! resolution, guided by the keyframe's image: each full-resolution pixel averages the 4x4
//! nearest depth-grid pixels with a spatial Gaussian (depth-grid pixels) times a range Gaussian
//! on the difference between its intensity and the block mean of the neighbour's cell. Depth
//! edges that coincide with image edges stay sharp; the learned upsampler of DROID-SLAM is
//! not available here.
//!
//! Where the neighbours straddle an occlusion boundary, their weighted mean is a depth between
//! the two surfaces that belongs to neither (a "flying pixel"). With a surface gap set, the
//! neighbours' inverse depths are sorted and only the run of values around their weighted
//! median with no step larger than the gap is averaged: the pixel takes the depth of the
//! surface most of the weight is on. Neighbours that lie on one smooth surface have no such
//! step, and the result is the plain weighted mean.

use duv_core::PlaneF32;
use rayon::prelude::*;

/// Weights of the joint bilateral upsampling (from `TrackerConfig`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct UpsampleParams {
    /// Spatial sigma, depth-grid pixels.
    pub sigma_px: f32,
    /// Range sigma, intensity in [0, 1].
    pub sigma_intensity: f32,
    /// Weight of the neighbours' spread added to the upsampled variance.
    pub spread_gain: f32,
    /// Largest step between sorted neighbour values, relative to their weighted median, that
    /// still counts as one surface; 0 averages every neighbour.
    pub surface_gap: f32,
}

/// Neighbours one output pixel mixes (4x4 depth-grid pixels).
const NEIGHBOURS: usize = 16;

/// The 4x4 depth-grid neighbours that a run of output pixels shares (every output pixel of a
/// cell row and column mixes the same ones), sorted by value once for all of them.
struct Neighbourhood {
    /// First and last neighbour column; `usize::MAX` before the first load.
    columns: (usize, usize),
    count: usize,
    /// Values in the order the weights are enumerated (rows of columns).
    values: [f32; NEIGHBOURS],
    /// Enumeration indices sorted by value.
    order: [u8; NEIGHBOURS],
    /// Whether some step between sorted values exceeds `gap` times the smallest value, the
    /// least the per-pixel threshold (`gap` times the weighted median) can be; without one,
    /// every pixel of the run takes the plain weighted mean.
    has_step: bool,
}

impl Neighbourhood {
    const EMPTY: Neighbourhood = Neighbourhood { columns: (usize::MAX, usize::MAX), count: 0, values: [0.0; NEIGHBOURS], order: [0; NEIGHBOURS], has_step: false };

    fn load(&mut self, low: &PlaneF32, (x0, x1): (usize, usize), (y0, y1): (usize, usize), gap: f32) {
        self.columns = (x0, x1);
        self.count = 0;
        for qy in y0..=y1 {
            for qx in x0..=x1 {
                self.values[self.count] = low.data[qy * low.width + qx];
                self.count += 1;
            }
        }
        let (lo, hi) = self.values[..self.count].iter().fold((f32::MAX, f32::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
        // Every step is at most the range.
        self.has_step = gap > 0.0 && self.count > 1 && hi - lo > gap * lo.abs();
        if !self.has_step {
            return;
        }
        // Insertion sort of at most 16 indices by value.
        for i in 0..self.count {
            self.order[i] = i as u8;
            let mut j = i;
            while j > 0 && self.values[self.order[j - 1] as usize] > self.values[self.order[j] as usize] {
                self.order.swap(j - 1, j);
                j -= 1;
            }
        }
        let sorted = |k: usize| self.values[self.order[k] as usize];
        self.has_step = (1..self.count).any(|k| sorted(k) - sorted(k - 1) > gap * lo.abs());
    }

    /// Value of one output pixel with neighbour weights `weights` (enumeration order, total
    /// `wsum`, weighted mean `mean`): the weighted mean when no step between the sorted values
    /// exceeds `gap` times their weighted median, otherwise the weighted mean of the run of
    /// values around the weighted median that has no such step.
    fn surface_value(&self, weights: &[f32; NEIGHBOURS], wsum: f32, mean: f32, gap: f32) -> f32 {
        if !self.has_step || wsum <= 0.0 {
            return mean;
        }
        let n = self.count;
        let value = |k: usize| self.values[self.order[k] as usize];
        let weight = |k: usize| weights[self.order[k] as usize];
        let mut acc = 0.0;
        let mut mid = n - 1;
        for k in 0..n {
            acc += weight(k);
            if acc >= 0.5 * wsum {
                mid = k;
                break;
            }
        }
        let step = gap * value(mid).abs();
        let mut first = mid;
        while first > 0 && value(first) - value(first - 1) <= step {
            first -= 1;
        }
        let mut last = mid;
        while last + 1 < n && value(last + 1) - value(last) <= step {
            last += 1;
        }
        if first == 0 && last + 1 == n {
            return mean;
        }
        let (ws, vs) = (first..=last).fold((0.0f32, 0.0f32), |(ws, vs), k| (ws + weight(k), vs + weight(k) * value(k)));
        if ws > 0.0 {
            vs / ws
        } else {
            mean
        }
    }
}

/// Upsamples `low` (one plane, and optionally a second with the same weights) at `cell` input
/// pixels per low pixel into `out` / `out2` (full size), with `guide` (full-resolution 8-bit
/// grey) and `guide_low` (block means at the low grid, [0, 1]). The first plane keeps to one
/// surface where its neighbours straddle a depth step (`surface_gap`). When the second plane is
/// the first's variance, it is the weighted mean over every neighbour plus `spread_gain` times
/// the weighted spread of the first plane's neighbours (interpolation uncertainty: at a depth
/// step, the uncertainty of which surface the pixel is on). Allocation-free.
pub(crate) fn joint_bilateral(
    guide: &[u8],
    guide_low: &PlaneF32,
    cell: usize,
    params: &UpsampleParams,
    low: &PlaneF32,
    out: &mut PlaneF32,
    second: Option<(&PlaneF32, &mut PlaneF32)>,
) {
    let (lw, lh) = (guide_low.width, guide_low.height);
    let w = out.width;
    let inv_s = -0.5 / (params.sigma_px * params.sigma_px);
    let inv_r = -0.5 / (params.sigma_intensity * params.sigma_intensity);
    let (spread_gain, surface_gap) = (params.spread_gain, params.surface_gap);
    let c = cell as f32;
    let off = 0.5 * (c - 1.0);
    let row = |y: usize, row1: &mut [f32], mut row2: Option<&mut [f32]>, low2: Option<&PlaneF32>| {
        let ly = (y as f32 - off) / c;
        let y0 = (ly.floor() as isize - 1).clamp(0, lh as isize - 1) as usize;
        let y1 = (ly.floor() as isize + 2).clamp(0, lh as isize - 1) as usize;
        let mut hood = Neighbourhood::EMPTY;
        for x in 0..w {
            let lx = (x as f32 - off) / c;
            let x0 = (lx.floor() as isize - 1).clamp(0, lw as isize - 1) as usize;
            let x1 = (lx.floor() as isize + 2).clamp(0, lw as isize - 1) as usize;
            let g = guide[y * w + x] as f32 / 255.0;
            if hood.columns != (x0, x1) {
                hood.load(low, (x0, x1), (y0, y1), surface_gap);
            }
            let (mut wsum, mut a1, mut s1, mut a2) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
            let mut weights = [0.0f32; NEIGHBOURS];
            let mut count = 0;
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
                    weights[count] = wgt;
                    count += 1;
                    if let Some(l2) = low2 {
                        a2 += wgt * l2.data[q];
                    }
                }
            }
            let inv = if wsum > 0.0 { 1.0 / wsum } else { 0.0 };
            let mean = a1 * inv;
            row1[x] = hood.surface_value(&weights, wsum, mean, surface_gap);
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

/// Standard deviation of the 8-bit quantisation of an intensity in [0, 1]: `1 / (255 sqrt 12)`.
const QUANTISATION_STD: f32 = 1.0 / (255.0 * 3.464_101_6);

/// Grey-level variance (intensity in [0, 1]) of the guide pixels in depth-grid cell
/// `(cx, cy)` of a `grid_w` x `grid_h` grid, plus the 8-bit quantisation variance; the last
/// row and column of cells take the image rows and columns the grid does not cover.
fn cell_texture(guide: &[u8], w: usize, h: usize, cell: usize, grid: (usize, usize), cx: usize, cy: usize) -> f32 {
    let (x0, y0) = (cx * cell, cy * cell);
    let x1 = if cx + 1 == grid.0 { w } else { x0 + cell };
    let y1 = if cy + 1 == grid.1 { h } else { y0 + cell };
    let (mut s, mut s2) = (0u64, 0u64);
    for y in y0..y1 {
        for &g in &guide[y * w + x0..y * w + x1] {
            s += g as u64;
            s2 += (g as u64) * (g as u64);
        }
    }
    let n = ((x1 - x0) * (y1 - y0)).max(1) as f64;
    let mean = s as f64 / n;
    let var = (s2 as f64 / n - mean * mean).max(0.0) / (255.0 * 255.0);
    var as f32 + QUANTISATION_STD * QUANTISATION_STD
}

/// Texture term of a full-resolution inverse-depth variance: each depth-grid cell's variance is
/// multiplied by `g / t`, `t` the grey-level variance of the guide image inside the cell (plus
/// the 8-bit quantisation variance) and `g` the geometric mean of `t` over the keyframe, so the
/// keyframe's log-mean variance stays as it was. Eq. 4 is the information the pooled flow
/// weights carry per cell, and they are blind to how much of the cell is texture: a flat cell's
/// depth is interpolated from its neighbours, not measured, and its error is larger than the
/// Hessian says (hazy, far seabed in turbid water most of all). Saturated values (`f32::MAX`,
/// no information) stay saturated. `grid` is the depth grid's `(width, height)`.
pub(crate) fn texture_variance(variance: &mut PlaneF32, guide: &[u8], cell: usize, grid: (usize, usize)) {
    let (w, h) = (variance.width, variance.height);
    let (gw, gh) = grid;
    if gw == 0 || gh == 0 || cell == 0 || guide.len() != w * h || gw * cell > w || gh * cell > h {
        return;
    }
    let log_sum: f64 = (0..gh).into_par_iter().map(|cy| (0..gw).map(|cx| (cell_texture(guide, w, h, cell, grid, cx, cy) as f64).ln()).sum::<f64>()).sum();
    let g = (log_sum / (gw * gh) as f64).exp() as f32;
    // Bands of `cell` rows; the rows past the grid's last row of cells belong to it.
    variance.data.par_chunks_mut(w * cell).enumerate().for_each(|(band, rows)| {
        let cy = band.min(gh - 1);
        for cx in 0..gw {
            let f = g / cell_texture(guide, w, h, cell, grid, cx, cy);
            let x1 = if cx + 1 == gw { w } else { (cx + 1) * cell };
            for row in rows.chunks_mut(w) {
                for v in &mut row[cx * cell..x1] {
                    if *v < f32::MAX {
                        *v = (*v * f).min(f32::MAX);
                    }
                }
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_variance_raises_flat_cells_lowers_textured_ones_and_keeps_the_log_mean() {
        // 4x3 cells of 8 px: the left half of the cells textured (a checker of 0/200), the
        // right half flat grey.
        let (w, h, cell) = (32, 24, 8);
        let guide: Vec<u8> = (0..w * h).map(|i| if (i % w) < w / 2 { if (i % w + i / w) % 2 == 0 { 0 } else { 200 } } else { 90 }).collect();
        let mut v = PlaneF32::new(w, h);
        v.data.fill(1e-4);
        let mut saturated = v.clone();
        saturated.data[w - 1] = f32::MAX;
        texture_variance(&mut v, &guide, cell, (4, 3));
        texture_variance(&mut saturated, &guide, cell, (4, 3));
        assert_eq!(saturated.data[w - 1], f32::MAX);
        let q = QUANTISATION_STD * QUANTISATION_STD;
        let textured = (100.0f32 / 255.0).powi(2) + q;
        let g = (textured * q).sqrt();
        let (at_textured, at_flat) = (v.data[5 * w + 3], v.data[5 * w + 20]);
        assert!((at_textured / (1e-4 * g / textured) - 1.0).abs() < 1e-4, "{at_textured}");
        assert!((at_flat / (1e-4 * g / q) - 1.0).abs() < 1e-4, "{at_flat}");
        // Constant inside each cell; the log-mean over the keyframe is the one before.
        assert!(v.data[..w / 2].iter().chain(&v.data[23 * w..23 * w + w / 2]).all(|x| *x == at_textured));
        let log_mean = v.data.iter().map(|x| (*x as f64).ln()).sum::<f64>() / (w * h) as f64;
        assert!((log_mean - (1e-4f64).ln()).abs() < 1e-3, "{log_mean}");
        // Rows and columns past the grid (34x27 for a 4x3 grid of 8 px) belong to its last cells.
        let (w2, h2) = (34, 27);
        let guide2: Vec<u8> = (0..w2 * h2).map(|i| ((i % w2) * 7 + (i / w2) * 13 % 50) as u8).collect();
        let mut v2 = PlaneF32::new(w2, h2);
        v2.data.fill(1e-4);
        texture_variance(&mut v2, &guide2, cell, (4, 3));
        assert_eq!(v2.data[10 * w2 + 33], v2.data[10 * w2 + 24]);
        assert_eq!(v2.data[26 * w2 + 5], v2.data[16 * w2 + 5]);
        assert_ne!(v2.data[10 * w2 + 24], v2.data[10 * w2 + 23]);
        // A uniform image leaves the variance as it was.
        let mut u = PlaneF32::new(w, h);
        u.data.fill(3e-3);
        texture_variance(&mut u, &vec![77; w * h], cell, (4, 3));
        assert!(u.data.iter().all(|x| (*x / 3e-3 - 1.0).abs() < 1e-5));
    }

    /// A depth grid of `lw` x `lh` cells of `cell` px with inverse depth `f(cx, cy)` and
    /// variance 1e-4, a uniform guide (no intensity cue), upsampled with `gap`.
    fn upsample_uniform_guide(lw: usize, lh: usize, cell: usize, f: impl Fn(usize, usize) -> f32, gap: f32) -> (PlaneF32, PlaneF32) {
        let (w, h) = (lw * cell, lh * cell);
        let mut low = PlaneF32::new(lw, lh);
        for cy in 0..lh {
            for cx in 0..lw {
                low.data[cy * lw + cx] = f(cx, cy);
            }
        }
        let mut low_var = PlaneF32::new(lw, lh);
        low_var.data.fill(1e-4);
        let mut guide_low = PlaneF32::new(lw, lh);
        guide_low.data.fill(0.5);
        let guide = vec![128u8; w * h];
        let params = UpsampleParams { sigma_px: 0.8, sigma_intensity: 0.08, spread_gain: 1.0, surface_gap: gap };
        let (mut out, mut var) = (PlaneF32::new(w, h), PlaneF32::new(w, h));
        joint_bilateral(&guide, &guide_low, cell, &params, &low, &mut out, Some((&low_var, &mut var)));
        (out, var)
    }

    #[test]
    fn surface_gap_keeps_each_pixel_on_one_side_of_a_depth_step() {
        // Near seabed (inverse depth 0.5) left of cell column 6, a far one (0.25) from it on.
        let step = |cx: usize, _: usize| if cx < 6 { 0.5 } else { 0.25 };
        let (mixed, mixed_var) = upsample_uniform_guide(12, 8, 8, step, 0.0);
        let (kept, kept_var) = upsample_uniform_guide(12, 8, 8, step, 0.1);
        let w = 96;
        // Plain averaging blends the two surfaces over about a cell on either side of the step.
        let row = 4 * 8 * w;
        let blended = (0..w).filter(|&x| (0.26..0.49).contains(&mixed.data[row + x])).count();
        assert!(blended >= 8, "{blended} blended pixels");
        // With the gap every pixel takes one surface's depth, the nearer side of the step.
        for (i, &d) in kept.data.iter().enumerate() {
            let x = i % w;
            let expect = if (x as f32 + 0.5) < 48.0 { 0.5 } else { 0.25 };
            assert!((d - expect).abs() < 1e-6, "pixel {x}: {d}, expected {expect}");
        }
        // The variance still carries the spread of both surfaces: the step stays uncertain.
        assert_eq!(mixed_var.data, kept_var.data);
        assert!(kept_var.data[row + 47] > 1e-3, "{}", kept_var.data[row + 47]);
    }

    #[test]
    fn surface_gap_leaves_a_smooth_slope_as_plain_averaging_does() {
        // A seabed sloping away by 3 % of inverse depth per cell: no step is a gap of 0.1.
        let slope = |cx: usize, cy: usize| 0.5 * (1.0 - 0.03 * cy as f32) * (1.0 - 0.01 * cx as f32);
        let (plain, _) = upsample_uniform_guide(12, 8, 8, slope, 0.0);
        let (kept, _) = upsample_uniform_guide(12, 8, 8, slope, 0.1);
        assert_eq!(plain.data, kept.data);
        // A gap below the slope's steps splits it into runs, and the result moves.
        let (split, _) = upsample_uniform_guide(12, 8, 8, slope, 0.001);
        assert!(plain.data.iter().zip(&split.data).any(|(a, b)| (a - b).abs() > 1e-3));
    }

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
