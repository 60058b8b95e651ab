//! Bundle adjustment (`duv_track::ba`): analytic Jacobians against central differences, the
//! Schur solve and the covariance (Eq. 3-4) against dense solves of the full system built
//! explicitly, the variance of unit weight against the known flow noise, convergence on a
//! synthetic scene with and without outliers, motion-only BA, and the error variants of bad
//! input.

use crate::ba_scene;

use ba_scene::{perturb, Scene};
use duv_core::pose::se3_exp;
use duv_core::rng::Rng;
use duv_core::{Image, PinholeCamera, PlaneF32, RadTan, Se3};
use duv_track::ba::{
    huber_weight, reproject, solve_motion_only, BaCapacity, BaConfig, BaError, BaWorkspace, Capacity, MotionOnlyObservation, Termination,
};
use nalgebra::{DMatrix, DVector, Vector2, Vector6};

/// Central differences vs analytic Jacobians, relative to the Jacobian's largest entry.
const JACOBIAN_REL_TOL: f64 = 1e-6;
/// Schur increments vs the dense solve, relative to the largest dense increment.
const SCHUR_VS_DENSE_TOL: f64 = 1e-8;
/// Covariances vs the dense inverse of the full Hessian, relative.
const COVARIANCE_REL_TOL: f64 = 1e-6;
/// Convergence on clean data: position (m), rotation (deg), RMS relative depth error.
const POSITION_TOL_M: f64 = 1e-3;
const ROTATION_TOL_DEG: f64 = 0.05;
const DEPTH_RMS_REL_TOL: f64 = 0.01;
/// With 20% outliers under Huber weighting. Depths by median and 90th percentile: a pixel
/// seen twice, once through a gross outlier on the longer baseline, has its Huber optimum at
/// the outlier (the estimator's breakdown, not the solver's), so RMS and max mean little.
const OUTLIER_POSITION_TOL_M: f64 = 2e-3;
const OUTLIER_ROTATION_TOL_DEG: f64 = 0.1;
const OUTLIER_DEPTH_MEDIAN_REL_TOL: f64 = 0.01;
const OUTLIER_DEPTH_P90_REL_TOL: f64 = 0.02;

fn random_pose(rng: &mut Rng, trans: f64, rot: f64) -> Se3 {
    let xi = Vector6::new(
        rng.range(-trans, trans),
        rng.range(-trans, trans),
        rng.range(-trans, trans),
        rng.range(-rot, rot),
        rng.range(-rot, rot),
        rng.range(-rot, rot),
    );
    se3_exp(&xi)
}

fn unit(k: usize) -> Vector6<f64> {
    let mut e = Vector6::zeros();
    e[k] = 1.0;
    e
}

#[test]
fn jacobians_match_central_differences() {
    let camera = PinholeCamera::new(31.0, 29.5, 19.3, 14.8, 40, 30).unwrap();
    let mut rng = Rng::new(11);
    let h = 1e-6;
    let mut checked = 0;
    let mut worst: f64 = 0.0;
    for _ in 0..200 {
        let world_from_i = random_pose(&mut rng, 1.0, 0.5);
        let world_from_j = world_from_i * random_pose(&mut rng, 0.4, 0.3);
        let uv = Vector2::new(rng.range(0.0, 39.0), rng.range(0.0, 29.0));
        let d = rng.range(0.05, 2.0);
        let predict = |wi: &Se3, wj: &Se3, d: f64| reproject(&camera, uv, d, &wj.inv_mul(wi)).map(|r| r.uv);
        let Some(rp) = reproject(&camera, uv, d, &world_from_j.inv_mul(&world_from_i)) else { continue };
        // Skip configurations too close to the validity limit for differences to be clean.
        if (world_from_j.inv_mul(&world_from_i) * nalgebra::Point3::from(camera.unproject(&uv).unwrap() / d)).z * d < 0.2 {
            continue;
        }
        let scale_i = rp.d_uv_d_pose_i.abs().max().max(1e-3);
        let scale_j = rp.d_uv_d_pose_j.abs().max().max(1e-3);
        for k in 0..6 {
            let step = unit(k) * h;
            let num_i = (predict(&(world_from_i * se3_exp(&step)), &world_from_j, d).unwrap()
                - predict(&(world_from_i * se3_exp(&-step)), &world_from_j, d).unwrap())
                / (2.0 * h);
            let err_i = (num_i - rp.d_uv_d_pose_i.column(k)).abs().max() / scale_i;
            assert!(err_i < JACOBIAN_REL_TOL, "pose i column {k}: {err_i:e}");
            worst = worst.max(err_i);
            let num_j = (predict(&world_from_i, &(world_from_j * se3_exp(&step)), d).unwrap()
                - predict(&world_from_i, &(world_from_j * se3_exp(&-step)), d).unwrap())
                / (2.0 * h);
            let err_j = (num_j - rp.d_uv_d_pose_j.column(k)).abs().max() / scale_j;
            assert!(err_j < JACOBIAN_REL_TOL, "pose j column {k}: {err_j:e}");
            worst = worst.max(err_j);
        }
        let hd = 1e-7 * d.max(1e-2);
        let num_d = (predict(&world_from_i, &world_from_j, d + hd).unwrap() - predict(&world_from_i, &world_from_j, d - hd).unwrap()) / (2.0 * hd);
        let err_d = (num_d - rp.d_uv_d_inv_depth).abs().max() / rp.d_uv_d_inv_depth.abs().max().max(1e-3);
        assert!(err_d < JACOBIAN_REL_TOL, "depth: {err_d:e}");
        worst = worst.max(err_d);
        checked += 1;
    }
    println!("Jacobians: {checked} configurations, worst relative error {worst:.2e}");
    assert!(checked > 150, "only {checked} configurations checked");
}

/// A loaded small window with its exact f64 state, for the dense comparisons.
struct Small {
    ws: BaWorkspace,
    scene: Scene,
    targets: Vec<(Image<f32, 2>, Image<f32, 2>)>,
    /// The inverse depth maps as loaded (the prior's anchors).
    anchors: Vec<PlaneF32>,
}

/// 3 keyframes, 6x5 depth maps, 5 edges; poses and depths perturbed, targets noisy with a
/// few outliers so some Huber weights are below 1.
fn small_window() -> Small {
    small_window_freezing(None)
}

/// As [`small_window`]; `frozen` zeroes every weight of that pixel of keyframe 0, so with no
/// depth prior its depth has no information at all.
fn small_window_freezing(frozen: Option<usize>) -> Small {
    let scene = Scene::new(3, 6, 5, 2);
    let mut rng = Rng::new(5);
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 4, max_pixels_per_keyframe: 30, max_edges: 8 });
    ws.begin(&scene.camera).unwrap();
    let mut anchors = Vec::new();
    for k in 0..3 {
        let pose = if k == 0 { scene.world_from_cam[0] } else { perturb(&scene.world_from_cam[k], 0.01, 0.01, &mut rng) };
        anchors.push(scene.perturbed_inv_depth(k, 0.05, &mut rng));
        ws.add_keyframe(&pose, &anchors[k]).unwrap();
    }
    let mut targets = Vec::new();
    for &(i, j) in scene.edges.iter().take(5) {
        let (t, mut w) = scene.measurements(i, j, 0.05, 0.1, &mut rng);
        if let (Some(p), 0) = (frozen, i) {
            w.data[2 * p] = 0.0;
            w.data[2 * p + 1] = 0.0;
        }
        ws.add_edge(i, j, &t, &w).unwrap();
        targets.push((t, w));
    }
    Small { ws, scene, targets, anchors }
}

/// The full normal equations (poses of keyframes >= fixed, then every depth), built row by
/// row from explicit residual Jacobians: returns (H, b) undamped.
fn dense_normal_equations(s: &Small, config: &BaConfig) -> (DMatrix<f64>, DVector<f64>) {
    let (n_kf, n_pix) = (s.ws.num_keyframes(), s.scene.n_pixels());
    let fixed = config.fixed_poses;
    let n_free = n_kf - fixed;
    let dim = 6 * n_free + n_kf * n_pix;
    let mut h = DMatrix::<f64>::zeros(dim, dim);
    let mut b = DVector::<f64>::zeros(dim);
    let poses: Vec<Se3> = (0..n_kf).map(|k| s.ws.world_from_cam(k).unwrap()).collect();
    let w = s.scene.camera.width;
    for (e, &(i, j)) in s.scene.edges.iter().take(s.targets.len()).enumerate() {
        let (target, weight) = &s.targets[e];
        let depth = s.ws.inv_depth(i).unwrap();
        for p in 0..n_pix {
            let (wx, wy) = (weight.data[2 * p] as f64, weight.data[2 * p + 1] as f64);
            if wx == 0.0 && wy == 0.0 {
                continue;
            }
            let uv = Vector2::new((p % w) as f64, (p / w) as f64);
            let Some(rp) = reproject(&s.scene.camera, uv, depth[p], &poses[j].inv_mul(&poses[i])) else { continue };
            let r = Vector2::new(target.data[2 * p] as f64 - rp.uv.x, target.data[2 * p + 1] as f64 - rp.uv.y);
            let rw = huber_weight((wx * r.x * r.x + wy * r.y * r.y).sqrt(), config.huber_threshold);
            for (axis, wa) in [(0, rw * wx), (1, rw * wy)] {
                let mut row = DVector::<f64>::zeros(dim);
                if i >= fixed {
                    for c in 0..6 {
                        row[6 * (i - fixed) + c] = rp.d_uv_d_pose_i[(axis, c)];
                    }
                }
                if j >= fixed {
                    for c in 0..6 {
                        row[6 * (j - fixed) + c] = rp.d_uv_d_pose_j[(axis, c)];
                    }
                }
                row[6 * n_free + i * n_pix + p] = rp.d_uv_d_inv_depth[axis];
                h += &row * row.transpose() * wa;
                b += &row * (wa * r[axis]);
            }
        }
    }
    // Depth prior anchored at the loaded values.
    for k in 0..n_kf {
        for (p, (d, d0)) in s.ws.inv_depth(k).unwrap().iter().zip(&s.anchors[k].data).enumerate() {
            let q = 6 * n_free + k * n_pix + p;
            h[(q, q)] += config.depth_prior_weight;
            b[q] += config.depth_prior_weight * (*d0 as f64 - d);
        }
    }
    (h, b)
}

#[test]
fn schur_step_matches_dense_solve() {
    for fixed_poses in [1, 2] {
        for damping in [0.0, 1e-3] {
            let mut s = small_window();
            let config = BaConfig { fixed_poses, huber_threshold: 2.0, depth_prior_weight: 1e-2, ..BaConfig::default() };
            // Move the state away from the loaded one so the prior has a gradient too.
            s.ws.solve(&BaConfig { max_iterations: 1, ..config }).unwrap();
            s.ws.compute_step(&config, damping).unwrap();
            let (mut h, b) = dense_normal_equations(&s, &config);
            for q in 0..h.nrows() {
                h[(q, q)] *= 1.0 + damping;
            }
            let x = h.clone().cholesky().expect("dense H positive definite").solve(&b);
            let n_free = 3 - fixed_poses;
            let scale = x.amax().max(1e-12);
            let mut worst: f64 = 0.0;
            for k in fixed_poses..3 {
                let step = s.ws.step_pose(k).unwrap();
                for c in 0..6 {
                    worst = worst.max((step[c] - x[6 * (k - fixed_poses) + c]).abs());
                }
            }
            for k in 0..3 {
                for (p, dd) in s.ws.step_inv_depth(k).unwrap().iter().enumerate() {
                    worst = worst.max((dd - x[6 * n_free + k * 30 + p]).abs());
                }
            }
            assert!(s.ws.step_pose(0).is_none());
            println!("Schur vs dense, fixed {fixed_poses}, damping {damping}: relative error {:.2e}", worst / scale);
            assert!(worst / scale < SCHUR_VS_DENSE_TOL, "fixed {fixed_poses} damping {damping}: {:e} (step scale {scale:e})", worst / scale);
        }
    }
}

#[test]
fn uninformed_pixels_are_frozen() {
    // No depth prior, scale fixed by two fixed poses: a pixel without measurements has
    // H_dd = 0, gets no step, no Schur contribution, and infinite variance; the rest of the
    // step still equals the dense solve with that pixel's (all-zero) row and column removed.
    let frozen = 7;
    let mut s = small_window_freezing(Some(frozen));
    let config = BaConfig { fixed_poses: 2, huber_threshold: 2.0, depth_prior_weight: 0.0, ..BaConfig::default() };
    s.ws.compute_step(&config, 1e-3).unwrap();
    assert_eq!(s.ws.step_inv_depth(0).unwrap()[frozen], 0.0);
    let (mut h, b) = dense_normal_equations(&s, &config);
    let q = 6 + frozen;
    assert!(h.row(q).iter().all(|v| *v == 0.0));
    for r in 0..h.nrows() {
        h[(r, r)] *= 1.0 + 1e-3;
    }
    let h = h.remove_row(q).remove_column(q);
    let x = h.cholesky().unwrap().solve(&b.remove_row(q));
    let step = s.ws.step_pose(2).unwrap();
    let mut worst: f64 = (0..6).map(|c| (step[c] - x[c]).abs()).fold(0.0, f64::max);
    for k in 0..3 {
        for (p, dd) in s.ws.step_inv_depth(k).unwrap().iter().enumerate() {
            let full = 6 + k * 30 + p;
            if full != q {
                worst = worst.max((dd - x[if full > q { full - 1 } else { full }]).abs());
            }
        }
    }
    assert!(worst / x.amax() < SCHUR_VS_DENSE_TOL, "{:e}", worst / x.amax());
    s.ws.solve(&config).unwrap();
    s.ws.compute_covariance(&config).unwrap();
    let var = s.ws.inv_depth_variance(0).unwrap();
    assert!(var[frozen].is_infinite() && var.iter().enumerate().all(|(p, v)| p == frozen || v.is_finite()));
}

#[test]
fn covariance_matches_dense_inverse() {
    for fixed_poses in [1, 2] {
        let mut s = small_window();
        let config = BaConfig { fixed_poses, huber_threshold: 2.0, depth_prior_weight: 1e-2, ..BaConfig::default() };
        s.ws.solve(&config).unwrap();
        s.ws.compute_covariance(&config).unwrap();
        let (h, _) = dense_normal_equations(&s, &config);
        let inv = h.clone().cholesky().expect("dense H positive definite").inverse();
        let n_free = 3 - fixed_poses;
        let pose_scale = inv.view((0, 0), (6 * n_free, 6 * n_free)).amax();
        for a in fixed_poses..3 {
            for b in fixed_poses..3 {
                let block = s.ws.pose_cross_covariance(a, b).unwrap();
                let dense = inv.view((6 * (a - fixed_poses), 6 * (b - fixed_poses)), (6, 6));
                let err = (block - dense).abs().max() / pose_scale;
                assert!(err < COVARIANCE_REL_TOL, "fixed {fixed_poses}: pose block ({a},{b}) relative error {err:e}");
                println!("covariance, fixed {fixed_poses}: pose block ({a},{b}) relative error {err:.2e}");
            }
        }
        assert!(s.ws.pose_covariance(0).is_none());
        let mut worst: f64 = 0.0;
        for k in 0..3 {
            for (p, v) in s.ws.inv_depth_variance(k).unwrap().iter().enumerate() {
                let q = 6 * n_free + k * 30 + p;
                worst = worst.max((v - inv[(q, q)]).abs() / inv[(q, q)]);
            }
        }
        assert!(worst < COVARIANCE_REL_TOL, "fixed {fixed_poses}: depth variance relative error {worst:e}");
        println!("covariance, fixed {fixed_poses}: depth variance relative error {worst:.2e}");
    }
}

struct Errors {
    position_m: f64,
    rotation_deg: f64,
    depth_rms_rel: f64,
    depth_median_rel: f64,
    depth_p90_rel: f64,
    depth_max_rel: f64,
    scale: f64,
}

/// Errors after the gauge: keyframe 0 is fixed at the truth; with one fixed pose the
/// remaining free direction (scale about camera 0) is aligned by least squares first.
/// Depth errors cover pixels seen in at least `min_views` edges.
fn errors_after_gauge(ws: &BaWorkspace, scene: &Scene, views: &[Vec<usize>], min_views: usize, align_scale: bool) -> Errors {
    let n = scene.world_from_cam.len();
    let c0 = scene.world_from_cam[0].translation.vector;
    let (mut num, mut den) = (0.0, 0.0);
    for k in 1..n {
        let est = ws.world_from_cam(k).unwrap().translation.vector - c0;
        let gt = scene.world_from_cam[k].translation.vector - c0;
        num += est.dot(&gt);
        den += est.dot(&est);
    }
    let scale = if align_scale { num / den } else { 1.0 };
    let mut e = Errors { position_m: 0.0, rotation_deg: 0.0, depth_rms_rel: 0.0, depth_median_rel: 0.0, depth_p90_rel: 0.0, depth_max_rel: 0.0, scale };
    let mut rels = Vec::new();
    for (k, views) in views.iter().enumerate() {
        let est = ws.world_from_cam(k).unwrap();
        let pos = c0 + (est.translation.vector - c0) * scale;
        e.position_m = e.position_m.max((pos - scene.world_from_cam[k].translation.vector).norm());
        e.rotation_deg = e.rotation_deg.max(est.rotation.angle_to(&scene.world_from_cam[k].rotation).to_degrees());
        for (p, d) in ws.inv_depth(k).unwrap().iter().enumerate() {
            if views[p] < min_views {
                continue;
            }
            let depth_est = scale / d;
            let depth_gt = 1.0 / scene.inv_depth[k][p];
            rels.push((depth_est - depth_gt).abs() / depth_gt);
        }
    }
    rels.sort_by(f64::total_cmp);
    e.depth_rms_rel = (rels.iter().map(|r| r * r).sum::<f64>() / rels.len() as f64).sqrt();
    e.depth_median_rel = rels[rels.len() / 2];
    e.depth_p90_rel = rels[rels.len() * 9 / 10];
    e.depth_max_rel = rels[rels.len() - 1];
    e
}

/// 5 keyframes, 40x30 depth, every ordered pair an edge (20); poses perturbed by ~2 cm / 1
/// degree, depths by 10%; targets with 0.02 px noise (weights 1/sigma^2) and a fraction of
/// 1-5 px outliers. Depth errors cover every pixel seen in at least one edge.
fn converge(outliers: f64, fixed_poses: usize, huber_threshold: f64, seed: u64) -> (Errors, Termination) {
    let scene = Scene::new(5, 40, 30, 4);
    let mut rng = Rng::new(seed);
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 5, max_pixels_per_keyframe: 1200, max_edges: 20 });
    ws.begin(&scene.camera).unwrap();
    for k in 0..5 {
        let pose = if k < fixed_poses { scene.world_from_cam[k] } else { perturb(&scene.world_from_cam[k], 0.02, 1f64.to_radians(), &mut rng) };
        ws.add_keyframe(&pose, &scene.perturbed_inv_depth(k, 0.1, &mut rng)).unwrap();
    }
    let mut views = vec![vec![0; scene.n_pixels()]; 5];
    for &(i, j) in &scene.edges {
        let (t, w) = scene.measurements(i, j, 0.02, outliers, &mut rng);
        for (v, wp) in views[i].iter_mut().zip(w.data.chunks_exact(2)) {
            *v += (wp[0] > 0.0) as usize;
        }
        ws.add_edge(i, j, &t, &w).unwrap();
    }
    let config = BaConfig { fixed_poses, huber_threshold, max_iterations: 30, ..BaConfig::default() };
    let report = ws.solve(&config).unwrap();
    assert!(report.final_cost < report.initial_cost);
    (errors_after_gauge(&ws, &scene, &views, 1, fixed_poses == 1), report.termination)
}

#[test]
fn converges_on_synthetic_scene() {
    for fixed_poses in [1, 2] {
        let (e, termination) = converge(0.0, fixed_poses, 3.0, 21);
        println!(
            "clean, fixed {fixed_poses}: position {:.3} mm, rotation {:.4} deg, depth rms {:.3}% median {:.3}% max {:.3}%, scale {:.5}, {termination:?}",
            e.position_m * 1e3,
            e.rotation_deg,
            e.depth_rms_rel * 100.0,
            e.depth_median_rel * 100.0,
            e.depth_max_rel * 100.0,
            e.scale
        );
        assert!(e.position_m < POSITION_TOL_M && e.rotation_deg < ROTATION_TOL_DEG && e.depth_rms_rel < DEPTH_RMS_REL_TOL);
    }
}

/// Solves the 5-keyframe scene with flow noise `noise_px` and every weight multiplied by
/// `weight_gain` (1: exact inverse variances), no outliers and no Huber down-weighting;
/// returns the unit variance and keyframe 4's inverse-depth variances.
fn unit_variance_run(noise_px: f64, weight_gain: f32) -> (f64, Vec<f64>) {
    let scene = Scene::new(5, 40, 30, 4);
    let mut rng = Rng::new(33);
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 5, max_pixels_per_keyframe: 1200, max_edges: 20 });
    ws.begin(&scene.camera).unwrap();
    for k in 0..5 {
        let pose = if k < 2 { scene.world_from_cam[k] } else { perturb(&scene.world_from_cam[k], 0.01, 0.5f64.to_radians(), &mut rng) };
        ws.add_keyframe(&pose, &scene.perturbed_inv_depth(k, 0.05, &mut rng)).unwrap();
    }
    for &(i, j) in &scene.edges {
        let (t, mut w) = scene.measurements(i, j, noise_px, 0.0, &mut rng);
        w.data.iter_mut().for_each(|x| *x *= weight_gain);
        ws.add_edge(i, j, &t, &w).unwrap();
    }
    let config = BaConfig { fixed_poses: 2, huber_threshold: 1e6, depth_prior_weight: 0.0, max_iterations: 30, ..BaConfig::default() };
    ws.solve(&config).unwrap();
    assert!(ws.unit_variance().is_none(), "no unit variance before a covariance");
    ws.compute_covariance(&config).unwrap();
    let unit = ws.unit_variance().expect("the window is redundant");
    (unit, ws.inv_depth_variance(4).unwrap().to_vec())
}

#[test]
fn unit_variance_measures_the_flow_noise() {
    // Weights that are exact inverse variances: the variance of unit weight is near 1 (the
    // residuals' chi-square over their redundancy).
    let (unit, var) = unit_variance_run(0.05, 1.0);
    println!("unit variance with exact weights: {unit:.4}");
    assert!((0.85..1.15).contains(&unit), "unit variance {unit}");
    // Weights that are relative confidences (all 1/400 of the truth): the unit variance is
    // 1/400 of before, and the covariance scaled by it is the calibrated one again.
    let (unit_rel, var_rel) = unit_variance_run(0.05, 1.0 / 400.0);
    println!("unit variance with weights 1/400 of the truth: {unit_rel:.3e}");
    assert!((unit_rel * 400.0 / unit - 1.0).abs() < 0.01, "unit variance {unit_rel} against {unit}/400");
    let mut worst: f64 = 0.0;
    for (&a, &b) in var.iter().zip(&var_rel) {
        if a.is_finite() && a > 0.0 {
            worst = worst.max((b * unit_rel - a * unit).abs() / (a * unit));
        }
    }
    println!("scaled variances, relative difference: {worst:.2e}");
    assert!(worst < 0.01, "scaled variances differ by {worst}");
    // Twice the noise the weights assume: four times the unit variance.
    let (unit_2, _) = unit_variance_run(0.1, 4.0);
    println!("noise 0.1 px, weights for 0.05 px: unit variance {unit_2:.4}");
    assert!((unit_2 / (4.0 * unit) - 1.0).abs() < 0.15, "noise 0.1 px with weights for 0.05 px: unit variance {unit_2} against 4 x {unit}");
}

#[test]
fn converges_with_outliers_under_huber() {
    let report = |name: &str, e: &Errors, termination: Termination| {
        println!(
            "{name}: position {:.3} mm, rotation {:.4} deg, depth median {:.3}% p90 {:.3}% rms {:.3}%, scale {:.5}, {termination:?}",
            e.position_m * 1e3,
            e.rotation_deg,
            e.depth_median_rel * 100.0,
            e.depth_p90_rel * 100.0,
            e.depth_rms_rel * 100.0,
            e.scale
        )
    };
    let (e, termination) = converge(0.2, 1, 3.0, 22);
    report("20% outliers, Huber at 3 sigma", &e, termination);
    assert!(e.position_m < OUTLIER_POSITION_TOL_M && e.rotation_deg < OUTLIER_ROTATION_TOL_DEG);
    assert!(e.depth_median_rel < OUTLIER_DEPTH_MEDIAN_REL_TOL && e.depth_p90_rel < OUTLIER_DEPTH_P90_REL_TOL);
    // Plain least squares on the same data is far worse: the robust weights do the work.
    let (l2, termination) = converge(0.2, 1, 1e12, 22);
    report("20% outliers, least squares", &l2, termination);
    assert!(l2.position_m > 5.0 * e.position_m && l2.depth_median_rel > 5.0 * e.depth_median_rel);
}

#[test]
fn motion_only_recovers_perturbed_pose() {
    let scene = Scene::new(5, 40, 30, 4);
    let mut rng = Rng::new(31);
    let frame = 4;
    let depths: Vec<PlaneF32> = (0..3).map(|k| scene.inv_depth_plane(k)).collect();
    let meas: Vec<_> = (0..3).map(|k| scene.measurements(k, frame, 0.02, 0.0, &mut rng)).collect();
    let observations: Vec<MotionOnlyObservation<'_>> = (0..3)
        .map(|k| MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[k], inv_depth: &depths[k], target_xy: &meas[k].0, weight_xy: &meas[k].1, inv_depth_variance: None, variance_of_unit_weight: 1.0 })
        .collect();
    let truth = scene.world_from_cam[frame];
    let mut pose = truth * se3_exp(&Vector6::new(0.03, -0.02, 0.025, 0.02, -0.03, 0.015));
    let config = BaConfig { huber_threshold: 3.0, max_iterations: 20, ..BaConfig::default() };
    let report = solve_motion_only(&scene.camera, &observations, &mut pose, &config).unwrap();
    let pos_err = (pose.translation.vector - truth.translation.vector).norm();
    let rot_err = pose.rotation.angle_to(&truth.rotation).to_degrees();
    println!("motion-only: {pos_err:.2e} m, {rot_err:.2e} deg, {report:?}");
    assert!(pos_err < POSITION_TOL_M && rot_err < ROTATION_TOL_DEG);
    assert!(report.covariance.diagonal().iter().all(|v| *v > 0.0 && v.is_finite()));
}

/// A keyframe whose top quarter carries wrong inverse depths (the truth times `1 + 0.3 N(0,
/// 1)`, kept positive: what the depth prior alone holds where no edge measured it) with the
/// variance that says so, the rest exact with a small one. The frame's flow is
/// right everywhere, so without the variance the wrong depths pull the pose; with it their
/// weights shrink to what their depth error allows.
#[test]
fn motion_only_discounts_pixels_whose_depth_is_uncertain() {
    let scene = Scene::new(5, 40, 30, 4);
    let mut rng = Rng::new(32);
    let frame = 3;
    let (w, h) = (scene.camera.width, scene.camera.height);
    let (target, weight) = scene.measurements(0, frame, 0.02, 0.0, &mut rng);
    let mut depth = scene.inv_depth_plane(0);
    let mut variance = PlaneF32::new(w, h);
    for p in 0..w * h {
        let d = depth.data[p];
        if p / w < h / 4 {
            depth.data[p] = d * (1.0 + 0.3 * rng.normal()).max(0.1) as f32;
            variance.data[p] = (0.3 * d) * (0.3 * d);
        } else {
            variance.data[p] = (1e-3 * d) * (1e-3 * d);
        }
    }
    let truth = scene.world_from_cam[frame];
    let start = truth * se3_exp(&Vector6::new(0.02, -0.01, 0.015, 0.01, -0.02, 0.01));
    let config = BaConfig { huber_threshold: 3.0, max_iterations: 30, ..BaConfig::default() };
    let solve = |var: Option<&PlaneF32>, wt: &Image<f32, 2>| {
        let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &target, weight_xy: wt, inv_depth_variance: var, variance_of_unit_weight: 1.0 }];
        let mut pose = start;
        solve_motion_only(&scene.camera, &obs, &mut pose, &config).unwrap();
        pose
    };
    let error = |pose: &Se3| ((pose.translation.vector - truth.translation.vector).norm(), pose.rotation.angle_to(&truth.rotation).to_degrees());
    let (plain_m, plain_deg) = error(&solve(None, &weight));
    let (with_m, with_deg) = error(&solve(Some(&variance), &weight));
    let mut cut = weight.clone();
    for p in 0..w * h / 4 {
        cut.data[2 * p] = 0.0;
        cut.data[2 * p + 1] = 0.0;
    }
    let (cut_m, cut_deg) = error(&solve(None, &cut));
    println!("wrong top quarter: without the variance {plain_m:.2e} m {plain_deg:.3} deg, with it {with_m:.2e} m {with_deg:.3} deg, cut {cut_m:.2e} m {cut_deg:.3} deg");
    // Measured: 7.2 mm / 0.179 deg without, 3.1 mm / 0.086 deg with, 0.35 mm cut. The deflated
    // weights keep a little of the wrong pixels (their variance is a first-order bound, the
    // depth errors are up to 90 %), so the variance at least halves the error and cutting the
    // wrong pixels outright stays the best case.
    assert!(with_m < 0.5 * plain_m && with_deg < 0.5 * plain_deg, "with {with_m} m {with_deg} deg, without {plain_m} m {plain_deg} deg");
    assert!(cut_m < with_m && cut_m < POSITION_TOL_M && cut_deg < ROTATION_TOL_DEG, "cut {cut_m} m {cut_deg} deg");
    // A zero variance is an exact depth: the same solve as none, to the bit.
    let zero = PlaneF32::new(w, h);
    assert_eq!(solve(Some(&zero), &weight), solve(None, &weight));
    // An unknown depth (f32::MAX) takes the pixel out, as a zero weight does.
    let mut unknown = zero.clone();
    for p in 0..w * h / 4 {
        unknown.data[p] = f32::MAX;
    }
    assert_eq!(solve(Some(&unknown), &weight), solve(None, &cut));
    // Bad variances are errors that name the keyframe and pixel.
    let mut bad = zero.clone();
    bad.data[7] = f32::NAN;
    let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &target, weight_xy: &weight, inv_depth_variance: Some(&bad), variance_of_unit_weight: 1.0 }];
    let mut pose = start;
    assert!(matches!(solve_motion_only(&scene.camera, &obs, &mut pose, &config), Err(BaError::BadVariance { keyframe: 0, pixel: 7, .. })));
    let small = PlaneF32::new(w - 1, h);
    let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &target, weight_xy: &weight, inv_depth_variance: Some(&small), variance_of_unit_weight: 1.0 }];
    assert!(matches!(solve_motion_only(&scene.camera, &obs, &mut pose, &config), Err(BaError::VarianceSizeMismatch { keyframe: 0, .. })));
    let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &target, weight_xy: &weight, inv_depth_variance: Some(&zero), variance_of_unit_weight: 0.0 }];
    assert!(matches!(solve_motion_only(&scene.camera, &obs, &mut pose, &config), Err(BaError::BadVarianceOfUnitWeight { keyframe: 0, .. })));
}

#[test]
fn depth_only_window_when_every_pose_is_fixed() {
    // fixed_poses >= keyframes: an empty reduced system, depths still solved (and no faer call).
    let scene = Scene::new(3, 20, 15, 2);
    let mut rng = Rng::new(4);
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 3, max_pixels_per_keyframe: 300, max_edges: 6 });
    ws.begin(&scene.camera).unwrap();
    for k in 0..3 {
        ws.add_keyframe(&scene.world_from_cam[k], &scene.perturbed_inv_depth(k, 0.1, &mut rng)).unwrap();
    }
    for &(i, j) in &scene.edges {
        let (t, w) = scene.measurements(i, j, 0.0, 0.0, &mut rng);
        ws.add_edge(i, j, &t, &w).unwrap();
    }
    let config = BaConfig { fixed_poses: 3, max_iterations: 20, ..BaConfig::default() };
    ws.solve(&config).unwrap();
    let mut worst: f64 = 0.0;
    for k in 0..3 {
        assert_eq!(ws.world_from_cam(k), Some(scene.world_from_cam[k]));
        for (d, gt) in ws.inv_depth(k).unwrap().iter().zip(&scene.inv_depth[k]) {
            worst = worst.max((d / gt - 1.0).abs());
        }
    }
    assert!(worst < 1e-4, "noise-free depths off by {worst:e}");
    ws.compute_covariance(&config).unwrap();
    assert!(ws.pose_covariance(1).is_none() && ws.inv_depth_variance(0).unwrap().iter().all(|v| *v > 0.0));
}

#[test]
fn workspace_can_move_to_the_tracking_thread() {
    fn assert_send<T: Send>() {}
    assert_send::<BaWorkspace>();
}

#[test]
fn bad_inputs_return_errors() {
    let scene = Scene::new(2, 8, 6, 1);
    let cap = BaCapacity { max_keyframes: 2, max_pixels_per_keyframe: 48, max_edges: 2 };
    let mut rng = Rng::new(1);
    let (t, w) = scene.measurements(0, 1, 0.1, 0.0, &mut rng);
    let depth = scene.inv_depth_plane(0);
    let mut ws = BaWorkspace::new(cap);
    let config = BaConfig::default();

    assert_eq!(ws.add_keyframe(&Se3::identity(), &depth), Err(BaError::NotStarted));
    assert_eq!(ws.solve(&config), Err(BaError::NotStarted));
    ws.begin(&scene.camera).unwrap();
    assert_eq!(ws.solve(&config), Err(BaError::EmptyWindow));
    ws.add_keyframe(&scene.world_from_cam[0], &depth).unwrap();
    assert_eq!(ws.add_edge(0, 1, &t, &w), Err(BaError::EdgeToMissingKeyframe { edge: 0, from: 0, to: 1, keyframes: 1 }));
    assert_eq!(ws.add_edge(0, 0, &t, &w), Err(BaError::SelfEdge { edge: 0, keyframe: 0 }));
    assert_eq!(ws.solve(&config), Err(BaError::NoEdges));

    // Bad depth values and sizes.
    let mut nan_depth = depth.clone();
    nan_depth.data[7] = f32::NAN;
    assert!(matches!(ws.add_keyframe(&scene.world_from_cam[1], &nan_depth), Err(BaError::BadInverseDepth { keyframe: 1, pixel: 7, .. })));
    nan_depth.data[7] = -1.0;
    assert!(matches!(ws.add_keyframe(&scene.world_from_cam[1], &nan_depth), Err(BaError::BadInverseDepth { keyframe: 1, pixel: 7, .. })));
    assert!(matches!(ws.add_keyframe(&scene.world_from_cam[1], &PlaneF32::new(4, 4)), Err(BaError::DepthSizeMismatch { keyframe: 1, .. })));
    let mut nan_pose = scene.world_from_cam[1];
    nan_pose.translation.vector.x = f64::NAN;
    assert_eq!(ws.add_keyframe(&nan_pose, &depth), Err(BaError::NonFinitePose { keyframe: 1 }));

    ws.add_keyframe(&scene.world_from_cam[1], &scene.inv_depth_plane(1)).unwrap();
    assert_eq!(
        ws.add_keyframe(&scene.world_from_cam[1], &depth),
        Err(BaError::CapacityExceeded { capacity: Capacity::Keyframes, limit: 2, requested: 3 })
    );
    // A free pose without edges cannot be solved.
    ws.add_edge(1, 0, &t, &w).unwrap();
    let mut ws2 = BaWorkspace::new(BaCapacity { max_keyframes: 3, ..cap });
    ws2.begin(&scene.camera).unwrap();
    for k in 0..2 {
        ws2.add_keyframe(&scene.world_from_cam[k], &scene.inv_depth_plane(k)).unwrap();
    }
    ws2.add_keyframe(&scene.world_from_cam[1], &scene.inv_depth_plane(1)).unwrap();
    ws2.add_edge(0, 1, &t, &w).unwrap();
    assert_eq!(ws2.solve(&config), Err(BaError::UnconstrainedPose { keyframe: 2 }));

    // Bad measurements.
    let mut nan_t = t.clone();
    nan_t.data[2 * 5 + 1] = f32::NAN;
    assert!(matches!(ws.add_edge(0, 1, &nan_t, &w), Err(BaError::NonFiniteTarget { edge: 1, pixel: 5, .. })));
    let mut neg_w = w.clone();
    neg_w.data[2 * 3] = -1.0;
    assert!(matches!(ws.add_edge(0, 1, &t, &neg_w), Err(BaError::BadWeight { edge: 1, pixel: 3, .. })));
    assert!(matches!(ws.add_edge(0, 1, &Image::<f32, 2>::new(3, 3), &w), Err(BaError::MeasurementSizeMismatch { edge: 1, .. })));
    ws.add_edge(0, 1, &t, &w).unwrap();
    assert_eq!(ws.add_edge(0, 1, &t, &w), Err(BaError::CapacityExceeded { capacity: Capacity::Edges, limit: 2, requested: 3 }));

    // Bad config, then a good solve of the same window.
    assert!(matches!(ws.solve(&BaConfig { fixed_poses: 0, ..config }), Err(BaError::InvalidConfig { field: "fixed_poses", .. })));
    assert!(matches!(ws.solve(&BaConfig { huber_threshold: f64::NAN, ..config }), Err(BaError::InvalidConfig { field: "huber_threshold", .. })));
    ws.solve(&config).unwrap();

    // Cameras.
    let big = PinholeCamera::from_hfov(70.0, 16, 12).unwrap();
    assert_eq!(ws.begin(&big), Err(BaError::CapacityExceeded { capacity: Capacity::PixelsPerKeyframe, limit: 48, requested: 192 }));
    let distorted = scene.camera.with_distortion(RadTan { k1: 0.1, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 }).unwrap();
    assert_eq!(ws.begin(&distorted), Err(BaError::DistortedCamera));
    assert_eq!(ws.num_keyframes(), 2, "a failed begin leaves the loaded window as it was");
    assert!(matches!(ws.write_inv_depth(5, &mut PlaneF32::new(8, 6)), Err(BaError::NoSuchKeyframe { keyframe: 5, .. })));

    // Motion-only.
    let mut pose = scene.world_from_cam[1];
    assert_eq!(solve_motion_only(&scene.camera, &[], &mut pose, &config), Err(BaError::NoMeasurements));
    let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &nan_t, weight_xy: &w, inv_depth_variance: None, variance_of_unit_weight: 1.0 }];
    assert!(matches!(solve_motion_only(&scene.camera, &obs, &mut pose, &config), Err(BaError::NonFiniteTarget { edge: 0, pixel: 5, .. })));
    let zero_w = Image::<f32, 2>::new(8, 6);
    let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &t, weight_xy: &zero_w, inv_depth_variance: None, variance_of_unit_weight: 1.0 }];
    assert_eq!(solve_motion_only(&scene.camera, &obs, &mut pose, &config), Err(BaError::NoMeasurements));
    let mut nan_frame = pose;
    nan_frame.rotation = nalgebra::UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(f64::NAN, 0.0, 0.0, 0.0));
    let obs = [MotionOnlyObservation { world_from_keyframe: scene.world_from_cam[0], inv_depth: &depth, target_xy: &t, weight_xy: &w, inv_depth_variance: None, variance_of_unit_weight: 1.0 }];
    assert_eq!(solve_motion_only(&scene.camera, &obs, &mut nan_frame, &config), Err(BaError::NonFiniteFramePose));
}

#[test]
fn variances_shrink_with_observations_and_scale_direction_is_loose() {
    // Sanity of Eq. 4 on the convergence scene: observed pixels are far more certain than the
    // prior alone, and the pose covariance is symmetric positive definite.
    let scene = Scene::new(4, 20, 15, 1);
    let mut rng = Rng::new(3);
    let mut ws = BaWorkspace::new(BaCapacity { max_keyframes: 4, max_pixels_per_keyframe: 300, max_edges: 6 });
    ws.begin(&scene.camera).unwrap();
    for k in 0..4 {
        ws.add_keyframe(&scene.world_from_cam[k], &scene.inv_depth_plane(k)).unwrap();
    }
    for &(i, j) in &scene.edges {
        let (t, w) = scene.measurements(i, j, 0.05, 0.0, &mut rng);
        ws.add_edge(i, j, &t, &w).unwrap();
    }
    let config = BaConfig::default();
    ws.solve(&config).unwrap();
    ws.compute_covariance(&config).unwrap();
    let prior_var = 1.0 / config.depth_prior_weight;
    let var = ws.inv_depth_variance(1).unwrap();
    let median = {
        let mut v = var.to_vec();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    assert!(median < 1e-3 * prior_var, "median inverse-depth variance {median:e}");
    let c = ws.pose_covariance(3).unwrap();
    assert!((c - c.transpose()).abs().max() < 1e-12 * c.abs().max());
    assert!(c.cholesky().is_some());
}

