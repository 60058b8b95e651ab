//! A streaming MCAP reader for our own logs, safe on damaged files: records larger than
//! [`ReadLimits::max_record_bytes`] are refused before they are buffered, chunks are checked
//! against their CRC before any of their messages is handed out, and reading stops at the
//! first damage with everything before it delivered.

use super::LogError;
use mcap::records::Record;
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use std::collections::{BTreeMap, HashMap};
use std::io::Read;
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

/// How far a segment could be read.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReadOutcome {
    pub path: PathBuf,
    pub file_bytes: u64,
    pub messages: u64,
    /// The footer and closing magic were read: the file was finished properly.
    pub complete: bool,
    /// Why reading stopped early (truncation, bad CRC, oversized record); `None` when the
    /// whole file was read.
    pub damage: Option<String>,
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

/// Pull reader of one segment: [`SegmentReader::next_event`] until `None`, then
/// [`SegmentReader::outcome`] says whether the file ended cleanly or where it was damaged.
pub struct SegmentReader {
    file: std::fs::File,
    reader: LinearReader,
    limits: ReadLimits,
    channels: HashMap<u16, ChannelInfo>,
    outcome: ReadOutcome,
    consumed: u64,
    done: bool,
}

impl SegmentReader {
    pub fn open(path: &Path, limits: ReadLimits) -> Result<Self, LogError> {
        let file = std::fs::File::open(path).map_err(|source| LogError::Io { path: path.to_path_buf(), source })?;
        let file_bytes = file.metadata().map(|m| m.len()).unwrap_or(0);
        let options = LinearReaderOptions::default()
            .with_emit_chunks(false)
            .with_validate_chunk_crcs(true)
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(limits.max_record_bytes);
        Ok(SegmentReader {
            file,
            reader: LinearReader::new_with_options(options),
            limits,
            channels: HashMap::new(),
            outcome: ReadOutcome { path: path.to_path_buf(), file_bytes, ..Default::default() },
            consumed: 0,
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

    fn damaged(&mut self, problem: String) -> Option<OwnedEvent> {
        self.outcome.damage = Some(format!("after byte {}: {problem}", self.consumed));
        self.done = true;
        None
    }

    /// The next schema, channel, message or metadata record; `None` at the end or the damage.
    pub fn next_event(&mut self) -> Option<OwnedEvent> {
        while !self.done {
            let event = match self.reader.next_event() {
                None => {
                    self.done = true;
                    return None;
                }
                Some(Ok(e)) => e,
                Some(Err(e)) => return self.damaged(e.to_string()),
            };
            match event {
                LinearReadEvent::ReadRequest(n) => {
                    if n > self.limits.max_record_bytes.saturating_add(64) {
                        let limit = self.limits.max_record_bytes;
                        return self.damaged(format!("a record of {n} bytes exceeds the limit of {limit} bytes"));
                    }
                    let buf = self.reader.insert(n);
                    match self.file.read(buf) {
                        Ok(k) => {
                            self.consumed += k as u64;
                            self.reader.notify_read(k);
                        }
                        Err(e) => return self.damaged(format!("read error: {e}")),
                    }
                }
                LinearReadEvent::Record { data, opcode } => {
                    let record = match mcap::parse_record(opcode, data) {
                        Ok(r) => r,
                        Err(e) => return self.damaged(format!("bad record (opcode {opcode:#x}): {e}")),
                    };
                    match record {
                        Record::Schema { header, data } => {
                            return Some(OwnedEvent::Schema(SchemaInfo { id: header.id, name: header.name, encoding: header.encoding, data: data.into_owned() }));
                        }
                        Record::Channel(c) => {
                            let c = ChannelInfo { id: c.id, schema_id: c.schema_id, topic: c.topic, message_encoding: c.message_encoding, metadata: c.metadata };
                            self.channels.insert(c.id, c.clone());
                            return Some(OwnedEvent::Channel(c));
                        }
                        Record::Message { header, data } => {
                            if !self.channels.contains_key(&header.channel_id) {
                                let id = header.channel_id;
                                return self.damaged(format!("message on unknown channel {id}"));
                            }
                            self.outcome.messages += 1;
                            return Some(OwnedEvent::Message {
                                channel_id: header.channel_id,
                                sequence: header.sequence,
                                log_time_ns: header.log_time,
                                publish_time_ns: header.publish_time,
                                data: data.into_owned(),
                            });
                        }
                        Record::Metadata(m) => {
                            self.outcome.metadata.push((m.name.clone(), m.metadata.clone()));
                            return Some(OwnedEvent::Metadata { name: m.name, metadata: m.metadata });
                        }
                        Record::Footer(_) => self.outcome.complete = true,
                        _ => {}
                    }
                }
            }
        }
        None
    }
}

/// Reads `path` up to its end or its first damage, calling `on_event` for every schema,
/// channel, message and metadata record. Only failing to open the file is an error; damage
/// is reported in [`ReadOutcome::damage`].
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
