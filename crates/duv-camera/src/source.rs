//! `--source` specs: one parser for every kind of frame source.

use super::dataset::{open_dataset, DATASET_KINDS};
use super::sim::SimSource;
use super::{CameraError, FrameSource};
use duv_core::config::board::Board;

/// The kinds a `--source` spec may name, for help and error messages.
pub const SOURCE_KINDS: &str = "v4l2, aravis, tum, euroc, tartanair, folder, sim, mcap, rosbag";

/// Opens a frame source from a spec `KIND:ARG[,OPTION=VALUE]...`:
///
/// - `v4l2:/dev/video0[,calib=FILE]`: a V4L2 device (feature `v4l2`);
/// - `aravis:ID[,calib=FILE]`: a GenICam camera by Aravis id, e.g. `Fake_1` (the in-process
///   fake camera) or `127.0.0.1` (feature `aravis`);
/// - `tum:DIR`, `euroc:DIR`, `tartanair:DIR`, `folder:DIR` with the dataset options of
///   [`super::dataset::open_dataset`];
/// - `sim:WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=realtime|none][,nav=on][,lamps=on]`
///   `[,backscatter=S][,snow=N][,seabed=C][,burst=START:DURATION[:FACTOR]][,night=on]`: the generator at
///   the board's resolution and frame rate (see [`super::sim::SimSpec`]);
/// - `mcap:FILE` is the replay module's: this returns [`CameraError::HandledByReplay`].
///
/// Live cameras take resolution, frame rate, pixel format, exposure and driver buffer count
/// from `board.camera`.
pub fn open_source(spec: &str, board: &Board) -> Result<Box<dyn FrameSource>, CameraError> {
    let (kind, rest) = spec.split_once(':').ok_or_else(|| CameraError::UnknownSource { spec: spec.to_string(), kinds: SOURCE_KINDS })?;
    match kind.trim() {
        "v4l2" => open_v4l2(spec, rest, board),
        "aravis" => open_aravis(spec, rest, board),
        "sim" => Ok(Box::new(SimSource::open(spec, rest, board)?)),
        "mcap" => Err(CameraError::HandledByReplay { spec: spec.to_string() }),
        k if DATASET_KINDS.split(", ").any(|d| d == k) => Ok(Box::new(open_dataset(spec)?.into_source())),
        _ => Err(CameraError::UnknownSource { spec: spec.to_string(), kinds: SOURCE_KINDS }),
    }
}

#[cfg(feature = "v4l2")]
fn open_v4l2(spec: &str, rest: &str, board: &Board) -> Result<Box<dyn FrameSource>, CameraError> {
    let live = super::live::LiveSpec::parse("v4l2", spec, rest)?;
    Ok(Box::new(super::v4l2::V4l2Source::open(&live, board)?))
}

#[cfg(not(feature = "v4l2"))]
fn open_v4l2(spec: &str, _rest: &str, _board: &Board) -> Result<Box<dyn FrameSource>, CameraError> {
    Err(CameraError::FeatureDisabled { spec: spec.to_string(), kind: "V4L2", feature: "v4l2" })
}

#[cfg(feature = "aravis")]
fn open_aravis(spec: &str, rest: &str, board: &Board) -> Result<Box<dyn FrameSource>, CameraError> {
    let live = super::live::LiveSpec::parse("aravis", spec, rest)?;
    Ok(Box::new(super::aravis::AravisSource::open(&live, board)?))
}

#[cfg(not(feature = "aravis"))]
fn open_aravis(spec: &str, _rest: &str, _board: &Board) -> Result<Box<dyn FrameSource>, CameraError> {
    Err(CameraError::FeatureDisabled { spec: spec.to_string(), kind: "Aravis (GenICam)", feature: "aravis" })
}
