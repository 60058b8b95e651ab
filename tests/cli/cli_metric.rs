//! Metric outputs end to end (issue 40): `duv sim` writes `nav.csv`, `duv run` on the dataset
//! writes its trajectory, keyframe depth and `metric.json` in metres; `--no-nav` and a `sim:`
//! source without `nav=on` stay in map units and say why; `duv eval --align se3` refuses map
//! units; a nav file with a broken line is an error naming it.

use duv_core::io::pfm::read_pfm;
use duv_core::io::tum::read_trajectory;
use duv_pipeline::metric::MetricRecord;
use nalgebra::Vector3;
use std::path::Path;
use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

fn ok(c: &mut Command) -> (String, String) {
    let res = c.output().unwrap();
    let (o, e) = (String::from_utf8_lossy(&res.stdout).to_string(), String::from_utf8_lossy(&res.stderr).to_string());
    assert!(res.status.success(), "stdout:\n{o}\nstderr:\n{e}");
    (o, e)
}

/// The Sim(3) scale that takes `est` onto the ground truth (Umeyama over the common frames).
fn scale_to_truth(est: &Path, gt: &Path) -> f64 {
    let est = read_trajectory(est).unwrap();
    let gt = read_trajectory(gt).unwrap();
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = est.iter().filter_map(|e| gt.iter().find(|g| g.t_ns == e.t_ns).map(|g| (e.world_from_cam.translation.vector, g.world_from_cam.translation.vector))).collect();
    let (src, dst): (Vec<_>, Vec<_>) = pairs.into_iter().unzip();
    duv_core::align::umeyama(&src, &dst, true).unwrap().scaling()
}

#[test]
fn a_dataset_with_nav_csv_gives_metric_outputs_and_without_it_map_units() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    ok(duv().args(["sim", "--water", "coastal", "--frames", "120", "--width", "160", "--height", "120", "--no-progress", "--out"]).arg(&data));
    assert!(data.join("nav.csv").is_file());
    let run = dir.path().join("run");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--source", &format!("tum:{}", data.display()), "--out"]).arg(&run));
    assert!(stdout.contains("outputs in metres: 1 map unit = "), "{stdout}");
    assert!(stdout.contains("metric: ATE with SE(3) alignment"), "{stdout}");
    let m = MetricRecord::read(&run).unwrap().unwrap();
    assert_eq!(m.length_unit, "m", "{m:?}");
    assert!(m.from_altitude.is_some(), "the altimeter sees the scale on this survey: {m:?}");
    assert_eq!(m.nav_samples, 120);
    // The trajectory is metric: the scale to the truth is 1 (the target: 2 %).
    let s = scale_to_truth(&run.join("trajectory.txt"), &data.join("groundtruth.txt"));
    assert!((s - 1.0).abs() < 0.02, "Sim(3) scale to the truth {s}");
    // So is the keyframes' depth: its median against the truth's range at the same frames is
    // checked through the camera's height above the seabed (about 2 m, the generator's
    // altitude): inverse depth in 1/m is around 1/2..1/6 at the image centre.
    let kf = std::fs::read_to_string(run.join("keyframes.txt")).unwrap();
    let id: u64 = kf.lines().find(|l| !l.starts_with('#')).unwrap().split_whitespace().next().unwrap().parse().unwrap();
    let inv = read_pfm(&run.join("keyframes").join(format!("{id:06}_invdepth.pfm"))).unwrap();
    let centre = inv.data[(inv.height / 2) * inv.width + inv.width / 2] as f64;
    assert!(centre > 1.0 / 8.0 && centre < 1.0, "inverse depth at the centre {centre} 1/m");
    // duv eval with SE(3) alignment takes the metric run.
    ok(duv().args(["eval", "--align", "se3", "--gt"]).arg(&data).arg("--run").arg(&run).arg("--out").arg(dir.path().join("eval-se3")));

    // --no-nav: map units, said so.
    let flat = dir.path().join("run-no-nav");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--no-nav", "--source", &format!("tum:{}", data.display()), "--out"]).arg(&flat));
    assert!(stdout.contains("outputs in map units (scale unknown): navigation input turned off"), "{stdout}");
    let m = MetricRecord::read(&flat).unwrap().unwrap();
    assert_eq!(m.length_unit, "map");
    assert!(m.metres_per_map_unit.is_none());
    // ... which duv eval refuses to compare with metres without a scale, unless told.
    let res = duv().args(["eval", "--align", "se3", "--gt"]).arg(&data).arg("--run").arg(&flat).arg("--out").arg(dir.path().join("eval-refused")).output().unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success() && err.contains("map units") && err.contains("--allow-map-units"), "{err}");
    ok(duv().args(["eval", "--align", "se3", "--allow-map-units", "--gt"]).arg(&data).arg("--run").arg(&flat).arg("--out").arg(dir.path().join("eval-allowed")));
}

#[test]
fn sim_sources_have_nav_only_when_asked_and_a_broken_nav_file_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--source", "sim:coastal,frames=40", "--width", "160", "--height", "120", "--out"]).arg(&plain));
    assert!(stdout.contains("outputs in map units (scale unknown): the source has no navigation input"), "{stdout}");
    let nav = dir.path().join("nav");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--source", "sim:coastal,frames=100,nav=on", "--width", "160", "--height", "120", "--out"]).arg(&nav));
    assert!(stdout.contains("outputs in metres"), "{stdout}");
    assert_eq!(MetricRecord::read(&nav).unwrap().unwrap().length_unit, "m");
    // A bad option value.
    let res = duv().args(["run", "--no-map", "--source", "sim:coastal,nav=yes", "--out"]).arg(dir.path().join("bad")).output().unwrap();
    assert!(!res.status.success() && String::from_utf8_lossy(&res.stderr).contains("nav=\"yes\""), "{}", String::from_utf8_lossy(&res.stderr));
    // A nav file with a cell that is not a number: the error names the file and the line.
    let data = dir.path().join("data");
    ok(duv().args(["sim", "--frames", "10", "--width", "64", "--height", "48", "--no-progress", "--out"]).arg(&data));
    let text = std::fs::read_to_string(data.join("nav.csv")).unwrap();
    let lines: Vec<String> = text.lines().map(str::to_string).collect();
    let broken: Vec<String> = lines.iter().enumerate().map(|(i, l)| if i == 3 { let mut f: Vec<&str> = l.split(',').collect(); f[1] = "deep"; f.join(",") } else { l.clone() }).collect();
    std::fs::write(data.join("nav.csv"), broken.join("\n") + "\n").unwrap();
    let res = duv().args(["run", "--no-map", "--source", &format!("tum:{}", data.display()), "--out"]).arg(dir.path().join("broken")).output().unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success() && err.contains("nav.csv") && err.contains("line 4"), "{err}");
}

/// One navigation sample (camera frame, as `nav.csv`) as the MAVLink messages an ArduSub
/// autopilot sends, for a camera mounted as `body_from_cam`.
fn autopilot_messages(s: &duv_core::nav::NavSample, body_from_cam: nalgebra::UnitQuaternion<f64>, dt_s: f64) -> Vec<u8> {
    use mavlink::dialects::ardupilotmega as ap;
    let mut out = Vec::new();
    let mut send = |m: ap::MavMessage| {
        mavlink::write_versioned_msg(&mut out, mavlink::MavlinkVersion::V2, mavlink::MavHeader { system_id: 1, component_id: 1, sequence: 0 }, &m).unwrap();
    };
    if let Some(d) = s.depth_m {
        send(ap::MavMessage::SCALED_PRESSURE2(ap::SCALED_PRESSURE2_DATA { press_abs: ((101_325.0 + 1025.0 * 9.80665 * d) / 100.0) as f32, ..Default::default() }));
    }
    if let Some(a) = s.altitude_m {
        let orientation = ap::MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270;
        send(ap::MavMessage::DISTANCE_SENSOR(ap::DISTANCE_SENSOR_DATA { current_distance: (a * 100.0).round() as u16, min_distance: 5, max_distance: 5000, orientation, ..Default::default() }));
    }
    if let Some(v) = s.vel_cam_mps {
        let d = body_from_cam * v * dt_s;
        let position_delta = [d.x as f32, d.y as f32, d.z as f32];
        send(ap::MavMessage::VISION_POSITION_DELTA(ap::VISION_POSITION_DELTA_DATA { time_delta_usec: (dt_s * 1e6) as u64, position_delta, confidence: 95.0, ..Default::default() }));
    }
    if let Some(q) = s.world_from_cam_rot {
        let nwu_from_ned = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let ned_from_body = nwu_from_ned.inverse() * q * body_from_cam.inverse();
        let (w, i, j, k) = (ned_from_body.w as f32, ned_from_body.i as f32, ned_from_body.j as f32, ned_from_body.k as f32);
        send(ap::MavMessage::ATTITUDE_QUATERNION(ap::ATTITUDE_QUATERNION_DATA { q1: w, q2: i, q3: j, q4: k, ..Default::default() }));
    }
    out
}

/// `duv run --nav mavlink:...` against a simulated autopilot on 127.0.0.1: a generated survey
/// replayed at its recorded timing while a thread sends the generator's navigation sensors as
/// ArduSub's MAVLink messages (pressure, down-facing range, DVL deltas, attitude quaternion) in
/// step with the frames, for a camera mounted 40 degrees down (the board's `[nav]`). The run
/// receives them on arrival and comes out in metres.
#[test]
fn a_live_mavlink_stream_makes_a_paced_run_metric() {
    use std::io::BufRead;
    // Played at half its recorded rate (the stream keeps the same pace, as a hardware-in-the-loop
    // simulator would) into a frame queue that holds the whole sequence: a debug build on a
    // loaded machine falls behind during its initial BA and catches up, dropping no frame.
    const SPEED: f64 = 0.5;
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    ok(duv().args(["sim", "--water", "coastal", "--frames", "100", "--width", "160", "--height", "120", "--no-progress", "--out"]).arg(&data));
    // The dataset keeps no nav.csv: the stream is the only navigation input.
    let sent = dir.path().join("nav-sent.csv");
    std::fs::rename(data.join("nav.csv"), &sent).unwrap();
    let samples = duv_core::nav::read_nav_csv(&sent).unwrap().samples;
    let board_text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/sim.toml")).unwrap().replace("frame_queue = 4 ", "frame_queue = 128 ") + "\n[nav]\ncamera_rpy_deg = [0.0, -40.0, 0.0]\n";
    assert!(board_text.contains("frame_queue = 128 "));
    let board = dir.path().join("board.toml");
    std::fs::write(&board, &board_text).unwrap();
    let body_from_cam = duv_core::config::board::Board::parse(&board, &board_text).unwrap().nav.body_from_cam();
    let port = std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let run = dir.path().join("run");
    let mut child = duv()
        .args(["run", "--no-map", "--no-progress", "--announce", "--speed", &SPEED.to_string(), "--source", &format!("tum:{}", data.display())])
        .arg("--board")
        .arg(&board)
        .args(["--nav", &format!("mavlink:udpin:127.0.0.1:{port},depth=pressure2")])
        .arg("--out")
        .arg(&run)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    // The frames' clock against the wall clock, from the first frame the run announces.
    let (first_tx, first_rx) = std::sync::mpsc::sync_channel::<(std::time::Instant, i64)>(1);
    let reader = std::thread::spawn(move || {
        let mut lines = Vec::new();
        for line in std::io::BufReader::new(stdout).lines().map_while(Result::ok) {
            if lines.iter().all(|l: &String| !l.starts_with("tracked ")) && line.starts_with("tracked ") {
                let t_ns: i64 = line.split_whitespace().nth(2).unwrap().parse().unwrap();
                let _ = first_tx.try_send((std::time::Instant::now(), t_ns));
            }
            lines.push(line);
        }
        lines
    });
    let (wall0, t0_ns) = first_rx.recv_timeout(std::time::Duration::from_secs(120)).expect("the run announces its first frame");
    let tx = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut sent_count = 0;
    for s in &samples {
        let due = std::time::Duration::from_nanos(((s.t_ns.t_ns() - t0_ns).max(0) as f64 / SPEED) as u64);
        if s.t_ns.t_ns() < t0_ns {
            continue; // before the run's first frame: an autopilot would have sent it already
        }
        if let Some(wait) = (wall0 + due).checked_duration_since(std::time::Instant::now()) {
            std::thread::sleep(wait);
        }
        tx.send_to(&autopilot_messages(s, body_from_cam, 0.1), ("127.0.0.1", port)).unwrap();
        sent_count += 1;
    }
    let status = child.wait().unwrap();
    let lines = reader.join().unwrap();
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
    let stdout = lines.join("\n");
    assert!(status.success(), "{stdout}\n{stderr}");
    assert!(sent_count >= 95, "{sent_count} samples sent");
    assert!(stdout.contains(&format!("navigation stream mavlink:udpin:127.0.0.1:{port},depth=pressure2: ")), "{stdout}");
    assert!(stdout.contains("100 frames captured, 100 tracked, 0 dropped"), "{stdout}");
    assert!(stdout.contains("outputs in metres: 1 map unit = "), "{stdout}");
    let m = MetricRecord::read(&run).unwrap().unwrap();
    assert_eq!(m.length_unit, "m", "{m:?}");
    assert!(m.nav_samples >= 4 * 90, "depth, altitude, DVL and attitude arrive as separate samples: {m:?}");
    let s = scale_to_truth(&run.join("trajectory.txt"), &data.join("groundtruth.txt"));
    // The stream's samples are in the log too, on the frames' clock (for replay and resume).
    let (logged, _) = duv_log::read_log_nav(&run.join("log"), duv_log::ReadLimits::default()).unwrap();
    assert!(logged.len() >= 4 * 90, "{} samples logged", logged.len());
    let (first, last) = (logged[0].t_ns.t_ns() as f64 * 1e-9, logged[logged.len() - 1].t_ns.t_ns() as f64 * 1e-9);
    assert!(first > -0.5 && last < 10.5, "logged from {first} to {last} s");
    let metric_line = stdout.lines().find(|l| l.starts_with("metric: ")).unwrap_or("no metric line");
    eprintln!("live MAVLink run: Sim(3) scale to the truth {s:.4}, {} navigation samples; {metric_line}", m.nav_samples);
    assert!((s - 1.0).abs() < 0.03, "Sim(3) scale to the truth {s}");
}

/// The navigation samples go into the log (`/nav/sample`) as the frames pass their time: a
/// replay of the log comes out in metres as the run did, and a dive resumed without any
/// navigation input still fits its scale on what the earlier part logged.
#[test]
fn logged_navigation_keeps_replays_and_resumed_dives_metric() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    ok(duv().args(["sim", "--water", "coastal", "--frames", "120", "--width", "160", "--height", "120", "--no-progress", "--out"]).arg(&data));
    let nav_file = dir.path().join("nav-sent.csv");
    std::fs::rename(data.join("nav.csv"), &nav_file).unwrap();
    let source = format!("tum:{}", data.display());
    let run = dir.path().join("run");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--frames", "90", "--source", &source, "--nav"]).arg(&nav_file).arg("--out").arg(&run));
    assert!(stdout.contains("outputs in metres: 1 map unit = "), "{stdout}");
    // One sample a frame, logged up to the last frame's time.
    let (logged, undecodable) = duv_log::read_log_nav(&run.join("log"), duv_log::ReadLimits::default()).unwrap();
    assert_eq!((logged.len(), undecodable), (90, 0));
    let sent = duv_core::nav::read_nav_csv(&nav_file).unwrap().samples;
    let close = |a: Option<f64>, b: Option<f64>| a.is_some() == b.is_some() && (a.unwrap_or(0.0) - b.unwrap_or(0.0)).abs() < 1e-12;
    for (l, s) in logged.iter().zip(&sent) {
        assert!(l.t_ns == s.t_ns && close(l.depth_m, s.depth_m) && close(l.altitude_m, s.altitude_m), "logged {l:?}, sent {s:?}");
        assert!(l.vel_cam_mps.zip(s.vel_cam_mps).is_some_and(|(a, b)| (a - b).norm() < 1e-12), "logged {l:?}, sent {s:?}");
        assert!(l.world_from_cam_rot.zip(s.world_from_cam_rot).is_some_and(|(a, b)| a.angle_to(&b) < 1e-9), "logged {l:?}, sent {s:?}");
    }
    // A replay of the log: the same metric outputs.
    let replayed = dir.path().join("replayed");
    let (stdout, _) = ok(duv().args(["replay", "--deterministic", "--no-map", "--no-progress", "--out"]).arg(&replayed).arg(run.join("log")));
    assert!(stdout.contains("outputs in metres: 1 map unit = "), "{stdout}");
    assert_eq!(MetricRecord::read(&replayed).unwrap().unwrap().nav_samples, 90);
    // The dive continued to its end without --nav: the 90 logged samples fix the scale.
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--continue", "--source", &source, "--out"]).arg(&run));
    assert!(stdout.contains("outputs in metres: 1 map unit = "), "{stdout}");
    let m = MetricRecord::read(&run).unwrap().unwrap();
    assert_eq!((m.length_unit.as_str(), m.nav_samples), ("m", 90), "{m:?}");
    let s = scale_to_truth(&run.join("trajectory.txt"), &data.join("groundtruth.txt"));
    eprintln!("resumed dive on logged navigation: Sim(3) scale to the truth {s:.4}");
    // Weaker than a whole dive with its sensors (-0.14 % with --nav on both parts here): the
    // samples cover frames 0-89 only, whose poses the resumed run has as they were logged,
    // before the window BA refined them (+3.9 % here).
    assert!((s - 1.0).abs() < 0.05, "Sim(3) scale to the truth {s}");
}
