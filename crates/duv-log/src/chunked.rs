//! Our MCAP writer: chunked, compressed (zstd, lz4 or none), fully indexed (message indexes after every chunk,
//! schemas, channels, statistics, chunk and metadata indexes and summary offsets in the
//! summary, data-section and summary CRCs), and allocation-free once warm.
//!
//! The `mcap` crate's writer rebuilds each chunk's buffers and index maps afresh, so the
//! logging thread allocated about 25 times per chunk. Here every buffer is kept in
//! [`WriterBuffers`] and handed from one segment's writer to the next: the open chunk's
//! records (capacity fixed at the chunk size), the per-channel message index entries, the
//! chunk index table and the message-index offsets. A message larger than the chunk size is
//! written as a chunk of its own, straight from the caller's slice (no copy, no growth).
//! Schema, channel and metadata records go into the data section outside chunks, before the
//! first message that uses them; the reader in [`super::reader`] and the PyPI `mcap` package
//! read both layouts.
//!
//! **Compression** ([`ChunkCompression`], the board's `[log] compression`): each chunk's records
//! are compressed into [`WriterBuffers`]' `compressed` buffer, reserved at the bound of the
//! largest chunk seen, so it grows once per size class (a map checkpoint is a chunk of its
//! own, tens of MB at 640x480, and the first one grows it) and never again.
//! - `zstd` (the default): libzstd's streaming API on one reused compression context
//!   (`ZSTD_compressStream2`, level [`ZSTD_LEVEL`]); a split record (message head + body) is
//!   fed in two parts, so nothing is copied. The context's memory comes from libzstd's own C
//!   allocator, outside Rust's global allocator (and so outside the counting-allocator tests):
//!   it is allocated with the first chunk and reused after that (`ZSTD_CCtx` keeps its
//!   workspace while the parameters stay the same).
//! - `lz4`: LZ4 frames (independent blocks of at most 4 MiB, no checksums) around
//!   `lz4_flex`'s block compressor, written here. `lz4_flex` allocates its 16 KiB hash table
//!   afresh for every block, so this path makes one allocation per chunk; it is offered for a
//!   board whose log thread cannot spare zstd's time.
//! - `none`: the records as they are.
//!
//! Measured on a real log's content (`docs/results/2026-11-28-log-budget.md`): zstd level 1
//! gave the better ratio on every topic at a log-thread cost the Jetson budget allows, so it
//! is the default.

use std::collections::BTreeMap;
use std::io::{self, Write};
use zstd::zstd_safe::{self, zstd_sys::ZSTD_EndDirective, CCtx, CParameter, InBuffer, OutBuffer, ResetDirective};

/// The zstd level of compressed chunks: 1 (fastest regular level).
pub const ZSTD_LEVEL: i32 = 1;

/// How a chunk's records are compressed (the MCAP chunk's `compression` field).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ChunkCompression {
    /// Uncompressed records (`""`).
    None,
    /// A Zstandard frame (`"zstd"`).
    #[default]
    Zstd,
    /// An LZ4 frame (`"lz4"`).
    Lz4,
}

impl ChunkCompression {
    /// The name MCAP gives it in chunks and chunk indexes.
    pub fn mcap_name(self) -> &'static str {
        match self {
            ChunkCompression::None => "",
            ChunkCompression::Zstd => "zstd",
            ChunkCompression::Lz4 => "lz4",
        }
    }
}

/// LZ4 frame header: magic, FLG (version 01, independent blocks, no checksums, no content
/// size), BD (blocks of at most 4 MiB), header checksum (byte 1 of xxh32 of FLG BD).
const LZ4_FRAME_HEADER: [u8; 7] = [0x04, 0x22, 0x4D, 0x18, 0x60, 0x70, 0x73];
const LZ4_BLOCK_MAX: usize = 4 << 20;

fn lz4_bound(total: usize, parts: usize) -> usize {
    let blocks = total / LZ4_BLOCK_MAX + parts;
    LZ4_FRAME_HEADER.len() + 4 + blocks * 4 + total + total / 255 + blocks * 16 + 64
}

fn zstd_error(code: usize) -> io::Error {
    io::Error::other(format!("zstd: {}", zstd_safe::get_error_name(code)))
}

/// Compresses `parts` (one record stream, in order) into `out` (cleared first); the
/// capacity is reserved up front, so `out` grows only for a larger chunk than any before.
fn compress_parts(kind: ChunkCompression, ctx: &mut Option<CCtx<'static>>, out: &mut Vec<u8>, parts: &[&[u8]]) -> io::Result<()> {
    out.clear();
    let total: usize = parts.iter().map(|p| p.len()).sum();
    match kind {
        ChunkCompression::None => {
            out.reserve(total);
            for p in parts {
                out.extend_from_slice(p);
            }
        }
        ChunkCompression::Zstd => {
            out.reserve(zstd_safe::compress_bound(total));
            let cctx = match ctx {
                Some(c) => c,
                None => {
                    let mut c = CCtx::create();
                    c.set_parameter(CParameter::CompressionLevel(ZSTD_LEVEL)).map_err(zstd_error)?;
                    ctx.insert(c)
                }
            };
            cctx.reset(ResetDirective::SessionOnly).map_err(zstd_error)?;
            // The size in the frame header: readers that decompress in one call need it.
            cctx.set_pledged_src_size(Some(total as u64)).map_err(zstd_error)?;
            for (i, part) in parts.iter().enumerate() {
                let end = if i + 1 == parts.len() { ZSTD_EndDirective::ZSTD_e_end } else { ZSTD_EndDirective::ZSTD_e_continue };
                let mut input = InBuffer::around(part);
                loop {
                    let pos = out.len();
                    let mut output = OutBuffer::around_pos(out, pos);
                    let left = cctx.compress_stream2(&mut output, &mut input, end).map_err(zstd_error)?;
                    let done = input.pos() == part.len() && (end == ZSTD_EndDirective::ZSTD_e_continue || left == 0);
                    if done {
                        break;
                    }
                    if out.len() == out.capacity() {
                        return Err(io::Error::other("zstd: output bound exceeded"));
                    }
                }
            }
        }
        ChunkCompression::Lz4 => {
            out.reserve(lz4_bound(total, parts.len()));
            out.extend_from_slice(&LZ4_FRAME_HEADER);
            for part in parts {
                for block in part.chunks(LZ4_BLOCK_MAX) {
                    let at = out.len();
                    let room = lz4_flex::block::get_maximum_output_size(block.len());
                    out.resize(at + 4 + room, 0);
                    let n = lz4_flex::block::compress_into(block, &mut out[at + 4..]).map_err(|e| io::Error::other(format!("lz4: {e}")))?;
                    if n < block.len() {
                        out[at..at + 4].copy_from_slice(&(n as u32).to_le_bytes());
                        out.truncate(at + 4 + n);
                    } else {
                        // Stored: the high bit marks an uncompressed block.
                        out.truncate(at);
                        out.extend_from_slice(&(block.len() as u32 | 0x8000_0000).to_le_bytes());
                        out.extend_from_slice(block);
                    }
                }
            }
            out.extend_from_slice(&0u32.to_le_bytes());
        }
    }
    Ok(())
}

/// The MCAP magic at both ends of a file.
pub const MAGIC: [u8; 8] = *b"\x89MCAP0\r\n";

/// Record opcodes (MCAP specification, "Records"), shared with the reader.
pub(crate) mod op {
    pub const HEADER: u8 = 0x01;
    pub const FOOTER: u8 = 0x02;
    pub const SCHEMA: u8 = 0x03;
    pub const CHANNEL: u8 = 0x04;
    pub const MESSAGE: u8 = 0x05;
    pub const CHUNK: u8 = 0x06;
    pub const MESSAGE_INDEX: u8 = 0x07;
    pub const CHUNK_INDEX: u8 = 0x08;
    pub const STATISTICS: u8 = 0x0B;
    pub const METADATA: u8 = 0x0C;
    pub const METADATA_INDEX: u8 = 0x0D;
    pub const SUMMARY_OFFSET: u8 = 0x0E;
    pub const DATA_END: u8 = 0x0F;
}

/// Opcode, record length, channel id, sequence, log time, publish time.
const MESSAGE_HEAD_BYTES: usize = 1 + 8 + 2 + 4 + 8 + 8;
/// Chunk fields before the records: start and end time, uncompressed size and CRC, the
/// compression string's length (its bytes come on top), the records' length.
const CHUNK_FIELDS_BYTES: u64 = 8 + 8 + 8 + 4 + 4 + 8;

/// One chunk's entry of the summary's chunk index.
#[derive(Clone, Copy, Debug)]
struct ChunkIndexEntry {
    start_ns: u64,
    end_ns: u64,
    offset: u64,
    length: u64,
    /// Range in [`WriterBuffers::message_index_offsets`].
    offsets_from: usize,
    offsets_to: usize,
    message_index_bytes: u64,
    records_bytes: u64,
    compressed_bytes: u64,
    compression: ChunkCompression,
}

/// The buffers a writer works in, passed from a finished writer to the next one so a new
/// segment starts warm.
#[derive(Default)]
pub struct WriterBuffers {
    chunk: Vec<u8>,
    /// Message index entries (log time, offset in the chunk), one list per channel slot.
    channel_entries: Vec<Vec<(u64, u64)>>,
    chunk_indexes: Vec<ChunkIndexEntry>,
    message_index_offsets: Vec<(u16, u64)>,
    /// Small records written outside chunks (schemas, channels, indexes, summary).
    scratch: Vec<u8>,
    metadata_indexes: Vec<(u64, u64, String)>,
    /// The compressed records of the chunk being written.
    compressed: Vec<u8>,
    /// The zstd context, created with the first compressed chunk and reused.
    zstd: Option<CCtx<'static>>,
}

impl WriterBuffers {
    /// Buffers for chunks of `chunk_bytes`, `channels` channels and about `chunks` chunks per
    /// file: reserved now so the first segment does not grow them either.
    pub fn with_capacity(chunk_bytes: usize, channels: usize, chunks: usize) -> Self {
        WriterBuffers {
            chunk: Vec::with_capacity(chunk_bytes),
            channel_entries: (0..channels).map(|_| Vec::with_capacity(256)).collect(),
            chunk_indexes: Vec::with_capacity(chunks),
            message_index_offsets: Vec::with_capacity(chunks * channels.max(1)),
            scratch: Vec::with_capacity(4096),
            metadata_indexes: Vec::with_capacity(8),
            compressed: Vec::with_capacity(zstd_safe::compress_bound(chunk_bytes).max(lz4_bound(chunk_bytes, 2))),
            zstd: None,
        }
    }
}

struct ChannelSlot {
    id: u16,
    schema_id: u16,
    topic: String,
    message_encoding: String,
    metadata: BTreeMap<String, String>,
    messages: u64,
}

struct SchemaSlot {
    id: u16,
    name: String,
    encoding: String,
    data: Vec<u8>,
}

/// The output with its position and the running CRC of everything written.
struct Output<W: Write> {
    inner: W,
    pos: u64,
    crc: crc32fast::Hasher,
}

impl<W: Write> Output<W> {
    fn put(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.inner.write_all(bytes)?;
        self.crc.update(bytes);
        self.pos += bytes.len() as u64;
        Ok(())
    }
}

fn put_u16(v: &mut Vec<u8>, x: u16) {
    v.extend_from_slice(&x.to_le_bytes());
}
fn put_u32(v: &mut Vec<u8>, x: u32) {
    v.extend_from_slice(&x.to_le_bytes());
}
fn put_u64(v: &mut Vec<u8>, x: u64) {
    v.extend_from_slice(&x.to_le_bytes());
}
fn put_str(v: &mut Vec<u8>, s: &str) {
    put_u32(v, s.len() as u32);
    v.extend_from_slice(s.as_bytes());
}
fn put_map(v: &mut Vec<u8>, map: &BTreeMap<String, String>) {
    let bytes: usize = map.iter().map(|(k, x)| 8 + k.len() + x.len()).sum();
    put_u32(v, bytes as u32);
    for (k, x) in map {
        put_str(v, k);
        put_str(v, x);
    }
}
/// Starts a record in `v`; [`end_record`] fills in its length.
fn begin_record(v: &mut Vec<u8>, opcode: u8) -> usize {
    v.push(opcode);
    put_u64(v, 0);
    v.len()
}
fn end_record(v: &mut [u8], content_from: usize) {
    let len = (v.len() - content_from) as u64;
    v[content_from - 8..content_from].copy_from_slice(&len.to_le_bytes());
}

fn message_head(channel_id: u16, sequence: u32, log_time_ns: u64, publish_time_ns: u64, data_len: usize) -> [u8; MESSAGE_HEAD_BYTES] {
    let mut h = [0u8; MESSAGE_HEAD_BYTES];
    h[0] = op::MESSAGE;
    h[1..9].copy_from_slice(&((MESSAGE_HEAD_BYTES - 9 + data_len) as u64).to_le_bytes());
    h[9..11].copy_from_slice(&channel_id.to_le_bytes());
    h[11..15].copy_from_slice(&sequence.to_le_bytes());
    h[15..23].copy_from_slice(&log_time_ns.to_le_bytes());
    h[23..31].copy_from_slice(&publish_time_ns.to_le_bytes());
    h
}

fn invalid(msg: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, msg)
}

/// Writes one MCAP file. Call [`ChunkedWriter::finish`] to write the summary and footer; a
/// writer that is dropped instead leaves the file as far as it got (recovery reads it).
pub struct ChunkedWriter<W: Write> {
    out: Output<W>,
    chunk_limit: usize,
    buf: WriterBuffers,
    chunk_start_ns: u64,
    chunk_end_ns: u64,
    schemas: Vec<SchemaSlot>,
    /// Sorted by id.
    channels: Vec<ChannelSlot>,
    messages: u64,
    first_ns: u64,
    last_ns: u64,
    metadata_count: u32,
    compression: ChunkCompression,
}

impl<W: Write> ChunkedWriter<W> {
    /// Writes the magic and the header record. Messages are gathered into chunks of at most
    /// `chunk_bytes` (a larger message gets a chunk of its own).
    pub fn new(out: W, library: &str, chunk_bytes: usize, buf: WriterBuffers) -> io::Result<Self> {
        Self::with_profile(out, "", library, chunk_bytes, buf)
    }

    /// [`ChunkedWriter::new`] with a header `profile` (`ros2` for a ROS 2 bag's files).
    pub fn with_profile(out: W, profile: &str, library: &str, chunk_bytes: usize, mut buf: WriterBuffers) -> io::Result<Self> {
        buf.chunk.clear();
        if buf.chunk.capacity() < chunk_bytes {
            buf.chunk.reserve_exact(chunk_bytes);
        }
        buf.chunk_indexes.clear();
        buf.message_index_offsets.clear();
        buf.metadata_indexes.clear();
        for e in &mut buf.channel_entries {
            e.clear();
        }
        let mut w = ChunkedWriter {
            out: Output { inner: out, pos: 0, crc: crc32fast::Hasher::new() },
            chunk_limit: chunk_bytes.max(MESSAGE_HEAD_BYTES + 1),
            buf,
            chunk_start_ns: u64::MAX,
            chunk_end_ns: 0,
            schemas: Vec::new(),
            channels: Vec::new(),
            messages: 0,
            first_ns: u64::MAX,
            last_ns: 0,
            metadata_count: 0,
            compression: ChunkCompression::None,
        };
        w.out.put(&MAGIC)?;
        let s = &mut w.buf.scratch;
        s.clear();
        let from = begin_record(s, op::HEADER);
        put_str(s, profile);
        put_str(s, library);
        end_record(s, from);
        w.out.put(&w.buf.scratch)?;
        Ok(w)
    }

    /// Compresses the chunks written from now on (files start with [`ChunkCompression::None`]).
    pub fn set_compression(&mut self, compression: ChunkCompression) {
        self.compression = compression;
    }

    /// Bytes written so far (what the file holds once the output is flushed).
    pub fn position(&self) -> u64 {
        self.out.pos
    }

    fn put_scratch(&mut self) -> io::Result<()> {
        self.out.put(&self.buf.scratch)
    }

    /// Whether schema `id` is registered.
    pub fn has_schema(&self, id: u16) -> bool {
        self.schemas.iter().any(|s| s.id == id)
    }

    /// Whether channel `id` is registered.
    pub fn has_channel(&self, id: u16) -> bool {
        self.channels.iter().any(|c| c.id == id)
    }

    /// Registers schema `id` (1..; 0 means "no schema") and writes its record.
    pub fn add_schema(&mut self, id: u16, name: &str, encoding: &str, data: &[u8]) -> io::Result<()> {
        if id == 0 || self.has_schema(id) {
            return Err(invalid(format!("schema id {id} is reserved or already registered")));
        }
        self.schemas.push(SchemaSlot { id, name: name.into(), encoding: encoding.into(), data: data.to_vec() });
        let s = &mut self.buf.scratch;
        s.clear();
        schema_record(s, self.schemas.last().expect("pushed"));
        self.put_scratch()
    }

    /// Registers channel `id` on `schema_id` (0: schemaless) and writes its record.
    pub fn add_channel(&mut self, id: u16, schema_id: u16, topic: &str, message_encoding: &str, metadata: &BTreeMap<String, String>) -> io::Result<()> {
        if self.has_channel(id) {
            return Err(invalid(format!("channel id {id} ({topic}) is already registered")));
        }
        if schema_id != 0 && !self.schemas.iter().any(|s| s.id == schema_id) {
            return Err(invalid(format!("channel {topic} names schema {schema_id}, which is not registered")));
        }
        let slot = ChannelSlot { id, schema_id, topic: topic.into(), message_encoding: message_encoding.into(), metadata: metadata.clone(), messages: 0 };
        let at = self.channels.partition_point(|c| c.id < id);
        self.channels.insert(at, slot);
        // One message-index list per channel slot, kept in the same order as the channels.
        let entries = if self.buf.channel_entries.len() > self.channels.len() - 1 { self.buf.channel_entries.pop().expect("non-empty") } else { Vec::with_capacity(256) };
        self.buf.channel_entries.insert(at, entries);
        let s = &mut self.buf.scratch;
        s.clear();
        channel_record(s, &self.channels[at]);
        self.put_scratch()
    }

    /// Writes a metadata record (after closing the open chunk, so records stay in call order).
    pub fn write_metadata(&mut self, name: &str, metadata: &BTreeMap<String, String>) -> io::Result<()> {
        self.close_chunk()?;
        let offset = self.out.pos;
        let s = &mut self.buf.scratch;
        s.clear();
        let from = begin_record(s, op::METADATA);
        put_str(s, name);
        put_map(s, metadata);
        end_record(s, from);
        let length = s.len() as u64;
        self.put_scratch()?;
        self.buf.metadata_indexes.push((offset, length, name.to_string()));
        self.metadata_count += 1;
        Ok(())
    }

    /// Writes one message on a registered channel.
    pub fn write_message(&mut self, channel_id: u16, sequence: u32, log_time_ns: u64, publish_time_ns: u64, data: &[u8]) -> io::Result<()> {
        let Some(slot) = self.channels.iter().position(|c| c.id == channel_id) else {
            return Err(invalid(format!("message on channel {channel_id}, which is not registered")));
        };
        let head = message_head(channel_id, sequence, log_time_ns, publish_time_ns, data.len());
        let record_bytes = MESSAGE_HEAD_BYTES + data.len();
        if record_bytes > self.chunk_limit {
            self.close_chunk()?;
            self.write_single_message_chunk(slot, &head, log_time_ns, data)?;
        } else {
            if self.buf.chunk.len() + record_bytes > self.chunk_limit {
                self.close_chunk()?;
            }
            let offset = self.buf.chunk.len() as u64;
            self.buf.chunk.extend_from_slice(&head);
            self.buf.chunk.extend_from_slice(data);
            self.buf.channel_entries[slot].push((log_time_ns, offset));
            self.chunk_start_ns = self.chunk_start_ns.min(log_time_ns);
            self.chunk_end_ns = self.chunk_end_ns.max(log_time_ns);
        }
        self.channels[slot].messages += 1;
        self.messages += 1;
        self.first_ns = self.first_ns.min(log_time_ns);
        self.last_ns = self.last_ns.max(log_time_ns);
        Ok(())
    }

    fn chunk_header(&mut self, start_ns: u64, end_ns: u64, records_bytes: u64, crc: u32, compression: &str, compressed_bytes: u64) -> io::Result<u64> {
        let offset = self.out.pos;
        let name = compression.as_bytes();
        let mut h = [0u8; 9 + 8 + 8 + 8 + 4 + 4];
        h[0] = op::CHUNK;
        h[1..9].copy_from_slice(&(CHUNK_FIELDS_BYTES + name.len() as u64 + compressed_bytes).to_le_bytes());
        h[9..17].copy_from_slice(&start_ns.to_le_bytes());
        h[17..25].copy_from_slice(&end_ns.to_le_bytes());
        h[25..33].copy_from_slice(&records_bytes.to_le_bytes());
        h[33..37].copy_from_slice(&crc.to_le_bytes());
        h[37..41].copy_from_slice(&(name.len() as u32).to_le_bytes());
        self.out.put(&h)?;
        self.out.put(name)?;
        self.out.put(&compressed_bytes.to_le_bytes())?;
        Ok(offset)
    }

    /// Writes the message index records of the chunk just written and its chunk index entry.
    fn index_chunk(&mut self, start_ns: u64, end_ns: u64, offset: u64, records_bytes: u64, compressed_bytes: u64) -> io::Result<()> {
        let length = self.out.pos - offset;
        let offsets_from = self.buf.message_index_offsets.len();
        let index_from = self.out.pos;
        for slot in 0..self.channels.len() {
            if self.buf.channel_entries[slot].is_empty() {
                continue;
            }
            let at = self.out.pos;
            let s = &mut self.buf.scratch;
            s.clear();
            let from = begin_record(s, op::MESSAGE_INDEX);
            put_u16(s, self.channels[slot].id);
            put_u32(s, (16 * self.buf.channel_entries[slot].len()) as u32);
            for &(t, o) in &self.buf.channel_entries[slot] {
                put_u64(s, t);
                put_u64(s, o);
            }
            end_record(s, from);
            self.put_scratch()?;
            self.buf.message_index_offsets.push((self.channels[slot].id, at));
            self.buf.channel_entries[slot].clear();
        }
        self.buf.chunk_indexes.push(ChunkIndexEntry {
            start_ns,
            end_ns,
            offset,
            length,
            offsets_from,
            offsets_to: self.buf.message_index_offsets.len(),
            message_index_bytes: self.out.pos - index_from,
            records_bytes,
            compressed_bytes,
            compression: self.compression,
        });
        Ok(())
    }

    fn write_single_message_chunk(&mut self, slot: usize, head: &[u8; MESSAGE_HEAD_BYTES], log_time_ns: u64, data: &[u8]) -> io::Result<()> {
        let records_bytes = (MESSAGE_HEAD_BYTES + data.len()) as u64;
        let mut crc = crc32fast::Hasher::new();
        crc.update(head);
        crc.update(data);
        let (offset, compressed_bytes) = if self.compression == ChunkCompression::None {
            let offset = self.chunk_header(log_time_ns, log_time_ns, records_bytes, crc.finalize(), "", records_bytes)?;
            self.out.put(head)?;
            self.out.put(data)?;
            (offset, records_bytes)
        } else {
            compress_parts(self.compression, &mut self.buf.zstd, &mut self.buf.compressed, &[head, data])?;
            let n = self.buf.compressed.len() as u64;
            let offset = self.chunk_header(log_time_ns, log_time_ns, records_bytes, crc.finalize(), self.compression.mcap_name(), n)?;
            self.out.put(&self.buf.compressed)?;
            (offset, n)
        };
        self.buf.channel_entries[slot].push((log_time_ns, 0));
        self.index_chunk(log_time_ns, log_time_ns, offset, records_bytes, compressed_bytes)
    }

    /// Writes the open chunk (if it holds anything) with its message indexes.
    pub fn close_chunk(&mut self) -> io::Result<()> {
        if self.buf.chunk.is_empty() {
            return Ok(());
        }
        let records_bytes = self.buf.chunk.len() as u64;
        let crc = crc32fast::hash(&self.buf.chunk);
        let (start_ns, end_ns) = (self.chunk_start_ns, self.chunk_end_ns);
        let (offset, compressed_bytes) = if self.compression == ChunkCompression::None {
            let offset = self.chunk_header(start_ns, end_ns, records_bytes, crc, "", records_bytes)?;
            self.out.put(&self.buf.chunk)?;
            (offset, records_bytes)
        } else {
            compress_parts(self.compression, &mut self.buf.zstd, &mut self.buf.compressed, &[&self.buf.chunk])?;
            let n = self.buf.compressed.len() as u64;
            let offset = self.chunk_header(start_ns, end_ns, records_bytes, crc, self.compression.mcap_name(), n)?;
            self.out.put(&self.buf.compressed)?;
            (offset, n)
        };
        self.buf.chunk.clear();
        self.chunk_start_ns = u64::MAX;
        self.chunk_end_ns = 0;
        self.index_chunk(start_ns, end_ns, offset, records_bytes, compressed_bytes)
    }

    /// Closes the open chunk and flushes the output (a chunk boundary the file can be
    /// recovered up to).
    pub fn flush(&mut self) -> io::Result<()> {
        self.close_chunk()?;
        self.out.inner.flush()
    }

    /// Writes the data end, the summary (schemas, channels, statistics, chunk indexes,
    /// metadata indexes, summary offsets), the footer and the closing magic. Returns the
    /// output and the buffers for the next file.
    pub fn finish(mut self) -> io::Result<(W, WriterBuffers)> {
        self.close_chunk()?;
        let data_crc = self.out.crc.clone().finalize();
        let s = &mut self.buf.scratch;
        s.clear();
        let from = begin_record(s, op::DATA_END);
        put_u32(s, data_crc);
        end_record(s, from);
        self.put_scratch()?;

        // From here the CRC is the summary's.
        self.out.crc = crc32fast::Hasher::new();
        let summary_start = self.out.pos;
        let mut groups: [(u8, u64, u64); 5] = [(0, 0, 0); 5];
        let mut n_groups = 0;
        let mut group = |w: &mut Self, opcode: u8, start: u64| {
            if w.out.pos > start {
                groups[n_groups] = (opcode, start, w.out.pos - start);
                n_groups += 1;
            }
        };

        let start = self.out.pos;
        for i in 0..self.schemas.len() {
            self.buf.scratch.clear();
            schema_record(&mut self.buf.scratch, &self.schemas[i]);
            self.put_scratch()?;
        }
        group(&mut self, op::SCHEMA, start);

        let start = self.out.pos;
        for i in 0..self.channels.len() {
            self.buf.scratch.clear();
            channel_record(&mut self.buf.scratch, &self.channels[i]);
            self.put_scratch()?;
        }
        group(&mut self, op::CHANNEL, start);

        let start = self.out.pos;
        let s = &mut self.buf.scratch;
        s.clear();
        let from = begin_record(s, op::STATISTICS);
        put_u64(s, self.messages);
        put_u16(s, self.schemas.len() as u16);
        put_u32(s, self.channels.len() as u32);
        put_u32(s, 0); // attachments
        put_u32(s, self.metadata_count);
        put_u32(s, self.buf.chunk_indexes.len() as u32);
        let (first, last) = if self.messages == 0 { (0, 0) } else { (self.first_ns, self.last_ns) };
        put_u64(s, first);
        put_u64(s, last);
        put_u32(s, (10 * self.channels.len()) as u32);
        for c in &self.channels {
            put_u16(s, c.id);
            put_u64(s, c.messages);
        }
        end_record(s, from);
        self.put_scratch()?;
        group(&mut self, op::STATISTICS, start);

        let start = self.out.pos;
        for i in 0..self.buf.chunk_indexes.len() {
            let e = self.buf.chunk_indexes[i];
            let s = &mut self.buf.scratch;
            s.clear();
            let from = begin_record(s, op::CHUNK_INDEX);
            put_u64(s, e.start_ns);
            put_u64(s, e.end_ns);
            put_u64(s, e.offset);
            put_u64(s, e.length);
            put_u32(s, (10 * (e.offsets_to - e.offsets_from)) as u32);
            for &(id, at) in &self.buf.message_index_offsets[e.offsets_from..e.offsets_to] {
                put_u16(s, id);
                put_u64(s, at);
            }
            put_u64(s, e.message_index_bytes);
            put_str(s, e.compression.mcap_name());
            put_u64(s, e.compressed_bytes);
            put_u64(s, e.records_bytes);
            end_record(s, from);
            self.put_scratch()?;
        }
        group(&mut self, op::CHUNK_INDEX, start);

        let start = self.out.pos;
        for i in 0..self.buf.metadata_indexes.len() {
            let s = &mut self.buf.scratch;
            s.clear();
            let (offset, length, name) = &self.buf.metadata_indexes[i];
            let from = begin_record(s, op::METADATA_INDEX);
            put_u64(s, *offset);
            put_u64(s, *length);
            put_str(s, name);
            end_record(s, from);
            self.put_scratch()?;
        }
        group(&mut self, op::METADATA_INDEX, start);

        let summary_offset_start = self.out.pos;
        for &(opcode, start, length) in &groups[..n_groups] {
            let s = &mut self.buf.scratch;
            s.clear();
            let from = begin_record(s, op::SUMMARY_OFFSET);
            s.push(opcode);
            put_u64(s, start);
            put_u64(s, length);
            end_record(s, from);
            self.put_scratch()?;
        }
        let s = &mut self.buf.scratch;
        s.clear();
        s.push(op::FOOTER);
        put_u64(s, 20);
        put_u64(s, summary_start);
        put_u64(s, summary_offset_start);
        self.put_scratch()?;
        let summary_crc = self.out.crc.clone().finalize();
        self.out.put(&summary_crc.to_le_bytes())?;
        self.out.put(&MAGIC)?;
        self.out.inner.flush()?;
        Ok((self.out.inner, self.buf))
    }

    /// Gives up on the file: the output as far as it was written (nothing more is written)
    /// and the buffers.
    pub fn abandon(self) -> (W, WriterBuffers) {
        (self.out.inner, self.buf)
    }
}

fn schema_record(s: &mut Vec<u8>, schema: &SchemaSlot) {
    let from = begin_record(s, op::SCHEMA);
    put_u16(s, schema.id);
    put_str(s, &schema.name);
    put_str(s, &schema.encoding);
    put_u32(s, schema.data.len() as u32);
    s.extend_from_slice(&schema.data);
    end_record(s, from);
}

fn channel_record(s: &mut Vec<u8>, c: &ChannelSlot) {
    let from = begin_record(s, op::CHANNEL);
    put_u16(s, c.id);
    put_u16(s, c.schema_id);
    put_str(s, &c.topic);
    put_str(s, &c.message_encoding);
    put_map(s, &c.metadata);
    end_record(s, from);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_sample(chunk_bytes: usize) -> Vec<u8> {
        write_sample_with(chunk_bytes, ChunkCompression::None)
    }

    fn write_sample_with(chunk_bytes: usize, compression: ChunkCompression) -> Vec<u8> {
        let mut w = ChunkedWriter::new(Vec::new(), "test", chunk_bytes, WriterBuffers::default()).unwrap();
        w.set_compression(compression);
        let mut meta = BTreeMap::new();
        meta.insert("board".to_string(), "sim".to_string());
        w.write_metadata("duv.board", &meta).unwrap();
        w.add_schema(1, "foxglove.PoseInFrame", "protobuf", b"schema bytes").unwrap();
        w.add_channel(3, 1, "/pose", "protobuf", &BTreeMap::new()).unwrap();
        w.add_channel(0, 0, "/state", "json", &meta).unwrap();
        for i in 0..100u32 {
            let body = vec![i as u8; 50 + (i as usize % 7) * 13];
            w.write_message(3, i, 1_000 + 10 * i as u64, 2_000 + i as u64, &body).unwrap();
            if i % 3 == 0 {
                w.write_message(0, i / 3, 1_005 + 10 * i as u64, 0, b"{\"ok\":true}").unwrap();
            }
            if i == 40 {
                w.flush().unwrap();
                // Larger than a chunk: a chunk of its own.
                w.write_message(3, 1000, 1_401, 1_401, &vec![7u8; 3 * chunk_bytes]).unwrap();
            }
        }
        let (out, _) = w.finish().unwrap();
        out
    }

    #[test]
    fn the_mcap_crate_reads_every_message_the_summary_and_the_indexes() {
        let bytes = write_sample(1024);
        // Linear reading with chunk and data-section CRCs validated.
        let messages: Vec<_> = mcap::MessageStream::new(&bytes).unwrap().map(|m| m.unwrap()).collect();
        assert_eq!(messages.len(), 100 + 34 + 1);
        let big = messages.iter().find(|m| m.sequence == 1000).unwrap();
        assert_eq!(big.data.len(), 3072);
        assert_eq!(big.channel.topic, "/pose");
        assert_eq!(messages[0].channel.schema.as_ref().unwrap().name, "foxglove.PoseInFrame");
        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        let stats = summary.stats.as_ref().unwrap();
        assert_eq!(stats.message_count, 135);
        assert_eq!(stats.channel_message_counts[&3], 101);
        assert_eq!(stats.channel_message_counts[&0], 34);
        assert_eq!(stats.metadata_count, 1);
        assert_eq!(stats.message_start_time, 1_000);
        assert_eq!(stats.message_end_time, 1_000 + 990 + 5);
        assert_eq!(summary.channels.len(), 2);
        assert_eq!(summary.schemas.len(), 1);
        assert_eq!(summary.metadata_indexes.len(), 1);
        assert_eq!(stats.chunk_count as usize, summary.chunk_indexes.len());
        assert!(summary.chunk_indexes.len() > 5, "{} chunks", summary.chunk_indexes.len());
        // Every message index points at its message.
        let mut indexed = 0;
        for ci in &summary.chunk_indexes {
            let indexes = summary.read_message_indexes(&bytes, ci).unwrap();
            for (channel, entries) in indexes {
                for e in entries {
                    let m = summary.seek_message(&bytes, ci, &e).unwrap();
                    assert_eq!(m.channel.id, channel.id);
                    assert_eq!(m.log_time, e.log_time);
                    indexed += 1;
                }
            }
        }
        assert_eq!(indexed, 135);
        // The data-section and summary CRCs (checked by hand: the readers above may skip them).
        let n = bytes.len();
        let u32_at = |i: usize| u32::from_le_bytes(bytes[i..i + 4].try_into().unwrap());
        let footer = n - 8 - 29;
        assert_eq!(bytes[footer], op::FOOTER);
        let summary_start = u64::from_le_bytes(bytes[footer + 9..footer + 17].try_into().unwrap()) as usize;
        let data_end = summary_start - 13;
        assert_eq!(bytes[data_end], op::DATA_END);
        assert_eq!(crc32fast::hash(&bytes[..data_end]), u32_at(data_end + 9));
        assert_eq!(crc32fast::hash(&bytes[summary_start..n - 12]), u32_at(n - 12));
    }

    #[test]
    fn a_warm_writer_does_not_allocate_per_message_and_bad_ids_are_refused() {
        let mut w = ChunkedWriter::new(Vec::with_capacity(1 << 20), "test", 4096, WriterBuffers::with_capacity(4096, 2, 64)).unwrap();
        w.add_channel(1, 0, "/a", "json", &BTreeMap::new()).unwrap();
        assert!(w.add_channel(1, 0, "/a", "json", &BTreeMap::new()).is_err());
        assert!(w.add_channel(2, 9, "/b", "json", &BTreeMap::new()).is_err());
        let e = w.write_message(5, 0, 0, 0, b"x").unwrap_err();
        assert!(e.to_string().contains("channel 5"), "{e}");
        for i in 0..200 {
            w.write_message(1, i, i as u64, i as u64, &[1u8; 100]).unwrap();
        }
        let cap = (w.buf.chunk.capacity(), w.buf.channel_entries[0].capacity(), w.buf.chunk_indexes.capacity());
        for i in 200..400 {
            w.write_message(1, i, i as u64, i as u64, &[1u8; 100]).unwrap();
        }
        assert_eq!(cap, (w.buf.chunk.capacity(), w.buf.channel_entries[0].capacity(), w.buf.chunk_indexes.capacity()));
        let (out, _) = w.finish().unwrap();
        assert_eq!(mcap::MessageStream::new(&out).unwrap().count(), 400);
    }

    #[test]
    fn compressed_chunks_read_back_with_their_indexes_and_are_smaller() {
        let plain = write_sample(1024);
        let plain_messages = read_all(&plain);
        assert_eq!(plain_messages.len(), 135);
        for kind in [ChunkCompression::Zstd, ChunkCompression::Lz4] {
            let bytes = write_sample_with(1024, kind);
            // Our reader decompresses (ruzstd, lz4_flex's frame decoder) and checks the CRCs.
            assert_eq!(read_all(&bytes), plain_messages, "{kind:?}");
            // The repetitive sample compresses well: under half the file.
            assert!(bytes.len() * 2 < plain.len(), "{kind:?}: {} vs {} bytes", bytes.len(), plain.len());
            // The chunk index says the compression and both sizes.
            let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
            assert!(summary.chunk_indexes.len() > 5);
            for ci in &summary.chunk_indexes {
                assert_eq!(ci.compression, kind.mcap_name());
                assert!(ci.compressed_size < ci.uncompressed_size, "{ci:?}");
            }
        }
    }

    fn read_all(bytes: &[u8]) -> Vec<(u16, u32, u64, Vec<u8>)> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.mcap");
        std::fs::write(&path, bytes).unwrap();
        let mut v = Vec::new();
        let outcome = crate::reader::read_segment(&path, crate::reader::ReadLimits::default(), |m| v.push((m.channel.id, m.sequence, m.log_time_ns, m.data.to_vec()))).unwrap();
        assert!(outcome.complete && outcome.damage.is_none(), "{outcome:?}");
        v
    }

    #[test]
    fn a_warm_compressing_writer_keeps_its_buffers() {
        for kind in [ChunkCompression::Zstd, ChunkCompression::Lz4] {
            let mut w = ChunkedWriter::new(Vec::with_capacity(1 << 22), "test", 4096, WriterBuffers::with_capacity(4096, 2, 256)).unwrap();
            w.set_compression(kind);
            w.add_channel(1, 0, "/a", "json", &BTreeMap::new()).unwrap();
            let big: Vec<u8> = (0..100_000u32).map(|i| (i % 251) as u8).collect();
            let mut caps = Vec::new();
            for round in 0..3 {
                for i in 0..200u32 {
                    w.write_message(1, i, i as u64, i as u64, &[(i % 7) as u8; 100]).unwrap();
                }
                w.write_message(1, 999, 999, 999, &big).unwrap();
                caps.push((round, w.buf.compressed.capacity(), w.buf.chunk.capacity()));
            }
            assert_eq!(caps[1].1, caps[2].1, "{kind:?}: {caps:?}");
            assert_eq!(caps[0].2, caps[2].2, "{kind:?}: {caps:?}");
            let (out, _) = w.finish().unwrap();
            assert_eq!(read_all(&out).len(), 603, "{kind:?}");
        }
    }
}
