//! Resume after power loss: recover the log's unfinished segments, find where the recorded
//! trajectory stopped, reload the newest good map checkpoint, and relocalise a fresh tracker
//! in the recorded map frame from the last frames the log holds.
//!
//! Relocalisation: the last logged frames (with the poses recorded for them) are tracked again
//! by the new tracker; the Sim(3) that carries its positions onto the recorded ones (Umeyama)
//! becomes [`PipelineConfig::world_from_tracker`](super::PipelineConfig), so every pose after
//! the restart continues the same trajectory in the same frame and scale.

use super::{CheckpointStore, PipelineError};
use crate::core::{Frame, PinholeCamera, Se3, Sim3, Timestamp};
use crate::log::reader::OwnedEvent;
use crate::log::schema::{decode_calibration, decode_frame, decode_pose, StateMessage};
use crate::log::{list_segments, recover_folder, ReadLimits, RecoveryReport, SegmentReader, Topic};
use crate::track::Tracker;
use nalgebra::Vector3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// What a previous run left behind.
pub struct ResumeState {
    pub log_dir: PathBuf,
    pub recovered: Vec<RecoveryReport>,
    /// Last frame with a recorded pose.
    pub last_seq: u64,
    pub last_t_ns: Timestamp,
    /// Poses recorded in all segments.
    pub poses_recorded: u64,
    /// The last logged frames that have a recorded pose, oldest first: (frame, pose, not lost).
    pub recent: Vec<(Frame, Se3, bool)>,
    pub camera: Option<PinholeCamera>,
    /// Newest checkpoint that verified.
    pub checkpoint: Option<(PathBuf, Vec<u8>)>,
}

/// Looks at `out_dir`; `None` when it holds no log (a fresh start). Unfinished segments are
/// recovered in place. `keep_frames`: how many of the last frames to keep for relocalisation.
pub fn prepare(out_dir: &Path, limits: ReadLimits, keep_frames: usize) -> Result<Option<ResumeState>, PipelineError> {
    let log_dir = out_dir.join("log");
    if list_segments(&log_dir)?.is_empty() {
        return Ok(None);
    }
    let recovered = recover_folder(&log_dir, limits)?;
    // By seq: a frame logged by a run killed before tracking it is logged again by the next.
    let mut frames: BTreeMap<u64, (Vec<u8>, u64)> = BTreeMap::new();
    let mut poses: BTreeMap<u64, (Se3, bool)> = BTreeMap::new();
    let mut camera = None;
    let mut poses_recorded = 0u64;
    let mut last: Option<(u64, Timestamp)> = None;
    for (_, path) in list_segments(&log_dir)? {
        let mut r = SegmentReader::open(&path, limits)?;
        while let Some(e) = r.next_event() {
            let OwnedEvent::Message { channel_id, sequence, log_time_ns, data, .. } = e else { continue };
            let Some(topic) = r.channel(channel_id).and_then(|c| Topic::from_name(&c.topic)) else { continue };
            let seq = sequence as u64;
            match topic {
                Topic::CameraImage => {
                    frames.insert(seq, (data, log_time_ns));
                    while frames.len() > keep_frames * 4 {
                        frames.pop_first();
                    }
                }
                Topic::CameraCalibration => camera = decode_calibration(&data).ok(),
                Topic::Pose => {
                    if let Ok(p) = decode_pose(&data) {
                        poses_recorded += 1;
                        let tracked = poses.get(&seq).map(|x| x.1).unwrap_or(true);
                        poses.insert(seq, (p, tracked));
                        if last.is_none_or(|(s, _)| seq >= s) {
                            last = Some((seq, Timestamp::from_ns(log_time_ns as i64)));
                        }
                        while poses.len() > keep_frames * 8 {
                            poses.pop_first();
                        }
                    }
                }
                Topic::State => {
                    if let Ok(s) = serde_json::from_slice::<StateMessage>(&data) {
                        if let Some(p) = poses.get_mut(&s.seq) {
                            // Lost frames hold a prediction, not a measurement.
                            p.1 = !s.state.starts_with("lost");
                        }
                    }
                }
                _ => {}
            }
        }
    }
    let Some((last_seq, last_t_ns)) = last else {
        return Ok(Some(ResumeState { log_dir, recovered, last_seq: 0, last_t_ns: Timestamp::from_ns(0), poses_recorded: 0, recent: Vec::new(), camera, checkpoint: None }));
    };
    let mut recent = Vec::new();
    for (seq, (data, t)) in frames {
        let Some(&(pose, tracked)) = poses.get(&seq) else { continue };
        match decode_frame(&data, seq, t) {
            Ok(f) => recent.push((f, pose, tracked)),
            Err(e) => tracing::warn!("resume: logged frame {seq} unreadable: {e}"),
        }
    }
    if recent.len() > keep_frames {
        recent.drain(..recent.len() - keep_frames);
    }
    let checkpoint = CheckpointStore::new(out_dir.join("checkpoints"), 3).load_newest();
    Ok(Some(ResumeState { log_dir, recovered, last_seq, last_t_ns, poses_recorded, recent, camera, checkpoint }))
}

/// Tracks the recorded frames of `state` with `tracker` and returns the Sim(3) from the
/// tracker's frame to the recorded one, `None` when too few frames were tracked in both runs
/// (the run then continues in a new frame, which the caller reports).
pub fn relocalise(tracker: &mut Tracker, state: &ResumeState) -> Result<Option<Sim3>, PipelineError> {
    // Per warm-up frame: the recorded pose, whether it was measured, and the new tracker's
    // live pose and state.
    let mut live: Vec<(u64, Se3, bool, Se3, bool)> = Vec::new();
    tracker.run_in_pool(|tracker| -> Result<(), PipelineError> {
        for (frame, recorded, recorded_measured) in &state.recent {
            let out = tracker.track(frame)?;
            let usable = !matches!(out.state, crate::track::TrackingState::Lost(_));
            if usable {
                live.push((frame.seq, *recorded, *recorded_measured, out.world_from_cam, out.state.is_tracked()));
            }
        }
        Ok(())
    })?;
    // Preferred pairs: recorded poses that were measured (not provisional initialisation
    // poses, which would carry their scale error into every later resume), against the new
    // tracker's refined keyframe poses or its measured live poses.
    let refined: BTreeMap<u64, Se3> = tracker.keyframes().map(|k| (k.seq, k.world_from_cam)).collect();
    let mut src: Vec<Vector3<f64>> = Vec::new();
    let mut dst: Vec<Vector3<f64>> = Vec::new();
    for (seq, recorded, measured, new_pose, new_measured) in &live {
        let new_pose = match refined.get(seq) {
            Some(p) => Some(p),
            None => new_measured.then_some(new_pose),
        };
        if let (true, Some(p)) = (*measured, new_pose) {
            src.push(p.translation.vector);
            dst.push(recorded.translation.vector);
        }
    }
    if src.len() < 4 {
        // Fall back to every frame both runs gave a pose.
        src = live.iter().map(|l| l.3.translation.vector).collect();
        dst = live.iter().map(|l| l.1.translation.vector).collect();
    }
    if src.len() < 4 {
        tracing::warn!(pairs = src.len(), "resume: too few frames tracked to relocalise in the recorded frame");
        return Ok(None);
    }
    let spread = |v: &[Vector3<f64>]| {
        let c = v.iter().sum::<Vector3<f64>>() / v.len() as f64;
        v.iter().map(|p| (p - c).norm()).fold(0.0, f64::max)
    };
    if spread(&src) < 1e-9 || spread(&dst) < 1e-9 {
        tracing::warn!("resume: no motion in the relocalisation frames");
        return Ok(None);
    }
    match crate::eval::umeyama(&src, &dst, true) {
        Ok(a) => Ok(Some(a)),
        Err(e) => {
            tracing::warn!("resume: relocalisation alignment failed: {e}");
            Ok(None)
        }
    }
}
