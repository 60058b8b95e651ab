//! `camera::open_source`: every spec kind opens the right source or fails with an error that
//! names the cause (unknown kind, feature not built, `mcap:` belongs to replay, missing
//! device, missing calibration); the generator as a live source delivers the renderer's
//! frames at the board's size and frame rate with ground truth, paced in real time; the raw
//! pixel conversions do not allocate once their image has its size.

use duv_camera::pixel::{bayer_rg8_to_rgb8, grey_to_gray8, rgb24_to_rgb8, yuyv_to_rgb8};
use duv_camera::{open_source, CameraError, SourceStats};
use duv_core::config::board::Board;
use duv_core::alloc::{count_allocations_on_this_thread, is_installed, CountingAllocator};
use duv_core::{FrameImage, ImageGray8, ImageRgb8, Timestamp};
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use std::path::Path;
use std::time::Instant;

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

fn board() -> Board {
    Board::load(Path::new("boards/sim.toml")).expect("boards/sim.toml")
}

fn open_err(spec: &str, board: &Board) -> CameraError {
    match open_source(spec, board) {
        Ok(s) => panic!("{spec} opened: {}", s.describe()),
        Err(e) => e,
    }
}

fn assert_mentions(e: &CameraError, parts: &[&str]) {
    let text = e.to_string();
    for p in parts {
        assert!(text.contains(p), "error {text:?} lacks {p:?}");
    }
}

#[test]
fn specs_that_cannot_open_say_why() {
    let b = board();
    assert!(matches!(open_err("webcam0", &b), CameraError::UnknownSource { .. }));
    let e = open_err("gopro:/dev/x", &b);
    assert_mentions(&e, &["gopro:/dev/x", "v4l2, aravis, tum"]);
    let e = open_err("mcap:dive.mcap", &b);
    assert!(matches!(e, CameraError::HandledByReplay { .. }), "{e}");
    assert_mentions(&e, &["dive.mcap", "replay"]);
    let e = open_err("sim:murky", &b);
    assert_mentions(&e, &["sim:murky", "unknown water \"murky\""]);
    let e = open_err("sim:clear,frames=x", &b);
    assert_mentions(&e, &["frames=\"x\""]);
    let e = open_err("tum:/nonexistent/dive", &b);
    assert_mentions(&e, &["/nonexistent/dive", "not a directory"]);
}

#[cfg(not(feature = "v4l2"))]
#[test]
fn v4l2_without_the_feature_names_it() {
    let e = open_err("v4l2:/dev/video0", &board());
    assert!(matches!(e, CameraError::FeatureDisabled { feature: "v4l2", .. }), "{e}");
    assert_mentions(&e, &["--features v4l2"]);
}

#[cfg(not(feature = "aravis"))]
#[test]
fn aravis_without_the_feature_names_it() {
    let e = open_err("aravis:Fake_1", &board());
    assert!(matches!(e, CameraError::FeatureDisabled { feature: "aravis", .. }), "{e}");
    assert_mentions(&e, &["--features aravis"]);
}

/// A calibration file for the board's 320x240 image.
fn calibration_for_board(dir: &Path) -> std::path::PathBuf {
    let p = dir.join("calibration.txt");
    std::fs::write(&p, "300 300 160 120 320 240\n").unwrap();
    p
}

#[cfg(feature = "v4l2")]
#[test]
fn v4l2_missing_device_and_missing_calibration_are_named() {
    let b = board();
    let dir = tempfile::tempdir().unwrap();
    let calib = calibration_for_board(dir.path());
    // No calibration: refused before the device is touched.
    let e = open_err("v4l2:/dev/video0", &b);
    assert!(matches!(e, CameraError::MissingCalibration { .. }), "{e}");
    assert_mentions(&e, &["calib=FILE"]);
    // A calibration for another size.
    let small = dir.path().join("small.txt");
    std::fs::write(&small, "300 300 80 60 160 120\n").unwrap();
    let e = open_err(&format!("v4l2:/dev/video0,calib={}", small.display()), &b);
    assert_mentions(&e, &["small.txt", "160x120"]);
    // A device that does not exist.
    let e = open_err(&format!("v4l2:/dev/duv-no-such-video,calib={}", calib.display()), &b);
    assert!(matches!(e, CameraError::Device { .. }), "{e}");
    assert_mentions(&e, &["/dev/duv-no-such-video", "cannot open"]);
    // A file that is not a V4L2 device.
    let e = open_err(&format!("v4l2:/dev/null,calib={}", calib.display()), &b);
    assert_mentions(&e, &["/dev/null", "not a V4L2 device"]);
}

#[test]
fn sim_source_delivers_the_renderer_frames_with_ground_truth() {
    let mut b = board();
    b.camera.width = 96;
    b.camera.height = 64;
    b.camera.fps = 25.0;
    let mut src = open_source("sim:turbid-loop,frames=4,seed=7,pace=none", &b).unwrap();
    assert!(src.describe().contains("turbid water, loop path"), "{}", src.describe());
    assert_eq!((src.camera().width, src.camera().height), (96, 64));
    let gt = src.ground_truth().expect("the generator has ground truth").to_vec();
    assert_eq!(gt.len(), 4);

    let mut cfg = SimConfig::preset(WaterPreset::Turbid, TrajectoryKind::Loop);
    (cfg.width, cfg.height, cfg.fps, cfg.frames, cfg.seed) = (96, 64, 25.0, 4, 7);
    let reference = SimRenderer::new(&cfg).unwrap();
    for i in 0..4u64 {
        let f = src.next_frame().unwrap().expect("frame");
        assert_eq!(f.seq, i);
        // Board frame rate: 40 ms apart.
        assert_eq!(f.t_ns, Timestamp::from_ns(i as i64 * 40_000_000));
        assert_eq!(gt[i as usize].t_ns, f.t_ns);
        let want = reference.render(i as usize);
        assert_eq!(f.image, FrameImage::Rgb8(want.rgb), "frame {i} differs from the renderer's");
        assert_eq!(gt[i as usize].world_from_cam, want.world_from_cam);
    }
    assert!(src.next_frame().unwrap().is_none());
    assert_eq!(src.stats(), SourceStats { delivered: 4, dropped_corrupt: 0 });
}

#[test]
fn sim_source_paces_at_the_board_frame_rate() {
    let mut b = board();
    (b.camera.width, b.camera.height, b.camera.fps) = (32, 24, 20.0);
    let mut src = open_source("sim:clear,frames=5", &b).unwrap();
    let start = Instant::now();
    let mut n = 0;
    while src.next_frame().unwrap().is_some() {
        n += 1;
    }
    // Frame 4 is due 4 / 20 s after frame 0: never earlier.
    let elapsed = start.elapsed().as_secs_f64();
    assert_eq!(n, 5);
    assert!(elapsed >= 0.2, "5 frames at 20 fps came in {elapsed:.3} s");
}

#[test]
fn dataset_specs_open_through_open_source() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("calibration.txt"), "10 10 4 3 8 6\n").unwrap();
    for k in 0..3u8 {
        let img = ImageRgb8::filled(8, 6, [k * 10, 1, 2]);
        duv_core::io::png_io::write_rgb8(&dir.path().join(format!("img{k}.png")), &img).unwrap();
    }
    let mut src = open_source(&format!("folder:{},fps=5", dir.path().display()), &board()).unwrap();
    assert_eq!(src.camera().width, 8);
    let mut got = Vec::new();
    while let Some(f) = src.next_frame().unwrap() {
        got.push((f.t_ns.t_ns(), f.image.to_rgb8().data[0]));
    }
    assert_eq!(got, vec![(0, 0), (200_000_000, 10), (400_000_000, 20)]);
}

#[test]
fn raw_conversions_do_not_allocate_once_sized() {
    assert!(is_installed());
    let (w, h) = (64, 48);
    let yuyv = vec![128u8; w * h * 2];
    let grey = vec![7u8; w * h];
    let rgb = vec![9u8; w * h * 3];
    let mut c = ImageRgb8::new(w, h);
    let mut g = ImageGray8::new(w, h);
    // Warm-up (and proof that the counter sees allocations on this thread).
    let warm = count_allocations_on_this_thread(|| {
        let mut fresh = ImageRgb8::new(0, 0);
        yuyv_to_rgb8(&yuyv, w, h, w * 2, &mut fresh).unwrap();
    });
    assert!(warm >= 1);
    let allocations = count_allocations_on_this_thread(|| {
        for _ in 0..10 {
            yuyv_to_rgb8(&yuyv, w, h, w * 2, &mut c).unwrap();
            grey_to_gray8(&grey, w, h, w, &mut g).unwrap();
            rgb24_to_rgb8(&rgb, w, h, w * 3, &mut c).unwrap();
            bayer_rg8_to_rgb8(&grey, w, h, w, &mut c).unwrap();
        }
    });
    assert_eq!(allocations, 0);
    assert_eq!(c.pixel(w - 1, h - 1), [7, 7, 7]);
    assert_eq!(g.pixel(0, 0), [7]);
}

#[test]
fn duv_run_names_a_missing_camera() {
    let dir = tempfile::tempdir().unwrap();
    let calib = calibration_for_board(dir.path());
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_duv"))
        .args(["run", "--no-progress", "--frames", "3", "--source"])
        .arg(format!("v4l2:/dev/duv-no-such-video,calib={}", calib.display()))
        .arg("--out")
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    let needles: &[&str] = if cfg!(feature = "v4l2") { &["/dev/duv-no-such-video", "cannot open"] } else { &["--features v4l2"] };
    for n in needles {
        assert!(stderr.contains(n), "stderr lacks {n:?}: {stderr}");
    }
}
