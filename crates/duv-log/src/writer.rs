//! Segment files: one MCAP writer at a time, chunks closed and fsynced on a timer, rotation by
//! size and age, and a write error (disk full, device gone) that stops logging cleanly.

use super::chunked::{ChunkCompression, ChunkedWriter, WriterBuffers};
use super::encoder::{schema_in, ItemEncoder};
use super::schema::{FrameEncoding, LogFormat, LogItem, Topic, ALL_TOPICS};
use super::{list_segments, segment_name, LogError};
use duv_core::{PinholeCamera, Timestamp};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Chunks also close at this size (besides every `chunk_interval`): a write failure loses at
/// most the open chunk, and a reader's memory per chunk stays small.
const CHUNK_BYTES: u64 = 512 << 10;

/// The library string in every segment's header.
const LIBRARY: &str = concat!("duv-slam ", env!("CARGO_PKG_VERSION"));

/// Where and how the log is written.
#[derive(Clone, Debug)]
pub struct LogConfig {
    /// Folder of the segment files (created if missing).
    pub dir: PathBuf,
    /// A segment is closed once it holds this many bytes.
    pub segment_max_bytes: u64,
    /// A segment is closed once it has been open this long.
    pub segment_max_age: Duration,
    /// The open chunk is closed and the file fsynced at least this often.
    pub chunk_interval: Duration,
    /// Metadata records written at the start of every segment (board, config, run).
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    /// How input frames are stored (the board's `[log] frame_encoding`).
    pub frame_encoding: FrameEncoding,
    /// Message schemas: Foxglove's, or a ROS 2 bag (the board's `[log] format`).
    pub format: LogFormat,
    /// How chunks are compressed (the board's `[log] compression`).
    pub compression: ChunkCompression,
    /// The byte budget, MB (10^6 bytes) per second of log time (the board's `[log]
    /// max_mb_per_s`); `None`: every map logged.
    pub max_mb_per_s: Option<f64>,
}

impl LogConfig {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        LogConfig {
            dir: dir.into(),
            segment_max_bytes: 256 << 20,
            segment_max_age: Duration::from_secs(600),
            chunk_interval: Duration::from_millis(500),
            metadata: Vec::new(),
            frame_encoding: FrameEncoding::Raw,
            format: LogFormat::Foxglove,
            compression: ChunkCompression::Zstd,
            max_mb_per_s: None,
        }
    }
}

/// What the writer did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LogStats {
    pub messages: u64,
    /// Bytes in finished or synced segment files.
    pub bytes: u64,
    pub segments: u32,
    /// Chunks closed and fsynced.
    pub syncs: u64,
    /// Items dropped because logging had stopped after a write error.
    pub dropped_after_failure: u64,
    /// The write error that stopped logging.
    pub failure: Option<String>,
    /// Map checkpoints (with their point clouds) logged, and skipped because the byte budget
    /// did not cover them.
    pub maps_logged: u64,
    pub maps_skipped: u64,
    /// Log time from the first item to the last, ns (what MB/s is measured over).
    pub span_ns: i64,
}

impl LogStats {
    /// Bytes per second of log time, in MB (10^6 bytes); `None` before a second item.
    pub fn mb_per_s(&self) -> Option<f64> {
        (self.span_ns > 0).then(|| self.bytes as f64 / 1e6 / (self.span_ns as f64 * 1e-9))
    }
}

/// The byte budget: a token bucket filled at `max_mb_per_s` over log time. Every byte written
/// draws from it (what the files grew by); a map is written only when the bucket covers twice
/// its expected size (its uncompressed size times the compression ratio of the last logged
/// map), so that the final map, always written, is paid for too.
#[derive(Clone, Debug)]
struct Budget {
    bytes_per_ns: f64,
    tokens: f64,
    /// The newest log time seen.
    t_ns: Option<i64>,
    /// File bytes already drawn.
    drawn: u64,
    /// Compressed / uncompressed bytes of the last logged map.
    map_ratio: f64,
}

impl Budget {
    fn refill(&mut self, t_ns: i64) {
        if let Some(t0) = self.t_ns {
            if t_ns > t0 {
                self.tokens += (t_ns - t0) as f64 * self.bytes_per_ns;
            }
        }
        self.t_ns = Some(self.t_ns.map_or(t_ns, |t0| t0.max(t_ns)));
    }
}

struct OpenSegment {
    path: PathBuf,
    writer: ChunkedWriter<BufWriter<File>>,
    /// A second handle on the file, for fsync.
    sync: File,
    opened: Instant,
    last_sync: Instant,
    /// Whether the topic's channel (id = topic index) is registered in this segment.
    channels: [bool; ALL_TOPICS.len()],
    messages: u64,
}

/// Writes [`LogItem`]s into `segment-NNNNNN.mcap` files in [`LogConfig::dir`].
pub struct SegmentWriter {
    cfg: LogConfig,
    open: Option<OpenSegment>,
    next_index: u32,
    stats: LogStats,
    failed: bool,
    last_calibration: Option<(Timestamp, PinholeCamera)>,
    /// Message bodies and JPEG streams, buffers reused from item to item.
    encoder: ItemEncoder,
    /// The MCAP writer's buffers, handed from one segment to the next.
    spare: Option<WriterBuffers>,
    /// Called after every fsync with (segment path, messages in it, file bytes).
    on_sync: Option<Box<dyn FnMut(&Path, u64, u64) + Send>>,
    budget: Option<Budget>,
    first_t_ns: Option<i64>,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> LogError + '_ {
    move |source| LogError::Io { path: path.to_path_buf(), source }
}

impl SegmentWriter {
    /// A writer whose first segment follows the newest existing one in the folder.
    pub fn create(cfg: LogConfig) -> Result<Self, LogError> {
        std::fs::create_dir_all(&cfg.dir).map_err(io_err(&cfg.dir))?;
        let existing = list_segments(&cfg.dir)?;
        let next_index = existing.last().map(|(i, _)| i + 1).unwrap_or(0);
        // A resumed run in another format than the folder's: both are read back, but a ROS 2
        // bag lists only its ROS 2 segments.
        if let Some(profile) = existing.last().and_then(|(_, p)| super::bag::read_profile(p).ok()) {
            if profile != cfg.format.profile() {
                let was = if profile == super::ros2::PROFILE { "ros2" } else { "foxglove" };
                tracing::warn!("log: {} holds segments in the {was} format; this run's segments are {} (set [log] format or --log-format to keep one format)", cfg.dir.display(), cfg.format.name());
            }
        }
        let encoder = ItemEncoder::with_format(cfg.format, cfg.frame_encoding);
        // Chunks close every `chunk_interval` or at CHUNK_BYTES, so a segment holds at most
        // about this many; the chunk index table is reserved for it once.
        let by_age = cfg.segment_max_age.as_secs_f64() / cfg.chunk_interval.as_secs_f64().max(1e-3);
        let by_size = cfg.segment_max_bytes / CHUNK_BYTES;
        let chunks = (2.0 * by_age).min(1e6) as usize + by_size as usize + 64;
        let spare = Some(WriterBuffers::with_capacity(CHUNK_BYTES as usize, ALL_TOPICS.len(), chunks));
        let budget = cfg.max_mb_per_s.map(|mb| Budget { bytes_per_ns: mb * 1e6 * 1e-9, tokens: 0.0, t_ns: None, drawn: 0, map_ratio: 1.0 });
        Ok(SegmentWriter { cfg, open: None, next_index, stats: LogStats::default(), failed: false, last_calibration: None, encoder, spare, on_sync: None, budget, first_t_ns: None })
    }

    /// Reports every fsync (the crash harness reads this to know what must survive).
    pub fn set_on_sync(&mut self, f: impl FnMut(&Path, u64, u64) + Send + 'static) {
        self.on_sync = Some(Box::new(f));
    }

    pub fn stats(&self) -> &LogStats {
        &self.stats
    }

    /// Whether a write error has stopped logging.
    pub fn has_failed(&self) -> bool {
        self.failed
    }

    /// Path of the segment being written.
    pub fn current_segment(&self) -> Option<&Path> {
        self.open.as_ref().map(|o| o.path.as_path())
    }

    fn open_segment(&mut self) -> Result<(), LogError> {
        let path = self.cfg.dir.join(segment_name(self.next_index));
        self.next_index += 1;
        // Not create_new: a previous run may have left a file of that index only if recovery
        // failed to rename it, and then it is overwritten on purpose.
        let file = std::fs::OpenOptions::new().write(true).create(true).truncate(true).open(&path).map_err(io_err(&path))?;
        let sync = file.try_clone().map_err(io_err(&path))?;
        let out = BufWriter::with_capacity(1 << 20, file);
        let buffers = self.spare.take().unwrap_or_default();
        let mut writer = ChunkedWriter::with_profile(out, self.cfg.format.profile(), LIBRARY, CHUNK_BYTES as usize, buffers).map_err(io_err(&path))?;
        writer.set_compression(self.cfg.compression);
        let now = Instant::now();
        let mut seg = OpenSegment { path, writer, sync, opened: now, last_sync: now, channels: [false; ALL_TOPICS.len()], messages: 0 };
        for (name, map) in &self.cfg.metadata {
            seg.writer.write_metadata(name, map).map_err(io_err(&seg.path))?;
        }
        self.stats.segments += 1;
        tracing::info!(segment = %seg.path.display(), "log segment opened");
        self.open = Some(seg);
        // Every segment carries the calibration so it can be replayed on its own.
        if let Some((t_ns, camera)) = self.last_calibration {
            self.write_inner(&LogItem::Calibration { t_ns, camera })?;
        }
        Ok(())
    }

    /// The topic's channel id (its index in [`ALL_TOPICS`]; its schema, if any, has id
    /// index + 1), registered on first use in the segment.
    fn channel(seg: &mut OpenSegment, topic: Topic, format: LogFormat, frames: FrameEncoding) -> Result<u16, LogError> {
        let id = topic.index() as u16;
        if seg.channels[topic.index()] {
            return Ok(id);
        }
        let r = match schema_in(topic, format, frames) {
            Some(s) => seg
                .writer
                .add_schema(id + 1, &s.name, &s.encoding, &s.data)
                .and_then(|()| seg.writer.add_channel(id, id + 1, topic.name_in(format), &s.message_encoding, &BTreeMap::new())),
            None => seg.writer.add_channel(id, 0, topic.name_in(format), topic.schemaless_encoding(), &BTreeMap::new()),
        };
        r.map_err(io_err(&seg.path))?;
        seg.channels[topic.index()] = true;
        Ok(id)
    }

    fn write_inner(&mut self, item: &LogItem) -> Result<(), LogError> {
        if self.open.is_none() {
            self.open_segment()?;
        }
        let seg = self.open.as_mut().expect("opened above");
        let mut written = 0u64;
        let (format, frames) = (self.encoder.format(), self.encoder.frame_encoding());
        self.encoder.encode(item, |e, body| {
            let channel_id = Self::channel(seg, e.topic, format, frames)?;
            seg.writer.write_message(channel_id, e.sequence, e.log_time_ns, e.log_time_ns, body).map_err(io_err(&seg.path))?;
            written += 1;
            Ok(())
        })?;
        seg.messages += written;
        self.stats.messages += written;
        Ok(())
    }

    /// Writes one item. A write error stops logging: it is returned once (and logged at
    /// ERROR), the open segment is left as it is on disk (recoverable up to its last synced
    /// chunk), and every later item is dropped and counted.
    pub fn write(&mut self, item: &LogItem) -> Result<(), LogError> {
        if self.failed {
            self.stats.dropped_after_failure += 1;
            return Ok(());
        }
        let t_ns = item.t_ns().t_ns();
        let first = *self.first_t_ns.get_or_insert(t_ns);
        self.stats.span_ns = self.stats.span_ns.max(t_ns - first);
        let mut map_bytes = None;
        if let Some(b) = self.budget.as_mut() {
            b.refill(t_ns);
            if let LogItem::Map { last, .. } = item {
                // Twice its size: what is left must still cover the final map (about as large),
                // which is logged whatever the bucket holds.
                let expected = item.approx_bytes() as f64 * b.map_ratio;
                if !*last && b.tokens < 2.0 * expected {
                    self.stats.maps_skipped += 1;
                    return Ok(());
                }
                map_bytes = Some(item.approx_bytes());
            }
        }
        if matches!(item, LogItem::Map { .. }) {
            self.stats.maps_logged += 1;
        }
        // A large record (map checkpoint, keyframe maps) starts after a closed, synced chunk,
        // so a failure while writing it cannot take the smaller records before it along.
        let large = matches!(item, LogItem::Map { .. } | LogItem::Keyframe(_));
        let pre = if large && self.open.is_some() { self.sync_now() } else { Ok(()) };
        let before = self.file_bytes();
        let result = pre.and_then(|()| self.write_inner(item)).and_then(|()| {
            // A map is a chunk of its own: closed now, so its compressed size is known.
            if map_bytes.is_some() {
                self.sync_now()?;
            }
            self.rotate_if_due(false)
        });
        if let LogItem::Calibration { t_ns, camera } = item {
            self.last_calibration = Some((*t_ns, *camera));
        }
        let now = self.file_bytes();
        if let Some(b) = self.budget.as_mut() {
            if let Some(n) = map_bytes.filter(|&n| n > 0) {
                b.map_ratio = (now.saturating_sub(before) as f64 / n as f64).clamp(0.01, 1.1);
            }
            b.tokens -= now.saturating_sub(b.drawn) as f64;
            b.drawn = now;
        }
        self.check(result)
    }

    /// Bytes in the finished segments and the open one so far.
    fn file_bytes(&self) -> u64 {
        self.stats.bytes + self.open.as_ref().map_or(0, |s| s.writer_pos())
    }

    /// Closes the chunk and fsyncs when [`LogConfig::chunk_interval`] has passed; rotates an
    /// old segment. Call it regularly (the writer thread does, between items).
    pub fn tick(&mut self) -> Result<(), LogError> {
        if self.failed {
            return Ok(());
        }
        let due = self.open.as_ref().is_some_and(|s| s.last_sync.elapsed() >= self.cfg.chunk_interval);
        let result = if due { self.sync_now() } else { Ok(()) }.and_then(|()| self.rotate_if_due(false));
        self.check(result)
    }

    fn check(&mut self, result: Result<(), LogError>) -> Result<(), LogError> {
        if let Err(e) = &result {
            if matches!(e, LogError::Encode { .. } | LogError::EncodeWindow(_)) {
                return result;
            }
            self.failed = true;
            self.stats.failure = Some(e.to_string());
            tracing::error!("logging stopped: {e}");
            if let Some(seg) = self.open.take() {
                // Leave the file exactly as far as it was written (recovery reads it on the
                // next start): what the BufWriter still holds is discarded, not flushed.
                let (out, _) = seg.writer.abandon();
                let (_file, _unflushed) = out.into_parts();
            }
        }
        result
    }

    /// Closes the open chunk, flushes and fsyncs the segment.
    pub fn sync_now(&mut self) -> Result<(), LogError> {
        let Some(seg) = self.open.as_mut() else { return Ok(()) };
        let fail = |path: &Path, problem: String| LogError::WriteFailed { path: path.to_path_buf(), bytes_written: 0, problem };
        seg.writer.flush().map_err(|e| fail(&seg.path, e.to_string()))?;
        seg.sync.sync_data().map_err(|e| fail(&seg.path, e.to_string()))?;
        seg.last_sync = Instant::now();
        self.stats.syncs += 1;
        let bytes = seg.sync.metadata().map(|m| m.len()).unwrap_or(0);
        if let Some(f) = self.on_sync.as_mut() {
            f(&seg.path, seg.messages, bytes);
        }
        Ok(())
    }

    fn rotate_if_due(&mut self, force: bool) -> Result<(), LogError> {
        let Some(seg) = self.open.as_ref() else { return Ok(()) };
        let pos = seg.writer_pos();
        if force || pos >= self.cfg.segment_max_bytes || seg.opened.elapsed() >= self.cfg.segment_max_age {
            self.close_segment()?;
        }
        Ok(())
    }

    fn close_segment(&mut self) -> Result<(), LogError> {
        let Some(seg) = self.open.take() else { return Ok(()) };
        let fail = |path: &Path, problem: String| LogError::WriteFailed { path: path.to_path_buf(), bytes_written: 0, problem };
        let out = match seg.writer.finish() {
            Ok((out, buffers)) => {
                self.spare = Some(buffers);
                out
            }
            Err(e) => return Err(fail(&seg.path, e.to_string())),
        };
        let (_file, _) = out.into_parts();
        seg.sync.sync_all().map_err(|e| fail(&seg.path, e.to_string()))?;
        let bytes = seg.sync.metadata().map(|m| m.len()).unwrap_or(0);
        self.stats.bytes += bytes;
        self.stats.syncs += 1;
        if let Some(f) = self.on_sync.as_mut() {
            f(&seg.path, seg.messages, bytes);
        }
        sync_dir(&self.cfg.dir);
        tracing::info!(segment = %seg.path.display(), bytes, messages = seg.messages, "log segment closed");
        if self.cfg.format == LogFormat::Ros2 {
            // The segments are safe on disk; without the index the folder is re-indexed by
            // recovery on the next start, so a failure here does not stop logging.
            if let Err(e) = super::bag::write_metadata(&self.cfg.dir) {
                tracing::warn!("log: {}: not updated: {e}", super::bag::METADATA_FILE);
            }
        }
        Ok(())
    }

    /// Closes the open segment (summary, footer, fsync) and returns the statistics.
    pub fn finish(mut self) -> (LogStats, Result<(), LogError>) {
        let r = if self.failed { Ok(()) } else { self.close_segment() };
        let r = self.check(r);
        (self.stats.clone(), r)
    }
}

impl OpenSegment {
    fn writer_pos(&self) -> u64 {
        self.writer.position()
    }
}

pub use super::files::sync_dir;
