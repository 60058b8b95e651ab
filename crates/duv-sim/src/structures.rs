//! Man-made structures on the seabed, intersected analytically: a concrete-coated pipeline (a
//! chain of capsules following the seabed, partly buried, with free spans) and a wreck (a
//! tilted, half-buried hull with a wheelhouse and a fallen mast).

use super::noise::lerp;
use super::hit::{Hit, Surface};
use super::terrain::Terrain;
use super::trajectory::Layout;
use nalgebra::{Rotation3, Vector3};

type V3 = Vector3<f64>;

/// An axis-aligned box for quick rejection.
#[derive(Clone, Copy, Debug)]
pub(super) struct Aabb {
    lo: V3,
    hi: V3,
}

impl Aabb {
    fn empty() -> Self {
        Aabb { lo: V3::repeat(f64::INFINITY), hi: V3::repeat(f64::NEG_INFINITY) }
    }
    fn grow_point(&mut self, p: &V3, r: f64) {
        self.lo = self.lo.inf(&(p - V3::repeat(r)));
        self.hi = self.hi.sup(&(p + V3::repeat(r)));
    }
    #[inline]
    fn hit(&self, o: &V3, inv_d: &V3, t_max: f64) -> bool {
        let mut t0: f64 = 0.0;
        let mut t1 = t_max;
        for k in 0..3 {
            let a = (self.lo[k] - o[k]) * inv_d[k];
            let b = (self.hi[k] - o[k]) * inv_d[k];
            let (near, far) = if a < b { (a, b) } else { (b, a) };
            // NaN (0 * inf on a slab face) compares false and leaves the interval as is.
            if near > t0 {
                t0 = near;
            }
            if far < t1 {
                t1 = far;
            }
        }
        t0 <= t1
    }
}

/// A segment of the pipe: a capsule from `a` to `b`.
#[derive(Clone, Copy, Debug)]
struct Capsule {
    a: V3,
    b: V3,
    along0: f64,
    bounds: Aabb,
}

/// The pipeline: capsules following the seabed, constant radius.
#[derive(Clone, Debug)]
pub struct Pipe {
    caps: Vec<Capsule>,
    radius: f64,
    bounds: Aabb,
}

/// Pipe radius (a 0.4 m concrete-coated line), metres.
pub const PIPE_RADIUS_M: f64 = 0.2;

impl Pipe {
    fn new(nodes: &[V3], radius: f64) -> Pipe {
        let mut caps = Vec::new();
        let mut bounds = Aabb::empty();
        let mut along = 0.0;
        for w in nodes.windows(2) {
            let mut cb = Aabb::empty();
            cb.grow_point(&w[0], radius);
            cb.grow_point(&w[1], radius);
            bounds.grow_point(&w[0], radius);
            bounds.grow_point(&w[1], radius);
            caps.push(Capsule { a: w[0], b: w[1], along0: along, bounds: cb });
            along += (w[1] - w[0]).norm();
        }
        Pipe { caps, radius, bounds }
    }

    pub(super) fn intersect(&self, o: &V3, d: &V3, inv_d: &V3, t_max: f64) -> Option<Hit> {
        if !self.bounds.hit(o, inv_d, t_max) {
            return None;
        }
        let mut best: Option<(f64, usize)> = None;
        for (k, c) in self.caps.iter().enumerate() {
            let limit = best.map_or(t_max, |b| b.0);
            if !c.bounds.hit(o, inv_d, limit) {
                continue;
            }
            if let Some(t) = capsule_intersect(o, d, &c.a, &c.b, self.radius) {
                if t > 1e-6 && t < limit {
                    best = Some((t, k));
                }
            }
        }
        let (t, k) = best?;
        let c = &self.caps[k];
        let p = o + d * t;
        let ba = c.b - c.a;
        let s = ((p - c.a).dot(&ba) / ba.norm_squared()).clamp(0.0, 1.0);
        let axis_point = c.a + ba * s;
        let normal = (p - axis_point).normalize();
        let dir = ba.normalize();
        let side = dir.cross(&V3::z()).normalize();
        let up = side.cross(&dir);
        let around = (normal.dot(&up)).atan2(normal.dot(&side)) * self.radius;
        Some(Hit { t, point: p, normal, surface: Surface::Pipe { along_m: c.along0 + s * ba.norm(), around_m: around } })
    }
}

/// Ray-capsule intersection (Quilez), `d` unit length; the nearest positive root.
fn capsule_intersect(o: &V3, d: &V3, a: &V3, b: &V3, r: f64) -> Option<f64> {
    let ba = b - a;
    let oa = o - a;
    let baba = ba.dot(&ba);
    let bard = ba.dot(d);
    let baoa = ba.dot(&oa);
    let rdoa = d.dot(&oa);
    let oaoa = oa.dot(&oa);
    let qa = baba - bard * bard;
    let qb = baba * rdoa - baoa * bard;
    let qc = baba * oaoa - baoa * baoa - r * r * baba;
    let h = qb * qb - qa * qc;
    if h < 0.0 {
        // Misses the infinite cylinder, hence both end spheres inside it.
        return None;
    }
    let y = if qa > 1e-12 {
        let t = (-qb - h.sqrt()) / qa;
        let y = baoa + t * bard;
        if y > 0.0 && y < baba {
            return (t > 0.0).then_some(t);
        }
        y
    } else if bard > 0.0 {
        -1.0
    } else {
        baba + 1.0
    };
    // The end sphere on the side the ray meets.
    let oc = if y <= 0.0 { oa } else { o - b };
    let b2 = d.dot(&oc);
    let c2 = oc.dot(&oc) - r * r;
    let h2 = b2 * b2 - c2;
    if h2 > 0.0 {
        let t = -b2 - h2.sqrt();
        return (t > 0.0).then_some(t);
    }
    None
}

/// An oriented box.
#[derive(Clone, Copy, Debug)]
struct OBox {
    center: V3,
    /// Columns: the box axes in the world.
    world_from_box: Rotation3<f64>,
    half: V3,
    bounds: Aabb,
}

impl OBox {
    fn new(center: V3, world_from_box: Rotation3<f64>, half: V3) -> OBox {
        let mut bounds = Aabb::empty();
        for k in 0..8 {
            let corner = V3::new(
                if k & 1 == 0 { -half.x } else { half.x },
                if k & 2 == 0 { -half.y } else { half.y },
                if k & 4 == 0 { -half.z } else { half.z },
            );
            bounds.grow_point(&(center + world_from_box * corner), 0.0);
        }
        OBox { center, world_from_box, half, bounds }
    }

    /// `(t, axis, sign, local point)` of the entry into the box.
    fn intersect(&self, o: &V3, d: &V3, t_max: f64) -> Option<(f64, usize, f64, V3)> {
        let lo = self.world_from_box.inverse_transform_vector(&(o - self.center));
        let ld = self.world_from_box.inverse_transform_vector(d);
        let mut t_near = f64::NEG_INFINITY;
        let mut t_far = f64::INFINITY;
        let mut axis = 0;
        let mut sign = 1.0;
        for k in 0..3 {
            if ld[k].abs() < 1e-15 {
                if lo[k].abs() > self.half[k] {
                    return None;
                }
                continue;
            }
            let inv = 1.0 / ld[k];
            let (a, b) = ((-self.half[k] - lo[k]) * inv, (self.half[k] - lo[k]) * inv);
            let (near, far) = if a < b { (a, b) } else { (b, a) };
            if near > t_near {
                t_near = near;
                axis = k;
                sign = -ld[k].signum();
            }
            t_far = t_far.min(far);
        }
        if t_near > t_far || t_near <= 1e-6 || t_near >= t_max {
            return None;
        }
        Some((t_near, axis, sign, lo + ld * t_near))
    }
}

/// The wreck: hull, wheelhouse, fallen mast.
#[derive(Clone, Debug)]
pub struct Wreck {
    parts: [OBox; 3],
    bounds: Aabb,
}

impl Wreck {
    pub(super) fn intersect(&self, o: &V3, d: &V3, inv_d: &V3, t_max: f64) -> Option<Hit> {
        if !self.bounds.hit(o, inv_d, t_max) {
            return None;
        }
        let mut best: Option<(f64, usize, usize, f64, V3)> = None;
        for (i, part) in self.parts.iter().enumerate() {
            let limit = best.map_or(t_max, |b| b.0);
            if !part.bounds.hit(o, inv_d, limit) {
                continue;
            }
            if let Some((t, axis, sign, local)) = part.intersect(o, d, limit) {
                best = Some((t, i, axis, sign, local));
            }
        }
        let (t, i, axis, sign, local) = best?;
        let mut n_local = V3::zeros();
        n_local[axis] = sign;
        let normal = self.parts[i].world_from_box * n_local;
        let (u, v) = match axis {
            0 => (local.y, local.z),
            1 => (local.x, local.z),
            _ => (local.x, local.y),
        };
        Some(Hit { t, point: o + d * t, normal, surface: Surface::Wreck { part: i as u8, u: u + 7.3 * i as f64 + 3.1 * axis as f64, v } })
    }
}

/// Where the structures lie, in the plane (for placement tests and keep-out zones).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StructurePlacement {
    pub pipe_from: (f64, f64),
    pub pipe_to: (f64, f64),
    pub wreck_center: (f64, f64),
    pub wreck_yaw: f64,
}

/// Places the pipe across the path and the wreck beside it, in view early in the sequence
/// (and for a loop, again at its end).
pub fn place_structures(layout: &Layout, seed: u64) -> StructurePlacement {
    let mut rng = duv_core::rng::Rng::derive(seed, 0x0057_424B);
    let wreck_yaw = rng.range(0.25, 0.55) * if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
    match *layout {
        Layout::Survey { lane_length, spacing, lanes } => {
            let x = 0.62 * lane_length;
            StructurePlacement {
                pipe_from: (x, -4.0),
                pipe_to: (x, (lanes.max(1) - 1) as f64 * spacing + 4.0),
                wreck_center: (0.3 * lane_length + 2.0, 0.5 * spacing.max(3.0)),
                wreck_yaw,
            }
        }
        Layout::Loop { straight, radius } => {
            let x = -0.25 * straight - 0.3 * radius;
            StructurePlacement { pipe_from: (x, -4.0), pipe_to: (x, 2.0 * radius + 4.0), wreck_center: (2.6, -1.6), wreck_yaw }
        }
        Layout::Hover { .. } => StructurePlacement { pipe_from: (2.1, -5.0), pipe_to: (2.6, 5.0), wreck_center: (4.3, 0.9), wreck_yaw },
    }
}

/// Wreck hull half-extents (length, beam, height), metres.
const HULL_HALF: [f64; 3] = [1.6, 0.7, 0.5];
/// How deep the hull is sunk into the sediment, metres.
const HULL_BURIED_M: f64 = 0.38;
/// Keep-out radius around the wreck centre for rocks and boulders, metres.
pub const WRECK_KEEP_OUT_M: f64 = 1.9;

impl Pipe {
    /// The pipe of a placement: resting on the seabed, a little buried, bridging hollows
    /// (free spans).
    pub(super) fn on_seabed(placement: &StructurePlacement, terrain: &Terrain) -> Pipe {
        let (pa, pb) = (placement.pipe_from, placement.pipe_to);
        let length = ((pb.0 - pa.0).powi(2) + (pb.1 - pa.1).powi(2)).sqrt();
        let n_nodes = ((length / 1.6).ceil() as usize).max(1) + 1;
        let nodes: Vec<V3> = (0..n_nodes)
            .map(|k| {
                let s = k as f64 / (n_nodes - 1) as f64;
                let (x, y) = (lerp(pa.0, pb.0, s), lerp(pa.1, pb.1, s));
                V3::new(x, y, terrain.base(x, y) + 0.3 * PIPE_RADIUS_M)
            })
            .collect();
        Pipe::new(&nodes, PIPE_RADIUS_M)
    }
}

impl Wreck {
    /// The wreck of a placement: hull sunk into the sediment and tilted, wheelhouse, fallen
    /// mast.
    pub(super) fn on_seabed(placement: &StructurePlacement, terrain: &Terrain) -> Wreck {
        let (cx, cy) = placement.wreck_center;
        let ground = terrain.base(cx, cy);
        let hull_rot = Rotation3::from_axis_angle(&V3::z_axis(), placement.wreck_yaw)
            * Rotation3::from_axis_angle(&V3::x_axis(), 0.07)
            * Rotation3::from_axis_angle(&V3::y_axis(), -0.04);
        let half = V3::new(HULL_HALF[0], HULL_HALF[1], HULL_HALF[2]);
        let center = V3::new(cx, cy, ground + half.z - HULL_BURIED_M);
        let hull = OBox::new(center, hull_rot, half);
        let house_half = V3::new(0.45, 0.42, 0.27);
        let house = OBox::new(center + hull_rot * V3::new(-0.55, 0.05, half.z + house_half.z), hull_rot, house_half);
        // The mast lies across the deck and down onto the seabed beside the hull.
        let mast_rot = Rotation3::from_axis_angle(&V3::z_axis(), placement.wreck_yaw + 1.25) * Rotation3::from_axis_angle(&V3::y_axis(), 0.22);
        let mast_center = center + hull_rot * V3::new(0.7, 0.9, 0.05);
        let mast = OBox::new(mast_center, mast_rot, V3::new(1.0, 0.05, 0.05));
        let mut bounds = Aabb::empty();
        for p in [&hull, &house, &mast] {
            bounds.grow_point(&p.bounds.lo, 0.0);
            bounds.grow_point(&p.bounds.hi, 0.0);
        }
    Wreck { parts: [hull, house, mast], bounds }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn capsule_intersection_matches_geometry() {
        let a = V3::new(0.0, 0.0, 0.0);
        let b = V3::new(2.0, 0.0, 0.0);
        let t = capsule_intersect(&V3::new(1.0, 0.0, 5.0), &V3::new(0.0, 0.0, -1.0), &a, &b, 0.5).unwrap();
        assert!((t - 4.5).abs() < 1e-12);
        let t = capsule_intersect(&V3::new(-3.0, 0.0, 0.0), &V3::new(1.0, 0.0, 0.0), &a, &b, 0.5).unwrap();
        assert!((t - 2.5).abs() < 1e-12, "cap: {t}");
        assert!(capsule_intersect(&V3::new(1.0, 2.0, 5.0), &V3::new(0.0, 0.0, -1.0), &a, &b, 0.5).is_none());
    }
}
