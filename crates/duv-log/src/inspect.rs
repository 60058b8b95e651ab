//! `duv inspect`: what a log folder (or one segment) holds: topics, counts, bytes and MB/s
//! against the run's log budget, time span, gaps in the camera stream, recovered and damaged
//! segments.
//!
//! A topic's bytes on disk: each chunk's stored (compressed) bytes shared among the topics of
//! its messages in proportion to their uncompressed bytes (chunks mix topics, so this is an
//! apportionment, exact for the topics that have chunks of their own: map checkpoints).

use super::reader::{OwnedEvent, ReadLimits, SegmentReader};
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
    /// Message bytes (uncompressed).
    pub bytes: u64,
    /// Bytes on disk (the topic's share of its chunks' stored bytes).
    pub stored_bytes: f64,
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
    /// The run's board (`duv.board` metadata): its name and `[log] max_mb_per_s`.
    pub board: Option<String>,
    pub budget_mb_per_s: Option<f64>,
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

    /// Seconds of log time the messages span.
    pub fn span_s(&self) -> f64 {
        self.span_ns().map_or(0.0, |(a, b)| (b - a) as f64 * 1e-9)
    }

    /// File bytes per second of log time, MB (10^6 bytes).
    pub fn mb_per_s(&self) -> Option<f64> {
        let span = self.span_s();
        (span > 0.0).then(|| self.segments.iter().map(|g| g.bytes).sum::<u64>() as f64 / 1e6 / span)
    }

    /// The human-readable summary `duv inspect` prints.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let total_bytes: u64 = self.segments.iter().map(|g| g.bytes).sum();
        let _ = writeln!(s, "{} segment(s), {} messages, {:.1} MiB, format {}", self.segments.len(), self.messages(), total_bytes as f64 / (1 << 20) as f64, self.formats.join(" + "));
        if let Some((a, b)) = self.span_ns() {
            let _ = writeln!(s, "time span {:.3} s .. {:.3} s ({:.3} s)", a as f64 * 1e-9, b as f64 * 1e-9, (b - a) as f64 * 1e-9);
        }
        let run_s = self.span_s();
        let _ = writeln!(s, "{:<22} {:<30} {:>9} {:>12} {:>12} {:>8} {:>10}", "topic", "schema", "messages", "bytes", "on disk", "MB/s", "rate Hz");
        for (name, t) in &self.topics {
            let span = (t.last_ns.saturating_sub(t.first_ns)) as f64 * 1e-9;
            let rate = if span > 0.0 && t.messages > 1 { (t.messages - 1) as f64 / span } else { 0.0 };
            let mb_s = if run_s > 0.0 { t.stored_bytes / 1e6 / run_s } else { 0.0 };
            let _ = writeln!(s, "{:<22} {:<30} {:>9} {:>12} {:>12.0} {:>8.3} {:>10.2}", name, t.schema, t.messages, t.bytes, t.stored_bytes, mb_s, rate);
        }
        let mb_s = self.mb_per_s();
        let total = match mb_s {
            Some(v) => format!("{v:.2} MB/s"),
            None => "MB/s unknown (under two messages)".to_string(),
        };
        let budget = match (self.budget_mb_per_s, mb_s) {
            (Some(b), Some(v)) if v <= b => format!("budget {b} MB/s ({}): under by {:.2} MB/s", self.board.as_deref().unwrap_or("?"), b - v),
            (Some(b), Some(v)) => format!("budget {b} MB/s ({}): OVER by {:.2} MB/s", self.board.as_deref().unwrap_or("?"), v - b),
            (Some(b), None) => format!("budget {b} MB/s"),
            (None, _) => format!("no budget (board {} has no [log] max_mb_per_s)", self.board.as_deref().unwrap_or("unknown")),
        };
        let _ = writeln!(s, "total {:.1} MB over {:.2} s: {total}; {budget}", total_bytes as f64 / 1e6, run_s);
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
        let mut r = SegmentReader::open(&file, limits)?;
        // The open chunk's messages: (topic, uncompressed bytes), shared out when it ends.
        let mut in_chunk: Vec<(String, u64)> = Vec::new();
        // Chunks read so far, their stored bytes, and the stored bytes of the chunk whose
        // messages are in `in_chunk`.
        let (mut seen_chunks, mut seen_stored, mut open_stored) = (0u64, 0u64, 0u64);
        let share = |summary: &mut LogSummary, in_chunk: &mut Vec<(String, u64)>, stored: u64| {
            let total: u64 = in_chunk.iter().map(|(_, b)| *b).sum();
            for (topic, b) in in_chunk.drain(..) {
                if let Some(t) = summary.topics.get_mut(&topic) {
                    t.stored_bytes += if total > 0 { stored as f64 * b as f64 / total as f64 } else { 0.0 };
                }
            }
        };
        while let Some(e) = r.next_event() {
            let o = r.outcome();
            if o.chunks != seen_chunks {
                // A new chunk was read: the messages before it belong to the previous one.
                share(&mut summary, &mut in_chunk, open_stored);
                open_stored = o.chunk_stored_bytes - seen_stored;
                (seen_chunks, seen_stored) = (o.chunks, o.chunk_stored_bytes);
            }
            match e {
                OwnedEvent::Schema(s) => {
                    schema_names.insert(s.id, s.name.clone());
                }
                OwnedEvent::Channel(_) => {}
                OwnedEvent::Message { channel_id, log_time_ns, data, .. } => {
                    let channel = r.channel(channel_id).expect("checked by the reader");
                    let t = summary.topics.entry(channel.topic.clone()).or_insert_with(|| TopicSummary {
                        schema: schema_names.get(&channel.schema_id).cloned().unwrap_or_else(|| channel.message_encoding.clone()),
                        first_ns: u64::MAX,
                        ..Default::default()
                    });
                    t.messages += 1;
                    t.bytes += data.len() as u64;
                    t.first_ns = t.first_ns.min(log_time_ns);
                    t.last_ns = t.last_ns.max(log_time_ns);
                    in_chunk.push((channel.topic.clone(), data.len() as u64));
                    if channel.topic == super::Topic::CameraImage.name() {
                        frame_times.push(log_time_ns);
                    }
                }
                OwnedEvent::Metadata { name, metadata } => {
                    if name == RECOVERED_METADATA {
                        recovered = Some(metadata.clone());
                    } else if name == "duv.board" && summary.board.is_none() {
                        if let Some(b) = metadata.get("toml").and_then(|t| duv_core::config::board::Board::parse(&file, t).ok()) {
                            summary.budget_mb_per_s = b.log.max_mb_per_s;
                            summary.board = Some(b.name);
                        }
                    }
                    if name != RECOVERED_METADATA && !summary.metadata_names.contains(&name) {
                        summary.metadata_names.push(name);
                    }
                }
            }
        }
        share(&mut summary, &mut in_chunk, open_stored);
        let outcome = r.outcome().clone();
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
