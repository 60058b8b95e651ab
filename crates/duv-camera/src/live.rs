//! What the live cameras (V4L2, Aravis) share: their spec `KIND:DEVICE[,calib=FILE][,mask=FILE]`, the
//! camera model from the calibration file checked against the board's image size, the board's
//! pixel format as a raw layout, decoding a driver buffer into a reused frame image, and the
//! corrupt-frame accounting (drop and count; a long run of corrupt frames ends the stream).

use super::dataset::read_calibration;
use super::pixel::{self, PixelError, RawFormat};
use super::{CameraError, SourceStats};
use duv_core::config::board::{Board, PixelFormat};
use duv_core::{FrameImage, ImageGray8, ImageRgb8, PinholeCamera};
use std::path::PathBuf;
use std::time::Duration;

/// This many corrupt frames in a row end the stream with [`CameraError::CorruptStream`]: a
/// camera that sends nothing usable is as good as gone.
pub const CORRUPT_RUN_LIMIT: u32 = 100;

/// A parsed live-camera spec `KIND:DEVICE[,calib=FILE][,mask=FILE]`.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveSpec {
    /// `v4l2` or `aravis`.
    pub kind: &'static str,
    /// Device path (`/dev/video0`) or camera id (`Fake_1`, `127.0.0.1`, `Basler-123456`).
    pub device: String,
    /// `calib=FILE`: intrinsics in the `calibration.txt` format (`fx fy cx cy width height`).
    pub calib: Option<PathBuf>,
    /// `mask=FILE`: pixels to ignore (the vehicle's own frame in view, a burned-in overlay):
    /// an image of the board's delivered size, non-zero (any channel) where they are.
    pub mask: Option<PathBuf>,
}

impl LiveSpec {
    /// Parses the part after `KIND:`; `spec` is the whole text, for messages.
    pub fn parse(kind: &'static str, spec: &str, rest: &str) -> Result<LiveSpec, CameraError> {
        let bad = |problem: String| CameraError::BadSpec { spec: spec.to_string(), problem };
        let mut parts = rest.split(',');
        let device = parts.next().unwrap_or("").trim();
        if device.is_empty() {
            return Err(bad(format!("no device after {kind}:")));
        }
        let mut out = LiveSpec { kind, device: device.to_string(), calib: None, mask: None };
        for part in parts {
            match part.split_once('=').map(|(k, v)| (k.trim(), v.trim())) {
                Some(("calib", v)) if !v.is_empty() && out.calib.is_none() => out.calib = Some(PathBuf::from(v)),
                Some(("calib", _)) => return Err(bad("calib= given twice or empty".into())),
                Some(("mask", v)) if !v.is_empty() && out.mask.is_none() => out.mask = Some(PathBuf::from(v)),
                Some(("mask", _)) => return Err(bad("mask= given twice or empty".into())),
                _ => return Err(bad(format!("unknown option {part:?} (accepted: calib=FILE, mask=FILE)"))),
            }
        }
        Ok(out)
    }

    /// The pixels `mask=FILE` marks, 1 each, at `camera`'s size (the frames this camera
    /// delivers); `None` without `mask=`. An unreadable file, a wrong size or a mask of every
    /// pixel is an error naming the file.
    pub fn ignore_mask(&self, camera: &PinholeCamera) -> Result<Option<Vec<u8>>, CameraError> {
        let Some(path) = &self.mask else { return Ok(None) };
        let bad = |problem: String| CameraError::BadSpec { spec: format!("{}:{}", self.kind, self.device), problem: format!("mask={}: {problem}", path.display()) };
        let image = super::dataset::read_image_file(path).map_err(|e| bad(e.to_string()))?.to_rgb8();
        let (w, h) = (camera.width, camera.height);
        if image.width != w || image.height != h {
            return Err(bad(format!("{}x{}, the camera delivers {w}x{h}", image.width, image.height)));
        }
        let out: Vec<u8> = image.data.chunks_exact(3).map(|p| u8::from(p.iter().any(|&v| v > 0))).collect();
        let ignored = out.iter().filter(|&&m| m == 1).count();
        if ignored == out.len() {
            return Err(bad("every pixel is masked".into()));
        }
        tracing::info!("{}: {ignored} of {} pixels ignored ({:.1}%)", path.display(), out.len(), 100.0 * ignored as f64 / out.len() as f64);
        Ok(Some(out))
    }

    /// How errors name this camera: the device path, or `aravis:ID`.
    pub fn device_name(&self) -> String {
        if self.device.starts_with('/') {
            self.device.clone()
        } else {
            format!("{}:{}", self.kind, self.device)
        }
    }

    /// The camera model from `calib=FILE`, which must describe the board's image size.
    pub fn camera_model(&self, board: &Board) -> Result<PinholeCamera, CameraError> {
        let path = self.calib.clone().ok_or_else(|| CameraError::MissingCalibration {
            path: PathBuf::from(format!("{}:{},calib=?", self.kind, self.device)),
            hint: "a live camera needs its intrinsics: add calib=FILE (one line `fx fy cx cy width height`) to the source spec",
        })?;
        let camera = read_calibration(&path)?;
        let (w, h) = (board.camera.width as usize, board.camera.height as usize);
        if camera.width != w || camera.height != h {
            return Err(CameraError::ImageSize { path, width: w, height: h, expected_width: camera.width, expected_height: camera.height });
        }
        Ok(camera)
    }
}

/// The board's pixel format as a raw layout.
pub fn raw_format(format: PixelFormat) -> RawFormat {
    match format {
        PixelFormat::Rgb24 => RawFormat::Rgb24,
        PixelFormat::Yuyv => RawFormat::Yuyv,
        PixelFormat::Mjpeg => RawFormat::Mjpeg,
        PixelFormat::Grey => RawFormat::Grey,
        PixelFormat::BayerRg8 => RawFormat::BayerRg8,
    }
}

/// How long to wait for one frame before calling the camera gone: ten frame periods, at
/// least one second.
pub fn frame_timeout(fps: f64) -> Duration {
    Duration::from_secs_f64((10.0 / fps).max(1.0))
}

/// Decodes driver buffers into frame images and keeps the drop counters.
#[derive(Debug)]
pub struct FrameDecoder {
    pub format: RawFormat,
    pub width: usize,
    pub height: usize,
    /// Bytes per row in the driver buffer (raw layouts).
    pub stride_bytes: usize,
    pub stats: SourceStats,
    corrupt_run: u32,
    last_problem: String,
}

impl FrameDecoder {
    pub fn new(format: RawFormat, width: usize, height: usize, stride_bytes: usize) -> Self {
        FrameDecoder { format, width, height, stride_bytes, stats: SourceStats::default(), corrupt_run: 0, last_problem: String::new() }
    }

    /// An image of the right kind and size to decode into.
    pub fn blank_image(&self) -> FrameImage {
        if self.format.is_grey() {
            FrameImage::Gray8(ImageGray8::new(self.width, self.height))
        } else {
            FrameImage::Rgb8(ImageRgb8::new(self.width, self.height))
        }
    }

    /// Decodes `data` into `image` (reusing its buffer when it has the right kind).
    pub fn decode_into(&self, data: &[u8], image: &mut FrameImage) -> Result<(), PixelError> {
        let (w, h, s) = (self.width, self.height, self.stride_bytes);
        if self.format.is_grey() != matches!(image, FrameImage::Gray8(_)) {
            *image = self.blank_image();
        }
        match (self.format, image) {
            (RawFormat::Grey, FrameImage::Gray8(g)) => pixel::grey_to_gray8(data, w, h, s, g),
            (RawFormat::Yuyv, FrameImage::Rgb8(c)) => pixel::yuyv_to_rgb8(data, w, h, s, c),
            (RawFormat::Rgb24, FrameImage::Rgb8(c)) => pixel::rgb24_to_rgb8(data, w, h, s, c),
            (RawFormat::BayerRg8, FrameImage::Rgb8(c)) => pixel::bayer_rg8_to_rgb8(data, w, h, s, c),
            (RawFormat::Mjpeg, FrameImage::Rgb8(c)) => pixel::mjpeg_to_rgb8(data, w, h, c),
            (f, _) => Err(PixelError::Target { format: f.name(), target: "frame" }),
        }
    }

    /// Records a delivered frame.
    pub fn delivered(&mut self) {
        self.stats.delivered += 1;
        self.corrupt_run = 0;
    }

    /// Records a dropped frame; an error once [`CORRUPT_RUN_LIMIT`] come in a row.
    pub fn dropped(&mut self, device: &str, seq_hint: u64, problem: String) -> Result<(), CameraError> {
        self.stats.dropped_corrupt += 1;
        self.corrupt_run += 1;
        tracing::warn!(device, seq_hint, dropped = self.stats.dropped_corrupt, "dropping a corrupt frame: {problem}");
        self.last_problem = problem;
        if self.corrupt_run >= CORRUPT_RUN_LIMIT {
            return Err(CameraError::CorruptStream { device: device.to_string(), count: self.corrupt_run, last: self.last_problem.clone() });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn live_spec_parsing() {
        let s = LiveSpec::parse("v4l2", "v4l2:/dev/video2,calib=c.txt", "/dev/video2,calib=c.txt").unwrap();
        assert_eq!(s.device, "/dev/video2");
        assert_eq!(s.calib, Some(PathBuf::from("c.txt")));
        assert_eq!(s.device_name(), "/dev/video2");
        let a = LiveSpec::parse("aravis", "aravis:Fake_1", "Fake_1").unwrap();
        assert_eq!((a.device_name().as_str(), a.calib), ("aravis:Fake_1", None));
        assert!(LiveSpec::parse("v4l2", "v4l2:", "").is_err());
        let e = LiveSpec::parse("v4l2", "v4l2:/dev/video0,fps=3", "/dev/video0,fps=3").unwrap_err();
        assert!(e.to_string().contains("unknown option \"fps=3\""), "{e}");
        assert!(LiveSpec::parse("v4l2", "x", "/dev/video0,calib=a,calib=b").is_err());
        assert!(LiveSpec::parse("v4l2", "x", "/dev/video0,mask=a,mask=b").is_err());
    }

    #[test]
    fn a_live_mask_is_read_at_the_delivered_size() {
        let dir = tempfile::tempdir().unwrap();
        let camera = PinholeCamera { fx: 10.0, fy: 10.0, cx: 3.5, cy: 2.5, width: 8, height: 6, distortion: None };
        let mut img = ImageRgb8::new(8, 6);
        // The top two rows (a vehicle part in view).
        img.data[..2 * 8 * 3].fill(255);
        let p = dir.path().join("mask.png");
        duv_core::io::png_io::write_rgb8(&p, &img).unwrap();
        let rest = format!("/dev/video0,calib=c.txt,mask={}", p.display());
        let s = LiveSpec::parse("v4l2", "v4l2:...", &rest).unwrap();
        assert_eq!(s.mask.as_deref(), Some(p.as_path()));
        let m = s.ignore_mask(&camera).unwrap().unwrap();
        assert_eq!(m.len(), 48);
        assert_eq!(m.iter().filter(|&&v| v == 1).count(), 16);
        assert!(m[..16].iter().all(|&v| v == 1) && m[16..].iter().all(|&v| v == 0));
        // Without mask=: none.
        assert_eq!(LiveSpec::parse("v4l2", "x", "/dev/video0").unwrap().ignore_mask(&camera).unwrap(), None);
        // Wrong size, all masked, missing: errors naming the file.
        let small = PinholeCamera { width: 4, height: 3, ..camera };
        let e = s.ignore_mask(&small).unwrap_err().to_string();
        assert!(e.contains("mask.png") && e.contains("8x6") && e.contains("4x3"), "{e}");
        img.data.fill(1);
        duv_core::io::png_io::write_rgb8(&p, &img).unwrap();
        assert!(s.ignore_mask(&camera).unwrap_err().to_string().contains("every pixel"));
        let gone = LiveSpec::parse("v4l2", "x", "/dev/video0,mask=/nonexistent/m.png").unwrap();
        assert!(gone.ignore_mask(&camera).unwrap_err().to_string().contains("/nonexistent/m.png"));
    }

    #[test]
    fn corrupt_frames_are_counted_and_a_long_run_ends_the_stream() {
        let mut d = FrameDecoder::new(RawFormat::Grey, 4, 2, 4);
        let mut img = d.blank_image();
        d.decode_into(&[1, 2, 3, 4, 5, 6, 7, 8], &mut img).unwrap();
        d.delivered();
        assert!(matches!(&img, FrameImage::Gray8(g) if g.data == vec![1, 2, 3, 4, 5, 6, 7, 8]));
        // A short buffer is an error: drop it and count it.
        let err = d.decode_into(&[1, 2, 3], &mut img).unwrap_err();
        d.dropped("/dev/video9", 1, err.to_string()).unwrap();
        assert_eq!(d.stats, SourceStats { delivered: 1, dropped_corrupt: 1 });
        for i in 1..CORRUPT_RUN_LIMIT - 1 {
            d.dropped("/dev/video9", i as u64, "short".into()).unwrap();
        }
        let e = d.dropped("/dev/video9", 0, "short".into()).unwrap_err();
        assert!(e.to_string().contains("/dev/video9") && e.to_string().contains("100 frames"), "{e}");
        assert!(e.ends_stream());
        // A good frame resets the run.
        d.delivered();
        d.dropped("/dev/video9", 0, "short".into()).unwrap();
    }

    #[test]
    fn timeout_is_ten_periods_at_least_a_second() {
        assert_eq!(frame_timeout(30.0), Duration::from_secs(1));
        assert_eq!(frame_timeout(2.0), Duration::from_secs(5));
    }
}
