//! The generated scene and ray intersection against it: the seabed ([`super::terrain`],
//! sampled into a [`Heightfield`]), a pipeline and a wreck ([`super::structures`]) placed from
//! the planned path so they come into view. Surface colours are in [`super::materials`].

pub use super::hit::{Hit, Surface};
use super::heightfield::{Heightfield, BLOCK_M};
use super::structures::{place_structures, Pipe, StructurePlacement, Wreck, PIPE_RADIUS_M, WRECK_KEEP_OUT_M};
use super::terrain::{KeepOut, RockField, Terrain};
use super::trajectory::PlanarPlan;
use super::SimError;
use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// At most this many heightfield cells (fine plus coarse) for one scene.
pub const MAX_CELLS: usize = 60_000_000;

/// The whole scene: seabed heightfield, pipe, wreck.
#[derive(Clone, Debug)]
pub struct Scene {
    terrain: Terrain,
    heightfield: Heightfield,
    pipe: Pipe,
    wreck: Wreck,
    placement: StructurePlacement,
    pub(super) seeds: [u32; 16],
    /// Contrast of the seabed texture ([`crate::SimConfig::seabed_texture`]).
    pub(super) seabed_texture: f64,
}

impl Scene {
    /// Builds the seabed for a planned path: fine grid out to `fine_margin_m` around it,
    /// coarse grid out to `coarse_margin_m`.
    pub fn new(seed: u64, plan: &PlanarPlan, fine_margin_m: f64, coarse_margin_m: f64) -> Result<Scene, SimError> {
        let mut terrain = Terrain::new(seed);
        let placement = place_structures(&plan.layout, seed);
        let keep_out = [
            KeepOut { a: placement.pipe_from, b: placement.pipe_to, radius: PIPE_RADIUS_M + 0.3 },
            KeepOut { a: placement.wreck_center, b: placement.wreck_center, radius: WRECK_KEEP_OUT_M },
        ];

        // Extents: the path's bounds (and the structures') with margins, on whole blocks.
        let (mut x0, mut y0, mut x1, mut y1) = plan.bounds();
        for (x, y) in [placement.pipe_from, placement.pipe_to, placement.wreck_center] {
            x0 = x0.min(x);
            y0 = y0.min(y);
            x1 = x1.max(x);
            y1 = y1.max(y);
        }
        let snap_lo = |v: f64| (v / BLOCK_M).floor() * BLOCK_M;
        let snap_hi = |v: f64| (v / BLOCK_M).ceil() * BLOCK_M;
        let fine_rect = [snap_lo(x0 - fine_margin_m), snap_lo(y0 - fine_margin_m), snap_hi(x1 + fine_margin_m), snap_hi(y1 + fine_margin_m)];
        let outer = [snap_lo(x0 - coarse_margin_m), snap_lo(y0 - coarse_margin_m), snap_hi(x1 + coarse_margin_m), snap_hi(y1 + coarse_margin_m)];
        let outer = [outer[0].min(fine_rect[0]), outer[1].min(fine_rect[1]), outer[2].max(fine_rect[2]), outer[3].max(fine_rect[3])];
        let cells = Heightfield::cells(fine_rect, outer);
        if cells > MAX_CELLS || !x0.is_finite() || !y1.is_finite() {
            return Err(SimError::SceneTooLarge { cells, limit: MAX_CELLS, width_m: outer[2] - outer[0], height_m: outer[3] - outer[1] });
        }

        terrain.rocks = RockField::new(&terrain.seeds, outer, &keep_out);
        let heightfield = Heightfield::build(&terrain, fine_rect, outer);

        let pipe = Pipe::on_seabed(&placement, &terrain);
        let wreck = Wreck::on_seabed(&placement, &terrain);

        let mut rng = duv_core::rng::Rng::derive(seed, 0x00A1_BED0);
        let mut seeds = [0u32; 16];
        for s in &mut seeds {
            *s = (rng.next_u64() >> 32) as u32;
        }
        Ok(Scene { terrain, heightfield, pipe, wreck, placement, seeds, seabed_texture: 1.0 })
    }

    /// Sets the contrast of the seabed texture around a mid sand tint (1: as generated).
    pub fn set_seabed_texture(&mut self, contrast: f64) {
        self.seabed_texture = contrast;
    }

    /// The seabed.
    pub fn heightfield(&self) -> &Heightfield {
        &self.heightfield
    }

    /// Where the pipe and the wreck lie.
    pub fn placement(&self) -> &StructurePlacement {
        &self.placement
    }

    /// The smooth large-scale seabed height the vehicle keeps its altitude above.
    pub fn ground_reference(&self, x: f64, y: f64) -> f64 {
        self.terrain.reference(x, y)
    }

    /// First hit of the unit ray `o + t d` with the scene before `t_max`. `pixel_angle_rad` is
    /// the angle one pixel subtends (1 / fx): seabed normals are averaged over the pixel's
    /// footprint (0 for the finest normals).
    pub fn intersect(&self, o: &V3, d: &V3, t_max: f64, pixel_angle_rad: f64) -> Option<Hit> {
        let inv_d = V3::new(1.0 / d.x, 1.0 / d.y, 1.0 / d.z);
        let mut best = self.pipe.intersect(o, d, &inv_d, t_max);
        if let Some(h) = self.wreck.intersect(o, d, &inv_d, best.map_or(t_max, |b| b.t)) {
            best = Some(h);
        }
        let limit = best.map_or(t_max, |b| b.t);
        if let Some(t) = self.heightfield.march(o, d, limit) {
            let point = o + d * t;
            // Footprint along the ray's ground track (the long axis at grazing incidence).
            let footprint = t * pixel_angle_rad / d.z.abs().max(0.15);
            let normal = self.heightfield.normal_filtered(&point, footprint);
            return Some(Hit { t, point, normal, surface: Surface::Seabed });
        }
        best
    }

    /// Whether the segment from `p` along unit `dir` meets a structure (for sun shadows).
    pub fn structure_blocks(&self, p: &V3, dir: &V3, t_max: f64) -> bool {
        let inv_d = V3::new(1.0 / dir.x, 1.0 / dir.y, 1.0 / dir.z);
        self.pipe.intersect(p, dir, &inv_d, t_max).is_some() || self.wreck.intersect(p, dir, &inv_d, t_max).is_some()
    }

    /// Height of the camera above whatever lies straight below it (seabed or structure).
    pub fn altitude_below(&self, p: &V3) -> Option<f64> {
        self.intersect(p, &V3::new(0.0, 0.0, -1.0), 1000.0, 0.0).map(|h| h.t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trajectory::plan_planar;
    use crate::{SimConfig, TrajectoryKind, WaterPreset};

    fn small_scene() -> Scene {
        let cfg = SimConfig { frames: 20, ..SimConfig::preset(WaterPreset::Turbid, TrajectoryKind::Hover) };
        Scene::new(7, &plan_planar(&cfg), 3.0, 6.0).unwrap()
    }

    #[test]
    fn march_agrees_with_brute_force_sampling() {
        let scene = small_scene();
        let hf = scene.heightfield();
        let o = V3::new(0.1, 0.2, scene.ground_reference(0.1, 0.2) + 1.7);
        let mut hits = 0;
        for k in 0..300 {
            let a = k as f64 * 0.37;
            let elev = -0.15 - 1.2 * (k as f64 / 300.0);
            let d = V3::new(a.cos() * elev.cos(), a.sin() * elev.cos(), elev.sin()).normalize();
            let fast = hf.march(&o, &d, 5.5);
            // Brute force: 1 mm steps.
            let mut brute = None;
            let mut t = 0.0;
            while t < 5.5 {
                let p = o + d * t;
                if p.z <= hf.height(p.x, p.y) {
                    brute = Some(t);
                    break;
                }
                t += 0.001;
            }
            match (fast, brute) {
                (Some(f), Some(b)) => {
                    hits += 1;
                    assert!((f - b).abs() < 0.003, "ray {k}: march {f} vs brute {b}");
                    let p = o + d * f;
                    assert!((p.z - hf.height(p.x, p.y)).abs() < 1e-5);
                }
                (None, None) => {}
                other => panic!("ray {k}: {other:?}"),
            }
        }
        assert!(hits > 250, "{hits}");
    }

    #[test]
    fn structures_are_hit_analytically() {
        let scene = small_scene();
        let pl = scene.placement();
        // Straight down onto the middle of the pipe: hits its top at radius above the axis.
        let (x, y) = (0.5 * (pl.pipe_from.0 + pl.pipe_to.0), 0.5 * (pl.pipe_from.1 + pl.pipe_to.1));
        let o = V3::new(x, y, 10.0);
        let hit = scene.intersect(&o, &V3::new(0.0, 0.0, -1.0), 100.0, 0.0).unwrap();
        assert!(matches!(hit.surface, Surface::Pipe { .. }), "{hit:?}");
        assert!(hit.normal.z > 0.99);
        // Onto the wreck centre: hull or wheelhouse, well above the seabed.
        let (wx, wy) = pl.wreck_center;
        let hit = scene.intersect(&V3::new(wx, wy, 10.0), &V3::new(0.0, 0.0, -1.0), 100.0, 0.0).unwrap();
        assert!(matches!(hit.surface, Surface::Wreck { .. }), "{hit:?}");
        let top = 10.0 - hit.t;
        let ground = scene.terrain.base(wx, wy);
        assert!(top > ground + 0.3, "wreck top {top} over seabed {ground}");
        // An upward ray from above everything misses.
        assert!(scene.intersect(&o, &V3::new(0.1, 0.0, 1.0).normalize(), 100.0, 0.0).is_none());
    }

    #[test]
    fn albedo_is_deterministic_varied_and_detailed() {
        let scene = small_scene();
        let mut lum = Vec::new();
        for k in 0..4000 {
            let (x, y) = (-2.0 + (k % 80) as f64 * 0.05, -2.0 + (k / 80) as f64 * 0.08);
            let p = V3::new(x, y, scene.heightfield().height(x, y));
            let hit = Hit { t: 2.0, point: p, normal: V3::z(), surface: Surface::Seabed };
            let a = scene.albedo(&hit, 0.004);
            assert_eq!(a, scene.albedo(&hit, 0.004));
            assert!(a.iter().all(|v| (0.0..=1.0).contains(v)));
            lum.push(a[0] + a[1] + a[2]);
        }
        let mean = lum.iter().sum::<f64>() / lum.len() as f64;
        let var = lum.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / lum.len() as f64;
        assert!(var.sqrt() > 0.08 * mean, "texture contrast {} of {mean}", var.sqrt());
        // Neighbouring pixels at 1-2 m differ: detail at the pixel scale.
        let at = |x: f64| {
            let p = V3::new(x, 0.3, 0.0);
            scene.albedo(&Hit { t: 2.0, point: p, normal: V3::z(), surface: Surface::Seabed }, 0.005)[1]
        };
        let diffs: f64 = (0..200).map(|i| (at(i as f64 * 0.005) - at(i as f64 * 0.005 + 0.005)).abs()).sum::<f64>() / 200.0;
        assert!(diffs > 0.01, "pixel-to-pixel difference {diffs}");
    }
}
