//! Aravis / GenICam capture against Aravis's own fake cameras (feature `aravis`):
//!
//! 1. the in-process fake interface (`aravis:Fake_1`): pixel formats Mono8, RGB8 and BayerRG8,
//!    the board's region, frame rate and exposure read back from the camera, frames of the
//!    right size and kind with increasing camera time stamps and the fake camera's test
//!    pattern, and no allocation per frame in `next_frame_into` once warm;
//! 2. a camera id that does not exist: an error naming it and listing the cameras seen;
//! 3. the fake GigE Vision camera `arv-fake-gv-camera-0.8 -i 127.0.0.1` as a subprocess, so
//!    the real GVCP/GVSP protocol over UDP, losing 30% of its stream packets (`-r 300`):
//!    whole frames arrive, incomplete ones are dropped and counted, and killing the camera
//!    mid-run ("unplugged") ends the stream with an error naming it.
//!
//! `Aravis::initialize` succeeds once per process, so everything runs in one `#[test]`, in
//! sequence. Where `arv-fake-gv-camera-0.8` is missing the third case is skipped with a
//! message, except under `CI=true`, where it fails.

#![cfg(feature = "aravis")]

use duv_camera::aravis::AravisSource;
use duv_camera::live::LiveSpec;
use duv_camera::{CameraError, FrameSource, SourceStats};
use duv_core::config::board::{Board, PixelFormat};
use duv_core::{Frame, FrameImage};
use duv_core::alloc::{count_allocations_on_this_thread, is_installed, CountingAllocator};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

const FAKE_GV_CAMERA: &str = "arv-fake-gv-camera-0.8";
const W: u32 = 64;
const H: u32 = 48;

fn board(format: PixelFormat, fps: f64, exposure_us: Option<u32>) -> Board {
    let mut b = Board::load(Path::new("boards/sim.toml")).unwrap();
    (b.camera.width, b.camera.height, b.camera.fps, b.camera.pixel_format, b.camera.exposure_us) = (W, H, fps, format, exposure_us);
    b.camera.driver_buffers = 3;
    b
}

fn calib(dir: &Path) -> PathBuf {
    let p = dir.join("calibration.txt");
    std::fs::write(&p, format!("60 60 {} {} {W} {H}\n", W / 2, H / 2)).unwrap();
    p
}

fn open(id: &str, calib: &Path, board: &Board) -> Result<AravisSource, CameraError> {
    let spec = format!("aravis:{id},calib={}", calib.display());
    let live = LiveSpec::parse("aravis", &spec, spec.strip_prefix("aravis:").unwrap())?;
    AravisSource::open(&live, board)
}

fn grab(src: &mut AravisSource, n: usize) -> Vec<Frame> {
    (0..n).map(|i| src.next_frame().unwrap_or_else(|e| panic!("frame {i}: {e}")).expect("a camera never ends")).collect()
}

/// Sequence numbers 0.., strictly increasing time stamps, the board's size and image kind.
fn check_frames(frames: &[Frame], grey: bool) {
    for (i, f) in frames.iter().enumerate() {
        assert_eq!(f.seq, i as u64);
        assert_eq!((f.image.width(), f.image.height()), (W as usize, H as usize));
        assert_eq!(matches!(f.image, FrameImage::Gray8(_)), grey);
        if i > 0 {
            assert!(f.t_ns > frames[i - 1].t_ns, "time stamps must increase: {:?}", frames.iter().map(|f| f.t_ns).collect::<Vec<_>>());
        }
    }
}

fn in_process_fake_camera(dir: &Path) {
    let calib = calib(dir);
    // Mono8 with a fixed exposure at 20 fps.
    let b = board(PixelFormat::Grey, 20.0, Some(5000));
    let mut src = open("Fake_1", &calib, &b).expect("the in-process fake camera opens");
    let s = src.settings().clone();
    eprintln!("fake camera: {s:?}");
    assert_eq!((s.width, s.height), (W as usize, H as usize));
    assert_eq!(s.pixel_format, "Mono8");
    assert!((s.frame_rate_hz - 20.0).abs() < 0.2, "frame rate read back {}", s.frame_rate_hz);
    assert!((s.exposure_us.expect("the fake camera has ExposureTime") - 5000.0).abs() < 1.0, "{s:?}");
    let frames = grab(&mut src, 6);
    check_frames(&frames, true);
    // The fake camera draws a diagonal ramp: the image is not flat.
    let FrameImage::Gray8(g) = &frames[5].image else { unreachable!() };
    let (lo, hi) = (g.data.iter().min().unwrap(), g.data.iter().max().unwrap());
    assert!(hi - lo > 20, "flat fake image: {lo}..{hi}");
    // Camera time stamps at 20 fps: the median interval near 50 ms.
    let mut dt: Vec<i64> = frames.windows(2).map(|w| w[1].t_ns.t_ns() - w[0].t_ns.t_ns()).collect();
    dt.sort();
    let median_ms = dt[dt.len() / 2] as f64 * 1e-6;
    assert!((25.0..100.0).contains(&median_ms), "median frame interval {median_ms} ms at 20 fps");
    assert_eq!(src.stats(), SourceStats { delivered: 6, dropped_corrupt: 0 });
    // Steady state: capture into a reused frame allocates nothing on the Rust side (Aravis's
    // own C allocations are not seen by the counting allocator).
    assert!(is_installed());
    let mut frame = frames[0].clone();
    let mut ok = true;
    let allocations = count_allocations_on_this_thread(|| {
        for _ in 0..5 {
            ok &= matches!(src.next_frame_into(&mut frame), Ok(true));
        }
    });
    assert!(ok, "next_frame_into failed");
    assert_eq!(allocations, 0);
    assert_eq!(frame.seq, 10);
    assert_eq!(src.stats().delivered, 11);
    drop(src);

    // RGB8 and BayerRG8 become colour frames; auto exposure when the board gives none.
    for format in [PixelFormat::Rgb24, PixelFormat::BayerRg8] {
        let b = board(format, 30.0, None);
        let mut src = open("Fake_1", &calib, &b).unwrap_or_else(|e| panic!("{format:?}: {e}"));
        let frames = grab(&mut src, 3);
        check_frames(&frames, false);
        eprintln!("{format:?}: {}", src.describe());
    }

    // mask=FILE at the delivered size: the source carries it (the pipeline hands it to the
    // tracker); a mask of another size refuses the camera, naming the file.
    let mask_path = dir.join("mask.png");
    let mut m = duv_core::ImageRgb8::new(W as usize, H as usize);
    m.data[..W as usize * 3 * 4].fill(255);
    duv_core::io::png_io::write_rgb8(&mask_path, &m).unwrap();
    let spec = format!("aravis:Fake_1,calib={},mask={}", calib.display(), mask_path.display());
    let live = LiveSpec::parse("aravis", &spec, spec.strip_prefix("aravis:").unwrap()).unwrap();
    let src = AravisSource::open(&live, &board(PixelFormat::Grey, 20.0, None)).unwrap();
    let mask = src.ignore_mask().expect("the mask");
    assert_eq!((mask.len(), mask.iter().filter(|&&v| v == 1).count()), ((W * H) as usize, 4 * W as usize));
    drop(src);
    duv_core::io::png_io::write_rgb8(&mask_path, &duv_core::ImageRgb8::new(8, 8)).unwrap();
    let e = AravisSource::open(&live, &board(PixelFormat::Grey, 20.0, None)).err().expect("a mask of the wrong size");
    assert!(e.to_string().contains("mask.png") && e.to_string().contains("8x8"), "{e}");

    // MJPEG is not a GenICam format: refused with the reason.
    let e = open("Fake_1", &calib, &board(PixelFormat::Mjpeg, 10.0, None)).err().expect("MJPEG refused");
    assert!(e.to_string().contains("aravis:Fake_1") && e.to_string().contains("MJPEG"), "{e}");
}

fn missing_camera(dir: &Path) {
    let e = open("duv-no-such-camera", &calib(dir), &board(PixelFormat::Grey, 10.0, None)).err().expect("no such camera");
    let text = e.to_string();
    assert!(matches!(e, CameraError::Device { .. }), "{e}");
    assert!(text.contains("aravis:duv-no-such-camera") && text.contains("not found"), "{text}");
}

/// Kills the fake camera when the test ends, however it ends.
struct ChildGuard(Child);
impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn fake_gige_camera_over_udp(dir: &Path) {
    let spawned = Command::new(FAKE_GV_CAMERA).args(["-i", "127.0.0.1", "-r", "300"]).stdout(Stdio::null()).stderr(Stdio::null()).spawn();
    let child = match spawned {
        Ok(c) => ChildGuard(c),
        Err(e) if std::env::var("CI").as_deref() != Ok("true") => {
            eprintln!("SKIPPED the GigE Vision case: {FAKE_GV_CAMERA} cannot start ({e}); install aravis-tools");
            return;
        }
        Err(e) => panic!("CI=true and {FAKE_GV_CAMERA} cannot start ({e}): .ci/run installs aravis-tools"),
    };
    let calib = calib(dir);
    let b = board(PixelFormat::Grey, 25.0, Some(2000));
    // The camera needs a moment to bind its sockets.
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut src = loop {
        match open("127.0.0.1", &calib, &b) {
            Ok(s) => break s,
            Err(e) if Instant::now() < deadline => {
                eprintln!("waiting for the fake GigE camera: {e}");
                std::thread::sleep(Duration::from_millis(200));
            }
            Err(e) => panic!("the fake GigE Vision camera on 127.0.0.1 did not open: {e}"),
        }
    };
    eprintln!("GigE: {}", src.describe());
    let frames = grab(&mut src, 8);
    check_frames(&frames, true);
    // The camera loses 30% of its packets: incomplete frames are dropped and counted, whole
    // ones still come through (a frame is 3+ packets: P(no drop before 8 whole ones) < 1e-4).
    let stats = src.stats();
    eprintln!("GigE with 30% packet loss: {stats:?}");
    assert_eq!(stats.delivered, 8);
    assert!(stats.dropped_corrupt >= 1, "{stats:?}");
    assert!((src.settings().exposure_us.unwrap() - 2000.0).abs() < 1.0);

    // Unplug: kill the camera, the stream ends with an error naming it.
    drop(child);
    let t0 = Instant::now();
    let e = loop {
        match src.next_frame() {
            Ok(_) if t0.elapsed() < Duration::from_secs(10) => continue, // frames already in flight
            Ok(_) => panic!("frames keep coming after the camera was killed"),
            Err(e) => break e,
        }
    };
    let text = e.to_string();
    assert!(matches!(e, CameraError::Device { .. }) && e.ends_stream(), "{e}");
    assert!(text.contains("aravis:127.0.0.1") && text.contains("no frame within"), "{text}");
}

#[test]
fn aravis_fake_cameras() {
    let dir = tempfile::tempdir().unwrap();
    in_process_fake_camera(dir.path());
    missing_camera(dir.path());
    fake_gige_camera_over_udp(dir.path());
}
