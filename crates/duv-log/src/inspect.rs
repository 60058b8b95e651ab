//! `duv inspect`: what a log folder (or one segment) holds: topics, counts, time span, gaps
//! in the camera stream, recovered and damaged segments.

use super::reader::{read_segment_events, ReadEvent, ReadLimits};
use super::recover::RECOVERED_METADATA;
use super::{list_segments, LogError};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Per-topic figures.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TopicSummary {
    pub schema: String,
    pub messages: u64,
    pub bytes: u64,
    pub first_ns: u64,
    pub last_ns: u64,
}

/// Per-segment figures.
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentSummary {
    pub path: PathBuf,
    pub bytes: u64,
    pub messages: u64,
    pub complete: bool,
    pub damage: Option<String>,
    /// The `duv.recovered` record: the segment was re-indexed after a crash.
    pub recovered: Option<BTreeMap<String, String>>,
}

/// A whole log.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LogSummary {
    pub segments: Vec<SegmentSummary>,
    pub topics: BTreeMap<String, TopicSummary>,
    /// Gaps in the camera stream longer than 3x its median frame interval: (from, to) in ns.
    pub gaps: Vec<(u64, u64)>,
    pub metadata_names: Vec<String>,
    /// The formats of the segments (`foxglove`, `ros2`), each once, in segment order.
    pub formats: Vec<String>,
}

impl LogSummary {
    pub fn span_ns(&self) -> Option<(u64, u64)> {
        let first = self.topics.values().map(|t| t.first_ns).min()?;
        let last = self.topics.values().map(|t| t.last_ns).max()?;
        Some((first, last))
    }

    pub fn messages(&self) -> u64 {
        self.topics.values().map(|t| t.messages).sum()
    }

    /// The human-readable summary `duv inspect` prints.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let total_bytes: u64 = self.segments.iter().map(|g| g.bytes).sum();
        let _ = writeln!(s, "{} segment(s), {} messages, {:.1} MiB, format {}", self.segments.len(), self.messages(), total_bytes as f64 / (1 << 20) as f64, self.formats.join(" + "));
        if let Some((a, b)) = self.span_ns() {
            let _ = writeln!(s, "time span {:.3} s .. {:.3} s ({:.3} s)", a as f64 * 1e-9, b as f64 * 1e-9, (b - a) as f64 * 1e-9);
        }
        let _ = writeln!(s, "{:<22} {:<30} {:>9} {:>12} {:>10}", "topic", "schema", "messages", "bytes", "rate Hz");
        for (name, t) in &self.topics {
            let span = (t.last_ns.saturating_sub(t.first_ns)) as f64 * 1e-9;
            let rate = if span > 0.0 && t.messages > 1 { (t.messages - 1) as f64 / span } else { 0.0 };
            let _ = writeln!(s, "{:<22} {:<30} {:>9} {:>12} {:>10.2}", name, t.schema, t.messages, t.bytes, rate);
        }
        if self.gaps.is_empty() {
            let _ = writeln!(s, "gaps in /camera/image: none");
        } else {
            let _ = writeln!(s, "gaps in /camera/image: {}", self.gaps.len());
            for (a, b) in self.gaps.iter().take(20) {
                let _ = writeln!(s, "  {:.3} s .. {:.3} s ({:.3} s)", *a as f64 * 1e-9, *b as f64 * 1e-9, (b - a) as f64 * 1e-9);
            }
        }
        for g in &self.segments {
            let state = match (&g.recovered, g.complete, &g.damage) {
                (Some(r), _, _) => format!("recovered ({} of {} bytes kept; {})", g.bytes, r.get("original_bytes").map(String::as_str).unwrap_or("?"), r.get("damage").map(String::as_str).unwrap_or("")),
                (None, true, None) => "complete".to_string(),
                (None, _, Some(d)) => format!("UNFINISHED or DAMAGED, read with damaged ranges skipped: {d}"),
                (None, false, None) => "UNFINISHED".to_string(),
            };
            let _ = writeln!(s, "{}: {} messages, {state}", g.path.display(), g.messages);
        }
        if !self.metadata_names.is_empty() {
            let _ = writeln!(s, "metadata: {}", self.metadata_names.join(", "));
        }
        s
    }
}

/// Summarises a log folder (every segment) or a single `.mcap` file.
pub fn inspect_log(path: &Path, limits: ReadLimits) -> Result<LogSummary, LogError> {
    let files: Vec<PathBuf> = if path.is_dir() {
        list_segments(path)?.into_iter().map(|(_, p)| p).collect()
    } else {
        vec![path.to_path_buf()]
    };
    if files.is_empty() {
        return Err(LogError::NotALog { path: path.to_path_buf(), problem: "no segment-NNNNNN.mcap files".into() });
    }
    let mut summary = LogSummary::default();
    let mut frame_times: Vec<u64> = Vec::new();
    for file in files {
        let mut schema_names: BTreeMap<u16, String> = BTreeMap::new();
        let mut recovered = None;
        // The MCAP header's profile: `ros2` for a ROS 2 bag, empty for the Foxglove format.
        let format = match super::bag::read_profile(&file).as_deref() {
            Ok(super::ros2::PROFILE) => "ros2 (a ROS 2 bag: CDR messages, metadata.yaml)",
            Ok("") => "foxglove",
            Ok(_) | Err(_) => "unknown",
        };
        if !summary.formats.iter().any(|f| f == format) {
            summary.formats.push(format.to_string());
        }
        let outcome = read_segment_events(&file, limits, |e| match e {
            ReadEvent::Schema(s) => {
                schema_names.insert(s.id, s.name.clone());
            }
            ReadEvent::Channel(_) => {}
            ReadEvent::Message(m) => {
                let t = summary.topics.entry(m.channel.topic.clone()).or_insert_with(|| TopicSummary {
                    schema: schema_names.get(&m.channel.schema_id).cloned().unwrap_or_else(|| m.channel.message_encoding.clone()),
                    first_ns: u64::MAX,
                    ..Default::default()
                });
                t.messages += 1;
                t.bytes += m.data.len() as u64;
                t.first_ns = t.first_ns.min(m.log_time_ns);
                t.last_ns = t.last_ns.max(m.log_time_ns);
                if m.channel.topic == super::Topic::CameraImage.name() {
                    frame_times.push(m.log_time_ns);
                }
            }
            ReadEvent::Metadata { name, metadata } => {
                if name == RECOVERED_METADATA {
                    recovered = Some(metadata.clone());
                } else if !summary.metadata_names.iter().any(|n| n == name) {
                    summary.metadata_names.push(name.to_string());
                }
            }
        })?;
        summary.segments.push(SegmentSummary { path: file, bytes: outcome.file_bytes, messages: outcome.messages, complete: outcome.complete, damage: outcome.damage, recovered });
    }
    frame_times.sort_unstable();
    frame_times.dedup();
    if frame_times.len() >= 3 {
        let mut d: Vec<u64> = frame_times.windows(2).map(|w| w[1] - w[0]).collect();
        d.sort_unstable();
        let median = d[d.len() / 2].max(1);
        summary.gaps = frame_times.windows(2).filter(|w| w[1] - w[0] > 3 * median).map(|w| (w[0], w[1])).collect();
    }
    Ok(summary)
}
