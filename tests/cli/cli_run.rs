//! `duv run` end to end on a tiny `sim:` source: every output file, with the right line counts,
//! PFMs readable at full resolution, the eval report, the map exports; `duv refine` on the
//! finished run, from its keyframe folder and from its MCAP log (whole, truncated, without
//! keyframes); and clear errors for bad sources.

use duv_core::MediumParams;
use duv_core::io::keyframes::read_keyframe_folder;
use duv_core::io::pfm::read_pfm;
use duv_core::io::png_io::read_image;
use duv_map::mapper::Mapper;
use duv_map::ply::read_ply;
use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

#[test]
fn run_on_a_tiny_sim_source_writes_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let cfg = dir.path().join("tracker.toml");
    // A depth grid of 1/4 suits 160x120 images (40x30, as 1/8 of 320x240; also the automatic
    // choice): the config file is read.
    std::fs::write(&cfg, "depth_factor = 4\n").unwrap();
    let frames = 64;
    let res = duv()
        .args(["run", "--source", "sim:coastal", "--frames", &frames.to_string(), "--width", "160", "--height", "120", "--no-progress"])
        .args(["--map-iterations", "4", "--map-final-iterations", "10"])
        .arg("--tracker-config")
        .arg(&cfg)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&res.stdout);
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stdout.contains("frames/s") && stdout.contains("per frame: flow"), "{stdout}");
    assert!(stdout.contains("ATE RMSE"), "{stdout}");
    assert!(stderr.contains("tracking"), "state changes on stderr: {stderr}");
    assert!(stderr.contains("mapper renders with "), "the renderer is named: {stderr}");

    let traj = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    let poses = duv_core::io::tum::read_trajectory(&out.join("trajectory.txt")).unwrap();
    assert_eq!(poses.len(), frames, "{traj}");
    let kf_text = std::fs::read_to_string(out.join("keyframes.txt")).unwrap();
    let kf_lines: Vec<&str> = kf_text.lines().filter(|l| !l.starts_with('#')).collect();
    assert!(kf_lines.len() >= 8, "{kf_text}");
    for line in &kf_lines {
        let fields: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(fields.len(), 9, "{line}");
        let id: u64 = fields[0].parse().unwrap();
        for kind in ["invdepth", "variance"] {
            let p = read_pfm(&out.join("keyframes").join(format!("{id:06}_{kind}.pfm"))).unwrap();
            assert_eq!((p.width, p.height), (160, 120));
            assert!(p.data.iter().all(|v| v.is_finite() && *v > 0.0), "{kind} of keyframe {id}");
        }
    }
    let states = std::fs::read_to_string(out.join("states.txt")).unwrap();
    assert_eq!(states.lines().filter(|l| !l.starts_with('#')).count(), frames);
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("eval/report.json")).unwrap()).unwrap();
    assert_eq!(report["trajectory"]["associated"], frames);
    assert!(report["ause"]["keyframes"].as_u64().unwrap() >= 6, "{}", report["ause"]);

    // The run folder is a keyframe folder: calibration, poses, images, depth, variance.
    let kfs = read_keyframe_folder(&out).unwrap();
    assert_eq!(kfs.len(), kf_lines.len());
    assert!(kfs.iter().all(|k| (k.camera.width, k.camera.height) == (160, 120) && k.image.data.iter().any(|&v| v > 0)));

    // The map exports.
    assert!(stdout.contains("mapped") && stdout.contains("Gaussians"), "{stdout}");
    let map = read_ply(&out.join("map.ply"), 1 << 20).unwrap();
    assert!(map.len() > 1000, "{} Gaussians", map.len());
    assert!(map.len() <= 50_000, "board cap (boards/sim.toml max_gaussians)");
    let medium: MediumParams = serde_json::from_str(&std::fs::read_to_string(out.join("medium.json")).unwrap()).unwrap();
    assert!(medium.beta_d.iter().chain(&medium.beta_b).all(|v| v.is_finite() && *v > 0.0), "{medium:?}");
    assert!(medium.b_inf.iter().all(|v| *v > 0.0 && *v < 1.0), "{medium:?}");
    let restored = Mapper::load_checkpoint(&out.join("map.ckpt")).unwrap();
    assert_eq!(restored.gaussians().len(), map.len());
    let renders: Vec<_> = std::fs::read_dir(out.join("renders")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(renders.len(), restored.keyframe_count());
    assert!(renders.len() >= 6, "{} render panels", renders.len());
    let panel = read_image(&renders[0]).unwrap();
    assert_eq!((panel.width(), panel.height()), (5 * 160, 11 + 120), "input | render | restored | depth | uncertainty, under a label strip");

    // The map report: frames between keyframes, the restored view against the generator's
    // water-free view, the medium with its unit, a labelled panel per frame; the evaluation
    // report carries it and its image scores.
    let q: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("map/report.json")).unwrap()).unwrap();
    let views = q["views"].as_u64().unwrap();
    assert!((1..=8).contains(&views), "{q}");
    assert!(q["psnr_mean_db"].as_f64().unwrap() > 20.0, "{q}");
    assert!(q["coverage"].as_f64().unwrap() > 0.5, "{q}");
    assert_eq!(q["medium_unit"], "1/map unit");
    assert!(q["lpips_mean"].is_null() && q["lpips_missing"].is_string());
    let r = &q["restored"];
    assert!(r["psnr_mean_db"].as_f64().unwrap() > r["captured_psnr_mean_db"].as_f64().unwrap(), "restoring made it worse: {r}");
    for v in q["per_view"].as_array().unwrap() {
        let seq = v["seq"].as_u64().unwrap();
        let p = read_image(&out.join(format!("map/{seq:06}.png"))).unwrap();
        assert_eq!((p.width(), p.height()), (5 * 160, 11 + 120));
    }
    assert!(std::fs::read_to_string(out.join("map/report.md")).unwrap().contains("restored vs water-free truth"));
    assert_eq!(report["images"]["pairs"].as_u64(), Some(views), "{}", report["images"]);
    assert_eq!(report["map"]["views"].as_u64(), Some(views));
    assert!(stdout.contains("map on ") && stdout.contains("restored vs water-free truth"), "{stdout}");

    // The log's map checkpoints refer to the keyframes' own log messages instead of embedding
    // their pixels; with the log's keyframes the newest one restores the same map as the
    // newest checkpoint file, and refinement can continue from it.
    let from_log = duv_log::read_log_keyframes(&out, duv_log::ReadLimits::default()).unwrap();
    let logged_map = from_log.newest_map.clone().expect("a map checkpoint in the log");
    let (_, file_ckpt) = duv_pipeline::CheckpointStore::new(out.join("checkpoints"), 3).load_newest().expect("a checkpoint file");
    let options = duv_map::checkpoint::RestoreOptions { keyframes: &from_log.keyframes, capacity: None };
    let onboard = Mapper::from_checkpoint_bytes(&logged_map.bytes, "logged", options).unwrap();
    let on_disk = Mapper::from_checkpoint_bytes(&file_ckpt, "file", Default::default()).unwrap();
    // The logged checkpoint is smaller by at least every keyframe's RGB pixels.
    let pixels = on_disk.keyframe_count() * 160 * 120 * 3;
    assert!(logged_map.bytes.len() + pixels <= file_ckpt.len(), "logged {} bytes, file {} bytes, keyframe pixels {pixels} bytes", logged_map.bytes.len(), file_ckpt.len());
    assert_eq!(onboard.gaussians(), on_disk.gaussians());
    assert_eq!(onboard.keyframe_count(), on_disk.keyframe_count());
    let res = duv()
        .args(["refine", "--iterations", "5", "--no-progress", "--from-logged-map", "--mcap"])
        .arg(&out)
        .arg("--out")
        .arg(dir.path().join("from-logged-map"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "{stderr}");
    let said = format!("/map/checkpoint at {} ns: {} Gaussians, {} keyframes, iteration {}", logged_map.log_time_ns, on_disk.gaussians().len(), on_disk.keyframe_count(), on_disk.iteration());
    assert!(stderr.contains(&said), "expected '{said}' in:\n{stderr}");
    assert!(on_disk.iteration() > 0);

    // Offshore refinement reads the finished run, on the Vulkan mapper (lavapipe in CI).
    let refined = dir.path().join("refined");
    let res = duv()
        .args(["refine", "--iterations", "10", "--max-gaussians", "60000", "--no-progress", "--mapper", "vulkan", "--gpu-mb", "512"])
        .arg("--keyframes")
        .arg(&out)
        .arg("--out")
        .arg(&refined)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&res.stdout);
    assert!(res.status.success(), "stdout:\n{stdout}\nstderr:\n{}", String::from_utf8_lossy(&res.stderr));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(refined.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["keyframes"].as_array().unwrap().len(), kfs.len());
    assert!(metrics["mean_psnr_db"].as_f64().unwrap() > 10.0, "{}", metrics["mean_psnr_db"]);
    let renderer = metrics["renderer"].as_str().unwrap();
    assert!(renderer.starts_with("Vulkan on ") || std::env::var_os("CI").is_none(), "--mapper vulkan in CI rendered with {renderer}");
    assert!(refined.join("map.ply").exists() && refined.join("medium.json").exists());
}

#[test]
fn refine_reads_the_keyframes_of_a_run_log_around_the_damage() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    // 64 frames at 160x120 with a 1/4 depth grid: enough keyframes with confident depth to
    // seed Gaussians (a 30-frame run seeds none).
    let cfg = dir.path().join("tracker.toml");
    std::fs::write(&cfg, "depth_factor = 4\n").unwrap();
    let res = duv()
        .args(["run", "--source", "sim:coastal", "--frames", "64", "--width", "160", "--height", "120", "--no-progress", "--no-map"])
        .arg("--tracker-config")
        .arg(&cfg)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let seg = out.join("log/segment-000000.mcap");
    let summary = duv_log::inspect_log(&out.join("log"), duv_log::ReadLimits::default()).unwrap();
    let logged = summary.topics["/keyframe/pose"].messages as usize;
    assert!(logged >= 3, "{logged} keyframes logged");
    let refine_with = |flag: &str, from: &std::path::Path, to: &str| {
        let r = duv().args(["refine", "--iterations", "10", "--max-gaussians", "60000", "--no-progress"]).arg(flag).arg(from).arg("--out").arg(dir.path().join(to)).output().unwrap();
        (r.status.success(), String::from_utf8_lossy(&r.stdout).into_owned(), String::from_utf8_lossy(&r.stderr).into_owned())
    };
    let refine = |from: &std::path::Path, to: &str| refine_with("--mcap", from, to);
    let metrics = |to: &str| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(dir.path().join(to).join("metrics.json")).unwrap()).unwrap() };

    // The whole log (given as the run folder): every logged keyframe, the same exports as
    // from a keyframe folder.
    let (ok, stdout, stderr) = refine(&out, "whole");
    assert!(ok, "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stderr.contains(&format!("{logged} keyframe(s) from 1 segment(s)")), "{stderr}");
    let m = metrics("whole");
    assert_eq!(m["keyframes"].as_array().unwrap().len(), logged);
    assert!(m["mean_psnr_db"].as_f64().unwrap() > 10.0, "{}", m["mean_psnr_db"]);
    let whole = dir.path().join("whole");
    assert!(whole.join("map.ply").exists() && whole.join("map.ckpt").exists() && whole.join("medium.json").exists());
    assert_eq!(std::fs::read_dir(whole.join("renders")).unwrap().count(), logged);
    let gaussians = read_ply(&whole.join("map.ply"), 1 << 20).unwrap().len();
    assert!(gaussians > 100, "{gaussians} Gaussians");

    // The same keyframes as a keyframe folder refine to the same map (the folder's text poses
    // round to f64 printing, and the mapper's parallel sums are not ordered: 1e-4 dB measured).
    let logged_kfs = duv_log::read_log_keyframes(&out, duv_log::ReadLimits::default()).unwrap().keyframes;
    let folder = dir.path().join("as-folder");
    duv_core::io::keyframes::write_keyframe_folder(&folder, &logged_kfs).unwrap();
    let (ok, stdout, stderr) = refine_with("--keyframes", &folder, "from-folder");
    assert!(ok, "stdout:\n{stdout}\nstderr:\n{stderr}");
    let f = metrics("from-folder");
    assert_eq!(f["keyframes"].as_array().unwrap().len(), logged);
    let (a, b) = (m["mean_psnr_db"].as_f64().unwrap(), f["mean_psnr_db"].as_f64().unwrap());
    assert!((a - b).abs() < 0.01, "mean PSNR {a} dB from the log, {b} dB from the folder");
    let g = read_ply(&dir.path().join("from-folder/map.ply"), 1 << 20).unwrap().len();
    assert!(g.abs_diff(gaussians) <= gaussians / 100, "{gaussians} Gaussians from the log, {g} from the folder");

    // Truncated inside the keyframes (they leave tracking after the BA window, so in a short
    // run they are all near the end; the library finds a cut that keeps some of them): read
    // around the damage, said so, fewer keyframes refined.
    let bytes = std::fs::read(&seg).unwrap();
    let cut = dir.path().join("cut");
    std::fs::create_dir_all(&cut).unwrap();
    let cut_file = cut.join("segment-000000.mcap");
    let kept = (50..100).find_map(|pct| {
        std::fs::write(&cut_file, &bytes[..bytes.len() * pct / 100]).unwrap();
        let n = duv_log::read_log_keyframes(&cut, duv_log::ReadLimits::default()).map_or(0, |k| k.keyframes.len());
        (n >= 1 && n < logged).then_some(n)
    });
    let kept = kept.expect("a cut that keeps some but not all keyframes");
    let (ok, stdout, stderr) = refine(&cut, "cut-out");
    assert!(ok, "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stderr.contains("log damaged, damaged ranges skipped") && stderr.contains("segment-000000.mcap"), "{stderr}");
    assert!(stderr.contains(&format!("{kept} keyframe(s) from 1 segment(s)")), "{stderr}");
    assert_eq!(metrics("cut-out")["keyframes"].as_array().unwrap().len(), kept);

    // A tracking-only run logs keyframe poses, not a map: --from-logged-map says so.
    let r = duv().args(["refine", "--iterations", "1", "--no-progress", "--from-logged-map", "--mcap"]).arg(&out).arg("--out").arg(dir.path().join("no-map")).output().unwrap();
    let stderr = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success() && stderr.contains("/map/checkpoint") && stderr.contains("not a mapper checkpoint") && !stderr.contains("panicked"), "{stderr}");

    // Cut before the first keyframe: an error that names the log and the damage.
    std::fs::write(cut.join("segment-000000.mcap"), &bytes[..4096]).unwrap();
    let (ok, _, stderr) = refine(&cut, "none");
    assert!(!ok && stderr.contains("no keyframes in the log") && stderr.contains(cut.to_str().unwrap()) && stderr.contains("damaged") && !stderr.contains("panicked"), "{stderr}");
    // Not a log at all.
    let (ok, _, stderr) = refine(dir.path().join("none-such").as_path(), "none");
    assert!(!ok && stderr.contains("none-such") && !stderr.contains("panicked"), "{stderr}");
}

/// A mapped run logged as a ROS 2 bag: `duv refine --mcap` reads its keyframes from the CDR
/// messages and `--from-logged-map` restores the map from its `duv_msgs/msg/MapCheckpoint`.
#[test]
fn refine_reads_the_keyframes_and_the_map_of_a_ros2_log() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let cfg = dir.path().join("tracker.toml");
    std::fs::write(&cfg, "depth_factor = 4\n").unwrap();
    let res = duv()
        .args(["run", "--source", "sim:coastal", "--frames", "64", "--width", "160", "--height", "120", "--no-progress", "--log-format", "ros2"])
        .args(["--mapper", "cpu", "--map-iterations", "2", "--map-final-iterations", "4", "--config"])
        .arg(&cfg)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let summary = duv_log::inspect_log(&out.join("log"), duv_log::ReadLimits::default()).unwrap();
    assert_eq!(summary.topics["/map/checkpoint"].schema, "duv_msgs/msg/MapCheckpoint");
    let logged = summary.topics["/keyframe/pose"].messages as usize;
    assert!(logged >= 3, "{logged} keyframes logged");
    for (flags, to) in [(&["--mcap"][..], "whole"), (&["--from-logged-map", "--mcap"][..], "from-map")] {
        let r = duv().args(["refine", "--iterations", "2", "--quiet"]).args(flags).arg(&out).arg("--out").arg(dir.path().join(to)).output().unwrap();
        let stderr = String::from_utf8_lossy(&r.stderr);
        assert!(r.status.success(), "{flags:?}: {stderr}");
        if to == "from-map" {
            assert!(stderr.contains("/map/checkpoint at") && stderr.contains("Gaussians"), "{stderr}");
        }
        let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join(to).join("metrics.json")).unwrap()).unwrap();
        assert_eq!(m["keyframes"].as_array().unwrap().len(), logged, "{flags:?}");
        assert!(m["mean_psnr_db"].as_f64().unwrap() > 10.0, "{flags:?}: {}", m["mean_psnr_db"]);
    }
}

#[test]
fn bad_sources_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    for (source, needle) in [("sim:muddy", "unknown water"), ("sim:coastal-spiral", "unknown trajectory"), ("nope:x", "unknown source")] {
        let res = duv().args(["run", "--source", source, "--frames", "4", "--no-progress"]).arg("--out").arg(dir.path()).output().unwrap();
        assert!(!res.status.success());
        let stderr = String::from_utf8_lossy(&res.stderr);
        assert!(stderr.contains(needle) && !stderr.contains("panicked"), "{source}: {stderr}");
    }
}

/// `sim:`'s options (`frames=N`, `seed=S`) work in `duv run` as in every other source: the
/// README's `sim:coastal,frames=50,seed=3`, smaller.
#[test]
fn sim_spec_options_set_the_frames_and_the_seed() {
    let dir = tempfile::tempdir().unwrap();
    let run = |source: &str, out: &str| {
        let out = dir.path().join(out);
        let res = duv()
            .args(["run", "--source", source, "--width", "160", "--height", "120", "--no-progress", "--no-map"])
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(res.status.success(), "{source}: {}", String::from_utf8_lossy(&res.stderr));
        out
    };
    // states.txt without the tracker's time per frame: every frame's state, pose source and
    // why it waited (12 frames do not initialise at 160x120, so trajectory.txt is empty).
    let states = |dir: &std::path::Path| -> Vec<String> {
        std::fs::read_to_string(dir.join("states.txt"))
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split_whitespace().enumerate().filter(|(i, _)| *i != 4).map(|(_, w)| w).collect::<Vec<_>>().join(" "))
            .collect()
    };
    let a = run("sim:coastal,frames=12,seed=3", "a");
    assert_eq!(states(&a).len(), 12);
    // The seed reaches the generator: seed 3 and the flag's seed 3 give the same dive, seed 4 another.
    let b = dir.path().join("b");
    let res = duv()
        .args(["run", "--source", "sim:coastal", "--frames", "12", "--seed", "3", "--width", "160", "--height", "120", "--no-progress", "--no-map"])
        .arg("--out")
        .arg(&b)
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    assert_eq!(states(&a), states(&b));
    let c = run("sim:coastal,frames=12,seed=4", "c");
    assert_ne!(states(&a), states(&c));
    for (source, needle) in [("sim:coastal,frames=x", "not a whole number"), ("sim:coastal,depth=3", "unknown option"), ("sim:coastal,frames=5", "disagree")] {
        let res = duv().args(["run", "--source", source, "--frames", "4", "--no-progress", "--no-map"]).arg("--out").arg(dir.path().join("bad")).output().unwrap();
        assert!(!res.status.success(), "{source}");
        let stderr = String::from_utf8_lossy(&res.stderr);
        assert!(stderr.contains(needle) && !stderr.contains("panicked"), "{source}: {stderr}");
    }
}

/// `--speed 0` (or not finite) is refused before anything starts, naming the option; it used to
/// panic the capture thread and hang the process.
#[test]
fn a_speed_that_is_not_positive_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    for speed in ["0", "-1", "1e-320", "NaN", "inf"] {
        let t0 = std::time::Instant::now();
        let res = duv().args(["run", "--source", "sim:coastal", "--frames", "4", "--no-progress", "--no-map"]).arg(format!("--speed={speed}")).arg("--out").arg(dir.path().join(speed)).output().unwrap();
        let stderr = String::from_utf8_lossy(&res.stderr);
        assert!(!res.status.success(), "--speed {speed}: {stderr}");
        assert!(stderr.contains("--speed") && !stderr.contains("panicked"), "--speed {speed}: {stderr}");
        assert!(t0.elapsed() < std::time::Duration::from_secs(30), "--speed {speed} took {:?}", t0.elapsed());
    }
}

/// From a folder outside the repository the default board is the built-in copy; stderr
/// redirected to a file carries no ANSI colour codes; names are the ones the CLI takes.
#[test]
fn duv_run_works_from_any_folder_and_logs_plain_text() {
    let dir = tempfile::tempdir().unwrap();
    let res = Command::new(env!("CARGO_BIN_EXE_duv"))
        .current_dir(dir.path())
        .env("RUST_LOG", "info")
        .args(["run", "--source", "sim:coastal", "--frames", "4", "--width", "160", "--height", "120", "--no-progress", "--no-map", "--out", "run"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "{stderr}");
    assert!(dir.path().join("run/trajectory.txt").is_file());
    assert!(!stderr.contains('\u{1b}'), "ANSI codes in redirected stderr: {stderr:?}");
    assert!(stderr.contains("sim coastal water, survey path"), "{stderr}");
    // `duv replay` and `duv demo` take the same built-in board there.
    let here = |args: &[&str]| {
        let res = Command::new(env!("CARGO_BIN_EXE_duv")).current_dir(dir.path()).args(args).output().unwrap();
        assert!(res.status.success(), "{args:?}: {}", String::from_utf8_lossy(&res.stderr));
    };
    here(&["replay", "run/log", "--out", "replayed", "--no-progress", "--no-map"]);
    assert!(dir.path().join("replayed/trajectory.txt").is_file());
    here(&["demo", "--out", "demo", "--frames", "12", "--no-progress"]);
    assert!(dir.path().join("demo/demo.md").is_file());
}

/// Each bad value in a tracker or mapper config file is refused before any frame is tracked,
/// with the key and what it must be; a partial table takes the defaults for the rest.
#[test]
fn each_bad_config_value_is_refused_with_its_key_and_range() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        ("--tracker-config", "[ba]\nfixed_poses = 0\n", "fixed_poses"),
        ("--tracker-config", "[ba]\nhuber_threshold = -1.0\n", "huber"),
        ("--tracker-config", "keyframe_flow_px = -1.0\n", "keyframe_flow_px: must be finite and positive"),
        ("--tracker-config", "edge_min_overlap = 1.5\n", "edge_min_overlap: must be in [0, 1], got 1.5"),
        ("--tracker-config", "[flow]\npatch_size = 0\n", "patch_size"),
        ("--mapper-config", "window = 0\n", "window = 0 must be >= 1"),
        ("--mapper-config", "prune_min_opacity = 1.5\n", "prune_min_opacity = 1.5 must be in [0, 1]"),
        ("--mapper-config", "init_opacity = 1.0\n", "init_opacity = 1 must be in [1e-6, 1 - 1e-6]"),
    ];
    for (i, (flag, toml, needle)) in cases.iter().enumerate() {
        let cfg = dir.path().join(format!("bad-{i}.toml"));
        std::fs::write(&cfg, toml).unwrap();
        let out = dir.path().join(format!("run-{i}"));
        let res = duv().args(["run", "--source", "sim:coastal", "--frames", "3", "--width", "160", "--height", "120", "--no-progress"]).arg(flag).arg(&cfg).arg("--out").arg(&out).output().unwrap();
        let stderr = String::from_utf8_lossy(&res.stderr);
        assert_eq!(res.status.code(), Some(1), "{flag} {toml}: {stderr}");
        assert!(stderr.contains(needle) && !stderr.contains("panicked"), "{flag} {toml}: expected {needle:?} in {stderr}");
        assert!(!out.join("trajectory.txt").exists() && !out.join("log").exists(), "{flag} {toml}: the run started");
    }
    // A partial table: the rest from the defaults.
    let cfg = dir.path().join("partial.toml");
    std::fs::write(&cfg, "[ba]\nhuber_threshold = 2.0\n").unwrap();
    let res = duv().args(["run", "--source", "sim:coastal", "--frames", "3", "--width", "160", "--height", "120", "--no-progress", "--no-map", "--tracker-config"]).arg(&cfg).arg("--out").arg(dir.path().join("partial")).output().unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
}

/// Two processes on one run folder: the second is refused, naming the first's process id,
/// and the first goes on; once it has ended the folder is free again.
#[test]
fn a_second_writer_on_a_run_folder_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("dive");
    let mut first = duv()
        .args(["run", "--source", "sim:coastal,frames=600,pace=realtime", "--width", "160", "--height", "120", "--no-progress", "--no-map"])
        .arg("--out")
        .arg(&out)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let pid = first.id().to_string();
    let t0 = std::time::Instant::now();
    while std::fs::read_to_string(out.join("duv.lock")).map(|t| t.trim() != pid).unwrap_or(true) {
        assert!(t0.elapsed() < std::time::Duration::from_secs(60), "the first run never locked {}", out.display());
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let second = duv().args(["run", "--source", "sim:coastal", "--frames", "4", "--no-progress", "--no-map"]).arg("--out").arg(&out).output().unwrap();
    let stderr = String::from_utf8_lossy(&second.stderr);
    let still_running = first.try_wait().unwrap().is_none();
    let _ = first.kill();
    let _ = first.wait();
    assert!(!second.status.success(), "{stderr}");
    assert!(stderr.contains("in use by process") && stderr.contains(&pid), "{stderr}");
    assert!(still_running, "the first run must not be disturbed");
    // The holder is gone (killed): the lock went with it, and a run on the folder starts.
    let third = duv().args(["run", "--source", "sim:coastal", "--frames", "4", "--no-progress", "--no-map"]).arg("--out").arg(&out).output().unwrap();
    let stderr = String::from_utf8_lossy(&third.stderr);
    assert!(!stderr.contains("in use by process"), "{stderr}");
}
