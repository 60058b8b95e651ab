//! The onboard runtime end to end, through the built `duv` binary: replay (deterministic,
//! paced, ATE regression), shutdown on SIGTERM with mapping on (exit 143) and on a second
//! signal, a board refused for its budgets, disk
//! full, the crash harness (kill -9 at >= 20 random points, resume each time), and a kill
//! during the tracker's initialisation.

use duv_core::Se3;
use duv_log::reader::ReadLimits;
use duv_log::recover::is_finished;
use duv_log::schema::decode_pose;
use duv_log::{inspect_log, list_segments, read_segment, Topic};
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const DUV: &str = env!("CARGO_BIN_EXE_duv");
const W: &str = "160";
const H: &str = "120";

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn duv() -> Command {
    let mut c = Command::new(DUV);
    c.current_dir(root()).env("RUST_LOG", "warn");
    c
}

fn run_ok(c: &mut Command) -> String {
    let out = c.output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{c:?} failed:\n{text}");
    text
}

fn sim_run(out: &Path, frames: usize) -> Command {
    let mut c = duv();
    c.args(["run", "--source", "sim:coastal", "--width", W, "--height", H, "--no-progress", "--frames"]).arg(frames.to_string()).arg("--out").arg(out);
    c
}

/// Ground-truth positions of the generated sequence, by frame index.
fn ground_truth(frames: usize) -> Vec<Vector3<f64>> {
    let mut cfg = SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Survey);
    cfg.width = 160;
    cfg.height = 120;
    cfg.frames = frames;
    cfg.seed = 1;
    SimRenderer::new(&cfg).unwrap().poses().iter().map(|p| p.world_from_cam.translation.vector).collect()
}

/// Every `/slam/pose` in the log folder, by frame seq, with the index of the log segment that
/// wrote it last (a resumed run logs the frames it tracks again).
fn logged_poses_with_segment(log_dir: &Path) -> BTreeMap<u64, (Se3, usize)> {
    let mut poses = BTreeMap::new();
    for (i, (_, p)) in list_segments(log_dir).unwrap().iter().enumerate() {
        read_segment(p, ReadLimits::default(), |m| {
            if m.channel.topic == Topic::Pose.name() {
                poses.insert(m.sequence as u64, (decode_pose(m.data).unwrap(), i));
            }
        })
        .unwrap();
    }
    poses
}

/// Every `/slam/pose` in the log folder, by frame seq.
fn logged_poses(log_dir: &Path) -> BTreeMap<u64, Se3> {
    logged_poses_with_segment(log_dir).into_iter().map(|(seq, (pose, _))| (seq, pose)).collect()
}

/// Per-frame position error (m) of `est` (seq -> pose) after one Sim(3) alignment to `gt`.
fn aligned_errors(est: &BTreeMap<u64, Se3>, gt: &[Vector3<f64>]) -> BTreeMap<u64, f64> {
    let (src, dst): (Vec<_>, Vec<_>) = est.iter().filter(|(s, _)| (**s as usize) < gt.len()).map(|(s, p)| (p.translation.vector, gt[*s as usize])).unzip();
    let a = duv_eval::umeyama(&src, &dst, true).unwrap();
    est.iter().filter(|(s, _)| (**s as usize) < gt.len()).map(|(s, p)| (*s, (a.transform_point(&p.translation.vector.into()).coords - gt[*s as usize]).norm())).collect()
}

/// RMS of `errors` over `seqs` (all of them when `None`).
fn rms(errors: &BTreeMap<u64, f64>, seqs: Option<&[u64]>) -> f64 {
    let picked: Vec<f64> = match seqs {
        Some(seqs) => seqs.iter().filter_map(|s| errors.get(s).copied()).collect(),
        None => errors.values().copied().collect(),
    };
    (picked.iter().map(|x| x * x).sum::<f64>() / picked.len().max(1) as f64).sqrt()
}

/// ATE RMSE (m) after Sim(3) alignment of `est` (seq -> pose) to `gt`.
fn ate(est: &BTreeMap<u64, Se3>, gt: &[Vector3<f64>]) -> f64 {
    rms(&aligned_errors(est, gt), None)
}

/// The rows of `states.txt` (`seq t state pose tracker_ms [why]`), split at whitespace.
fn states_rows(p: &Path) -> Vec<Vec<String>> {
    std::fs::read_to_string(p)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(str::to_string).collect())
        .collect()
}

/// `states.txt`: frame number -> state.
fn read_states(p: &Path) -> BTreeMap<u64, String> {
    states_rows(p).into_iter().map(|v| (v[0].parse().unwrap(), v[2].clone())).collect()
}

/// Distinct frame numbers of the logged camera frames, and how many camera messages there are.
fn logged_frame_seqs(log_dir: &Path) -> (std::collections::BTreeSet<u64>, usize) {
    let mut seqs = std::collections::BTreeSet::new();
    let mut messages = 0;
    for (_, p) in list_segments(log_dir).unwrap() {
        read_segment(&p, ReadLimits::default(), |m| {
            if m.channel.topic == Topic::CameraImage.name() {
                seqs.insert(m.sequence as u64);
                messages += 1;
            }
        })
        .unwrap();
    }
    (seqs, messages)
}

/// Ids of the logged keyframes (`/keyframe/pose`, sequence = keyframe id).
fn logged_keyframe_ids(log_dir: &Path) -> std::collections::BTreeSet<u64> {
    let mut ids = std::collections::BTreeSet::new();
    for (_, p) in list_segments(log_dir).unwrap() {
        read_segment(&p, ReadLimits::default(), |m| {
            if m.channel.topic == Topic::KeyframePose.name() {
                ids.insert(m.sequence as u64);
            }
        })
        .unwrap();
    }
    ids
}

/// Walks an undamaged (possibly unfinished) MCAP file record by record and returns each
/// whole chunk's offset, length and message count (by the `mcap` crate's chunk reader):
/// an independent count, not the log's salvaging reader.
fn chunk_extents(bytes: &[u8]) -> Vec<(u64, u64, u64)> {
    let mut out = Vec::new();
    let mut p = 8usize;
    while p + 9 <= bytes.len() {
        let op = bytes[p];
        let len = u64::from_le_bytes(bytes[p + 1..p + 9].try_into().unwrap()) as usize;
        if p + 9 + len > bytes.len() {
            break;
        }
        if op == 0x06 {
            if let Ok(mcap::records::Record::Chunk { header, data }) = mcap::parse_record(op, &bytes[p + 9..p + 9 + len]) {
                let n = mcap::read::ChunkReader::new(header, &data).unwrap().filter(|r| matches!(r, Ok(mcap::records::Record::Message { .. }))).count();
                out.push((p as u64, (9 + len) as u64, n as u64));
            }
        }
        p += 9 + len;
    }
    out
}

/// Messages in a finished MCAP file, through the `mcap` crate's summary and chunk indexes.
fn indexed_messages(bytes: &[u8]) -> u64 {
    let summary = mcap::read::Summary::read(bytes).unwrap().expect("a summary");
    summary.chunk_indexes.iter().map(|ci| summary.stream_chunk(bytes, ci).unwrap().count() as u64).sum()
}

/// A run killed with kill -9, its unfinished segment then damaged (a flipped byte inside a
/// chunk, the tail cut off inside another): the next start recovers every chunk the damage
/// did not touch (counted independently, by the `mcap` crate, before and after), and the
/// final `trajectory.txt` holds every frame whose pose is in the log.
#[test]
fn a_damaged_unfinished_segment_is_salvaged_on_resume() {
    const FRAMES: usize = 150;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let mut child = sim_run(&out, FRAMES).args(["--no-map", "--announce"]).stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let lines = BufReader::new(child.stdout.take().unwrap()).lines().map_while(Result::ok);
    let tracked = lines.filter(|l| l.starts_with("tracked ")).take(90).count();
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(tracked, 90);
    let seg = list_segments(&out.join("log")).unwrap()[0].1.clone();
    let bytes = std::fs::read(&seg).unwrap();
    assert!(!is_finished(&seg).unwrap());
    let chunks = chunk_extents(&bytes);
    assert!(chunks.len() >= 8, "{} chunks", chunks.len());
    let n = chunks.len();
    let flip = chunks[n / 3].0 + chunks[n / 3].1 / 2;
    let cut = chunks[n - 2].0 + chunks[n - 2].1 / 2;
    let expected: u64 = chunks.iter().enumerate().filter(|(i, (o, l, _))| *i != n / 3 && o + l <= cut).map(|(_, c)| c.2).sum();
    let mut damaged = bytes[..cut as usize].to_vec();
    damaged[flip as usize] ^= 0x40;
    std::fs::write(&seg, &damaged).unwrap();

    let text = run_ok(sim_run(&out, FRAMES).arg("--no-map"));
    assert!(text.contains("recovered") && text.contains("damaged range(s) skipped"), "{text}");
    let recovered = std::fs::read(&seg).unwrap();
    let kept = indexed_messages(&recovered);
    eprintln!("damaged segment: {kept} messages salvaged, {expected} in chunks the damage did not touch (of {} before the damage)", chunks.iter().map(|c| c.2).sum::<u64>());
    assert_eq!(kept, expected);
    let poses = logged_poses(&out.join("log"));
    let states = read_states(&out.join("states.txt"));
    assert_eq!(states.keys().copied().collect::<Vec<_>>(), poses.keys().copied().collect::<Vec<_>>());
    // trajectory.txt: the frames with a pose estimate (the initialising frames' logged poses
    // were provisional), every one after the initialisation.
    let with_pose = frames_with_pose(&out.join("states.txt"));
    assert_eq!(read_trajectory(&out.join("trajectory.txt")).keys().copied().collect::<Vec<_>>(), with_pose);
    let tracked: Vec<u64> = states.iter().filter(|(_, s)| *s == "tracking" || *s == "relocalised").map(|(k, _)| *k).collect();
    assert!(tracked.len() >= 90 && tracked.iter().all(|k| with_pose.contains(k)), "tracked {tracked:?}, with a pose {with_pose:?}");
}

fn read_trajectory(p: &Path) -> BTreeMap<u64, Se3> {
    // TUM lines by frame number, through the time stamps of `states.txt` beside it (frames
    // without a pose estimate are in `states.txt` only).
    let seq_of: BTreeMap<String, u64> = states_rows(&p.with_file_name("states.txt")).into_iter().map(|v| (v[1].clone(), v[0].parse().unwrap())).collect();
    let text = std::fs::read_to_string(p).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let stamp = l.split_whitespace().next().unwrap();
            let v: Vec<f64> = l.split_whitespace().skip(1).map(|x| x.parse().unwrap()).collect();
            (seq_of[stamp], duv_core::pose::se3_from_tum([v[0], v[1], v[2], v[3], v[4], v[5], v[6]]).unwrap())
        })
        .collect()
}

/// Frame numbers of `states.txt` whose pose column says they have a pose estimate.
fn frames_with_pose(p: &Path) -> Vec<u64> {
    states_rows(p).into_iter().filter(|v| v[3] != "none").map(|v| v[0].parse().unwrap()).collect()
}

#[test]
fn replay_is_deterministic_paced_and_accurate() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("recorded");
    run_ok(&mut sim_run(&rec, 60));
    assert!(is_finished(&rec.join("log/segment-000000.mcap")).unwrap());
    let inspect = run_ok(duv().arg("inspect").arg(&rec));
    assert!(inspect.contains("/camera/image") && inspect.contains("complete"), "{inspect}");

    // Deterministic replay: bit-identical trajectories, and the log replays as the run saw it.
    let r1 = dir.path().join("r1");
    let r2 = dir.path().join("r2");
    // Replay runs the whole pipeline, mapping included: the map is bit-identical too.
    let mapped = ["--deterministic", "--no-progress", "--mapper", "cpu", "--map-iterations", "2", "--map-final-iterations", "4"];
    run_ok(duv().arg("replay").arg(&rec).arg("--out").arg(&r1).args(mapped));
    run_ok(duv().arg("replay").arg(&rec).arg("--out").arg(&r2).args(mapped));
    let t1 = std::fs::read(r1.join("trajectory.txt")).unwrap();
    let t2 = std::fs::read(r2.join("trajectory.txt")).unwrap();
    assert_eq!(String::from_utf8_lossy(&t1).lines().filter(|l| !l.starts_with('#')).count(), 60);
    assert!(t1 == t2, "deterministic replays differ");
    assert_eq!(std::fs::read(r1.join("keyframes.txt")).unwrap(), std::fs::read(r2.join("keyframes.txt")).unwrap());
    let ply1 = std::fs::read(r1.join("map.ply")).expect("a replay exports the map");
    assert!(ply1.len() > 1000, "map.ply of {} bytes", ply1.len());
    assert!(ply1 == std::fs::read(r2.join("map.ply")).unwrap(), "deterministic replays mapped differently");
    assert_eq!(std::fs::read(r1.join("medium.json")).unwrap(), std::fs::read(r2.join("medium.json")).unwrap());

    // Regression: the replayed trajectory against the generator's ground truth.
    let gt = ground_truth(60);
    let replay_ate = ate(&read_trajectory(&r1.join("trajectory.txt")), &gt);
    let path_len: f64 = gt.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    eprintln!("replay ATE {replay_ate:.4} m over a {path_len:.2} m path");
    assert!(replay_ate < 0.01 * path_len, "replay ATE {replay_ate} m, path {path_len} m");

    // Paced replay at recorded timing x2: 20 frames span 1.9 s of recorded time.
    let t0 = Instant::now();
    run_ok(duv().arg("replay").arg(&rec).arg("--out").arg(dir.path().join("paced")).args(["--speed", "2", "--frames", "20", "--no-progress", "--no-map"]));
    assert!(t0.elapsed() >= Duration::from_secs_f64(1.9 / 2.0), "paced replay took {:?}", t0.elapsed());
}

/// `boards/sim.toml` with every input frame logged as JPEG, written into `dir`.
fn jpeg_board(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(root().join("boards/sim.toml")).unwrap();
    let jpeg = text.replace("frame_encoding = \"raw\"", "frame_encoding = \"jpeg\"");
    assert_ne!(jpeg, text, "boards/sim.toml has no `frame_encoding = \"raw\"` line");
    let p = dir.join("sim-jpeg.toml");
    std::fs::write(&p, jpeg).unwrap();
    p
}

#[test]
fn jpeg_logged_run_resumes_inspects_and_replays() {
    let dir = tempfile::tempdir().unwrap();
    let board = jpeg_board(dir.path());
    let rec = dir.path().join("recorded");
    // 60 frames: at 160x120 the survey initialises after about 50 (keyframes are logged only
    // once the initial BA has run).
    run_ok(sim_run(&rec, 60).arg("--board").arg(&board).arg("--no-map"));
    let inspect = run_ok(duv().arg("inspect").arg(&rec));
    assert!(inspect.lines().any(|l| l.starts_with("/camera/image") && l.contains("foxglove.CompressedImage") && l.contains(" 60 ")), "{inspect}");
    // Resume reads the logged keyframes and the JPEG frames after them back to relocalise.
    // A finished dive is left as it is; --continue tracks the longer source on.
    let again = run_ok(sim_run(&rec, 90).arg("--board").arg(&board).arg("--no-map"));
    assert!(again.contains("holds a finished dive: 60 frames"), "{again}");
    let resumed = run_ok(sim_run(&rec, 90).arg("--board").arg(&board).args(["--no-map", "--continue"]));
    assert!(resumed.contains("in the recorded frame and scale; tracking") && resumed.contains("logged frames again"), "{resumed}");
    // Replay of the whole JPEG log (two segments): every frame, and the trajectory holds the
    // bound of the raw replay above. JPEG is lossy, so the replay is not the recorded run: on
    // this sequence it measured 0.33% of the path against 0.17% for a raw log.
    let r1 = dir.path().join("r1");
    run_ok(duv().arg("replay").arg(&rec).arg("--out").arg(&r1).args(["--deterministic", "--no-progress", "--no-map"]));
    let traj = read_trajectory(&r1.join("trajectory.txt"));
    assert_eq!(read_states(&r1.join("states.txt")).len(), 90);
    assert_eq!(traj.keys().copied().collect::<Vec<_>>(), frames_with_pose(&r1.join("states.txt")));
    assert!(traj.len() >= 80, "{} frames with a pose", traj.len());
    let gt = ground_truth(90);
    let replay_ate = ate(&traj, &gt);
    let path_len: f64 = gt.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    eprintln!("JPEG-logged replay ATE {replay_ate:.4} m over a {path_len:.2} m path");
    assert!(replay_ate < 0.01 * path_len, "JPEG replay ATE {replay_ate} m, path {path_len} m");
}

/// `tests/py/check_ros2_bag.py` (the `rosbags` package) on a log folder: it opens as a ROS 2
/// bag and every message deserialises; the counts per topic are our reader's. Skipped, saying
/// so, without Python and `rosbags`; a failure under CI=true or with DUV_PYTHON set.
fn rosbags_agrees(log_dir: &Path) {
    let candidates: Vec<PathBuf> = std::env::var_os("DUV_PYTHON").map(PathBuf::from).into_iter().chain([root().join("target/py-mcap/bin/python"), PathBuf::from("python3")]).collect();
    let Some(py) = candidates.into_iter().find(|py| Command::new(py).args(["-c", "import rosbags.rosbag2"]).output().is_ok_and(|o| o.status.success())) else {
        assert!(std::env::var("CI").as_deref() != Ok("true") && std::env::var_os("DUV_PYTHON").is_none(), "no Python with the `rosbags` package (run .ci/run, or set DUV_PYTHON)");
        eprintln!("SKIPPED the rosbags cross-check: no Python with the `rosbags` package");
        return;
    };
    let out = Command::new(py).arg(root().join("tests/py/check_ros2_bag.py")).arg(log_dir).output().unwrap();
    assert!(out.status.success(), "rosbags: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["errors"], serde_json::json!([]), "{v}");
    let mut ours: BTreeMap<String, u64> = BTreeMap::new();
    for (_, p) in list_segments(log_dir).unwrap() {
        read_segment(&p, ReadLimits::default(), |m| *ours.entry(m.channel.topic.clone()).or_default() += 1).unwrap();
    }
    let theirs: BTreeMap<String, u64> = v["counts"].as_object().unwrap().iter().map(|(k, n)| (k.clone(), n.as_u64().unwrap())).collect();
    assert_eq!(theirs, ours, "rosbags against our reader");
}

/// A run logged as a ROS 2 bag (`--log-format ros2`): `duv inspect` names the format and the
/// ROS types, `rosbags` reads it, a deterministic replay of it tracks exactly as a replay of the
/// same run logged in the Foxglove format (raw frames are lossless in both), and it resumes.
#[test]
fn a_ros2_logged_run_is_a_bag_that_replays_and_resumes_like_the_foxglove_one() {
    let dir = tempfile::tempdir().unwrap();
    let (fox, ros) = (dir.path().join("fox"), dir.path().join("ros"));
    run_ok(sim_run(&fox, 60).arg("--no-map"));
    run_ok(sim_run(&ros, 60).args(["--no-map", "--log-format", "ros2"]));
    let inspect = run_ok(duv().arg("inspect").arg(&ros));
    assert!(inspect.contains("format ros2"), "{inspect}");
    assert!(inspect.lines().any(|l| l.starts_with("/camera/image") && l.contains("sensor_msgs/msg/Image") && l.contains(" 60 ")), "{inspect}");
    assert!(inspect.lines().any(|l| l.starts_with("/slam/state") && l.contains("duv_msgs/msg/TrackingState")), "{inspect}");
    assert!(ros.join("log/metadata.yaml").is_file());
    rosbags_agrees(&ros.join("log"));
    let bad = duv().args(["run", "--source", "sim:coastal", "--log-format", "rosbag", "--out"]).arg(dir.path().join("bad")).output().unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("rosbag") && err.contains("foxglove") && err.contains("ros2"), "{err}");

    let replay = |log: &Path, out: &Path| {
        run_ok(duv().arg("replay").arg(log).arg("--out").arg(out).args(["--deterministic", "--no-progress", "--no-map"]));
        std::fs::read(out.join("trajectory.txt")).unwrap()
    };
    let (t_fox, t_ros) = (replay(&fox, &dir.path().join("r-fox")), replay(&ros, &dir.path().join("r-ros")));
    assert_eq!(String::from_utf8_lossy(&t_ros).lines().filter(|l| !l.starts_with('#')).count(), 60);
    assert!(t_fox == t_ros, "replays of the Foxglove and the ROS 2 log differ");

    // Resume reads the CDR log back (poses, states, window, keyframes and their frames).
    let resumed = run_ok(sim_run(&ros, 90).args(["--no-map", "--continue", "--log-format", "ros2"]));
    assert!(resumed.contains("in the recorded frame and scale; tracking") && resumed.contains("logged frames again"), "{resumed}");
    assert_eq!(read_states(&ros.join("states.txt")).len(), 90);
    assert!(list_segments(&ros.join("log")).unwrap().len() >= 2);
    rosbags_agrees(&ros.join("log"));
}

/// Sends `signal` to `child` and returns the seconds until it exited, with its exit code.
fn signal_and_wait(child: &mut std::process::Child, signals: &[&str]) -> (f64, Option<i32>) {
    let t0 = Instant::now();
    for (i, sig) in signals.iter().enumerate() {
        if i > 0 {
            std::thread::sleep(Duration::from_millis(100));
        }
        assert!(Command::new("kill").args([&format!("-{sig}"), &child.id().to_string()]).status().unwrap().success());
    }
    let status = child.wait().unwrap();
    (t0.elapsed().as_secs_f64(), status.code())
}

/// SIGTERM with mapping on (the CPU mapper, behind its queue on 2 cores): the mapper's queue
/// and final optimisation are abandoned, the log closes, the outputs are written, and the
/// process exits 143. It took 82-85 s when the mapper finished its queue first; the 2 s
/// target is measured, not asserted here (a loaded CI machine is no timer), but a bound far
/// below the old behaviour catches a shutdown that waits for the mapper again.
#[test]
fn sigterm_closes_the_log_and_exits_143_without_waiting_for_the_mapper() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let mut child = sim_run(&out, 2000).arg("--map-final-iterations").arg("100000").stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    // Until the mapper has keyframes to be busy with.
    let started = Instant::now();
    while !out.join("keyframes").read_dir().is_ok_and(|mut d| d.next().is_some()) && started.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(200));
    }
    std::thread::sleep(Duration::from_secs(2));
    let (secs, code) = signal_and_wait(&mut child, &["TERM"]);
    eprintln!("SIGTERM to exit with mapping on: {secs:.2} s");
    let mut stderr = String::new();
    std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut stderr).unwrap();
    assert_eq!(code, Some(143), "{stderr}");
    assert!(stderr.contains("stopped by signal 15"), "{stderr}");
    assert!(secs < 20.0, "{secs:.1} s from SIGTERM to exit");
    let segs = list_segments(&out.join("log")).unwrap();
    assert_eq!(segs.len(), 1);
    assert!(is_finished(&segs[0].1).unwrap(), "the log was not finished on SIGTERM");
    let s = inspect_log(&out.join("log"), ReadLimits::default()).unwrap();
    assert!(s.segments[0].complete && s.segments[0].damage.is_none());
    let frames = s.topics["/camera/image"].messages;
    assert!(frames > 0 && frames < 2000, "{frames} frames");
    // The outputs describe what was tracked, the map is exported as it was.
    let traj = read_trajectory(&out.join("trajectory.txt"));
    assert!(traj.len() as u64 + 8 >= frames && !traj.is_empty(), "{} poses, {frames} frames logged", traj.len());
    assert!(out.join("map.ply").is_file());
}

/// A second signal: the log is closed and the process ends at once, exit 130 for SIGINT.
#[test]
fn a_second_signal_closes_the_log_and_exits_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let mut child = sim_run(&out, 2000).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
    std::thread::sleep(Duration::from_secs(4));
    let (secs, code) = signal_and_wait(&mut child, &["INT", "INT"]);
    eprintln!("two SIGINTs to exit: {secs:.2} s");
    assert_eq!(code, Some(130));
    let segs = list_segments(&out.join("log")).unwrap();
    assert!(is_finished(&segs[0].1).unwrap(), "the log was not closed after the second signal");
}

#[test]
fn a_board_too_small_for_the_resolution_is_refused_with_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let board = std::fs::read_to_string(root().join("boards/sim.toml")).unwrap().replace("host_mb = 1024", "host_mb = 40");
    let path = dir.path().join("small.toml");
    std::fs::write(&path, board).unwrap();
    let out = duv().args(["run", "--source", "sim:coastal", "--frames", "5", "--width", "640", "--height", "480", "--board"]).arg(&path).arg("--out").arg(dir.path().join("o")).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("refused") && err.contains("budgets.host_mb = 40") && err.contains("640x480 needs"), "{err}");
}

/// Runs `duv run` on 160x120 `sim:coastal` under a file-size limit of `limit_kib` (every write
/// past it fails with EFBIG, like a full disk), returning the exit code and the output.
fn run_with_file_limit(out: &Path, limit_kib: u32, frames: usize, extra: &[&str]) -> (Option<i32>, String) {
    let mut c = Command::new("bash");
    c.current_dir(root()).env("RUST_LOG", "error").arg("-c").arg(format!("ulimit -f {limit_kib}; trap '' XFSZ; exec \"$0\" \"$@\"")).arg(DUV);
    c.args(["run", "--source", "sim:coastal", "--width", W, "--height", H, "--no-progress", "--frames"]).arg(frames.to_string()).args(extra).arg("--out").arg(out);
    let o = c.output().unwrap();
    (o.status.code(), format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
}

/// A full disk: logging stops cleanly and says so, tracking continues, the outputs are still
/// written, and the exit status (3) says the log is incomplete.
#[test]
fn disk_full_stops_logging_and_tracking_continues() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let (code, text) = run_with_file_limit(&out, 1200, 40, &["--no-map"]);
    assert_eq!(code, Some(3), "{text}");
    assert!(text.contains("LOGGING STOPPED") && text.contains("the log is incomplete"), "{text}");
    assert!(text.contains("40 tracked"), "{text}");
    assert_eq!(read_states(&out.join("states.txt")).len(), 40);
    let traj = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    assert_eq!(traj.lines().filter(|l| !l.starts_with('#')).count(), frames_with_pose(&out.join("states.txt")).len());
    // What reached the disk before the failure is readable.
    let seg = &list_segments(&out.join("log")).unwrap()[0].1;
    let mut frames = 0;
    let outcome = read_segment(seg, ReadLimits::default(), |m| frames += (m.channel.topic == "/camera/image") as u32).unwrap();
    assert!(frames >= 1, "{outcome:?}");
}

/// With mapping on, the map checkpoints and the map export fail too: mapping goes on, the
/// tracking outputs and `dive.json` are written, no partial file is left behind.
#[test]
fn disk_full_with_mapping_keeps_mapping_and_writes_the_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let (code, text) = run_with_file_limit(&out, 1200, 120, &[]);
    assert_eq!(code, Some(3), "{text}");
    assert!(text.contains("map checkpoint not written") && text.contains("mapping goes on"), "{text}");
    assert!(text.contains("120 tracked") && !text.contains("panicked"), "{text}");
    let traj = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    assert_eq!(traj.lines().filter(|l| !l.starts_with('#')).count(), 120);
    assert!(out.join("keyframes.txt").is_file() && out.join("dive.json").is_file());
    let leftovers: Vec<_> = walk_files(&out).into_iter().filter(|p| p.extension().is_some_and(|e| e == "tmp")).collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

fn walk_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk_files(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// What the child said, with when the harness heard it.
#[derive(Default)]
struct Heard {
    tracked: Vec<(u64, Instant)>,
    /// Per segment path: the last (messages, bytes) synced.
    synced: BTreeMap<PathBuf, (u64, u64)>,
}

/// The crash harness maps every keyframe (the map's resume is under test, not its quality)
/// with a few iterations each: with the defaults the final start's mapping of the whole
/// dive's keyframes took most of the harness's 21 CPU minutes in the test profile.
const HARNESS_MAP: [&str; 6] = ["--map-iterations", "3", "--map-idle-iterations", "3", "--map-final-iterations", "5"];

/// The crash harness: kill -9 at 20 points, resume each time. Every chunk synced
/// before a kill is readable, at most 1 s of data is lost per kill, and the combined
/// trajectory continues in the recorded frame: its ATE is within 2x an uninterrupted run's
/// (a resume in a new frame or scale costs metres on this 15 m survey).
/// Each start seeds its tracker with the newest logged tracker window (`/slam/window`, twice a
/// second of frame time) and tracks the logged frames after it again. The kill points are
/// counted in frames, so a slower machine kills at the same points (with wall-clock delays a
/// CI run once killed elsewhere and measured 0.229 m against 0.140 m, not reproduced since).
/// A kill during the initialisation (the first lands at 40-54 frames, about when it ends)
/// restarts it from the logged frames, which reproduces it exactly; seeding from its
/// provisional poses instead once measured 1.54x on CI. Measured with a busy-loop process
/// loading one of the two cores: ATE 0.1397 m combined against 0.1399 m uninterrupted (kill
/// seeds 1-3: 0.1379, 0.1399, 0.1382 m). On failure the per-segment errors printed show
/// where the runs part.
///
/// Three CI runs on slower machines failed the earlier bound of 1.5x: 1.64x (0.2293 m),
/// 1.54x (before the initialisation restart) and 2.12x (0.3007 m against 0.1418 m); here,
/// with a build loading both cores, 1.85x (0.2628 m). Which logged window a start is seeded
/// with depends on how far the log writer got before the kill, and a window logged right
/// after a keyframe insertion can hold a newest keyframe whose deferred depth rounds had not
/// run yet (the likeliest reading of what the fix below changed): the
/// seeded tracker tracked against that depth and its frames drifted up to 0.7 cm per frame
/// from the uninterrupted run's until the next keyframe, 0.44 m at worst after 15 resumes.
/// Seeding now re-solves the window's depth with every pose held as recorded
/// (`Tracker::seed`): with two busy loops on both cores 0.1440 m (1.02x, at most 2.9 cm from
/// the uninterrupted run's poses); kill seed 1: 0.1435 m (1.01x, 2.9 cm); kill seed 2, two busy
/// loops: 0.1437 m (1.01x).
#[test]
fn crash_harness_kill_9_and_resume() {
    const FRAMES: usize = 300;
    const KILLS: usize = 20;
    let started = Instant::now();
    let mut dir = tempfile::tempdir().unwrap();
    // DUV_KEEP_HARNESS=1 keeps the logs of both runs for a look afterwards.
    if std::env::var_os("DUV_KEEP_HARNESS").is_some() {
        dir.disable_cleanup(true);
        eprintln!("crash harness: keeping {}", dir.path().display());
    }
    let out = dir.path().join("run");
    // DUV_HARNESS_SEED=N draws other kill points.
    let mut rng = std::env::var("DUV_HARNESS_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(0x5eed_u64);
    let mut next = move || {
        rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (rng >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut losses_s: Vec<f64> = Vec::new();
    let mut kills = 0;
    let mut kills_after_a_sync = 0;
    let mut finished = false;
    while !finished {
        let err_path = dir.path().join(format!("start-{kills:02}.stderr"));
        let mut child = sim_run(&out, FRAMES).args(HARNESS_MAP).arg("--announce").stdout(Stdio::piped()).stderr(std::fs::File::create(&err_path).unwrap()).spawn().unwrap();
        let heard = Arc::new(Mutex::new(Heard::default()));
        let reader = {
            let heard = heard.clone();
            let stdout = child.stdout.take().unwrap();
            std::thread::spawn(move || {
                for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                    let now = Instant::now();
                    let mut h = heard.lock().unwrap();
                    let mut it = line.split_whitespace();
                    match it.next() {
                        Some("tracked") => h.tracked.push((it.next().unwrap().parse().unwrap(), now)),
                        Some("synced") => {
                            let p = PathBuf::from(it.next().unwrap());
                            let m: u64 = it.next().unwrap().parse().unwrap();
                            let b: u64 = it.next().unwrap().parse().unwrap();
                            h.synced.insert(p, (m, b));
                        }
                        _ => {}
                    }
                }
            })
        };
        if kills < KILLS {
            // Most kills land while frames flow: after 6-20 new poses of this start (40-54 for
            // the first), counted in frames so that the kill points do not depend on how fast
            // the machine is. Every fourth lands during start-up itself (recovery,
            // relocalisation): 0.1-1.6 s after the process starts.
            let during_startup = kills % 4 == 3;
            let poses_before_kill = if kills == 0 { 40 } else { 6 } + (15.0 * next()) as usize;
            let startup_delay_s = 0.1 + 1.5 * next();
            let spawned = Instant::now();
            while child.try_wait().unwrap().is_none() && spawned.elapsed() < Duration::from_secs(60) {
                let due = match during_startup {
                    true => spawned.elapsed() >= Duration::from_secs_f64(startup_delay_s),
                    false => heard.lock().unwrap().tracked.len() >= poses_before_kill,
                };
                if due {
                    break;
                }
                std::thread::sleep(Duration::from_millis(2));
            }
            if child.try_wait().unwrap().is_none() {
                child.kill().unwrap(); // SIGKILL
                let killed_at = Instant::now();
                child.wait().unwrap();
                reader.join().unwrap();
                kills += 1;
                let h = heard.lock().unwrap();
                kills_after_a_sync += (!h.synced.is_empty()) as usize;
                // Every chunk synced before the kill is readable, before any recovery.
                for (path, &(messages, _)) in &h.synced {
                    let outcome = read_segment(path, ReadLimits::default(), |_| {}).unwrap();
                    assert!(outcome.messages >= messages, "kill {kills}: {} has {} readable messages, {messages} were synced", path.display(), outcome.messages);
                }
                // Data lost: the age at the kill of the oldest pose this process announced
                // that did not reach the disk (0 when every announced pose is on disk).
                let on_disk = logged_poses(&out.join("log"));
                let lost = h
                    .tracked
                    .iter()
                    .find(|(seq, _)| !on_disk.contains_key(seq))
                    .map(|&(_, at)| killed_at.duration_since(at).as_secs_f64())
                    .unwrap_or(0.0);
                losses_s.push(lost);
                continue;
            }
        }
        let status = child.wait().unwrap();
        reader.join().unwrap();
        assert!(status.success(), "the final resumed run failed: {status}");
        finished = true;
    }
    assert!(kills >= KILLS, "only {kills} kills: the run finished too early");
    for k in 0..=kills {
        let text = std::fs::read_to_string(dir.path().join(format!("start-{k:02}.stderr"))).unwrap_or_default();
        for l in text.lines().filter(|l| l.contains("resumed") || l.contains("error")) {
            eprintln!("start {k}: {l}");
        }
    }
    let harness_s = started.elapsed().as_secs_f64();

    // Every segment is a valid file after the last resume; the poses cover the sequence.
    let log_dir = out.join("log");
    for (_, p) in list_segments(&log_dir).unwrap() {
        assert!(is_finished(&p).unwrap(), "{} unfinished", p.display());
    }
    let combined_with_segment = logged_poses_with_segment(&log_dir);
    let combined: BTreeMap<u64, Se3> = combined_with_segment.iter().map(|(seq, (pose, _))| (*seq, *pose)).collect();
    assert_eq!(combined.keys().next_back().copied(), Some(FRAMES as u64 - 1));
    // The files users read describe the whole dive: a pose for every frame whose pose
    // reached the log, across all the processes that worked on it.
    let states = read_states(&out.join("states.txt"));
    assert_eq!(states.keys().copied().collect::<Vec<_>>(), combined.keys().copied().collect::<Vec<_>>(), "states.txt frames differ from the logged poses");
    let with_pose = frames_with_pose(&out.join("states.txt"));
    assert_eq!(read_trajectory(&out.join("trajectory.txt")).keys().copied().collect::<Vec<_>>(), with_pose);
    let first_tracked = states.iter().find(|(_, s)| *s == "tracking").map(|(k, _)| *k).unwrap();
    assert!(combined.keys().filter(|&&k| k > first_tracked).all(|k| with_pose.contains(k)), "frames after the initialisation without a pose: {with_pose:?}");
    let (frames_logged, camera_messages) = logged_frame_seqs(&log_dir);
    eprintln!("final trajectory.txt: {} poses; {} frames logged in {camera_messages} camera messages", combined.len(), frames_logged.len());
    assert_eq!(frames_logged.len(), FRAMES);
    // No frame logged twice: a start tracks the frames the stopped run logged but had not
    // tracked from the log, and its source goes on after them.
    assert_eq!(camera_messages, FRAMES);
    // The map covers every logged keyframe: each was fed to mapping (its image is in the
    // keyframe folder) and is listed in keyframes.txt.
    let logged_keyframes = logged_keyframe_ids(&log_dir);
    let listed: std::collections::BTreeSet<u64> = std::fs::read_to_string(out.join("keyframes.txt")).unwrap().lines().filter(|l| !l.starts_with('#')).map(|l| l.split_whitespace().next().unwrap().parse().unwrap()).collect();
    let unmapped: Vec<u64> = logged_keyframes.iter().copied().filter(|id| !out.join("keyframes").join(format!("{id:06}.png")).exists()).collect();
    eprintln!("keyframes: {} logged, {} in keyframes.txt, {} not mapped", logged_keyframes.len(), listed.len(), unmapped.len());
    assert!(unmapped.is_empty(), "logged keyframes never mapped: {unmapped:?}");
    assert!(logged_keyframes.is_subset(&listed), "logged keyframes missing from keyframes.txt: {:?}", logged_keyframes.difference(&listed).collect::<Vec<_>>());
    assert!(out.join("map.ply").is_file());
    let dive: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("dive.json")).unwrap()).unwrap();
    assert_eq!(dive["finished"], true);
    assert_eq!(dive["frames"].as_u64(), Some(FRAMES as u64));
    assert!(dive["parts"].as_array().unwrap().len() > kills_after_a_sync, "{dive}");
    // Started again, the finished dive is left as it is.
    let before = std::fs::read(out.join("trajectory.txt")).unwrap();
    let again = run_ok(sim_run(&out, FRAMES).args(HARNESS_MAP));
    assert!(again.contains("holds a finished dive") && again.contains("nothing changed"), "{again}");
    assert_eq!(std::fs::read(out.join("trajectory.txt")).unwrap(), before);
    assert_eq!(list_segments(&log_dir).unwrap().len(), dive["log_segments"].as_u64().unwrap() as usize);
    let summary = inspect_log(&log_dir, ReadLimits::default()).unwrap();
    let recovered = summary.segments.iter().filter(|s| s.recovered.is_some()).count();
    // Each kill after the first fsync left one unfinished segment, recovered on the next start.
    assert!(recovered >= kills_after_a_sync, "{recovered} recovered segments, {kills_after_a_sync} kills after a sync");

    // The same sequence without interruption.
    let clean = dir.path().join("clean");
    // Tracking only: the poses do not depend on the mapper (a generated source waits for the
    // tracker, no frame is dropped).
    run_ok(sim_run(&clean, FRAMES).arg("--no-map"));
    let gt = ground_truth(FRAMES);
    let (err_combined, err_clean) = (aligned_errors(&combined, &gt), aligned_errors(&logged_poses(&clean.join("log")), &gt));
    let (ate_combined, ate_clean) = (rms(&err_combined, None), rms(&err_clean, None));
    // Where the combined trajectory departs from the uninterrupted one: per log segment, the
    // frames whose pose it wrote last and their RMS error in both runs (one alignment each).
    let mut by_segment: BTreeMap<usize, Vec<u64>> = BTreeMap::new();
    for (seq, (_, segment)) in &combined_with_segment {
        by_segment.entry(*segment).or_default().push(*seq);
    }
    for (i, seqs) in &by_segment {
        eprintln!(
            "segment {i}: frames {}-{} ({}), RMS error combined {:.4} m, uninterrupted {:.4} m",
            seqs[0],
            seqs[seqs.len() - 1],
            seqs.len(),
            rms(&err_combined, Some(seqs)),
            rms(&err_clean, Some(seqs))
        );
    }
    losses_s.sort_by(f64::total_cmp);
    let max_loss = *losses_s.last().unwrap();
    eprintln!(
        "crash harness: {kills} kills in {harness_s:.1} s; data lost per kill median {:.3} s, max {max_loss:.3} s; {} of {FRAMES} poses logged; ATE combined {ate_combined:.4} m, uninterrupted {ate_clean:.4} m",
        losses_s[losses_s.len() / 2],
        combined.len()
    );
    assert!(max_loss <= 1.0, "lost {max_loss:.3} s of data at one kill (losses {losses_s:?})");
    assert!(ate_combined <= 2.0 * ate_clean, "ATE combined {ate_combined} > 2 x uninterrupted {ate_clean}");
}

/// A power cut during the tracker's initialisation (no window or keyframe logged yet): the
/// next start tracks the logged frames again from the tracker's first, so the initialisation
/// is rebuilt as it was and the run goes on exactly as if never stopped. The tracker is
/// deterministic, so every recorded pose matches an uninterrupted run's (measured: identical
/// to the last bit). Seeding a tracker with the provisional poses of an unfinished
/// initialisation instead once cost the crash harness 1.54x its uninterrupted ATE.
#[test]
fn a_run_killed_during_its_initialisation_resumes_as_if_never_stopped() {
    const FRAMES: usize = 90;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    // Killed after 25 tracked frames: the initialisation (8 keyframes) takes ~50.
    let mut child = sim_run(&out, FRAMES).args(["--no-map", "--announce"]).stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let lines = BufReader::new(child.stdout.take().unwrap()).lines().map_while(Result::ok);
    let tracked = lines.filter(|l| l.starts_with("tracked ")).take(25).count();
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(tracked, 25, "the run ended before 25 frames were tracked");
    let before = logged_poses(&out.join("log"));
    assert!(!before.is_empty() && before.len() < 40, "{} poses logged before the kill", before.len());

    let resumed = run_ok(sim_run(&out, FRAMES).arg("--no-map"));
    let line = resumed.lines().find(|l| l.contains("resumed after")).unwrap_or_default();
    assert!(line.contains("stopped during its initialisation") && line.contains("from frame 0"), "{resumed}");
    let clean = dir.path().join("clean");
    run_ok(sim_run(&clean, FRAMES).arg("--no-map"));
    let (combined, uninterrupted) = (logged_poses(&out.join("log")), logged_poses(&clean.join("log")));
    assert_eq!(combined.len(), FRAMES);
    assert_eq!(logged_frame_seqs(&out.join("log")).1, FRAMES, "a frame was logged twice");
    assert_eq!(uninterrupted.len(), FRAMES);
    let worst = combined.iter().map(|(s, p)| (p.translation.vector - uninterrupted[s].translation.vector).norm()).fold(0.0, f64::max);
    eprintln!("killed after {} poses logged; worst position difference to the uninterrupted run {worst:.3e} m", before.len());
    assert!(worst < 1e-6, "resumed run departs from the uninterrupted one by {worst} m");
}

/// The same loss with the vehicle's navigation (the generator's `nav.csv`: depth, altitude,
/// DVL, attitude): the new segment never merges by sight, so the DVL dead-reckoned across the
/// gap and the segment's own metric alignment place it in the dive's world, and its poses are
/// in `trajectory.txt` in metres with segment 0's (one trajectory, SE(3) ATE over all of it
/// 0.60 % of path when measured). With the DVL silent for 2 s in the gap it stays apart in
/// `trajectory-segment-1.txt`, and `metric.json` says why.
#[test]
fn a_loss_in_new_territory_with_navigation_is_joined_in_metres() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("seq");
    run_ok(duv().args(["sim", "--frames", "150", "--burst", "6,1.5", "--width", W, "--height", H, "--out"]).arg(&data));
    let source = format!("tum:{}", data.display());
    let out = dir.path().join("run");
    let text = run_ok(duv().args(["run", "--source", &source, "--no-progress", "--no-map", "--out"]).arg(&out));
    let metric: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metric.json")).unwrap()).unwrap();
    let joined = metric["joined_segments"].as_array().unwrap_or_else(|| panic!("no joined segment: {metric}"));
    assert_eq!(joined.len(), 1, "{metric}");
    let j = &joined[0];
    assert_eq!((j["segment"].as_u64(), j["from_segment"].as_u64()), (Some(1), Some(0)), "{j}");
    // The burst lasts 1.5 s; tracking resumes after the new segment initialises.
    let (gap_s, dr_m) = (j["gap_s"].as_f64().unwrap(), j["dead_reckoned_m"].as_f64().unwrap());
    assert!(gap_s > 1.5 && gap_s < 12.0 && dr_m > 0.5 && dr_m < 0.6 * gap_s, "gap {gap_s} s, {dr_m} m dead-reckoned");
    let rows = states_rows(&out.join("states.txt"));
    let posed: Vec<u64> = rows.iter().filter(|v| v[5] != "-").map(|v| v[0].parse().unwrap()).collect();
    assert!(rows.iter().filter(|v| v[5] == "1").count() >= 20, "segment 1 tracked too little");
    assert_eq!(read_trajectory(&out.join("trajectory.txt")).keys().copied().collect::<Vec<_>>(), posed);
    assert!(!out.join("trajectory-segment-1.txt").exists());
    assert!(text.contains("joined by navigation"), "{text}");
    // One trajectory in metres: SE(3) ATE over every posed frame (0.60 % when measured).
    let line = text.lines().find(|l| l.starts_with("metric: ATE with SE(3) alignment")).unwrap_or_else(|| panic!("{text}"));
    let pct: f64 = line.split(" m RMSE, ").nth(1).and_then(|r| r.split(' ').next()).and_then(|v| v.parse().ok()).unwrap_or_else(|| panic!("{line}"));
    assert!(pct < 1.5, "{line}");

    // The DVL silent from 6.5 to 8.5 s: no dead reckoning across the gap.
    let nav_text = std::fs::read_to_string(data.join("nav.csv")).unwrap();
    let mut lines = nav_text.lines();
    let mut cut = format!("{}\n", lines.next().unwrap());
    for l in lines {
        let mut v: Vec<&str> = l.split(',').collect();
        let t: f64 = v[0].parse().unwrap();
        if t > 6.5 && t < 8.5 {
            v[3] = "";
            v[4] = "";
            v[5] = "";
        }
        cut.push_str(&v.join(","));
        cut.push('\n');
    }
    std::fs::write(data.join("nav.csv"), cut).unwrap();
    let apart = dir.path().join("apart");
    run_ok(duv().args(["run", "--source", &source, "--no-progress", "--no-map", "--out"]).arg(&apart));
    let metric: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(apart.join("metric.json")).unwrap()).unwrap();
    assert!(metric.get("joined_segments").is_none(), "{metric}");
    let why = metric["segments_not_joined"][0]["why"].as_str().unwrap_or_else(|| panic!("{metric}"));
    assert!(why.contains("no DVL velocity") && why.contains("2.00 s"), "{why}");
    let rows = states_rows(&apart.join("states.txt"));
    let in_segment = |s: &str| -> Vec<u64> { rows.iter().filter(|v| v[5] == s).map(|v| v[0].parse().unwrap()).collect() };
    assert_eq!(read_trajectory(&apart.join("trajectory.txt")).keys().copied().collect::<Vec<_>>(), in_segment("0"));
    assert_eq!(read_trajectory(&apart.join("trajectory-segment-1.txt")).keys().copied().collect::<Vec<_>>(), in_segment("1"));
}

/// Tracking lost in new territory (a turbidity burst on a survey, which never comes back over
/// its start): a new map segment starts and tracks. Its poses go to `trajectory-segment-1.txt`
/// (`trajectory.txt` holds segment 0's), `states.txt` and the log's state messages say which
/// segment each pose is in, `dive.json` counts both, and `keyframes.txt` lists segment 0's
/// keyframes only (the frame the map is built in). A re-run into the folder that does not lose
/// tracking leaves no stale segment file behind.
#[test]
fn a_loss_in_new_territory_starts_a_map_segment_in_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let text = run_ok(duv().args(["run", "--source", "sim:coastal,frames=150,burst=6:1.5", "--width", W, "--height", H, "--no-progress", "--no-map", "--out"]).arg(&out));
    assert!(text.contains("in trajectory-segment-1.txt"), "{text}");
    assert!(text.contains("map segments: 1 started after a loss, 0 merged;"), "{text}");
    // Columns: seq, time, state, pose, tracker ms, segment, why.
    let rows = states_rows(&out.join("states.txt"));
    assert_eq!(rows.len(), 150);
    let start = rows.iter().position(|v| v[6..].join(" ").contains("map segment 1 starts")).expect("a new segment");
    assert!(rows[..start].iter().all(|v| v[5] == "0" || (v[5] == "-" && v[3] == "none")), "{:?}", &rows[..start]);
    assert!(rows[start..].iter().all(|v| v[5] == "1" || (v[5] == "-" && v[3] == "none")), "{:?}", &rows[start..]);
    let in_segment = |s: &str| -> Vec<u64> { rows.iter().filter(|v| v[5] == s).map(|v| v[0].parse().unwrap()).collect() };
    let (seg0, seg1) = (in_segment("0"), in_segment("1"));
    assert!(seg0.len() >= 50 && seg1.len() >= 20, "{} frames in segment 0, {} in segment 1", seg0.len(), seg1.len());
    assert_eq!(read_trajectory(&out.join("trajectory.txt")).keys().copied().collect::<Vec<_>>(), seg0);
    assert_eq!(read_trajectory(&out.join("trajectory-segment-1.txt")).keys().copied().collect::<Vec<_>>(), seg1);
    let dive: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("dive.json")).unwrap()).unwrap();
    assert_eq!(dive["map_segments"], serde_json::json!([[0, seg0.len()], [1, seg1.len()]]), "{dive}");
    assert_eq!(dive["frames_with_pose"], seg0.len() + seg1.len());
    // The log: every state message carries its segment; the new segment's first keyframe.
    let mut logged: BTreeMap<u64, duv_log::schema::StateMessage> = BTreeMap::new();
    for (_, p) in list_segments(&out.join("log")).unwrap() {
        read_segment(&p, ReadLimits::default(), |m| {
            if m.channel.topic == Topic::State.name() {
                let s: duv_log::schema::StateMessage = serde_json::from_slice(m.data).unwrap();
                logged.insert(s.seq, s);
            }
        })
        .unwrap();
    }
    assert_eq!(logged.len(), 150);
    let first_kf_of_1 = logged[&(start as u64)].new_keyframe.expect("the segment's first keyframe");
    assert_eq!(logged[&(start as u64)].why.as_deref(), Some("new_segment"));
    assert!(logged.range(start as u64..).all(|(_, s)| s.segment == 1));
    assert!(logged.range(..start as u64).all(|(_, s)| s.segment == 0));
    let kf_ids: Vec<u64> = std::fs::read_to_string(out.join("keyframes.txt")).unwrap().lines().filter(|l| !l.starts_with('#')).map(|l| l.split_whitespace().next().unwrap().parse().unwrap()).collect();
    assert!(!kf_ids.is_empty() && kf_ids.iter().all(|&id| id < first_kf_of_1), "{kf_ids:?}, segment 1 from keyframe {first_kf_of_1}");
    // A run into the same folder without the burst (a fresh dive): no segment 1 file stays.
    std::fs::remove_file(out.join("dive.json")).unwrap();
    std::fs::remove_dir_all(out.join("log")).unwrap();
    run_ok(duv().args(["run", "--source", "sim:coastal,frames=20", "--width", W, "--height", H, "--no-progress", "--no-map", "--out"]).arg(&out));
    assert!(!out.join("trajectory-segment-1.txt").exists());
}
