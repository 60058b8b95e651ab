//! No allocation per window after warm-up (house habit 7): a counting global allocator shows
//! that reloading a window, `solve`, `compute_covariance` and `solve_motion_only` allocate
//! nothing once the `BaWorkspace` exists and has run once. Its own test binary, because the
//! global allocator is per binary.

#[path = "common/ba_scene.rs"]
mod ba_scene;

use ba_scene::{perturb, Scene};
use duv_core::rng::Rng;
use duv_core::{Image, PlaneF32, Se3};
use duv_track::ba::{solve_motion_only, BaCapacity, BaConfig, BaWorkspace, MotionOnlyObservation};
use duv_core::alloc::{self, CountingAllocator};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Allocations made by `f` on this thread.
fn count_allocations(f: impl FnOnce()) -> usize {
    alloc::count_allocations_on_this_thread(f)
}

struct Inputs {
    scene: Scene,
    poses: Vec<Se3>,
    depths: Vec<PlaneF32>,
    meas: Vec<(Image<f32, 2>, Image<f32, 2>)>,
}

fn load(ws: &mut BaWorkspace, inputs: &Inputs) {
    ws.begin(&inputs.scene.camera).unwrap();
    for (pose, depth) in inputs.poses.iter().zip(&inputs.depths) {
        ws.add_keyframe(pose, depth).unwrap();
    }
    for (&(i, j), (t, w)) in inputs.scene.edges.iter().zip(&inputs.meas) {
        ws.add_edge(i, j, t, w).unwrap();
    }
}

#[test]
fn solve_allocates_nothing_after_warm_up() {
    // 4 keyframes of 20x15 with 6 edges: small enough for a fast debug test, and a reduced
    // system of 18 unknowns, so faer's factor, solve and inverse all run.
    let scene = Scene::new(4, 20, 15, 1);
    let mut rng = Rng::new(9);
    let poses: Vec<Se3> = (0..4).map(|k| if k == 0 { scene.world_from_cam[0] } else { perturb(&scene.world_from_cam[k], 0.01, 0.01, &mut rng) }).collect();
    let depths: Vec<PlaneF32> = (0..4).map(|k| scene.perturbed_inv_depth(k, 0.05, &mut rng)).collect();
    let meas = scene.edges.iter().map(|&(i, j)| scene.measurements(i, j, 0.05, 0.1, &mut rng)).collect();
    let inputs = Inputs { scene, poses, depths, meas };
    // Capacity larger than the window, as on a board (window sizes vary).
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 6, max_pixels_per_keyframe: 400, max_edges: 10 });
    let config = BaConfig { max_iterations: 5, huber_threshold: 2.0, ..BaConfig::default() };
    let gt_depth = inputs.scene.inv_depth_plane(0);
    // A depth variance too (the tracker passes the keyframe's): the deflated weights must not allocate either.
    let depth_variance = PlaneF32::filled(gt_depth.width, gt_depth.height, [1e-4]);
    let motion_obs = [MotionOnlyObservation {
        world_from_keyframe: inputs.scene.world_from_cam[0],
        inv_depth: &gt_depth,
        target_xy: &inputs.meas[0].0,
        weight_xy: &inputs.meas[0].1,
        inv_depth_variance: Some(&depth_variance),
        variance_of_unit_weight: 1.0,
    }];
    let mut out = PlaneF32::new(20, 15);

    // Warm-up: first window, first solve, first covariance (faer, tracing callsites).
    load(&mut ws, &inputs);
    let first = ws.solve(&config).unwrap();
    ws.compute_covariance(&config).unwrap();
    let mut frame = inputs.poses[1];
    solve_motion_only(&inputs.scene.camera, &motion_obs, &mut frame, &config).unwrap();

    let mut second = None;
    let n = count_allocations(|| {
        load(&mut ws, &inputs);
        second = Some(ws.solve(&config).unwrap());
        ws.compute_covariance(&config).unwrap();
        ws.write_inv_depth(2, &mut out).unwrap();
        ws.write_inv_depth_variance(2, &mut out).unwrap();
        let mut frame = inputs.poses[1];
        solve_motion_only(&inputs.scene.camera, &motion_obs, &mut frame, &config).unwrap();
    });
    let second = second.unwrap();
    assert_eq!(n, 0, "allocations in a warmed-up window solve");
    // The counted run did real work: same window, same result.
    assert!(second.accepted > 0 && second.final_cost < second.initial_cost);
    assert_eq!(first, second);
    // And the counter does count.
    assert!(count_allocations(|| drop(std::hint::black_box(vec![0u8; 16]))) > 0);
}
