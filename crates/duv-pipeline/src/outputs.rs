//! The files a finished run leaves in its folder, written in one place: `trajectory.txt`
//! (every frame of map segment 0, the dive's world frame, with a pose estimate, TUM; a segment
//! started after a loss that never merged into it goes to `trajectory-segment-N.txt`, unless
//! the navigation placed it in the metric world ([`OutputFrames`]);
//! `states.txt` lists every frame with its state, where its pose comes from and its segment), `keyframes.txt`, the keyframes' full-resolution inverse depth and
//! variance (PFM, through the keyframe folder's writer, [`KeyframeFolder`]), `states.txt`. A resumed dive's poses are put in the recorded frame here,
//! once ([`finish_trajectory`]), and merged with what earlier processes of the dive logged
//! ([`DiveHistory`]): the files describe the whole dive.

use super::keyframe_folder::{KeyframeFolder, KeyframeFolderError};
use duv_core::pose::se3_to_tum;
use duv_core::{PlaneF32, Sim3, Timestamp};
use super::dive::DiveHistory;
use duv_core::StampedPose;
use duv_track::{FinalKeyframe, FinalTrajectory, KeyframeView, PoseSource, RecordedFrame, TrackError, Tracker, TrajectoryRecorder};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;

/// Why a run's output files could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error(transparent)]
    Io(#[from] duv_core::io::IoError),
    #[error(transparent)]
    KeyframeFolder(#[from] KeyframeFolderError),
    #[error("keyframe {id}: upsampling its depth: {source}")]
    Upsample { id: u64, source: TrackError },
}

/// The final poses of the run ([`TrajectoryRecorder::finish`]), in the recorded map frame when
/// the run resumed a dive (`world_from_tracker`, the resume's alignment).
pub fn finish_trajectory(recorder: &TrajectoryRecorder, tracker: &mut Tracker, world_from_tracker: Option<&Sim3>) -> FinalTrajectory {
    let mut fin = recorder.finish(tracker);
    // Keyframes the tracker was seeded with on resume never came out of `track`: they are
    // listed from the tracker's graph.
    let known: std::collections::BTreeSet<u64> = fin.keyframes.iter().map(|k| k.id).collect();
    let seeded: Vec<FinalKeyframe> = tracker.keyframes().filter(|k| !known.contains(&k.id)).map(|k| FinalKeyframe { id: k.id, t_ns: k.t_ns, seq: k.seq, world_from_cam: k.world_from_cam, segment: k.segment, live: true }).collect();
    fin.keyframes.extend(seeded);
    fin.keyframes.sort_by_key(|k| k.id);
    if let Some(a) = world_from_tracker {
        for f in &mut fin.frames {
            f.world_from_cam = duv_core::pose::sim3_apply_to_pose(a, &f.world_from_cam);
        }
        for k in &mut fin.keyframes {
            k.world_from_cam = duv_core::pose::sim3_apply_to_pose(a, &k.world_from_cam);
        }
    }
    fin
}

/// What [`write_tracking_outputs`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WrittenOutputs {
    /// The tracker's live keyframes of map segment 0, `(id, frame seq)`.
    pub live: Vec<(u64, u64)>,
    /// Frames in `states.txt` (the whole dive) and the first and last frame number.
    pub frames: u64,
    /// Of them, frames with a pose estimate (every segment's).
    pub frames_with_pose: u64,
    /// Frames with a pose estimate per map segment, ascending by segment: segment 0's are
    /// `trajectory.txt`, another's `trajectory-segment-N.txt` (or `trajectory.txt` when in
    /// `joined`).
    pub segments: Vec<(u32, u64)>,
    /// Segments other than 0 that the navigation placed in the world: in `trajectory.txt`.
    pub joined: Vec<u32>,
    pub first_seq: Option<u64>,
    pub last_seq: Option<u64>,
    /// Of them, poses logged by earlier processes of the dive (not tracked by this one).
    pub frames_from_log: u64,
    /// Keyframes in `keyframes.txt`.
    pub keyframes: u64,
    /// What `trajectory.txt` holds (segment 0 of the whole dive, by frame number).
    pub trajectory: Vec<StampedPose>,
}

/// Writes the full-resolution inverse depth and variance (PFM) of the tracker's live keyframes
/// into the keyframe folder: large files, written after the dive's small ones (a full disk then
/// costs these, not the record). `inv`/`var` are full-resolution scratch planes.
/// With `metric` (metric outputs, [`super::metric`]), inverse depth is in 1/m: divided by the
/// scale, the variance by its square.
pub fn write_keyframe_depths(folder: &KeyframeFolder, tracker: &Tracker, inv: &mut PlaneF32, var: &mut PlaneF32, metric: Option<&Sim3>) -> Result<(), OutputError> {
    // Segment 0's (the keyframes of `keyframes.txt`).
    let live: Vec<u64> = tracker.keyframes().filter(|k| k.segment == 0).map(|k: KeyframeView| k.id).collect();
    for id in live {
        tracker.upsample_keyframe(id, inv, var).map_err(|source| OutputError::Upsample { id, source })?;
        if let Some(a) = metric {
            let s = a.scaling() as f32;
            inv.data.iter_mut().for_each(|d| *d /= s);
            // Pixels without a variance hold f32::MAX: they stay so.
            var.data.iter_mut().filter(|v| **v < f32::MAX).for_each(|v| *v /= s * s);
        }
        folder.write_depth(id, inv, var)?;
    }
    Ok(())
}

/// The frame each map segment's poses are written in.
#[derive(Clone, Debug, Default)]
pub struct OutputFrames {
    /// `metric_from_map` of the dive's world frame (segment 0's; every pose without a frame of
    /// its own): metres when the navigation gave it, map units without.
    pub world: Option<Sim3>,
    /// Segments that never merged into segment 0 by sight, placed in the metric world by the
    /// navigation (`super::metric::join_segments`): `metric_from_map` of each. Their poses
    /// go to `trajectory.txt` with segment 0's.
    pub joined: BTreeMap<u32, Sim3>,
}

impl OutputFrames {
    /// `pose` of `segment` in the outputs' frame.
    fn to_output(&self, segment: u32, pose: &duv_core::Se3) -> duv_core::Se3 {
        match self.joined.get(&segment).or(self.world.as_ref()) {
            Some(a) => duv_core::pose::sim3_apply_to_pose(a, pose),
            None => *pose,
        }
    }

    /// Whether `segment`'s poses are in the dive's world frame (`trajectory.txt`).
    fn in_world(&self, segment: u32) -> bool {
        segment == 0 || self.joined.contains_key(&segment)
    }
}

/// Writes `trajectory.txt`, `keyframes.txt` (with `mapped`, the run's keyframe folder: only the
/// keyframes whose image it holds, those the mapping stage received, so `duv refine
/// --keyframes` reads the folder) and `states.txt`
/// (`frames` and `latencies` as the tracking thread recorded them), for the whole dive: this
/// process's final poses over what `history` (earlier processes, from the log) holds. The
/// keyframes' depth files are [`write_keyframe_depths`]'s.
pub fn write_tracking_outputs(
    out: &Path,
    fin: &FinalTrajectory,
    frames: &[RecordedFrame],
    latencies: &[Duration],
    tracker: &Tracker,
    mapped: Option<&KeyframeFolder>,
    history: Option<&DiveHistory>,
    frames_out: &OutputFrames,
) -> Result<WrittenOutputs, OutputError> {
    // seq -> (pose, state, where the pose comes from, tracker ms, note, segment): the log's
    // first, this process's over them.
    let mut dive: BTreeMap<u64, (StampedPose, String, PoseSource, Option<f64>, String, u32)> = BTreeMap::new();
    if let Some(h) = history {
        for (&seq, f) in &h.frames {
            let state = f.state.clone().unwrap_or_else(|| "unknown".into()).replace(' ', "_");
            // A logged pose is an estimate when its frame was tracked (or its state record
            // was lost with the power); initialising and lost frames' logged poses were
            // guesses.
            let source = match state.as_str() {
                "tracking" | "relocalised" => PoseSource::Measured,
                "unknown" => PoseSource::Logged,
                _ => PoseSource::None,
            };
            dive.insert(seq, (StampedPose { t_ns: f.t_ns, world_from_cam: f.world_from_cam }, state, source, None, f.note.clone().unwrap_or_default(), f.segment.unwrap_or(0)));
        }
    }
    let from_log = dive.len() as u64;
    let mut replaced = 0u64;
    let sources = fin.sources.iter().copied().chain(std::iter::repeat(PoseSource::None));
    let segments = fin.segments.iter().copied().chain(std::iter::repeat(0));
    for (((((f, pose), s), source), dt), segment) in frames.iter().zip(&fin.frames).zip(&fin.states).zip(sources).zip(latencies.iter().map(Some).chain(std::iter::repeat(None))).zip(segments) {
        let state = s.name().replace(' ', "_");
        if dive.insert(f.seq, (*pose, state, source, dt.map(|d| d.as_secs_f64() * 1e3), f.note.to_string(), segment)).is_some() {
            replaced += 1;
        }
    }
    // Metric outputs: every pose, logged or final, moved once ([`super::metric`]).
    for v in dive.values_mut() {
        v.0.world_from_cam = frames_out.to_output(v.5, &v.0.world_from_cam);
    }
    // Only estimated poses: a frame without one is in `states.txt` with pose `none`. One file
    // per frame of reference: segment 0 (the dive's world frame) and the segments the
    // navigation placed in it, `trajectory.txt`; another that never merged into it,
    // `trajectory-segment-N.txt` (its own frame and scale).
    let mut per_segment: BTreeMap<u32, Vec<StampedPose>> = BTreeMap::new();
    let mut trajectory: Vec<StampedPose> = Vec::new();
    for v in dive.values().filter(|v| v.2.has_pose()) {
        per_segment.entry(v.5).or_default().push(v.0);
        if frames_out.in_world(v.5) {
            trajectory.push(v.0);
        }
    }
    duv_core::io::tum::write_trajectory(&out.join("trajectory.txt"), &trajectory)?;
    for (segment, poses) in per_segment.iter().filter(|(s, _)| !frames_out.in_world(**s)) {
        duv_core::io::tum::write_trajectory(&out.join(format!("trajectory-segment-{segment}.txt")), poses)?;
    }
    // A segment file an earlier run of this folder left, that this dive does not have, goes.
    if let Ok(dir) = std::fs::read_dir(out) {
        for entry in dir.flatten() {
            let name = entry.file_name();
            let Some(n) = name.to_str().and_then(|n| n.strip_prefix("trajectory-segment-")).and_then(|n| n.strip_suffix(".txt")) else { continue };
            if n.parse::<u32>().map_or(true, |s| frames_out.in_world(s) || !per_segment.contains_key(&s)) {
                if let Err(e) = std::fs::remove_file(entry.path()) {
                    tracing::warn!("{}: stale segment trajectory not removed: {e}", entry.path().display());
                }
            }
        }
    }
    // Keyframes: the logged poses, this process's final ones over them.
    let mut keyframes: BTreeMap<u64, (Timestamp, duv_core::Se3)> = history.map(|h| h.keyframes.clone()).unwrap_or_default();
    // Segment 0's: the dive's world frame, as `trajectory.txt`.
    for k in fin.keyframes.iter().filter(|k| k.segment == 0) {
        keyframes.insert(k.id, (k.t_ns, k.world_from_cam));
    }
    let mut kf_text = String::from("# keyframe_id timestamp tx ty tz qx qy qz qw\n");
    let mut kf_written = 0u64;
    for (id, (t_ns, pose)) in &keyframes {
        // With mapping on, the keyframe folder lists the keyframes mapping received (their
        // images are written as they arrive), so `duv refine --keyframes` can read it.
        if mapped.is_some_and(|folder| !folder.has_image(*id)) {
            continue;
        }
        let _ = writeln!(kf_text, "{id} {}", tum_line(*t_ns, &frames_out.to_output(0, pose)));
        kf_written += 1;
    }
    duv_core::io::write_atomic(&out.join("keyframes.txt"), kf_text.as_bytes())?;
    let live: Vec<(u64, u64)> = tracker.keyframes().filter(|k| k.segment == 0).map(|k: KeyframeView| (k.id, k.seq)).collect();
    let mut states_text = String::from(
        "# seq timestamp state pose tracker_ms segment [why, while initialising] (pose: measured, interpolated between measured poses, none: no pose estimate, logged: an earlier process's pose whose state was lost; tracker_ms nan: tracked by an earlier process of the dive, see dive.json; segment: the map segment of the pose, 0 in trajectory.txt, N in trajectory-segment-N.txt or, when the navigation joined it (metric.json), in trajectory.txt, - without a pose)\n",
    );
    for (seq, (pose, state, source, ms, note, segment)) in &dive {
        let _ = write!(states_text, "{seq} {:.9} {state} {} {:.3}", pose.t_ns.as_secs_f64(), source.name(), ms.unwrap_or(f64::NAN));
        if source.has_pose() {
            let _ = write!(states_text, " {segment}");
        } else {
            states_text.push_str(" -");
        }
        if !note.is_empty() {
            let _ = write!(states_text, " {note}");
        }
        states_text.push('\n');
    }
    duv_core::io::write_atomic(&out.join("states.txt"), states_text.as_bytes())?;
    // The large files last: the small ones above always get the room kept for them.
    Ok(WrittenOutputs {
        live,
        frames: dive.len() as u64,
        frames_with_pose: per_segment.values().map(|v| v.len() as u64).sum(),
        segments: per_segment.iter().map(|(s, v)| (*s, v.len() as u64)).collect(),
        joined: frames_out.joined.keys().copied().filter(|s| per_segment.contains_key(s)).collect(),
        first_seq: dive.keys().next().copied(),
        last_seq: dive.keys().next_back().copied(),
        frames_from_log: from_log - replaced,
        keyframes: kf_written,
        trajectory,
    })
}

/// One line on what the initialisation waited for, when frames of this run waited: per
/// reason, the frames and the median value against its threshold (`None` when no frame waited).
pub fn init_summary(frames: &[RecordedFrame]) -> Option<String> {
    use duv_track::TrackNote;
    let mut by_kind: BTreeMap<&'static str, (Vec<f64>, f64)> = BTreeMap::new();
    for f in frames {
        let (Some(kind), TrackNote::InitLowConfidence { .. } | TrackNote::InitSmallFlow { .. } | TrackNote::InitPoseFailed) = (f.note.kind(), f.note) else { continue };
        let e = by_kind.entry(kind).or_insert_with(|| (Vec::new(), 0.0));
        if let Some((v, l)) = f.note.value_and_limit() {
            e.0.push(v);
            e.1 = l;
        } else {
            e.0.push(f64::NAN);
        }
    }
    if by_kind.is_empty() {
        return None;
    }
    let tracked = frames.iter().filter(|f| f.state.is_tracked()).count();
    let parts: Vec<String> = by_kind
        .into_iter()
        .map(|(kind, (mut v, limit))| {
            let n = v.len();
            v.sort_by(f64::total_cmp);
            let median = v[n / 2];
            match kind {
                "init_low_confidence" => format!("{n} with flow to the reference keyframe confident on too few pixels (median {:.1}% < {:.1}%)", median * 100.0, limit * 100.0),
                "init_small_flow" => format!("{n} with too little parallax (median mean flow {median:.2} px <= {limit:.2} px)"),
                _ => format!("{n} whose pose against the reference keyframe did not converge"),
            }
        })
        .collect();
    let waited = frames.iter().filter(|f| f.note.kind().is_some_and(|k| k != "init_keyframe")).count();
    Some(format!("initialisation waited on {waited} frame(s) ({tracked} of {} frames measured): {}", frames.len(), parts.join("; ")))
}

/// Space held back in the run folder for the final outputs: a file of zeros made at start and
/// removed right before the outputs are written, so a disk the log filled still takes the
/// trajectory, the keyframe list, the states and `dive.json`.
pub struct DiskReserve {
    path: std::path::PathBuf,
}

/// Bytes [`DiskReserve`] holds back.
pub const RESERVE_BYTES: usize = 8 << 20;

impl DiskReserve {
    /// Makes (or keeps) `OUT/duv.reserve`; a disk too full for it is reported, not an error.
    pub fn claim(out: &Path) -> DiskReserve {
        let path = out.join("duv.reserve");
        let ok = std::fs::metadata(&path).is_ok_and(|m| m.len() as usize == RESERVE_BYTES) || {
            let zeros = vec![0u8; RESERVE_BYTES];
            match std::fs::File::create(&path).and_then(|mut f| std::io::Write::write_all(&mut f, &zeros).and_then(|()| f.sync_all())) {
                Ok(()) => true,
                Err(e) => {
                    let _ = std::fs::remove_file(&path);
                    tracing::warn!("{}: no room for the {} MiB kept for the final outputs: {e}", path.display(), RESERVE_BYTES >> 20);
                    false
                }
            }
        };
        if !ok {
            tracing::warn!("the final outputs may not fit if the disk fills");
        }
        DiskReserve { path }
    }

    /// Frees the space for the outputs (dropping it does the same: a run that ends with an
    /// error leaves no reserve behind; only a killed one does, and its next start reuses it).
    pub fn release(self) {}
}

impl Drop for DiskReserve {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

fn tum_line(t_ns: Timestamp, pose: &duv_core::Se3) -> String {
    let v = se3_to_tum(pose);
    format!("{:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}", t_ns.as_secs_f64(), v[0], v[1], v[2], v[3], v[4], v[5], v[6])
}
