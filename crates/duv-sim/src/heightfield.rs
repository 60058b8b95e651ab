//! The seabed as a two-resolution heightfield and ray marching against it.
//!
//! The terrain is sampled once into a fine grid (2 cm) around the path, out to where ripples
//! stop being resolvable, and a coarse grid (8 cm, without ripples and small rocks) out to the
//! max range. Rays march it block by block: 0.64 m blocks know their maximum height and a
//! bound on the slope of the bilinear surface. Blocks the ray passes above are skipped; inside
//! a block the step is the larger of the Lipschitz-safe `clearance / (slope |d_xy| - d_z)` and
//! the drop to the block's top, over-relaxed when both ends' safe zones overlap, and at least
//! a fraction of a cell; a sign change is refined by regula falsi.

use super::noise::lerp;
use super::terrain::Terrain;
use nalgebra::Vector3;
use rayon::prelude::*;

type V3 = Vector3<f64>;

/// Ray marching takes steps up to this multiple of the Lipschitz-safe step when it can prove
/// nothing was skipped.
const OVER_RELAX: f64 = 2.0;
/// Hits are refined until the ray is this close to the seabed vertically, metres.
const REFINE_TOLERANCE_M: f64 = 2e-6;
/// Smallest ray-marching step, in cells (features thinner than this along a ray may be
/// grazed through).
const MIN_STEP_CELLS: f64 = 0.75;
/// Fine heightfield cell, metres.
pub const FINE_CELL_M: f64 = 0.02;
/// Coarse heightfield cell, metres (the terrain's coarse detail is cut at it).
pub use super::terrain::COARSE_CELL_M;
/// Acceleration block, metres (a whole number of fine and of coarse cells).
pub const BLOCK_M: f64 = 0.64;
const FINE_PER_BLOCK: usize = 32;
/// The smooth base of the fine grid is evaluated every this many cells and interpolated.
const BASE_STRIDE: usize = 4;
const COARSE_PER_BLOCK: usize = 8;

/// One regular grid of heights (f32, metres) and rockiness (u8, 0..255).
#[derive(Clone, Debug)]
struct Grid {
    x0: f64,
    y0: f64,
    cell: f64,
    inv_cell: f64,
    nx: usize,
    ny: usize,
    /// Largest fractional node coordinates that stay inside the last cell.
    max_fx: f64,
    max_fy: f64,
    h: Vec<f32>,
    rock: Vec<u8>,
}

impl Grid {
    /// Samples the terrain on `nx x ny` nodes from `(x0, y0)`. The smooth base (dunes and
    /// mounds, wavelengths of a metre and more) is evaluated every `BASE_STRIDE` nodes of the
    /// fine grid and interpolated (Catmull-Rom, error far below a millimetre); rocks, ripples
    /// and roughness are evaluated at every node.
    fn build(terrain: &Terrain, x0: f64, y0: f64, cell: f64, nx: usize, ny: usize, fine: bool) -> Grid {
        let stride = if fine { BASE_STRIDE } else { 1 };
        // Base lattice with one node before and two after the grid in each direction.
        let (bnx, bny) = ((nx - 1) / stride + 4, (ny - 1) / stride + 4);
        let base_cell = cell * stride as f64;
        let mut base = vec![0f64; bnx * bny];
        base.par_chunks_mut(bnx).enumerate().for_each(|(b, row)| {
            let y = y0 + (b as f64 - 1.0) * base_cell;
            for (a, v) in row.iter_mut().enumerate() {
                *v = terrain.base(x0 + (a as f64 - 1.0) * base_cell, y);
            }
        });
        let weights: Vec<[f64; 4]> = (0..stride)
            .map(|k| {
                let f = k as f64 / stride as f64;
                let (f2, f3) = (f * f, f * f * f);
                [0.5 * (-f3 + 2.0 * f2 - f), 0.5 * (3.0 * f3 - 5.0 * f2 + 2.0), 0.5 * (-3.0 * f3 + 4.0 * f2 + f), 0.5 * (f3 - f2)]
            })
            .collect();
        let mut h = vec![0f32; nx * ny];
        let mut rock = vec![0u8; nx * ny];
        h.par_chunks_mut(nx).zip(rock.par_chunks_mut(nx)).enumerate().for_each(|(j, (hr, rr))| {
            let y = y0 + j as f64 * cell;
            let (bj, wy) = (j / stride + 1, &weights[j % stride]);
            // The base interpolated along y once per lattice column of this row.
            let column: Vec<f64> = (0..bnx).map(|a| (0..4).map(|k| wy[k] * base[(bj + k - 1) * bnx + a]).sum()).collect();
            for i in 0..nx {
                let (bi, wx) = (i / stride + 1, &weights[i % stride]);
                let b = wx[0] * column[bi - 1] + wx[1] * column[bi] + wx[2] * column[bi + 1] + wx[3] * column[bi + 2];
                let (detail, rockiness) = terrain.detail(x0 + i as f64 * cell, y, fine);
                hr[i] = (b + detail) as f32;
                rr[i] = (rockiness * 255.0).round() as u8;
            }
        });
        Grid { x0, y0, cell, inv_cell: 1.0 / cell, nx, ny, max_fx: (nx - 1) as f64 * (1.0 - 1e-12), max_fy: (ny - 1) as f64 * (1.0 - 1e-12), h, rock }
    }

    #[inline(always)]
    fn locate(&self, x: f64, y: f64) -> (usize, f64, f64) {
        // Clamped to the grid (the edge cell extends outwards), then in-range casts.
        let fx = ((x - self.x0) * self.inv_cell).max(0.0).min(self.max_fx);
        let fy = ((y - self.y0) * self.inv_cell).max(0.0).min(self.max_fy);
        let (ix, iy) = (fx as usize, fy as usize);
        (iy * self.nx + ix, fx - ix as f64, fy - iy as f64)
    }

    #[inline(always)]
    fn sample(&self, x: f64, y: f64) -> f64 {
        let (k, ax, ay) = self.locate(x, y);
        let top = &self.h[k..k + 2];
        let bottom = &self.h[k + self.nx..k + self.nx + 2];
        let t = top[0] as f64 + (top[1] as f64 - top[0] as f64) * ax;
        let b = bottom[0] as f64 + (bottom[1] as f64 - bottom[0] as f64) * ax;
        t + (b - t) * ay
    }

    fn sample_rock(&self, x: f64, y: f64) -> f64 {
        let (k, ax, ay) = self.locate(x, y);
        let r = |i: usize| self.rock[i] as f64 * (1.0 / 255.0);
        lerp(lerp(r(k), r(k + 1), ax), lerp(r(k + self.nx), r(k + self.nx + 1), ax), ay)
    }

    /// Maximum height and gradient-norm bound of the bilinear surface over cells
    /// `[i0, i0 + n) x [j0, j0 + n)`.
    fn block_bounds(&self, i0: usize, j0: usize, n: usize) -> (f64, f64) {
        let mut hmax = f64::NEG_INFINITY;
        let mut slope: f64 = 0.0;
        for j in j0..j0 + n {
            for i in i0..i0 + n {
                let k = j * self.nx + i;
                let (a, b, c, d) = (self.h[k] as f64, self.h[k + 1] as f64, self.h[k + self.nx] as f64, self.h[k + self.nx + 1] as f64);
                hmax = hmax.max(a.max(b).max(c).max(d));
                let gx = (b - a).abs().max((d - c).abs()) * self.inv_cell;
                let gy = (c - a).abs().max((d - b).abs()) * self.inv_cell;
                slope = slope.max((gx * gx + gy * gy).sqrt());
            }
        }
        (hmax, slope)
    }
}

#[derive(Clone, Copy, Debug)]
struct Block {
    hmax: f32,
    slope: f32,
    step_min: f32,
}

/// The seabed as a two-resolution heightfield with per-block bounds for ray marching.
#[derive(Clone, Debug)]
pub struct Heightfield {
    fine: Grid,
    coarse: Grid,
    /// `x0, y0, x1, y1` of the fine grid.
    fine_rect: [f64; 4],
    bx0: f64,
    by0: f64,
    nbx: usize,
    nby: usize,
    blocks: Vec<Block>,
}

impl Heightfield {
    /// Blocks along x and y of a rectangle of whole blocks.
    fn blocks_in(rect: [f64; 4]) -> (usize, usize) {
        (((rect[2] - rect[0]) / BLOCK_M).round() as usize, ((rect[3] - rect[1]) / BLOCK_M).round() as usize)
    }

    /// Number of grid nodes [`Heightfield::build`] allocates for these rectangles.
    pub fn cells(fine_rect: [f64; 4], outer: [f64; 4]) -> usize {
        let (fbx, fby) = Self::blocks_in(fine_rect);
        let (nbx, nby) = Self::blocks_in(outer);
        let fine = (fbx * FINE_PER_BLOCK + 1).saturating_mul(fby * FINE_PER_BLOCK + 1);
        fine.saturating_add((nbx * COARSE_PER_BLOCK + 1).saturating_mul(nby * COARSE_PER_BLOCK + 1))
    }

    /// Samples `terrain` finely over `fine_rect` and coarsely over `outer` (both on whole
    /// blocks, `fine_rect` inside `outer`) and bounds every block.
    pub(super) fn build(terrain: &Terrain, fine_rect: [f64; 4], outer: [f64; 4]) -> Heightfield {
        let (fbx, fby) = Self::blocks_in(fine_rect);
        let (nbx, nby) = Self::blocks_in(outer);
        let fbx0 = ((fine_rect[0] - outer[0]) / BLOCK_M).round() as usize;
        let fby0 = ((fine_rect[1] - outer[1]) / BLOCK_M).round() as usize;
        let fine = Grid::build(terrain, fine_rect[0], fine_rect[1], FINE_CELL_M, fbx * FINE_PER_BLOCK + 1, fby * FINE_PER_BLOCK + 1, true);
        let coarse = Grid::build(terrain, outer[0], outer[1], COARSE_CELL_M, nbx * COARSE_PER_BLOCK + 1, nby * COARSE_PER_BLOCK + 1, false);
        let blocks: Vec<Block> = (0..nbx * nby)
            .into_par_iter()
            .map(|k| {
                let (bx, by) = (k % nbx, k / nbx);
                let is_fine = bx >= fbx0 && bx < fbx0 + fbx && by >= fby0 && by < fby0 + fby;
                // Slack: f32 rounding inside the fine grid; on coarse blocks also the fine
                // relief (ripples, pebbles) that a ray may meet exactly on a shared edge.
                let (hmax, slope, cell) = if is_fine {
                    let (h, s) = fine.block_bounds((bx - fbx0) * FINE_PER_BLOCK, (by - fby0) * FINE_PER_BLOCK, FINE_PER_BLOCK);
                    (h + 0.001, s, FINE_CELL_M)
                } else {
                    let (h, s) = coarse.block_bounds(bx * COARSE_PER_BLOCK, by * COARSE_PER_BLOCK, COARSE_PER_BLOCK);
                    (h + 0.08, s, COARSE_CELL_M)
                };
                Block { hmax: hmax as f32, slope: (slope * 1.05 + 0.02) as f32, step_min: (MIN_STEP_CELLS * cell) as f32 }
            })
            .collect();
        Heightfield { fine, coarse, fine_rect, bx0: outer[0], by0: outer[1], nbx, nby, blocks }
    }

    /// Seabed height at `(x, y)`: the fine grid where it exists, else the coarse one.
    #[inline(always)]
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let r = &self.fine_rect;
        if x >= r[0] && x <= r[2] && y >= r[1] && y <= r[3] {
            self.fine.sample(x, y)
        } else {
            self.coarse.sample(x, y)
        }
    }

    pub(super) fn rockiness(&self, x: f64, y: f64) -> f64 {
        let r = &self.fine_rect;
        if x >= r[0] && x <= r[2] && y >= r[1] && y <= r[3] {
            self.fine.sample_rock(x, y)
        } else {
            self.coarse.sample_rock(x, y)
        }
    }

    fn cell_at(&self, x: f64, y: f64) -> f64 {
        let r = &self.fine_rect;
        if x >= r[0] && x <= r[2] && y >= r[1] && y <= r[3] {
            FINE_CELL_M
        } else {
            COARSE_CELL_M
        }
    }

    /// Upward unit normal at a point on the seabed, from differences over `baseline_m` (at
    /// least a cell): a central difference is the mean slope between its samples, so a
    /// baseline of a pixel footprint low-passes relief the pixel cannot resolve (no ripple
    /// moire at grazing angles).
    pub fn normal_filtered(&self, p: &V3, baseline_m: f64) -> V3 {
        let cell = self.cell_at(p.x, p.y);
        let e = baseline_m.clamp(cell, 0.5);
        if e <= cell {
            // Forward differences: two samples instead of four.
            let gx = (self.height(p.x + e, p.y) - p.z) / e;
            let gy = (self.height(p.x, p.y + e) - p.z) / e;
            return V3::new(-gx, -gy, 1.0).normalize();
        }
        let gx = (self.height(p.x + e, p.y) - self.height(p.x - e, p.y)) / (2.0 * e);
        let gy = (self.height(p.x, p.y + e) - self.height(p.x, p.y - e)) / (2.0 * e);
        V3::new(-gx, -gy, 1.0).normalize()
    }

    /// `(x0, y0, x1, y1)` covered by the coarse grid (the whole seabed).
    pub fn extent(&self) -> [f64; 4] {
        [self.coarse.x0, self.coarse.y0, self.coarse.x0 + (self.coarse.nx - 1) as f64 * self.coarse.cell, self.coarse.y0 + (self.coarse.ny - 1) as f64 * self.coarse.cell]
    }

    /// `(x0, y0, x1, y1)` covered by the fine grid.
    pub fn fine_extent(&self) -> [f64; 4] {
        self.fine_rect
    }

    /// Height of the ray point at `t` above the seabed.
    #[inline(always)]
    fn clearance(&self, o: &V3, d: &V3, t: f64) -> f64 {
        o.z + d.z * t - self.height(o.x + d.x * t, o.y + d.y * t)
    }

    /// Root of the clearance between a point above (`fa > 0`) and one on or below (`fb <= 0`)
    /// the surface: regula falsi with the Illinois modification (a bracketing method, so it
    /// cannot leave the interval; converges superlinearly on the smooth bilinear surface).
    fn refine(&self, o: &V3, d: &V3, mut ta: f64, mut fa: f64, mut tb: f64, mut fb: f64) -> f64 {
        let mut side = 0i8;
        for _ in 0..40 {
            let tm = (ta * fb - tb * fa) / (fb - fa);
            let fm = self.clearance(o, d, tm);
            if fm.abs() < REFINE_TOLERANCE_M || tb - ta < REFINE_TOLERANCE_M {
                return tm;
            }
            if fm > 0.0 {
                ta = tm;
                fa = fm;
                if side == 1 {
                    fb *= 0.5;
                }
                side = 1;
            } else {
                tb = tm;
                fb = fm;
                if side == -1 {
                    fa *= 0.5;
                }
                side = -1;
            }
        }
        ta + (tb - ta) * fa / (fa - fb)
    }

    /// Distance along the unit ray `o + t d` to the seabed, if it is hit before `t_max`.
    pub fn march(&self, o: &V3, d: &V3, t_max: f64) -> Option<f64> {
        let gx = (o.x - self.bx0) / BLOCK_M;
        let gy = (o.y - self.by0) / BLOCK_M;
        if !(gx >= 0.0 && gy >= 0.0 && gx < self.nbx as f64 && gy < self.nby as f64) {
            return None;
        }
        let (mut bx, mut by) = (gx as i64, gy as i64);
        let axis = |o: f64, d: f64, origin: f64, cell: i64| -> (i64, f64, f64) {
            if d > 1e-15 {
                (1, BLOCK_M / d, (origin + (cell + 1) as f64 * BLOCK_M - o) / d)
            } else if d < -1e-15 {
                (-1, -BLOCK_M / d, (origin + cell as f64 * BLOCK_M - o) / d)
            } else {
                (0, f64::INFINITY, f64::INFINITY)
            }
        };
        let (sx, tdx, mut tnx) = axis(o.x, d.x, self.bx0, bx);
        let (sy, tdy, mut tny) = axis(o.y, d.y, self.by0, by);
        let dxy = (d.x * d.x + d.y * d.y).sqrt();
        let mut t0 = 0.0;
        let mut prev: Option<(f64, f64)> = None;
        loop {
            let t1 = tnx.min(tny).min(t_max);
            let b = self.blocks[by as usize * self.nbx + bx as usize];
            let (z0, z1) = (o.z + d.z * t0, o.z + d.z * t1);
            if z0.min(z1) > b.hmax as f64 {
                prev = None;
            } else {
                // Clearance can shrink at most `denom` per metre forwards and `denom_back`
                // per metre backwards along the ray.
                let denom = b.slope as f64 * dxy - d.z;
                let denom_back = b.slope as f64 * dxy + d.z;
                let step_min = b.step_min as f64;
                let (mut t, mut f) = match prev {
                    Some(p) => p,
                    None => (t0, self.clearance(o, d, t0)),
                };
                if f <= 0.0 {
                    return Some(t);
                }
                // A point known to be under the seabed (from a rejected long step), if any.
                let mut below: Option<(f64, f64)> = None;
                while t < t1 {
                    // Safe: by the slope bound, or (descending) down to the block's top.
                    let mut safe = if denom > 1e-12 { f / denom } else { f64::INFINITY };
                    if d.z < 0.0 {
                        safe = safe.max((o.z + d.z * t - b.hmax as f64) / -d.z);
                    }
                    if safe > 2.0 * step_min && below.is_none() {
                        // Over-relaxed step: accepted when the safe zones around both ends
                        // overlap, so nothing can rise above the ray in between.
                        let tn = (t + OVER_RELAX * safe).min(t1);
                        let fnext = self.clearance(o, d, tn);
                        if fnext > 0.0 {
                            let back = if denom_back > 1e-12 { fnext / denom_back } else { f64::INFINITY };
                            if tn - back <= t + safe {
                                t = tn;
                                f = fnext;
                                continue;
                            }
                        } else {
                            below = Some((tn, fnext));
                        }
                    }
                    let step = safe.max(step_min);
                    let tn = (t + step).min(t1);
                    let (tn, fnext) = match below {
                        Some((tb, fb)) if tb <= tn => (tb, fb),
                        _ => (tn, self.clearance(o, d, tn)),
                    };
                    if fnext <= 0.0 {
                        return Some(self.refine(o, d, t, f, tn, fnext));
                    }
                    t = tn;
                    f = fnext;
                }
                prev = Some((t, f));
            }
            if t1 >= t_max {
                return None;
            }
            if tnx < tny {
                bx += sx;
                tnx += tdx;
                if bx < 0 || bx >= self.nbx as i64 {
                    return None;
                }
            } else {
                by += sy;
                tny += tdy;
                if by < 0 || by >= self.nby as i64 {
                    return None;
                }
            }
            t0 = t1;
        }
    }
}

