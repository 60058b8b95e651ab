//! GenICam cameras through Aravis (`aravis:ID[,calib=FILE]`, cargo feature `aravis`): GigE
//! Vision and USB3 Vision cameras by Aravis id (`Basler-21234567`, an IP address such as
//! `127.0.0.1`, or `Fake_1`, the in-process fake camera of Aravis's "Fake" interface, which
//! this module enables when an id starts with `Fake`).
//!
//! Sets the board's region (width x height at offset 0), pixel format (RGB8, Mono8, BayerRG8,
//! YUV422 YUYV), frame rate and exposure (manual when the board gives `exposure_us`, else
//! continuous auto where the camera has it), then streams continuously through
//! `board.camera.driver_buffers` buffers that are pushed back after each frame. An incomplete
//! buffer (missing packets, timeout, size mismatch) is dropped and counted. Time stamps are
//! the camera's (`ArvBuffer` timestamp, ns), else the host's reception time. No frame within
//! [`super::live::frame_timeout`] is a [`CameraError::Device`]: the camera is gone.
//!
//! The `aravis` crate lets `Aravis::initialize` succeed once per process; this module does it
//! once, behind a `OnceLock`, and every source shares it.

use super::live::{frame_timeout, raw_format, FrameDecoder, LiveSpec};
use super::pixel::RawFormat;
use super::{CameraError, FrameSource, SourceStats};
use duv_core::config::board::Board;
use duv_core::{Frame, PinholeCamera, Timestamp};
use aravis::prelude::*;
use aravis::{AcquisitionMode, Auto, Buffer, BufferStatus, Camera, PixelFormat, Stream};
use std::sync::OnceLock;
use std::time::Duration;

/// The process-wide Aravis token (`None` when something else in the process took it first,
/// which is fine: the library needs no more than the flag).
static ARAVIS: OnceLock<Option<aravis::Aravis>> = OnceLock::new();

/// Marks Aravis initialised for this process (idempotent).
pub fn ensure_initialized() {
    ARAVIS.get_or_init(|| aravis::Aravis::initialize().ok());
}

/// Enables Aravis's in-process fake interface (cameras `Fake_1`, ...). Idempotent.
pub fn enable_fake_interface() {
    ensure_initialized();
    // SAFETY: a C string literal; the call only sets a flag in the interface table.
    unsafe { aravis_sys::arv_enable_interface(c"Fake".as_ptr()) };
}

/// Ids of the cameras Aravis sees now (all enabled interfaces).
pub fn device_ids() -> Vec<String> {
    ensure_initialized();
    // SAFETY: Aravis is initialised; the list is copied out.
    unsafe { aravis::get_device_list() }.into_iter().map(|d| d.id.to_string_lossy().into_owned()).collect()
}

/// The GenICam pixel format for a raw layout; `None` for MJPEG, which GenICam cameras do not
/// stream.
pub fn genicam_format(format: RawFormat) -> Option<PixelFormat> {
    match format {
        RawFormat::Rgb24 => Some(PixelFormat::RGB_8_PACKED),
        RawFormat::Grey => Some(PixelFormat::MONO_8),
        RawFormat::BayerRg8 => Some(PixelFormat::BAYER_RG_8),
        RawFormat::Yuyv => Some(PixelFormat::YUV_422_YUYV_PACKED),
        RawFormat::Mjpeg => None,
    }
}

/// What the camera reported after configuration, for logs and tests.
#[derive(Clone, Debug, PartialEq)]
pub struct AravisSettings {
    pub model: String,
    pub width: usize,
    pub height: usize,
    pub pixel_format: String,
    pub frame_rate_hz: f64,
    /// `None` when the camera has no exposure feature.
    pub exposure_us: Option<f64>,
}

/// A GenICam camera as a [`FrameSource`].
pub struct AravisSource {
    // Field order: the stream drops before the camera.
    stream: Stream,
    cam: Camera,
    name: String,
    settings: AravisSettings,
    camera: PinholeCamera,
    decoder: FrameDecoder,
    expected_format: PixelFormat,
    timeout: Duration,
    seq: u64,
    last_t_ns: Timestamp,
    /// `mask=FILE`: pixels to ignore.
    mask: Option<Vec<u8>>,
}

impl AravisSource {
    /// Opens, configures and starts the camera the spec names.
    pub fn open(spec: &LiveSpec, board: &Board) -> Result<AravisSource, CameraError> {
        let name = spec.device_name();
        let err = |problem: String| CameraError::Device { device: name.clone(), problem };
        let camera = spec.camera_model(board)?;
        let mask = spec.ignore_mask(&camera)?;
        let c = &board.camera;
        let format = raw_format(c.pixel_format);
        let expected_format = genicam_format(format).ok_or_else(|| err("GenICam cameras do not stream MJPEG: set camera.pixel_format to rgb24, grey, bayer_rg8 or yuyv".into()))?;
        if spec.device.starts_with("Fake") {
            enable_fake_interface();
        } else {
            ensure_initialized();
        }
        let cam = Camera::new(Some(&spec.device)).map_err(|e| {
            let seen = device_ids();
            err(format!("not found ({e}); cameras seen: [{}]", seen.join(", ")))
        })?;
        let setting = |what: &str, e: aravis::glib::Error| err(format!("setting {what}: {e}"));
        cam.set_pixel_format(expected_format).map_err(|e| setting(&format!("pixel format {}", format.name()), e))?;
        cam.set_region(0, 0, c.width as i32, c.height as i32).map_err(|e| setting(&format!("region {}x{}", c.width, c.height), e))?;
        let (_, _, w, h) = cam.region().map_err(|e| err(format!("reading the region: {e}")))?;
        if (w as u32, h as u32) != (c.width, c.height) {
            return Err(err(format!("asked for {}x{}, the camera set {w}x{h}", c.width, c.height)));
        }
        cam.set_acquisition_mode(AcquisitionMode::Continuous).map_err(|e| setting("continuous acquisition", e))?;
        if cam.is_frame_rate_available().unwrap_or(false) {
            cam.set_frame_rate(c.fps).map_err(|e| setting(&format!("{} fps", c.fps), e))?;
        } else {
            tracing::warn!(device = %name, "camera has no frame-rate feature; it runs at its own rate");
        }
        let frame_rate_hz = cam.frame_rate().unwrap_or(f64::NAN);
        if (frame_rate_hz - c.fps).abs() > 0.01 * c.fps {
            tracing::warn!(device = %name, asked = c.fps, got = frame_rate_hz, "the camera chose another frame rate");
        }
        let has_exposure = cam.is_exposure_time_available().unwrap_or(false);
        match (c.exposure_us, has_exposure) {
            (Some(us), true) => {
                if cam.is_exposure_auto_available().unwrap_or(false) {
                    cam.set_exposure_time_auto(Auto::Off).map_err(|e| setting("exposure auto off", e))?;
                }
                cam.set_exposure_time(us as f64).map_err(|e| setting(&format!("exposure {us} us"), e))?;
            }
            (Some(us), false) => return Err(err(format!("board asks exposure_us = {us} but the camera has no exposure feature"))),
            (None, _) => {
                if cam.is_exposure_auto_available().unwrap_or(false) {
                    if let Err(e) = cam.set_exposure_time_auto(Auto::Continuous) {
                        tracing::debug!(device = %name, "auto exposure not set: {e}");
                    }
                }
            }
        }
        let exposure_us = if has_exposure { cam.exposure_time().ok() } else { None };
        let model = format!("{} {}", cam.vendor_name().map(|s| s.to_string()).unwrap_or_default(), cam.model_name().map(|s| s.to_string()).unwrap_or_default());
        let pixel_format = cam.pixel_format_as_string().map(|s| s.to_string()).unwrap_or_default();
        let payload = cam.payload().map_err(|e| err(format!("reading the payload size: {e}")))? as usize;
        let stream = cam.create_stream().map_err(|e| err(format!("creating the stream: {e}")))?;
        for _ in 0..c.driver_buffers {
            stream.push_buffer(Buffer::new_allocate(payload));
        }
        cam.start_acquisition().map_err(|e| err(format!("starting acquisition: {e}")))?;
        let settings = AravisSettings { model: model.trim().to_string(), width: w as usize, height: h as usize, pixel_format, frame_rate_hz, exposure_us };
        tracing::info!(device = %name, ?settings, payload, "Aravis camera open");
        let stride = c.width as usize * format.bytes_per_pixel().unwrap_or(1);
        let decoder = FrameDecoder::new(format, c.width as usize, c.height as usize, stride);
        Ok(AravisSource {
            stream,
            cam,
            name,
            settings,
            camera,
            decoder,
            expected_format,
            timeout: frame_timeout(c.fps),
            seq: 0,
            last_t_ns: Timestamp::ZERO,
            mask,
        })
    }

    /// What the camera reported after configuration.
    pub fn settings(&self) -> &AravisSettings {
        &self.settings
    }

    /// Why `buffer` cannot be used as a frame, if it cannot.
    fn check(&self, buffer: &Buffer) -> Option<String> {
        let status = buffer.status();
        if status != BufferStatus::Success {
            return Some(format!("incomplete buffer ({status:?})"));
        }
        let (w, h) = (buffer.image_width() as usize, buffer.image_height() as usize);
        if (w, h) != (self.decoder.width, self.decoder.height) {
            return Some(format!("buffer is {w}x{h}, expected {}x{}", self.decoder.width, self.decoder.height));
        }
        let f = buffer.image_pixel_format();
        if f != self.expected_format {
            return Some(format!("buffer pixel format {f:?}, expected {:?}", self.expected_format));
        }
        None
    }
}

impl FrameSource for AravisSource {
    fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        let mut frame = Frame { t_ns: Timestamp::ZERO, seq: 0, image: self.decoder.blank_image() };
        Ok(self.next_frame_into(&mut frame)?.then_some(frame))
    }

    fn next_frame_into(&mut self, frame: &mut Frame) -> Result<bool, CameraError> {
        loop {
            let Some(buffer) = self.stream.timeout_pop_buffer(self.timeout.as_micros() as u64) else {
                return Err(CameraError::Device {
                    device: self.name.clone(),
                    problem: format!("no frame within {:?}: unplugged or stopped delivering", self.timeout),
                });
            };
            let seq = self.seq;
            let mut problem = self.check(&buffer);
            if problem.is_none() {
                let (ptr, len) = buffer.data();
                if ptr.is_null() {
                    problem = Some("buffer without data".into());
                } else {
                    // SAFETY: Aravis owns `len` bytes at `ptr` for as long as `buffer` lives,
                    // and the stream thread does not touch a buffer that has been popped.
                    let data = unsafe { std::slice::from_raw_parts(ptr as *const u8, len) };
                    problem = self.decoder.decode_into(data, &mut frame.image).err().map(|e| e.to_string());
                }
            }
            let t_ns = match buffer.timestamp() {
                0 => buffer.system_timestamp(),
                t => t,
            };
            self.stream.push_buffer(buffer);
            if let Some(problem) = problem {
                self.decoder.dropped(&self.name, seq, problem)?;
                continue;
            }
            let t_ns = match Timestamp::from_ns(t_ns.min(i64::MAX as u64) as i64) {
                t if t > self.last_t_ns => t,
                _ => Timestamp::from_ns(self.last_t_ns.t_ns() + 1),
            };
            self.last_t_ns = t_ns;
            self.seq += 1;
            self.decoder.delivered();
            tracing::trace!(seq, t_ns = t_ns.t_ns(), "aravis frame");
            (frame.t_ns, frame.seq) = (t_ns, seq);
            return Ok(true);
        }
    }

    fn describe(&self) -> String {
        let s = &self.settings;
        format!("Aravis {} ({}), {} {}x{} at {:.1} fps", self.name, s.model, s.pixel_format, s.width, s.height, s.frame_rate_hz)
    }

    fn ignore_mask(&self) -> Option<&[u8]> {
        self.mask.as_deref()
    }

    fn stats(&self) -> SourceStats {
        self.decoder.stats
    }
}

impl Drop for AravisSource {
    fn drop(&mut self) {
        if let Err(e) = self.cam.stop_acquisition() {
            tracing::debug!(device = %self.name, "stopping acquisition: {e}");
        }
    }
}
