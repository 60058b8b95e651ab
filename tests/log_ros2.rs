//! The log in the ROS 2 format (`[log] format = "ros2"`): a rosbag2 folder (metadata.yaml and
//! MCAP segments with the `ros2` profile, `ros2msg` schemas, CDR messages) that the `rosbags`
//! package from PyPI opens and deserialises message by message; our own readers read it back
//! (replay, keyframes, tracking state, window, map checkpoint); a segment cut by a crash is
//! recovered and the bag index rewritten; the writer allocates nothing once warm.

use duv_core::alloc::{count_allocations_on_this_thread, CountingAllocator};
use duv_core::{Frame, FrameImage, ImageGray8, ImageRgb8, Keyframe, PinholeCamera, PlaneF32, Se3, Timestamp};
use duv_camera::FrameSource;
use duv_log::bag::{read_profile, METADATA_FILE};
use duv_log::reader::ReadLimits;
use duv_log::recover::{is_finished, recover_folder};
use duv_log::replay::McapSource;
use duv_log::schema::{decode_state, PoseRecord};
use duv_log::{list_segments, read_log_keyframes, read_segment, FrameEncoding, LogConfig, LogFormat, LogItem, SegmentWriter, TrackerWindow, WindowKeyframe};
use nalgebra::{Translation3, UnitQuaternion};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

#[path = "common/python.rs"]
mod python;

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

const W: usize = 40;
const H: usize = 30;

fn frame(seq: u64, t_ns: i64) -> Frame {
    let mut img = ImageRgb8::new(W, H);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i as u64 * 31 + seq * 7) % 251) as u8;
    }
    Frame { t_ns: Timestamp::from_ns(t_ns), seq, image: FrameImage::Rgb8(img) }
}

fn world_from_cam(seq: u64) -> Se3 {
    Se3::from_parts(Translation3::new(0.1 * seq as f64, -0.5, 0.02 * seq as f64), UnitQuaternion::from_euler_angles(0.0, 0.01 * seq as f64, 0.0))
}

fn pose(seq: u64, t_ns: i64) -> PoseRecord {
    let init = seq < 2;
    PoseRecord {
        t_ns: Timestamp::from_ns(t_ns),
        seq,
        world_from_cam: world_from_cam(seq),
        state: if init { "initialising" } else { "tracking" },
        tracked: !init,
        keyframe: (!init).then_some(0),
        new_keyframe: (seq % 20 == 5).then_some(seq),
        loop_closed: false,
        segment: 0,
        why: init.then_some("init_small_flow"),
        value: init.then_some(0.25),
        limit: init.then_some(1.5),
    }
}

fn camera() -> PinholeCamera {
    PinholeCamera::new(30.0, 31.0, 19.5, 14.5, W, H).unwrap()
}

fn keyframe(index: u64, t_ns: i64) -> Keyframe {
    let FrameImage::Rgb8(image) = frame(index, t_ns).image else { unreachable!() };
    let mut inv_depth = PlaneF32::new(W, H);
    for (i, d) in inv_depth.data.iter_mut().enumerate() {
        *d = 0.2 + i as f32 * 1e-3;
    }
    Keyframe { index, t_ns: Timestamp::from_ns(t_ns), image, world_from_cam: world_from_cam(index), camera: camera(), inv_depth, inv_depth_variance: PlaneF32::filled(W, H, [0.01]) }
}

fn window(seq: u64, t_ns: i64) -> TrackerWindow {
    let kf = |id: u64| WindowKeyframe { id, seq: id * 5, t_ns: Timestamp::from_ns(id as i64 * 500_000_000), world_from_cam: world_from_cam(id), inv_depth: PlaneF32::filled(4, 3, [0.5]), variance: PlaneF32::filled(4, 3, [0.02]), has_variance: true };
    TrackerWindow { seq, t_ns: Timestamp::from_ns(t_ns), keyframes: vec![kf(0), kf(1), kf(2)] }
}

fn ros2_config(dir: &Path, frames: FrameEncoding) -> LogConfig {
    let mut cfg = LogConfig::new(dir);
    cfg.format = LogFormat::Ros2;
    cfg.frame_encoding = frames;
    cfg.chunk_interval = Duration::from_secs(3600);
    cfg.metadata.push(("duv.board".into(), [("toml".to_string(), "name = \"test\"".to_string())].into_iter().collect::<BTreeMap<_, _>>()));
    cfg
}

/// Writes `frames` frames at 10 Hz with poses, keyframes every 20 frames, health every 10,
/// a tracker window every 10 and a map checkpoint at the end.
fn write_log(cfg: LogConfig, frames: u64) {
    let mut w = SegmentWriter::create(cfg).unwrap();
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
    for seq in 0..frames {
        let t = 1_000_000_000 + seq as i64 * 100_000_000;
        w.write(&LogItem::Frame(Arc::new(frame(seq, t)))).unwrap();
        w.write(&LogItem::Pose(pose(seq, t))).unwrap();
        if seq % 20 == 5 {
            w.write(&LogItem::Keyframe(Arc::new(keyframe(seq, t)))).unwrap();
        }
        // A navigation sample a frame, every other one without its altimeter.
        let nav = duv_core::nav::NavSample {
            t_ns: Timestamp::from_ns(t),
            depth_m: Some(20.0 + seq as f64 * 0.01),
            altitude_m: (seq % 2 == 0).then_some(2.5),
            vel_cam_mps: Some(nalgebra::Vector3::new(0.0, 0.1, 0.5)),
            world_from_cam_rot: Some(nalgebra::UnitQuaternion::from_euler_angles(-1.2, 0.0, 0.3)),
        };
        w.write(&LogItem::Nav(nav)).unwrap();
        if seq % 10 == 9 {
            w.write(&LogItem::Health { t_ns: Timestamp::from_ns(t), json: format!("{{\"frames\":{seq}}}") }).unwrap();
            w.write(&LogItem::Window(Arc::new(window(seq, t)))).unwrap();
        }
        if seq % 10 == 0 {
            w.sync_now().unwrap();
        }
    }
    let t = 1_000_000_000 + frames as i64 * 100_000_000;
    let centres = vec![[1.0f32, 2.0, 3.0], [-1.0, 0.5, 4.0]];
    w.write(&LogItem::Map { t_ns: Timestamp::from_ns(t), centres_in_world: centres, checkpoint: b"DUVMAPCK checkpoint bytes".to_vec(), last: true }).unwrap();
    let (_stats, r) = w.finish();
    r.unwrap();
}

/// Messages per topic in the folder, by our reader.
fn our_counts(dir: &Path) -> BTreeMap<String, u64> {
    let mut counts = BTreeMap::new();
    for (_, path) in list_segments(dir).unwrap() {
        let outcome = read_segment(&path, ReadLimits::default(), |m| *counts.entry(m.channel.topic.clone()).or_insert(0) += 1).unwrap();
        assert!(outcome.damage.is_none(), "{outcome:?}");
    }
    counts
}


/// `tests/py/check_ros2_bag.py` on the folder; `None` (skipped, saying so) without Python and
/// `rosbags`, a failure under CI=true or with DUV_PYTHON set.
fn rosbags_check(dir: &Path) -> Option<serde_json::Value> {
    let py = python::python_with("rosbags.rosbag2", "rosbags")?;
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/check_ros2_bag.py");
    let out = std::process::Command::new(&py).arg(&script).arg(dir).output().unwrap();
    assert!(out.status.success(), "rosbags failed: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["errors"], serde_json::json!([]), "rosbags: {v}");
    assert_eq!(v["mismatched_definitions"], serde_json::json!([]), "rosbags: {v}");
    Some(v)
}

fn assert_counts_match(v: &serde_json::Value, ours: &BTreeMap<String, u64>) {
    let theirs: BTreeMap<String, u64> = v["counts"].as_object().unwrap().iter().map(|(k, n)| (k.clone(), n.as_u64().unwrap())).collect();
    assert_eq!(&theirs, ours, "rosbags against our reader");
    assert_eq!(v["message_count"].as_u64(), Some(ours.values().sum()), "metadata.yaml message_count");
}

#[test]
fn a_ros2_log_is_a_bag_that_rosbags_opens_and_deserialises() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = ros2_config(dir.path(), FrameEncoding::Raw);
    // Zstd chunks (the default): rosbags reads them too.
    cfg.segment_max_bytes = 6 << 10;
    write_log(cfg, 60);
    let segs = list_segments(dir.path()).unwrap();
    assert!(segs.len() >= 3, "{} segments", segs.len());
    for (_, p) in &segs {
        assert!(is_finished(p).unwrap());
        assert_eq!(read_profile(p).unwrap(), "ros2");
    }
    let yaml = std::fs::read_to_string(dir.path().join(METADATA_FILE)).unwrap();
    for (_, p) in &segs {
        assert!(yaml.contains(p.file_name().unwrap().to_str().unwrap()), "{yaml}");
    }
    let ours = our_counts(dir.path());
    assert_eq!((ours["/camera/image"], ours["/slam/state"], ours["/keyframe/variance"], ours["/health"], ours["/slam/window"], ours["/map/gaussians"]), (60, 60, 3, 6, 6, 1));
    assert_eq!(ours["/nav/sample"], 60);
    assert_eq!(ours["/slam/odometry"], 60);
    assert_eq!(ours.len(), 15, "every topic: {ours:?}");
    let Some(v) = rosbags_check(dir.path()) else { return };
    assert_counts_match(&v, &ours);
    let types = &v["types"];
    for (topic, ty) in [
        ("/camera/image", "sensor_msgs/msg/Image"),
        ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
        ("/slam/pose", "geometry_msgs/msg/PoseStamped"),
        ("/tf", "tf2_msgs/msg/TFMessage"),
        ("/slam/state", "duv_msgs/msg/TrackingState"),
        ("/nav/sample", "duv_msgs/msg/NavSample"),
        ("/slam/odometry", "nav_msgs/msg/Odometry"),
        ("/keyframe/image", "sensor_msgs/msg/Image"),
        ("/keyframe/inv_depth", "sensor_msgs/msg/Image"),
        ("/keyframe/variance", "sensor_msgs/msg/Image"),
        ("/keyframe/pose", "geometry_msgs/msg/PoseStamped"),
        ("/map/gaussians", "sensor_msgs/msg/PointCloud2"),
        ("/map/checkpoint", "duv_msgs/msg/MapCheckpoint"),
        ("/health", "duv_msgs/msg/Health"),
        ("/slam/window", "duv_msgs/msg/TrackerWindow"),
    ] {
        assert_eq!(types[topic].as_str(), Some(ty), "{topic}");
    }
    let f = &v["fields"];
    assert_eq!(f["image"]["encoding"], "rgb8");
    assert_eq!((f["image"]["width"].as_u64(), f["image"]["height"].as_u64()), (Some(W as u64), Some(H as u64)));
    assert_eq!(f["image"]["frame_id"], "camera");
    assert_eq!(f["image"]["stamp_ns"].as_u64(), Some(1_000_000_000));
    assert_eq!(f["camera_info"]["k"], serde_json::json!([30.0, 0.0, 19.5, 0.0, 31.0, 14.5, 0.0, 0.0, 1.0]));
    assert_eq!(f["pose"]["frame_id"], "world");
    assert_eq!(f["pose"]["position"], serde_json::json!([0.0, -0.5, 0.0]));
    assert_eq!((f["tf"]["parent"].as_str(), f["tf"]["child"].as_str()), (Some("world"), Some("camera")));
    assert_eq!(f["state"]["state"], "initialising");
    assert_eq!(f["state"]["why"], "init_small_flow");
    assert_eq!(f["state"]["has_keyframe"], false);
    assert_eq!(f["cloud"]["width"].as_u64(), Some(2));
    assert_eq!(f["cloud"]["fields"], serde_json::json!([["x", 0, 7, 1], ["y", 4, 7, 1], ["z", 8, 7, 1]]));
    assert_eq!(f["inv_depth"]["encoding"], "16FC1");
    assert_eq!(f["window_magic"], "DUVW");
    assert_eq!(f["checkpoint_bytes"].as_u64(), Some(25));
}

#[test]
fn a_ros2_log_reads_back_through_our_readers() {
    let dir = tempfile::tempdir().unwrap();
    write_log(ros2_config(dir.path(), FrameEncoding::Raw), 45);
    // Replay: every frame, bit for bit, with its time stamp, and the calibration.
    let mut src = McapSource::open(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(*src.camera(), camera());
    let mut n = 0u64;
    while let Some(f) = src.next_frame().unwrap() {
        assert_eq!(f, frame(n, 1_000_000_000 + n as i64 * 100_000_000));
        n += 1;
    }
    assert_eq!(n, 45);
    // Keyframes (refine --mcap): image, pose, depth, variance; the map checkpoint's bytes.
    let got = read_log_keyframes(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(got.keyframes.iter().map(|k| k.index).collect::<Vec<_>>(), vec![5, 25]);
    for k in &got.keyframes {
        let want = keyframe(k.index, k.t_ns.t_ns());
        assert_eq!(k.image, want.image);
        // Depth and variance are logged as f16: within 2^-11 of the value (relative).
        for (got, want) in [(&k.inv_depth, &want.inv_depth), (&k.inv_depth_variance, &want.inv_depth_variance)] {
            assert_eq!((got.width, got.height), (want.width, want.height));
            assert!(got.data.iter().zip(&want.data).all(|(a, b)| (a - b).abs() <= b.abs() * 2f32.powi(-11)), "f16 planes off by more than 2^-11");
        }
        assert!((k.world_from_cam.translation.vector - want.world_from_cam.translation.vector).norm() < 1e-12);
    }
    assert_eq!(got.newest_map.unwrap().bytes, b"DUVMAPCK checkpoint bytes");
    // Tracking state and tracker window (what a resume reads).
    let mut states = Vec::new();
    let mut windows = Vec::new();
    for (_, path) in list_segments(dir.path()).unwrap() {
        read_segment(&path, ReadLimits::default(), |m| match m.channel.topic.as_str() {
            "/slam/state" => states.push(decode_state(m.data).unwrap()),
            "/slam/window" => windows.push(TrackerWindow::decode(m.data).unwrap()),
            _ => {}
        })
        .unwrap();
    }
    assert_eq!(states.len(), 45);
    let s0 = &states[0];
    assert_eq!((s0.state.as_str(), s0.tracked, s0.keyframe, s0.why.as_deref(), s0.value, s0.limit), ("initialising", false, None, Some("init_small_flow"), Some(0.25), Some(1.5)));
    let s5 = &states[5];
    assert_eq!((s5.seq, s5.tracked, s5.keyframe, s5.new_keyframe, s5.why.as_deref(), s5.value), (5, true, Some(0), Some(5), None, None));
    assert_eq!(windows.len(), 4);
    assert_eq!(windows[0], window(9, 1_900_000_000));
    // inspect names the format.
    let summary = duv_log::inspect_log(dir.path(), ReadLimits::default()).unwrap();
    assert!(summary.render().contains("format ros2"), "{}", summary.render());
}

#[test]
fn jpeg_frames_are_compressed_images_in_a_ros2_log() {
    let dir = tempfile::tempdir().unwrap();
    write_log(ros2_config(dir.path(), FrameEncoding::Jpeg { quality: 90 }), 20);
    let mut src = McapSource::open(dir.path(), ReadLimits::default()).unwrap();
    let mut n = 0;
    while let Some(f) = src.next_frame().unwrap() {
        assert_eq!((f.seq, f.t_ns, f.image.width(), f.image.height()), (n, Timestamp::from_ns(1_000_000_000 + n as i64 * 100_000_000), W, H));
        n += 1;
    }
    assert_eq!(n, 20);
    let Some(v) = rosbags_check(dir.path()) else { return };
    assert_counts_match(&v, &our_counts(dir.path()));
    assert_eq!(v["types"]["/camera/image"], "sensor_msgs/msg/CompressedImage");
    assert_eq!(v["fields"]["image"]["format"], "jpeg");
    assert_eq!(v["fields"]["jpeg_streams"].as_u64(), Some(20));
}

#[test]
fn a_ros2_segment_cut_by_a_crash_is_recovered_and_the_bag_reindexed() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = ros2_config(dir.path(), FrameEncoding::Raw);
    cfg.segment_max_bytes = 96 << 10;
    write_log(cfg, 60);
    let segs = list_segments(dir.path()).unwrap();
    let last = &segs.last().unwrap().1;
    // A power cut: the last segment ends mid-chunk, metadata.yaml is from before it.
    let bytes = std::fs::read(last).unwrap();
    std::fs::write(last, &bytes[..bytes.len() * 2 / 3]).unwrap();
    std::fs::remove_file(dir.path().join(METADATA_FILE)).unwrap();
    let reports = recover_folder(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(reports.len(), 1, "{reports:?}");
    assert!(reports[0].messages_kept > 0, "{reports:?}");
    assert!(is_finished(last).unwrap());
    assert_eq!(read_profile(last).unwrap(), "ros2", "recovery keeps the profile");
    assert!(dir.path().join(METADATA_FILE).is_file());
    let ours = our_counts(dir.path());
    assert!(ours["/camera/image"] < 60 && ours["/camera/image"] > 30, "{ours:?}");
    // A resumed run appends segments to the same bag.
    let mut cfg = ros2_config(dir.path(), FrameEncoding::Raw);
    cfg.segment_max_bytes = 1 << 30;
    let mut w = SegmentWriter::create(cfg).unwrap();
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(9_000_000_000), camera: camera() }).unwrap();
    w.write(&LogItem::Frame(Arc::new(frame(100, 9_000_000_000)))).unwrap();
    w.finish().1.unwrap();
    let after = our_counts(dir.path());
    assert_eq!(after["/camera/image"], ours["/camera/image"] + 1);
    let Some(v) = rosbags_check(dir.path()) else { return };
    assert_counts_match(&v, &after);
}

/// Once warm, the ROS 2 encoder and the writer allocate nothing: frames (raw and JPEG, colour
/// and grey), poses (pose, transform, state), keyframes, health, tracker windows, map
/// checkpoints, each chunk closed and fsynced.
#[test]
fn the_ros2_log_writer_allocates_nothing_once_warm() {
    let frames: Vec<Arc<Frame>> = (0..40u64).map(|s| Arc::new(frame(s, s as i64 * 50_000_000))).collect();
    let grey: Vec<Arc<Frame>> = frames
        .iter()
        .map(|f| {
            let FrameImage::Rgb8(i) = &f.image else { unreachable!() };
            Arc::new(Frame { t_ns: f.t_ns, seq: f.seq, image: FrameImage::Gray8(ImageGray8::from_vec(W, H, i.data.iter().step_by(3).copied().collect()).unwrap()) })
        })
        .collect();
    let keyframes: Vec<Arc<Keyframe>> = (0..40u64).map(|s| Arc::new(keyframe(s, s as i64 * 50_000_000))).collect();
    let windows: Vec<Arc<TrackerWindow>> = (0..40u64).map(|s| Arc::new(window(s, s as i64 * 50_000_000))).collect();
    let maps: Vec<LogItem> = (0..40u64).map(|s| LogItem::Map { t_ns: Timestamp::from_ns(s as i64), centres_in_world: vec![[s as f32, 0.0, 1.0]; 100], checkpoint: vec![7u8; 1000], last: false }).collect();
    let health: Vec<LogItem> = (0..40u64).map(|s| LogItem::Health { t_ns: Timestamp::from_ns(s as i64), json: "{\"frames\":1}".into() }).collect();
    for (encoding, set) in [(FrameEncoding::Raw, &frames), (FrameEncoding::Jpeg { quality: 90 }, &frames), (FrameEncoding::Jpeg { quality: 75 }, &grey)] {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = ros2_config(dir.path(), encoding);
        cfg.chunk_interval = Duration::ZERO;
        let mut writer = SegmentWriter::create(cfg).unwrap();
        writer.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
        let mut log = |i: usize| {
            writer.write(&LogItem::Frame(Arc::clone(&set[i]))).unwrap();
            writer.write(&LogItem::Pose(pose(i as u64, set[i].t_ns.t_ns()))).unwrap();
            writer.write(&LogItem::Keyframe(Arc::clone(&keyframes[i]))).unwrap();
            writer.write(&LogItem::Window(Arc::clone(&windows[i]))).unwrap();
            writer.write(&maps[i]).unwrap();
            writer.write(&health[i]).unwrap();
            writer.tick().unwrap();
        };
        for i in 0..10 {
            log(i);
        }
        let n = count_allocations_on_this_thread(|| {
            for i in 10..40 {
                log(i);
            }
        });
        assert_eq!(n, 0, "{encoding:?}: {n} allocations over 30 rounds");
        let (stats, r) = writer.finish();
        r.unwrap();
        assert!(stats.messages >= 40 * 11, "{stats:?}");
    }
}
