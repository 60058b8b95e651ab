//! A run folder is one dive, whatever number of processes worked on it (a power cut, a kill,
//! an operator's stop and a resume, a re-run). What each process logged is collected on the
//! next start ([`DiveHistory`], read by [`resume::prepare`](super::resume::prepare) in the same
//! pass as the rest of the log), and the output files are written from that history merged
//! with the current process's final poses ([`outputs`](super::outputs)): `trajectory.txt`,
//! `states.txt` and `keyframes.txt` always cover the whole dive.
//!
//! Each process writes a `duv.part` metadata record into every segment it opens (its part
//! number, process id, start time, how it started), so the log itself says which process wrote
//! what. `dive.json` in the run folder is the summary a user reads: the parts with their frames
//! and segments and how each ended, and whether the dive is finished (its source ended): a
//! finished dive started again is left as it is unless asked to continue.

use duv_core::{Se3, Timestamp};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Name of the metadata record each process writes into its segments.
pub const PART_METADATA: &str = "duv.part";
/// File name of the dive summary in the run folder.
pub const DIVE_FILE: &str = "dive.json";

/// A frame as the log recorded it.
#[derive(Clone, Debug, PartialEq)]
pub struct LoggedFrame {
    pub t_ns: Timestamp,
    /// In the recorded map frame.
    pub world_from_cam: Se3,
    /// The tracking state logged for it (`None` when its state record was lost).
    pub state: Option<String>,
    /// Why it had no measured pose yet, as logged (`init_small_flow 1.2 / 2.5`).
    pub note: Option<String>,
    /// The map segment it was tracked in, as logged.
    pub segment: Option<u32>,
}

/// One process's share of the dive.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DivePart {
    pub part: u32,
    pub pid: u32,
    pub started_unix_s: u64,
    /// How it started: `fresh`, or how it resumed.
    pub start: String,
    /// How it ended; `None` in the log (a process that was killed never says).
    pub end: Option<String>,
    /// Log segments it wrote.
    pub segments: Vec<u32>,
    /// Frames it logged a pose for.
    pub poses_logged: u64,
    pub first_seq: Option<u64>,
    pub last_seq: Option<u64>,
}

/// What the log holds about the dive so far.
#[derive(Clone, Debug, Default)]
pub struct DiveHistory {
    /// Every frame with a logged pose, by frame number (a frame logged again by a later
    /// process, tracked again on resume, takes the later pose).
    pub frames: BTreeMap<u64, LoggedFrame>,
    /// Every logged keyframe pose, by keyframe id (refined: keyframes are logged when they
    /// leave the BA window).
    pub keyframes: BTreeMap<u64, (Timestamp, Se3)>,
    /// The processes that wrote the log, by part number.
    pub parts: BTreeMap<u32, DivePart>,
    /// Every logged navigation sample (`/nav/sample`), in log order.
    pub nav: Vec<duv_core::nav::NavSample>,
}

impl DiveHistory {
    /// The part number the next process gets.
    pub fn next_part(&self) -> u32 {
        self.parts.keys().next_back().map_or(0, |p| p + 1)
    }

    /// Reads a segment's `duv.part` record (the part of a log written before parts were
    /// recorded is numbered from its first segment, marked `unrecorded`).
    pub fn open_segment(&mut self, segment: u32, metadata: Option<&BTreeMap<String, String>>) -> u32 {
        let parsed = metadata.and_then(|m| {
            let part = m.get("part")?.parse().ok()?;
            Some(DivePart {
                part,
                pid: m.get("pid").and_then(|v| v.parse().ok()).unwrap_or(0),
                started_unix_s: m.get("started_unix_s").and_then(|v| v.parse().ok()).unwrap_or(0),
                start: m.get("start").cloned().unwrap_or_default(),
                ..Default::default()
            })
        });
        let part = match parsed {
            Some(p) => {
                let n = p.part;
                self.parts.entry(n).or_insert(p);
                n
            }
            None => {
                let n = self.parts.keys().next_back().map_or(0, |p| p + 1);
                self.parts.entry(n).or_insert(DivePart { part: n, start: "unrecorded".into(), ..Default::default() });
                n
            }
        };
        let p = self.parts.get_mut(&part).expect("inserted above");
        if !p.segments.contains(&segment) {
            p.segments.push(segment);
        }
        part
    }

    pub fn add_pose(&mut self, part: u32, seq: u64, t_ns: Timestamp, world_from_cam: Se3) {
        let (state, note, segment) = self.frames.get(&seq).map_or((None, None, None), |f| (f.state.clone(), f.note.clone(), f.segment));
        self.frames.insert(seq, LoggedFrame { t_ns, world_from_cam, state, note, segment });
        if let Some(p) = self.parts.get_mut(&part) {
            p.poses_logged += 1;
            p.first_seq = Some(p.first_seq.map_or(seq, |s| s.min(seq)));
            p.last_seq = Some(p.last_seq.map_or(seq, |s| s.max(seq)));
        }
    }

    pub fn add_state(&mut self, seq: u64, state: &str, note: Option<String>, segment: u32) {
        if let Some(f) = self.frames.get_mut(&seq) {
            f.state = Some(state.to_string());
            f.note = note;
            f.segment = Some(segment);
        }
    }

    pub fn add_keyframe(&mut self, id: u64, t_ns: Timestamp, world_from_cam: Se3) {
        self.keyframes.insert(id, (t_ns, world_from_cam));
    }

    /// How each earlier part ended, from the previous `dive.json` (the parts it does not
    /// name were killed or lost power before writing it).
    pub fn take_ends(&mut self, previous: Option<&DiveRecord>) {
        for p in self.parts.values_mut() {
            p.end = previous.and_then(|r| r.parts.iter().find(|q| q.part == p.part)).and_then(|q| q.end.clone());
            if p.end.is_none() {
                p.end = Some("stopped without writing its outputs (killed or power lost)".into());
            }
        }
    }
}

/// `dive.json`: the dive as the last process that finished its outputs saw it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiveRecord {
    /// The source ended (a finished dive is not resumed unless asked to continue).
    pub finished: bool,
    /// How the last process ended.
    pub end: String,
    /// Frames of the dive (`states.txt`).
    pub frames: u64,
    /// Of them, frames with a pose estimate (every map segment's).
    #[serde(default)]
    pub frames_with_pose: u64,
    /// Frames with a pose estimate per map segment at the end, `[segment, frames]`: segment
    /// 0's are `trajectory.txt`, another's `trajectory-segment-N.txt` (segments that never
    /// merged into the first; their frames and scales are their own).
    #[serde(default)]
    pub map_segments: Vec<(u32, u64)>,
    pub first_seq: Option<u64>,
    pub last_seq: Option<u64>,
    /// Keyframes in `keyframes.txt`.
    pub keyframes: u64,
    /// Log segments when it was written: a later process that wrote more makes it stale.
    pub log_segments: u32,
    pub parts: Vec<DivePart>,
}

impl DiveRecord {
    /// The record in `out_dir`, `None` when there is none or it does not parse (an older run
    /// folder, a torn write: the dive is then rebuilt from the log).
    pub fn load(out_dir: &Path) -> Option<DiveRecord> {
        let text = std::fs::read_to_string(out_dir.join(DIVE_FILE)).ok()?;
        match serde_json::from_str(&text) {
            Ok(r) => Some(r),
            Err(e) => {
                tracing::warn!("{}: not read ({e}); the dive is rebuilt from the log", out_dir.join(DIVE_FILE).display());
                None
            }
        }
    }

    pub fn write(&self, out_dir: &Path) -> Result<(), duv_core::io::IoError> {
        let json = serde_json::to_string_pretty(self).unwrap_or_default();
        duv_core::io::write_atomic(&out_dir.join(DIVE_FILE), json.as_bytes())
    }
}

/// Seconds since the Unix epoch (0 when the clock is before it).
pub fn unix_now_s() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

/// The `duv.part` record of a process.
pub fn part_metadata(part: u32, start: &str) -> BTreeMap<String, String> {
    [
        ("part".to_string(), part.to_string()),
        ("pid".to_string(), std::process::id().to_string()),
        ("started_unix_s".to_string(), unix_now_s().to_string()),
        ("start".to_string(), start.to_string()),
    ]
    .into_iter()
    .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_come_from_segment_metadata_and_later_poses_win() {
        let mut h = DiveHistory::default();
        let p0 = h.open_segment(0, Some(&part_metadata(0, "fresh")));
        h.add_pose(p0, 0, Timestamp::from_ns(0), Se3::identity());
        h.add_state(0, "initializing", Some("init_small_flow 1.2 <= 2.5".into()), 0);
        h.add_pose(p0, 1, Timestamp::from_ns(10), Se3::identity());
        let p1 = h.open_segment(1, Some(&part_metadata(1, "resumed")));
        let moved = Se3::from_parts(nalgebra::Translation3::new(1.0, 0.0, 0.0), nalgebra::UnitQuaternion::identity());
        h.add_pose(p1, 1, Timestamp::from_ns(10), moved);
        h.add_pose(p1, 2, Timestamp::from_ns(20), moved);
        assert_eq!((p0, p1), (0, 1));
        assert_eq!(h.frames.len(), 3);
        assert_eq!(h.frames[&1].world_from_cam, moved);
        assert_eq!(h.frames[&0].state.as_deref(), Some("initializing"));
        assert_eq!(h.frames[&0].note.as_deref(), Some("init_small_flow 1.2 <= 2.5"));
        assert_eq!((h.parts[&0].first_seq, h.parts[&0].last_seq, h.parts[&0].poses_logged), (Some(0), Some(1), 2));
        assert_eq!((h.parts[&1].first_seq, h.parts[&1].last_seq), (Some(1), Some(2)));
        assert_eq!(h.next_part(), 2);
        // A segment without the record (an older log) is a part of its own.
        let p2 = h.open_segment(2, None);
        assert_eq!((p2, h.parts[&2].start.as_str()), (2, "unrecorded"));
        let previous = DiveRecord { parts: vec![DivePart { part: 0, end: Some("stopped by signal 15".into()), ..Default::default() }], ..Default::default() };
        h.take_ends(Some(&previous));
        assert_eq!(h.parts[&0].end.as_deref(), Some("stopped by signal 15"));
        assert!(h.parts[&1].end.as_deref().unwrap().contains("killed"));
    }
}
