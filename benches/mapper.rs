//! Mapper timings: one full mapping iteration (medium forward, render forward, total loss,
//! render backward, medium backward, Adam on every group; densification off) at 320x240 with
//! 20k and 100k random Gaussians in front of a keyframe camera (depth 1-10 m, 0.7-4 px). Prints
//! the median of several iterations, with the medium network exact per pixel (`grid_step_px`
//! 1, the reference) and on the default 1/8 direction grid, in the same run.
//!
//! Run: `cargo bench --bench mapper` (release profile; plain `main`).

#[path = "../tests/common/render_scene.rs"]
mod render_scene;

use std::time::Instant;

use duv_core::rng::Rng;
use duv_core::{ImageRgb8, Keyframe, PlaneF32, Timestamp};
use duv_map::mapper::{Mapper, MapperCapacity, MapperConfig};
use render_scene::{camera, random_gaussians, world_from_cam};

const RUNS: usize = 7;

fn main() {
    let (w, h) = (320, 240);
    let cam = camera(w, h, 280.0);
    let pose = world_from_cam();
    for (n, step) in [(20_000usize, 1usize), (20_000, 8), (100_000, 1), (100_000, 8)] {
        let mut rng = Rng::new(11);
        let g = random_gaussians(&mut rng, n, n, &cam, &pose, (1.0, 10.0), (0.7, 4.0), (-1.0, 3.0));
        let mut image = ImageRgb8::new(w, h);
        for v in image.data.iter_mut() {
            *v = rng.below(256) as u8;
        }
        let inv_depth = PlaneF32::filled(w, h, [0.3]);
        let inv_depth_variance = PlaneF32::filled(w, h, [1e-4]);
        let kf = Keyframe { index: 0, t_ns: Timestamp(0), image, world_from_cam: pose, camera: cam, inv_depth, inv_depth_variance };
        // No carving: the keyframe's flat depth would remove the random map's nearer part.
        let mut config = MapperConfig { densify_every: 0, init_covered_alpha: 0.0, carve_in_front_factor: 0.0, intersections_per_gaussian: 64, ..MapperConfig::default() };
        config.medium.grid_step_px = step;
        let mut m = Mapper::new(config, MapperCapacity { max_gaussians: n, max_keyframes: 1, width: w, height: h }).expect("mapper");
        m.set_gaussians(&g).expect("map");
        m.add_keyframe(kf).expect("keyframe");
        m.iterate().expect("warm-up");
        let mut times: Vec<f64> = (0..RUNS)
            .map(|_| {
                let t = Instant::now();
                m.iterate().expect("iteration");
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        times.sort_by(f64::total_cmp);
        println!("mapper iteration 320x240, {n} Gaussians, medium grid step {step}: median {:.1} ms (min {:.1}, max {:.1}, {RUNS} runs)", times[RUNS / 2], times[0], times[RUNS - 1]);
    }
}
