//! ROS 2 bags in (`--source rosbag:`): bags written here with the `mcap` crate (ROS 2 profile,
//! `ros2msg` schemas, CDR bodies) from a generated sequence, read back against the generator's
//! truth (frames, stamps, pixels, camera, navigation samples); `duv run` end to end on a bag
//! of a generated survey (tracked frames, ATE, metric scale); bags written by the independent
//! Python `rosbags` package (chunks uncompressed, zstd, lz4); bad input (no MCAP, missing or ambiguous topics, an unknown
//! encoding, a truncated message or file) as errors naming the thing.

use duv_camera::FrameSource;
use duv_core::nav::NavSample;
use duv_core::{FrameImage, ImageRgb8, PinholeCamera, RadTan, Timestamp};
use duv_log::rosbag_source::{RosbagError, RosbagSource, RosbagSpec, DEFAULT_SURFACE_PRESSURE_PA, DEFAULT_WATER_DENSITY_KG_M3, GRAVITY_MPS2};
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "common/python.rs"]
mod python;

/// A little-endian CDR writer (the byte order `rclcpp` writes on x86 and ARM).
struct Cdr(Vec<u8>);

impl Cdr {
    fn new() -> Self {
        Cdr(vec![0, 1, 0, 0])
    }
    fn pad(&mut self, a: usize) {
        while !(self.0.len() - 4).is_multiple_of(a) {
            self.0.push(0);
        }
    }
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.pad(4);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.pad(4);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.pad(8);
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64s(&mut self, v: &[f64]) {
        for &x in v {
            self.f64(x);
        }
    }
    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.0.extend_from_slice(s.as_bytes());
        self.0.push(0);
    }
    fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.0.extend_from_slice(b);
    }
    fn header(&mut self, t: Timestamp, frame_id: &str) {
        let ns = t.t_ns();
        self.u32(ns.div_euclid(1_000_000_000) as i32 as u32);
        self.u32(ns.rem_euclid(1_000_000_000) as u32);
        self.string(frame_id);
    }
}

fn image_msg(t: Timestamp, img: &ImageRgb8, encoding: &str) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "camera");
    m.u32(img.height as u32);
    m.u32(img.width as u32);
    m.string(encoding);
    m.u8(0);
    let data: Vec<u8> = match encoding {
        "rgb8" => img.data.clone(),
        "bgr8" => img.data.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]]).collect(),
        "mono8" => img.data.chunks_exact(3).map(|p| p[1]).collect(),
        // Unknown encodings carry the RGB bytes.
        _ => img.data.clone(),
    };
    m.u32((data.len() / img.height) as u32);
    m.bytes(&data);
    m.0
}

fn compressed_msg(t: Timestamp, format: &str, data: &[u8]) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "camera");
    m.string(format);
    m.bytes(data);
    m.0
}

fn camera_info_msg(t: Timestamp, c: &PinholeCamera) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "camera");
    m.u32(c.height as u32);
    m.u32(c.width as u32);
    m.string("plumb_bob");
    let d = c.distortion.map_or([0.0; 5], |d| [d.k1, d.k2, d.p1, d.p2, d.k3]);
    m.u32(5);
    m.f64s(&d);
    m.f64s(&[c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0]);
    m.f64s(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    m.f64s(&[c.fx, 0.0, c.cx, 0.0, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0]);
    m.u32(0);
    m.u32(0);
    for _ in 0..4 {
        m.u32(0);
    }
    m.u8(0);
    m.0
}

fn pressure_msg(t: Timestamp, depth_m: f64) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "pressure");
    m.f64(DEFAULT_SURFACE_PRESSURE_PA + DEFAULT_WATER_DENSITY_KG_M3 * GRAVITY_MPS2 * depth_m);
    m.f64(0.0);
    m.0
}

fn range_msg(t: Timestamp, range_m: f64) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "altimeter");
    m.u8(1);
    m.f32(0.1);
    m.f32(0.3);
    m.f32(50.0);
    m.f32(range_m as f32);
    m.0
}

fn twist_msg(t: Timestamp, v: &Vector3<f64>) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "dvl");
    m.f64s(&[v.x, v.y, v.z, 0.0, 0.0, 0.0]);
    m.f64s(&[0.0; 36]);
    m.0
}

fn imu_msg(t: Timestamp, q: [f64; 4]) -> Vec<u8> {
    let mut m = Cdr::new();
    m.header(t, "imu");
    m.f64s(&q);
    m.f64s(&[0.0; 9]);
    m.f64s(&[0.0; 3]);
    m.f64s(&[0.0; 9]);
    m.f64s(&[0.0; 3]);
    m.f64s(&[0.0; 9]);
    m.0
}

/// A ROS 2 bag being written: one MCAP file (`NAME_0.mcap`) and `metadata.yaml`.
struct Bag {
    w: mcap::Writer<std::io::BufWriter<std::fs::File>>,
    channels: BTreeMap<String, u16>,
    seq: u32,
    dir: PathBuf,
    file: String,
}

impl Bag {
    fn create(dir: &Path) -> Bag {
        std::fs::create_dir_all(dir).unwrap();
        let file = format!("{}_0.mcap", dir.file_name().unwrap().to_string_lossy());
        let f = std::io::BufWriter::new(std::fs::File::create(dir.join(&file)).unwrap());
        let w = mcap::WriteOptions::new().profile("ros2").compression(None).chunk_size(Some(256 << 10)).create(f).unwrap();
        Bag { w, channels: BTreeMap::new(), seq: 0, dir: dir.to_path_buf(), file }
    }

    fn topic(&mut self, topic: &str, schema: &str) {
        let definition = format!("# {schema} (the definition is not read)\n");
        let s = self.w.add_schema(schema, "ros2msg", definition.as_bytes()).unwrap();
        let metadata = BTreeMap::from([("offered_qos_profiles".to_string(), String::new())]);
        let c = self.w.add_channel(s, topic, "cdr", &metadata).unwrap();
        self.channels.insert(topic.to_string(), c);
    }

    fn write(&mut self, topic: &str, t: Timestamp, data: &[u8]) {
        let channel_id = self.channels[topic];
        self.seq += 1;
        let header = mcap::records::MessageHeader { channel_id, sequence: self.seq, log_time: t.t_ns() as u64, publish_time: t.t_ns() as u64 };
        self.w.write_to_known_channel(&header, data).unwrap();
    }

    fn finish(mut self) -> PathBuf {
        self.w.finish().unwrap();
        let meta = format!("rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n  relative_file_paths:\n    - {}\n", self.file);
        std::fs::write(self.dir.join("metadata.yaml"), meta).unwrap();
        self.dir.join(&self.file)
    }
}

fn renderer(frames: usize, width: usize, height: usize) -> SimRenderer {
    let mut cfg = SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Survey);
    cfg.frames = frames;
    cfg.width = width;
    cfg.height = height;
    cfg.seed = 7;
    SimRenderer::new(&cfg).unwrap()
}

/// Writes the renderer's frames (`/cam/image_raw`, `encoding`), its camera
/// (`/cam/camera_info`) and its navigation sensors (pressure, altimeter, DVL, IMU) in time
/// order. Returns the navigation samples written.
fn write_sim_bag(dir: &Path, r: &SimRenderer, encoding: &str) -> Vec<NavSample> {
    let nav = duv_sim::nav::simulate(r, &duv_sim::NavNoise::default(), 7).unwrap();
    let mut bag = Bag::create(dir);
    bag.topic("/cam/image_raw", "sensor_msgs/msg/Image");
    bag.topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo");
    bag.topic("/nav/pressure", "sensor_msgs/msg/FluidPressure");
    bag.topic("/nav/altimeter", "sensor_msgs/msg/Range");
    bag.topic("/dvl/twist", "geometry_msgs/msg/TwistWithCovarianceStamped");
    bag.topic("/imu/data", "sensor_msgs/msg/Imu");
    for (i, n) in nav.iter().enumerate() {
        let f = r.render(i);
        if let Some(d) = n.depth_m {
            bag.write("/nav/pressure", n.t_ns, &pressure_msg(n.t_ns, d));
        }
        if let Some(a) = n.altitude_m {
            bag.write("/nav/altimeter", n.t_ns, &range_msg(n.t_ns, a));
        }
        if let Some(v) = n.vel_cam_mps {
            bag.write("/dvl/twist", n.t_ns, &twist_msg(n.t_ns, &v));
        }
        if let Some(q) = n.world_from_cam_rot {
            let q = q.quaternion();
            bag.write("/imu/data", n.t_ns, &imu_msg(n.t_ns, [q.i, q.j, q.k, q.w]));
        }
        bag.write("/cam/camera_info", f.t_ns, &camera_info_msg(f.t_ns, r.camera()));
        bag.write("/cam/image_raw", f.t_ns, &image_msg(f.t_ns, &f.rgb, encoding));
    }
    bag.finish();
    nav
}

fn board() -> duv_core::config::board::Board {
    duv_core::config::board::Board::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/sim.toml")).unwrap()
}

fn open(spec: &str) -> Result<RosbagSource, RosbagError> {
    RosbagSource::open(&RosbagSpec::parse(spec)?, None)
}

fn frames_of(src: &mut RosbagSource) -> Vec<duv_core::Frame> {
    std::iter::from_fn(|| src.next_frame().unwrap()).collect()
}

#[test]
fn a_bag_of_a_generated_sequence_reads_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let r = renderer(24, 96, 72);
    let bag = dir.path().join("dive");
    let nav = write_sim_bag(&bag, &r, "bgr8");
    let mut src = open(&bag.display().to_string()).unwrap();
    assert_eq!(src.image_topic(), "/cam/image_raw");
    assert_eq!(src.camera_from(), "/cam/camera_info");
    assert_eq!(src.camera(), r.camera(), "intrinsics from CameraInfo");
    assert_eq!(src.topics().len(), 6);
    assert!(src.topics().iter().all(|t| t.message_encoding == "cdr"));
    let frames = frames_of(&mut src);
    assert_eq!(frames.len(), 24);
    for (i, f) in frames.iter().enumerate() {
        let truth = r.render(i);
        assert_eq!((f.seq, f.t_ns), (i as u64, truth.t_ns), "frame {i}");
        assert_eq!(f.image, FrameImage::Rgb8(truth.rgb), "frame {i}: pixels (bgr8 in the bag)");
    }
    assert_eq!(src.bad_frames().0, 0);
    // Navigation: every sample back, values equal (altitude through the Range's f32, depth
    // through pressure).
    let got = src.nav();
    assert_eq!(got.rejected.total(), 0, "{}", got.rejected.describe());
    assert_eq!(got.samples.len(), nav.len());
    let used: Vec<(&str, &str, u64)> = src.nav_topics().iter().map(|n| (n.sensor, n.topic.as_str(), n.messages)).collect();
    assert_eq!(used[0], ("depth", "/nav/pressure", 24));
    assert_eq!(used.iter().map(|u| u.1).collect::<Vec<_>>(), ["/nav/pressure", "/nav/altimeter", "/dvl/twist", "/imu/data"]);
    let mut max_depth_err = 0.0f64;
    for (a, b) in nav.iter().zip(&got.samples) {
        assert_eq!(a.t_ns, b.t_ns);
        max_depth_err = max_depth_err.max((a.depth_m.unwrap() - b.depth_m.unwrap()).abs());
        assert_eq!(a.altitude_m.map(|v| v as f32 as f64), b.altitude_m);
        assert_eq!(a.vel_cam_mps, b.vel_cam_mps);
        assert!(a.world_from_cam_rot.unwrap().angle_to(&b.world_from_cam_rot.unwrap()) < 1e-12);
    }
    assert!(max_depth_err < 1e-9, "depth through pressure: {max_depth_err} m");
    assert!(nav.iter().filter(|n| n.altitude_m.is_some()).count() > 20, "the survey keeps bottom lock");
    // One .mcap file named directly, at most N frames; `depth=none` turns pressure off.
    let mcap = bag.join("dive_0.mcap");
    let mut src = open(&format!("{},depth=none", mcap.display())).unwrap().with_max_frames(Some(5));
    assert_eq!(frames_of(&mut src).len(), 5);
    assert!(src.nav().samples.iter().all(|s| s.depth_m.is_none()));
    assert_eq!(src.nav().samples.len(), 24);
}

#[test]
fn compressed_png_and_jpeg_mono_and_distortion() {
    let dir = tempfile::tempdir().unwrap();
    let r = renderer(6, 64, 48);
    let bag_dir = dir.path().join("cams");
    let mut bag = Bag::create(&bag_dir);
    bag.topic("/a/image_raw/compressed", "sensor_msgs/msg/CompressedImage");
    bag.topic("/a/camera_info", "sensor_msgs/msg/CameraInfo");
    bag.topic("/b/image_mono", "sensor_msgs/msg/Image");
    bag.topic("/b/camera_info", "sensor_msgs/msg/CameraInfo");
    bag.topic("/c/image_raw/compressed", "sensor_msgs/msg/CompressedImage");
    bag.topic("/c/camera_info", "sensor_msgs/msg/CameraInfo");
    let jpeg = duv_log::jpeg::JpegEncoder::new(95).unwrap();
    let mut jpeg_bytes = Vec::new();
    let lens = RadTan { k1: -0.21, k2: 0.04, p1: 1e-4, p2: -2e-4, k3: 0.0 };
    let distorted = r.camera().with_distortion(lens).unwrap();
    let png_path = dir.path().join("f.png");
    for i in 0..r.len() {
        let f = r.render(i);
        duv_core::io::png_io::write_rgb8(&png_path, &f.rgb).unwrap();
        bag.write("/a/image_raw/compressed", f.t_ns, &compressed_msg(f.t_ns, "rgb8; png compressed bgr8", &std::fs::read(&png_path).unwrap()));
        bag.write("/a/camera_info", f.t_ns, &camera_info_msg(f.t_ns, r.camera()));
        bag.write("/b/image_mono", f.t_ns, &image_msg(f.t_ns, &f.rgb, "mono8"));
        bag.write("/b/camera_info", f.t_ns, &camera_info_msg(f.t_ns, &distorted));
        jpeg.encode(&f.rgb.data, f.rgb.width, f.rgb.height, 3, &mut jpeg_bytes).unwrap();
        bag.write("/c/image_raw/compressed", f.t_ns, &compressed_msg(f.t_ns, "jpeg", &jpeg_bytes));
        bag.write("/c/camera_info", f.t_ns, &camera_info_msg(f.t_ns, r.camera()));
    }
    bag.finish();
    // Two image topics: the error lists both and asks for image=.
    let e = open(&bag_dir.display().to_string()).err().unwrap().to_string();
    assert!(e.starts_with("several image topics: /a/image_raw/compressed (sensor_msgs/msg/CompressedImage, 6 messages), /b/image_mono (sensor_msgs/msg/Image, 6 messages), /c/image_raw/compressed"), "{e}");
    assert!(e.ends_with("name one with image=/topic"), "{e}");
    // PNG: lossless; the camera from the namespace above image_raw/compressed.
    let mut a = open(&format!("{},image=/a/image_raw/compressed", bag_dir.display())).unwrap();
    assert_eq!(a.camera_from(), "/a/camera_info");
    let frames = frames_of(&mut a);
    assert_eq!(frames.len(), 6);
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f.image, FrameImage::Rgb8(r.render(i).rgb), "frame {i}");
    }
    // JPEG (quality 95): close to the source frames.
    let mut c = open(&format!("{},image=/c/image_raw/compressed", bag_dir.display())).unwrap();
    let frames = frames_of(&mut c);
    assert_eq!(frames.len(), 6);
    let mut min_psnr = f64::INFINITY;
    for (i, f) in frames.iter().enumerate() {
        let FrameImage::Rgb8(img) = &f.image else { panic!("colour JPEG gives RGB") };
        let truth = r.render(i).rgb;
        let mse = img.data.iter().zip(&truth.data).map(|(&a, &b)| (a as f64 - b as f64).powi(2)).sum::<f64>() / img.data.len() as f64;
        let psnr = 10.0 * (255.0f64.powi(2) / mse).log10();
        assert!(psnr > 30.0, "frame {i}: PSNR {psnr:.1} dB");
        assert_eq!(f.t_ns, r.render(i).t_ns);
        min_psnr = min_psnr.min(psnr);
    }
    eprintln!("JPEG frames from the bag: PSNR >= {min_psnr:.1} dB");
    // mono8, with plumb_bob distortion from the namespace's camera_info.
    let mut b = open(&format!("{},image=/b/image_mono", bag_dir.display())).unwrap();
    assert_eq!(b.camera_from(), "/b/camera_info");
    assert_eq!(*b.camera(), distorted);
    let f = b.next_frame().unwrap().unwrap();
    let FrameImage::Gray8(g) = &f.image else { panic!("mono8 gives grey frames") };
    assert_eq!(g.data, r.render(0).rgb.data.chunks_exact(3).map(|p| p[1]).collect::<Vec<_>>());
    // Through the pipeline's source: undistorted to the camera without distortion.
    let run = duv_pipeline::source::Source::open(&format!("rosbag:{},image=/b/image_mono", bag_dir.display()), &Default::default(), &board(), 0);
    let mut run = run.unwrap();
    assert_eq!(run.camera(), distorted.undistorted());
    let f = run.next().unwrap().unwrap();
    assert!(matches!(f.image, FrameImage::Rgb8(_)), "undistorted frames are RGB");
    assert!(run.describe().contains("camera from /b/camera_info"), "{}", run.describe());
    assert!(run.nav().unwrap().is_none(), "no navigation topics");
}

#[test]
fn bad_bags_are_errors_naming_the_thing() {
    let dir = tempfile::tempdir().unwrap();
    // A folder without MCAP files; one with a SQLite bag; a path that does not exist.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = open(&empty.display().to_string()).err().unwrap().to_string();
    assert_eq!(e, format!("{}: no .mcap file here", empty.display()));
    std::fs::write(empty.join("old_0.db3"), b"SQLite format 3\0").unwrap();
    let e = open(&empty.display().to_string()).err().unwrap().to_string();
    assert!(e.ends_with("this is a SQLite bag (.db3): convert it to MCAP (ros2 bag convert)"), "{e}");
    let e = open(&dir.path().join("nope").display().to_string()).err().unwrap().to_string();
    assert!(e.ends_with("nope: not found"), "{e}");

    let r = renderer(5, 32, 24);
    let camera = *r.camera();
    let write = |name: &str, encoding: &str, info: bool, cut_message: Option<usize>| -> PathBuf {
        let d = dir.path().join(name);
        let mut bag = Bag::create(&d);
        bag.topic("/cam/image_raw", "sensor_msgs/msg/Image");
        bag.topic("/nav/odom", "nav_msgs/msg/Odometry");
        if info {
            bag.topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo");
        }
        for i in 0..r.len() {
            let f = r.render(i);
            let mut m = image_msg(f.t_ns, &f.rgb, encoding);
            if cut_message == Some(i) {
                m.truncate(m.len() / 2);
            }
            if info {
                bag.write("/cam/camera_info", f.t_ns, &camera_info_msg(f.t_ns, &camera));
            }
            bag.write("/cam/image_raw", f.t_ns, &m);
        }
        bag.finish();
        d
    };
    // A missing image topic lists the image topics there are; a topic of the wrong type.
    let good = write("good", "rgb8", true, None);
    let e = open(&format!("{},image=/cam/image", good.display())).err().unwrap().to_string();
    assert_eq!(e, "image=/cam/image: no such topic in the bag; image topics: /cam/image_raw (sensor_msgs/msg/Image, 5 messages)");
    let e = open(&format!("{},imu=/nav/odom", good.display())).err().unwrap().to_string();
    assert_eq!(e, "imu=/nav/odom: its type is nav_msgs/msg/Odometry, expected sensor_msgs/msg/Imu");
    let e = open(&format!("{},image=/cam/camera_info", good.display())).err().unwrap().to_string();
    assert!(e.starts_with("image=/cam/camera_info: its type is sensor_msgs/msg/CameraInfo"), "{e}");
    // An unknown encoding, at open, naming the topic and the encoding.
    let yuv = write("yuv", "yuv422", true, None);
    let e = open(&yuv.display().to_string()).err().unwrap().to_string();
    assert!(e.starts_with("/cam/image_raw, message 0: image encoding \"yuv422\" is not read"), "{e}");
    // No CameraInfo: an error saying where it looked and what to give; fov= guesses.
    let no_info = write("noinfo", "rgb8", false, None);
    let e = open(&no_info.display().to_string()).err().unwrap().to_string();
    assert_eq!(e, "no camera for /cam/image_raw: no sensor_msgs/msg/CameraInfo at /cam/camera_info or /camera_info; name one with camera_info=/topic, or give calib=FILE or fov=DEG");
    let src = open(&format!("{},fov=70", no_info.display())).unwrap();
    assert_eq!((src.camera().width, src.camera().height, src.camera_from()), (32, 24, "fov=70"));
    // calib= through the pipeline: a calibration of another size is refused naming both.
    let calib = dir.path().join("calibration.txt");
    std::fs::write(&calib, "50 50 19.5 14.5 40 30\n").unwrap();
    let board = board();
    let e = duv_pipeline::source::Source::open(&format!("rosbag:{},calib={}", no_info.display(), calib.display()), &Default::default(), &board, 0).err().unwrap();
    let e = format!("{e}: {}", std::error::Error::source(&e).map(|s| s.to_string()).unwrap_or_default());
    assert!(e.contains("/cam/image_raw: the camera is 40x30, the images 32x24"), "{e}");
    // A truncated image message: skipped and counted, the reason names topic, message, field.
    let cut = write("cut", "rgb8", true, Some(2));
    let mut src = open(&cut.display().to_string()).unwrap();
    let frames = frames_of(&mut src);
    assert_eq!(frames.iter().map(|f| f.seq).collect::<Vec<_>>(), [0, 1, 3, 4]);
    let (bad, why) = src.bad_frames();
    assert_eq!(bad, 1);
    assert!(why.unwrap().starts_with("/cam/image_raw, message 2: the message ends inside data"), "{why:?}");
    // A truncated file (the recorder lost power): the frames before the cut, no panic.
    let file = good.join("good_0.mcap");
    let bytes = std::fs::read(&file).unwrap();
    for keep in [bytes.len() * 3 / 4, bytes.len() / 2, 200, 9] {
        std::fs::write(&file, &bytes[..keep]).unwrap();
        match open(&good.display().to_string()) {
            Ok(mut s) => assert!(frames_of(&mut s).len() < 5, "cut at {keep}"),
            Err(e) => assert!(!e.to_string().is_empty(), "cut at {keep}"),
        }
    }
}

#[test]
fn bad_navigation_samples_are_rejected_and_counted_like_nav_csv_rows() {
    let dir = tempfile::tempdir().unwrap();
    let r = renderer(2, 32, 24);
    let d = dir.path().join("nav");
    let mut bag = Bag::create(&d);
    bag.topic("/cam/image_raw", "sensor_msgs/msg/Image");
    bag.topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo");
    bag.topic("/pressure", "sensor_msgs/msg/FluidPressure");
    bag.topic("/altimeter", "sensor_msgs/msg/Range");
    bag.topic("/imu", "sensor_msgs/msg/Imu");
    bag.topic("/dvl", "geometry_msgs/msg/TwistStamped");
    for i in 0..r.len() {
        let f = r.render(i);
        bag.write("/cam/camera_info", f.t_ns, &camera_info_msg(f.t_ns, r.camera()));
        bag.write("/cam/image_raw", f.t_ns, &image_msg(f.t_ns, &f.rgb, "rgb8"));
    }
    let t = |s: f64| Timestamp::from_secs_f64(s);
    // Depth: good, NaN, out of order, repeated, 12 km, good.
    for (s, depth) in [(1.0, 10.0), (2.0, f64::NAN), (1.5, 10.1), (2.0, 10.2), (3.0, 12_000.0), (4.0, 10.3)] {
        bag.write("/pressure", t(s), &pressure_msg(t(s), depth));
    }
    // A pressure message cut short: noted, counted, the rest kept.
    let cut = pressure_msg(t(5.0), 10.4);
    bag.write("/pressure", t(5.0), &cut[..cut.len() - 10]);
    // Altitude: good, negative, infinite (a Range beyond max_range).
    for (s, a) in [(1.0, 2.0), (2.5, -0.5), (3.5, f64::INFINITY)] {
        bag.write("/altimeter", t(s), &range_msg(t(s), a));
    }
    // Attitude: unit, far from unit, and one without orientation (covariance[0] = -1).
    bag.write("/imu", t(1.0), &imu_msg(t(1.0), [0.0, 0.0, 0.0, 1.0]));
    bag.write("/imu", t(2.2), &imu_msg(t(2.2), [0.0, 0.0, 0.0, 2.0]));
    let mut no_orientation = Cdr::new();
    no_orientation.header(t(2.4), "imu");
    no_orientation.f64s(&[0.0, 0.0, 0.0, 1.0, -1.0]);
    no_orientation.f64s(&[0.0; 8 + 3 + 9 + 3 + 9]);
    bag.write("/imu", t(2.4), &no_orientation.0);
    // Velocity: 25 m/s (over the limit), then good.
    for (s, v) in [(1.2, 25.0), (1.3, 0.4)] {
        let mut m = Cdr::new();
        m.header(t(s), "dvl");
        m.f64s(&[0.0, 0.0, v, 0.0, 0.0, 0.0]);
        bag.write("/dvl", t(s), &m.0);
    }
    bag.finish();
    let src = open(&d.display().to_string()).unwrap();
    let nav = src.nav();
    let rej = nav.rejected;
    assert_eq!(
        (rej.non_finite, rej.out_of_order, rej.duplicate_time, rej.depth_out_of_range, rej.altitude_out_of_range, rej.bad_quaternion, rej.velocity_out_of_range),
        (2, 1, 1, 1, 1, 1, 1),
        "{}",
        rej.describe()
    );
    assert_eq!(src.notes(), ["/pressure: 1 message(s) could not be decoded (first: /pressure, message 6: the message ends inside fluid_pressure (needs 8 bytes at offset 28, has 34))"]);
    let depths: Vec<f64> = nav.samples.iter().filter_map(|s| s.depth_m).collect();
    assert_eq!(depths.len(), 2);
    assert!((depths[0] - 10.0).abs() < 1e-9 && (depths[1] - 10.3).abs() < 1e-9, "{depths:?}");
    // The samples at 1 s of depth, altitude and attitude share one row.
    let first = nav.samples[0];
    assert_eq!(first.t_ns, t(1.0));
    assert!(first.depth_m.is_some() && first.altitude_m == Some(2.0) && first.world_from_cam_rot.is_some());
    assert_eq!(nav.samples.iter().filter_map(|s| s.vel_cam_mps).collect::<Vec<_>>(), [Vector3::new(0.0, 0.0, 0.4)]);
    assert_eq!(nav.samples.iter().filter(|s| s.world_from_cam_rot.is_some()).count(), 1);
}

/// Root-mean-square position error of `est` (TUM) against the generator's poses after the
/// Sim(3) alignment, the number of poses compared, and the alignment's scale.
fn ate_sim3(est_path: &Path, r: &SimRenderer) -> (f64, usize, f64) {
    let est = duv_core::io::tum::read_trajectory(est_path).unwrap();
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = est.iter().filter_map(|e| r.poses().iter().find(|g| g.t_ns == e.t_ns).map(|g| (e.world_from_cam.translation.vector, g.world_from_cam.translation.vector))).collect();
    let (src, dst): (Vec<_>, Vec<_>) = pairs.into_iter().unzip();
    let s = duv_core::align::umeyama(&src, &dst, true).unwrap();
    let se: f64 = src.iter().zip(&dst).map(|(a, b)| (s.transform_point(&(*a).into()).coords - b).norm_squared()).sum();
    ((se / src.len() as f64).sqrt(), src.len(), s.scaling())
}

#[test]
fn duv_run_tracks_a_bag_of_a_generated_survey() {
    let dir = tempfile::tempdir().unwrap();
    let r = renderer(100, 160, 120);
    let bag = dir.path().join("survey");
    write_sim_bag(&bag, &r, "rgb8");
    let out = dir.path().join("run");
    let res = Command::new(env!("CARGO_BIN_EXE_duv"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("RUST_LOG", "warn")
        .args(["run", "--no-map", "--no-progress", "--source", &format!("rosbag:{}", bag.display()), "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&res.stdout), String::from_utf8_lossy(&res.stderr));
    assert!(res.status.success(), "{text}");
    assert!(text.contains("ROS 2 bag"), "{text}");
    assert!(text.contains("outputs in metres"), "the bag's navigation topics give the scale: {text}");
    let (ate, n, scale) = ate_sim3(&out.join("trajectory.txt"), &r);
    eprintln!("rosbag run: {n} poses, ATE (Sim3) {ate:.4} m, scale to truth {scale:.4}");
    assert!(n >= 95, "{n} of 100 frames with a pose:\n{text}");
    assert!(ate < 0.035, "ATE {ate} m (measured 0.0165):\n{text}");
    assert!((scale - 1.0).abs() < 0.02, "metric from the bag's sensors: scale to truth {scale} (measured 1.0044)");
    // At recorded timing over 2: 30 frames at 10 fps take at least 2.9 s / 2.
    let start = std::time::Instant::now();
    let res = Command::new(env!("CARGO_BIN_EXE_duv"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("RUST_LOG", "warn")
        .args(["run", "--no-map", "--no-progress", "--frames", "30", "--speed", "2", "--source", &format!("rosbag:{}", bag.display()), "--out"])
        .arg(dir.path().join("paced"))
        .output()
        .unwrap();
    let paced_s = start.elapsed().as_secs_f64();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    eprintln!("30 frames at --speed 2: {paced_s:.2} s");
    assert!(paced_s >= 1.45, "paced at recorded timing / 2: {paced_s} s");
}


#[test]
fn a_bag_written_by_the_python_rosbags_package_reads_back() {
    let Some(py) = python::python_with("rosbags.rosbag2, numpy", "rosbags") else { return };
    let dir = tempfile::tempdir().unwrap();
    let r = renderer(4, 48, 36);
    let mut args: Vec<String> = Vec::new();
    for i in 0..r.len() {
        let f = r.render(i);
        let png = dir.path().join(format!("{i}.png"));
        duv_core::io::png_io::write_rgb8(&png, &f.rgb).unwrap();
        args.push(format!("{}:{}", f.t_ns.t_ns(), png.display()));
    }
    let c = r.camera();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_rosbag.py");
    // Chunks uncompressed, zstd (rosbag2's default for MCAP) and lz4.
    for compress in ["none", "zstd", "lz4"] {
        let bag = dir.path().join(format!("from_python_{compress}"));
        let mut cmd = Command::new(&py);
        cmd.arg(&script);
        if compress != "none" {
            cmd.args(["--compress", compress]);
        }
        let out = cmd.arg(&bag).args([c.fx, c.fy, c.cx, c.cy].map(|v| v.to_string())).args(&args).output().unwrap();
        assert!(out.status.success(), "{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        // Two image topics (raw bgr8 and its PNG-compressed twin): each named, each equal to
        // the generator's frames; the camera from /cam/camera_info; attitude from /imu/data.
        let e = open(&bag.display().to_string()).err().unwrap().to_string();
        assert!(e.starts_with("several image topics: /cam/image_raw (sensor_msgs/msg/Image, 4 messages), /cam/image_raw/compressed"), "{compress}: {e}");
        for topic in ["/cam/image_raw", "/cam/image_raw/compressed"] {
            let mut src = open(&format!("{},image={topic}", bag.display())).unwrap();
            assert_eq!((src.camera_from(), *src.camera()), ("/cam/camera_info", *c), "{compress} {topic}");
            let frames = frames_of(&mut src);
            assert_eq!(frames.len(), 4, "{compress} {topic}");
            for (i, f) in frames.iter().enumerate() {
                let truth = r.render(i);
                assert_eq!(f.t_ns, truth.t_ns, "{compress} {topic} {i}");
                assert_eq!(f.image, FrameImage::Rgb8(truth.rgb), "{compress} {topic} {i}");
            }
            assert_eq!(src.nav().samples.len(), 4);
            assert!(src.nav().samples.iter().all(|s| s.world_from_cam_rot.is_some_and(|q| q.angle() == 0.0)));
            assert_eq!(src.nav_topics()[0].topic, "/imu/data");
        }
    }
}
