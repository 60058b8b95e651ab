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
    /// The spec names a known kind but its directory or options are unusable.
    #[error("source {spec:?}: {problem}")]
    BadSpec { spec: String, problem: String },
    #[error("{path}: {problem}")]
    Dataset { path: PathBuf, problem: String },
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    #[error("{path}: calibration: {source}")]
    Calibration { path: PathBuf, source: crate::core::CameraModelError },
    /// A required calibration file is absent; `hint` says how to provide one.
    #[error("{path}: calibration file not found; {hint}")]
    MissingCalibration { path: PathBuf, hint: &'static str },
    /// A list file (`rgb.txt`, `data.csv`, ...) names a file that does not exist.
    #[error("{list}, line {line}: {missing} does not exist")]
    MissingFile { list: PathBuf, line: usize, missing: PathBuf },
    /// A folder holds none of what it must hold.
    #[error("{path}: no {what} found")]
    Empty { path: PathBuf, what: &'static str },
    #[error("{path}: not a readable .npy array: {problem}")]
    BadNpy { path: PathBuf, problem: String },
    /// A frame could not be read; `source` names the file. The stream can continue after it.
    #[error("frame {index}: {source}")]
    BadFrame { index: usize, path: PathBuf, source: Box<CameraError> },
    /// An image whose size is not the one the calibration describes.
    #[error("{path}: image is {width}x{height}, the camera model is {expected_width}x{expected_height}")]
    ImageSize { path: PathBuf, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("{root}: this dataset has no depth")]
    NoDepth { root: PathBuf },
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
