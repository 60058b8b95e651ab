//! The rosbag2 side of a log written in the ROS 2 format: `metadata.yaml` in the log folder
//! (what `ros2 bag` and the `rosbags` package open first), built from the segments' MCAP
//! summaries and written atomically (temporary file, fsync, rename). The writer rewrites it
//! whenever a segment closes, recovery after a crash once it has re-indexed the segments, so
//! a folder cut by a power loss opens as a bag again after the next start.
//!
//! Only segments whose MCAP header has the profile `ros2` are listed: a folder where a resumed
//! run switched formats is a bag of its ROS 2 segments.

use super::chunked::MAGIC;
use super::reader::{read_segment_events, ReadEvent, ReadLimits};
use super::files::{is_finished, sync_dir};
use super::{list_segments, ros2, LogError};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{Read, Seek, SeekFrom, Write as _};
use std::path::{Path, PathBuf};

/// The bag's index file in the log folder.
pub const METADATA_FILE: &str = "metadata.yaml";

/// The rosbag2 metadata version written (7 added `type_description_hash`, 8 `ros_distro`;
/// QoS profiles stay a YAML string, as before version 9).
pub const BAG_VERSION: u32 = 8;

/// Records longer than this in a segment's summary are not read (a damaged length).
const SUMMARY_LIMIT: u64 = 64 << 20;

/// The MCAP header profile of a segment (`""` for the Foxglove format, `ros2`).
pub fn read_profile(path: &Path) -> Result<String, LogError> {
    let io = |source| LogError::Io { path: path.to_path_buf(), source };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let mut head = [0u8; 8 + 9 + 4];
    f.read_exact(&mut head).map_err(io)?;
    let not_log = |problem: &str| LogError::NotALog { path: path.to_path_buf(), problem: problem.into() };
    if head[..8] != MAGIC || head[8] != 0x01 {
        return Err(not_log("no MCAP magic and header record"));
    }
    let len = u32::from_le_bytes(head[17..21].try_into().expect("4 bytes")) as usize;
    if len > 4096 {
        return Err(not_log("header profile longer than 4096 bytes"));
    }
    let mut profile = vec![0u8; len];
    f.read_exact(&mut profile).map_err(io)?;
    String::from_utf8(profile).map_err(|_| not_log("header profile is not UTF-8"))
}

/// What one segment holds, per (topic, type).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SegmentCounts {
    pub file: String,
    pub messages: u64,
    pub first_ns: u64,
    pub last_ns: u64,
    pub topics: BTreeMap<(String, String), u64>,
}

/// The counts of a finished segment from its summary (schemas, channels, statistics); of an
/// unfinished one by reading it with damaged ranges skipped.
pub fn segment_counts(path: &Path) -> Result<SegmentCounts, LogError> {
    let file = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
    if is_finished(path)? {
        if let Some(c) = summary_counts(path, &file)? {
            return Ok(c);
        }
    }
    let mut c = SegmentCounts { file, first_ns: u64::MAX, ..Default::default() };
    let mut schemas: BTreeMap<u16, String> = BTreeMap::new();
    read_segment_events(path, ReadLimits::default(), |e| match e {
        ReadEvent::Schema(s) => {
            schemas.insert(s.id, s.name.clone());
        }
        ReadEvent::Message(m) => {
            let ty = schemas.get(&m.channel.schema_id).cloned().unwrap_or_default();
            *c.topics.entry((m.channel.topic.clone(), ty)).or_default() += 1;
            c.messages += 1;
            c.first_ns = c.first_ns.min(m.log_time_ns);
            c.last_ns = c.last_ns.max(m.log_time_ns);
        }
        _ => {}
    })?;
    if c.messages == 0 {
        c.first_ns = 0;
    }
    Ok(c)
}

/// Counts from the summary section; `None` when the file has no usable summary.
fn summary_counts(path: &Path, file: &str) -> Result<Option<SegmentCounts>, LogError> {
    let io = |source| LogError::Io { path: path.to_path_buf(), source };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    // Footer: opcode, length 20, summary start, summary offset start, CRC; then the magic.
    let footer_at = match len.checked_sub(8 + 29) {
        Some(a) => a,
        None => return Ok(None),
    };
    f.seek(SeekFrom::Start(footer_at)).map_err(io)?;
    let mut footer = [0u8; 29];
    f.read_exact(&mut footer).map_err(io)?;
    let summary_start = u64::from_le_bytes(footer[9..17].try_into().expect("8 bytes"));
    if footer[0] != 0x02 || summary_start == 0 || summary_start >= footer_at || footer_at - summary_start > SUMMARY_LIMIT {
        return Ok(None);
    }
    let mut summary = vec![0u8; (footer_at - summary_start) as usize];
    f.seek(SeekFrom::Start(summary_start)).map_err(io)?;
    f.read_exact(&mut summary).map_err(io)?;
    let mut schemas: BTreeMap<u16, String> = BTreeMap::new();
    let mut channels: BTreeMap<u16, (String, String)> = BTreeMap::new();
    let mut stats = None;
    let mut p = 0usize;
    while p + 9 <= summary.len() {
        let op = summary[p];
        let n = u64::from_le_bytes(summary[p + 1..p + 9].try_into().expect("8 bytes"));
        let Some(body) = usize::try_from(n).ok().and_then(|n| summary.get(p + 9..p + 9 + n)) else { return Ok(None) };
        match mcap::parse_record(op, body) {
            Ok(mcap::records::Record::Schema { header, .. }) => {
                schemas.insert(header.id, header.name.clone());
            }
            Ok(mcap::records::Record::Channel(c)) => {
                channels.insert(c.id, (c.topic.clone(), schemas.get(&c.schema_id).cloned().unwrap_or_default()));
            }
            Ok(mcap::records::Record::Statistics(s)) => stats = Some(s),
            _ => {}
        }
        p += 9 + body.len();
    }
    let Some(s) = stats else { return Ok(None) };
    let mut c = SegmentCounts { file: file.to_string(), messages: s.message_count, first_ns: s.message_start_time, last_ns: s.message_end_time, topics: BTreeMap::new() };
    for (id, count) in &s.channel_message_counts {
        let Some(key) = channels.get(id) else { return Ok(None) };
        *c.topics.entry(key.clone()).or_default() += count;
    }
    Ok(Some(c))
}

/// The `metadata.yaml` text for these segments.
pub fn metadata_yaml(segments: &[SegmentCounts]) -> String {
    let with_messages: Vec<&SegmentCounts> = segments.iter().filter(|s| s.messages > 0).collect();
    let first = with_messages.iter().map(|s| s.first_ns).min().unwrap_or(0);
    let last = with_messages.iter().map(|s| s.last_ns).max().unwrap_or(0);
    let mut topics: BTreeMap<&(String, String), u64> = BTreeMap::new();
    for s in segments {
        for (k, n) in &s.topics {
            *topics.entry(k).or_default() += n;
        }
    }
    let total: u64 = segments.iter().map(|s| s.messages).sum();
    let mut y = String::new();
    let _ = writeln!(y, "rosbag2_bagfile_information:");
    let _ = writeln!(y, "  version: {BAG_VERSION}");
    let _ = writeln!(y, "  storage_identifier: mcap");
    let _ = writeln!(y, "  duration:\n    nanoseconds: {}", last - first);
    let _ = writeln!(y, "  starting_time:\n    nanoseconds_since_epoch: {first}");
    let _ = writeln!(y, "  message_count: {total}");
    if topics.is_empty() {
        let _ = writeln!(y, "  topics_with_message_count: []");
    } else {
        let _ = writeln!(y, "  topics_with_message_count:");
    }
    for ((name, ty), n) in topics {
        let _ = writeln!(y, "    - topic_metadata:");
        let _ = writeln!(y, "        name: {}", quoted(name));
        let _ = writeln!(y, "        type: {}", quoted(ty));
        let _ = writeln!(y, "        serialization_format: {}", ros2::MESSAGE_ENCODING);
        let _ = writeln!(y, "        offered_qos_profiles: \"\"");
        let _ = writeln!(y, "        type_description_hash: \"\"");
        let _ = writeln!(y, "      message_count: {n}");
    }
    let _ = writeln!(y, "  compression_format: \"\"");
    let _ = writeln!(y, "  compression_mode: \"\"");
    if segments.is_empty() {
        let _ = writeln!(y, "  relative_file_paths: []\n  files: []");
    } else {
        let _ = writeln!(y, "  relative_file_paths:");
        for s in segments {
            let _ = writeln!(y, "    - {}", quoted(&s.file));
        }
        let _ = writeln!(y, "  files:");
        for s in segments {
            let (a, b) = if s.messages > 0 { (s.first_ns, s.last_ns) } else { (0, 0) };
            let _ = writeln!(y, "    - path: {}", quoted(&s.file));
            let _ = writeln!(y, "      starting_time:\n        nanoseconds_since_epoch: {a}");
            let _ = writeln!(y, "      duration:\n        nanoseconds: {}", b - a);
            let _ = writeln!(y, "      message_count: {}", s.messages);
        }
    }
    let _ = writeln!(y, "  custom_data:\n    writer: {}", quoted(concat!("duv-slam ", env!("CARGO_PKG_VERSION"))));
    let _ = writeln!(y, "  ros_distro: \"\"");
    y
}

/// A YAML double-quoted scalar.
fn quoted(s: &str) -> String {
    let mut q = String::with_capacity(s.len() + 2);
    q.push('"');
    for ch in s.chars() {
        match ch {
            '"' => q.push_str("\\\""),
            '\\' => q.push_str("\\\\"),
            c if (c as u32) < 0x20 => {
                let _ = write!(q, "\\x{:02x}", c as u32);
            }
            c => q.push(c),
        }
    }
    q.push('"');
    q
}

/// Writes `dir/metadata.yaml` for the ROS 2 segments in `dir` (temporary file, fsync,
/// rename). Returns how many segments it lists; with none, nothing is written.
pub fn write_metadata(dir: &Path) -> Result<usize, LogError> {
    let mut segments = Vec::new();
    for (_, path) in list_segments(dir)? {
        if read_profile(&path).ok().as_deref() == Some(ros2::PROFILE) {
            segments.push(segment_counts(&path)?);
        }
    }
    if segments.is_empty() {
        return Ok(0);
    }
    let text = metadata_yaml(&segments);
    let path = dir.join(METADATA_FILE);
    let tmp: PathBuf = dir.join(format!("{METADATA_FILE}.tmp"));
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| LogError::Io { path: p, source }
    };
    let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    f.write_all(text.as_bytes()).map_err(io(&tmp))?;
    f.sync_all().map_err(io(&tmp))?;
    drop(f);
    std::fs::rename(&tmp, &path).map_err(io(&path))?;
    sync_dir(dir);
    Ok(segments.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_lists_topics_files_and_times() {
        let mut a = SegmentCounts { file: "segment-000000.mcap".into(), messages: 3, first_ns: 100, last_ns: 400, topics: BTreeMap::new() };
        a.topics.insert(("/camera/image".into(), "sensor_msgs/msg/Image".into()), 2);
        a.topics.insert(("/tf".into(), "tf2_msgs/msg/TFMessage".into()), 1);
        let mut b = a.clone();
        b.file = "segment-000001.mcap".into();
        b.first_ns = 500;
        b.last_ns = 900;
        let y = metadata_yaml(&[a, b]);
        assert!(y.contains("  duration:\n    nanoseconds: 800\n"), "{y}");
        assert!(y.contains("nanoseconds_since_epoch: 100\n"), "{y}");
        assert!(y.contains("  message_count: 6\n"), "{y}");
        assert!(y.contains("        name: \"/camera/image\"\n        type: \"sensor_msgs/msg/Image\"\n        serialization_format: cdr\n"), "{y}");
        assert!(y.contains("      message_count: 4\n"), "{y}");
        assert!(y.contains("    - \"segment-000001.mcap\"\n"), "{y}");
        assert_eq!(quoted("a\"b\\"), "\"a\\\"b\\\\\"");
    }
}
