//! The evaluator against the reference tools: ATE/RPE against evo on the TUM trajectories
//! in ../shared/data/trajectories, PSNR/SSIM against scikit-image and scipy.

use duv_core::{ImageRgbF32, PlaneF32, StampedPose};
use duv_eval::trajectory::{evaluate_trajectory, TrajectoryEvaluation, TrajectoryOptions};
use duv_eval::{psnr, ssim, Alignment, SsimConvention};
use duv_core::io::tum::read_trajectory;
use std::path::Path;

const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/trajectories");

/// Agreement asked for with the README's six-decimal values (metres).
const README_TOL_M: f64 = 1e-5;
/// Agreement with evo's full-precision output (printed with 10 decimals).
const EVO_FULL_TOL: f64 = 1e-9;

fn load(name: &str) -> Vec<StampedPose> {
    read_trajectory(&Path::new(DATA).join(name)).unwrap_or_else(|e| panic!("{e}"))
}

fn run(gt: &str, est: &str, alignment: Alignment) -> TrajectoryEvaluation {
    let opts = TrajectoryOptions { alignment, ..Default::default() };
    evaluate_trajectory(&load(gt), &load(est), &opts, gt, est).unwrap_or_else(|e| panic!("{e}"))
}

fn close(what: &str, got: f64, want: f64, tol: f64) {
    assert!((got - want).abs() <= tol, "{what}: got {got:.10}, want {want:.10} (tolerance {tol:e})");
}

// Reference values: the README table (evo 1.38.1, max diff 0.01 s), and, for the extra digits
// and statistics, evo 1.38.1 from PyPI (numpy 2.4) run as
//   ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
//   est.align(ref, correct_scale=<Sim3?>); APE(translation_part); RPE(translation_part |
//   rotation_angle_deg, delta=1, delta_unit=frames, all_pairs=True)
// and printed with 10 decimals.

#[test]
fn fr1_xyz_orb_keyframes_sim3_matches_evo() {
    let ev = run("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-ORB_kf_mono.txt", Alignment::Sim3);
    let r = &ev.report;
    let a = &r.ate.stats_m;
    close("rmse", a.rmse, 0.009755, README_TOL_M);
    close("mean", a.mean, 0.008219, README_TOL_M);
    close("max", a.max, 0.027924, README_TOL_M);
    assert_eq!(r.associated, 32);
    close("rmse (evo)", a.rmse, 0.0097545819, EVO_FULL_TOL);
    close("mean (evo)", a.mean, 0.0082186986, EVO_FULL_TOL);
    close("median (evo)", a.median, 0.0079090703, EVO_FULL_TOL);
    close("std (evo)", a.std, 0.0052540329, EVO_FULL_TOL);
    close("min (evo)", a.min, 0.0018768481, EVO_FULL_TOL);
    close("max (evo)", a.max, 0.0279240017, EVO_FULL_TOL);
    close("scale (evo)", r.alignment.scale, 1.105622363737, 1e-11);
    close("gt path total (evo)", r.gt_path_length_total_m, 9.1592678773, EVO_FULL_TOL);
    let rpe = r.rpe.as_ref().unwrap();
    close("rpe trans rmse (evo)", rpe.translation_m.rmse, 0.0138349178, EVO_FULL_TOL);
    close("rpe rot mean deg (evo)", rpe.rotation_deg.mean, 0.7877250571, 1e-8);
}

#[test]
fn fr1_xyz_rgbdslam_se3_matches_evo_ate_and_rpe() {
    let ev = run("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", Alignment::Se3);
    let r = &ev.report;
    let a = &r.ate.stats_m;
    close("rmse", a.rmse, 0.013470, README_TOL_M);
    close("mean", a.mean, 0.012024, README_TOL_M);
    close("max", a.max, 0.034760, README_TOL_M);
    assert_eq!(r.associated, 785);
    assert_eq!(r.alignment.scale, 1.0);
    close("rmse (evo)", a.rmse, 0.0134700888, EVO_FULL_TOL);
    close("median (evo)", a.median, 0.0111831868, EVO_FULL_TOL);
    close("max (evo)", a.max, 0.0347595459, EVO_FULL_TOL);
    let rpe = r.rpe.as_ref().unwrap();
    assert_eq!((rpe.delta_frames, rpe.translation_m.count), (1, 784));
    close("rpe mean", rpe.translation_m.mean, 0.004816, README_TOL_M);
    close("rpe rmse", rpe.translation_m.rmse, 0.005764, README_TOL_M);
    close("rpe mean (evo)", rpe.translation_m.mean, 0.0048156095, EVO_FULL_TOL);
    close("rpe rmse (evo)", rpe.translation_m.rmse, 0.0057643708, EVO_FULL_TOL);
    close("rpe max (evo)", rpe.translation_m.max, 0.0208658145, EVO_FULL_TOL);
    close("rpe rot rmse deg (evo)", rpe.rotation_deg.rmse, 0.3536131610, 1e-8);
    close("rpe rot max deg (evo)", rpe.rotation_deg.max, 1.6332960623, 1e-8);
}

#[test]
fn fr1_xyz_rgbdslam_rpe_delta_3_both_pair_modes_match_evo() {
    let gt = load("freiburg1_xyz-groundtruth.txt");
    let est = load("freiburg1_xyz-rgbdslam.txt");
    for (all_pairs, rmse, mean) in [(true, 0.0088037928, 0.0072775885), (false, 0.0089213413, 0.0072832997)] {
        let opts = TrajectoryOptions { alignment: Alignment::Se3, rpe_delta_frames: 3, rpe_all_pairs: all_pairs, ..Default::default() };
        let r = evaluate_trajectory(&gt, &est, &opts, "gt", "est").unwrap().report;
        let rpe = r.rpe.unwrap();
        close("rpe d3 rmse (evo)", rpe.translation_m.rmse, rmse, EVO_FULL_TOL);
        close("rpe d3 mean (evo)", rpe.translation_m.mean, mean, EVO_FULL_TOL);
    }
}

#[test]
fn fr2_desk_orb_keyframes_sim3_matches_evo() {
    let ev = run("fr2_desk_groundtruth.txt", "fr2_desk_ORB_kf_mono.txt", Alignment::Sim3);
    let r = &ev.report;
    let a = &r.ate.stats_m;
    close("rmse", a.rmse, 0.007729, README_TOL_M);
    close("mean", a.mean, 0.007104, README_TOL_M);
    close("max", a.max, 0.015689, README_TOL_M);
    assert_eq!(r.associated, 118);
    close("rmse (evo)", a.rmse, 0.0077292648, EVO_FULL_TOL);
    close("mean (evo)", a.mean, 0.0071036160, EVO_FULL_TOL);
    close("max (evo)", a.max, 0.0156885576, EVO_FULL_TOL);
    close("scale (evo)", r.alignment.scale, 2.228021753589, 1e-11);
    close("gt path total (evo)", r.gt_path_length_total_m, 20.3390091222, EVO_FULL_TOL);
    // The evaluated span's full-rate path lies between the associated keyframes' path and
    // the whole file's.
    assert!(r.gt_path_length_m > 15.5732004580 && r.gt_path_length_m <= r.gt_path_length_total_m);
    let pct = r.ate_rmse_percent_of_path.unwrap();
    close("ATE %", pct, 100.0 * a.rmse / r.gt_path_length_m, 1e-12);
}

// ---- PSNR / SSIM against scikit-image ------------------------------------------------------

/// Integer test pattern, reproduced exactly by `pattern_a` in tests/fixtures/ssim_reference.py.
fn pattern_a(x: i64, y: i64, c: i64) -> i64 {
    (x * 5 + y * 7 + c * 40 + ((x * y + 3 * c) % 11) * 9) % 256
}

/// A perturbed copy: per-pixel noise and a block pattern, clipped (`pattern_b` in the script).
fn pattern_b(x: i64, y: i64, c: i64) -> i64 {
    let noise = (x * 31 + y * 17 + c * 7) % 23 - 11;
    let block = if ((x / 6) + (y / 5)) % 2 == 0 { 20 } else { -15 };
    (pattern_a(x, y, c) + noise + block).clamp(0, 255)
}

fn images<const C: usize>(w: usize, h: usize) -> (duv_core::Image<f32, C>, duv_core::Image<f32, C>) {
    let make = |f: fn(i64, i64, i64) -> i64| {
        let mut data = Vec::with_capacity(w * h * C);
        for y in 0..h {
            for x in 0..w {
                for c in 0..C {
                    data.push(f(x as i64, y as i64, c as i64) as f32 / 255.0);
                }
            }
        }
        duv_core::Image::<f32, C>::from_vec(w, h, data).unwrap()
    };
    (make(pattern_a), make(pattern_b))
}

/// Our f64 arithmetic against the same f64 computation in numpy/scipy: the sums run in another
/// order, nothing more.
const IMAGE_TOL: f64 = 1e-10;

// Reference values from tests/fixtures/ssim_reference.py, run with numpy 2.4.6, scipy 1.17.1,
// scikit-image 0.26.0 (pip, Python 3.11):
//   skimage: structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
//            use_sample_covariance=False, data_range=1.0, channel_axis=-1) on float64 copies
//            of the float32 images;
//   same:    11x11 Gaussian (sigma 1.5) correlated with zero padding ('same' size; separable
//            scipy.ndimage.correlate1d, cross-checked against scipy.signal.correlate2d),
//            the 3DGS/MonoGS formula, mean over the whole map, then over channels;
//   psnr:    peak_signal_noise_ratio(a, b, data_range=1.0).
// Output: 37x29x3: psnr 22.869933238110626 ssim_skimage 0.925403952274167 ssim_same 0.934630445470887
//         41x19x1: psnr 22.816736040051488 ssim_skimage 0.928036352580357 ssim_same 0.938565825398025
//         64x48x3: psnr 22.863129721005198 ssim_skimage 0.910104557652716 ssim_same 0.920821808862836

#[test]
fn rgb_metrics_match_skimage_and_the_same_convention() {
    for (w, h, p, sk, same) in [
        (37, 29, 22.869933238110626, 0.925403952274167, 0.934630445470887),
        (64, 48, 22.863129721005198, 0.910104557652716, 0.920821808862836),
    ] {
        let (a, b): (ImageRgbF32, ImageRgbF32) = images::<3>(w, h);
        close("psnr", psnr(&a, &b).unwrap(), p, IMAGE_TOL);
        close("ssim skimage", ssim(&a, &b, SsimConvention::Skimage).unwrap(), sk, IMAGE_TOL);
        close("ssim same", ssim(&a, &b, SsimConvention::Same).unwrap(), same, IMAGE_TOL);
        // Symmetric in its arguments.
        close("ssim swapped", ssim(&b, &a, SsimConvention::Skimage).unwrap(), sk, IMAGE_TOL);
    }
}

#[test]
fn grey_metrics_match_skimage_and_the_same_convention() {
    let (a, b): (PlaneF32, PlaneF32) = images::<1>(41, 19);
    close("psnr", psnr(&a, &b).unwrap(), 22.816736040051488, IMAGE_TOL);
    close("ssim skimage", ssim(&a, &b, SsimConvention::Skimage).unwrap(), 0.928036352580357, IMAGE_TOL);
    close("ssim same", ssim(&a, &b, SsimConvention::Same).unwrap(), 0.938565825398025, IMAGE_TOL);
}
