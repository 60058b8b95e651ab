//! The procedural seabed height function: a tilted plane with dunes (the C2-smooth altitude
//! reference of the vehicle), mounds, sand ripples in patches, gravel beds, scattered rocks and
//! a few boulders, all a pure function of the seed.

use super::noise::{floor_i32, gnoise, hash2, rehash, smoothstep, unit};

/// Coarse heightfield cell, metres: the heightfield's coarse grid ([`super::heightfield`]) and
/// the size below which its rocks leave their detail out.
pub const COARSE_CELL_M: f64 = 0.08;

/// Sand ripple wavelength and amplitude, metres.
const RIPPLE_LAMBDA_M: f64 = 0.12;
const RIPPLE_AMPLITUDE_M: f64 = 0.014;

/// A keep-out zone for rocks and boulders: a segment in the plane with a radius.
#[derive(Clone, Copy, Debug)]
pub(super) struct KeepOut {
    pub(super) a: (f64, f64),
    pub(super) b: (f64, f64),
    pub(super) radius: f64,
}

impl KeepOut {
    fn distance(&self, x: f64, y: f64) -> f64 {
        let (ax, ay) = self.a;
        let (bx, by) = (self.b.0 - ax, self.b.1 - ay);
        let l2 = bx * bx + by * by;
        let s = if l2 > 0.0 { (((x - ax) * bx + (y - ay) * by) / l2).clamp(0.0, 1.0) } else { 0.0 };
        ((x - ax - s * bx).powi(2) + (y - ay - s * by).powi(2)).sqrt() - self.radius
    }
}

/// One rock or boulder: an irregular elliptic dome.
#[derive(Clone, Copy, Debug)]
struct Rock {
    x: f64,
    y: f64,
    cos_a: f64,
    sin_a: f64,
    radius: f64,
    inv_radius: f64,
    inv_minor: f64,
    height: f64,
    exponent: f64,
    outline_offset: f64,
    boulder: bool,
}

/// One population of rocks scattered on a jittered grid.
struct RockLayer {
    /// Grid cell, metres; at most one rock per cell.
    cell: f64,
    /// Probability that a cell holds a rock.
    density: f64,
    /// Radius range, metres (small radii are more common).
    radius: (f64, f64),
    /// Height over radius range, and a cap in metres.
    height_ratio: (f64, f64),
    height_cap: f64,
    /// Profile `(1 - q^2)^exponent`: smaller is steeper-sided.
    exponent: f64,
    /// Boulders get lumps and stay in the coarse grid.
    boulder: bool,
    /// Density modulated by a patch field (gravel beds).
    patchy: bool,
}

const ROCK_LAYERS: [RockLayer; 3] = [
    RockLayer { cell: 0.22, density: 0.6, radius: (0.03, 0.07), height_ratio: (0.5, 0.8), height_cap: 0.05, exponent: 0.6, boulder: false, patchy: true },
    RockLayer { cell: 0.9, density: 0.4, radius: (0.06, 0.3), height_ratio: (0.45, 0.8), height_cap: 0.25, exponent: 0.65, boulder: false, patchy: false },
    RockLayer { cell: 4.5, density: 0.5, radius: (0.5, 1.2), height_ratio: (0.45, 0.75), height_cap: 0.6, exponent: 0.5, boulder: true, patchy: false },
];
/// Rocks reach at most this many radii from their centre (outline noise included).
const ROCK_REACH: f64 = 1.3;
/// Side of the bins rocks are sorted into, metres.
const ROCK_BIN_M: f64 = 0.5;

/// The rocks and boulders of the scene, binned for lookup.
#[derive(Clone, Debug, Default)]
pub(super) struct RockField {
    rocks: Vec<Rock>,
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    /// CSR: rocks of bin `k` are `items[offsets[k]..offsets[k + 1]]`.
    offsets: Vec<u32>,
    items: Vec<u32>,
    outline_seed: u32,
    lump_seed: u32,
}

impl RockField {
    /// Scatters rocks on jittered grids over `extent` (x0, y0, x1, y1), away from `keep_out`.
    pub(super) fn new(seeds: &[u32; 12], extent: [f64; 4], keep_out: &[KeepOut]) -> RockField {
        let mut rocks = Vec::new();
        for (layer, l) in ROCK_LAYERS.iter().enumerate() {
            let seed = seeds[8 + layer];
            let cell = l.cell;
            let (r_lo, r_hi) = l.radius;
            let pad = ROCK_REACH * r_hi;
            let (cx0, cy0) = (floor_i32((extent[0] - pad) / cell) - 1, floor_i32((extent[1] - pad) / cell) - 1);
            let (cx1, cy1) = (floor_i32((extent[2] + pad) / cell) + 1, floor_i32((extent[3] + pad) / cell) + 1);
            for cy in cy0..=cy1 {
                for cx in cx0..=cx1 {
                    let h = hash2(cx, cy, seed);
                    let density = if l.patchy {
                        l.density * smoothstep(0.0, 0.45, gnoise(cx as f64 * cell / 3.5, cy as f64 * cell / 3.5, seeds[11]))
                    } else {
                        l.density
                    };
                    if unit(h) >= density {
                        continue;
                    }
                    let u = |k: u32| unit(rehash(h, k));
                    let radius = r_lo + (r_hi - r_lo) * u(1) * u(1);
                    let (x, y) = ((cx as f64 + u(2)) * cell, (cy as f64 + u(3)) * cell);
                    if keep_out.iter().any(|k| k.distance(x, y) < radius) {
                        continue;
                    }
                    let (sin_a, cos_a) = (u(4) * std::f64::consts::PI).sin_cos();
                    let aspect = 0.6 + 0.4 * u(5);
                    rocks.push(Rock {
                        x,
                        y,
                        cos_a,
                        sin_a,
                        radius,
                        inv_radius: 1.0 / radius,
                        inv_minor: 1.0 / (radius * aspect),
                        height: (radius * (l.height_ratio.0 + (l.height_ratio.1 - l.height_ratio.0) * u(7))).min(l.height_cap),
                        exponent: l.exponent,
                        outline_offset: u(6) * 50.0,
                        boulder: l.boulder,
                    });
                }
            }
        }
        let nx = ((extent[2] - extent[0]) / ROCK_BIN_M).ceil().max(1.0) as usize;
        let ny = ((extent[3] - extent[1]) / ROCK_BIN_M).ceil().max(1.0) as usize;
        let bin_range = |lo: f64, origin: f64, n: usize| (((lo - origin) / ROCK_BIN_M).floor().max(0.0) as usize).min(n - 1);
        let mut per_bin: Vec<Vec<u32>> = vec![Vec::new(); nx * ny];
        for (k, r) in rocks.iter().enumerate() {
            let reach = ROCK_REACH * r.radius;
            let (bx0, bx1) = (bin_range(r.x - reach, extent[0], nx), bin_range(r.x + reach, extent[0], nx));
            let (by0, by1) = (bin_range(r.y - reach, extent[1], ny), bin_range(r.y + reach, extent[1], ny));
            for by in by0..=by1 {
                for bx in bx0..=bx1 {
                    per_bin[by * nx + bx].push(k as u32);
                }
            }
        }
        let mut offsets = Vec::with_capacity(nx * ny + 1);
        let mut items = Vec::new();
        offsets.push(0);
        for bin in per_bin {
            items.extend_from_slice(&bin);
            offsets.push(items.len() as u32);
        }
        RockField { rocks, x0: extent[0], y0: extent[1], nx, ny, offsets, items, outline_seed: seeds[8] ^ 0x51, lump_seed: seeds[10] ^ 0x77 }
    }

    /// Height of the highest rock at `(x, y)` (0 where there is none). Without `fine`, rocks
    /// under `min_radius` and the boulders' small lumps are left out.
    fn height(&self, x: f64, y: f64, fine: bool, min_radius: f64) -> f64 {
        let bx = (((x - self.x0) / ROCK_BIN_M) as isize).clamp(0, self.nx as isize - 1) as usize;
        let by = (((y - self.y0) / ROCK_BIN_M) as isize).clamp(0, self.ny as isize - 1) as usize;
        let k = by * self.nx + bx;
        let mut best: f64 = 0.0;
        for &i in &self.items[self.offsets[k] as usize..self.offsets[k + 1] as usize] {
            let r = &self.rocks[i as usize];
            if r.radius < min_radius {
                continue;
            }
            let (dx, dy) = (x - r.x, y - r.y);
            let reach = ROCK_REACH * r.radius;
            if dx.abs() > reach || dy.abs() > reach {
                continue;
            }
            let (lx, ly) = ((r.cos_a * dx + r.sin_a * dy) * r.inv_radius, (-r.sin_a * dx + r.cos_a * dy) * r.inv_minor);
            let mut q2 = lx * lx + ly * ly;
            if q2 > 1.69 {
                continue;
            }
            // Irregular outline: the radius wobbles with direction and position.
            q2 *= 1.0 + 0.35 * gnoise(lx * 1.7 + r.outline_offset, ly * 1.7, self.outline_seed);
            if q2 >= 1.0 {
                continue;
            }
            let mut bump = r.height * (1.0 - q2).powf(r.exponent);
            if r.boulder && fine {
                bump *= 1.0 + 0.12 * gnoise(x / 0.22, y / 0.22, self.lump_seed) + 0.05 * gnoise(x / 0.07, y / 0.07, self.lump_seed ^ 1);
            }
            best = best.max(bump);
        }
        best
    }
}

/// The procedural seabed height function (sampled into the grids once).
#[derive(Clone, Debug)]
pub(super) struct Terrain {
    pub(super) seeds: [u32; 12],
    tilt: (f64, f64),
    ripple_dir: (f64, f64),
    pub(super) rocks: RockField,
}

impl Terrain {
    pub(super) fn new(seed: u64) -> Self {
        let mut rng = duv_core::rng::Rng::derive(seed, 0x005E_ABED);
        let mut seeds = [0u32; 12];
        for s in &mut seeds {
            *s = (rng.next_u64() >> 32) as u32;
        }
        let tilt = (rng.normal() * 0.02, rng.normal() * 0.02);
        let a = rng.range(0.0, std::f64::consts::PI);
        Terrain { seeds, tilt, ripple_dir: (a.cos(), a.sin()), rocks: RockField::default() }
    }

    /// The large-scale seabed (a gentle tilt and dunes): C2 smooth, the vehicle's altitude
    /// reference.
    pub(super) fn reference(&self, x: f64, y: f64) -> f64 {
        let s = &self.seeds;
        self.tilt.0 * x + self.tilt.1 * y + 0.45 * gnoise(x / 16.0, y / 16.0, s[0]) + 0.18 * gnoise(x / 6.5 + 3.1, y / 6.5, s[1])
    }

    /// Mounds and hollows of a metre or two.
    pub(super) fn mounds(&self, x: f64, y: f64) -> f64 {
        let s = &self.seeds;
        0.06 * gnoise(x / 2.2, y / 2.2, s[2]) + 0.025 * gnoise(x / 0.9, y / 0.9, s[3])
    }

    fn ripples(&self, x: f64, y: f64) -> f64 {
        let s = &self.seeds;
        let field = smoothstep(-0.25, 0.25, gnoise(x / 9.0, y / 9.0, s[4]));
        if field <= 0.0 {
            return 0.0;
        }
        let along = x * self.ripple_dir.0 + y * self.ripple_dir.1;
        let phase = std::f64::consts::TAU * along / RIPPLE_LAMBDA_M + 2.4 * gnoise(x / 1.3, y / 1.3, s[5]) + 0.7 * gnoise(x / 0.45, y / 0.45, s[6]);
        // Asymmetric crests (steep lee side), amplitude varying across the field.
        let (sin1, cos1) = phase.sin_cos();
        let profile = sin1 + 0.56 * sin1 * cos1;
        field * RIPPLE_AMPLITUDE_M * (0.75 + 0.25 * gnoise(x / 2.5, y / 2.5, s[7])) * profile
    }

    /// The smooth part of the seabed: dunes and mounds.
    pub(super) fn base(&self, x: f64, y: f64) -> f64 {
        self.reference(x, y) + self.mounds(x, y)
    }

    /// What lies on the smooth base, and rockiness in [0, 1]. `fine` adds what only the fine
    /// grid resolves (ripples, grain roughness, small rocks, boulder lumps).
    pub(super) fn detail(&self, x: f64, y: f64, fine: bool) -> (f64, f64) {
        let bump = self.rocks.height(x, y, fine, if fine { 0.0 } else { 1.5 * COARSE_CELL_M });
        let rockiness = smoothstep(0.008, 0.04, bump);
        let mut h = bump;
        if fine {
            h += (1.0 - rockiness) * self.ripples(x, y) + 0.003 * gnoise(x / 0.07, y / 0.07, self.seeds[10]);
        }
        (h, rockiness)
    }
}

