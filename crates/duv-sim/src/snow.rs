//! Marine snow: organic particles suspended in the water, fixed in the world apart from a slow
//! common drift (a current plus sinking) and a small bounded wobble per particle.
//!
//! The particles come from a hashed 3D grid of [`SNOW_CELL_M`] cells: each cell's count
//! (Poisson with mean density x cell volume), positions, radii and albedos are a pure function
//! of the seed and the cell, so any frame can be rendered alone and the same particle is seen
//! from every frame that looks at it. Only particles between [`SNOW_NEAR_M`] and
//! [`SNOW_FAR_M`] in front of the camera are drawn (nearer ones are out of focus, farther ones
//! under a pixel and lost in the haze); the renderer shades and composites them.

use super::noise::floor_i32;
use duv_core::rng::Rng;
use duv_core::{PinholeCamera, Se3};
use nalgebra::{Point3, Vector3};

/// Edge of a grid cell, metres.
pub const SNOW_CELL_M: f64 = 0.5;
/// Nearest drawn particle, metres along the optical axis.
pub const SNOW_NEAR_M: f64 = 0.15;
/// Farthest drawn particle, metres along the optical axis.
pub const SNOW_FAR_M: f64 = 3.0;
/// Particle radius range, metres (small ones are more common: `r = min + (max - min) u^2`).
pub const SNOW_RADIUS_M: (f64, f64) = (0.001, 0.004);
/// Particle albedo range.
pub const SNOW_ALBEDO: (f64, f64) = (0.6, 0.9);
/// A particle is drawn at least this large (pixels); a smaller one is drawn this large and
/// fainter, so its light is kept.
pub const SNOW_MIN_RADIUS_PX: f64 = 0.7;
/// Amplitude of the per-particle wobble around the common drift, metres (each axis), at
/// 0.05-0.2 Hz: at most 6.3 mm/s per axis on top of the drift.
pub const SNOW_WOBBLE_M: f64 = 0.005;
/// Most particles a cell may hold (the density limit of `SimConfig::validate` keeps the mean
/// far below it).
const MAX_PER_CELL: usize = 4096;

/// Stream id of the particle field (mixed with the seed).
const SNOW_STREAM: u64 = 0x5A0_5E00;

/// One particle at one time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Particle {
    /// Its cell and its index in the cell: the same particle in every frame.
    pub id: ([i32; 3], u32),
    pub p_in_world: Vector3<f64>,
    pub radius_m: f64,
    pub albedo: f64,
}

/// A particle as the camera of one frame sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SnowSplat {
    pub particle: Particle,
    pub p_in_cam: Vector3<f64>,
    /// Distance from the camera centre, metres.
    pub range_m: f64,
    /// Projected centre, pixels.
    pub u: f64,
    pub v: f64,
    /// Drawn radius, pixels (at least [`SNOW_MIN_RADIUS_PX`]).
    pub radius_px: f64,
    /// Opacity at the centre: 1, or the true over the drawn area for sub-pixel particles.
    pub alpha: f64,
}

/// The particle field of a sequence.
#[derive(Clone, Debug)]
pub struct SnowField {
    seed: u64,
    density_per_m3: f64,
    drift_mps: Vector3<f64>,
}

impl SnowField {
    /// The field of `seed` with `density_per_m3` particles per cubic metre. The common drift
    /// is seeded: a horizontal current of 1-3 cm/s in any direction and sinking at 0.5-1.5 cm/s.
    pub fn new(seed: u64, density_per_m3: f64) -> Self {
        let mut rng = Rng::derive(seed ^ SNOW_STREAM, u64::MAX);
        let heading = rng.range(0.0, std::f64::consts::TAU);
        let current = rng.range(0.01, 0.03);
        let sink = rng.range(0.005, 0.015);
        SnowField { seed, density_per_m3, drift_mps: Vector3::new(current * heading.cos(), current * heading.sin(), -sink) }
    }

    /// Common drift velocity of every particle, world frame, m/s.
    pub fn drift_mps(&self) -> Vector3<f64> {
        self.drift_mps
    }

    /// Calls `f` for each particle of cell `cell` at time `t_s`.
    fn cell(&self, cell: [i32; 3], t_s: f64, mut f: impl FnMut(Particle)) {
        let key = ((cell[0] as u32 as u64 & 0x1F_FFFF) << 42) | ((cell[1] as u32 as u64 & 0x1F_FFFF) << 21) | (cell[2] as u32 as u64 & 0x1F_FFFF);
        let mut rng = Rng::derive(self.seed ^ SNOW_STREAM, key);
        let mean = self.density_per_m3 * SNOW_CELL_M.powi(3);
        let count = if mean < 30.0 {
            // Knuth: multiply uniforms until the product falls under exp(-mean).
            let limit = (-mean).exp();
            let mut product = rng.uniform();
            let mut n = 0;
            while product > limit && n < MAX_PER_CELL {
                n += 1;
                product *= rng.uniform();
            }
            n
        } else {
            (mean + mean.sqrt() * rng.normal()).round().clamp(0.0, MAX_PER_CELL as f64) as usize
        };
        let origin = Vector3::new(cell[0] as f64, cell[1] as f64, cell[2] as f64) * SNOW_CELL_M;
        let drift = self.drift_mps * t_s;
        for k in 0..count {
            let base = origin + Vector3::new(rng.uniform(), rng.uniform(), rng.uniform()) * SNOW_CELL_M;
            let u = rng.uniform();
            let radius_m = SNOW_RADIUS_M.0 + (SNOW_RADIUS_M.1 - SNOW_RADIUS_M.0) * u * u;
            let albedo = rng.range(SNOW_ALBEDO.0, SNOW_ALBEDO.1);
            let rate = std::f64::consts::TAU * rng.range(0.05, 0.2);
            let phase = [rng.range(0.0, std::f64::consts::TAU), rng.range(0.0, std::f64::consts::TAU), rng.range(0.0, std::f64::consts::TAU)];
            let wobble = Vector3::new((rate * t_s + phase[0]).sin(), (rate * t_s + phase[1]).sin(), (rate * t_s + phase[2]).sin()) * SNOW_WOBBLE_M;
            f(Particle { id: (cell, k as u32), p_in_world: base + drift + wobble, radius_m, albedo });
        }
    }

    /// The particles between [`SNOW_NEAR_M`] and `far_m` (at most [`SNOW_FAR_M`]) in front of
    /// the camera that project into the image at time `t_s`, farthest first (ties in id
    /// order), so painting them in order composites them back to front.
    pub fn visible(&self, camera: &PinholeCamera, world_from_cam: &Se3, t_s: f64, far_m: f64) -> Vec<SnowSplat> {
        let far_m = far_m.min(SNOW_FAR_M);
        let mut out = Vec::new();
        if self.density_per_m3 <= 0.0 || far_m <= SNOW_NEAR_M {
            return out;
        }
        // The frustum's corners in the drifted frame (where the particles' base positions
        // live), boxed, widened by the wobble and the largest drawn radius with its soft edge.
        let (w, h) = (camera.width as f64, camera.height as f64);
        let drift = self.drift_mps * t_s;
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for z in [SNOW_NEAR_M, far_m] {
            for (u, v) in [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)] {
                let p_in_cam = Vector3::new((u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z);
                let q = (world_from_cam * Point3::from(p_in_cam)).coords - drift;
                lo = lo.inf(&q);
                hi = hi.sup(&q);
            }
        }
        let margin = SNOW_WOBBLE_M * 3f64.sqrt() + SNOW_RADIUS_M.1.max((SNOW_MIN_RADIUS_PX + 0.5) * far_m / camera.fx.min(camera.fy));
        let cell_lo = (lo - Vector3::repeat(margin)).map(|x| floor_i32(x / SNOW_CELL_M));
        let cell_hi = (hi + Vector3::repeat(margin)).map(|x| floor_i32(x / SNOW_CELL_M));
        let cam_from_world = world_from_cam.inverse();
        for iz in cell_lo.z..=cell_hi.z {
            for iy in cell_lo.y..=cell_hi.y {
                for ix in cell_lo.x..=cell_hi.x {
                    self.cell([ix, iy, iz], t_s, |particle| {
                        let p_in_cam = (cam_from_world * Point3::from(particle.p_in_world)).coords;
                        let z = p_in_cam.z;
                        if !(SNOW_NEAR_M..=far_m).contains(&z) {
                            return;
                        }
                        let (u, v) = (camera.cx + camera.fx * p_in_cam.x / z, camera.cy + camera.fy * p_in_cam.y / z);
                        let true_px = particle.radius_m * camera.fx / z;
                        let radius_px = true_px.max(SNOW_MIN_RADIUS_PX);
                        let reach = radius_px + 0.5;
                        if u < -0.5 - reach || u > w - 0.5 + reach || v < -0.5 - reach || v > h - 0.5 + reach {
                            return;
                        }
                        let alpha = (true_px / radius_px).powi(2);
                        out.push(SnowSplat { particle, p_in_cam, range_m: p_in_cam.norm(), u, v, radius_px, alpha });
                    });
                }
            }
        }
        out.sort_by(|a, b| b.range_m.total_cmp(&a.range_m).then(a.particle.id.cmp(&b.particle.id)));
        out
    }
}

/// Coverage of pixel centre `(u, v)` by a splat: 1 inside, a smooth one-pixel edge, 0 outside.
#[inline]
pub fn coverage(splat: &SnowSplat, u: f64, v: f64) -> f64 {
    let d = ((u - splat.u).powi(2) + (v - splat.v).powi(2)).sqrt();
    super::noise::smoothstep(splat.radius_px + 0.5, splat.radius_px - 0.5, d) * splat.alpha
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_density_and_determinism() {
        let field = SnowField::new(3, 200.0);
        let mut n = 0usize;
        let mut first = Vec::new();
        for ix in 0..8 {
            for iy in 0..8 {
                for iz in 0..8 {
                    field.cell([ix, iy, iz], 1.5, |p| {
                        n += 1;
                        if first.len() < 5 {
                            first.push(p);
                        }
                        // Inside its cell, give or take the drift and the wobble.
                        let rel = p.p_in_world - field.drift_mps() * 1.5 - Vector3::new(ix as f64, iy as f64, iz as f64) * SNOW_CELL_M;
                        assert!(rel.iter().all(|x| (-SNOW_WOBBLE_M..SNOW_CELL_M + SNOW_WOBBLE_M).contains(x)), "{rel:?}");
                        assert!((0.001..=0.004).contains(&p.radius_m) && (0.6..0.9).contains(&p.albedo));
                    });
                }
            }
        }
        // 512 cells of 0.125 m^3 at 200 per m^3: 12800 expected, Poisson spread ~113.
        assert!((n as f64 - 12_800.0).abs() < 500.0, "{n}");
        let mut again = Vec::new();
        field.cell([0, 0, 0], 1.5, |p| again.push(p));
        assert_eq!(first[..again.len().min(first.len())], again[..again.len().min(first.len())]);
        // Drift of a few cm/s, sinking.
        let v = field.drift_mps();
        assert!(v.norm() > 0.01 && v.norm() < 0.04 && v.z < 0.0, "{v:?}");
        // Dense fields take the normal approximation.
        let mut dense = 0;
        SnowField::new(3, 2000.0).cell([1, 2, 3], 0.0, |_| dense += 1);
        assert!((dense as f64 - 250.0).abs() < 80.0, "{dense}");
    }
}
