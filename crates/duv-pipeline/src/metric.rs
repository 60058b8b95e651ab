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
                format!(
                    "outputs in metres: 1 map unit = {s:.4} m ± {:.4} (from{sensors}); gravity from {} attitudes, tilt rms {:.2} deg",
                    self.metres_per_map_unit_sigma.unwrap_or(f64::NAN),
                    self.attitudes.unwrap_or(0),
                    self.tilt_rms_deg.unwrap_or(f64::NAN)
                )
            }
            (None, why) => format!("outputs in map units (scale unknown): {}", why.as_deref().unwrap_or("no navigation input")),
        }
    }
}

/// The dive's map-to-metric similarity: every tracked (or relocalised) frame of the dive, this
/// process's over the logged history, and the tracker's live keyframes (their depth on the
/// tracker's grid, moved into the dive's frame by `world_from_tracker`); map segment 0's only
/// (the dive's world frame: another segment's poses are in a frame and scale of their own).
pub fn estimate_for_dive(nav: &[NavSample], fin: &FinalTrajectory, history: Option<&DiveHistory>, tracker: &Tracker, world_from_tracker: Option<&Sim3>) -> Result<MetricAlignment, duv_track::metric::MetricError> {
    let mut frames: std::collections::BTreeMap<i64, MapFrame> = std::collections::BTreeMap::new();
    if let Some(h) = history {
        for f in h.frames.values() {
            if matches!(f.state.as_deref(), Some("tracking") | Some("relocalised")) && f.segment.unwrap_or(0) == 0 {
                frames.insert(f.t_ns.t_ns(), MapFrame { t_ns: f.t_ns, world_from_cam: f.world_from_cam });
            }
        }
    }
    for ((pose, state), segment) in fin.frames.iter().zip(&fin.states).zip(&fin.segments) {
        if matches!(state, TrackingState::Tracking | TrackingState::Relocalised) && *segment == 0 {
            frames.insert(pose.t_ns.t_ns(), MapFrame { t_ns: pose.t_ns, world_from_cam: pose.world_from_cam });
        }
    }
    let frames: Vec<MapFrame> = frames.into_values().collect();
    let grid = *tracker.depth_camera();
    // Depth scales with the alignment: inverse depth by 1/s.
    let s = world_from_tracker.map_or(1.0, |a| a.scaling()) as f32;
    let scaled: Vec<(duv_core::Timestamp, duv_core::Se3, PlaneF32)> = tracker
        .keyframes()
        .filter(|k| s != 1.0 && k.segment == 0)
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
            .filter(|k| k.segment == 0)
            .map(|k| MapKeyframe { t_ns: k.t_ns, world_from_cam: world_from_tracker.map_or(k.world_from_cam, |a| duv_core::pose::sim3_apply_to_pose(a, &k.world_from_cam)), inv_depth: k.inv_depth, camera: grid })
            .collect()
    };
    estimate_metric_alignment(&frames, &keyframes, nav, &MetricOptions::default())
}
