//! Frame sources. Everything that delivers images (dataset folders today; V4L2, Aravis and
//! MCAP replay later) implements [`FrameSource`], so the pipeline never knows which it has.

pub mod dataset;

use crate::core::{Frame, PinholeCamera};
use std::path::PathBuf;

/// Errors of the `camera` module.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("unknown source {spec:?}: expected KIND:ARG with KIND one of {kinds}")]
    UnknownSource { spec: String, kinds: &'static str },
    #[error("{path}: {problem}")]
    Dataset { path: PathBuf, problem: String },
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    #[error("{path}: calibration: {source}")]
    Calibration { path: PathBuf, source: crate::core::CameraModelError },
}

/// A source of time-stamped frames with a known camera model.
pub trait FrameSource: Send {
    /// Intrinsics of the images this source delivers.
    fn camera(&self) -> &PinholeCamera;
    /// The next frame, `Ok(None)` at end of stream. A frame that cannot be decoded is an
    /// error naming it; the caller may skip it and continue.
    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError>;
    /// One line for logs: what this source is.
    fn describe(&self) -> String;
}
