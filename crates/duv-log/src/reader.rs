//! A streaming MCAP reader for our own logs that salvages damaged files: records larger than
//! [`ReadLimits::max_record_bytes`] are refused before they are buffered, chunks are checked
//! against their CRC before any of their messages is handed out, and a damaged record does not
//! end the read: the reader skips it and resynchronises on the next valid record (a chunk whose
//! CRC holds, or a chain of records that parse and lead to one), so every intact chunk after
//! the damage is still delivered. Where the file's summary survived (a finished file with a
//! flipped byte), its channels are known from the start and its chunk index bounds each
//! resynchronisation. Each skipped byte range is reported with why ([`ReadOutcome::skipped`]).
//!
//! Hand-written on top of the `mcap` crate's record parser because the crate's readers stop
//! at the first error (its linear reader) or need an intact summary (its indexed reader); a
//! black box must get back every chunk that survived.

use super::chunked::{op, MAGIC};
use super::LogError;
use mcap::records::Record;
use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
/// Memory bounds of the reader.
#[derive(Clone, Copy, Debug)]
pub struct ReadLimits {
    /// Largest record (a whole chunk included) the reader buffers.
    pub max_record_bytes: usize,
}

impl Default for ReadLimits {
    fn default() -> Self {
        ReadLimits { max_record_bytes: 64 << 20 }
    }
}

/// A schema as it appears in the file.
#[derive(Clone, Debug, PartialEq)]
pub struct SchemaInfo {
    pub id: u16,
    pub name: String,
    pub encoding: String,
    pub data: Vec<u8>,
}

/// A channel as it appears in the file.
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelInfo {
    pub id: u16,
    pub schema_id: u16,
    pub topic: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
}

/// One message with its channel.
#[derive(Debug)]
pub struct SegmentMessage<'a> {
    pub channel: &'a ChannelInfo,
    pub sequence: u32,
    pub log_time_ns: u64,
    pub publish_time_ns: u64,
    pub data: &'a [u8],
}

/// What the reader sees, in file order.
pub enum ReadEvent<'a> {
    Schema(&'a SchemaInfo),
    Channel(&'a ChannelInfo),
    Message(SegmentMessage<'a>),
    Metadata { name: &'a str, metadata: &'a BTreeMap<String, String> },
}

/// A byte range the reader could not use, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct SkippedRange {
    pub from_byte: u64,
    pub to_byte: u64,
    pub why: String,
}

/// How far a segment could be read.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReadOutcome {
    pub path: PathBuf,
    pub file_bytes: u64,
    pub messages: u64,
    /// The footer and closing magic were read: the file was finished properly.
    pub complete: bool,
    /// What was not readable, in words (damaged ranges skipped, no footer); `None` when the
    /// whole file was read.
    pub damage: Option<String>,
    /// The damaged byte ranges skipped, in file order.
    pub skipped: Vec<SkippedRange>,
    /// Messages in intact chunks whose channel record was lost to the damage (not delivered).
    pub orphaned_messages: u64,
    /// Chunks whose CRC held and whose messages were delivered.
    pub chunks: u64,
    /// Their records' bytes as stored (compressed or not) and uncompressed, summed.
    pub chunk_stored_bytes: u64,
    pub chunk_uncompressed_bytes: u64,
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
}

/// An owned event of [`SegmentReader`].
#[derive(Clone, Debug, PartialEq)]
pub enum OwnedEvent {
    Schema(SchemaInfo),
    Channel(ChannelInfo),
    Message { channel_id: u16, sequence: u32, log_time_ns: u64, publish_time_ns: u64, data: Vec<u8> },
    Metadata { name: String, metadata: BTreeMap<String, String> },
}

/// Opcode and length.
const RECORD_HEAD: u64 = 9;
/// Bytes the resynchronisation scan reads at a time.
const SCAN_BLOCK: usize = 1 << 20;
/// Records a chain of small records may hold before it must reach a chunk whose CRC holds.
const CHAIN_RECORDS: usize = 32;

/// Pull reader of one segment: [`SegmentReader::next_event`] until `None`, then
/// [`SegmentReader::outcome`] says whether the file ended cleanly and what was skipped.
pub struct SegmentReader {
    file: std::fs::File,
    limits: ReadLimits,
    channels: HashMap<u16, ChannelInfo>,
    schemas_seen: HashSet<u16>,
    outcome: ReadOutcome,
    /// Where the next record starts.
    pos: u64,
    /// Events of the last chunk (or the summary's channels) not yet handed out.
    pending: VecDeque<OwnedEvent>,
    /// Chunk offsets from the summary's chunk index, ascending (empty without a summary).
    chunk_offsets: Vec<u64>,
    body: Vec<u8>,
    started: bool,
    done: bool,
}

/// Why a record cannot be used.
type Bad = String;

impl SegmentReader {
    pub fn open(path: &Path, limits: ReadLimits) -> Result<Self, LogError> {
        let file = std::fs::File::open(path).map_err(|source| LogError::Io { path: path.to_path_buf(), source })?;
        let file_bytes = file.metadata().map(|m| m.len()).map_err(|source| LogError::Io { path: path.to_path_buf(), source })?;
        Ok(SegmentReader {
            file,
            limits,
            channels: HashMap::new(),
            schemas_seen: HashSet::new(),
            outcome: ReadOutcome { path: path.to_path_buf(), file_bytes, ..Default::default() },
            pos: 0,
            pending: VecDeque::new(),
            chunk_offsets: Vec::new(),
            body: Vec::new(),
            started: false,
            done: false,
        })
    }

    /// The channel a message names.
    pub fn channel(&self, id: u16) -> Option<&ChannelInfo> {
        self.channels.get(&id)
    }

    pub fn outcome(&self) -> &ReadOutcome {
        &self.outcome
    }

    fn read_exact_at(&self, buf: &mut [u8], at: u64) -> Result<(), Bad> {
        self.file.read_exact_at(buf, at).map_err(|e| format!("read error at byte {at}: {e}"))
    }

    /// Opcode and body length of the record at `at`, if its head is plausible: a known opcode
    /// and a body that fits the file and the limit.
    fn head_at(&self, at: u64) -> Result<(u8, u64), Bad> {
        let file_bytes = self.outcome.file_bytes;
        if at + RECORD_HEAD > file_bytes {
            return Err(format!("the file ends at byte {file_bytes} inside a record head"));
        }
        let mut h = [0u8; RECORD_HEAD as usize];
        self.read_exact_at(&mut h, at)?;
        let len = u64::from_le_bytes(h[1..9].try_into().expect("8 bytes"));
        check_head(h[0], len, at, file_bytes, self.limits.max_record_bytes)?;
        Ok((h[0], len))
    }

    /// Reads the body of the record at `at` into `self.body`.
    fn load_body(&mut self, at: u64, len: u64) -> Result<(), Bad> {
        let mut body = std::mem::take(&mut self.body);
        body.clear();
        body.resize(len as usize, 0);
        let r = self.read_exact_at(&mut body, at + RECORD_HEAD);
        self.body = body;
        r
    }

    /// Reads the summary of a finished file (footer, summary CRC): its schemas and channels
    /// become known before any damage, its chunk index bounds the resynchronisation.
    fn preload_summary(&mut self) {
        let file_bytes = self.outcome.file_bytes;
        let footer_len = 1 + 8 + 20;
        if file_bytes < 8 + footer_len + 8 {
            return;
        }
        let footer_at = file_bytes - 8 - footer_len;
        let mut f = [0u8; 37];
        if self.read_exact_at(&mut f, footer_at).is_err() || f[29..37] != MAGIC || f[0] != op::FOOTER {
            return;
        }
        let Ok(Record::Footer(footer)) = mcap::parse_record(op::FOOTER, &f[9..29]) else { return };
        let start = footer.summary_start;
        if start < 8 || start >= footer_at || footer_at - start > self.limits.max_record_bytes as u64 {
            return;
        }
        let mut summary = vec![0u8; (footer_at - start) as usize];
        if self.read_exact_at(&mut summary, start).is_err() {
            return;
        }
        if footer.summary_crc != 0 {
            let mut crc = crc32fast::Hasher::new();
            crc.update(&summary);
            crc.update(&f[..1 + 8 + 16]);
            if crc.finalize() != footer.summary_crc {
                return;
            }
        }
        let mut events = Vec::new();
        let mut offsets = Vec::new();
        if for_each_record(&summary, |opcode, body| {
            match mcap::parse_record(opcode, body).map_err(|e| e.to_string())? {
                Record::Schema { header, data } => events.push(OwnedEvent::Schema(SchemaInfo { id: header.id, name: header.name, encoding: header.encoding, data: data.into_owned() })),
                Record::Channel(c) => events.push(OwnedEvent::Channel(ChannelInfo { id: c.id, schema_id: c.schema_id, topic: c.topic, message_encoding: c.message_encoding, metadata: c.metadata })),
                Record::ChunkIndex(ci) => offsets.push(ci.chunk_start_offset),
                _ => {}
            }
            Ok(())
        })
        .is_err()
        {
            return;
        }
        offsets.sort_unstable();
        self.chunk_offsets = offsets;
        for e in events {
            if let Some(e) = self.first_sighting(e) {
                self.pending.push_back(e);
            }
        }
    }

    /// `e` unless it repeats a schema or channel already handed out.
    fn first_sighting(&mut self, e: OwnedEvent) -> Option<OwnedEvent> {
        match &e {
            OwnedEvent::Schema(s) if !self.schemas_seen.insert(s.id) => None,
            OwnedEvent::Channel(c) if self.channels.contains_key(&c.id) => None,
            OwnedEvent::Channel(c) => {
                self.channels.insert(c.id, c.clone());
                Some(e)
            }
            _ => Some(e),
        }
    }

    /// Handles the record at `self.pos`: its events go to `pending`, `pos` moves past it. On
    /// damage: why, and where the record ends when its head was plausible.
    fn read_record(&mut self) -> Result<(), (Bad, Option<u64>)> {
        let at = self.pos;
        let (opcode, len) = self.head_at(at).map_err(|why| (why, None))?;
        let end = at + RECORD_HEAD + len;
        self.load_body(at, len).map_err(|why| (why, None))?;
        let body = std::mem::take(&mut self.body);
        let r = self.take_record(opcode, &body);
        self.body = body;
        r.map_err(|why| (why, Some(end)))?;
        self.pos = end;
        Ok(())
    }

    fn take_record(&mut self, opcode: u8, body: &[u8]) -> Result<(), Bad> {
        let record = mcap::parse_record(opcode, body).map_err(|e| format!("bad record (opcode {opcode:#x}): {e}"))?;
        match record {
            Record::Chunk { header, data } => {
                let records = chunk_records(&header, &data, self.limits.max_record_bytes)?;
                let mut events = Vec::new();
                let mut orphaned = 0;
                for_each_record(&records, |opcode, body| {
                    match mcap::parse_record(opcode, body).map_err(|e| format!("bad record in a chunk (opcode {opcode:#x}): {e}"))? {
                        Record::Message { header, data } => events.push(OwnedEvent::Message {
                            channel_id: header.channel_id,
                            sequence: header.sequence,
                            log_time_ns: header.log_time,
                            publish_time_ns: header.publish_time,
                            data: data.into_owned(),
                        }),
                        Record::Schema { header, data } => events.push(OwnedEvent::Schema(SchemaInfo { id: header.id, name: header.name, encoding: header.encoding, data: data.into_owned() })),
                        Record::Channel(c) => events.push(OwnedEvent::Channel(ChannelInfo { id: c.id, schema_id: c.schema_id, topic: c.topic, message_encoding: c.message_encoding, metadata: c.metadata })),
                        _ => {}
                    }
                    Ok(())
                })?;
                self.outcome.chunks += 1;
                self.outcome.chunk_stored_bytes += data.len() as u64;
                self.outcome.chunk_uncompressed_bytes += records.len() as u64;
                for e in events {
                    if let OwnedEvent::Message { channel_id, .. } = &e {
                        if !self.channels.contains_key(channel_id) {
                            orphaned += 1;
                            continue;
                        }
                    }
                    if let Some(e) = self.first_sighting(e) {
                        self.pending.push_back(e);
                    }
                }
                self.outcome.orphaned_messages += orphaned;
            }
            Record::Message { header, data } => {
                if self.channels.contains_key(&header.channel_id) {
                    self.pending.push_back(OwnedEvent::Message {
                        channel_id: header.channel_id,
                        sequence: header.sequence,
                        log_time_ns: header.log_time,
                        publish_time_ns: header.publish_time,
                        data: data.into_owned(),
                    });
                } else {
                    self.outcome.orphaned_messages += 1;
                }
            }
            Record::Schema { header, data } => {
                let e = OwnedEvent::Schema(SchemaInfo { id: header.id, name: header.name, encoding: header.encoding, data: data.into_owned() });
                if let Some(e) = self.first_sighting(e) {
                    self.pending.push_back(e);
                }
            }
            Record::Channel(c) => {
                let e = OwnedEvent::Channel(ChannelInfo { id: c.id, schema_id: c.schema_id, topic: c.topic, message_encoding: c.message_encoding, metadata: c.metadata });
                if let Some(e) = self.first_sighting(e) {
                    self.pending.push_back(e);
                }
            }
            Record::Metadata(m) => {
                self.outcome.metadata.push((m.name.clone(), m.metadata.clone()));
                self.pending.push_back(OwnedEvent::Metadata { name: m.name, metadata: m.metadata });
            }
            Record::Footer(_) => {
                self.outcome.complete = true;
                self.done = true;
            }
            _ => {}
        }
        Ok(())
    }

    /// Whether a record chain starting at `at` is real: a chunk whose CRC holds, or small
    /// records (not messages) that parse, one after the other, up to such a chunk, the footer
    /// or the file's end. With `after_damage` (`at` is right after a damaged record whose
    /// length was plausible), a chain of small records may also end at a chunk that parses but
    /// fails its CRC: that chunk is skipped in turn, and the records before it (a channel
    /// record written between the two chunks) are read, not lost with them.
    fn chain_holds(&mut self, at: u64, after_damage: bool) -> bool {
        let file_bytes = self.outcome.file_bytes;
        let mut p = at;
        for _ in 0..CHAIN_RECORDS {
            if p == file_bytes {
                return true;
            }
            let Ok((opcode, len)) = self.head_at(p) else { return false };
            if self.load_body(p, len).is_err() {
                return false;
            }
            let ok = match opcode {
                op::CHUNK => {
                    return match mcap::parse_record(opcode, &self.body) {
                        Ok(Record::Chunk { header, data }) => chunk_records(&header, &data, self.limits.max_record_bytes).is_ok() || (after_damage && p > at),
                        _ => false,
                    }
                }
                op::FOOTER => return mcap::parse_record(opcode, &self.body).is_ok(),
                op::MESSAGE_INDEX => message_index_ok(&self.body),
                op::HEADER | op::SCHEMA | op::CHANNEL | op::CHUNK_INDEX | op::METADATA | op::DATA_END => mcap::parse_record(opcode, &self.body).is_ok(),
                // The records inside a damaged chunk look like messages: never resynchronise on
                // one (our writer puts every message in a chunk).
                op::MESSAGE => false,
                _ => true,
            };
            if !ok {
                return false;
            }
            p += RECORD_HEAD + len;
        }
        false
    }

    /// The next position after `from` where a real record starts (see [`Self::chain_holds`]),
    /// scanning no further than the next chunk the summary's index names.
    fn resync(&mut self, from: u64) -> Option<u64> {
        let file_bytes = self.outcome.file_bytes;
        let bound = self.chunk_offsets.iter().copied().find(|&o| o >= from).unwrap_or(file_bytes);
        let mut block = vec![0u8; SCAN_BLOCK + RECORD_HEAD as usize];
        let mut start = from;
        while start < bound {
            let n = ((bound - start) as usize + RECORD_HEAD as usize).min(block.len()).min((file_bytes - start) as usize);
            if self.read_exact_at(&mut block[..n], start).is_err() {
                return None;
            }
            let scan_to = ((bound - start).min(SCAN_BLOCK as u64) as usize).min(n);
            for i in 0..scan_to {
                let opcode = block[i];
                if !(op::HEADER..=op::DATA_END).contains(&opcode) || i + RECORD_HEAD as usize > n {
                    continue;
                }
                let len = u64::from_le_bytes(block[i + 1..i + 9].try_into().expect("8 bytes"));
                let at = start + i as u64;
                if check_head(opcode, len, at, file_bytes, self.limits.max_record_bytes).is_ok() && self.chain_holds(at, false) {
                    return Some(at);
                }
            }
            start += scan_to as u64;
        }
        (bound < file_bytes).then_some(bound)
    }

    /// Skips the damaged record at `self.pos`: reading goes on at the next real record (right
    /// after it when its length was plausible and a real record follows there).
    fn skip_damage(&mut self, why: Bad, end: Option<u64>) {
        let from_byte = self.pos;
        let next = match end {
            Some(e) if self.chain_holds(e, true) => Some(e),
            _ => self.resync(from_byte + 1),
        };
        let to_byte = next.unwrap_or(self.outcome.file_bytes);
        self.outcome.skipped.push(SkippedRange { from_byte, to_byte, why });
        match next {
            Some(p) => self.pos = p,
            None => self.done = true,
        }
    }

    fn finish(&mut self) {
        self.done = true;
        let mut parts: Vec<String> = self.outcome.skipped.iter().map(|s| format!("bytes {}..{} skipped ({})", s.from_byte, s.to_byte, s.why)).collect();
        if self.outcome.orphaned_messages > 0 {
            parts.push(format!("{} messages of intact chunks lost with their channel record", self.outcome.orphaned_messages));
        }
        if !self.outcome.complete {
            parts.push("no footer (the writer did not finish the file)".into());
        }
        self.outcome.damage = (!parts.is_empty()).then(|| parts.join("; "));
    }

    /// The next schema, channel, message or metadata record; `None` at the end of the file.
    pub fn next_event(&mut self) -> Option<OwnedEvent> {
        loop {
            if let Some(e) = self.pending.pop_front() {
                match &e {
                    OwnedEvent::Message { .. } => self.outcome.messages += 1,
                    OwnedEvent::Channel(c) => {
                        self.channels.insert(c.id, c.clone());
                    }
                    _ => {}
                }
                return Some(e);
            }
            if self.done {
                if self.outcome.damage.is_none() {
                    self.finish();
                }
                return None;
            }
            if !self.started {
                self.started = true;
                self.preload_summary();
                let mut magic = [0u8; 8];
                if self.outcome.file_bytes < 8 || self.read_exact_at(&mut magic, 0).is_err() || magic != MAGIC {
                    self.skip_damage("no MCAP magic at the start".into(), None);
                } else {
                    self.pos = 8;
                }
                continue;
            }
            if self.pos >= self.outcome.file_bytes {
                self.done = true;
                continue;
            }
            if let Err((why, end)) = self.read_record() {
                self.skip_damage(why, end);
            }
        }
    }
}

/// Checks a record head: an opcode the specification defines (or a user opcode), a body that
/// fits the file and the limit, a header or footer only where they belong.
fn check_head(opcode: u8, len: u64, at: u64, file_bytes: u64, limit: usize) -> Result<(), Bad> {
    if opcode == 0 || (0x10..0x80).contains(&opcode) {
        return Err(format!("unknown opcode {opcode:#x} at byte {at}"));
    }
    if len > limit as u64 {
        return Err(format!("a record of {len} bytes at byte {at} exceeds the limit of {limit} bytes"));
    }
    if at + RECORD_HEAD + len > file_bytes {
        return Err(format!("a record of {len} bytes at byte {at} runs past the end of the file ({file_bytes} bytes)"));
    }
    // The header opens the file and the footer closes it, right before the closing magic.
    if opcode == op::HEADER && at != 8 {
        return Err(format!("a header record at byte {at}"));
    }
    if opcode == op::FOOTER && (len != 20 || at + RECORD_HEAD + len + 8 != file_bytes) {
        return Err(format!("a footer record at byte {at}, not at the end of the file"));
    }
    Ok(())
}

/// The records of a chunk after its CRC is checked: `zstd` and `lz4` chunks (ours, by the
/// board's `[log] compression`, and other writers': rosbag2 writes zstd by default) are
/// decompressed, at most `max_bytes`.
fn chunk_records<'a>(header: &mcap::records::ChunkHeader, data: &'a [u8], max_bytes: usize) -> Result<std::borrow::Cow<'a, [u8]>, Bad> {
    use std::io::Read;
    let data: std::borrow::Cow<'a, [u8]> = match header.compression.as_str() {
        "" => std::borrow::Cow::Borrowed(data),
        kind @ ("zstd" | "lz4") => {
            if header.uncompressed_size > max_bytes as u64 {
                return Err(format!("a {kind} chunk of {} bytes uncompressed, over the limit of {max_bytes}", header.uncompressed_size));
            }
            let mut out = Vec::with_capacity(header.uncompressed_size as usize);
            let limit = header.uncompressed_size + 1;
            let read = match kind {
                "zstd" => ruzstd::decoding::StreamingDecoder::new(data).map_err(|e| e.to_string()).and_then(|d| d.take(limit).read_to_end(&mut out).map_err(|e| e.to_string())),
                _ => lz4_flex::frame::FrameDecoder::new(data).take(limit).read_to_end(&mut out).map_err(|e| e.to_string()),
            };
            read.map_err(|e| format!("a {kind} chunk that does not decompress: {e}"))?;
            std::borrow::Cow::Owned(out)
        }
        other => return Err(format!("a chunk compressed with {other} (not read)")),
    };
    if data.len() as u64 != header.uncompressed_size {
        return Err(format!("a chunk of {} bytes says {}", data.len(), header.uncompressed_size));
    }
    if header.uncompressed_crc != 0 && crc32fast::hash(&data) != header.uncompressed_crc {
        return Err("chunk CRC mismatch".into());
    }
    Ok(data)
}

fn message_index_ok(body: &[u8]) -> bool {
    body.len() >= 6 && {
        let n = u32::from_le_bytes(body[2..6].try_into().expect("4 bytes")) as usize;
        n % 16 == 0 && body.len() == 6 + n
    }
}

/// Calls `f(opcode, body)` for each record laid out back to back in `bytes`.
fn for_each_record(bytes: &[u8], mut f: impl FnMut(u8, &[u8]) -> Result<(), Bad>) -> Result<(), Bad> {
    let mut p = 0usize;
    while p < bytes.len() {
        if p + RECORD_HEAD as usize > bytes.len() {
            return Err("a record head cut short".into());
        }
        let opcode = bytes[p];
        let len = u64::from_le_bytes(bytes[p + 1..p + 9].try_into().expect("8 bytes"));
        let body_at = p + RECORD_HEAD as usize;
        if len > (bytes.len() - body_at) as u64 {
            return Err(format!("a record of {len} bytes runs past its container"));
        }
        f(opcode, &bytes[body_at..body_at + len as usize])?;
        p = body_at + len as usize;
    }
    Ok(())
}

/// Reads `path` to its end, damaged ranges skipped, calling `on_event` for every schema,
/// channel, message and metadata record. Only failing to open the file is an error; damage
/// is reported in [`ReadOutcome::damage`] and [`ReadOutcome::skipped`].
pub fn read_segment_events(path: &Path, limits: ReadLimits, mut on_event: impl FnMut(ReadEvent<'_>)) -> Result<ReadOutcome, LogError> {
    let mut r = SegmentReader::open(path, limits)?;
    while let Some(e) = r.next_event() {
        match e {
            OwnedEvent::Schema(s) => on_event(ReadEvent::Schema(&s)),
            OwnedEvent::Channel(c) => on_event(ReadEvent::Channel(&c)),
            OwnedEvent::Message { channel_id, sequence, log_time_ns, publish_time_ns, data } => {
                let channel = r.channel(channel_id).expect("checked by the reader");
                on_event(ReadEvent::Message(SegmentMessage { channel, sequence, log_time_ns, publish_time_ns, data: &data }));
            }
            OwnedEvent::Metadata { name, metadata } => on_event(ReadEvent::Metadata { name: &name, metadata: &metadata }),
        }
    }
    Ok(r.outcome.clone())
}

/// [`read_segment_events`] for messages only.
pub fn read_segment(path: &Path, limits: ReadLimits, mut on_message: impl FnMut(&SegmentMessage<'_>)) -> Result<ReadOutcome, LogError> {
    read_segment_events(path, limits, |e| {
        if let ReadEvent::Message(m) = e {
            on_message(&m);
        }
    })
}
