//! What every frame source delivers: the [`FrameSource`] trait, its error and its counters.
//! The trait lives here, below the stages, so that the camera stage (datasets, the generator,
//! live cameras) and the log stage (replay of a recorded log) implement it without depending
//! on one another; only the pipeline holds a `Box<dyn FrameSource>`.

use crate::{Frame, PinholeCamera, StampedPose};
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
    /// A navigation file (`nav.csv`) that cannot be read; the error names it.
    #[error(transparent)]
    Nav(#[from] crate::nav::NavError),
    #[error("{path}: calibration: {source}")]
    Calibration { path: PathBuf, source: crate::CameraModelError },
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
    /// The spec names a source kind this binary was built without.
    #[error("source {spec:?}: this build has no {kind} support; rebuild with `--features {feature}`")]
    FeatureDisabled { spec: String, kind: &'static str, feature: &'static str },
    /// `mcap:FILE` is read by the replay module, not by the camera module.
    #[error("source {spec:?}: MCAP logs are read by the replay module (`duv replay`), not by camera::open_source")]
    HandledByReplay { spec: String },
    /// A live camera could not be opened, configured or read: missing, unplugged, busy, or
    /// refusing a setting the board asks for. `device` names it (`/dev/video0`, `aravis:Fake_1`).
    #[error("camera {device}: {problem}")]
    Device { device: String, problem: String },
    /// A live camera delivered frames but every one of the last `count` was corrupt.
    #[error("camera {device}: the last {count} frames were all corrupt (last: {last})")]
    CorruptStream { device: String, count: u32, last: String },
}

impl CameraError {
    /// True when the source cannot deliver more frames after this error (a camera gone or
    /// misconfigured); false when only one frame was bad and the next call may succeed.
    pub fn ends_stream(&self) -> bool {
        !matches!(self, CameraError::BadFrame { .. } | CameraError::ImageSize { .. } | CameraError::Io(_))
    }
}

/// Counters a source keeps about what it delivered and what it dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SourceStats {
    /// Frames returned by `next_frame`.
    pub delivered: u64,
    /// Frames the source received but dropped because they were corrupt (wrong size,
    /// truncated JPEG, incomplete transfer, driver error flag).
    pub dropped_corrupt: u64,
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
    /// Like [`FrameSource::next_frame`], into `frame`, reusing its image buffer where the
    /// source can: the live cameras then decode without allocating (on the Rust side) once
    /// `frame` has the right size. Returns `false` at end of stream; after an error or `false`
    /// the contents of `frame` are unspecified.
    fn next_frame_into(&mut self, frame: &mut Frame) -> Result<bool, CameraError> {
        match self.next_frame()? {
            Some(f) => {
                *frame = f;
                Ok(true)
            }
            None => Ok(false),
        }
    }
    /// Delivered and dropped-frame counters (all zero for sources that never drop).
    fn stats(&self) -> SourceStats {
        SourceStats::default()
    }
    /// `world_from_cam` ground truth of the frames, where the source knows it (the generator).
    fn ground_truth(&self) -> Option<&[StampedPose]> {
        None
    }
    /// Pixels to ignore in every frame, 1 each at the frames' size (a live camera's
    /// `mask=FILE`: the vehicle's own frame in view, a burned-in overlay).
    fn ignore_mask(&self) -> Option<&[u8]> {
        None
    }
}
