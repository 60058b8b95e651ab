//! Dataset readers on tiny fixtures written into temp dirs: every layout opens and yields the
//! right frames, time stamps, camera, ground truth and depth; bad input is an error naming
//! the file (and line), never a panic; a TUM-layout dataset written with the io writers reads
//! back exactly; the `duv dataset` command summarises and checks.

use duv_camera::dataset::npy::write_npy_f32;
use duv_camera::dataset::{open_dataset, DatasetKind, DepthFormat};
use duv_camera::{CameraError, FrameSource};
use duv_core::pose::se3_from_tum;
use duv_core::{FrameImage, ImageGray16, ImageGray8, ImageRgb8, PlaneF32, StampedPose, Timestamp};
use duv_core::io::png_io::{write_gray16, write_gray8, write_rgb8};
use duv_core::io::tum::{format_trajectory, write_trajectory};
use nalgebra::{Point3, Vector3};
use std::fmt::Write as _;
use std::path::Path;

const W: usize = 8;
const H: usize = 6;
const S: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// Poses are written with 9 decimals; comparisons after a text round trip use this.
const POSE_TOL: f64 = 1e-8;

fn rgb(k: usize) -> ImageRgb8 {
    ImageRgb8 { width: W, height: H, data: (0..W * H * 3).map(|i| ((i * 7 + k * 31) % 256) as u8).collect() }
}

fn grey(k: usize) -> ImageGray8 {
    ImageGray8 { width: W, height: H, data: (0..W * H).map(|i| ((i * 5 + k * 40) % 256) as u8).collect() }
}

fn spec(kind: &str, dir: &Path) -> String {
    format!("{kind}:{}", dir.display())
}

fn assert_err_contains(e: &CameraError, parts: &[&str]) {
    let text = e.to_string();
    for p in parts {
        assert!(text.contains(p), "error {text:?} lacks {p:?}");
    }
}

// ---- TUM ----

fn tum_poses() -> Vec<StampedPose> {
    [(1.0, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]), (1.1, [0.5, -0.25, 1.0, 0.0, S, 0.0, S]), (1.2, [1.0, -0.5, 2.0, 0.0, 0.0, 0.6, 0.8])]
        .iter()
        .map(|&(t, v)| StampedPose { t_ns: Timestamp::from_secs_f64(t), world_from_cam: se3_from_tum(v).unwrap() })
        .collect()
}

fn depth_image() -> ImageGray16 {
    let mut d = ImageGray16 { width: W, height: H, data: vec![5000; W * H] };
    d.data[0] = 0;
    d.data[1] = 12345;
    d
}

/// Three 8x6 frames at 1.0, 1.1, 1.2 s; depth 5 ms later; ground truth; medium; calibration.
fn write_tum(dir: &Path) {
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    let (mut rgb_txt, mut depth_txt) = ("# color images\n# timestamp filename\n".to_string(), "# depth\n".to_string());
    for (k, t) in ["1.000000", "1.100000", "1.200000"].iter().enumerate() {
        write_rgb8(&dir.join(format!("rgb/{t}.png")), &rgb(k)).unwrap();
        writeln!(rgb_txt, "{t} rgb/{t}.png").unwrap();
        let td = format!("1.{}05", k);
        write_gray16(&dir.join(format!("depth/{td}.png")), &depth_image()).unwrap();
        writeln!(depth_txt, "{td} depth/{td}.png").unwrap();
    }
    std::fs::write(dir.join("rgb.txt"), rgb_txt).unwrap();
    std::fs::write(dir.join("depth.txt"), depth_txt).unwrap();
    std::fs::write(dir.join("calibration.txt"), "# fx fy cx cy width height\n4 4.5 3.5 2.5 8 6\n").unwrap();
    std::fs::write(dir.join("medium.json"), r#"{"beta_D":[0.4,0.1,0.05],"beta_B":[0.3,0.1,0.06],"B_inf":[0.05,0.3,0.4]}"#).unwrap();
    write_trajectory(&dir.join("groundtruth.txt"), &tum_poses()).unwrap();
}

#[test]
fn tum_layout_opens_with_frames_depth_ground_truth_and_medium() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    let d = open_dataset(&spec("tum", dir.path())).unwrap();
    assert_eq!(d.kind, DatasetKind::Tum);
    assert_eq!((d.camera.fx, d.camera.fy, d.camera.cx, d.camera.cy, d.camera.width, d.camera.height), (4.0, 4.5, 3.5, 2.5, W, H));
    let ts: Vec<i64> = d.frames.iter().map(|f| f.t_ns.t_ns()).collect();
    assert_eq!(ts, [1_000_000_000, 1_100_000_000, 1_200_000_000]);
    assert!(d.frames[1].path.ends_with("rgb/1.100000.png"));
    let gt = d.ground_truth.as_ref().unwrap();
    assert_eq!(gt.len(), 3);
    assert!((gt[2].world_from_cam.translation.vector - Vector3::new(1.0, -0.5, 2.0)).norm() < POSE_TOL);
    assert_eq!(d.medium.unwrap().b_inf, [0.05, 0.3, 0.4]);
    let track = d.depth.as_ref().unwrap();
    assert_eq!(track.format, DepthFormat::PngU16 { units_per_metre: 5000.0 });
    assert_eq!(track.frames[0].t_ns, Timestamp(1_005_000_000));

    // Depth in metres, 0 stays invalid; association pairs each frame with the map 5 ms later.
    let depth = d.load_depth_for_frame(2).unwrap().unwrap();
    assert_eq!((depth.width, depth.height), (W, H));
    assert_eq!(depth.data[0], 0.0);
    assert!((depth.data[1] - 2.469).abs() < 1e-6 && depth.data[2] == 1.0);
    assert_eq!(d.depth_index_for(d.frames[2].t_ns, 20_000_000), Some(2));

    // depth_scale option.
    let d2 = open_dataset(&format!("{},depth_scale=1000", spec("tum", dir.path()))).unwrap();
    assert!((d2.load_depth(0).unwrap().data[2] - 5.0).abs() < 1e-6);

    // The source delivers the frames in order, then ends.
    let mut src = d.into_source();
    assert_eq!(src.camera().width, W);
    for k in 0..3 {
        let f = src.next_frame().unwrap().unwrap();
        assert_eq!((f.seq, f.image.clone()), (k as u64, FrameImage::Rgb8(rgb(k))));
    }
    assert!(src.next_frame().unwrap().is_none());
    assert!(src.describe().contains("tum dataset"));
}

#[test]
fn tum_round_trip_through_the_io_writers_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    let d = open_dataset(&spec("tum", dir.path())).unwrap();
    let gt = d.ground_truth.clone().unwrap();
    // Poses: the text form is identical and the values agree to the written precision.
    assert_eq!(format_trajectory(&gt), format_trajectory(&tum_poses()));
    for (a, b) in gt.iter().zip(tum_poses()) {
        assert_eq!(a.t_ns, b.t_ns);
        assert!((a.world_from_cam.to_homogeneous() - b.world_from_cam.to_homogeneous()).abs().max() < 1e-9);
    }
    // Images and depth: bit for bit.
    let mut src = d.clone().into_source();
    let mut k = 0;
    while let Some(f) = src.next_frame().unwrap() {
        assert_eq!(f.image, FrameImage::Rgb8(rgb(k)));
        k += 1;
    }
    assert_eq!(k, 3);
    let raw = duv_core::io::png_io::read_gray16(&d.depth.as_ref().unwrap().frames[1].path).unwrap();
    assert_eq!(raw, depth_image());
}

// ---- EuRoC ----

/// body_from_cam: camera x = -body y, camera y = -body z, camera z = body x; 0.1 m along body x.
const T_BS_YAML: &str = "T_BS:
  cols: 4
  rows: 4
  data: [0.0, 0.0, 1.0, 0.1,
        -1.0, 0.0, 0.0, 0.0,   # second row
         0.0, -1.0, 0.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
";

fn euroc_yaml() -> String {
    format!(
        "# General sensor definitions.\nsensor_type: camera\ncomment: test cam0\n\n{T_BS_YAML}\nrate_hz: 20\nresolution: [8, 6]\ncamera_model: pinhole\nintrinsics: [4.0, 4.5, 3.5, 2.5] #fu, fv, cu, cv\ndistortion_model: radial-tangential\ndistortion_coefficients: [-0.1, 0.01, 0.001, -0.002]\n"
    )
}

const EUROC_T0: i64 = 1_403_636_579_763_555_584;

/// Three grey frames 50 ms apart; ground truth at the first two.
fn write_euroc(root: &Path) {
    let cam = root.join("mav0/cam0");
    std::fs::create_dir_all(cam.join("data")).unwrap();
    let mut csv = String::from("#timestamp [ns],filename\n");
    for k in 0..3 {
        let t = EUROC_T0 + k as i64 * 50_000_000;
        write_gray8(&cam.join(format!("data/{t}.png")), &grey(k)).unwrap();
        // EuRoC files end lines in CRLF.
        write!(csv, "{t},{t}.png\r\n").unwrap();
    }
    std::fs::write(cam.join("data.csv"), csv).unwrap();
    std::fs::write(cam.join("sensor.yaml"), euroc_yaml()).unwrap();
    let gt = root.join("mav0/state_groundtruth_estimate0");
    std::fs::create_dir_all(&gt).unwrap();
    let rest = ",0,0,0,0,0,0,0,0,0";
    let text = format!(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], ...\n{EUROC_T0},0,0,0,1,0,0,0{rest}\n{},1,2,3,{S},0,0,{S}{rest}\n",
        EUROC_T0 + 50_000_000
    );
    std::fs::write(gt.join("data.csv"), text).unwrap();
}

#[test]
fn euroc_opens_with_distortion_grey_frames_and_camera_poses() {
    let dir = tempfile::tempdir().unwrap();
    write_euroc(dir.path());
    let d = open_dataset(&spec("euroc", dir.path())).unwrap();
    assert_eq!(d.kind, DatasetKind::Euroc);
    let c = d.camera;
    assert_eq!((c.fx, c.fy, c.cx, c.cy, c.width, c.height), (4.0, 4.5, 3.5, 2.5, W, H));
    let k = c.distortion.unwrap();
    assert_eq!((k.k1, k.k2, k.p1, k.p2, k.k3), (-0.1, 0.01, 0.001, -0.002, 0.0));
    assert_eq!(d.frames.iter().map(|f| f.t_ns.t_ns() - EUROC_T0).collect::<Vec<_>>(), [0, 50_000_000, 100_000_000]);
    assert!(d.depth.is_none());

    // world_from_cam = world_from_body * T_BS, checked against numbers worked out by hand.
    let gt = d.ground_truth.as_ref().unwrap();
    assert_eq!(gt.len(), 2);
    let p0 = gt[0].world_from_cam;
    assert!((p0.translation.vector - Vector3::new(0.1, 0.0, 0.0)).norm() < 1e-12);
    assert!((p0.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12, "camera looks along body x");
    assert!((p0.rotation * Vector3::x() + Vector3::y()).norm() < 1e-12, "camera right is body -y");
    let p1 = gt[1].world_from_cam;
    assert_eq!(gt[1].t_ns.t_ns(), EUROC_T0 + 50_000_000);
    // Body at (1, 2, 3) yawed 90 degrees: its x axis is world y.
    assert!((p1.translation.vector - Vector3::new(1.0, 2.1, 3.0)).norm() < 1e-12);
    assert!((p1.rotation * Vector3::z() - Vector3::y()).norm() < 1e-12);
    assert!((p1.rotation * Vector3::y() + Vector3::z()).norm() < 1e-12, "camera down is world down");
    assert!(d.body_from_cam.is_some());

    // Also opens when pointed at mav0/ directly; cam= picks another camera folder.
    assert_eq!(open_dataset(&spec("euroc", &dir.path().join("mav0"))).unwrap().frames.len(), 3);
    let e = open_dataset(&format!("{},cam=cam1", spec("euroc", dir.path()))).unwrap_err();
    assert_err_contains(&e, &["mav0/cam1/data.csv", "not found"]);

    let mut src = d.into_source();
    assert_eq!(src.next_frame().unwrap().unwrap().image, FrameImage::Gray8(grey(0)));
}

// ---- TartanAir ----

/// Three frames; NED poses: at (1, 2, 3) heading east, then 1 m further east, then 2 m.
fn write_tartanair(root: &Path, with_calibration: bool) {
    std::fs::create_dir_all(root.join("image_left")).unwrap();
    std::fs::create_dir_all(root.join("depth_left")).unwrap();
    let mut poses = String::new();
    for k in 0..3 {
        write_rgb8(&root.join(format!("image_left/{k:06}_left.png")), &rgb(k)).unwrap();
        let mut depth = PlaneF32 { width: W, height: H, data: vec![2.5 + k as f32; W * H] };
        depth.data[0] = f32::NAN;
        depth.data[1] = -1.0;
        write_npy_f32(&root.join(format!("depth_left/{k:06}_left_depth.npy")), &depth).unwrap();
        writeln!(poses, "1.0 {} 3.0 0.0 0.0 {S} {S}", 2 + k).unwrap();
    }
    std::fs::write(root.join("pose_left.txt"), poses).unwrap();
    if with_calibration {
        std::fs::write(root.join("calibration.txt"), "4 4 3.5 2.5 8 6\n").unwrap();
    }
}

#[test]
fn tartanair_opens_and_converts_ned_poses() {
    let dir = tempfile::tempdir().unwrap();
    write_tartanair(dir.path(), true);
    let d = open_dataset(&spec("tartanair", dir.path())).unwrap();
    assert_eq!(d.kind, DatasetKind::TartanAir);
    assert_eq!((d.camera.fx, d.camera.width, d.camera.height), (4.0, W, H));
    assert_eq!(d.frames.iter().map(|f| f.t_ns.t_ns()).collect::<Vec<_>>(), [0, 100_000_000, 200_000_000]);
    let gt = d.ground_truth.as_ref().unwrap();
    // NED (1, 2, 3) -> camera world (y, z, x) = (2, 3, 1); heading east (NED y) -> world x.
    let p0 = gt[0].world_from_cam;
    assert!((p0.translation.vector - Vector3::new(2.0, 3.0, 1.0)).norm() < 1e-12);
    assert!((p0.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12);
    assert!((p0.rotation * Vector3::y() - Vector3::y()).norm() < 1e-12, "down stays down");
    // Moving forward is +z in the camera's own frame.
    let next_in_cam0 = p0.inverse_transform_point(&Point3::from(gt[1].world_from_cam.translation.vector));
    assert!((next_in_cam0.coords - Vector3::new(0.0, 0.0, 1.0)).norm() < 1e-12, "{next_in_cam0}");

    let depth = d.load_depth(1).unwrap();
    assert_eq!((depth.data[0], depth.data[1], depth.data[2]), (0.0, 0.0, 3.5));
    assert_eq!(d.load_depth_for_frame(2).unwrap().unwrap().data[5], 4.5);

    // fps option; the default TartanAir camera when there is no calibration file, which then
    // does not match these tiny images: a size error naming the file, at read time.
    let d20 = open_dataset(&format!("{},fps=20", spec("tartanair", dir.path()))).unwrap();
    assert_eq!(d20.frames[2].t_ns, Timestamp(100_000_000));
    std::fs::remove_file(dir.path().join("calibration.txt")).unwrap();
    let d = open_dataset(&spec("tartanair", dir.path())).unwrap();
    assert_eq!((d.camera.fx, d.camera.fy, d.camera.cx, d.camera.cy, d.camera.width, d.camera.height), (320.0, 320.0, 320.0, 240.0, 640, 480));
    let e = d.into_source().next_frame().unwrap_err();
    assert_err_contains(&e, &["000000_left.png", "image is 8x6, the camera model is 640x480"]);
}

#[test]
fn tartanair_gaps_and_pose_count_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    write_tartanair(dir.path(), true);
    std::fs::write(dir.path().join("pose_left.txt"), "1 2 3 0 0 0 1\n").unwrap();
    let e = open_dataset(&spec("tartanair", dir.path())).unwrap_err();
    assert_err_contains(&e, &["pose_left.txt", "1 poses for 3 images"]);
    std::fs::remove_file(dir.path().join("image_left/000001_left.png")).unwrap();
    let e = open_dataset(&spec("tartanair", dir.path())).unwrap_err();
    assert_err_contains(&e, &["000001_left.png", "missing"]);
}

// ---- plain folder ----

#[test]
fn folder_time_stamps_from_names_or_rate() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path();
    std::fs::write(p.join("calibration.txt"), "4 4 3.5 2.5 8 6\n").unwrap();
    for (k, name) in ["10.250000", "1.500000", "2.000000"].iter().enumerate() {
        write_rgb8(&p.join(format!("{name}.png")), &rgb(k)).unwrap();
    }
    std::fs::write(p.join("notes.txt"), "not an image").unwrap();
    let d = open_dataset(&spec("folder", p)).unwrap();
    assert_eq!(d.kind, DatasetKind::Folder);
    // Ordered by time, not by name.
    assert_eq!(d.frames.iter().map(|f| f.t_ns.t_ns()).collect::<Vec<_>>(), [1_500_000_000, 2_000_000_000, 10_250_000_000]);
    // fps= forces i / fps in name order.
    let d = open_dataset(&format!("{},fps=20", spec("folder", p))).unwrap();
    assert_eq!(d.frames.iter().map(|f| f.t_ns.t_ns()).collect::<Vec<_>>(), [0, 50_000_000, 100_000_000]);
    assert!(d.frames[0].path.ends_with("1.500000.png"));

    // 19-digit nanosecond names; a calibration file elsewhere via calib=.
    let ns = tempfile::tempdir().unwrap();
    for k in 0..2 {
        write_rgb8(&ns.path().join(format!("{}.png", EUROC_T0 + k)), &rgb(k as usize)).unwrap();
    }
    let cal = p.join("calibration.txt").display().to_string();
    let d = open_dataset(&format!("{},calib={cal}", spec("folder", ns.path()))).unwrap();
    assert_eq!(d.frames[1].t_ns, Timestamp(EUROC_T0 + 1));

    // Anything else: name order at the default 10 fps.
    let plain = tempfile::tempdir().unwrap();
    for (k, name) in ["img_b", "img_a", "000123"].iter().enumerate() {
        write_rgb8(&plain.path().join(format!("{name}.png")), &rgb(k)).unwrap();
    }
    let d = open_dataset(&format!("{},calib={cal}", spec("folder", plain.path()))).unwrap();
    assert_eq!(d.frames.iter().map(|f| f.t_ns.t_ns()).collect::<Vec<_>>(), [0, 100_000_000, 200_000_000]);
    assert!(d.frames[0].path.ends_with("000123.png") && d.frames[2].path.ends_with("img_b.png"));
    let mut src = d.into_source();
    assert_eq!(src.next_frame().unwrap().unwrap().image, FrameImage::Rgb8(rgb(2)));

    // Without any calibration: an error naming the file looked for.
    let e = open_dataset(&spec("folder", plain.path())).unwrap_err();
    assert!(matches!(e, CameraError::MissingCalibration { .. }));
    assert_err_contains(&e, &["calibration.txt", "calibration file not found"]);
}

/// JPEG frames named by video time in `DIR/images/`, no calibration file: `fov=DEG` guesses
/// the intrinsics; frames decode within JPEG's error of the pixels written.
#[test]
fn folder_of_jpeg_frames_with_video_times_and_a_field_of_view_guess() {
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("images");
    std::fs::create_dir_all(&images).unwrap();
    // A smooth image (JPEG's 8x8 blocks keep it within a few levels).
    let (w, h) = (64usize, 48usize);
    let smooth = |k: usize| ImageRgb8 { width: w, height: h, data: (0..w * h * 3).map(|i| ((i / 3 % w) * 2 + (i / 3 / w) + k * 10) as u8).collect() };
    let enc = duv_log::jpeg::JpegEncoder::new(95).unwrap();
    for (k, name) in ["frame_00_00_21.000", "frame_00_00_35.500", "frame_00_00_22.000"].iter().enumerate() {
        let mut bytes = Vec::new();
        enc.encode(&smooth(k).data, w, h, 3, &mut bytes).unwrap();
        std::fs::write(images.join(format!("{name}.jpg")), bytes).unwrap();
    }
    // No calibration: the error says how to guess one.
    let e = open_dataset(&spec("folder", dir.path())).unwrap_err();
    assert_err_contains(&e, &["calibration.txt", "fov=DEG"]);
    let d = open_dataset(&format!("{},fov=90", spec("folder", dir.path()))).unwrap();
    // Irregular gaps kept, in time order.
    assert_eq!(d.frames.iter().map(|f| f.t_ns.t_ns()).collect::<Vec<_>>(), [21_000_000_000, 22_000_000_000, 35_500_000_000]);
    // 90 degrees: fx = half the width.
    assert!((d.camera.fx - 32.0).abs() < 1e-9 && d.camera.fx == d.camera.fy && (d.camera.cx - 31.5).abs() < 1e-9 && (d.camera.cy - 23.5).abs() < 1e-9);
    assert_eq!((d.camera.width, d.camera.height), (w, h));
    let mut src = d.into_source();
    let f = src.next_frame().unwrap().unwrap();
    let FrameImage::Rgb8(img) = f.image else { panic!("JPEG frames decode to RGB") };
    let max_err = img.data.iter().zip(&smooth(0).data).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
    assert!(max_err <= 8, "JPEG frame differs by up to {max_err} levels");
    // downsample=2: half the size, the camera scaled, each pixel the mean of its 2x2 block.
    let d = open_dataset(&format!("{},fov=90,downsample=2", spec("folder", dir.path()))).unwrap();
    assert_eq!((d.camera.width, d.camera.height), (w / 2, h / 2));
    assert!((d.camera.fx - 16.0).abs() < 1e-9 && (d.camera.cx - 15.5).abs() < 1e-9);
    let full = img.clone();
    let f = d.into_source().next_frame().unwrap().unwrap();
    let FrameImage::Rgb8(half) = f.image else { panic!("RGB") };
    assert_eq!((half.width, half.height), (w / 2, h / 2));
    let mean = |x: usize, y: usize, c: usize| ((0..4).map(|k| full.data[((2 * y + k / 2) * w + 2 * x + k % 2) * 3 + c] as u32).sum::<u32>() + 2) / 4;
    assert_eq!(half.data[(5 * (w / 2) + 7) * 3 + 1] as u32, mean(7, 5, 1));
    let e = open_dataset(&format!("{},fov=90,downsample=9", spec("folder", dir.path()))).unwrap_err();
    assert_err_contains(&e, &["downsample", "1 to 8"]);
    // A bad field of view is refused by name.
    let e = open_dataset(&format!("{},fov=200", spec("folder", dir.path()))).unwrap_err();
    assert_err_contains(&e, &["fov", "1 to 170"]);
}

/// 16-bit TIFF frames (RGB and grey, as a scientific camera writes them) in a folder: read
/// with each sample's high byte, the same mapping for every frame; a float TIFF is refused by
/// name, and a truncated one is an error naming the file, not a panic.
#[test]
fn folder_of_16_bit_tiff_frames() {
    use tiff::encoder::{colortype, TiffEncoder};
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (40usize, 30usize);
    let rgb16 = |k: usize| -> Vec<u16> { (0..w * h * 3).map(|i| ((i * 97 + k * 4099) % 65536) as u16).collect() };
    for k in 0..3 {
        let f = std::fs::File::create(dir.path().join(format!("{k:04}.tif"))).unwrap();
        TiffEncoder::new(f).unwrap().write_image::<colortype::RGB16>(w as u32, h as u32, &rgb16(k)).unwrap();
    }
    std::fs::write(dir.path().join("calibration.txt"), "30 30 19.5 14.5 40 30\n").unwrap();
    let d = open_dataset(&spec("folder", dir.path())).unwrap();
    assert_eq!(d.frames.len(), 3);
    let mut src = d.into_source();
    for k in 0..3 {
        let f = src.next_frame().unwrap().unwrap();
        let FrameImage::Rgb8(img) = f.image else { panic!("RGB TIFF frames decode to RGB") };
        assert_eq!((img.width, img.height), (w, h));
        assert!(img.data.iter().zip(rgb16(k)).all(|(&a, b)| a == (b >> 8) as u8), "frame {k}: not the high bytes");
    }
    // Grey 16-bit.
    let grey_path = dir.path().join("grey.tiff");
    let grey16: Vec<u16> = (0..w * h).map(|i| (i * 50) as u16).collect();
    TiffEncoder::new(std::fs::File::create(&grey_path).unwrap()).unwrap().write_image::<colortype::Gray16>(w as u32, h as u32, &grey16).unwrap();
    let FrameImage::Gray8(g) = duv_camera::dataset::read_image_file(&grey_path).unwrap() else { panic!("grey TIFF decodes to grey") };
    assert!(g.data.iter().zip(&grey16).all(|(&a, &b)| a == (b >> 8) as u8));
    // Float samples are refused by name; a cut file is an error naming it.
    let float_path = dir.path().join("float.tif");
    TiffEncoder::new(std::fs::File::create(&float_path).unwrap()).unwrap().write_image::<colortype::Gray32Float>(w as u32, h as u32, &vec![0.5f32; w * h]).unwrap();
    let e = duv_camera::dataset::read_image_file(&float_path).unwrap_err();
    assert_err_contains(&e, &["float.tif", "TIFF"]);
    let bytes = std::fs::read(dir.path().join("0000.tif")).unwrap();
    let cut = dir.path().join("cut.tif");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = duv_camera::dataset::read_image_file(&cut).unwrap_err();
    assert_err_contains(&e, &["cut.tif"]);
}

/// The real SUBVO pool footage (`../shared/data/real/subvo`, Neyestani et al., I2MTC 2025, CC
/// BY 4.0) opens as it ships: 220 JPEG frames of 1280x720 in `images/`, time stamps from the
/// video times in the names (1-14 s gaps), the ground truth beside them.
#[test]
fn real_subvo_footage_opens_as_shipped() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/real/subvo");
    let d = open_dataset(&format!("folder:{},fov=77", root.display())).unwrap();
    assert_eq!(d.frames.len(), 220);
    assert_eq!((d.camera.width, d.camera.height), (1280, 720));
    assert!((d.camera.fx - 640.0 / (38.5f64).to_radians().tan()).abs() < 1e-6);
    let gaps: Vec<f64> = d.frames.windows(2).map(|w| (w[1].t_ns.t_ns() - w[0].t_ns.t_ns()) as f64 * 1e-9).collect();
    let (min, max) = gaps.iter().fold((f64::MAX, 0.0f64), |(a, b), &g| (a.min(g), b.max(g)));
    assert!(min >= 0.9 && max <= 15.0, "gaps {min}..{max} s");
    assert_eq!(d.frames[0].t_ns.t_ns(), 21_000_000_000);
    let gt = d.ground_truth.as_ref().expect("groundtruth.txt");
    assert_eq!(gt.len(), 220);
    let mut src = d.into_source();
    let f = src.next_frame().unwrap().unwrap();
    assert_eq!((f.image.width(), f.image.height()), (1280, 720));
}

// ---- bad input ----

#[test]
fn calibration_line_with_five_numbers() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    std::fs::write(dir.path().join("calibration.txt"), "# fx fy cx cy width height\n4 4.5 3.5 2.5 8\n").unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["calibration.txt, line 2", "expected 6 or 11 numbers", "found 5"]);
    std::fs::remove_file(dir.path().join("calibration.txt")).unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["calibration.txt", "not found", "calib=FILE"]);
}

#[test]
fn corrupt_png_fails_at_next_frame_and_the_stream_continues() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    std::fs::write(dir.path().join("rgb/1.100000.png"), b"\x89PNG\r\n\x1a\ntruncated").unwrap();
    let mut src = open_dataset(&spec("tum", dir.path())).unwrap().into_source();
    assert_eq!(src.next_frame().unwrap().unwrap().seq, 0);
    let e = src.next_frame().unwrap_err();
    assert!(matches!(e, CameraError::BadFrame { index: 1, .. }));
    assert_err_contains(&e, &["frame 1", "rgb/1.100000.png", "not a readable PNG"]);
    let f = src.next_frame().unwrap().unwrap();
    assert_eq!((f.seq, f.image), (2, FrameImage::Rgb8(rgb(2))));
    assert!(src.next_frame().unwrap().is_none());
}

#[test]
fn ground_truth_line_with_nan() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    std::fs::write(dir.path().join("groundtruth.txt"), "# gt\n1.0 0 0 0 0 0 0 1\n1.1 0 nan 0 0 0 0 1\n").unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["groundtruth.txt, line 3", "non-finite"]);
    // EuRoC ground truth too.
    let eu = tempfile::tempdir().unwrap();
    write_euroc(eu.path());
    let gt = eu.path().join("mav0/state_groundtruth_estimate0/data.csv");
    std::fs::write(&gt, format!("#t\n{EUROC_T0},0,0,NaN,1,0,0,0\n")).unwrap();
    let e = open_dataset(&spec("euroc", eu.path())).unwrap_err();
    assert_err_contains(&e, &["state_groundtruth_estimate0/data.csv, line 2", "field 4", "not a finite number"]);
}

#[test]
fn rgb_list_naming_a_missing_file() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    std::fs::remove_file(dir.path().join("rgb/1.200000.png")).unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert!(matches!(e, CameraError::MissingFile { line: 5, .. }), "{e}");
    assert_err_contains(&e, &["rgb.txt, line 5", "rgb/1.200000.png does not exist"]);
    // Time stamps must increase.
    let mut text = std::fs::read_to_string(dir.path().join("rgb.txt")).unwrap();
    text = text.replace("1.200000 rgb/1.200000.png", "1.000000 rgb/1.000000.png");
    std::fs::write(dir.path().join("rgb.txt"), text).unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["rgb.txt, line 5", "not after the previous one"]);
}

#[test]
fn truncated_euroc_data_csv_line() {
    let dir = tempfile::tempdir().unwrap();
    write_euroc(dir.path());
    let csv = dir.path().join("mav0/cam0/data.csv");
    let mut text = std::fs::read_to_string(&csv).unwrap();
    text.push_str("14036365799");
    std::fs::write(&csv, &text).unwrap();
    let e = open_dataset(&spec("euroc", dir.path())).unwrap_err();
    assert_err_contains(&e, &["mav0/cam0/data.csv, line 5", "expected 2 fields (timestamp [ns],filename), found 1"]);
    std::fs::write(&csv, text.replace("14036365799", &format!("{},", EUROC_T0 + 150_000_000))).unwrap();
    let e = open_dataset(&spec("euroc", dir.path())).unwrap_err();
    assert_err_contains(&e, &["data.csv, line 5", "found 1"]);
}

#[test]
fn malformed_sensor_yaml() {
    let dir = tempfile::tempdir().unwrap();
    write_euroc(dir.path());
    let yaml = dir.path().join("mav0/cam0/sensor.yaml");
    std::fs::write(&yaml, euroc_yaml().replace("[4.0, 4.5, 3.5, 2.5]", "[4.0, 4.5, abc, 2.5]")).unwrap();
    let e = open_dataset(&spec("euroc", dir.path())).unwrap_err();
    assert_err_contains(&e, &["sensor.yaml, line 16", "`intrinsics` value \"abc\" is not a finite number"]);
    std::fs::write(&yaml, euroc_yaml().replace("  data: [0.0,", "  data: 0.0,")).unwrap();
    let e = open_dataset(&spec("euroc", dir.path())).unwrap_err();
    assert_err_contains(&e, &["sensor.yaml, line 9", "expected `key: value`"]);
}

#[test]
fn empty_folders() {
    let dir = tempfile::tempdir().unwrap();
    let e = open_dataset(&spec("folder", dir.path())).unwrap_err();
    assert!(matches!(e, CameraError::Empty { .. }));
    assert_err_contains(&e, &[&dir.path().display().to_string(), "no PNG, JPEG or TIFF images (here or in images/) found"]);
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["rgb.txt", "not found"]);
    std::fs::write(dir.path().join("rgb.txt"), "# nothing\n").unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["rgb.txt", "no image lines found"]);
    std::fs::create_dir(dir.path().join("image_left")).unwrap();
    let e = open_dataset(&spec("tartanair", dir.path())).unwrap_err();
    assert_err_contains(&e, &["image_left", "no NNNNNN_left.png images found"]);
    let e = open_dataset(&spec("euroc", dir.path())).unwrap_err();
    assert_err_contains(&e, &["mav0/cam0/data.csv", "not found"]);
    let e = open_dataset(&format!("kitti:{}", dir.path().display())).unwrap_err();
    assert!(matches!(e, CameraError::UnknownSource { .. }), "{e}");
}

#[test]
fn npy_depth_with_the_wrong_dtype() {
    let dir = tempfile::tempdir().unwrap();
    write_tartanair(dir.path(), true);
    let p = dir.path().join("depth_left/000001_left_depth.npy");
    let mut bytes = std::fs::read(&p).unwrap();
    let at = bytes.windows(3).position(|w| w == b"<f4").unwrap();
    bytes[at..at + 3].copy_from_slice(b"<f8");
    std::fs::write(&p, bytes).unwrap();
    let d = open_dataset(&spec("tartanair", dir.path())).unwrap();
    assert!(d.load_depth(0).is_ok());
    let e = d.load_depth(1).unwrap_err();
    assert!(matches!(e, CameraError::BadNpy { .. }));
    assert_err_contains(&e, &["000001_left_depth.npy", "dtype \"<f8\" is not little-endian float32"]);
}

// ---- the `duv dataset` command ----

#[test]
fn dataset_command_summarises_and_checks() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    let run = |args: &[&str]| std::process::Command::new(env!("CARGO_BIN_EXE_duv")).args(args).output().unwrap();
    let s = spec("tum", dir.path());
    let out = run(&["dataset", &s, "--check"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    for want in [
        "kind          tum",
        "frames        3 from 1.000000000 to 1.200000000 s (0.200 s), mean rate 10.000 Hz",
        "resolution    8x6",
        "intrinsics    fx 4 fy 4.5 cx 3.5 cy 2.5",
        "distortion    none",
        "depth         yes: 3 maps, 16-bit PNG, 5000 per metre",
        "ground truth  3 poses over 0.200 s, path length 2.291 m",
        "medium        beta_D [0.4, 0.1, 0.05]",
        "checked       3 images, 3 depth maps: 0 bad images, 0 bad depth maps",
    ] {
        assert!(stdout.contains(want), "missing {want:?} in\n{stdout}");
    }
    std::fs::write(dir.path().join("rgb/1.100000.png"), b"garbage").unwrap();
    let out = run(&["dataset", &s, "--check"]);
    assert!(!out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("bad frame 1: ") && stdout.contains("rgb/1.100000.png"), "{stdout}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("could not read 1 of 3 images and 0 of 3 depth maps"), "{stderr}");
    // Without --check the summary alone succeeds; a bad spec fails with the reason.
    assert!(run(&["dataset", &s]).status.success());
    let out = run(&["dataset", "nope:/x"]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("unknown source"));
}

// ---- Navigation sensors (nav.csv) ----

const NAV_HEADER: &str = "t_s,depth_m,altitude_m,vel_x_mps,vel_y_mps,vel_z_mps,qx,qy,qz,qw\n";

#[test]
fn nav_csv_beside_a_dataset_is_read_with_its_rejections() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    // No nav.csv: no nav data.
    assert!(open_dataset(&spec("tum", dir.path())).unwrap().nav().is_none());
    // Depth and attitude at every frame, altitude and velocity at one; a NaN depth and a
    // repeated time are rejected and counted, not fatal.
    let nav = format!(
        "{NAV_HEADER}1.000000,23.25,2.5,0.0,0.1,0.5,0,0,0,1\n1.05,NaN,,,,,,,,\n1.100000,23.5,,,,,0,0,{S},{S}\n1.1,23.4,,,,,,,,\n1.200000,23.75,,,,,,,,\n"
    );
    std::fs::write(dir.path().join("nav.csv"), nav).unwrap();
    let d = open_dataset(&spec("tum", dir.path())).unwrap();
    let track = d.nav().unwrap();
    assert_eq!(track.len(), 3);
    assert_eq!((track.rejected.non_finite, track.rejected.duplicate_time, track.rejected.total()), (1, 1, 2));
    let ts: Vec<i64> = track.samples.iter().map(|s| s.t_ns.t_ns()).collect();
    assert_eq!(ts, d.frames.iter().map(|f| f.t_ns.t_ns()).collect::<Vec<_>>(), "on the clock of rgb.txt");
    let s0 = &track.samples[0];
    assert_eq!((s0.depth_m, s0.altitude_m, s0.vel_cam_mps), (Some(23.25), Some(2.5), Some(Vector3::new(0.0, 0.1, 0.5))));
    let q = track.samples[1].world_from_cam_rot.unwrap();
    assert!((q.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    assert_eq!(track.samples[2].depth_m, Some(23.75));
    assert!((track.depth_at(Timestamp::from_secs_f64(1.15), 200_000_000).unwrap() - 23.625).abs() < 1e-12);
    // Frame times bracket their samples.
    assert_eq!(track.between(d.frames[1].t_ns, d.frames[2].t_ns).len(), 1);
}

#[test]
fn nav_option_names_the_file_for_any_layout() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    std::fs::write(dir.path().join("nav.csv"), format!("{NAV_HEADER}1.0,10,,,,,,,,\n")).unwrap();
    let other = dir.path().join("vehicle_nav.csv");
    std::fs::write(&other, format!("{NAV_HEADER}1.0,20,,,,,,,,\n1.1,20.5,,,,,,,,\n")).unwrap();
    // nav=FILE wins over DIR/nav.csv.
    let d = open_dataset(&format!("{},nav={}", spec("tum", dir.path()), other.display())).unwrap();
    assert_eq!(d.nav().unwrap().samples.iter().map(|s| s.depth_m.unwrap()).collect::<Vec<_>>(), [20.0, 20.5]);
    // EuRoC and the plain folder take it too; EuRoC also finds DIR/nav.csv.
    let eu = tempfile::tempdir().unwrap();
    write_euroc(eu.path());
    let d = open_dataset(&format!("{},nav={}", spec("euroc", eu.path()), other.display())).unwrap();
    assert_eq!(d.nav().unwrap().len(), 2);
    std::fs::write(eu.path().join("nav.csv"), format!("{NAV_HEADER}0.5,3,,,,,,,,\n")).unwrap();
    assert_eq!(open_dataset(&spec("euroc", eu.path())).unwrap().nav().unwrap().samples[0].depth_m, Some(3.0));
    let folder = tempfile::tempdir().unwrap();
    std::fs::write(folder.path().join("calibration.txt"), "4 4 3.5 2.5 8 6\n").unwrap();
    write_rgb8(&folder.path().join("1.000000.png"), &rgb(0)).unwrap();
    let d = open_dataset(&format!("{},nav={}", spec("folder", folder.path()), other.display())).unwrap();
    assert_eq!(d.nav().unwrap().len(), 2);
    // A named file that does not exist is an error naming it.
    let e = open_dataset(&format!("{},nav={}", spec("tum", dir.path()), dir.path().join("nope.csv").display())).unwrap_err();
    assert!(matches!(e, CameraError::Nav(_)), "{e}");
    assert_err_contains(&e, &["nope.csv"]);
    let e = open_dataset(&format!("{},nav=", spec("tum", dir.path()))).unwrap_err();
    assert!(matches!(e, CameraError::BadSpec { .. }), "{e}");
}

#[test]
fn bad_nav_file_is_an_error_naming_file_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    write_tum(dir.path());
    let nav = dir.path().join("nav.csv");
    std::fs::write(&nav, "t,depth\n1.0,5\n").unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["nav.csv, line 1", "expected the header `t_s,depth_m,altitude_m,"]);
    std::fs::write(&nav, format!("# vehicle 7\n{NAV_HEADER}1.0,5,,,,,,,,\n1.1,5.1,1.5 m,,,,,,,\n")).unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_eq!(e.to_string(), format!("{}, line 4, column altitude_m: \"1.5 m\" is not a number", nav.display()));
    std::fs::write(&nav, format!("{NAV_HEADER}1.0,5,,0.1,0.2,,,,,\n")).unwrap();
    let e = open_dataset(&spec("tum", dir.path())).unwrap_err();
    assert_err_contains(&e, &["nav.csv, line 2", "vel_x_mps,vel_y_mps,vel_z_mps", "vel_z_mps is empty"]);
    // A depth spike of 100 m and a sensor that stops are not errors.
    let mut rows = NAV_HEADER.to_string();
    for k in 0..30 {
        let depth = if k == 12 { 120.0 } else { 20.0 + 0.01 * k as f64 };
        let alt = if k < 10 { "2.0" } else { "" };
        writeln!(rows, "{:.1},{depth},{alt},,,,,,,", 1.0 + 0.1 * k as f64).unwrap();
    }
    std::fs::write(&nav, rows).unwrap();
    let track = open_dataset(&spec("tum", dir.path())).unwrap().nav.unwrap();
    assert_eq!((track.len(), track.rejected.depth_spike, track.rejected.total()), (29, 1, 1));
    assert_eq!(track.samples.iter().filter(|s| s.altitude_m.is_some()).count(), 10);
}

/// `mask=FILE`: pixels to ignore, read at the stored size, brought down with `downsample` (a
/// block with any masked pixel is masked); a mask of another size, or one that masks
/// everything, is an error naming the file.
#[test]
fn mask_option_reads_the_pixels_to_ignore() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path();
    std::fs::write(p.join("calibration.txt"), "4 4 3.5 2.5 8 6\n").unwrap();
    for k in 0..2 {
        write_rgb8(&p.join(format!("{k}.0.png")), &rgb(k)).unwrap();
    }
    let masks = tempfile::tempdir().unwrap();
    // The top-left 3x1 pixels (a burned-in stamp).
    let mut m = ImageGray8 { width: W, height: H, data: vec![0; W * H] };
    m.data[..3].fill(255);
    let mask = masks.path().join("mask.png");
    write_gray8(&mask, &m).unwrap();
    let d = open_dataset(&format!("{},mask={}", spec("folder", p), mask.display())).unwrap();
    let ignore = d.ignore_mask.as_ref().unwrap();
    assert_eq!(ignore.len(), W * H);
    assert_eq!(ignore.iter().enumerate().filter(|(_, &v)| v == 1).map(|(i, _)| i).collect::<Vec<_>>(), [0, 1, 2]);
    // Downsampled by 2: blocks (0, 0) and (1, 0) hold masked pixels.
    let d = open_dataset(&format!("{},downsample=2,mask={}", spec("folder", p), mask.display())).unwrap();
    assert_eq!(d.ignore_mask.as_deref().unwrap(), &[1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
    // Wrong size, everything masked, missing file: errors naming it.
    let small = masks.path().join("small.png");
    write_gray8(&small, &ImageGray8 { width: 4, height: 3, data: vec![0; 12] }).unwrap();
    let e = open_dataset(&format!("{},mask={}", spec("folder", p), small.display())).unwrap_err();
    assert_err_contains(&e, &["small.png", "4x3", "8x6"]);
    let all = masks.path().join("all.png");
    write_gray8(&all, &ImageGray8 { width: W, height: H, data: vec![1; W * H] }).unwrap();
    let e = open_dataset(&format!("{},mask={}", spec("folder", p), all.display())).unwrap_err();
    assert_err_contains(&e, &["all.png", "every pixel"]);
    let e = open_dataset(&format!("{},mask={}", spec("folder", p), masks.path().join("none.png").display())).unwrap_err();
    assert_err_contains(&e, &["none.png"]);
}
