//! Multi-view consistency term of the depth variance handed to mapping.
//!
//! Eq. 4 propagates the flow noise that the BA weights describe. It cannot see a bias that the
//! flow shares over a region: haze flattening the far seabed, the small parallax around the
//! focus of expansion, smoothing across a depth step. Such errors are spatially smooth and
//! dominate the true depth error where they occur (turbid water most of all), so Eq. 4 alone
//! ranks them poorly.
//!
//! Neighbouring keyframes measure the same surface through their own flow edges (a keyframe's
//! inverse depth is a variable only of the edges leaving it), from other distances and other
//! places in the image. Where a keyframe's depth-grid point lands in a neighbour's view, the
//! neighbour's inverse depth along that ray, converted to this keyframe's, gives a second
//! estimate; the squared difference is a sample of the squared error (plus the neighbour's).
//! [`consistency_grid`] averages these samples over the neighbours and over a small window of
//! depth-grid cells, and [`blend_consistency`] blends the mean into the full-resolution
//! variance geometrically, `var^(1 - a) * d2^a`, where every depth-grid cell the pixel
//! interpolates has a sample. Elsewhere (parts of the view no neighbour sees) the variance
//! stays as Eq. 4 and the other terms made it.

use duv_core::{PinholeCamera, PlaneF32, Se3};
use nalgebra::{Point3, Vector2};

/// Depth-grid cells within this distance of a neighbour's border give no sample: bilinear
/// sampling there reads the border cells, whose flow is the least reliable.
const SAMPLE_MARGIN_CELLS: f64 = 1.0;

/// Workspace of the consistency term at the depth grid (allocated once, at the grid's size).
pub(crate) struct ConsistencyScratch {
    /// Sum over neighbours of the squared inverse-depth differences, per cell, (1/m)^2.
    sum: PlaneF32,
    /// Number of neighbours that gave a sample, per cell.
    count: PlaneF32,
    /// Mean over the window of cells (NaN where no cell of the window has a sample).
    pub mean: PlaneF32,
}

impl ConsistencyScratch {
    pub(crate) fn new(grid_w: usize, grid_h: usize) -> Self {
        ConsistencyScratch { sum: PlaneF32::new(grid_w, grid_h), count: PlaneF32::new(grid_w, grid_h), mean: PlaneF32::new(grid_w, grid_h) }
    }
}

/// Mean squared inverse-depth disagreement of keyframe `world_from_k` (depth grid `inv_k`,
/// camera `grid`) with `neighbours` (pose and depth grid each, same camera), averaged over the
/// neighbours that see each cell and over the `(2 radius + 1)^2` cells around it; written into
/// `scratch.mean` in (1/m)^2, NaN where nothing in the window was seen. A cell's sample from
/// neighbour `j`: the point at the cell's inverse depth `rho`, moved into `j`, lands at depth
/// `z_j` and pixel `p`; `j`'s inverse depth `rho_j(p)` (bilinear) puts the surface at the
/// relative offset `r = rho_j(p) z_j - 1` along the ray, which is `r rho` in this keyframe's
/// inverse depth. Non-positive or non-finite depths give no sample.
pub(crate) fn consistency_grid<'a>(grid: &PinholeCamera, world_from_k: &Se3, inv_k: &PlaneF32, neighbours: impl IntoIterator<Item = (Se3, &'a PlaneF32)>, radius: usize, scratch: &mut ConsistencyScratch) {
    let (w, h) = (inv_k.width, inv_k.height);
    scratch.sum.data.fill(0.0);
    scratch.count.data.fill(0.0);
    for (world_from_j, inv_j) in neighbours {
        if inv_j.width != w || inv_j.height != h {
            continue;
        }
        let j_from_k = world_from_j.inverse() * world_from_k;
        for y in 0..h {
            for x in 0..w {
                let rho = inv_k.data[y * w + x] as f64;
                if !(rho.is_finite() && rho > 0.0) {
                    continue;
                }
                let Some(ray) = grid.unproject(&Vector2::new(x as f64, y as f64)) else { continue };
                let p_j = j_from_k * Point3::from(ray / (ray.z * rho));
                if !(p_j.z > 0.0) {
                    continue;
                }
                let Some(uv) = grid.project(&p_j.coords) else { continue };
                let m = SAMPLE_MARGIN_CELLS;
                if !(uv.x >= m && uv.x <= (w - 1) as f64 - m && uv.y >= m && uv.y <= (h - 1) as f64 - m) {
                    continue;
                }
                let Some(rho_j) = inv_j.sample_bilinear(uv.x as f32, uv.y as f32) else { continue };
                if !(rho_j.is_finite() && rho_j > 0.0) {
                    continue;
                }
                let d = (rho_j as f64 * p_j.z - 1.0) * rho;
                scratch.sum.data[y * w + x] += (d * d) as f32;
                scratch.count.data[y * w + x] += 1.0;
            }
        }
    }
    let r = radius as isize;
    for y in 0..h as isize {
        for x in 0..w as isize {
            let (mut s, mut n) = (0.0f64, 0.0f64);
            for yy in (y - r).max(0)..=(y + r).min(h as isize - 1) {
                for xx in (x - r).max(0)..=(x + r).min(w as isize - 1) {
                    let i = yy as usize * w + xx as usize;
                    s += scratch.sum.data[i] as f64;
                    n += scratch.count.data[i] as f64;
                }
            }
            scratch.mean.data[y as usize * w + x as usize] = if n > 0.0 { (s / n) as f32 } else { f32::NAN };
        }
    }
}

/// Blends the depth-grid disagreement `mean` (from [`consistency_grid`]) into the
/// full-resolution `variance` of a `cell`-pixel grid: `var^(1 - exponent) * d2^exponent`, `d2`
/// the bilinear interpolation of `mean` at the pixel (cell centres at `(i + 0.5) cell - 0.5`,
/// clamped at the grid's edge). Pixels that interpolate a cell without a sample, and saturated
/// variances (`f32::MAX`, no information), keep their variance. A zero disagreement is floored
/// at the smallest positive normal `f32` so the variance stays positive.
pub(crate) fn blend_consistency(variance: &mut PlaneF32, mean: &PlaneF32, cell: usize, exponent: f32) {
    use rayon::prelude::*;
    let (w, gw, gh) = (variance.width, mean.width, mean.height);
    if exponent <= 0.0 || gw == 0 || gh == 0 || cell == 0 {
        return;
    }
    let c = cell as f32;
    // Grid position along one axis: the lower cell, the upper one and the upper one's weight.
    let axis = |p: usize, n: usize| -> (usize, usize, f32) {
        let g = ((p as f32 + 0.5) / c - 0.5).clamp(0.0, (n - 1) as f32);
        let i0 = (g.floor() as usize).min(n - 1);
        let i1 = (i0 + 1).min(n - 1);
        (i0, i1, g - i0 as f32)
    };
    variance.data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let (y0, y1, fy) = axis(y, gh);
        for (x, v) in row.iter_mut().enumerate() {
            if *v >= f32::MAX {
                continue;
            }
            let (x0, x1, fx) = axis(x, gw);
            let mut d2 = 0.0f32;
            let mut seen = true;
            for (i, wgt) in [(y0 * gw + x0, (1.0 - fx) * (1.0 - fy)), (y0 * gw + x1, fx * (1.0 - fy)), (y1 * gw + x0, (1.0 - fx) * fy), (y1 * gw + x1, fx * fy)] {
                if wgt > 0.0 {
                    let m = mean.data[i];
                    if m.is_nan() {
                        seen = false;
                        break;
                    }
                    d2 += wgt * m;
                }
            }
            if seen {
                let d2 = d2.max(f32::MIN_POSITIVE);
                *v = (v.powf(1.0 - exponent) * d2.powf(exponent)).clamp(f32::MIN_POSITIVE, f32::MAX);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn grid_camera() -> PinholeCamera {
        PinholeCamera::new(30.0, 30.0, 19.5, 14.5, 40, 30).unwrap()
    }

    fn plane(depth_m: f32) -> PlaneF32 {
        PlaneF32::from_vec(40, 30, vec![1.0 / depth_m; 40 * 30]).unwrap()
    }

    #[test]
    fn consistency_grid_measures_a_biased_region_against_a_neighbour() {
        // A fronto-parallel seabed 3 m ahead. The keyframe puts a 6x6-cell patch 10 % too far
        // in inverse depth; the neighbour, 0.2 m further forward and 0.5 m to the right, has
        // it right.
        let cam = grid_camera();
        let mut inv_k = plane(3.0);
        for y in 12..18 {
            for x in 17..23 {
                inv_k.data[y * 40 + x] *= 0.9;
            }
        }
        let inv_j = plane(2.8);
        let world_from_j = Se3::from_parts(Translation3::new(0.5, 0.0, 0.2), UnitQuaternion::identity());
        let mut scratch = ConsistencyScratch::new(40, 30);
        consistency_grid(&cam, &Se3::identity(), &inv_k, [(world_from_j, &inv_j)], 1, &mut scratch);
        // Inside the patch: the point at 3.333 m is 3.133 m from the neighbour, whose surface
        // there is at 2.8 m: r = 3.133 / 2.8 - 1, d = r * 0.3 (1/m).
        let d = ((10.0 / 3.0 - 0.2) / 2.8 - 1.0) * 0.3;
        let inside = scratch.mean.data[14 * 40 + 19] as f64;
        assert!((inside / (d * d) - 1.0).abs() < 1e-4, "{inside} vs {}", d * d);
        // Away from the patch (more than the window's radius) the two agree.
        let outside = scratch.mean.data[5 * 40 + 30];
        assert!(outside.abs() < 1e-10, "{outside}");
        // Half-way over the patch's edge the window mixes both: 3 of its 9 cells are biased.
        let edge = scratch.mean.data[14 * 40 + 16] as f64;
        assert!((edge / (d * d / 3.0) - 1.0).abs() < 1e-3, "{edge}");
        // The left columns land left of the neighbour's view (5.4 cells shift): no sample.
        assert!(scratch.mean.data[14 * 40].is_nan() && scratch.mean.data[14 * 40 + 1].is_nan());
        // Without neighbours nothing is seen.
        consistency_grid(&cam, &Se3::identity(), &inv_k, [], 1, &mut scratch);
        assert!(scratch.mean.data.iter().all(|m| m.is_nan()));
        // A keyframe inverse depth that is not positive gives no sample.
        inv_k.data[14 * 40 + 19] = 0.0;
        consistency_grid(&cam, &Se3::identity(), &inv_k, [(world_from_j, &inv_j)], 0, &mut scratch);
        assert!(scratch.mean.data[14 * 40 + 19].is_nan());
        assert!(scratch.mean.data[14 * 40 + 20].is_finite());
    }

    #[test]
    fn consistency_grid_is_zero_for_a_consistent_rotated_pair() {
        // Both keyframes right about a tilted plane, the neighbour rotated and moved: every
        // sample agrees to rounding.
        let cam = grid_camera();
        let plane_at = |pose: &Se3| {
            // Plane n . p = 3 in the world, n tilted 0.2 rad about x.
            let n = Vector3::new(0.0, (0.2f64).sin(), (0.2f64).cos());
            let mut p = PlaneF32::new(40, 30);
            for y in 0..30 {
                for x in 0..40 {
                    let ray = cam.unproject(&Vector2::new(x as f64, y as f64)).unwrap();
                    let (n_c, o) = (pose.rotation.inverse() * n, pose.translation.vector);
                    // Depth z with n . (o + R ray z) = 3.
                    let z = (3.0 - n.dot(&o)) / n_c.dot(&ray);
                    p.data[y * 40 + x] = (1.0 / z) as f32;
                }
            }
            p
        };
        let world_from_j = Se3::from_parts(Translation3::new(0.1, -0.2, 0.3), UnitQuaternion::from_euler_angles(0.05, -0.04, 0.1));
        let (inv_k, inv_j) = (plane_at(&Se3::identity()), plane_at(&world_from_j));
        let mut scratch = ConsistencyScratch::new(40, 30);
        consistency_grid(&cam, &Se3::identity(), &inv_k, [(world_from_j, &inv_j)], 1, &mut scratch);
        let seen: Vec<f32> = scratch.mean.data.iter().copied().filter(|m| m.is_finite()).collect();
        assert!(seen.len() > 600, "{} cells seen", seen.len());
        // Bilinear sampling of a plane's inverse depth (linear in the pixel) is exact up to f32.
        assert!(seen.iter().all(|&m| m < 1e-10), "{:?}", seen.iter().copied().fold(0.0f32, f32::max));
    }

    #[test]
    fn blend_consistency_mixes_geometrically_where_every_cell_was_seen() {
        // A 4x3 grid of 4-pixel cells; cell (2, 1) unseen, one saturated pixel.
        let mut mean = PlaneF32::from_vec(4, 3, vec![1e-4; 12]).unwrap();
        mean.data[4 + 2] = f32::NAN;
        let mut var = PlaneF32::from_vec(16, 12, vec![1e-2; 16 * 12]).unwrap();
        var.data[0] = f32::MAX;
        let untouched = var.clone();
        blend_consistency(&mut var, &mean, 4, 0.0);
        assert_eq!(var, untouched);
        blend_consistency(&mut var, &mean, 4, 0.5);
        assert_eq!(var.data[0], f32::MAX);
        // Pixel (1, 1) interpolates cell (0, 0) only: sqrt(1e-2 * 1e-4).
        assert!((var.data[16 + 1] / 1e-3 - 1.0).abs() < 1e-5, "{}", var.data[17]);
        // Pixel (9, 5) sits in cell (2, 1): kept. So do pixels that interpolate it, e.g. (6, 6)
        // (between cells 1 and 2 in x, 1 and 2 in y).
        assert_eq!(var.data[5 * 16 + 9], 1e-2);
        assert_eq!(var.data[6 * 16 + 6], 1e-2);
        // Far from it, blended: (1, 10) interpolates cells (0, 1) and (0, 2), both seen.
        assert!((var.data[10 * 16 + 1] / 1e-3 - 1.0).abs() < 1e-5);
        // A disagreement of zero does not zero the variance.
        let zero = PlaneF32::from_vec(4, 3, vec![0.0; 12]).unwrap();
        let mut v = PlaneF32::from_vec(16, 12, vec![1e-2; 16 * 12]).unwrap();
        blend_consistency(&mut v, &zero, 4, 1.0);
        assert!(v.data.iter().all(|&x| x > 0.0 && x <= f32::MIN_POSITIVE * 2.0));
    }
}
