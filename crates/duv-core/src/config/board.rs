//! Board profiles: what a compute module can give duv-slam. Every capacity the runtime
//! allocates comes from here; nothing grows past it at run time.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The board file schema this build reads.
pub const BOARD_SCHEMA_VERSION: u32 = 1;

/// Errors of the `config` module.
#[derive(Debug, thiserror::Error)]
pub enum BoardError {
    #[error("{path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Syntax { path: PathBuf, message: String },
    #[error("{path}: schema_version {found} is not supported (this build reads {expected})")]
    SchemaVersion { path: PathBuf, found: u32, expected: u32 },
    #[error("{path}: {key} = {value} is invalid: {why}")]
    Invalid { path: PathBuf, key: &'static str, value: String, why: &'static str },
}

/// One compute module's profile.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Board {
    /// Version of this file's layout; must equal [`BOARD_SCHEMA_VERSION`].
    pub schema_version: u32,
    /// Short name used in logs and reports.
    pub name: String,
    /// One line on the hardware this profile is for.
    pub description: String,
    pub camera: CameraConfig,
    pub budgets: Budgets,
    pub threads: Threads,
    /// The black-box log; absent: raw frames.
    #[serde(default)]
    pub log: LogSettings,
    /// The live view over the tether (`duv run --live-view`); absent: the defaults.
    #[serde(default)]
    pub live: LiveSettings,
    /// The vehicle's navigation sensors as its autopilot reports them (MAVLink); absent: a
    /// camera looking straight ahead along the vehicle's axis.
    #[serde(default)]
    pub nav: NavSettings,
}

/// The `[nav]` section: how the camera sits in the vehicle, for sensors the autopilot reports
/// in the vehicle's body frame (MAVLink attitude and DVL velocity: x forward, y right, z down).
/// A `nav.csv` is already in the camera frame and does not use it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavSettings {
    /// The camera's mounting as roll, pitch, yaw in degrees (body frame, applied in that
    /// order about fixed axes), from a camera looking straight ahead (its x right = body y,
    /// y down = body z, optical axis = body x): e.g. `[0, -40, 0]`, the camera pitched 40
    /// degrees down.
    #[serde(default)]
    pub camera_rpy_deg: [f64; 3],
    /// Navigation samples kept for a live dive (the receiver's buffer, allocated at start;
    /// later samples are counted and dropped).
    #[serde(default = "default_nav_max_samples")]
    pub max_samples: u32,
}

/// [`NavSettings::max_samples`] when the board does not say: four hours at 50 samples a second.
pub const DEFAULT_NAV_MAX_SAMPLES: u32 = 720_000;

fn default_nav_max_samples() -> u32 {
    DEFAULT_NAV_MAX_SAMPLES
}

impl Default for NavSettings {
    fn default() -> Self {
        NavSettings { camera_rpy_deg: [0.0; 3], max_samples: DEFAULT_NAV_MAX_SAMPLES }
    }
}

impl NavSettings {
    /// Camera-to-body rotation (body: x forward, y right, z down).
    pub fn body_from_cam(&self) -> nalgebra::UnitQuaternion<f64> {
        let [r, p, y] = self.camera_rpy_deg.map(f64::to_radians);
        // Columns: the camera's x, y, z axes in the body frame, looking straight ahead.
        let ahead = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::new(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0));
        nalgebra::UnitQuaternion::from_euler_angles(r, p, y) * nalgebra::UnitQuaternion::from_rotation_matrix(&ahead)
    }
}

/// The pixel layout a camera delivers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PixelFormat {
    Rgb24,
    Yuyv,
    Mjpeg,
    Grey,
    BayerRg8,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Default frame source, e.g. `sim:coastal`, `v4l2:/dev/video0`, `aravis:ID`, `tum:DIR`.
    pub source: String,
    /// Image width in pixels delivered to tracking.
    pub width: u32,
    /// Image height in pixels delivered to tracking.
    pub height: u32,
    /// Nominal frame rate in frames per second.
    pub fps: f64,
    /// Pixel format requested from the camera.
    pub pixel_format: PixelFormat,
    /// Fixed exposure time in microseconds; absent for the camera's auto exposure.
    #[serde(default)]
    pub exposure_us: Option<u32>,
    /// Buffers a live camera's driver fills ahead of capture (V4L2 mmap buffers, Aravis
    /// stream buffers), 2 to 32.
    #[serde(default = "default_driver_buffers")]
    pub driver_buffers: u32,
}

/// [`CameraConfig::driver_buffers`] when the board does not say.
pub const DEFAULT_DRIVER_BUFFERS: u32 = 4;

fn default_driver_buffers() -> u32 {
    DEFAULT_DRIVER_BUFFERS
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Budgets {
    /// Host memory the whole process may use, in MiB.
    pub host_mb: u32,
    /// GPU memory the mapper may allocate, in MiB.
    pub gpu_mb: u32,
    /// Hard cap on the number of Gaussians in the map.
    pub max_gaussians: u32,
    /// Keyframes kept in the factor graph (older ones are pruned).
    pub max_keyframes: u32,
    /// Keyframes the mapper keeps to optimise against (the newest window plus older ones);
    /// each holds the image (8-bit and f32), inverse depth and variances at full size.
    pub map_keyframes: u32,
    /// Keyframes in the sliding bundle-adjustment window.
    pub ba_window: u32,
    /// Frames buffered between capture and tracking (when full, the frame whose neighbours lie
    /// closest together in time is dropped).
    pub frame_queue: u32,
    /// Keyframes buffered between tracking and mapping.
    pub keyframe_queue: u32,
    /// Bytes buffered for the log writer, in MiB (drop and count when full).
    pub log_queue_mb: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Threads {
    /// Worker threads for tracking's data-parallel loops (flow, BA linearisation).
    pub tracking: u32,
    /// Worker threads for the CPU mapper (unused when mapping runs on the GPU): the mapping
    /// thread's own data-parallel pool, so the mapper never takes more than this many cores.
    pub mapping: u32,
    /// CPU cores (0-based ids) the tracking thread and its workers are pinned to; absent:
    /// any core. Pinning is applied where the OS allows (Linux); elsewhere, or for a core the
    /// machine does not have, a warning and the threads run unpinned.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tracking_cores: Option<Vec<u32>>,
    /// CPU cores the mapping thread and its workers are pinned to; absent: any core.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mapping_cores: Option<Vec<u32>>,
    /// Nice value (0..=19, higher yields more) of the mapping thread and its workers; tracking
    /// stays at the process's own priority, so on a busy machine mapping yields to it.
    /// Lowering a priority needs no privileges.
    #[serde(default = "default_mapping_nice")]
    pub mapping_nice: u8,
    /// Nice value (0..=19) of the logging thread.
    #[serde(default = "default_logging_nice")]
    pub logging_nice: u8,
}

/// [`Threads::mapping_nice`] when the board does not say.
pub const DEFAULT_MAPPING_NICE: u8 = 10;
/// [`Threads::logging_nice`] when the board does not say.
pub const DEFAULT_LOGGING_NICE: u8 = 0;
/// The highest nice value (the lowest priority) Linux knows.
pub const MAX_NICE: u8 = 19;
/// Core ids a board may name (glibc's `CPU_SETSIZE`).
pub const MAX_CORE_ID: u32 = 1023;

fn default_mapping_nice() -> u8 {
    DEFAULT_MAPPING_NICE
}
fn default_logging_nice() -> u8 {
    DEFAULT_LOGGING_NICE
}

/// How input frames are stored in the log.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameLogEncoding {
    /// Uncompressed (`foxglove.RawImage`): lossless, 0.9 MB per 640x480 RGB frame.
    #[default]
    Raw,
    /// JPEG (`foxglove.CompressedImage`) at [`LogSettings::jpeg_quality`].
    Jpeg,
}

/// Which message schemas the log is written in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LogFormatSetting {
    /// Foxglove protobuf schemas and JSON records: the log opens in Foxglove.
    #[default]
    Foxglove,
    /// A ROS 2 bag (rosbag2 folder: `metadata.yaml`, MCAP files with CDR messages): opens
    /// with `ros2 bag`, the `rosbags` package, and in Foxglove.
    Ros2,
}

/// How the log's MCAP chunks are compressed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LogCompression {
    /// Zstandard (level 1): the better ratio, the default.
    #[default]
    Zstd,
    /// LZ4 frames: faster, larger.
    Lz4,
    /// Uncompressed chunks.
    None,
}

/// The `[log]` section.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogSettings {
    /// `foxglove` or `ros2`: the message schemas of the log (`duv run --log-format` overrides).
    #[serde(default)]
    pub format: LogFormatSetting,
    /// `raw` or `jpeg`: how every input frame is logged (keyframe images stay raw).
    #[serde(default)]
    pub frame_encoding: FrameLogEncoding,
    /// JPEG quality, 1 to 100 (with `frame_encoding = "jpeg"`).
    #[serde(default = "default_jpeg_quality")]
    pub jpeg_quality: u8,
    /// `zstd`, `lz4` or `none`: how the MCAP chunks are compressed.
    #[serde(default)]
    pub compression: LogCompression,
    /// The log's byte budget, MB (10^6 bytes) per second of the run, on average. Frames,
    /// poses, state, keyframes, navigation and health are always logged and draw from it
    /// first; map checkpoints and point clouds are logged when what is left covers them (the
    /// final map always). Absent: no budget, every checkpoint logged.
    #[serde(default)]
    pub max_mb_per_s: Option<f64>,
}

/// [`LogSettings::jpeg_quality`] when the board does not say.
pub const DEFAULT_JPEG_QUALITY: u8 = 90;

fn default_jpeg_quality() -> u8 {
    DEFAULT_JPEG_QUALITY
}

impl Default for LogSettings {
    fn default() -> Self {
        LogSettings { format: LogFormatSetting::Foxglove, frame_encoding: FrameLogEncoding::Raw, jpeg_quality: DEFAULT_JPEG_QUALITY, compression: LogCompression::Zstd, max_mb_per_s: None }
    }
}

/// The `[live]` section: the live view's WebSocket server (`duv run --live-view`, a build with
/// the `live-view` feature) and what it may send over the tether.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LiveSettings {
    /// Address the server listens on, `HOST:PORT` (`0.0.0.0`: every interface; port 0: any
    /// free port). `--live-view ADDR` overrides it.
    pub bind: String,
    /// Bandwidth cap of everything the live view sends, KiB/s (all clients together): camera
    /// frames are dropped first, then point clouds and keyframe lists, poses and state last.
    pub max_kb_per_s: u32,
    /// The live camera's size as a fraction of the input frame's, (0, 1].
    pub image_scale: f64,
    /// ... and at most this wide, pixels (16..=4096; the height follows the aspect ratio).
    pub image_max_width: u32,
    /// Live camera frames per second of frame time, at most 60; 0: no camera.
    pub image_hz: f64,
    /// JPEG quality of the live camera, 1..=100.
    pub jpeg_quality: u8,
    /// Gaussian centres per point cloud at most (an even subsample of the map).
    pub cloud_max_points: u32,
    /// Items waiting for the live view's thread (poses, frames, keyframes, clouds); when full,
    /// new ones are dropped and counted, tracking never waits.
    pub queue: u32,
}

impl Default for LiveSettings {
    fn default() -> Self {
        LiveSettings { bind: "0.0.0.0:8765".into(), max_kb_per_s: 256, image_scale: 0.5, image_max_width: 320, image_hz: 2.0, jpeg_quality: 60, cloud_max_points: 20_000, queue: 64 }
    }
}

impl Board {
    /// Parses and validates a board file.
    pub fn load(path: &Path) -> Result<Board, BoardError> {
        let text = std::fs::read_to_string(path).map_err(|source| BoardError::Read { path: path.to_path_buf(), source })?;
        Board::parse(path, &text)
    }

    /// Parses board text; `path` is only used in messages.
    pub fn parse(path: &Path, text: &str) -> Result<Board, BoardError> {
        // Check the version first so an old file gets the right message, not a field error.
        let version = toml::from_str::<toml::Table>(text)
            .map_err(|e| BoardError::Syntax { path: path.to_path_buf(), message: e.to_string().trim_end().to_string() })?
            .get("schema_version")
            .and_then(|v| v.as_integer());
        match version {
            Some(v) if v == BOARD_SCHEMA_VERSION as i64 => {}
            Some(v) => {
                return Err(BoardError::SchemaVersion { path: path.to_path_buf(), found: v.clamp(0, u32::MAX as i64) as u32, expected: BOARD_SCHEMA_VERSION })
            }
            None => return Err(BoardError::Syntax { path: path.to_path_buf(), message: "missing integer key `schema_version`".into() }),
        }
        let board: Board = toml::from_str(text)
            .map_err(|e| BoardError::Syntax { path: path.to_path_buf(), message: e.to_string().trim_end().to_string() })?;
        board.validate(path)?;
        Ok(board)
    }

    fn validate(&self, path: &Path) -> Result<(), BoardError> {
        let invalid = |key: &'static str, value: String, why: &'static str| BoardError::Invalid { path: path.to_path_buf(), key, value, why };
        let c = &self.camera;
        if c.source.trim().is_empty() {
            return Err(invalid("camera.source", format!("{:?}", c.source), "must name a frame source"));
        }
        if c.width < 16 || c.height < 16 {
            return Err(invalid("camera.width/height", format!("{}x{}", c.width, c.height), "must be at least 16x16"));
        }
        if !(c.fps.is_finite() && c.fps > 0.0 && c.fps <= 1000.0) {
            return Err(invalid("camera.fps", c.fps.to_string(), "must be in (0, 1000]"));
        }
        if c.exposure_us == Some(0) {
            return Err(invalid("camera.exposure_us", "0".into(), "must be > 0 (omit it for auto exposure)"));
        }
        if !(2..=32).contains(&c.driver_buffers) {
            return Err(invalid("camera.driver_buffers", c.driver_buffers.to_string(), "must be in 2..=32"));
        }
        let b = &self.budgets;
        let positive: [(&'static str, u32); 9] = [
            ("budgets.host_mb", b.host_mb),
            ("budgets.gpu_mb", b.gpu_mb),
            ("budgets.max_gaussians", b.max_gaussians),
            ("budgets.max_keyframes", b.max_keyframes),
            ("budgets.map_keyframes", b.map_keyframes),
            ("budgets.ba_window", b.ba_window),
            ("budgets.frame_queue", b.frame_queue),
            ("budgets.keyframe_queue", b.keyframe_queue),
            ("budgets.log_queue_mb", b.log_queue_mb),
        ];
        for (key, v) in positive {
            if v == 0 {
                return Err(invalid(key, "0".into(), "a budget must be > 0"));
            }
        }
        if b.ba_window < 2 {
            return Err(invalid("budgets.ba_window", b.ba_window.to_string(), "bundle adjustment needs at least 2 keyframes"));
        }
        if b.ba_window > b.max_keyframes {
            return Err(invalid("budgets.ba_window", b.ba_window.to_string(), "must not exceed budgets.max_keyframes"));
        }
        for (key, v) in [("threads.tracking", self.threads.tracking), ("threads.mapping", self.threads.mapping)] {
            if v == 0 {
                return Err(invalid(key, "0".into(), "at least one thread"));
            }
        }
        for (key, v) in [("threads.mapping_nice", self.threads.mapping_nice), ("threads.logging_nice", self.threads.logging_nice)] {
            if v > MAX_NICE {
                return Err(invalid(key, v.to_string(), "a nice value must be in 0..=19 (higher yields more)"));
            }
        }
        for (key, cores) in [("threads.tracking_cores", &self.threads.tracking_cores), ("threads.mapping_cores", &self.threads.mapping_cores)] {
            let Some(cores) = cores else { continue };
            if cores.is_empty() {
                return Err(invalid(key, "[]".into(), "name at least one core, or leave the key out for any core"));
            }
            if let Some(c) = cores.iter().find(|c| **c > MAX_CORE_ID) {
                return Err(invalid(key, c.to_string(), "a core id must be at most 1023"));
            }
            if cores.iter().enumerate().any(|(i, c)| cores[..i].contains(c)) {
                return Err(invalid(key, format!("{cores:?}"), "a core is named twice"));
            }
        }
        if let Some(v) = self.nav.camera_rpy_deg.iter().find(|v| !(v.is_finite() && v.abs() <= 360.0)) {
            return Err(invalid("nav.camera_rpy_deg", v.to_string(), "must be finite degrees within [-360, 360]"));
        }
        if self.nav.max_samples == 0 {
            return Err(invalid("nav.max_samples", "0".into(), "must be at least 1"));
        }
        if !(1..=100).contains(&self.log.jpeg_quality) {
            return Err(invalid("log.jpeg_quality", self.log.jpeg_quality.to_string(), "must be in 1..=100"));
        }
        if let Some(v) = self.log.max_mb_per_s {
            if !(v.is_finite() && v > 0.0 && v <= 10_000.0) {
                return Err(invalid("log.max_mb_per_s", v.to_string(), "must be a number of MB/s in (0, 10000]"));
            }
        }
        self.live.validate().map_err(|(key, value, why)| invalid(key, value, why))
    }

    /// Every `*.toml` directly in `dir`, sorted by name.
    pub fn files_in(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "toml"))
            .collect();
        v.sort();
        Ok(v)
    }
}

impl LiveSettings {
    /// The first invalid key, its value and why (the board's messages).
    pub fn validate(&self) -> Result<(), (&'static str, String, &'static str)> {
        let l = self;
        if l.bind.parse::<std::net::SocketAddr>().is_err() {
            return Err(("live.bind", format!("{:?}", l.bind), "must be HOST:PORT with a numeric address, e.g. \"0.0.0.0:8765\""));
        }
        if l.max_kb_per_s == 0 {
            return Err(("live.max_kb_per_s", "0".into(), "must be > 0"));
        }
        if !(l.image_scale.is_finite() && l.image_scale > 0.0 && l.image_scale <= 1.0) {
            return Err(("live.image_scale", l.image_scale.to_string(), "must be in (0, 1]"));
        }
        if !(16..=4096).contains(&l.image_max_width) {
            return Err(("live.image_max_width", l.image_max_width.to_string(), "must be in 16..=4096"));
        }
        if !(l.image_hz.is_finite() && (0.0..=60.0).contains(&l.image_hz)) {
            return Err(("live.image_hz", l.image_hz.to_string(), "must be in [0, 60] (0: no camera)"));
        }
        if !(1..=100).contains(&l.jpeg_quality) {
            return Err(("live.jpeg_quality", l.jpeg_quality.to_string(), "must be in 1..=100"));
        }
        if l.cloud_max_points == 0 {
            return Err(("live.cloud_max_points", "0".into(), "must be > 0"));
        }
        if l.queue < 4 {
            return Err(("live.queue", l.queue.to_string(), "must be at least 4"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) const MINIMAL: &str = r#"
schema_version = 1
name = "t"
description = "test"
[camera]
source = "sim:clear"
width = 320
height = 240
fps = 10.0
pixel_format = "rgb24"
[budgets]
host_mb = 512
gpu_mb = 256
max_gaussians = 1000
max_keyframes = 32
map_keyframes = 16
ba_window = 8
frame_queue = 4
keyframe_queue = 4
log_queue_mb = 16
[threads]
tracking = 2
mapping = 1
"#;

    #[test]
    fn parses_minimal_board() {
        let b = Board::parse(Path::new("t.toml"), MINIMAL).unwrap();
        assert_eq!(b.budgets.ba_window, 8);
        assert_eq!(b.camera.pixel_format, PixelFormat::Rgb24);
        assert_eq!(b.camera.driver_buffers, DEFAULT_DRIVER_BUFFERS);
    }

    #[test]
    fn thread_placement_keys_parse_and_are_validated() {
        let b = Board::parse(Path::new("t.toml"), MINIMAL).unwrap();
        assert_eq!((b.threads.tracking_cores.as_deref(), b.threads.mapping_cores.as_deref()), (None, None));
        assert_eq!((b.threads.mapping_nice, b.threads.logging_nice), (DEFAULT_MAPPING_NICE, DEFAULT_LOGGING_NICE));
        let with = |extra: &str| MINIMAL.replace("mapping = 1\n", &format!("mapping = 1\n{extra}\n"));
        let b = Board::parse(Path::new("t.toml"), &with("tracking_cores = [0]\nmapping_cores = [1, 2]\nmapping_nice = 19\nlogging_nice = 5")).unwrap();
        assert_eq!(b.threads.tracking_cores, Some(vec![0]));
        assert_eq!(b.threads.mapping_cores, Some(vec![1, 2]));
        assert_eq!((b.threads.mapping_nice, b.threads.logging_nice), (19, 5));
        // Written back and read again: the same board.
        let again = Board::parse(Path::new("t.toml"), &toml::to_string(&b).unwrap()).unwrap();
        assert_eq!(again, b);
        for (extra, key) in [
            ("mapping_nice = 20", "threads.mapping_nice"),
            ("logging_nice = 25", "threads.logging_nice"),
            ("tracking_cores = []", "threads.tracking_cores"),
            ("mapping_cores = [0, 0]", "threads.mapping_cores"),
            ("mapping_cores = [4096]", "threads.mapping_cores"),
        ] {
            let e = Board::parse(Path::new("t.toml"), &with(extra)).unwrap_err();
            assert!(e.to_string().contains(key), "{extra}: {e}");
        }
        // A negative nice (a higher priority) needs privileges: not a board value.
        assert!(Board::parse(Path::new("t.toml"), &with("mapping_nice = -5")).is_err());
    }

    #[test]
    fn driver_buffers_are_bounded() {
        let with = |n: u32| MINIMAL.replace("pixel_format = \"rgb24\"", &format!("pixel_format = \"rgb24\"\ndriver_buffers = {n}"));
        assert_eq!(Board::parse(Path::new("t.toml"), &with(8)).unwrap().camera.driver_buffers, 8);
        for n in [0, 1, 33] {
            let e = Board::parse(Path::new("t.toml"), &with(n)).unwrap_err();
            assert!(e.to_string().contains("camera.driver_buffers"), "{e}");
        }
    }

    #[test]
    fn log_section_is_optional_and_strict() {
        let b = Board::parse(Path::new("t.toml"), MINIMAL).unwrap();
        assert_eq!(b.log, LogSettings { format: LogFormatSetting::Foxglove, frame_encoding: FrameLogEncoding::Raw, jpeg_quality: 90, compression: LogCompression::Zstd, max_mb_per_s: None });
        let with = |body: &str| format!("{MINIMAL}[log]\n{body}\n");
        let b = Board::parse(Path::new("t.toml"), &with("frame_encoding = \"jpeg\"\njpeg_quality = 75")).unwrap();
        assert_eq!(b.log, LogSettings { format: LogFormatSetting::Foxglove, frame_encoding: FrameLogEncoding::Jpeg, jpeg_quality: 75, compression: LogCompression::Zstd, max_mb_per_s: None });
        let b = Board::parse(Path::new("t.toml"), &with("compression = \"lz4\"\nmax_mb_per_s = 8")).unwrap();
        assert_eq!((b.log.compression, b.log.max_mb_per_s), (LogCompression::Lz4, Some(8.0)));
        assert_eq!(Board::parse(Path::new("t.toml"), &with("compression = \"none\"")).unwrap().log.compression, LogCompression::None);
        let e = Board::parse(Path::new("t.toml"), &with("compression = \"gzip\"")).unwrap_err().to_string();
        assert!(e.contains("unknown variant `gzip`") && e.contains("zstd") && e.contains("lz4"), "{e}");
        for v in ["0", "-1", "nan", "20000"] {
            let e = Board::parse(Path::new("t.toml"), &with(&format!("max_mb_per_s = {v}"))).unwrap_err().to_string();
            assert!(e.starts_with("t.toml: log.max_mb_per_s = ") && e.contains("MB/s"), "{v}: {e}");
        }
        let b = Board::parse(Path::new("t.toml"), &with("format = \"ros2\"")).unwrap();
        assert_eq!(b.log.format, LogFormatSetting::Ros2);
        let e = Board::parse(Path::new("t.toml"), &with("format = \"rosbag\"")).unwrap_err().to_string();
        assert!(e.starts_with("t.toml:") && e.contains("unknown variant `rosbag`") && e.contains("foxglove") && e.contains("ros2"), "{e}");
        for q in [0, 101] {
            let e = Board::parse(Path::new("t.toml"), &with(&format!("frame_encoding = \"jpeg\"\njpeg_quality = {q}"))).unwrap_err();
            assert_eq!(e.to_string(), format!("t.toml: log.jpeg_quality = {q} is invalid: must be in 1..=100"));
        }
        let e = Board::parse(Path::new("t.toml"), &with("jpeg_quality = 300")).unwrap_err().to_string();
        assert!(e.starts_with("t.toml:") && e.contains("jpeg_quality"), "{e}");
        let e = Board::parse(Path::new("t.toml"), &with("frame_encoding = \"png\"")).unwrap_err().to_string();
        assert!(e.contains("unknown variant `png`") && e.contains("raw") && e.contains("jpeg"), "{e}");
        let e = Board::parse(Path::new("t.toml"), &with("frame_encodng = \"jpeg\"")).unwrap_err().to_string();
        assert!(e.contains("unknown field `frame_encodng`"), "{e}");
    }

    #[test]
    fn live_section_is_optional_and_validated_by_key() {
        let b = Board::parse(Path::new("t.toml"), MINIMAL).unwrap();
        assert_eq!(b.live, LiveSettings::default());
        let with = |body: &str| format!("{MINIMAL}[live]\n{body}\n");
        let b = Board::parse(Path::new("t.toml"), &with("bind = \"127.0.0.1:9000\"\nmax_kb_per_s = 64\nimage_hz = 0")).unwrap();
        assert_eq!((b.live.bind.as_str(), b.live.max_kb_per_s, b.live.image_hz, b.live.queue), ("127.0.0.1:9000", 64, 0.0, 64));
        for (body, want) in [
            ("bind = \"vehicle\"", "t.toml: live.bind = \"vehicle\" is invalid: must be HOST:PORT"),
            ("max_kb_per_s = 0", "t.toml: live.max_kb_per_s = 0 is invalid: must be > 0"),
            ("image_scale = 1.5", "t.toml: live.image_scale = 1.5 is invalid: must be in (0, 1]"),
            ("image_max_width = 8", "t.toml: live.image_max_width = 8 is invalid"),
            ("image_hz = -1", "t.toml: live.image_hz = -1 is invalid"),
            ("jpeg_quality = 0", "t.toml: live.jpeg_quality = 0 is invalid"),
            ("cloud_max_points = 0", "t.toml: live.cloud_max_points = 0 is invalid"),
            ("queue = 2", "t.toml: live.queue = 2 is invalid: must be at least 4"),
        ] {
            let e = Board::parse(Path::new("t.toml"), &with(body)).unwrap_err().to_string();
            assert!(e.starts_with(want), "{body}: {e}");
        }
        let e = Board::parse(Path::new("t.toml"), &with("port = 1")).unwrap_err().to_string();
        assert!(e.contains("unknown field `port`"), "{e}");
    }

    #[test]
    fn unknown_key_names_file_and_key() {
        let text = MINIMAL.replace("mapping = 1", "mapping = 1\nturbo = true");
        let e = Board::parse(Path::new("boards/x.toml"), &text).unwrap_err();
        let s = e.to_string();
        assert!(s.starts_with("boards/x.toml:") && s.contains("unknown field `turbo`") && s.contains("line"), "{s}");
    }

    #[test]
    fn zero_budget_is_rejected_by_name() {
        let text = MINIMAL.replace("max_gaussians = 1000", "max_gaussians = 0");
        let e = Board::parse(Path::new("b.toml"), &text).unwrap_err();
        assert_eq!(e.to_string(), "b.toml: budgets.max_gaussians = 0 is invalid: a budget must be > 0");
    }

    #[test]
    fn wrong_schema_version_and_window() {
        let e = Board::parse(Path::new("b.toml"), &MINIMAL.replace("schema_version = 1", "schema_version = 2")).unwrap_err();
        assert!(matches!(e, BoardError::SchemaVersion { found: 2, .. }));
        let e = Board::parse(Path::new("b.toml"), &MINIMAL.replace("ba_window = 8", "ba_window = 64")).unwrap_err();
        assert!(e.to_string().contains("budgets.ba_window"));
        let e = Board::parse(Path::new("b.toml"), &MINIMAL.replace("fps = 10.0", "fps = nan")).unwrap_err();
        assert!(e.to_string().contains("camera.fps"), "{e}");
    }

    #[test]
    fn the_camera_mounting_turns_camera_axes_into_the_body_frame() {
        use nalgebra::Vector3;
        let ahead = NavSettings::default().body_from_cam();
        assert!((ahead * Vector3::z() - Vector3::x()).norm() < 1e-12, "optical axis = body forward");
        assert!((ahead * Vector3::x() - Vector3::y()).norm() < 1e-12, "image right = body right");
        assert!((ahead * Vector3::y() - Vector3::z()).norm() < 1e-12, "image down = body down");
        let down40 = NavSettings { camera_rpy_deg: [0.0, -40.0, 0.0], ..NavSettings::default() }.body_from_cam();
        let axis = down40 * Vector3::z();
        let (c, s) = (40f64.to_radians().cos(), 40f64.to_radians().sin());
        assert!((axis - Vector3::new(c, 0.0, s)).norm() < 1e-12, "pitched 40 degrees down: {axis}");
        let b = Board::parse(Path::new("b.toml"), &format!("{MINIMAL}\n[nav]\ncamera_rpy_deg = [0.0, -40.0, 0.0]\nmax_samples = 1000\n")).unwrap();
        assert_eq!((b.nav.camera_rpy_deg, b.nav.max_samples), ([0.0, -40.0, 0.0], 1000));
        let e = Board::parse(Path::new("b.toml"), &format!("{MINIMAL}\n[nav]\ncamera_rpy_deg = [0.0, 400.0, 0.0]\n")).unwrap_err();
        assert_eq!(e.to_string(), "b.toml: nav.camera_rpy_deg = 400 is invalid: must be finite degrees within [-360, 360]");
    }
}
