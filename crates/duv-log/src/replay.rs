//! Replay: a recorded log as a [`FrameSource`] (`--source mcap:FILE_OR_LOG_FOLDER`). Frames
//! come out in recorded order with their recorded time stamps; pacing (`--speed`) and the
//! deterministic mode are the pipeline's. Reading streams segment by segment with the log's
//! record-size limit, so a damaged log replays with its damaged ranges skipped.

use duv_core::source::{CameraError, FrameSource};
use duv_core::{Frame, PinholeCamera};
use crate::reader::OwnedEvent;
use crate::schema::{decode_calibration, decode_frame};
use crate::{list_segments, ReadLimits, SegmentReader, Topic};
use std::path::{Path, PathBuf};

/// Errors of replay.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error("{path}: no log segments (segment-NNNNNN.mcap) or .mcap file here")]
    NoLog { path: PathBuf },
    #[error("{path}: no /camera/calibration message before the first frame")]
    NoCalibration { path: PathBuf },
    #[error(transparent)]
    Log(#[from] crate::LogError),
}

impl From<ReplayError> for CameraError {
    fn from(e: ReplayError) -> Self {
        CameraError::BadSpec { spec: "mcap:".into(), problem: e.to_string() }
    }
}

/// Frames of a recorded log.
pub struct McapSource {
    path: PathBuf,
    files: Vec<PathBuf>,
    next_file: usize,
    reader: Option<SegmentReader>,
    camera: PinholeCamera,
    limits: ReadLimits,
    /// Frames already delivered (segments of a resumed run may repeat none, but a frame seq
    /// seen twice is skipped).
    last_seq: Option<u64>,
    frames: u64,
    /// Damage met while reading, per segment.
    pub damage: Vec<String>,
    max_frames: Option<u64>,
}

impl McapSource {
    /// Opens a log folder (every segment in order) or one `.mcap` file.
    pub fn open(path: &Path, limits: ReadLimits) -> Result<Self, ReplayError> {
        let files: Vec<PathBuf> = if path.is_dir() {
            let d = list_segments(path)?;
            let d = if d.is_empty() { list_segments(&path.join("log"))? } else { d };
            d.into_iter().map(|(_, p)| p).collect()
        } else if path.is_file() {
            vec![path.to_path_buf()]
        } else {
            Vec::new()
        };
        if files.is_empty() {
            return Err(ReplayError::NoLog { path: path.to_path_buf() });
        }
        // The calibration: the first one in the first segment that has it.
        let mut camera = None;
        'outer: for f in &files {
            let mut r = SegmentReader::open(f, limits)?;
            while let Some(e) = r.next_event() {
                if let OwnedEvent::Message { channel_id, data, .. } = e {
                    match r.channel(channel_id).and_then(|c| Topic::from_name(&c.topic)) {
                        Some(Topic::CameraCalibration) => {
                            camera = decode_calibration(&data).ok();
                            if camera.is_some() {
                                break 'outer;
                            }
                        }
                        Some(Topic::CameraImage) => break,
                        _ => {}
                    }
                }
            }
        }
        let camera = camera.ok_or_else(|| ReplayError::NoCalibration { path: path.to_path_buf() })?;
        Ok(McapSource { path: path.to_path_buf(), files, next_file: 0, reader: None, camera, limits, last_seq: None, frames: 0, damage: Vec::new(), max_frames: None })
    }

    /// Stop after `n` frames.
    pub fn with_max_frames(mut self, n: Option<usize>) -> Self {
        self.max_frames = n.map(|n| n as u64);
        self
    }

    pub fn segments(&self) -> usize {
        self.files.len()
    }
}

impl FrameSource for McapSource {
    fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        if self.max_frames.is_some_and(|m| self.frames >= m) {
            return Ok(None);
        }
        loop {
            if self.reader.is_none() {
                let Some(f) = self.files.get(self.next_file) else { return Ok(None) };
                self.next_file += 1;
                self.reader = Some(SegmentReader::open(f, self.limits).map_err(ReplayError::from)?);
            }
            let r = self.reader.as_mut().expect("opened above");
            let Some(e) = r.next_event() else {
                if let Some(d) = &r.outcome().damage {
                    tracing::warn!("replay: {}: {d}", r.outcome().path.display());
                    self.damage.push(format!("{}: {d}", r.outcome().path.display()));
                }
                self.reader = None;
                continue;
            };
            let OwnedEvent::Message { channel_id, sequence, log_time_ns, data, .. } = e else { continue };
            if r.channel(channel_id).and_then(|c| Topic::from_name(&c.topic)) != Some(Topic::CameraImage) {
                continue;
            }
            let seq = sequence as u64;
            if self.last_seq.is_some_and(|l| seq <= l) {
                continue;
            }
            match decode_frame(&data, seq, log_time_ns) {
                Ok(frame) => {
                    if frame.image.width() != self.camera.width || frame.image.height() != self.camera.height {
                        tracing::warn!("replay: frame {seq} is {}x{}, the calibration {}x{}: dropped", frame.image.width(), frame.image.height(), self.camera.width, self.camera.height);
                        continue;
                    }
                    self.last_seq = Some(seq);
                    self.frames += 1;
                    return Ok(Some(frame));
                }
                Err(problem) => tracing::warn!("replay: frame {seq} dropped: {problem}"),
            }
        }
    }

    fn describe(&self) -> String {
        format!("MCAP replay of {} ({} segment(s), {}x{})", self.path.display(), self.files.len(), self.camera.width, self.camera.height)
    }
}
