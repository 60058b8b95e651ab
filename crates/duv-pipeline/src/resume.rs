//! Resume after power loss: recover the log's unfinished segments, find where the recorded
//! trajectory stopped, reload the newest good map checkpoint, and relocalise a new tracker in
//! the recorded map frame.
//!
//! Relocalisation against what was logged: the tracker's newest keyframes seed the new tracker
//! ([`Tracker::seed`]) with their poses in the recorded world frame and their inverse depth
//! and variance. They come from the newest `/slam/window` record (tracking logs its window
//! twice a second of frame time: ids, frame numbers, poses and the depth grids; the images are
//! the logged frames), or from the logged keyframes (`/keyframe/*`, which keyframes reach
//! only after leaving the BA window) when those are newer. Their recorded poses are the
//! fixed, oldest poses of its next BA windows, so it continues in the recorded frame and
//! scale: nothing is re-initialised and nothing is aligned. The logged frames after the newest
//! of those keyframes, up to the last recorded pose, are tracked again first
//! ([`Relocalisation::Seeded`]`::retrack`): that rebuilds the window and hands the keyframes
//! made there to mapping and the log.
//!
//! A log with neither comes from a run stopped during its initialisation (before its first
//! window record). When it still holds every frame from the tracker's first one (recorded at
//! the identity), a new tracker starts there again and tracks them all
//! ([`Relocalisation::Restarted`]): a tracker is deterministic, so it rebuilds the
//! initialisation the stopped run was building, in the recorded frame and scale, and goes on
//! from its last frame (exactly with raw-logged frames; JPEG-logged frames come back decoded,
//! so closely). Otherwise it is seeded with the logged frames that were the newest
//! keyframes instead, at their recorded poses (refined by the
//! keyframe's BA round), their depth triangulated from those poses ([`SeedFrame`]); the frames
//! after them are tracked again as above.
//!
//! Fallback, when the log holds none of these (fewer than 3 such frames: a run stopped early
//! in its initialisation): the last logged frames (with the poses recorded for them) are
//! tracked by the new tracker from scratch, and the Sim(3) that carries its positions onto the
//! recorded ones (Umeyama) becomes [`PipelineConfig::world_from_tracker`](super::PipelineConfig).
//! Its scale comes from ~20 frames of a re-initialisation, so it drifts; the caller says which
//! path was taken.

use super::dive::{DiveHistory, PART_METADATA};
use super::{CheckpointStore, PipelineError};
use duv_core::{Frame, ImageRgb8, Keyframe, PinholeCamera, PlaneF32, Se3, Sim3, Timestamp};
use duv_log::reader::OwnedEvent;
use duv_log::schema::{decode_calibration, decode_frame, decode_nav, decode_plane_f32, decode_pose, decode_state};
use duv_log::{list_segments, recover_folder, ReadLimits, RecoveryReport, SegmentReader, Topic, TrackerWindow};
use duv_track::{ResumePoint, SeedFrame, SeedKeyframe, Tracker, TrackerSeed};
use nalgebra::Vector3;
use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};

/// How much of the log a resume keeps in memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ResumeOptions {
    /// Logged frames the fallback (re-initialisation and Sim(3)) tracks again.
    pub relocalisation_frames: usize,
    /// Newest logged keyframes the new tracker is seeded with (at most the tracker's
    /// `max_keyframes`).
    pub seed_keyframes: usize,
    /// Logged frames kept to track again after the newest keyframe, in bytes of image data
    /// (the oldest go first; tracking then picks up at the recorded pose before the first kept).
    pub retrack_bytes: usize,
}

/// Recorded poses kept while reading (the newest), for the resume point and the fallback.
const POSES_KEPT: usize = 1 << 14;
/// Frames between the recorded frames that seed the tracker when the log holds no keyframe.
const SEED_FRAME_SPACING: u64 = 4;

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
    /// What the fallback tracks again.
    pub recent: Vec<(Frame, Se3, bool)>,
    /// The keyframes that seed the tracker, oldest first, as (frame seq, keyframe): the newest
    /// logged tracker window's, or the newest logged keyframes that are whole (image, inverse
    /// depth, variance, pose) with a known frame number when those are newer.
    pub keyframes: Vec<(u64, Keyframe)>,
    /// The frame after which the tracker window `keyframes` come from was logged; `None`
    /// when they are logged keyframes.
    pub window_seq: Option<u64>,
    /// One more than the largest keyframe id the log mentions (logged, or announced in a
    /// tracking state): the new tracker's keyframes get ids from here.
    pub next_keyframe_id: u64,
    /// One more than the largest map segment the log mentions: the new tracker's new
    /// segments get ids from here (segment 0, the dive's world frame, is what it continues in).
    pub next_segment: u32,
    /// When the log holds no whole keyframe: the logged frames that were the newest keyframes
    /// (up to `seed_keyframes`, at least 3), else the newest with measured recorded poses
    /// `SEED_FRAME_SPACING` apart (at least 3); oldest first, to seed the tracker.
    pub seed_frames: Vec<(Frame, Se3)>,
    /// The run stopped during its initialisation (no window or keyframe logged) and the log
    /// holds every frame from the tracker's first (recorded at the identity): `retrack` is all
    /// of them, tracked again by a new tracker from the start.
    pub restart: bool,
    /// Logged frames after the newest of `keyframes` (or `seed_frames`) up to `last_seq`,
    /// oldest first.
    pub retrack: Vec<Frame>,
    /// Logged frames after `last_seq` (captured and logged, not yet tracked when the run
    /// stopped), oldest first: tracked from the log, so the source goes on after the last
    /// logged frame and no frame is logged twice.
    pub unposed: Vec<Frame>,
    /// The newest logged camera frame.
    pub last_frame_seq: Option<u64>,
    /// Recorded poses of the last frames: seq -> (pose, measured).
    pub poses: BTreeMap<u64, (Se3, bool)>,
    pub camera: Option<PinholeCamera>,
    /// Newest checkpoint that verified.
    pub checkpoint: Option<(PathBuf, Vec<u8>)>,
    /// Every logged pose, state and keyframe pose, and the processes that wrote them: what
    /// the output files of the whole dive are written from.
    pub history: DiveHistory,
}

/// A keyframe's four records as they arrive.
#[derive(Default)]
struct PartialKeyframe {
    image: Option<ImageRgb8>,
    inv_depth: Option<PlaneF32>,
    variance: Option<PlaneF32>,
}

/// Looks at `out_dir`; `None` when it holds no log (a fresh start). Unfinished segments are
/// recovered in place.
pub fn prepare(out_dir: &Path, limits: ReadLimits, options: &ResumeOptions) -> Result<Option<ResumeState>, PipelineError> {
    let log_dir = out_dir.join("log");
    if list_segments(&log_dir)?.is_empty() {
        return Ok(None);
    }
    let recovered = recover_folder(&log_dir, limits)?;
    // By seq: a frame logged by a run killed before tracking it is logged again by the next.
    let mut frames: BTreeMap<u64, (Vec<u8>, u64)> = BTreeMap::new();
    let mut frame_bytes = 0usize;
    let mut poses: BTreeMap<u64, (Se3, bool)> = BTreeMap::new();
    // Frames whose recorded pose can seed a tracker: measured (tracking or relocalised), or
    // keyframes of an initialisation.
    let mut measured: std::collections::BTreeSet<u64> = std::collections::BTreeSet::new();
    // Frames that became keyframes (not lost): poses refined by the keyframe's BA round.
    let mut keyframe_frames: std::collections::BTreeSet<u64> = std::collections::BTreeSet::new();
    // Pose time -> seq: a keyframe's frame number (keyframes are logged by id and time).
    let mut seq_of_t: BTreeMap<u64, u64> = BTreeMap::new();
    let mut partial: BTreeMap<u64, PartialKeyframe> = BTreeMap::new();
    // The newest logged tracker window (`/slam/window`) and the frames its keyframes were.
    let mut window: Option<TrackerWindow> = None;
    let mut window_seqs: Vec<u64> = Vec::new();
    let mut keyframes: VecDeque<(u64, Keyframe)> = VecDeque::new();
    let mut next_keyframe_id = 0u64;
    let mut next_segment = 1u32;
    let mut camera = None;
    let mut poses_recorded = 0u64;
    let mut last: Option<(u64, Timestamp)> = None;
    let mut history = DiveHistory::default();
    for (segment, path) in list_segments(&log_dir)? {
        let mut r = SegmentReader::open(&path, limits)?;
        let mut part: Option<u32> = None;
        while let Some(e) = r.next_event() {
            let (channel_id, sequence, log_time_ns, data) = match e {
                OwnedEvent::Message { channel_id, sequence, log_time_ns, data, .. } => (channel_id, sequence, log_time_ns, data),
                OwnedEvent::Metadata { name, metadata } if name == PART_METADATA && part.is_none() => {
                    part = Some(history.open_segment(segment, Some(&metadata)));
                    continue;
                }
                _ => continue,
            };
            let Some(topic) = r.channel(channel_id).and_then(|c| Topic::from_name(&c.topic)) else { continue };
            let seq = sequence as u64;
            match topic {
                Topic::CameraImage => {
                    frame_bytes += data.len();
                    if let Some(old) = frames.insert(seq, (data, log_time_ns)) {
                        frame_bytes -= old.0.len();
                    }
                    // The oldest go first, except the frames of the newest window's keyframes.
                    while frames.len() > options.relocalisation_frames * 4 && frame_bytes > options.retrack_bytes {
                        let Some(victim) = frames.keys().find(|s| !window_seqs.contains(s)).copied() else { break };
                        if let Some((d, _)) = frames.remove(&victim) {
                            frame_bytes -= d.len();
                        }
                    }
                }
                Topic::CameraCalibration => camera = decode_calibration(&data).ok(),
                Topic::Pose => {
                    if let Ok(p) = decode_pose(&data) {
                        let part = *part.get_or_insert_with(|| history.open_segment(segment, None));
                        history.add_pose(part, seq, Timestamp::from_ns(log_time_ns as i64), p);
                        poses_recorded += 1;
                        let tracked = poses.get(&seq).map(|x| x.1).unwrap_or(true);
                        poses.insert(seq, (p, tracked));
                        seq_of_t.insert(log_time_ns, seq);
                        if last.is_none_or(|(s, _)| seq >= s) {
                            last = Some((seq, Timestamp::from_ns(log_time_ns as i64)));
                        }
                        while poses.len() > POSES_KEPT {
                            poses.pop_first();
                        }
                        while seq_of_t.len() > POSES_KEPT {
                            seq_of_t.pop_first();
                        }
                    }
                }
                Topic::State => {
                    if let Ok(s) = decode_state(&data) {
                        let note = s.why.as_ref().map(|w| match (s.value, s.limit) {
                            (Some(v), Some(l)) => format!("{w} {v:.4} (limit {l:.4})"),
                            _ => w.clone(),
                        });
                        history.add_state(s.seq, &s.state, note, s.segment);
                        next_segment = next_segment.max(s.segment.saturating_add(1));
                        // A resume continues in segment 0 (the dive's world frame): another
                        // segment's poses are in another frame and seed nothing.
                        let in_world = s.segment == 0;
                        if let Some(p) = poses.get_mut(&s.seq) {
                            // Lost frames hold a prediction, not a measurement.
                            p.1 = !s.state.starts_with("lost") && in_world;
                        }
                        // Measured, or a keyframe of the initialisation (its pose refined by
                        // the initialisation BA; the frames between hold provisional poses).
                        if in_world && (s.tracked || (s.new_keyframe.is_some() && !s.state.starts_with("lost"))) {
                            measured.insert(s.seq);
                        } else {
                            measured.remove(&s.seq);
                        }
                        while measured.len() > POSES_KEPT {
                            measured.pop_first();
                        }
                        if s.new_keyframe.is_some() && !s.state.starts_with("lost") {
                            keyframe_frames.insert(s.seq);
                        } else {
                            keyframe_frames.remove(&s.seq);
                        }
                        while keyframe_frames.len() > POSES_KEPT {
                            keyframe_frames.pop_first();
                        }
                        if let Some(id) = s.new_keyframe {
                            next_keyframe_id = next_keyframe_id.max(id + 1);
                        }
                    }
                }
                Topic::Nav => {
                    if let Ok(n) = decode_nav(&data) {
                        history.nav.push(n);
                    }
                }
                Topic::TrackerWindow => match TrackerWindow::decode(&data) {
                    Ok(w) if w.keyframes.len() >= 2 => {
                        for k in &w.keyframes {
                            next_keyframe_id = next_keyframe_id.max(k.id + 1);
                        }
                        if window.as_ref().is_none_or(|old| w.seq >= old.seq) {
                            window_seqs = w.keyframes.iter().map(|k| k.seq).collect();
                            window = Some(w);
                        }
                    }
                    Ok(_) => {}
                    Err(e) => tracing::warn!("resume: logged tracker window at frame {seq} unreadable: {e}"),
                },
                Topic::KeyframeImage => match decode_frame(&data, seq, log_time_ns) {
                    Ok(f) => partial.entry(seq).or_default().image = Some(f.image.to_rgb8()),
                    Err(e) => tracing::warn!("resume: logged keyframe {seq}: image unreadable: {e}"),
                },
                Topic::KeyframeInvDepth => match decode_plane_f32(&data) {
                    Ok(p) => partial.entry(seq).or_default().inv_depth = Some(p),
                    Err(e) => tracing::warn!("resume: logged keyframe {seq}: inverse depth unreadable: {e}"),
                },
                Topic::KeyframeVariance => match decode_plane_f32(&data) {
                    Ok(p) => partial.entry(seq).or_default().variance = Some(p),
                    Err(e) => tracing::warn!("resume: logged keyframe {seq}: variance unreadable: {e}"),
                },
                Topic::KeyframePose => {
                    // The last of a keyframe's four records.
                    next_keyframe_id = next_keyframe_id.max(seq + 1);
                    let parts = partial.remove(&seq).unwrap_or_default();
                    if let Ok(pose) = decode_pose(&data) {
                        history.add_keyframe(seq, Timestamp::from_ns(log_time_ns as i64), pose);
                    }
                    let (Ok(pose), Some(image), Some(inv_depth), Some(variance), Some(cam)) = (decode_pose(&data), parts.image, parts.inv_depth, parts.variance, camera) else {
                        tracing::warn!("resume: logged keyframe {seq} incomplete, not used");
                        continue;
                    };
                    let Some(&frame_seq) = seq_of_t.get(&log_time_ns) else {
                        tracing::warn!("resume: logged keyframe {seq}: no recorded pose at its time, not used");
                        continue;
                    };
                    let kf = Keyframe { index: seq, t_ns: Timestamp::from_ns(log_time_ns as i64), image, world_from_cam: pose, camera: cam, inv_depth, inv_depth_variance: variance };
                    if !kf.is_consistent() {
                        tracing::warn!("resume: logged keyframe {seq}: planes do not match the camera, not used");
                        continue;
                    }
                    // Ids of one log increase; a log written before ids continued across
                    // resumes may repeat one: the newer keyframe replaces the older.
                    keyframes.retain(|(_, k)| k.index < seq);
                    keyframes.push_back((frame_seq, kf));
                    while keyframes.len() > options.seed_keyframes {
                        keyframes.pop_front();
                    }
                }
                _ => {}
            }
        }
    }
    let Some((last_seq, last_t_ns)) = last else {
        // Stopped before its first pose: the frames it logged are tracked from the log (when
        // they follow one another), not captured and logged again.
        let contiguous = frames.keys().zip(frames.keys().skip(1)).all(|(a, b)| b == &(a + 1));
        let mut unposed = Vec::new();
        if contiguous {
            for (seq, (data, t)) in &frames {
                match decode_frame(data, *seq, *t) {
                    Ok(f) => unposed.push(f),
                    Err(e) => {
                        tracing::warn!("resume: logged frame {seq} unreadable: {e}; the source starts again at the first");
                        unposed.clear();
                        break;
                    }
                }
            }
        }
        let last_frame_seq = unposed.last().map(|f| f.seq);
        return Ok(Some(ResumeState {
            log_dir,
            recovered,
            last_seq: 0,
            last_t_ns: Timestamp::from_ns(0),
            poses_recorded: 0,
            recent: Vec::new(),
            keyframes: Vec::new(),
            window_seq: None,
            next_keyframe_id,
            next_segment,
            seed_frames: Vec::new(),
            restart: false,
            retrack: Vec::new(),
            unposed,
            last_frame_seq,
            poses,
            camera,
            checkpoint: None,
            history,
        }));
    };
    let mut keyframes: Vec<(u64, Keyframe)> = keyframes.into_iter().filter(|(s, _)| *s <= last_seq).collect();
    // The newest window, when it is newer than the newest whole keyframe (the rule: keyframes
    // reach the log only after they leave the window), replaces the logged keyframes.
    let newest_logged = keyframes.last().map(|(s, _)| *s);
    let mut window_seq = None;
    if let (Some(w), Some(cam)) = (window.filter(|w| w.seq <= last_seq), camera) {
        if newest_logged.is_none_or(|n| w.keyframes.last().is_some_and(|k| k.seq > n)) {
            match window_keyframes(&w, &cam, &frames, &log_dir, limits) {
                Ok(k) => {
                    keyframes = k;
                    window_seq = Some(w.seq);
                }
                Err(e) => tracing::warn!("resume: the logged tracker window at frame {} is not used: {e}", w.seq),
            }
        }
    }
    // Stopped during its initialisation (no window, no keyframe logged) with every frame
    // from the tracker's start still in the log: the initialisation is tracked again from
    // that first frame, as it was.
    let restart_from = match poses.first_key_value() {
        Some((&first, (pose, _))) if keyframes.is_empty() && poses.len() < POSES_KEPT && is_tracker_start(pose) && (first..=last_seq).all(|s| frames.contains_key(&s)) => Some(first),
        _ => None,
    };
    let mut seed_seqs: Vec<u64> = Vec::new();
    if keyframes.is_empty() && restart_from.is_none() {
        // The frames that were the newest keyframes, as the stopped tracker's window held them.
        seed_seqs.extend(frames.keys().rev().filter(|s| **s <= last_seq && keyframe_frames.contains(s) && poses.contains_key(s)).take(options.seed_keyframes));
        if seed_seqs.len() < 3 {
            seed_seqs.clear();
        }
    }
    if keyframes.is_empty() && seed_seqs.is_empty() && restart_from.is_none() {
        for &s in frames.keys().rev().filter(|s| **s <= last_seq && measured.contains(s) && poses.contains_key(s)) {
            if seed_seqs.last().is_none_or(|l| l - s >= SEED_FRAME_SPACING) {
                seed_seqs.push(s);
                if seed_seqs.len() >= options.seed_keyframes {
                    break;
                }
            }
        }
        if seed_seqs.len() < 3 {
            seed_seqs.clear();
        }
    }
    seed_seqs.reverse();
    // Frames to track again come after this one (all of them from `restart_from`).
    let after = keyframes.last().map(|(s, _)| *s).or(seed_seqs.last().copied());
    let retrack_from = after.map(|a| a + 1).or(restart_from);
    let mut seed_frames = Vec::new();
    let mut recent = Vec::new();
    let mut retrack = Vec::new();
    let mut unposed = Vec::new();
    let last_frame_seq = frames.keys().next_back().copied();
    let first_recent = frames.keys().rev().filter(|s| poses.contains_key(s)).nth(options.relocalisation_frames.saturating_sub(1)).copied().unwrap_or(0);
    for (seq, (data, t)) in frames {
        let wanted_retrack = retrack_from.is_some_and(|a| seq >= a && seq <= last_seq);
        let pose = poses.get(&seq).copied();
        let wanted_recent = seq >= first_recent && pose.is_some();
        let wanted_seed = seed_seqs.contains(&seq);
        let wanted_unposed = seq > last_seq;
        if !(wanted_retrack || wanted_recent || wanted_seed || wanted_unposed) {
            continue;
        }
        match decode_frame(&data, seq, t) {
            Ok(f) => {
                if let (true, Some((p, tracked))) = (wanted_recent, pose) {
                    recent.push((f.clone(), p, tracked));
                }
                if let (true, Some((p, _))) = (wanted_seed, pose) {
                    seed_frames.push((f.clone(), p));
                }
                if wanted_unposed {
                    unposed.push(f);
                } else if wanted_retrack {
                    retrack.push(f);
                }
            }
            Err(e) => tracing::warn!("resume: logged frame {seq} unreadable: {e}"),
        }
    }
    let checkpoint = CheckpointStore::new(out_dir.join("checkpoints"), 3).load_newest();
    // A logged frame that does not decode is skipped like a dropped frame.
    let restart = restart_from.is_some();
    Ok(Some(ResumeState { log_dir, recovered, last_seq, last_t_ns, poses_recorded, recent, keyframes, window_seq, next_keyframe_id, next_segment, seed_frames, restart, retrack, unposed, last_frame_seq, poses, camera, checkpoint, history }))
}

/// Whether `pose` is where a tracker starts (its first keyframe, the identity), so that a new
/// tracker given the same first frame starts in the recorded frame.
fn is_tracker_start(pose: &Se3) -> bool {
    pose.translation.vector.norm() < 1e-9 && pose.rotation.angle() < 1e-9
}

/// Why a logged tracker window cannot seed the tracker (the resume then uses the logged
/// keyframes, and says why).
#[derive(Debug, thiserror::Error)]
pub enum WindowSeedError {
    #[error(transparent)]
    Log(#[from] duv_log::LogError),
    #[error("keyframe {id}: its frame {seq} is not in the log")]
    FrameMissing { id: u64, seq: u64 },
    #[error("keyframe {id}: frame {seq}: {source}")]
    Frame { id: u64, seq: u64, source: duv_log::DecodeError },
    #[error("keyframe {id}: frame {seq} is {width}x{height}, the calibration {expected_width}x{expected_height}")]
    FrameSize { id: u64, seq: u64, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("keyframe {id}: depth grid {grid_width}x{grid_height} does not fit {width}x{height}")]
    GridSize { id: u64, grid_width: usize, grid_height: usize, width: usize, height: usize },
}

/// The keyframes of a logged tracker window as whole [`Keyframe`]s for [`Tracker::seed`]: each
/// image is the logged frame it was (from `frames`, or read again from the segments, newest
/// first, when the byte budget let it go), its depth grid repeated over each cell at the input
/// resolution (the seed takes cell means again, so the grid comes back as it was logged).
fn window_keyframes(w: &TrackerWindow, camera: &PinholeCamera, frames: &BTreeMap<u64, (Vec<u8>, u64)>, log_dir: &Path, limits: ReadLimits) -> Result<Vec<(u64, Keyframe)>, WindowSeedError> {
    let mut found: BTreeMap<u64, (Vec<u8>, u64)> = BTreeMap::new();
    let missing: Vec<u64> = w.keyframes.iter().map(|k| k.seq).filter(|s| !frames.contains_key(s)).collect();
    if !missing.is_empty() {
        let segments = list_segments(log_dir)?;
        for (_, path) in segments.iter().rev() {
            let mut r = SegmentReader::open(path, limits)?;
            while let Some(e) = r.next_event() {
                let OwnedEvent::Message { channel_id, sequence, log_time_ns, data, .. } = e else { continue };
                let seq = sequence as u64;
                if missing.contains(&seq) && r.channel(channel_id).is_some_and(|c| c.topic == Topic::CameraImage.name()) {
                    found.insert(seq, (data, log_time_ns));
                }
            }
            if missing.iter().all(|s| found.contains_key(s)) {
                break;
            }
        }
    }
    let (width, height) = (camera.width, camera.height);
    let mut out = Vec::with_capacity(w.keyframes.len());
    for k in &w.keyframes {
        let (data, t) = frames.get(&k.seq).or(found.get(&k.seq)).ok_or(WindowSeedError::FrameMissing { id: k.id, seq: k.seq })?;
        let frame = decode_frame(data, k.seq, *t).map_err(|source| WindowSeedError::Frame { id: k.id, seq: k.seq, source })?;
        if frame.image.width() != width || frame.image.height() != height {
            return Err(WindowSeedError::FrameSize { id: k.id, seq: k.seq, width: frame.image.width(), height: frame.image.height(), expected_width: width, expected_height: height });
        }
        let (gw, gh) = (k.inv_depth.width, k.inv_depth.height);
        if gw == 0 || gh == 0 || gw > width || gh > height {
            return Err(WindowSeedError::GridSize { id: k.id, grid_width: gw, grid_height: gh, width, height });
        }
        let cell = (width / gw).min(height / gh).max(1);
        let spread = |grid: Option<&PlaneF32>| {
            let mut p = PlaneF32::new(width, height);
            match grid {
                Some(g) => {
                    for y in 0..height {
                        let gy = (y / cell).min(gh - 1);
                        for x in 0..width {
                            p.data[y * width + x] = g.data[gy * gw + (x / cell).min(gw - 1)];
                        }
                    }
                }
                None => p.data.fill(f32::MAX),
            }
            p
        };
        let kf = Keyframe {
            index: k.id,
            t_ns: k.t_ns,
            image: frame.image.to_rgb8(),
            world_from_cam: k.world_from_cam,
            camera: *camera,
            inv_depth: spread(Some(&k.inv_depth)),
            inv_depth_variance: spread(k.variance()),
        };
        out.push((k.seq, kf));
    }
    Ok(out)
}

/// How a resumed run continues the recorded trajectory.
pub enum Relocalisation {
    /// The tracker holds the newest logged keyframes in the recorded frame and scale; the
    /// pipeline tracks `retrack` (logged frames after the newest keyframe) before the source.
    /// `keyframes` logged keyframes, or `frames` logged frames at their recorded poses (depth
    /// triangulated) when the log holds no keyframe.
    Seeded { keyframes: usize, frames: usize, newest_keyframe_seq: u64, retrack: Vec<Frame> },
    /// Stopped during its initialisation: the new tracker starts again at `from_seq`, the
    /// tracker's first frame (recorded at the identity), and the pipeline tracks `retrack`
    /// (every logged frame from there) before the source, so the initialisation is rebuilt as
    /// it was, in the recorded frame.
    Restarted { from_seq: u64, retrack: Vec<Frame> },
    /// Fallback: re-initialised on the last logged frames; `world_from_tracker` carries the new
    /// tracker's frame onto the recorded one. `why`: why the keyframes were not used.
    Aligned { world_from_tracker: Sim3, why: String },
    /// Nothing to relocalise with: the run continues in a new frame.
    NewFrame { why: String },
}

/// Recorded pose of `seq` and the motion per frame into it (from the recorded pose before it,
/// when both are there).
fn resume_point(poses: &BTreeMap<u64, (Se3, bool)>, seq: u64) -> Option<ResumePoint> {
    let &(pose, _) = poses.get(&seq)?;
    let velocity = match seq.checked_sub(1).and_then(|s| poses.get(&s)) {
        Some((prev, true)) => prev.inv_mul(&pose),
        _ => Se3::identity(),
    };
    Some(ResumePoint { seq, world_from_cam: pose, velocity })
}

/// Relocalises a new, empty `tracker` in the frame `state` recorded: seeded with the logged
/// keyframes when the log holds any, else by the fallback (see the module docs).
pub fn relocalise(tracker: &mut Tracker, state: &mut ResumeState) -> Result<Relocalisation, PipelineError> {
    tracker.reserve_segment_ids(state.next_segment);
    if state.restart && tracker.num_keyframes() == 0 {
        let from_seq = state.retrack.first().map_or(0, |f| f.seq);
        return Ok(Relocalisation::Restarted { from_seq, retrack: std::mem::take(&mut state.retrack) });
    }
    let why = if state.keyframes.is_empty() && state.seed_frames.is_empty() {
        "no whole keyframe in the log and fewer than 3 frames with measured poses or initialisation keyframes".to_string()
    } else {
        let seeds: Vec<SeedKeyframe<'_>> = state.keyframes.iter().map(|(seq, k)| SeedKeyframe { seq: *seq, keyframe: k }).collect();
        let frames: Vec<SeedFrame<'_>> = state.seed_frames.iter().map(|(frame, pose)| SeedFrame { frame, world_from_cam: *pose }).collect();
        let newest_keyframe_seq = frames.last().map(|f| f.frame.seq).or(seeds.last().map(|k| k.seq)).unwrap_or(0);
        // Straight on from the newest keyframe when its next frames were kept; otherwise from
        // the recorded pose before the first frame there is to track.
        let first = state.retrack.first().map(|f| f.seq).unwrap_or(state.last_seq + 1);
        let resume = if first == newest_keyframe_seq + 1 { None } else { resume_point(&state.poses, first - 1) };
        match tracker.seed(&TrackerSeed { keyframes: &seeds, frames: &frames, resume, next_keyframe_id: state.next_keyframe_id }) {
            Ok(()) => {
                let (keyframes, frames) = (seeds.len(), frames.len());
                return Ok(Relocalisation::Seeded { keyframes, frames, newest_keyframe_seq, retrack: std::mem::take(&mut state.retrack) });
            }
            Err(e) => format!("the logged keyframes did not seed the tracker: {e}"),
        }
    };
    tracing::warn!("resume: {why}; relocalising by re-initialisation");
    Ok(match align_by_reinitialising(tracker, state)? {
        Some(world_from_tracker) => Relocalisation::Aligned { world_from_tracker, why },
        None => Relocalisation::NewFrame { why },
    })
}

/// The fallback: tracks the recorded frames of `state` with `tracker` and returns the Sim(3)
/// from the tracker's frame to the recorded one, `None` when too few frames were tracked in
/// both runs.
fn align_by_reinitialising(tracker: &mut Tracker, state: &ResumeState) -> Result<Option<Sim3>, PipelineError> {
    // Per warm-up frame: the recorded pose, whether it was measured, and the new tracker's
    // live pose and state.
    let mut live: Vec<(u64, Se3, bool, Se3, bool)> = Vec::new();
    tracker.run_in_pool(|tracker| -> Result<(), PipelineError> {
        for (frame, recorded, recorded_measured) in &state.recent {
            let out = tracker.track(frame)?;
            let usable = !matches!(out.state, duv_track::TrackingState::Lost(_));
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
    match duv_core::align::umeyama(&src, &dst, true) {
        Ok(a) => Ok(Some(a)),
        Err(e) => {
            tracing::warn!("resume: relocalisation alignment failed: {e}");
            Ok(None)
        }
    }
}
