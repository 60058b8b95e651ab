//! A synthetic BA scene shared by `tests/algorithms/ba.rs`, `tests/ba_alloc.rs` and `benches/ba.rs`: a
//! plane at about 2 m with Gaussian bumps, seen by keyframes strung along a gentle arc,
//! ground-truth inverse depth by ray casting, and flow-like targets with optional noise and
//! outliers (weight 0 where the point leaves the target view, as a flow front end would).
#![allow(dead_code)]

use duv_core::pose::{se3_exp, so3_exp};
use duv_core::rng::Rng;
use duv_core::{Image, PinholeCamera, PlaneF32, Se3};
use nalgebra::{Point3, Translation3, Vector2, Vector3, Vector6};

/// Distance of the base plane from the first camera, metres.
pub const PLANE_Z_M: f64 = 2.0;

pub struct Scene {
    /// Camera at the depth-map resolution.
    pub camera: PinholeCamera,
    pub world_from_cam: Vec<Se3>,
    /// Ground-truth inverse depth per keyframe, row-major, 1/m.
    pub inv_depth: Vec<Vec<f64>>,
    pub edges: Vec<(usize, usize)>,
}

/// Height field: the plane `z = PLANE_Z_M` with bumps towards the cameras.
fn surface_z(x: f64, y: f64) -> (f64, f64, f64) {
    // (centre x, centre y, height, sigma)
    const BUMPS: [(f64, f64, f64, f64); 4] = [(0.2, 0.1, 0.35, 0.25), (-0.5, -0.3, 0.25, 0.3), (0.7, -0.4, 0.3, 0.2), (-0.1, 0.5, 0.2, 0.35)];
    let (mut z, mut dzdx, mut dzdy) = (PLANE_Z_M + 0.1 * x, 0.1, 0.0);
    for (bx, by, h, s) in BUMPS {
        let g = h * (-((x - bx).powi(2) + (y - by).powi(2)) / (2.0 * s * s)).exp();
        z -= g;
        dzdx += g * (x - bx) / (s * s);
        dzdy += g * (y - by) / (s * s);
    }
    (z, dzdx, dzdy)
}

impl Scene {
    /// `n` keyframes of a `width x height` depth map (70 degree horizontal field of view).
    /// Keyframe k sits 0.15 m further along x on a gentle arc, turned slightly to keep the
    /// bumps in view. Edges: every ordered pair with `1 <= |i - j| <= max_gap`.
    pub fn new(n: usize, width: usize, height: usize, max_gap: usize) -> Scene {
        let camera = PinholeCamera::from_hfov(70.0, width, height).unwrap();
        let world_from_cam: Vec<Se3> = (0..n)
            .map(|k| {
                let s = k as f64;
                let position = Vector3::new(0.15 * s - 0.3, 0.05 * (0.7 * s).sin(), 0.04 * (0.5 * s).cos() - 0.04);
                let rotation = so3_exp(&Vector3::new(0.02 * (0.9 * s).sin(), -0.05 * s + 0.1, 0.01 * s));
                Se3::from_parts(Translation3::from(position), rotation)
            })
            .collect();
        let inv_depth = world_from_cam.iter().map(|pose| cast_inv_depth(&camera, pose)).collect();
        let mut edges = Vec::new();
        for i in 0..n {
            for j in 0..n {
                if i != j && i.abs_diff(j) <= max_gap {
                    edges.push((i, j));
                }
            }
        }
        Scene { camera, world_from_cam, inv_depth, edges }
    }

    pub fn n_pixels(&self) -> usize {
        self.camera.width * self.camera.height
    }

    pub fn inv_depth_plane(&self, k: usize) -> PlaneF32 {
        let data = self.inv_depth[k].iter().map(|v| *v as f32).collect();
        PlaneF32::from_vec(self.camera.width, self.camera.height, data).unwrap()
    }

    /// Inverse depth of keyframe k, each pixel scaled by `1 + rel_sigma N(0, 1)` (clamped to
    /// stay positive).
    pub fn perturbed_inv_depth(&self, k: usize, rel_sigma: f64, rng: &mut Rng) -> PlaneF32 {
        let data = self.inv_depth[k].iter().map(|v| (v * (1.0 + rel_sigma * rng.normal()).max(0.5)) as f32).collect();
        PlaneF32::from_vec(self.camera.width, self.camera.height, data).unwrap()
    }

    /// Where pixel `p` of keyframe `i` lands in keyframe `j` (ground truth), if in front.
    pub fn true_target(&self, i: usize, j: usize, p: usize) -> Option<Vector2<f64>> {
        let w = self.camera.width;
        let uv = Vector2::new((p % w) as f64, (p / w) as f64);
        let q = self.camera.unproject(&uv)?;
        let x_in_i = Point3::from(q / self.inv_depth[i][p]);
        let x_in_j = self.world_from_cam[j].inverse_transform_point(&(self.world_from_cam[i] * x_in_i));
        self.camera.project(&x_in_j.coords)
    }

    /// Flow-like measurements for edge `(i, j)`: true targets plus N(0, noise_px) noise,
    /// a fraction `outliers` of them displaced by 1-5 px in a random direction; weight
    /// `1 / noise_floor^2` on both axes inside the target image, 0 outside.
    pub fn measurements(&self, i: usize, j: usize, noise_px: f64, outliers: f64, rng: &mut Rng) -> (Image<f32, 2>, Image<f32, 2>) {
        let (w, h) = (self.camera.width, self.camera.height);
        let mut target = Image::<f32, 2>::new(w, h);
        let mut weight = Image::<f32, 2>::new(w, h);
        let wt = 1.0 / noise_px.max(0.01).powi(2);
        for p in 0..w * h {
            let Some(uv) = self.true_target(i, j, p) else { continue };
            let mut t = uv + Vector2::new(rng.normal(), rng.normal()) * noise_px;
            if rng.uniform() < outliers {
                let angle = rng.range(0.0, std::f64::consts::TAU);
                t += Vector2::new(angle.cos(), angle.sin()) * rng.range(1.0, 5.0);
            }
            target.data[2 * p] = t.x as f32;
            target.data[2 * p + 1] = t.y as f32;
            if self.camera.contains(&uv) {
                weight.data[2 * p] = wt as f32;
                weight.data[2 * p + 1] = wt as f32;
            }
        }
        (target, weight)
    }
}

/// Ray-casts the height field from every pixel centre: inverse depth (1/m) along the optical axis.
fn cast_inv_depth(camera: &PinholeCamera, world_from_cam: &Se3) -> Vec<f64> {
    let (w, h) = (camera.width, camera.height);
    let c = world_from_cam.translation.vector;
    (0..w * h)
        .map(|p| {
            let q = camera.unproject(&Vector2::new((p % w) as f64, (p / w) as f64)).unwrap();
            let r = world_from_cam.rotation * q;
            // Newton on f(t) = c_z + t r_z - surface_z(c + t r); t is the depth (q has z = 1).
            let mut t = (PLANE_Z_M - c.z) / r.z;
            for _ in 0..50 {
                let x = c + r * t;
                let (z, dzdx, dzdy) = surface_z(x.x, x.y);
                let f = x.z - z;
                let df = r.z - dzdx * r.x - dzdy * r.y;
                let dt = f / df;
                t -= dt;
                if dt.abs() < 1e-14 * t.abs() {
                    break;
                }
            }
            1.0 / t
        })
        .collect()
}

/// `pose * exp(xi)` with `xi` drawn as N(0, trans_sigma_m) per translation axis and
/// N(0, rot_sigma_rad) per rotation axis.
pub fn perturb(pose: &Se3, trans_sigma_m: f64, rot_sigma_rad: f64, rng: &mut Rng) -> Se3 {
    let xi = Vector6::new(
        rng.normal() * trans_sigma_m,
        rng.normal() * trans_sigma_m,
        rng.normal() * trans_sigma_m,
        rng.normal() * rot_sigma_rad,
        rng.normal() * rot_sigma_rad,
        rng.normal() * rot_sigma_rad,
    );
    pose * se3_exp(&xi)
}
