//! The caller's record of a run: every frame's output, kept to write the final trajectory once
//! the graph has settled. A frame's pose is re-expressed through its anchor keyframe (so loop
//! closures and global BA move it too); frames without an anchor (initialisation, lost) are
//! interpolated in time between their anchored neighbours when those are at most
//! [`MAX_INTERPOLATION_GAP_S`] apart, and have no pose otherwise ([`PoseSource`]): a pose
//! that was not estimated is never passed off as one. This grows with the run, so it
//! belongs to offline runs and evaluation (`duv run`), not to the fixed-memory tracker.

use super::tracker::{EvictedKeyframe, FrameAnchor, TrackNote, Tracker, TrackingState, TrackOutput};
use duv_core::{Se3, StampedPose, Timestamp};
use nalgebra::{Translation3, UnitQuaternion};
use std::collections::BTreeMap;

/// One recorded frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RecordedFrame {
    pub t_ns: Timestamp,
    pub seq: u64,
    /// The pose the tracker reported live.
    pub live: Se3,
    pub state: TrackingState,
    pub anchor: Option<FrameAnchor>,
    /// Why it has no measured pose yet (initialisation).
    pub note: TrackNote,
}

/// A keyframe of the final result.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FinalKeyframe {
    pub id: u64,
    pub t_ns: Timestamp,
    pub seq: u64,
    pub world_from_cam: Se3,
    /// Map segment at the end (after merges).
    pub segment: u32,
    /// Still in the graph at the end (its depth maps are available from the tracker).
    pub live: bool,
}

/// Longest time between two measured poses across which the frames in between are
/// interpolated, seconds: the keyframes collected while initialising are closer than this at
/// any usual speed; a longer gap (lost, an initialisation that started again) leaves its
/// frames without a pose.
pub const MAX_INTERPOLATION_GAP_S: f64 = 2.0;

/// Where a frame's final pose comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PoseSource {
    /// Measured: through the keyframe it was tracked against.
    Measured,
    /// Interpolated in time between two measured poses at most [`MAX_INTERPOLATION_GAP_S`]
    /// apart (frames between the keyframes collected while initialising, short losses).
    Interpolated,
    /// No estimate: before the first or after the last measured pose, across a longer gap, or
    /// its keyframe was dropped (an initialisation that started again). The pose held is the
    /// tracker's live guess and is not an output.
    None,
    /// A pose an earlier process of the dive logged, whose state record was lost (a power cut):
    /// kept, as the frame may well have been tracked.
    Logged,
}

impl PoseSource {
    /// Short name (`states.txt`'s pose column).
    pub fn name(self) -> &'static str {
        match self {
            PoseSource::Measured => "measured",
            PoseSource::Interpolated => "interpolated",
            PoseSource::None => "none",
            PoseSource::Logged => "logged",
        }
    }
    /// Whether the frame has a pose estimate (measured or interpolated).
    pub fn has_pose(self) -> bool {
        self != PoseSource::None
    }
}

/// Final poses of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct FinalTrajectory {
    /// Every frame, in the order tracked (those without an estimate hold the live guess; see
    /// `sources`).
    pub frames: Vec<StampedPose>,
    pub states: Vec<TrackingState>,
    /// Where each frame's pose comes from.
    pub sources: Vec<PoseSource>,
    /// Each frame's map segment at the end (after merges; meaningful where it has a pose):
    /// poses of different segments are in different frames and scales.
    pub segments: Vec<u32>,
    /// Every keyframe kept (pruned ones excluded), by id.
    pub keyframes: Vec<FinalKeyframe>,
}

impl FinalTrajectory {
    /// The frames with a pose estimate, in order, of every segment.
    pub fn estimated(&self) -> Vec<StampedPose> {
        self.frames.iter().zip(&self.sources).filter(|(_, s)| s.has_pose()).map(|(p, _)| *p).collect()
    }
    /// The frames of `segment` with a pose estimate, in order (`trajectory.txt` holds segment
    /// 0's, the dive's world frame).
    pub fn estimated_in(&self, segment: u32) -> Vec<StampedPose> {
        (0..self.frames.len()).filter(|&i| self.sources[i].has_pose() && self.segments[i] == segment).map(|i| self.frames[i]).collect()
    }
    /// The segments with at least one posed frame, ascending, with their posed frame counts.
    pub fn segment_counts(&self) -> Vec<(u32, usize)> {
        let mut counts: BTreeMap<u32, usize> = BTreeMap::new();
        for i in 0..self.frames.len() {
            if self.sources[i].has_pose() {
                *counts.entry(self.segments[i]).or_default() += 1;
            }
        }
        counts.into_iter().collect()
    }
}

/// Collects [`TrackOutput`]s; [`finish`](Self::finish) resolves them against the tracker.
#[derive(Clone, Debug, Default)]
pub struct TrajectoryRecorder {
    frames: Vec<RecordedFrame>,
    evicted: BTreeMap<u64, EvictedRecord>,
    keyframes: Vec<(u64, Timestamp, u64)>,
}

#[derive(Clone, Copy, Debug)]
struct EvictedRecord {
    ev: EvictedKeyframe,
}

impl TrajectoryRecorder {
    pub fn new() -> Self {
        Self::default()
    }

    /// Room for `frames` frames and `keyframes` keyframes before the record grows (it holds
    /// the whole run, so a run longer than that grows it, by doubling).
    pub fn with_capacity(frames: usize, keyframes: usize) -> Self {
        TrajectoryRecorder { frames: Vec::with_capacity(frames), evicted: BTreeMap::new(), keyframes: Vec::with_capacity(keyframes) }
    }

    pub fn record(&mut self, out: &TrackOutput) {
        self.frames.push(RecordedFrame { t_ns: out.t_ns, seq: out.seq, live: out.world_from_cam, state: out.state, anchor: out.anchor, note: out.note });
        if let Some(id) = out.new_keyframe {
            self.keyframes.push((id, out.t_ns, out.seq));
        }
        if let Some(ev) = out.evicted {
            self.evicted.insert(ev.id, EvictedRecord { ev });
        }
    }

    pub fn frames(&self) -> &[RecordedFrame] {
        &self.frames
    }

    /// Pose, current scale correction and segment of keyframe `id`, following eviction
    /// anchors (an evicted keyframe is anchored to one of its segment).
    fn keyframe_pose(&self, live: &BTreeMap<u64, (Se3, f64, u32)>, id: u64) -> Option<(Se3, f64, u32)> {
        // Walk up to a live keyframe, then compose back down.
        let mut chain: Vec<&EvictedKeyframe> = Vec::new();
        let mut cur = id;
        let (mut pose, mut scale, segment) = loop {
            if let Some(&(p, s, seg)) = live.get(&cur) {
                break (p, s, seg);
            }
            let rec = self.evicted.get(&cur)?;
            chain.push(&rec.ev);
            cur = rec.ev.anchor.keyframe;
            if chain.len() > self.evicted.len() {
                return None;
            }
        };
        for ev in chain.iter().rev() {
            let ratio = scale / ev.anchor.kf_scale;
            pose *= scale_translation(&ev.anchor.kf_from_cam, ratio);
            scale = ev.scale_correction * ratio;
        }
        Some((pose, scale, segment))
    }

    /// Final poses: anchored frames through their keyframe's current pose, the rest
    /// interpolated. A global BA still running in the background is applied first (the end
    /// of the stream; [`Tracker::finish_global_ba`]).
    pub fn finish(&self, tracker: &mut Tracker) -> FinalTrajectory {
        tracker.finish_global_ba();
        // Before the initial BA the keyframes' poses are provisional: nothing is measured yet;
        // the same holds for a later segment still collecting its first keyframes.
        let collecting = tracker.collecting_segment();
        let live: BTreeMap<u64, (Se3, f64, u32)> = if tracker.is_initialised() {
            tracker.keyframes().filter(|k| Some(k.segment) != collecting).map(|k| (k.id, (k.world_from_cam, k.scale_correction, k.segment))).collect()
        } else {
            BTreeMap::new()
        };
        let resolved: Vec<Option<(Se3, u32)>> = self
            .frames
            .iter()
            .map(|f| {
                let a = f.anchor?;
                let (kf_pose, scale, segment) = self.keyframe_pose(&live, a.keyframe)?;
                Some((kf_pose * scale_translation(&a.kf_from_cam, scale / a.kf_scale), segment))
            })
            .collect();
        let mut frames = Vec::with_capacity(self.frames.len());
        let mut sources = Vec::with_capacity(self.frames.len());
        let mut segments = Vec::with_capacity(self.frames.len());
        let max_gap_ns = MAX_INTERPOLATION_GAP_S * 1e9;
        for (i, f) in self.frames.iter().enumerate() {
            let (pose, source, segment) = match resolved[i] {
                Some((p, seg)) => (p, PoseSource::Measured, seg),
                None => {
                    let before = (0..i).rev().find(|&j| resolved[j].is_some());
                    let after = (i + 1..self.frames.len()).find(|&j| resolved[j].is_some());
                    match (before.and_then(|b| Some((b, resolved[b]?))), after.and_then(|a| Some((a, resolved[a]?)))) {
                        (Some((b, (pb, sb))), Some((a, (pa, sa)))) => {
                            let (tb, ta) = (self.frames[b].t_ns.0 as f64, self.frames[a].t_ns.0 as f64);
                            let u = if ta > tb { ((f.t_ns.0 as f64 - tb) / (ta - tb)).clamp(0.0, 1.0) } else { 0.0 };
                            let pose = interpolate(&pb, &pa, u);
                            // Only between two poses of one segment (two frames otherwise).
                            if ta - tb <= max_gap_ns && sb == sa {
                                (pose, PoseSource::Interpolated, sb)
                            } else {
                                (pose, PoseSource::None, sb)
                            }
                        }
                        _ => (f.live, PoseSource::None, 0),
                    }
                }
            };
            frames.push(StampedPose { t_ns: f.t_ns, world_from_cam: pose });
            sources.push(source);
            segments.push(segment);
        }
        let keyframes = self
            .keyframes
            .iter()
            .filter_map(|&(id, t_ns, seq)| {
                let (pose, _, segment) = self.keyframe_pose(&live, id)?;
                Some(FinalKeyframe { id, t_ns, seq, world_from_cam: pose, segment, live: live.contains_key(&id) })
            })
            .collect();
        FinalTrajectory { frames, states: self.frames.iter().map(|f| f.state).collect(), sources, segments, keyframes }
    }
}

fn scale_translation(pose: &Se3, s: f64) -> Se3 {
    Se3::from_parts(Translation3::from(pose.translation.vector * s), pose.rotation)
}

fn interpolate(a: &Se3, b: &Se3, u: f64) -> Se3 {
    let t = a.translation.vector * (1.0 - u) + b.translation.vector * u;
    let q: UnitQuaternion<f64> = a.rotation.try_slerp(&b.rotation, u, 1e-9).unwrap_or(a.rotation);
    Se3::from_parts(Translation3::from(t), q)
}
