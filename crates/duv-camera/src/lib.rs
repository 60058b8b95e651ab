//! Frame sources. Everything that delivers images (dataset folders, the generator, V4L2 and
//! Aravis cameras; MCAP replay lives in `replay/`) implements [`FrameSource`], so the pipeline
//! never knows which it has. [`open_source`] turns a `--source` spec into one.

#[cfg(feature = "aravis")]
pub mod aravis;
pub mod dataset;
pub mod live;
pub mod mavlink_nav;
pub mod pixel;
pub mod sim;
mod source;
#[cfg(feature = "v4l2")]
pub mod v4l2;

pub use source::{open_source, SOURCE_KINDS};

pub use duv_core::source::{CameraError, FrameSource, SourceStats};

