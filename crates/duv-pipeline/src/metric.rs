//! Metric outputs (issue 40): with navigation input (a dataset's `nav.csv`, `sim:...,nav=on`),
//! the similarity from the dive's map frame to metres
//! ([`duv_track::metric::estimate_metric_alignment`] over every tracked frame of the dive and
//! the tracker's keyframes) is applied once, when the outputs are written: `trajectory.txt`,
//! `keyframes.txt`, the keyframes' depth, `map.ply` and `medium.json`. `metric.json` says which
//! unit the run folder is in, and how the scale was found; without navigation input (or when no
//! sensor observed the scale) it says the outputs are in map units and why.

use duv_core::nav::NavSample;
use duv_core::{PlaneF32, Sim3};
use duv_track::metric::{estimate_metric_alignment, MapFrame, MapKeyframe, MetricAlignment, MetricOptions, ScaleEstimate};
use duv_track::{FinalTrajectory, Tracker, TrackingState};
use std::path::Path;

use super::dive::DiveHistory;

/// What `metric.json` records.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct MetricRecord {
    /// `"m"` when the outputs are metric, `"map"` (the tracker's unscaled units) otherwise.
    pub length_unit: String,
    /// Why the outputs are in map units (no navigation input, no sensor observed the scale).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub why_not_metric: Option<String>,
    /// Metres per map unit and its one-sigma uncertainty.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metres_per_map_unit: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metres_per_map_unit_sigma: Option<f64>,
    /// Each sensor's own scale estimate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_depth: Option<ScaleEstimate>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_altitude: Option<ScaleEstimate>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub from_velocity: Option<ScaleEstimate>,
    /// Frames whose attitude set gravity, and their RMS tilt against it (deg).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attitudes: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilt_rms_deg: Option<f64>,
    /// `metric_from_map`: scale, rotation (x, y, z, w) and translation (m), so the logged
    /// (map-unit) poses can be converted too.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metric_from_map: Option<SimilarityRecord>,
    /// Navigation samples the source gave.
    pub nav_samples: usize,
    /// Map segments that never merged into segment 0 by sight, placed in the world (metres)
    /// by the navigation ([`join_segments`]): their poses are in `trajectory.txt`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub joined_segments: Vec<JoinedSegmentRecord>,
    /// The other segments (`trajectory-segment-N.txt`, their own frame and scale), and why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub segments_not_joined: Vec<SegmentNotJoined>,
}

#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct SimilarityRecord {
    pub scale: f64,
    pub rotation_xyzw: [f64; 4],
    pub translation_m: [f64; 3],
}

impl MetricRecord {
    /// Map units, for `why`.
    pub fn map_units(why: impl Into<String>, nav_samples: usize) -> Self {
        MetricRecord {
            length_unit: "map".into(),
            why_not_metric: Some(why.into()),
            metres_per_map_unit: None,
            metres_per_map_unit_sigma: None,
            from_depth: None,
            from_altitude: None,
            from_velocity: None,
            attitudes: None,
            tilt_rms_deg: None,
            metric_from_map: None,
            nav_samples,
            joined_segments: Vec::new(),
            segments_not_joined: Vec::new(),
        }
    }

    /// Metres, from `a`.
    pub fn metric(a: &MetricAlignment, nav_samples: usize) -> Self {
        let q = a.metric_from_map.isometry.rotation;
        let t = a.metric_from_map.isometry.translation.vector;
        MetricRecord {
            length_unit: "m".into(),
            why_not_metric: None,
            metres_per_map_unit: Some(a.scale.metres_per_unit),
            metres_per_map_unit_sigma: Some(a.scale.sigma),
            from_depth: a.from_depth,
            from_altitude: a.from_altitude,
            from_velocity: a.from_velocity,
            attitudes: Some(a.attitudes),
            tilt_rms_deg: Some(a.tilt_rms_deg),
            metric_from_map: Some(SimilarityRecord { scale: a.metric_from_map.scaling(), rotation_xyzw: [q.i, q.j, q.k, q.w], translation_m: [t.x, t.y, t.z] }),
            nav_samples,
            joined_segments: Vec::new(),
            segments_not_joined: Vec::new(),
        }
    }

    /// Writes `OUT/metric.json`.
    pub fn write(&self, out: &Path) -> Result<(), duv_core::io::IoError> {
        let path = out.join("metric.json");
        let text = serde_json::to_string_pretty(self).map_err(|e| duv_core::io::IoError::invalid(&path, e.to_string()))?;
        duv_core::io::write_atomic(&path, text.as_bytes())
    }

    /// Reads `DIR/metric.json`; `None` when the folder has none (a run from before metric
    /// outputs, or not a run folder).
    pub fn read(dir: &Path) -> Result<Option<Self>, duv_core::io::IoError> {
        let path = dir.join("metric.json");
        match std::fs::read_to_string(&path) {
            Ok(text) => serde_json::from_str(&text).map(Some).map_err(|e| duv_core::io::IoError::invalid(&path, e.to_string())),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(duv_core::io::IoError::file(&path, e)),
        }
    }

    /// One line for the operator.
    pub fn summary(&self) -> String {
        match (self.metres_per_map_unit, &self.why_not_metric) {
            (Some(s), _) => {
                let part = |name: &str, e: &Option<ScaleEstimate>| e.map(|e| format!(" {name} {:.4}±{:.4} ({} used)", e.metres_per_unit, e.sigma, e.used));
                let sensors: String = [part("depth", &self.from_depth), part("altitude", &self.from_altitude), part("velocity", &self.from_velocity)].into_iter().flatten().collect();
                let mut line = format!(
                    "outputs in metres: 1 map unit = {s:.4} m ± {:.4} (from{sensors}); gravity from {} attitudes, tilt rms {:.2} deg",
                    self.metres_per_map_unit_sigma.unwrap_or(f64::NAN),
                    self.attitudes.unwrap_or(0),
                    self.tilt_rms_deg.unwrap_or(f64::NAN)
                );
                for j in &self.joined_segments {
                    line.push_str(&format!(
                        "; map segment {} joined by navigation ({} frames, 1 map unit = {:.4} m ± {:.4}, {:.2} m dead-reckoned over {:.1} s from segment {})",
                        j.segment, j.frames, j.metres_per_map_unit, j.metres_per_map_unit_sigma, j.dead_reckoned_m, j.gap_s, j.from_segment
                    ));
                }
                for n in &self.segments_not_joined {
                    line.push_str(&format!("; map segment {} not joined: {}", n.segment, n.why));
                }
                line
            }
            (None, why) => format!("outputs in map units (scale unknown): {}", why.as_deref().unwrap_or("no navigation input")),
        }
    }
}

/// The dive's map-to-metric similarity: every tracked (or relocalised) frame of the dive, this
/// process's over the logged history, and the tracker's live keyframes (their depth on the
/// tracker's grid, moved into the dive's frame by `world_from_tracker`); map segment 0's only
/// (the dive's world frame: another segment's poses are in a frame and scale of their own, see
/// [`join_segments`]).
pub fn estimate_for_dive(nav: &[NavSample], fin: &FinalTrajectory, history: Option<&DiveHistory>, tracker: &Tracker, world_from_tracker: Option<&Sim3>) -> Result<MetricAlignment, duv_track::metric::MetricError> {
    estimate_for_segment(nav, &segment_frames(fin, history, 0), tracker, world_from_tracker, 0)
}

/// The tracked (or relocalised) frames of map `segment`, this process's over the logged
/// history, in time order.
fn segment_frames(fin: &FinalTrajectory, history: Option<&DiveHistory>, segment: u32) -> Vec<MapFrame> {
    let mut frames: std::collections::BTreeMap<i64, MapFrame> = std::collections::BTreeMap::new();
    if let Some(h) = history {
        for f in h.frames.values() {
            if matches!(f.state.as_deref(), Some("tracking") | Some("relocalised")) && f.segment.unwrap_or(0) == segment {
                frames.insert(f.t_ns.t_ns(), MapFrame { t_ns: f.t_ns, world_from_cam: f.world_from_cam });
            }
        }
    }
    for ((pose, state), s) in fin.frames.iter().zip(&fin.states).zip(&fin.segments) {
        if matches!(state, TrackingState::Tracking | TrackingState::Relocalised) && *s == segment {
            frames.insert(pose.t_ns.t_ns(), MapFrame { t_ns: pose.t_ns, world_from_cam: pose.world_from_cam });
        }
    }
    frames.into_values().collect()
}

/// The alignment of map `segment` from its `frames` and the tracker's live keyframes of it.
fn estimate_for_segment(nav: &[NavSample], frames: &[MapFrame], tracker: &Tracker, world_from_tracker: Option<&Sim3>, segment: u32) -> Result<MetricAlignment, duv_track::metric::MetricError> {
    let grid = *tracker.depth_camera();
    // Depth scales with the alignment: inverse depth by 1/s.
    let s = world_from_tracker.map_or(1.0, |a| a.scaling()) as f32;
    let scaled: Vec<(duv_core::Timestamp, duv_core::Se3, PlaneF32)> = tracker
        .keyframes()
        .filter(|k| s != 1.0 && k.segment == segment)
        .map(|k| {
            let mut inv = k.inv_depth.clone();
            inv.data.iter_mut().for_each(|d| *d /= s);
            (k.t_ns, duv_core::pose::sim3_apply_to_pose(world_from_tracker.expect("s != 1 only with an alignment"), &k.world_from_cam), inv)
        })
        .collect();
    // Without a resume's scale the tracker's own planes are read as they are (no copies).
    let keyframes: Vec<MapKeyframe<'_>> = if s != 1.0 {
        scaled.iter().map(|(t_ns, pose, inv)| MapKeyframe { t_ns: *t_ns, world_from_cam: *pose, inv_depth: inv, camera: grid }).collect()
    } else {
        tracker
            .keyframes()
            .filter(|k| k.segment == segment)
            .map(|k| MapKeyframe { t_ns: k.t_ns, world_from_cam: world_from_tracker.map_or(k.world_from_cam, |a| duv_core::pose::sim3_apply_to_pose(a, &k.world_from_cam)), inv_depth: k.inv_depth, camera: grid })
            .collect()
    };
    estimate_metric_alignment(frames, &keyframes, nav, &MetricOptions::default())
}

/// The longest gap (s) between a map segment and the frame before it that dead reckoning
/// bridges: the DVL's scale error (about 1 %) and the AHRS's heading drift grow with it.
pub const MAX_JOIN_GAP_S: f64 = 120.0;

/// The longest hole (s) in the DVL velocity (with an attitude) that dead reckoning accepts.
pub const MAX_DVL_HOLE_S: f64 = 1.0;

/// A map segment that never merged into segment 0 by sight, placed in the dive's metric world
/// by the navigation: its own alignment (gravity and heading from the attitude, scale from the
/// depth sensor, altimeter or DVL, height from the depth sensor) and, for its horizontal
/// position, the DVL dead-reckoned across the gap from the last frame placed before it.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct JoinedSegmentRecord {
    pub segment: u32,
    /// Its tracked frames the alignment used.
    pub frames: usize,
    pub metres_per_map_unit: f64,
    pub metres_per_map_unit_sigma: f64,
    /// The segment of the frame it was dead-reckoned from, the gap (s) and the horizontal
    /// distance (m) the DVL covered across it.
    pub from_segment: u32,
    pub gap_s: f64,
    pub dead_reckoned_m: f64,
    pub metric_from_map: SimilarityRecord,
}

/// A map segment that stays in its own frame and scale, and why.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct SegmentNotJoined {
    pub segment: u32,
    pub why: String,
}

/// Places every map segment other than 0 in the dive's metric world (`world`, segment 0's
/// alignment) where the navigation can ([`JoinedSegmentRecord`]), in the order the segments
/// start; the others, with why. A segment joined this way is in metres and in the world frame,
/// so its poses go to `trajectory.txt`; it is not merged into the map (the mapper never mixes
/// segments that did not merge by sight).
pub fn join_segments(nav: &[NavSample], fin: &FinalTrajectory, history: Option<&DiveHistory>, tracker: &Tracker, world_from_tracker: Option<&Sim3>, world: &Sim3) -> (Vec<(Sim3, JoinedSegmentRecord)>, Vec<SegmentNotJoined>) {
    let mut ids: Vec<u32> = fin.segments.iter().copied().chain(history.into_iter().flat_map(|h| h.frames.values().filter_map(|f| f.segment))).filter(|s| *s != 0).collect();
    ids.sort_unstable();
    ids.dedup();
    // (first frame time, segment, its frames), in the order the segments start.
    let mut segments: Vec<(i64, u32, Vec<MapFrame>)> = ids.into_iter().map(|s| (segment_frames(fin, history, s), s)).filter_map(|(f, s)| Some((f.first()?.t_ns.t_ns(), s, f))).collect();
    segments.sort_by_key(|s| s.0);
    // (time, segment, metric position) of every frame placed so far.
    let mut placed: Vec<(i64, u32, nalgebra::Vector3<f64>)> = segment_frames(fin, history, 0).iter().map(|f| (f.t_ns.t_ns(), 0, (world * nalgebra::Point3::from(f.world_from_cam.translation.vector)).coords)).collect();
    let (mut joined, mut not) = (Vec::new(), Vec::new());
    let (max_dt_ns, max_hole_ns) = (MetricOptions::default().max_dt_ns, (MAX_DVL_HOLE_S * 1e9) as i64);
    for (t_first, segment, frames) in segments {
        let Some(&(t_from, from_segment, p_from)) = placed.iter().filter(|p| p.0 < t_first).max_by_key(|p| p.0) else {
            not.push(SegmentNotJoined { segment, why: "no frame placed in the world before it to dead-reckon from".into() });
            continue;
        };
        let gap_s = (t_first - t_from) as f64 * 1e-9;
        if gap_s > MAX_JOIN_GAP_S {
            not.push(SegmentNotJoined { segment, why: format!("a gap of {gap_s:.1} s since the last placed frame (dead reckoning bridges at most {MAX_JOIN_GAP_S} s)") });
            continue;
        }
        let dr = match duv_track::metric::dead_reckon(nav, duv_core::Timestamp::from_ns(t_from), frames[0].t_ns, max_dt_ns, max_hole_ns) {
            Ok(d) => d,
            Err(e) => {
                not.push(SegmentNotJoined { segment, why: e.to_string() });
                continue;
            }
        };
        let a = match estimate_for_segment(nav, &frames, tracker, world_from_tracker, segment) {
            Ok(a) => a,
            Err(e) => {
                not.push(SegmentNotJoined { segment, why: e.to_string() });
                continue;
            }
        };
        // The alignment puts the segment's first frame at x = y = 0: move it to where the DVL
        // says it was (its height stays the depth sensor's).
        let mut m = a.metric_from_map;
        m.isometry.translation.vector.x += p_from.x + dr.x;
        m.isometry.translation.vector.y += p_from.y + dr.y;
        placed.extend(frames.iter().map(|f| (f.t_ns.t_ns(), segment, (m * nalgebra::Point3::from(f.world_from_cam.translation.vector)).coords)));
        let q = m.isometry.rotation;
        let t = m.isometry.translation.vector;
        joined.push((
            m,
            JoinedSegmentRecord {
                segment,
                frames: frames.len(),
                metres_per_map_unit: a.scale.metres_per_unit,
                metres_per_map_unit_sigma: a.scale.sigma,
                from_segment,
                gap_s,
                dead_reckoned_m: dr.xy().norm(),
                metric_from_map: SimilarityRecord { scale: m.scaling(), rotation_xyzw: [q.i, q.j, q.k, q.w], translation_m: [t.x, t.y, t.z] },
            },
        ));
    }
    (joined, not)
}
