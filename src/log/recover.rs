//! Recovery of segments a crash left unfinished: every whole chunk is kept and re-written,
//! with a summary and index, into a valid file that replaces the damaged one (write to a
//! temporary name, fsync, rename). The recovered file carries a `duv.recovered` metadata
//! record that `duv inspect` reports.

use super::reader::{read_segment_events, ReadEvent, ReadLimits};
use super::writer::sync_dir;
use super::{list_segments, LogError};
use std::collections::BTreeMap;
use std::io::{BufWriter, Read, Seek, SeekFrom};
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
    /// Where and why the damaged file stopped being readable.
    pub damage: String,
}

/// Whether `path` ends with the MCAP closing magic (a finished file).
pub fn is_finished(path: &Path) -> Result<bool, LogError> {
    let io = |source| LogError::Io { path: path.to_path_buf(), source };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    if len < (2 * mcap::MAGIC.len()) as u64 {
        return Ok(false);
    }
    f.seek(SeekFrom::End(-(mcap::MAGIC.len() as i64))).map_err(io)?;
    let mut tail = [0u8; 8];
    f.read_exact(&mut tail).map_err(io)?;
    Ok(tail == mcap::MAGIC)
}

/// Re-writes the readable part of `path` into a valid MCAP file in its place.
pub fn recover_segment(path: &Path, limits: ReadLimits) -> Result<RecoveryReport, LogError> {
    let tmp = path.with_extension("mcap.recovering");
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| LogError::Io { path: p, source }
    };
    let file = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    let options = mcap::WriteOptions::new().compression(None).library(concat!("duv-slam ", env!("CARGO_PKG_VERSION"), " recovery"));
    let mut writer = options.create(BufWriter::new(file)).map_err(|source| LogError::Mcap { path: tmp.clone(), source })?;
    let mut write_error: Option<mcap::McapError> = None;
    let outcome = read_segment_events(path, limits, |event| {
        if write_error.is_some() {
            return;
        }
        let r = match event {
            ReadEvent::Schema(s) => writer.add_schema_with_id(s.id, &s.name, &s.encoding, &s.data).map(|_| ()),
            ReadEvent::Channel(c) => writer.add_channel_with_id(c.id, c.schema_id, &c.topic, &c.message_encoding, &c.metadata).map(|_| ()),
            ReadEvent::Message(m) => writer.write_to_known_channel(
                &mcap::records::MessageHeader { channel_id: m.channel.id, sequence: m.sequence, log_time: m.log_time_ns, publish_time: m.publish_time_ns },
                m.data,
            ),
            ReadEvent::Metadata { name, metadata } => writer.write_metadata(&mcap::records::Metadata { name: name.to_string(), metadata: metadata.clone() }),
        };
        if let Err(e) = r {
            write_error = Some(e);
        }
    })?;
    if let Some(source) = write_error {
        let _ = std::fs::remove_file(&tmp);
        return Err(LogError::Mcap { path: tmp, source });
    }
    let damage = outcome.damage.clone().unwrap_or_else(|| "no footer".into());
    let mut meta = BTreeMap::new();
    meta.insert("original_bytes".to_string(), outcome.file_bytes.to_string());
    meta.insert("messages_kept".to_string(), outcome.messages.to_string());
    meta.insert("damage".to_string(), damage.clone());
    let finish = writer
        .write_metadata(&mcap::records::Metadata { name: RECOVERED_METADATA.into(), metadata: meta })
        .and_then(|()| writer.finish().map(|_| ()));
    if let Err(source) = finish {
        let _ = std::fs::remove_file(&tmp);
        return Err(LogError::Mcap { path: tmp, source });
    }
    let file = writer.into_inner().into_inner().map_err(|e| LogError::Io { path: tmp.clone(), source: e.into_error() })?;
    file.sync_all().map_err(io(&tmp))?;
    let bytes_after = file.metadata().map(|m| m.len()).unwrap_or(0);
    drop(file);
    std::fs::rename(&tmp, path).map_err(io(path))?;
    if let Some(dir) = path.parent() {
        sync_dir(dir);
    }
    tracing::warn!(segment = %path.display(), messages = outcome.messages, "recovered an unfinished log segment: {damage}");
    Ok(RecoveryReport { segment: path.to_path_buf(), bytes_before: outcome.file_bytes, bytes_after, messages_kept: outcome.messages, damage })
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
    for (_, path) in list_segments(dir)? {
        if !is_finished(&path)? {
            reports.push(recover_segment(&path, limits)?);
        }
    }
    Ok(reports)
}
