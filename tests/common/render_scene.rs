//! Random Gaussian scenes in front of a camera, shared by `tests/algorithms/render.rs`,
//! `tests/render_alloc.rs` and `benches/render.rs`.
#![allow(dead_code)]

use duv_core::pose::so3_exp;
use duv_core::rng::Rng;
use duv_core::{PinholeCamera, Se3};
use duv_map::gaussians::{GaussianParam, Gaussians, SH_C0};
use duv_map::render::{MediumPlanes, RenderUpstream};
use nalgebra::{Point3, Translation3, Vector3};

/// A camera with the principal point at the image centre.
pub fn camera(width: usize, height: usize, f: f64) -> PinholeCamera {
    PinholeCamera::new(f, f, (width as f64 - 1.0) * 0.5, (height as f64 - 1.0) * 0.5, width, height).unwrap()
}

/// A camera somewhere off the world origin, slightly turned: `world_from_cam`.
pub fn world_from_cam() -> Se3 {
    Se3::from_parts(Translation3::new(0.3, -0.2, 0.1), so3_exp(&Vector3::new(0.05, -0.1, 0.03)))
}

/// SH degree-0 coefficient giving colour `c` (with no degree-1 terms).
pub fn f_dc_for(c: f64) -> f32 {
    ((c - 0.5) / SH_C0) as f32
}

/// `n` Gaussians in the camera's view: `x/z`, `y/z` within `spread` of the image half-size,
/// depth in `z_range` (camera frame), projected standard deviations of `sigma_px` pixels
/// (anisotropic, randomly rotated), opacity logits in `logit_range`, colours with view
/// dependence.
#[allow(clippy::too_many_arguments)]
pub fn random_gaussians(
    rng: &mut Rng,
    n: usize,
    capacity: usize,
    camera: &PinholeCamera,
    world_from_cam: &Se3,
    z_range: (f64, f64),
    sigma_px: (f64, f64),
    logit_range: (f64, f64),
) -> Gaussians {
    let mut g = Gaussians::with_capacity(capacity);
    let half_x = 0.5 * camera.width as f64 / camera.fx;
    let half_y = 0.5 * camera.height as f64 / camera.fy;
    for _ in 0..n {
        let z = rng.range(z_range.0, z_range.1);
        let p_in_cam = Point3::new(rng.range(-1.0, 1.0) * half_x * z, rng.range(-1.0, 1.0) * half_y * z, z);
        let p_in_world = world_from_cam * p_in_cam;
        let s = rng.range(sigma_px.0, sigma_px.1) * z / camera.fx;
        let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        // Deliberately not unit length: the renderer normalises.
        let scale = rng.range(0.7, 1.4) / norm;
        let p = GaussianParam {
            mean: [p_in_world.x as f32, p_in_world.y as f32, p_in_world.z as f32],
            log_scale: std::array::from_fn(|_| (s * rng.range(0.5, 1.6)).ln() as f32),
            rotation: q.map(|v| (v * scale) as f32),
            opacity_logit: rng.range(logit_range.0, logit_range.1) as f32,
            f_dc: std::array::from_fn(|_| f_dc_for(rng.range(0.15, 0.85))),
            f_rest: std::array::from_fn(|_| rng.range(-0.2, 0.2) as f32),
        };
        g.push(&p).unwrap();
    }
    g
}

/// Per-pixel medium parameters drawn uniformly.
pub fn random_medium(rng: &mut Rng, width: usize, height: usize) -> MediumPlanes {
    let mut m = MediumPlanes::new(width, height);
    for v in m.c_med.data.iter_mut() {
        *v = rng.range(0.05, 0.6) as f32;
    }
    for v in m.sigma_att.data.iter_mut().chain(m.sigma_bs.data.iter_mut()) {
        *v = rng.range(0.02, 0.5) as f32;
    }
    m
}

/// Upstream gradients drawn uniformly in [-1, 1] (a random linear loss).
pub fn random_upstream(rng: &mut Rng, width: usize, height: usize) -> RenderUpstream {
    let mut u = RenderUpstream::new(width, height);
    for v in u
        .colour
        .data
        .iter_mut()
        .chain(u.restored.data.iter_mut())
        .chain(u.depth.data.iter_mut())
        .chain(u.depth_var.data.iter_mut())
        .chain(u.alpha.data.iter_mut())
    {
        *v = rng.range(-1.0, 1.0) as f32;
    }
    u
}
