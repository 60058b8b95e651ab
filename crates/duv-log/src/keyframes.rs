//! Keyframes back from a log (`duv refine --mcap`): every keyframe the run logged, with its
//! image, pose, inverse depth and variance (the four `/keyframe/*` messages that share the
//! keyframe index as their sequence) and the camera of the `/camera/calibration` before it.
//!
//! The poses are the ones logged when each keyframe left tracking's BA window; corrections
//! made later (loop closure, the global BA) are in the run's `keyframes.txt`, not in the log.
//! The newest logged map checkpoint comes along ([`LogKeyframes::newest_map`]): with these
//! keyframes it restores the onboard map (`duv refine --from-logged-map`).
//! A damaged segment is read with its damaged ranges skipped, and a keyframe whose messages were cut apart by
//! it is left out and counted.

use super::reader::{OwnedEvent, ReadLimits, SegmentReader};
use super::schema::{decode_calibration, decode_frame, decode_payload, decode_plane_f32, decode_pose, Topic};
use super::{list_segments, LogError};
use duv_core::{ImageRgb8, Keyframe, PinholeCamera, PlaneF32, Se3, Timestamp};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// What [`read_log_keyframes`] found.
#[derive(Clone, Debug)]
pub struct LogKeyframes {
    /// Complete keyframes in log order, indices unique.
    pub keyframes: Vec<Keyframe>,
    /// The segment files read, in order.
    pub segments: Vec<PathBuf>,
    /// Per damaged segment: where and why reading it stopped.
    pub damage: Vec<String>,
    /// Keyframes left out, with why (messages missing after damage, unreadable, sizes that
    /// differ from the calibration).
    pub skipped: Vec<(u64, String)>,
    /// Keyframes whose index an earlier one already had (a resumed run's new tracker numbers
    /// from 0 again): given the next free index, (logged index, new index).
    pub renumbered: Vec<(u64, u64)>,
    /// The newest `/map/checkpoint` read (damaged ranges skipped), for `duv refine --from-logged-map`.
    pub newest_map: Option<LoggedMap>,
}

/// A map checkpoint as logged: the mapper's checkpoint bytes with the keyframes referring to
/// their `/keyframe/*` messages (`map::checkpoint::KeyframePixels::Referenced`).
#[derive(Clone, Debug)]
pub struct LoggedMap {
    pub log_time_ns: u64,
    pub segment: PathBuf,
    pub bytes: Vec<u8>,
}

/// The segment files of a log folder, a run's output folder (its `log/`), or one `.mcap` file.
pub fn log_files(path: &Path) -> Result<Vec<PathBuf>, LogError> {
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    if !path.is_dir() {
        return Err(LogError::NotALog { path: path.to_path_buf(), problem: "no such file or folder".into() });
    }
    let mut files = list_segments(path)?;
    if files.is_empty() {
        files = list_segments(&path.join("log"))?;
    }
    if files.is_empty() {
        return Err(LogError::NotALog { path: path.to_path_buf(), problem: "no segment-NNNNNN.mcap files here or in log/".into() });
    }
    Ok(files.into_iter().map(|(_, p)| p).collect())
}

/// The parts of one keyframe seen so far.
#[derive(Default)]
struct Partial {
    image: Option<(ImageRgb8, Timestamp)>,
    inv_depth: Option<PlaneF32>,
    variance: Option<PlaneF32>,
    pose: Option<Se3>,
    camera: Option<PinholeCamera>,
    problem: Option<String>,
}

/// Reads every complete keyframe of the log at `path` (see [`log_files`]). A log that holds
/// none is [`LogError::NoKeyframes`]; damage is reported in [`LogKeyframes::damage`].
pub fn read_log_keyframes(path: &Path, limits: ReadLimits) -> Result<LogKeyframes, LogError> {
    let mut keyframes = Vec::new();
    let mut out = for_each_log_keyframe(path, limits, |_| true, |kf| keyframes.push(kf))?;
    out.keyframes = keyframes;
    Ok(out)
}

/// Streams the complete keyframes of the log at `path` whose logged index `keep` accepts to
/// `on_keyframe`, in log order, one at a time (the others are not decoded): memory for one
/// keyframe, not the dive's. [`LogKeyframes::keyframes`] comes back empty; a log with no
/// keyframe `keep` accepts is [`LogError::NoKeyframes`].
pub fn for_each_log_keyframe(path: &Path, limits: ReadLimits, keep: impl Fn(u64) -> bool, mut on_keyframe: impl FnMut(Keyframe)) -> Result<LogKeyframes, LogError> {
    let segments = log_files(path)?;
    let mut out = LogKeyframes { keyframes: Vec::new(), segments: segments.clone(), damage: Vec::new(), skipped: Vec::new(), renumbered: Vec::new(), newest_map: None };
    let mut used: BTreeSet<u64> = BTreeSet::new();
    let mut delivered = 0usize;
    for file in &segments {
        let mut r = SegmentReader::open(file, limits)?;
        let mut camera: Option<PinholeCamera> = None;
        // By logged index; a keyframe's four messages follow one another, in one segment.
        let mut partial: BTreeMap<u64, Partial> = BTreeMap::new();
        // Keyframes already left out for an unreadable message: their later parts are ignored.
        let mut failed: BTreeSet<u64> = BTreeSet::new();
        while let Some(e) = r.next_event() {
            let OwnedEvent::Message { channel_id, sequence, log_time_ns, data, .. } = e else { continue };
            let Some(topic) = r.channel(channel_id).and_then(|c| Topic::from_name(&c.topic)) else { continue };
            let index = sequence as u64;
            let p = match topic {
                Topic::CameraCalibration => {
                    camera = decode_calibration(&data).ok().or(camera);
                    continue;
                }
                Topic::MapCheckpoint => {
                    // The checkpoint's bytes (the `data` of a `duv_msgs/msg/MapCheckpoint` in the
                    // ROS 2 format); one that does not parse is left for the mapper to reject.
                    let bytes = match decode_payload(&data) {
                        Ok(b) if b.len() != data.len() => b.to_vec(),
                        _ => data,
                    };
                    out.newest_map = Some(LoggedMap { log_time_ns, segment: file.clone(), bytes });
                    continue;
                }
                Topic::KeyframeImage | Topic::KeyframeInvDepth | Topic::KeyframeVariance | Topic::KeyframePose if !failed.contains(&index) && keep(index) => partial.entry(index).or_default(),
                _ => continue,
            };
            p.camera = p.camera.or(camera);
            let result = match topic {
                Topic::KeyframeImage => decode_frame(&data, index, log_time_ns).map(|f| p.image = Some((f.image.to_rgb8(), f.t_ns))),
                Topic::KeyframeInvDepth => decode_plane_f32(&data).map(|d| p.inv_depth = Some(d)),
                Topic::KeyframeVariance => decode_plane_f32(&data).map(|v| p.variance = Some(v)),
                Topic::KeyframePose => decode_pose(&data).map(|q| p.pose = Some(q)),
                _ => Ok(()),
            };
            if let Err(problem) = result {
                p.problem.get_or_insert(format!("{}: {problem}", topic.name()));
            }
            if (p.image.is_some() && p.inv_depth.is_some() && p.variance.is_some() && p.pose.is_some()) || p.problem.is_some() {
                if p.problem.is_some() {
                    failed.insert(index);
                }
                if let Some(p) = partial.remove(&index) {
                    if let Some(kf) = finish(index, p, &mut used, &mut out) {
                        delivered += 1;
                        on_keyframe(kf);
                    }
                }
            }
        }
        if let Some(d) = &r.outcome().damage {
            out.damage.push(format!("{}: {d}", file.display()));
        }
        for (index, p) in partial {
            let mut missing = Vec::new();
            for (have, name) in [(p.image.is_some(), "image"), (p.inv_depth.is_some(), "inv_depth"), (p.variance.is_some(), "variance"), (p.pose.is_some(), "pose")] {
                if !have {
                    missing.push(name);
                }
            }
            out.skipped.push((index, format!("{}: no /keyframe/{{{}}} message", file.display(), missing.join(","))));
        }
    }
    if delivered == 0 {
        let mut why = String::new();
        if !out.skipped.is_empty() {
            why.push_str(&format!("; {} incomplete or unreadable ({})", out.skipped.len(), out.skipped[0].1));
        }
        if let Some(d) = out.damage.first() {
            why.push_str(&format!("; damaged: {d}"));
        }
        return Err(LogError::NoKeyframes { path: path.to_path_buf(), segments: segments.len(), why });
    }
    Ok(out)
}

/// Turns the parts of keyframe `index` into a keyframe, or records why it is left out.
fn finish(index: u64, p: Partial, used: &mut BTreeSet<u64>, out: &mut LogKeyframes) -> Option<Keyframe> {
    if let Some(problem) = p.problem {
        out.skipped.push((index, problem));
        return None;
    }
    let Some(camera) = p.camera else {
        out.skipped.push((index, "no /camera/calibration before it".into()));
        return None;
    };
    let (Some((image, t_ns)), Some(inv_depth), Some(inv_depth_variance), Some(world_from_cam)) = (p.image, p.inv_depth, p.variance, p.pose) else {
        return None;
    };
    let mut kf = Keyframe { index, t_ns, image, world_from_cam, camera, inv_depth, inv_depth_variance };
    if !kf.is_consistent() {
        out.skipped.push((index, format!("image {}x{} or depth {}x{} differs from the calibration {}x{}", kf.image.width, kf.image.height, kf.inv_depth.width, kf.inv_depth.height, camera.width, camera.height)));
        return None;
    }
    if used.contains(&index) {
        let new = used.last().map_or(0, |m| m + 1);
        out.renumbered.push((index, new));
        kf.index = new;
    }
    used.insert(kf.index);
    Some(kf)
}

/// Every navigation sample a log holds (`/nav/sample`), sorted by time, from a log folder, a
/// run folder or one segment; damaged ranges are skipped, undecodable messages counted.
pub fn read_log_nav(path: &Path, limits: ReadLimits) -> Result<(Vec<duv_core::nav::NavSample>, usize), LogError> {
    let mut samples = Vec::new();
    let mut undecodable = 0;
    for file in log_files(path)? {
        let mut r = SegmentReader::open(&file, limits)?;
        while let Some(e) = r.next_event() {
            let OwnedEvent::Message { channel_id, data, .. } = e else { continue };
            if r.channel(channel_id).and_then(|c| Topic::from_name(&c.topic)) != Some(Topic::Nav) {
                continue;
            }
            match super::schema::decode_nav(&data) {
                Ok(n) => samples.push(n),
                Err(_) => undecodable += 1,
            }
        }
    }
    samples.sort_by_key(|s: &duv_core::nav::NavSample| s.t_ns);
    Ok((samples, undecodable))
}
