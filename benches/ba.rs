//! Bundle adjustment timings on the board-sized window: 8 keyframes, 40x30 inverse depth
//! (1200 pixels each), 26 edges (every ordered pair at most two keyframes apart). Prints the
//! median of several runs for one damped Gauss-Newton iteration (full `solve` divided by its
//! iterations, and its parts), and for the covariance (Eq. 4).
//!
//! Run: `cargo bench --bench ba` (release profile; no criterion, plain `main`).

#[path = "../tests/common/ba_scene.rs"]
mod ba_scene;

use std::time::{Duration, Instant};

use ba_scene::{perturb, Scene};
use duv_core::rng::Rng;
use duv_core::{Image, PlaneF32, Se3};
use duv_track::ba::{BaCapacity, BaConfig, BaWorkspace};

const RUNS: usize = 15;

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

fn median_ms(mut samples: Vec<Duration>) -> f64 {
    samples.sort();
    samples[samples.len() / 2].as_secs_f64() * 1e3
}

fn main() {
    let scene = Scene::new(8, 40, 30, 2);
    let mut rng = Rng::new(1);
    let poses = (0..8).map(|k| if k == 0 { scene.world_from_cam[0] } else { perturb(&scene.world_from_cam[k], 0.02, 0.02, &mut rng) }).collect();
    let depths = (0..8).map(|k| scene.perturbed_inv_depth(k, 0.1, &mut rng)).collect();
    let meas = scene.edges.iter().map(|&(i, j)| scene.measurements(i, j, 0.05, 0.05, &mut rng)).collect();
    let inputs = Inputs { scene, poses, depths, meas };
    let (n_kf, n_edges, n_pix) = (8, inputs.scene.edges.len(), inputs.scene.n_pixels());
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: n_kf, max_pixels_per_keyframe: n_pix, max_edges: n_edges });
    // Fixed iteration count: no early stop, so every run does the same work.
    let config = BaConfig { max_iterations: 8, cost_tolerance: 0.0, step_tolerance: 0.0, huber_threshold: 3.0, ..BaConfig::default() };

    let (mut per_iter, mut linearize, mut step, mut cov, mut cov_relin) = (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut last = None;
    for _ in 0..RUNS {
        load(&mut ws, &inputs);
        let t = Instant::now();
        let report = ws.solve(&config).unwrap();
        per_iter.push(t.elapsed() / report.iterations as u32);
        last = Some(report);

        // Covariance right after the solve (relinearises at the final state), then again
        // with the linearisation current (Eq. 4 alone).
        let t = Instant::now();
        ws.compute_covariance(&config).unwrap();
        cov_relin.push(t.elapsed());
        let t = Instant::now();
        ws.compute_covariance(&config).unwrap();
        cov.push(t.elapsed());

        // The parts of one iteration: linearisation, then Schur + Cholesky + back-substitution.
        let pose = ws.world_from_cam(1).unwrap();
        ws.set_world_from_cam(1, &pose).unwrap(); // invalidates the linearisation
        let t = Instant::now();
        ws.linearize(&config).unwrap();
        linearize.push(t.elapsed());
        let t = Instant::now();
        ws.compute_step(&config, 1e-4).unwrap();
        step.push(t.elapsed());
    }
    let report = last.unwrap();
    println!("BA window: {n_kf} keyframes, {}x{} inverse depth ({n_pix} px each), {n_edges} edges, {} residuals", inputs.scene.camera.width, inputs.scene.camera.height, n_edges * n_pix);
    println!("last solve: {report:?}");
    println!("median of {RUNS} runs:");
    println!("  GN iteration (solve / iterations) : {:8.3} ms", median_ms(per_iter));
    println!("    linearise (H_pp, H_pd, H_dd, b) : {:8.3} ms", median_ms(linearize));
    println!("    Schur + Cholesky + back-subst.  : {:8.3} ms", median_ms(step));
    println!("  covariance (Eq. 4), linearised    : {:8.3} ms", median_ms(cov));
    println!("  covariance incl. relinearisation  : {:8.3} ms", median_ms(cov_relin));
}
