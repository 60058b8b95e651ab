//! The `duv` binary as a user meets it: help lists every subcommand, board checking works,
//! and failures are reported as errors with a non-zero exit, never a panic.

use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

#[test]
fn help_lists_every_subcommand() {
    let out = duv().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for sub in ["demo", "run", "sim", "refine", "eval", "board", "dataset"] {
        assert!(text.lines().any(|l| l.trim_start().starts_with(sub)), "`duv --help` does not list {sub}:\n{text}");
    }
}

#[test]
fn board_check_passes_on_repo_boards_and_fails_on_a_broken_one() {
    let out = duv().arg("board").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().filter(|l| l.starts_with("ok")).count(), 3, "{text}");
    assert!(text.lines().any(|l| l.contains("jetson-orin-nx-16gb") && l.ends_with("| log frames jpeg q90")), "{text}");
    assert!(text.lines().any(|l| l.contains(" sim ") && l.ends_with("| log frames raw")), "{text}");

    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    let sim = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/boards/sim.toml")).unwrap();
    std::fs::write(&bad, sim.replace("frame_queue = 4", "frame_queue = 0")).unwrap();
    let out = duv().arg("board").arg(&bad).output().unwrap();
    assert!(!out.status.success());
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert!(stdout.contains("bad.toml: budgets.frame_queue = 0 is invalid"), "{stdout}");
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn refine_with_pose_refinement_writes_the_poses_and_says_what_it_did() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("posed");
    let r = duv()
        .args(["refine", "--water", "coastal", "--width", "64", "--height", "48", "--frames", "16", "--every", "4", "--iterations", "20", "--no-progress"])
        .args(["--refine-poses", "--refine-poses-every", "5", "--perturb-poses-m", "0.02", "--perturb-poses-deg", "0.3", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&r.stdout);
    assert!(r.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&r.stderr));
    // Rounds at iterations 5, 10 and 15 (none in the last 5), 3 keyframes each (the first is the anchor).
    assert!(stdout.contains("poses     3 refinement round(s): "), "{stdout}");
    let poses = std::fs::read_to_string(out.join("poses.txt")).unwrap();
    assert_eq!(poses.lines().filter(|l| !l.starts_with('#')).count(), 4, "{poses}");
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["pose_refinement"]["rounds"], 3);
    let before = metrics["pose_error_before"][0].as_f64().unwrap();
    assert!((before - 0.015).abs() < 1e-9, "3 of 4 keyframes moved 2 cm: mean {before}");
    assert_eq!(metrics["keyframes"][0]["pose_shift_m"], 0.0, "the anchor stays");

    // Perturbing needs the true poses; the error names the flag and nothing is written.
    let r = duv().args(["refine", "--keyframes", "nowhere", "--perturb-poses-m", "0.1", "--out"]).arg(dir.path().join("x")).output().unwrap();
    assert!(!r.status.success());
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(stderr.contains("--perturb-poses-m and --perturb-poses-deg need --water") && !stderr.contains("panicked"), "{stderr}");
    assert!(!dir.path().join("x").exists());
}

#[test]
fn a_missing_file_is_named_once_in_the_error() {
    let out = duv().args(["bench", "map", "--poses", "tracked", "--board", "boards/no-such-board.toml", "--frames", "10"]).output().unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8(out.stderr).unwrap();
    let line = stderr.lines().find(|l| l.starts_with("error: ")).unwrap_or_else(|| panic!("no error line:\n{stderr}"));
    assert!(line.contains("boards/no-such-board.toml"), "{line}");
    assert_eq!(line.matches("No such file or directory").count(), 1, "{line}");
}

/// `duv sim --altitude-swing`: the yo-yo profile reaches `sim.json` and the ground truth
/// climbs and descends by the swing over one period.
#[test]
fn sim_flies_a_yo_yo_altitude_profile() {
    let dir = tempfile::tempdir().unwrap();
    let args = ["sim", "--frames", "21", "--width", "32", "--height", "24", "--max-range", "6", "--wobble-scale", "0", "--no-progress"];
    let out = duv().args(args).args(["--altitude-swing", "0.4", "--altitude-period", "2", "--out"]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let sim: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("sim.json")).unwrap()).unwrap();
    let cfg = &sim["config"];
    assert_eq!((cfg["altitude_swing_m"].as_f64(), cfg["altitude_period_s"].as_f64()), (Some(0.4), Some(2.0)), "{sim}");
    // TUM ground truth: `t tx ty tz qx qy qz qw`; frames 5 and 15 are the top and the bottom
    // of the cycle (the seabed under the first lane is smooth, so z follows the swing).
    let gt = std::fs::read_to_string(dir.path().join("groundtruth.txt")).unwrap();
    let z: Vec<f64> = gt.lines().filter(|l| !l.starts_with('#') && !l.trim().is_empty()).map(|l| l.split_whitespace().nth(3).unwrap().parse().unwrap()).collect();
    assert_eq!(z.len(), 21);
    assert!(((z[5] - z[15]) - 0.8).abs() < 0.1, "top {} bottom {}", z[5], z[15]);
    let bad = duv().args(args).args(["--altitude-swing", "2.5", "--out"]).arg(dir.path().join("bad")).output().unwrap();
    assert!(!bad.status.success());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(stderr.contains("altitude_swing_m = 2.5") && !stderr.contains("panicked"), "{stderr}");
}

/// `duv sim` writes `nav.csv` beside `rgb.txt`: one sample per frame at the frame's time,
/// read back with no rejections, equal to what the generator simulates in memory, and the
/// depth is the surface height minus the ground-truth z. `--no-nav` leaves it out.
#[test]
fn sim_writes_a_nav_csv_the_reader_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let args = ["sim", "--frames", "21", "--width", "32", "--height", "24", "--max-range", "6", "--seed", "3", "--no-progress", "--out"];
    let out = duv().args(args).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let track = duv_core::nav::read_nav_csv(&dir.path().join("nav.csv")).unwrap();
    assert_eq!(track.rejected, duv_core::nav::NavRejections::default(), "{}", track.rejected.describe());
    assert_eq!(track.len(), 21);
    let gt = duv_core::io::tum::read_trajectory(&dir.path().join("groundtruth.txt")).unwrap();
    for (s, p) in track.samples.iter().zip(&gt) {
        assert_eq!(s.t_ns, p.t_ns);
        let depth_truth = duv_sim::nav::SURFACE_Z_M - p.world_from_cam.translation.vector.z;
        assert!((s.depth_m.unwrap() - depth_truth).abs() < 0.05, "{:?} vs {depth_truth}", s.depth_m);
        assert!(s.world_from_cam_rot.unwrap().angle_to(&p.world_from_cam.rotation) < 2f64.to_radians());
    }
    // The same samples as the generator's in-memory sensors for this config and seed.
    let sim: duv_sim::writer::SimManifest = serde_json::from_str(&std::fs::read_to_string(dir.path().join("sim.json")).unwrap()).unwrap();
    let renderer = duv_sim::SimRenderer::new(&sim.config).unwrap();
    let mem = duv_sim::nav::simulate(&renderer, &duv_sim::NavNoise::default(), 3).unwrap();
    for (a, b) in mem.iter().zip(&track.samples) {
        assert_eq!((a.t_ns, a.depth_m, a.altitude_m, a.vel_cam_mps), (b.t_ns, b.depth_m, b.altitude_m, b.vel_cam_mps));
        assert!(a.world_from_cam_rot.unwrap().angle_to(&b.world_from_cam_rot.unwrap()) < 1e-12);
    }
    // --no-nav: a camera-only folder, the earlier nav.csv removed.
    let out = duv().args(args).arg(dir.path()).arg("--no-nav").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(!dir.path().join("nav.csv").exists() && dir.path().join("rgb.txt").exists());
}
