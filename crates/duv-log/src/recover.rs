//! Recovery of segments a crash left unfinished: every whole chunk is kept and re-written,
//! with a summary and index, into a valid file that replaces the damaged one (write to a
//! temporary name, fsync, rename). The recovered file carries a `duv.recovered` metadata
//! record that `duv inspect` reports.

use super::chunked::{ChunkedWriter, WriterBuffers, MAGIC};
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

/// Chunk size of recovered files.
const RECOVERY_CHUNK_BYTES: usize = 768 << 10;

/// Whether `path` ends with the MCAP closing magic (a finished file).
pub fn is_finished(path: &Path) -> Result<bool, LogError> {
    let io = |source| LogError::Io { path: path.to_path_buf(), source };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    if len < (2 * MAGIC.len()) as u64 {
        return Ok(false);
    }
    f.seek(SeekFrom::End(-(MAGIC.len() as i64))).map_err(io)?;
    let mut tail = [0u8; 8];
    f.read_exact(&mut tail).map_err(io)?;
    Ok(tail == MAGIC)
}

/// Re-writes the readable part of `path` into a valid MCAP file in its place.
pub fn recover_segment(path: &Path, limits: ReadLimits) -> Result<RecoveryReport, LogError> {
    let tmp = path.with_extension("mcap.recovering");
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| LogError::Io { path: p, source }
    };
    let file = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    let library = concat!("duv-slam ", env!("CARGO_PKG_VERSION"), " recovery");
    let mut writer = ChunkedWriter::new(BufWriter::new(file), library, RECOVERY_CHUNK_BYTES, WriterBuffers::default()).map_err(io(&tmp))?;
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
