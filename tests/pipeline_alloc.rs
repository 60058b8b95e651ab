//! The steady state of the whole threaded pipeline (capture, tracking, mapping and logging
//! threads at once) under a counting allocator, per stage (`alloc::ThreadRole`): after
//! warm-up, frames flow from a live-camera-like source (it decodes into the pipeline's pooled
//! frame, as V4L2 and Aravis do) through tracking, with keyframes and tracker-window records
//! handed to mapping and the log from fixed pools. Capture, tracking (its worker threads
//! included), the mapping thread and the logging thread allocate nothing: the log encodes
//! into reused buffers and writes through our own MCAP writer (`log::chunked`), whose chunk,
//! index and summary buffers are kept from chunk to chunk and segment to segment. (With the
//! `mcap` crate's writer the logging thread made 664 allocations over these 80 frames, about
//! 25 per chunk.) Map checkpoints (every 5 s) and the health record (once a second, on the
//! caller's thread) allocate by design.

#[path = "common/track_sim.rs"]
mod track_sim;

use duv_camera::{CameraError, FrameSource};
use duv_core::config::board::Board;
use duv_core::alloc::CountingAllocator;
use duv_core::{Frame, FrameImage, PinholeCamera};
use duv_pipeline::{self as pipeline, NoMapping, PipelineConfig, StageAllocations};
use duv_sim::{SimRenderer, TrajectoryKind, WaterPreset};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Frames rendered up front, delivered by copying into the caller's frame (no allocation once
/// the frame has the size), and how far delivery got.
struct CopyingSource {
    camera: PinholeCamera,
    frames: Vec<Frame>,
    next: usize,
    delivered: Arc<AtomicU64>,
}

impl FrameSource for CopyingSource {
    fn camera(&self) -> &PinholeCamera {
        &self.camera
    }
    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        let mut f = Frame::empty();
        Ok(self.next_frame_into(&mut f)?.then_some(f))
    }
    fn next_frame_into(&mut self, frame: &mut Frame) -> Result<bool, CameraError> {
        let Some(src) = self.frames.get(self.next) else { return Ok(false) };
        self.next += 1;
        let (FrameImage::Rgb8(s), FrameImage::Rgb8(d)) = (&src.image, &mut frame.image) else { unreachable!("the test source is RGB") };
        d.width = s.width;
        d.height = s.height;
        d.data.clear();
        d.data.extend_from_slice(&s.data);
        frame.seq = src.seq;
        frame.t_ns = src.t_ns;
        self.delivered.store(self.next as u64, Ordering::SeqCst);
        // A camera's pace: tracking keeps up and the queues stay short.
        std::thread::sleep(Duration::from_millis(20));
        Ok(true)
    }
    fn describe(&self) -> String {
        "copying test source".into()
    }
}

#[test]
fn capture_tracking_mapping_and_logging_allocate_nothing_in_the_steady_state() {
    const FRAMES: usize = 220;
    const WARM: u64 = 120;
    const COUNTED: u64 = 80;
    let cfg = track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, FRAMES, 160, 120, 0.3);
    let renderer = SimRenderer::new(&cfg).unwrap();
    let frames = track_sim::render_all(&renderer);
    let camera = *renderer.camera();
    let board = Board::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/sim.toml")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let mut pcfg = PipelineConfig::from_board(&board, dir.path().to_path_buf());
    pcfg.lossless_frames = true;
    // Map checkpoints (every 5 s on a vehicle) serialise the map into a new buffer: periodic,
    // not per frame, and kept out of the counted window here.
    pcfg.checkpoint_interval = Duration::from_secs(3600);
    // A build with the live view has it on here: tracking queues every pose and a frame at
    // every frame time for the live thread, and still allocates nothing.
    #[cfg(feature = "live-view")]
    {
        pcfg.live = Some(duv_core::config::board::LiveSettings { bind: "127.0.0.1:0".into(), image_hz: 60.0, ..Default::default() });
    }
    let cap = track_sim::capacity(2);
    let tracker = duv_track::Tracker::new(&camera, &track_sim::small_tracker_config(), cap).unwrap();
    let delivered = Arc::new(AtomicU64::new(0));
    let source = CopyingSource { camera, frames, next: 0, delivered: delivered.clone() };
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let run = std::thread::spawn(move || pipeline::run(source, tracker, Box::new(NoMapping::with_capacity(FRAMES)), &pcfg, Vec::new(), stop).map(|r| (r.frames_captured, r.log.messages, r.log.syncs, r.after_init_from, r.latencies.len())));
    while delivered.load(Ordering::SeqCst) < WARM {
        std::thread::sleep(Duration::from_millis(2));
    }
    let before = StageAllocations::now();
    let window_start = std::time::Instant::now();
    let first = delivered.load(Ordering::SeqCst);
    while delivered.load(Ordering::SeqCst) < first + COUNTED {
        std::thread::sleep(Duration::from_millis(2));
    }
    let after = StageAllocations::now();
    let window = window_start.elapsed();
    let counted = delivered.load(Ordering::SeqCst) - first;
    let (captured, messages, syncs, after_init_from, tracked) = run.join().unwrap().unwrap();
    let d = |a: usize, b: usize| b - a;
    eprintln!(
        "steady state, {counted} frames: allocations capture {}, tracking {}, mapping {}, logging {} ({captured} frames captured, {messages} messages, {syncs} chunks synced)",
        d(before.capture, after.capture),
        d(before.tracking, after.tracking),
        d(before.mapping, after.mapping),
        d(before.logging, after.logging)
    );
    assert_eq!(captured, FRAMES as u64);
    // The steady-state latency figure starts after the initialisation (the survey initialises
    // within its first half).
    assert!(after_init_from.is_some_and(|i| i > 0 && i < tracked / 2), "after_init_from {after_init_from:?} of {tracked} latencies");
    // The counts are live: start-up allocated on these threads.
    assert!(before.capture > 0 && before.tracking > 0 && before.logging > 0, "{before:?}");
    assert_eq!(d(before.capture, after.capture), 0, "capture allocated in the steady state");
    assert_eq!(d(before.tracking, after.tracking), 0, "tracking allocated in the steady state");
    assert_eq!(d(before.mapping, after.mapping), 0, "the mapping thread (no mapper) allocated in the steady state");
    assert_eq!(d(before.logging, after.logging), 0, "the logging thread allocated in the steady state");
    // The source paces 20 ms per frame, so the window spans several of the log's 0.5 s chunk
    // closes and fsyncs: those are counted too.
    assert!(window.as_secs_f64() >= 3.0 * 0.5, "the counted window ({window:?}) must span several chunk closes");
}

/// The log writer on its own, per frame encoding and chunk compression: once warm, encoding a
/// frame (raw, or JPEG through `log::jpeg` at 4:4:4 and 4:2:0 qualities), writing it,
/// compressing and closing the chunk (zstd, the boards' default, or none) and fsyncing
/// allocate nothing. (libzstd's context is C memory, outside the counting allocator; it is
/// made with the first chunk and reused. `lz4` allocates lz4_flex's hash table per chunk.) (The threaded test above logs raw frames, as `boards/sim.toml`
/// does; the real boards log JPEG.)
#[test]
fn the_log_writer_allocates_nothing_per_frame_once_warm_for_raw_and_jpeg_frames() {
    use duv_core::alloc::count_allocations_on_this_thread;
    use duv_log::{FrameEncoding, LogConfig, LogItem, SegmentWriter};
    let cfg = track_sim::sim_config(WaterPreset::Turbid, TrajectoryKind::Survey, 24, 160, 120, 0.3);
    let frames: Vec<Arc<Frame>> = track_sim::render_all(&SimRenderer::new(&cfg).unwrap()).into_iter().map(Arc::new).collect();
    let cases = [FrameEncoding::Raw, FrameEncoding::Jpeg { quality: 90 }, FrameEncoding::Jpeg { quality: 75 }]
        .into_iter()
        .flat_map(|e| [(e, duv_log::ChunkCompression::Zstd), (e, duv_log::ChunkCompression::None)]);
    for (encoding, compression) in cases {
        let dir = tempfile::tempdir().unwrap();
        let mut lcfg = LogConfig::new(dir.path());
        lcfg.frame_encoding = encoding;
        lcfg.compression = compression;
        lcfg.max_mb_per_s = Some(8.0);
        // Every tick closes the chunk and fsyncs: that path is counted too.
        lcfg.chunk_interval = Duration::ZERO;
        let mut writer = SegmentWriter::create(lcfg).unwrap();
        let mut log = |f: &Arc<Frame>| {
            writer.write(&LogItem::Frame(Arc::clone(f))).unwrap();
            writer.tick().unwrap();
        };
        for f in &frames[..12] {
            log(f);
        }
        let n = count_allocations_on_this_thread(|| {
            for f in &frames[12..] {
                log(f);
            }
        });
        assert_eq!(n, 0, "{encoding:?} {compression:?}: {n} allocations over {} frames", frames.len() - 12);
        let (stats, r) = writer.finish();
        r.unwrap();
        assert_eq!(stats.messages, frames.len() as u64);
        assert!(stats.syncs >= frames.len() as u64, "{encoding:?}: {} syncs", stats.syncs);
    }
}
