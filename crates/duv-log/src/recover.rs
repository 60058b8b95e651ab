//! Recovery of segments a crash left unfinished: every chunk whose CRC holds is kept (damaged
//! ranges are skipped by the salvaging reader, not the end of the read) and re-written, with a
//! summary and index, into a valid file that replaces the damaged one (write to a temporary
//! name, fsync, rename: the original stays until the copy is on disk). The recovered file
//! carries a `duv.recovered` metadata record that `duv inspect` reports. Recovery needs free
//! space for the copy (at most the segment's size); without it the segment is left as it is
//! (every reader salvages it the same way) and the report says so.

use super::chunked::{ChunkedWriter, WriterBuffers};
use super::reader::{read_segment_events, ReadEvent, ReadLimits};
pub use super::files::is_finished;
use super::files::sync_dir;
use super::{list_segments, LogError};
use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// Name of the metadata record a recovered segment carries.
pub const RECOVERED_METADATA: &str = "duv.recovered";

/// What recovering one segment did.
#[derive(Clone, Debug, PartialEq)]
pub struct RecoveryReport {
    pub segment: PathBuf,
    pub bytes_before: u64,
    pub bytes_after: u64,
    pub messages_kept: u64,
    /// What was not readable and skipped, in words.
    pub damage: String,
    /// Damaged byte ranges skipped.
    pub skipped_ranges: usize,
    /// `Some(why)` when the segment was not rewritten (not enough free space): it stays as it
    /// was, readable by the salvaging reader.
    pub left_in_place: Option<String>,
}

/// Free bytes for an unprivileged writer on the file system holding `dir`.
pub fn available_bytes(dir: &Path) -> Result<u64, LogError> {
    let s = rustix::fs::statvfs(dir).map_err(|e| LogError::Io { path: dir.to_path_buf(), source: e.into() })?;
    Ok(s.f_bavail.saturating_mul(s.f_frsize))
}

/// Free space recovery leaves for the run that follows it.
const RECOVERY_RESERVE_BYTES: u64 = 4 << 20;

/// Chunk size of recovered files.
const RECOVERY_CHUNK_BYTES: usize = 768 << 10;


/// Re-writes the readable part of `path` into a valid MCAP file in its place.
pub fn recover_segment(path: &Path, limits: ReadLimits) -> Result<RecoveryReport, LogError> {
    let bytes_before = std::fs::metadata(path).map_err(|source| LogError::Io { path: path.to_path_buf(), source })?.len();
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let free = available_bytes(dir)?;
    if free < bytes_before + RECOVERY_RESERVE_BYTES {
        // Count what a reader gets from it as it is.
        let outcome = read_segment_events(path, limits, |_| {})?;
        let why = format!("recovering needs up to {:.1} MB free, {:.1} MB available", (bytes_before + RECOVERY_RESERVE_BYTES) as f64 / 1e6, free as f64 / 1e6);
        tracing::warn!(segment = %path.display(), "unfinished log segment left as it is: {why}; it is read by salvage");
        return Ok(RecoveryReport {
            segment: path.to_path_buf(),
            bytes_before,
            bytes_after: bytes_before,
            messages_kept: outcome.messages,
            damage: outcome.damage.unwrap_or_default(),
            skipped_ranges: outcome.skipped.len(),
            left_in_place: Some(why),
        });
    }
    let tmp = path.with_extension("mcap.recovering");
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| LogError::Io { path: p, source }
    };
    let file = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    let library = concat!("duv-slam ", env!("CARGO_PKG_VERSION"), " recovery");
    // The original's profile (`ros2` for a ROS 2 bag) is kept; an unreadable header is the
    // Foxglove format's empty one.
    let profile = super::bag::read_profile(path).unwrap_or_default();
    let mut writer = ChunkedWriter::with_profile(BufWriter::new(file), &profile, library, RECOVERY_CHUNK_BYTES, WriterBuffers::default()).map_err(io(&tmp))?;
    let mut write_error: Option<std::io::Error> = None;
    let outcome = read_segment_events(path, limits, |event| {
        if write_error.is_some() {
            return;
        }
        let r = match event {
            // A schema or channel the damaged file repeats (a summary read before the damage)
            // is already registered: keep the first.
            ReadEvent::Schema(s) if writer.has_schema(s.id) => Ok(()),
            ReadEvent::Channel(c) if writer.has_channel(c.id) => Ok(()),
            ReadEvent::Schema(s) => writer.add_schema(s.id, &s.name, &s.encoding, &s.data),
            ReadEvent::Channel(c) => writer.add_channel(c.id, c.schema_id, &c.topic, &c.message_encoding, &c.metadata),
            ReadEvent::Message(m) => writer.write_message(m.channel.id, m.sequence, m.log_time_ns, m.publish_time_ns, m.data),
            ReadEvent::Metadata { name, metadata } => writer.write_metadata(name, metadata),
        };
        if let Err(e) = r {
            write_error = Some(e);
        }
    })?;
    if let Some(source) = write_error {
        let _ = std::fs::remove_file(&tmp);
        return Err(LogError::Io { path: tmp, source });
    }
    let damage = outcome.damage.clone().unwrap_or_else(|| "no footer".into());
    let mut meta = BTreeMap::new();
    meta.insert("original_bytes".to_string(), outcome.file_bytes.to_string());
    meta.insert("messages_kept".to_string(), outcome.messages.to_string());
    meta.insert("damage".to_string(), damage.clone());
    meta.insert("skipped_ranges".to_string(), outcome.skipped.len().to_string());
    meta.insert("skipped_bytes".to_string(), outcome.skipped.iter().map(|r| r.to_byte - r.from_byte).sum::<u64>().to_string());
    let finish = writer.write_metadata(RECOVERED_METADATA, &meta).and_then(|()| writer.finish());
    let out = match finish {
        Ok((out, _)) => out,
        Err(source) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(LogError::Io { path: tmp, source });
        }
    };
    let file = out.into_inner().map_err(|e| LogError::Io { path: tmp.clone(), source: e.into_error() })?;
    file.sync_all().map_err(io(&tmp))?;
    let bytes_after = file.metadata().map(|m| m.len()).unwrap_or(0);
    drop(file);
    std::fs::rename(&tmp, path).map_err(io(path))?;
    if let Some(dir) = path.parent() {
        sync_dir(dir);
    }
    tracing::warn!(segment = %path.display(), messages = outcome.messages, "recovered an unfinished log segment: {damage}");
    Ok(RecoveryReport {
        segment: path.to_path_buf(),
        bytes_before: outcome.file_bytes,
        bytes_after,
        messages_kept: outcome.messages,
        damage,
        skipped_ranges: outcome.skipped.len(),
        left_in_place: None,
    })
}

/// Recovers every unfinished segment in `dir` (leftover temporary files are removed first).
pub fn recover_folder(dir: &Path, limits: ReadLimits) -> Result<Vec<RecoveryReport>, LogError> {
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            if e.file_name().to_str().is_some_and(|n| n.ends_with(".mcap.recovering")) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    let mut reports = Vec::new();
    let mut ros2 = false;
    for (_, path) in list_segments(dir)? {
        if !is_finished(&path)? {
            reports.push(recover_segment(&path, limits)?);
        }
        ros2 |= super::bag::read_profile(&path).is_ok_and(|p| p == super::ros2::PROFILE);
    }
    // A ROS 2 bag's index, rebuilt once its segments are readable again.
    if ros2 {
        super::bag::write_metadata(dir)?;
    }
    Ok(reports)
}
