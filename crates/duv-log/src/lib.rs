//! The MCAP black box: everything the vehicle saw and decided, in files that open in Foxglove
//! and survive a power cut.
//!
//! - [`schema`]: topics and their Foxglove schemas (`foxglove.RawImage`, or
//!   `foxglove.CompressedImage` for input frames when the board asks for JPEG,
//!   `foxglove.CameraCalibration`, `foxglove.PoseInFrame`, `foxglove.FrameTransform`,
//!   `foxglove.PointCloud`) and the JSON schemas of our own records (`duv.TrackingState`,
//!   `duv.Health`); [`LogItem`] is what the other stages hand to the log.
//! - [`jpeg`]: baseline JPEG encoding of input frames for boards that log JPEG, allocation-free.
//! - [`chunked`]: our MCAP writer (chunked, indexed, allocation-free once warm);
//!   [`writer`]: segment files, a chunk closed and fsynced at least every
//!   [`LogConfig::chunk_interval`], rotation by size and age, disk errors that stop logging
//!   cleanly instead of failing the run.
//! - [`reader`]: a streaming reader with a record-size limit that salvages a damaged file
//!   (damaged ranges skipped, every chunk whose CRC holds read); [`recover`] re-writes an
//!   unfinished segment's intact chunks into a valid file;
//!   [`inspect`] summarises a log folder (`duv inspect`); [`keyframes`] reads the logged
//!   keyframes back (`duv refine --mcap`); [`window`] is the tracker's sliding window as
//!   logged for a resume (`/slam/window`).
//! - With `[log] format = "ros2"` ([`LogFormat::Ros2`]) the same topics are written as a ROS 2
//!   bag: [`ros2`] holds the message definitions and their encoding, [`cdr`] the CDR writer and
//!   reader and the decoding of what our readers take back, [`bag`] the rosbag2
//!   `metadata.yaml`. [`encoder`] encodes log items in either format; [`records`] holds the
//!   plain records both carry; [`files`] whether a segment is finished and the folder fsync.
//! - [`rosbag_source`]: a ROS 2 bag (MCAP, CDR) as a frame source with its camera and navigation
//!   topics (`--source rosbag:`).
//!
//! The log never imports another stage: what it writes arrives as plain `core` types.

pub mod chunked;
pub mod inspect;
pub mod bag;
pub mod cdr;
pub mod encoder;
pub mod files;
/// Baseline JPEG encoding, allocation-free (in `duv-core`, shared with the live view).
pub use duv_core::jpeg;
pub mod keyframes;
pub mod reader;
pub mod records;
pub mod recover;
pub mod replay;
pub mod ros2;
pub mod rosbag_source;
pub mod schema;
pub mod window;
pub mod writer;

pub use inspect::{inspect_log, LogSummary};
pub use keyframes::{for_each_log_keyframe, log_files, read_log_keyframes, read_log_nav, LogKeyframes, LoggedMap};
pub use reader::{read_segment, OwnedEvent, ReadLimits, ReadOutcome, SegmentMessage, SegmentReader};
pub use recover::{recover_folder, RecoveryReport};
pub use schema::{DecodeError, FrameEncoding, LogFormat, LogItem, PoseRecord, Topic};
pub use window::{TrackerWindow, WindowError, WindowKeyframe};
pub use chunked::ChunkCompression;
pub use writer::{LogConfig, LogStats, SegmentWriter};

use std::path::PathBuf;

/// File name prefix and extension of log segments: `segment-NNNNNN.mcap`.
pub const SEGMENT_PREFIX: &str = "segment-";
pub const SEGMENT_EXT: &str = "mcap";

/// Errors of the `log` module.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: MCAP: {source}")]
    Mcap { path: PathBuf, source: mcap::McapError },
    /// Writing failed (disk full, device gone): logging stopped, nothing before it was lost.
    #[error("{path}: write failed after {bytes_written} bytes, logging stopped: {problem}")]
    WriteFailed { path: PathBuf, bytes_written: u64, problem: String },
    /// A record claims more bytes than the reader allows (damage or a hostile file).
    #[error("{path}: record at byte {offset} is larger than the limit of {limit} bytes")]
    RecordTooLarge { path: PathBuf, offset: u64, limit: usize },
    #[error("{path}: not a duv log: {problem}")]
    NotALog { path: PathBuf, problem: String },
    #[error("{what}: cannot encode: {problem}")]
    Encode { what: &'static str, problem: String },
    /// The tracker window could not be encoded (its keyframes' depth grids differ): the item
    /// is skipped, logging goes on.
    #[error("tracker window: cannot encode: {0}")]
    EncodeWindow(#[from] window::WindowError),
    /// A log without one complete keyframe (`duv refine --mcap`).
    #[error("{path}: no keyframes in the log ({segments} segment(s) read; a keyframe is a /keyframe/image, /keyframe/inv_depth, /keyframe/variance and /keyframe/pose message of one index){why}")]
    NoKeyframes { path: PathBuf, segments: usize, why: String },
    #[error("{path}: message {topic} at {log_time_ns} ns: cannot decode: {source}")]
    Decode { path: PathBuf, topic: String, log_time_ns: u64, source: schema::DecodeError },
}

/// Segment file name for `index`.
pub fn segment_name(index: u32) -> String {
    format!("{SEGMENT_PREFIX}{index:06}.{SEGMENT_EXT}")
}

/// The segment index of a file name, `None` for other files.
pub fn segment_index(name: &str) -> Option<u32> {
    name.strip_prefix(SEGMENT_PREFIX)?.strip_suffix(".mcap")?.parse().ok()
}

/// The segments in `dir`, sorted by index.
pub fn list_segments(dir: &std::path::Path) -> Result<Vec<(u32, PathBuf)>, LogError> {
    let rd = match std::fs::read_dir(dir) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(source) => return Err(LogError::Io { path: dir.to_path_buf(), source }),
    };
    let mut v = Vec::new();
    for e in rd.flatten() {
        let name = e.file_name();
        if let Some(i) = name.to_str().and_then(segment_index) {
            v.push((i, e.path()));
        }
    }
    v.sort();
    Ok(v)
}
