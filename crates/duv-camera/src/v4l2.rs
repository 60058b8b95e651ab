//! Video4Linux2 cameras (`v4l2:/dev/video0[,calib=FILE]`, cargo feature `v4l2`).
//!
//! Opens the device, sets the board's resolution, pixel format (YUYV, MJPEG, GREY, RGB24),
//! frame rate and exposure, and streams through `board.camera.driver_buffers` mmap buffers.
//! Each dequeued buffer is decoded into the frame image (see [`super::pixel`]); a buffer the
//! driver flags as erroneous, one that is too short, or a truncated JPEG is dropped and
//! counted. Time stamps are the driver's (`CLOCK_MONOTONIC` on every current driver). A
//! device that is missing, not a capture device, refuses a setting, stops delivering or is
//! unplugged is a [`CameraError::Device`] naming its path.

use super::live::{frame_timeout, raw_format, FrameDecoder, LiveSpec};
use super::pixel::RawFormat;
use super::{CameraError, FrameSource, SourceStats};
use duv_core::config::board::Board;
use duv_core::{Frame, PinholeCamera, Timestamp};
use v4l::buffer::{Flags as BufferFlags, Type as BufferType};
use v4l::capability::Flags as CapFlags;
use v4l::control::{Control, Value};
use v4l::io::mmap::Stream as MmapStream;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, Format, FourCC, Fraction};

/// `V4L2_CID_EXPOSURE_AUTO` (camera class base `0x009a0900` + 1).
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
/// `V4L2_CID_EXPOSURE_ABSOLUTE`, in units of 100 µs.
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_EXPOSURE_MANUAL`.
pub const EXPOSURE_MANUAL: i64 = 1;
/// `V4L2_EXPOSURE_APERTURE_PRIORITY`: auto exposure time, the usual UVC auto mode.
pub const EXPOSURE_APERTURE_PRIORITY: i64 = 3;

/// The V4L2 four-character code of a raw layout.
pub fn fourcc(format: RawFormat) -> FourCC {
    FourCC::new(match format {
        RawFormat::Yuyv => b"YUYV",
        RawFormat::Mjpeg => b"MJPG",
        RawFormat::Grey => b"GREY",
        RawFormat::Rgb24 => b"RGB3",
        RawFormat::BayerRg8 => b"RGGB",
    })
}

/// `V4L2_CID_EXPOSURE_ABSOLUTE` value (100 µs units, at least 1) for an exposure in µs.
pub fn exposure_control_value(exposure_us: u32) -> i64 {
    ((exposure_us as i64 + 50) / 100).max(1)
}

/// The frame interval (seconds per frame) V4L2 is asked for at `fps`, as a fraction with a
/// millisecond-per-second resolution: 30 -> 1/30, 12.5 -> 2/25, 29.97 -> 1000/29970 reduced.
pub fn frame_interval(fps: f64) -> (u32, u32) {
    let num = 1000u32;
    let den = (fps * 1000.0).round().max(1.0) as u32;
    let g = gcd(num, den);
    (num / g, den / g)
}

fn gcd(a: u32, b: u32) -> u32 {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// A driver time stamp (`struct timeval`) in nanoseconds; `None` when it is unset (zero) or
/// negative, which drivers without time stamps deliver.
pub fn driver_time_ns(sec: i64, usec: i64) -> Option<Timestamp> {
    if sec < 0 || !(0..1_000_000).contains(&usec) || (sec == 0 && usec == 0) {
        return None;
    }
    Some(Timestamp::from_ns(sec.checked_mul(1_000_000_000)?.checked_add(usec * 1000)?))
}

/// A V4L2 capture device as a [`FrameSource`].
pub struct V4l2Source {
    // Field order matters: the stream (which unmaps the buffers and stops streaming) drops
    // before the device closes its file descriptor.
    stream: MmapStream<'static>,
    device: Device,
    path: String,
    card: String,
    camera: PinholeCamera,
    decoder: FrameDecoder,
    seq: u64,
    timeout: std::time::Duration,
    /// When the driver gives no time stamp: the last one, to keep time increasing.
    last_t_ns: Timestamp,
    /// `mask=FILE`: pixels to ignore.
    mask: Option<Vec<u8>>,
}

impl V4l2Source {
    /// Opens and configures the device the spec names; streaming starts with the first frame.
    pub fn open(spec: &LiveSpec, board: &Board) -> Result<V4l2Source, CameraError> {
        let path = spec.device.clone();
        let err = |problem: String| CameraError::Device { device: path.clone(), problem };
        let camera = spec.camera_model(board)?;
        let mask = spec.ignore_mask(&camera)?;
        let device = Device::with_path(&path).map_err(|e| err(format!("cannot open: {e}")))?;
        let caps = device.query_caps().map_err(|e| err(format!("not a V4L2 device: {e}")))?;
        if !caps.capabilities.contains(CapFlags::VIDEO_CAPTURE) || !caps.capabilities.contains(CapFlags::STREAMING) {
            return Err(err(format!("{} ({}) is not a streaming video capture device", caps.card, caps.driver)));
        }
        let c = &board.camera;
        let format = raw_format(c.pixel_format);
        if format == RawFormat::BayerRg8 {
            tracing::info!(device = %path, "asking a V4L2 device for Bayer RGGB");
        }
        let wanted = Format::new(c.width, c.height, fourcc(format));
        let got = device.set_format(&wanted).map_err(|e| err(format!("setting the format: {e}")))?;
        if got.fourcc != wanted.fourcc || got.width != c.width || got.height != c.height {
            let offered: Vec<String> = device
                .enum_formats()
                .map(|v| v.iter().map(|d| d.fourcc.str().unwrap_or("?").to_string()).collect())
                .unwrap_or_default();
            return Err(err(format!(
                "asked for {} {}x{}, the driver set {} {}x{} (it offers {})",
                format.name(),
                c.width,
                c.height,
                got.fourcc.str().unwrap_or("?"),
                got.width,
                got.height,
                offered.join(", ")
            )));
        }
        let (num, den) = frame_interval(c.fps);
        match device.set_params(&v4l::video::capture::Parameters::new(Fraction::new(num, den))) {
            Ok(p) => {
                let fps = p.interval.denominator as f64 / p.interval.numerator.max(1) as f64;
                if (fps - c.fps).abs() > 0.01 * c.fps {
                    tracing::warn!(device = %path, asked = c.fps, got = fps, "the driver chose another frame rate");
                }
            }
            Err(e) => return Err(err(format!("setting {} fps: {e}", c.fps))),
        }
        match c.exposure_us {
            Some(us) => {
                let manual = [
                    Control { id: CID_EXPOSURE_AUTO, value: Value::Integer(EXPOSURE_MANUAL) },
                    Control { id: CID_EXPOSURE_ABSOLUTE, value: Value::Integer(exposure_control_value(us)) },
                ];
                for ctrl in manual {
                    let id = ctrl.id;
                    device.set_control(ctrl).map_err(|e| err(format!("board asks exposure_us = {us}; control {id:#x}: {e}")))?;
                }
            }
            None => {
                // Auto exposure is the power-on default of most cameras; a device without the
                // control is fine.
                if let Err(e) = device.set_control(Control { id: CID_EXPOSURE_AUTO, value: Value::Integer(EXPOSURE_APERTURE_PRIORITY) }) {
                    tracing::debug!(device = %path, "auto exposure not set: {e}");
                }
            }
        }
        let mut stream = MmapStream::with_buffers(&device, BufferType::VideoCapture, c.driver_buffers)
            .map_err(|e| err(format!("allocating {} mmap buffers: {e}", c.driver_buffers)))?;
        let timeout = frame_timeout(c.fps);
        stream.set_timeout(timeout);
        let stride = if got.stride > 0 { got.stride as usize } else { c.width as usize * format.bytes_per_pixel().unwrap_or(0) };
        let decoder = FrameDecoder::new(format, c.width as usize, c.height as usize, stride);
        tracing::info!(device = %path, card = %caps.card, driver = %caps.driver, format = format.name(), stride, "V4L2 camera open");
        Ok(V4l2Source { stream, device, path, card: caps.card, camera, decoder, seq: 0, timeout, last_t_ns: Timestamp::ZERO, mask })
    }
}

impl FrameSource for V4l2Source {
    fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        let mut frame = Frame { t_ns: Timestamp::ZERO, seq: 0, image: self.decoder.blank_image() };
        Ok(self.next_frame_into(&mut frame)?.then_some(frame))
    }

    fn next_frame_into(&mut self, frame: &mut Frame) -> Result<bool, CameraError> {
        loop {
            let (buf, meta) = match CaptureStream::next(&mut self.stream) {
                Ok(x) => x,
                Err(e) => {
                    let problem = match (e.kind(), e.raw_os_error()) {
                        (std::io::ErrorKind::TimedOut, _) => format!("no frame within {:?}: stopped delivering", self.timeout),
                        (_, Some(19)) => format!("unplugged (ENODEV): {e}"),
                        _ => format!("capture failed: {e}"),
                    };
                    return Err(CameraError::Device { device: self.path.clone(), problem });
                }
            };
            let used = (meta.bytesused as usize).min(buf.len());
            let seq = self.seq;
            let problem = if meta.flags.contains(BufferFlags::ERROR) {
                Some("the driver flagged the buffer as corrupt".to_string())
            } else {
                self.decoder.decode_into(&buf[..used], &mut frame.image).err().map(|e| e.to_string())
            };
            let t_ns = driver_time_ns(meta.timestamp.sec, meta.timestamp.usec);
            if let Some(problem) = problem {
                self.decoder.dropped(&self.path, seq, problem)?;
                continue;
            }
            let t_ns = match t_ns {
                Some(t) if t > self.last_t_ns => t,
                _ => Timestamp::from_ns(self.last_t_ns.t_ns() + 1),
            };
            self.last_t_ns = t_ns;
            self.seq += 1;
            self.decoder.delivered();
            tracing::trace!(seq, t_ns = t_ns.t_ns(), driver_seq = meta.sequence, "v4l2 frame");
            (frame.t_ns, frame.seq) = (t_ns, seq);
            return Ok(true);
        }
    }

    fn describe(&self) -> String {
        let _ = &self.device;
        format!("V4L2 {} ({}), {} {}x{}", self.path, self.card, self.decoder.format.name(), self.decoder.width, self.decoder.height)
    }

    fn ignore_mask(&self) -> Option<&[u8]> {
        self.mask.as_deref()
    }

    fn stats(&self) -> SourceStats {
        self.decoder.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_intervals_and_exposure_units() {
        assert_eq!(frame_interval(30.0), (1, 30));
        assert_eq!(frame_interval(12.5), (2, 25));
        assert_eq!(frame_interval(29.97), (100, 2997));
        assert_eq!(exposure_control_value(5000), 50);
        assert_eq!(exposure_control_value(149), 1);
        assert_eq!(exposure_control_value(10), 1);
        assert_eq!(fourcc(RawFormat::Mjpeg), FourCC::new(b"MJPG"));
    }

    #[test]
    fn driver_time_stamps() {
        assert_eq!(driver_time_ns(12, 345_678), Some(Timestamp::from_ns(12_345_678_000)));
        assert_eq!(driver_time_ns(0, 0), None);
        assert_eq!(driver_time_ns(-1, 0), None);
        assert_eq!(driver_time_ns(1, 1_000_000), None);
        assert_eq!(driver_time_ns(i64::MAX, 0), None);
    }
}
