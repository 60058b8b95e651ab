//! `duv eval` end to end on a small generated run: dataset folder, run folder, image pairs and
//! depth maps in, report files out; and the errors bad input gets.

use duv_core::pose::{se3_exp, sim3_apply_to_pose, sim3_from_parts};
use duv_core::rng::Rng;
use duv_core::{ImageGray16, ImageRgb8, PlaneF32, StampedPose, Timestamp};
use duv_core::io::{pfm, png_io, tum};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector6};
use std::path::Path;
use std::process::{Command, Output};

fn duv(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_duv")).args(args).output().expect("duv runs")
}

/// A ground-truth survey (dataset folder with groundtruth.txt) and a run folder whose
/// trajectory is a noisy, scaled, moved copy.
fn write_trajectories(root: &Path) {
    let gt: Vec<StampedPose> = (0..150)
        .map(|i| {
            let a = i as f64 * 0.05;
            let xi = Vector6::new(2.0 * a.cos(), 1.5 * a.sin(), 0.1 * a, 0.05 * a, 0.02, 0.3 * a);
            StampedPose { t_ns: Timestamp(1_000_000_000 + i as i64 * 33_333_333), world_from_cam: se3_exp(&xi) }
        })
        .collect();
    let s = sim3_from_parts(0.5, &Isometry3::from_parts(Translation3::new(1.0, 2.0, -1.0), UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3)));
    let mut rng = Rng::new(9);
    let est: Vec<StampedPose> = gt
        .iter()
        .map(|p| {
            let mut pose = sim3_apply_to_pose(&s, &p.world_from_cam);
            pose.translation.vector += nalgebra::Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.005;
            StampedPose { t_ns: p.t_ns.offset_ns(1_000_000), world_from_cam: pose }
        })
        .collect();
    std::fs::create_dir_all(root.join("dataset")).unwrap();
    std::fs::create_dir_all(root.join("run")).unwrap();
    tum::write_trajectory(&root.join("dataset/groundtruth.txt"), &gt).unwrap();
    tum::write_trajectory(&root.join("run/trajectory.txt"), &est).unwrap();
}

fn write_images(root: &Path) {
    for d in ["rendered", "reference"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let img = |seed: u64| {
        let mut rng = Rng::new(seed);
        ImageRgb8 { width: 40, height: 30, data: (0..40 * 30 * 3).map(|i| ((i % 97) as f64 * 2.0 + rng.range(0.0, 20.0)) as u8).collect() }
    };
    png_io::write_rgb8(&root.join("reference/0001.png"), &img(1)).unwrap();
    png_io::write_rgb8(&root.join("rendered/0001.png"), &img(1)).unwrap();
    png_io::write_rgb8(&root.join("reference/0002.png"), &img(2)).unwrap();
    png_io::write_rgb8(&root.join("rendered/0002.png"), &img(3)).unwrap();
}

/// Depth maps whose error follows the variance: a useful uncertainty.
fn write_depth(root: &Path) {
    for d in ["depth", "variance", "gt_depth"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let (w, h) = (40, 30);
    for (k, name) in ["kf_000", "kf_001"].iter().enumerate() {
        let mut rng = Rng::new(100 + k as u64);
        let gt: Vec<f32> = (0..w * h).map(|i| 1.0 + (i % w) as f32 * 0.02 + (i / w) as f32 * 0.01).collect();
        let sigma: Vec<f32> = (0..w * h).map(|_| rng.range(0.005, 0.1) as f32).collect();
        let est: Vec<f32> = gt.iter().zip(&sigma).map(|(g, s)| g + s * rng.normal() as f32).collect();
        let var: Vec<f32> = sigma.iter().map(|s| s * s).collect();
        pfm::write_pfm(&root.join(format!("depth/{name}.pfm")), &PlaneF32::from_vec(w, h, est).unwrap()).unwrap();
        pfm::write_pfm(&root.join(format!("variance/{name}.pfm")), &PlaneF32::from_vec(w, h, var).unwrap()).unwrap();
        if k == 0 {
            pfm::write_pfm(&root.join(format!("gt_depth/{name}.pfm")), &PlaneF32::from_vec(w, h, gt).unwrap()).unwrap();
        } else {
            // TUM-style 16-bit PNG, 5000 per metre.
            let raw = ImageGray16 { width: w, height: h, data: gt.iter().map(|g| (g * 5000.0).round() as u16).collect() };
            png_io::write_gray16(&root.join(format!("gt_depth/{name}.png")), &raw).unwrap();
        }
    }
}

#[test]
fn full_evaluation_writes_report_and_figures() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write_trajectories(root);
    write_images(root);
    write_depth(root);
    let p = |s: &str| root.join(s).display().to_string();
    let out = duv(&[
        "eval", "--gt", &p("dataset"), "--run", &p("run"), "--rendered", &p("rendered"), "--reference", &p("reference"),
        "--depth", &p("depth"), "--variance", &p("variance"), "--gt-depth", &p("gt_depth"), "--out", &p("out"),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("ATE RMSE (m)") && stdout.contains("PSNR mean") && stdout.contains("AUSE"), "{stdout}");

    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(root.join("out/report.json")).unwrap()).unwrap();
    let t = &json["trajectory"];
    assert_eq!(t["associated"], 150);
    // Noise of 5 mm per axis in a frame at half scale: about 1.5 cm after rescaling.
    let rmse = t["ate"]["stats_m"]["rmse"].as_f64().unwrap();
    assert!(rmse > 0.005 && rmse < 0.03, "{rmse}");
    assert!((t["alignment"]["scale"].as_f64().unwrap() - 2.0).abs() < 0.02);
    let imgs = &json["images"];
    assert_eq!(imgs["pairs"], 2);
    assert_eq!(imgs["per_image"][0]["psnr_db"], "inf");
    assert_eq!(imgs["per_image"][0]["ssim"], 1.0);
    assert_eq!(imgs["psnr_mean_db"], "inf");
    assert_eq!(imgs["identical"], 1);
    let ause = &json["ause"];
    assert_eq!(ause["keyframes"], 2);
    let (a, r) = (ause["ause_mean"].as_f64().unwrap(), ause["ause_random_mean"].as_f64().unwrap());
    assert!(a < 0.5 * r, "AUSE {a} vs random {r}");
    for f in ["report.json", "report.md"] {
        assert!(root.join("out").join(f).is_file(), "{f}");
    }
    // The figures need the `figures` feature (CI tests with --all-features); without it the
    // report says why they are missing.
    for f in ["trajectory_top.png", "ate_along_path.png", "sparsification.png"] {
        assert_eq!(root.join("out").join(f).is_file(), cfg!(feature = "figures"), "{f}");
    }
    if !cfg!(feature = "figures") {
        let md = std::fs::read_to_string(root.join("out/report.md")).unwrap();
        assert!(md.contains("--features figures"), "{md}");
    }
    // The report reads back into the library type.
    let back: duv_eval::Report = serde_json::from_value(json).unwrap();
    assert_eq!(back.images.unwrap().per_image[0].psnr_db, f64::INFINITY);
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write_trajectories(root);
    let p = |s: &str| root.join(s).display().to_string();

    // Clocks that do not overlap: no pairs, both files named.
    let late: Vec<StampedPose> = tum::read_trajectory(&root.join("run/trajectory.txt"))
        .unwrap()
        .into_iter()
        .map(|s| StampedPose { t_ns: s.t_ns.offset_ns(1_000_000_000_000), ..s })
        .collect();
    tum::write_trajectory(&root.join("late.txt"), &late).unwrap();
    let out = duv(&["eval", "--gt", &p("dataset"), "--est", &p("late.txt"), "--out", &p("out")]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("groundtruth.txt") && err.contains("late.txt") && err.contains("0.01 s"), "{err}");

    // Images of different sizes: both files named.
    for d in ["r", "f"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    png_io::write_rgb8(&root.join("r/a.png"), &ImageRgb8::filled(20, 20, [1, 2, 3])).unwrap();
    png_io::write_rgb8(&root.join("f/a.png"), &ImageRgb8::filled(20, 21, [1, 2, 3])).unwrap();
    let out = duv(&["eval", "--gt", &p("dataset"), "--run", &p("run"), "--rendered", &p("r"), "--reference", &p("f"), "--out", &p("out")]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("differ in size") && err.contains(&p("r/a.png")) && err.contains(&p("f/a.png")), "{err}");

    // A missing estimate file is named.
    let out = duv(&["eval", "--gt", &p("dataset"), "--est", &p("nope.txt"), "--out", &p("out")]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("nope.txt"));
}

/// A run folder with a map segment that never merged (`trajectory-segment-1.txt`, another
/// frame and scale): `duv eval --run` scores it aligned on its own, beside segment 0, and
/// writes `segments.md` and `segments.json`; with `--align se3` it says why it does not.
#[test]
fn run_folder_map_segments_are_scored_each_on_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    write_trajectories(root);
    let p = |s: &str| root.join(s).display().to_string();
    // Split the run at frame 90: the rest in another frame and scale (segment 1).
    let est = tum::read_trajectory(&root.join("run/trajectory.txt")).unwrap();
    let other = sim3_from_parts(3.0, &Isometry3::from_parts(Translation3::new(-5.0, 0.0, 4.0), UnitQuaternion::from_euler_angles(-0.4, 0.1, 1.2)));
    let seg1: Vec<StampedPose> = est[90..].iter().map(|s| StampedPose { t_ns: s.t_ns, world_from_cam: sim3_apply_to_pose(&other, &s.world_from_cam) }).collect();
    tum::write_trajectory(&root.join("run/trajectory.txt"), &est[..90]).unwrap();
    tum::write_trajectory(&root.join("run/trajectory-segment-1.txt"), &seg1).unwrap();
    let out = duv(&["eval", "--gt", &p("dataset"), "--run", &p("run"), "--out", &p("out")]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(root.join("out/segments.json")).unwrap()).unwrap();
    let segs = json["segments"].as_array().unwrap();
    assert_eq!(segs.len(), 2, "{json}");
    assert_eq!((segs[0]["segment"].as_u64(), segs[0]["poses"].as_u64()), (Some(0), Some(90)));
    assert_eq!((segs[1]["segment"].as_u64(), segs[1]["poses"].as_u64()), (Some(1), Some(60)));
    // Each aligned on its own: the 5 mm noise (scaled by 0.5 into the estimate), not the split.
    for s in segs {
        let rmse = s["ate_rmse_m"].as_f64().unwrap();
        assert!(rmse < 0.02, "segment {}: {rmse} m", s["segment"]);
    }
    assert_eq!(json["poses"].as_u64(), Some(150));
    assert!(std::fs::read_to_string(root.join("out/segments.md")).unwrap().contains("trajectory-segment-1.txt"));
    // Scored as one trajectory the split would show.
    let whole: Vec<StampedPose> = est[..90].iter().copied().chain(seg1.iter().copied()).collect();
    tum::write_trajectory(&root.join("whole.txt"), &whole).unwrap();
    let out = duv(&["eval", "--gt", &p("dataset"), "--est", &p("whole.txt"), "--out", &p("whole")]);
    assert!(out.status.success());
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(root.join("whole/report.json")).unwrap()).unwrap();
    assert!(report["trajectory"]["ate"]["stats_m"]["rmse"].as_f64().unwrap() > 0.2, "{}", report["trajectory"]["ate"]);
    // --align se3 keeps the scale: segments are not compared, and it says so.
    let out = duv(&["eval", "--gt", &p("dataset"), "--run", &p("run"), "--align", "se3", "--allow-map-units", "--out", &p("out-se3")]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(!root.join("out-se3/segments.json").exists());
    assert!(text.contains("map segments 1: not scored"), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
}
