//! The onboard pipeline: one named thread per stage, bounded queues between them, end of
//! stream passed down, clean shutdown on SIGINT/SIGTERM, health telemetry once a second.
//!
//! ```text
//!  capture ──frames (spread)──> tracking ──keyframes (defer)──> mapping
//!     │                             │                                     │
//!     └───────────── log records (bounded in bytes, drop newest) ────────┴──> logging
//! ```
//!
//! Every capacity comes from the board ([`budget::plan`] refuses a board that cannot hold the
//! resolution). Tracking never waits on mapping or logging: the log edge refuses and counts
//! when full, the keyframe edge defers the keyframe its neighbours cover best to the end of
//! the run ([`keyframe_queue`]). Tracking owns its cores; mapping and logging yield to it
//! ([`placement`]). The caller's thread publishes health and watches the shutdown flag.
//! `deterministic` runs every stage in order on the caller's thread (no drops, no timing):
//! the same input gives bit-identical output.
//!
//! [`run`] is the pipeline; [`run_dive`] ([`dive_run`]) is a whole run around it, what `duv run`
//! does below its command line: the run folder's lock, resume, the mapping stage, the
//! end-of-run keyframe catch-up, the outputs and `dive.json`. The keyframe folder has one
//! writer, [`KeyframeFolder`]. [`export`] reads a finished run folder back as input for offline
//! splatting (a COLMAP text model, a nerfstudio `transforms.json`).

pub mod budget;
pub mod checkpoints;
pub mod clock;
pub mod dive;
pub mod dive_run;
pub mod export;
mod handoff;
pub mod keyframe_folder;
pub mod keyframe_queue;
pub mod live;
pub mod lock;
pub mod map_report;
pub mod mapping;
pub mod metric;
pub mod outputs;
pub mod placement;
pub mod pool;
pub mod progress;
pub mod queue;
pub mod resume;
pub mod source;
pub mod stop;

pub use dive_run::{run_dive, DiveError, DiveOptions, DiveOutcome, Progress};
pub use keyframe_folder::KeyframeFolder;
pub use progress::{ProgressSnapshot, RunProgress};
pub use stop::Stop;

use duv_camera::FrameSource;
use duv_core::config::board::{Board, FrameLogEncoding, LogCompression, LogFormatSetting};
use duv_core::alloc::{self, ThreadRole};
use duv_core::{Frame, Keyframe, Se3, Sim3, Timestamp};
use duv_log::{FrameEncoding, LogConfig, LogItem, LogStats, PoseRecord, SegmentWriter};
use duv_track::{TrackOutput, Tracker, TrajectoryRecorder};
use handoff::{Handoff, HandoffConfig};
use keyframe_queue::{KeyframeQueue, Scheduled};
use placement::{PlacementReport, StageThread, ThreadPlacement};
use queue::{BoundedQueue, FullPolicy, Pushed, QueueStats};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub use budget::BudgetPlan;
pub use checkpoints::CheckpointStore;

/// Errors of the pipeline.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("board {board:?} refused: {problem}")]
    Budget { board: String, problem: String },
    /// A pipeline setting out of range, named (`pace_speed`: `--speed`).
    #[error("{setting} = {value}: {problem}")]
    BadSetting { setting: &'static str, value: f64, problem: &'static str },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: corrupt checkpoint: {problem}")]
    BadCheckpoint { path: PathBuf, problem: String },
    #[error(transparent)]
    Log(#[from] duv_log::LogError),
    #[error(transparent)]
    Track(#[from] duv_track::TrackError),
    #[error("frame source: {0}")]
    Source(#[from] duv_camera::CameraError),
    #[error("stage {stage} failed: {problem}")]
    Stage { stage: &'static str, problem: String },
    #[error("stage mapping failed: {0}")]
    Mapping(#[source] MapStageError),
    #[error("resume from {path}: {problem}")]
    Resume { path: PathBuf, problem: String },
    /// The live view could not start (or this build lacks it).
    #[error("{problem}")]
    Live { problem: String },
    /// A second signal: the log was closed, the other stages were left where they were.
    #[error("stopped at once by a second signal (the log is closed; {frames_captured} frames captured)")]
    Aborted { frames_captured: u64 },
}

/// Why a call of the mapping stage failed ([`MapStage`]); the messages are the stage's own.
#[derive(Debug, thiserror::Error)]
pub enum MapStageError {
    /// The mapper failed (its error names what).
    #[error(transparent)]
    Mapper(#[from] duv_map::stage::StageError),
    /// The mapper's device could not be opened ([`mapping::GaussianMapping::use_device`]).
    #[error(transparent)]
    Device(#[from] duv_map::mapper::MapperError),
    /// Writing a checkpoint's scratch file.
    #[error(transparent)]
    Io(#[from] duv_core::io::IoError),
    /// Writing the keyframe folder.
    #[error(transparent)]
    KeyframeFolder(#[from] keyframe_folder::KeyframeFolderError),
    #[error("mapping keyframe {id}: {source}")]
    Keyframe { id: u64, source: duv_map::stage::StageError },
    #[error("exporting the map to {path}: {source}")]
    Export { path: PathBuf, source: duv_map::stage::StageError },
    /// A [`NoMapping`] checkpoint (its keyframe pose list) that does not decode.
    #[error(transparent)]
    PoseList(#[from] serde_json::Error),
}

/// The mapping stage as the pipeline drives it. The mapper binds to this at merge; tests and
/// tracking-only runs use [`NoMapping`].
pub trait MapStage: Send {
    /// A keyframe from tracking (a pooled buffer: copy what is kept).
    fn add_keyframe(&mut self, kf: &Keyframe) -> Result<(), MapStageError>;
    /// One unit of optimisation when no keyframe is waiting; `false` when idle.
    fn step(&mut self) -> Result<bool, MapStageError>;
    /// A checkpoint to persist now (`None` when nothing changed since the last one).
    fn checkpoint(&mut self) -> Option<MapCheckpoint>;
    /// The run's final checkpoint: made even when nothing changed since the last one (that one
    /// may have been left out of the log for its byte budget), `None` only for an empty map.
    fn final_checkpoint(&mut self) -> Option<MapCheckpoint> {
        self.checkpoint()
    }
    /// The time the mapping thread took to write a checkpoint of this stage to disk (reported
    /// with the stage's own times).
    fn checkpoint_written(&mut self, _took: Duration) {}
    /// Restores a checkpoint written by [`MapStage::checkpoint`] (on resume).
    fn restore(&mut self, bytes: &[u8]) -> Result<(), MapStageError>;
    /// The newest keyframe id the stage was fed (keyframes come in id order), `None` when it
    /// has none or keeps none: on resume, the logged keyframes after it are fed again.
    fn newest_keyframe(&self) -> Option<u64> {
        None
    }
    /// The frame and unit the exports of [`MapStage::finish`] are written in: `to_from_map`
    /// takes the map's frame there (e.g. metres from the navigation sensors); `None`, the
    /// map's own frame (the default).
    fn set_output_frame(&mut self, _to_from_map: Option<Sim3>) {}
    /// The mapper and the restoration of its panels, for the map report (`None`: no map).
    fn mapper_mut(&mut self) -> Option<(&mut duv_map::mapper::Mapper, duv_map::restore::RestoreConfig)> {
        None
    }
    /// Gaussians in the map now (`None`: the stage keeps no map).
    fn gaussians(&self) -> Option<usize> {
        None
    }
    /// Whether the stage runs data-parallel CPU work (the pipeline then gives it a pool of
    /// `threads.mapping` workers); a stage that keeps no map needs none.
    fn uses_cpu_workers(&self) -> bool {
        true
    }
    /// After the run: the final keyframe poses (after loop closures and global BA), a last
    /// optimisation and the exports into `out` (with `optimise` false, a stopped run: no
    /// optimisation and no keyframe renders, the map as it is); a one-line summary for the operator.
    fn finish(&mut self, _final_poses: &[(u64, Se3)], _out: &Path, _optimise: bool) -> Result<Option<String>, MapStageError> {
        Ok(None)
    }
}

/// What the mapping stage persists: the checkpoint file a resume restores, the smaller one the
/// log stores, and the Gaussian centres the log shows as a point cloud.
#[derive(Clone, Debug)]
pub struct MapCheckpoint {
    /// Everything, keyframe pixels included (`checkpoints/map-NNNNNN.ckpt`; [`MapStage::restore`]).
    pub file: Vec<u8>,
    /// For `/map/checkpoint`: the same state with the keyframes referring to their own log
    /// messages instead of embedding their pixels (`map::checkpoint::KeyframePixels`).
    pub logged: Vec<u8>,
    pub centres_in_world: Vec<[f32; 3]>,
    /// The view-independent colour of each centre (RGB) for the live view; empty: none.
    pub colours: Vec<[u8; 3]>,
}

/// A mapping stage that keeps the keyframe poses it was sent (its checkpoint is their list):
/// tracking-only runs, and the stand-in until the mapper is bound.
#[derive(Default)]
pub struct NoMapping {
    pub keyframes: Vec<(u64, i64, [f64; 7])>,
    dirty: bool,
}

impl NoMapping {
    /// Room for `keyframes` poses before the list grows.
    pub fn with_capacity(keyframes: usize) -> Self {
        NoMapping { keyframes: Vec::with_capacity(keyframes), dirty: false }
    }
}

impl MapStage for NoMapping {
    fn uses_cpu_workers(&self) -> bool {
        false
    }
    fn add_keyframe(&mut self, kf: &Keyframe) -> Result<(), MapStageError> {
        self.keyframes.push((kf.index, kf.t_ns.t_ns(), duv_core::pose::se3_to_tum(&kf.world_from_cam)));
        self.dirty = true;
        Ok(())
    }
    fn step(&mut self) -> Result<bool, MapStageError> {
        Ok(false)
    }
    fn checkpoint(&mut self) -> Option<MapCheckpoint> {
        if !std::mem::take(&mut self.dirty) {
            return None;
        }
        let file = serde_json::to_vec(&self.keyframes).ok()?;
        let centres_in_world = self.keyframes.iter().map(|k| [k.2[0] as f32, k.2[1] as f32, k.2[2] as f32]).collect();
        Some(MapCheckpoint { logged: file.clone(), file, centres_in_world, colours: Vec::new() })
    }
    fn restore(&mut self, bytes: &[u8]) -> Result<(), MapStageError> {
        self.keyframes = serde_json::from_slice(bytes)?;
        Ok(())
    }
}

/// Pooled frames beyond the frame queue, the log queue's share and the keyframe lag: the one
/// in tracking, the one being filled, one spare.
pub const FRAME_SLOTS_IN_FLIGHT: usize = 3;
/// Pooled keyframes beyond the keyframe queue: the one in mapping and some in the log queue.
pub const KEYFRAME_SLOTS_IN_FLIGHT: usize = 4;

/// Frames a run records (poses, latencies) before its records grow: an hour at 30 frames/s.
const RECORD_FRAMES: usize = 30 * 3600;
/// Deferred keyframe ids a run remembers for mapping to take from the log at its end.
pub const DEFERRED_KEYFRAMES_KEPT: usize = 1 << 14;

/// How the pipeline runs.
#[derive(Clone, Debug)]
pub struct PipelineConfig {
    /// Output folder: the log goes to `out/log/`, map checkpoints to `out/checkpoints/`.
    pub out_dir: PathBuf,
    pub frame_queue: usize,
    pub keyframe_queue: usize,
    pub log_queue_bytes: usize,
    pub log: LogConfig,
    /// Pace the source at its time stamps divided by this factor (replay); `None`: as fast
    /// as the source delivers.
    pub pace_speed: Option<f64>,
    /// Single-threaded, no drops (bit-identical output).
    pub deterministic: bool,
    /// Capture waits for room in the frame queue instead of dropping a frame: for unpaced
    /// recorded sources (datasets, generated sequences, replay without `--speed`), whose
    /// frames are not lost by waiting. Live and paced sources drop, spread
    /// ([`queue::FullPolicy::Spread`]).
    pub lossless_frames: bool,
    pub health_interval: Duration,
    pub checkpoint_interval: Duration,
    /// Print one line per fsync and per tracked frame on stdout (the crash harness reads it).
    pub announce: bool,
    /// Applied to every pose before it leaves the pipeline (resume: the new tracker's frame
    /// to the recorded map frame).
    pub world_from_tracker: Option<Sim3>,
    /// The board's frame period (health: latency headroom).
    pub frame_period_ms: f64,
    /// The board's host memory budget (health: memory headroom).
    pub host_budget_mb: f64,
    /// Keyframes leave tracking once this many newer ones exist (the board's BA window), so
    /// the depth and variance mapping gets have been through the window BA; the rest at the
    /// end of the stream.
    pub keyframe_lag: usize,
    /// The tracker's newest keyframes (this many: the board's BA window) go to the log every
    /// `window_interval` of frame time (`/slam/window`): what a resume seeds a tracker with.
    /// 0: none.
    pub window_keyframes: usize,
    pub window_interval: Duration,
    /// Keyframes a resumed tracker holds that never reached mapping and the log (they were
    /// waiting in the stopped run's hand-off lag; seeded from its logged window), with their
    /// frames: handed on like new keyframes, so the map and `keyframes.txt` miss none.
    pub unlogged_keyframes: Vec<(u64, Arc<Frame>)>,
    /// Frames tracked again on resume whose pose the log does not hold (logged frames the
    /// stopped run had not tracked yet, or whose pose was lost to damage): their poses are
    /// logged this time.
    pub retrack_unlogged: std::collections::BTreeSet<u64>,
    /// Counters for a progress line (frames, state, keyframes, map size), set as the stages go.
    pub progress: Arc<RunProgress>,
    /// The run's clock against the frames' (inputs stamped on arrival).
    pub arrival_clock: Arc<clock::ArrivalClock>,
    /// Navigation samples for the log (`/nav/sample`).
    pub nav_to_log: NavToLog,
    /// The live view over the tether (`--live-view`): the board's `[live]` section, the bind
    /// address as asked; `None`: off.
    pub live: Option<duv_core::config::board::LiveSettings>,
    /// Where the stage threads run (the board's `[threads]`); the default places nothing.
    pub placement: ThreadPlacement,
}

/// Navigation samples the capture thread logs: the known ones (a dataset's `nav.csv`, the
/// generator's sensors, `--nav FILE`) as the frames pass their time, the live ones (a MAVLink
/// stream, stamped on the run's clock) as they arrive, moved onto the frames' clock. Replay and
/// resume read them back.
#[derive(Clone, Default)]
pub struct NavToLog {
    /// Sorted by time.
    pub known: Arc<[duv_core::nav::NavSample]>,
    /// Samples stamped with the run's clock (ns since [`clock::ArrivalClock::epoch`]).
    pub live: Option<Arc<BoundedQueue<duv_core::nav::NavSample>>>,
}

impl std::fmt::Debug for NavToLog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NavToLog").field("known", &self.known.len()).field("live", &self.live.is_some()).finish()
    }
}

/// Known navigation samples older than this before a resumed run's first frame were logged by
/// the earlier process.
const NAV_RELOG_NS: i64 = 2_000_000_000;

impl PipelineConfig {
    fn handoff(&self) -> HandoffConfig {
        HandoffConfig {
            keyframe_lag: self.keyframe_lag,
            // The keyframe queue, one in mapping, and some waiting in the log queue.
            keyframe_slots: self.keyframe_queue + KEYFRAME_SLOTS_IN_FLIGHT,
            window_keyframes: self.window_keyframes,
            window_interval: self.window_interval,
            align: self.world_from_tracker,
        }
    }

    /// Capacities from the board, log into `out_dir/log`.
    pub fn from_board(board: &Board, out_dir: PathBuf) -> Self {
        let mut log = LogConfig::new(out_dir.join("log"));
        log.frame_encoding = match board.log.frame_encoding {
            FrameLogEncoding::Raw => FrameEncoding::Raw,
            FrameLogEncoding::Jpeg => FrameEncoding::Jpeg { quality: board.log.jpeg_quality },
        };
        log.format = match board.log.format {
            LogFormatSetting::Foxglove => duv_log::LogFormat::Foxglove,
            LogFormatSetting::Ros2 => duv_log::LogFormat::Ros2,
        };
        log.compression = match board.log.compression {
            LogCompression::Zstd => duv_log::ChunkCompression::Zstd,
            LogCompression::Lz4 => duv_log::ChunkCompression::Lz4,
            LogCompression::None => duv_log::ChunkCompression::None,
        };
        log.max_mb_per_s = board.log.max_mb_per_s;
        log.metadata.push(("duv.board".into(), [("toml".to_string(), toml::to_string(board).unwrap_or_default())].into_iter().collect()));
        PipelineConfig {
            out_dir,
            frame_queue: board.budgets.frame_queue as usize,
            keyframe_queue: board.budgets.keyframe_queue as usize,
            log_queue_bytes: board.budgets.log_queue_mb as usize * (1 << 20),
            log,
            pace_speed: None,
            deterministic: false,
            lossless_frames: false,
            health_interval: Duration::from_secs(1),
            checkpoint_interval: Duration::from_secs(5),
            announce: false,
            world_from_tracker: None,
            frame_period_ms: 1e3 / board.camera.fps,
            host_budget_mb: board.budgets.host_mb as f64,
            keyframe_lag: board.budgets.ba_window as usize,
            window_keyframes: board.budgets.ba_window as usize,
            window_interval: Duration::from_millis(500),
            unlogged_keyframes: Vec::new(),
            retrack_unlogged: std::collections::BTreeSet::new(),
            progress: Arc::new(RunProgress::new()),
            arrival_clock: Arc::new(clock::ArrivalClock::new()),
            nav_to_log: NavToLog::default(),
            placement: ThreadPlacement::from_board(&board.threads),
            live: None,
        }
    }
}

/// Per-stage latency figures, milliseconds.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct LatencyMs {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

fn latency_of(v: &mut [f64]) -> LatencyMs {
    if v.is_empty() {
        return LatencyMs::default();
    }
    v.sort_by(f64::total_cmp);
    let at = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    LatencyMs { p50: at(0.5), p99: at(0.99), max: v[v.len() - 1] }
}

/// One health record (published once a second on `/health`).
#[derive(Clone, Debug, Serialize)]
pub struct Health {
    pub uptime_s: f64,
    pub frames_captured: u64,
    /// Frames dropped at capture because every pooled frame buffer was held downstream.
    pub frames_dropped_no_buffer: u64,
    pub frames_tracked: u64,
    pub keyframes: u64,
    pub frame_queue: QueueStats,
    pub keyframe_queue: QueueStats,
    pub log_queue: QueueStats,
    /// Frame-in to pose-out latency over the last interval.
    pub track_latency_ms: LatencyMs,
    /// The board's frame period minus the p99 latency: negative means falling behind.
    pub frame_budget_headroom_ms: f64,
    pub host_live_mb: f64,
    pub host_peak_mb: f64,
    pub host_budget_mb: f64,
    pub host_headroom_mb: f64,
    pub counting_allocator: bool,
    /// Heap allocations made so far by each stage's threads (with the counting allocator):
    /// flat in the steady state for capture and tracking.
    pub allocations: StageAllocations,
    pub log_failure: Option<String>,
}

/// Allocations made so far per stage ([`alloc::role_allocations`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct StageAllocations {
    pub capture: usize,
    pub tracking: usize,
    pub mapping: usize,
    pub logging: usize,
}

impl StageAllocations {
    pub fn now() -> Self {
        StageAllocations {
            capture: alloc::role_allocations(ThreadRole::Capture),
            tracking: alloc::role_allocations(ThreadRole::Tracking),
            mapping: alloc::role_allocations(ThreadRole::Mapping),
            logging: alloc::role_allocations(ThreadRole::Logging),
        }
    }
}

/// What a finished run hands back.
pub struct PipelineResult<S> {
    pub source: S,
    pub tracker: Tracker,
    pub recorder: TrajectoryRecorder,
    /// Frame-in (capture) to pose-out latency of every tracked frame.
    pub latencies: Vec<Duration>,
    /// The first of `latencies` whose frame was captured after the tracker's first measured
    /// pose (`None`: none was): from there on, the steady state (frames do not wait for the
    /// initial BA).
    pub after_init_from: Option<usize>,
    /// Tracker-only time of every tracked frame.
    pub track_times: Vec<Duration>,
    pub frames_captured: u64,
    pub frame_queue: QueueStats,
    pub keyframe_queue: QueueStats,
    pub log_queue: QueueStats,
    pub log: LogStats,
    pub log_error: Option<String>,
    /// The mapping stage, handed back for [`MapStage::finish`].
    pub map: Box<dyn MapStage>,
    /// Shutdown came from a signal, not the end of the source.
    pub interrupted: bool,
    /// Ids of the keyframes the full keyframe queue deferred (they are in the log; mapping
    /// takes them at the end of the run), the first [`DEFERRED_KEYFRAMES_KEPT`].
    pub deferred_keyframes: Vec<u64>,
    /// What thread placement was applied ([`PlacementReport::summary`]); empty when none ran.
    pub threads: String,
    pub wall: Duration,
    /// What the live view sent and dropped (`None`: off).
    pub live: Option<live::LiveReport>,
}

struct Shared {
    stop: Arc<AtomicBool>,
    frames_captured: AtomicU64,
    /// Frames read and dropped because every pooled frame buffer was in use.
    frames_no_buffer: AtomicU64,
    latest_t_ns: AtomicI64,
    /// Latencies (ms) since the last health record.
    recent_ms: Mutex<Vec<f64>>,
    log_failure: Mutex<Option<String>>,
    /// Ids of the keyframes the full keyframe queue deferred (capacity fixed at start).
    deferred_keyframes: Mutex<Vec<u64>>,
    placed: PlacementReport,
}

fn pose_record(out: &TrackOutput, world_from_tracker: Option<&Sim3>) -> PoseRecord {
    let world_from_cam = apply(world_from_tracker, &out.world_from_cam);
    PoseRecord {
        t_ns: out.t_ns,
        seq: out.seq,
        world_from_cam,
        state: out.state.name(),
        tracked: out.state.is_tracked(),
        keyframe: out.anchor.map(|a| a.keyframe),
        new_keyframe: out.new_keyframe,
        loop_closed: out.loop_closed,
        segment: out.segment,
        why: out.note.kind(),
        value: out.note.value_and_limit().map(|v| v.0),
        limit: out.note.value_and_limit().map(|v| v.1),
    }
}

fn apply(align: Option<&Sim3>, pose: &Se3) -> Se3 {
    match align {
        Some(a) => duv_core::pose::sim3_apply_to_pose(a, pose),
        None => *pose,
    }
}

fn spawn<T: Send + 'static>(name: &str, f: impl FnOnce() -> T + Send + 'static) -> Result<std::thread::JoinHandle<T>, PipelineError> {
    std::thread::Builder::new().name(name.into()).spawn(f).map_err(|source| PipelineError::Io { path: PathBuf::from(format!("<thread {name}>")), source })
}

fn join<T>(h: std::thread::JoinHandle<T>, stage: &'static str) -> Result<T, PipelineError> {
    h.join().map_err(|_| PipelineError::Stage { stage, problem: "thread panicked".into() })
}

/// Paces frames at their time stamps / `speed`.
struct Pacer {
    speed: f64,
    start: Option<(Instant, Timestamp)>,
}

impl Pacer {
    fn wait(&mut self, t_ns: Timestamp, stop: &AtomicBool) {
        let (t0, first) = *self.start.get_or_insert((Instant::now(), t_ns));
        let due = Duration::from_secs_f64((t_ns.secs_since(first) / self.speed).max(0.0));
        while !stop.load(Ordering::Relaxed) {
            let now = t0.elapsed();
            if now >= due {
                break;
            }
            std::thread::sleep((due - now).min(Duration::from_millis(50)));
        }
    }
}

/// Runs `source` through tracking, mapping and logging until the source ends or `stop` is
/// set, then closes the log. `map`: the mapping stage. `retrack`: frames already in the log
/// that tracking goes through before the source (resume: the logged frames after the newest
/// logged keyframe, see [`resume`]); their poses are in the log already and are not logged
/// again, the keyframes they make go to mapping and the log like any other. `stop`: a flag,
/// or a [`Stop`] whose second level (`abort`) returns [`PipelineError::Aborted`] as soon as
/// the log is closed.
pub fn run<S: FrameSource + 'static>(
    mut source: S,
    tracker: Tracker,
    map: Box<dyn MapStage>,
    cfg: &PipelineConfig,
    retrack: Vec<Frame>,
    stop: impl Into<Stop>,
) -> Result<PipelineResult<S>, PipelineError> {
    let stop_levels: Stop = stop.into();
    let stop = stop_levels.requested.clone();
    if let Some(speed) = cfg.pace_speed {
        if !(speed.is_finite() && speed >= 1e-3) {
            return Err(PipelineError::BadSetting { setting: "pace_speed (--speed)", value: speed, problem: "must be a finite factor >= 0.001" });
        }
    }
    if cfg.deterministic && cfg.live.is_some() {
        return Err(PipelineError::Live { problem: "the live view is not available with --deterministic (every stage runs on one thread)".into() });
    }
    // The live view (off unless asked) first: a server that cannot start leaves no log behind.
    let (live, live_thread) = live::LiveFeed::start(cfg.live.as_ref())?;
    let retrack: Vec<Arc<Frame>> = retrack.into_iter().map(Arc::new).collect();
    let started = Instant::now();
    let mut writer = match SegmentWriter::create(cfg.log.clone()) {
        Ok(w) => w,
        Err(e) => {
            live.close();
            return Err(e.into());
        }
    };
    if cfg.announce {
        writer.set_on_sync(|path, messages, bytes| println!("synced {} {messages} {bytes}", path.display()));
    }
    let checkpoints = CheckpointStore::new(cfg.out_dir.join("checkpoints"), 3);
    let camera = *source.camera();
    writer.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera }).ok();
    if cfg.deterministic {
        return run_deterministic(source, tracker, map, cfg, writer, checkpoints, retrack, stop, started);
    }

    let frames: Arc<BoundedQueue<(Arc<Frame>, Instant)>> = Arc::new(BoundedQueue::new("frames", cfg.frame_queue, 0, FullPolicy::Spread));
    let keyframes: Arc<KeyframeQueue> = Arc::new(KeyframeQueue::new(cfg.keyframe_queue));
    let log_q: Arc<BoundedQueue<LogItem>> = Arc::new(BoundedQueue::new("log", 1 << 16, cfg.log_queue_bytes, FullPolicy::DropNewest));
    let shared = Arc::new(Shared {
        stop: stop.clone(),
        frames_captured: AtomicU64::new(0),
        frames_no_buffer: AtomicU64::new(0),
        latest_t_ns: AtomicI64::new(0),
        recent_ms: Mutex::new(Vec::with_capacity(4096)),
        log_failure: Mutex::new(None),
        deferred_keyframes: Mutex::new(Vec::with_capacity(DEFERRED_KEYFRAMES_KEPT)),
        placed: PlacementReport::default(),
    });
    let log_push = |q: &BoundedQueue<LogItem>, item: LogItem| {
        let b = item.approx_bytes();
        let _ = q.push(item, b);
    };

    // Logging.
    let logging = {
        let q = log_q.clone();
        let sh = shared.clone();
        let tick = cfg.log.chunk_interval / 4;
        let abort = stop_levels.abort.clone();
        let placement = cfg.placement.clone();
        spawn("logging", move || {
            alloc::label_current_thread(ThreadRole::Logging);
            sh.placed.apply_here(&placement, StageThread::Logging);
            let _span = tracing::info_span!("log").entered();
            let mut first_error: Option<String> = None;
            loop {
                match q.pop_timeout(tick) {
                    Ok(Some(item)) => {
                        if let Err(e) = writer.write(&item) {
                            first_error.get_or_insert_with(|| e.to_string());
                            *sh.log_failure.lock().unwrap_or_else(|p| p.into_inner()) = Some(e.to_string());
                        }
                    }
                    Ok(None) => {}
                    Err(()) => break,
                }
                // A second signal: what is still queued is dropped, the segment is closed.
                if abort.load(Ordering::Relaxed) {
                    break;
                }
                if let Err(e) = writer.tick() {
                    first_error.get_or_insert_with(|| e.to_string());
                    *sh.log_failure.lock().unwrap_or_else(|p| p.into_inner()) = Some(e.to_string());
                }
            }
            let (stats, r) = writer.finish();
            if let Err(e) = r {
                first_error.get_or_insert_with(|| e.to_string());
            }
            (stats, first_error)
        })?
    };

    // Mapping.
    let mapping = {
        let kq = keyframes.clone();
        let lq = log_q.clone();
        let interval = cfg.checkpoint_interval;
        let progress = cfg.progress.clone();
        let mut map = map;
        let stop = stop.clone();
        let live = live.clone();
        let placement = cfg.placement.clone();
        let sh = shared.clone();
        spawn("mapping", move || -> Result<Box<dyn MapStage>, PipelineError> {
            let kq_on_exit = kq.clone();
            // The CPU mapper's data-parallel loops run in a pool of the board's size, placed
            // like this thread, so mapping never takes more than `threads.mapping` cores. Made
            // before this thread is placed: its workers would inherit the nice value, and each
            // raises its own.
            let pool = (placement.mapping_workers > 0 && map.uses_cpu_workers())
                .then(|| {
                    let (sh, placement) = (sh.clone(), placement.clone());
                    rayon::ThreadPoolBuilder::new()
                        .num_threads(placement.mapping_workers)
                        .thread_name(|i| format!("mapping-{i}"))
                        .start_handler(move |_| sh.placed.apply_here(&placement, StageThread::Mapping))
                        .build()
                        .map_err(|e| tracing::warn!("mapping worker pool not made ({e}); the mapper uses the shared one"))
                        .ok()
                })
                .flatten();
            if pool.is_some() {
                sh.placed.mapping_pool_made(placement.mapping_workers);
            }
            sh.placed.apply_here(&placement, StageThread::Mapping);
            let run = move || -> Result<Box<dyn MapStage>, PipelineError> {
                alloc::label_current_thread(ThreadRole::Mapping);
                let _span = tracing::info_span!("map").entered();
                let mut last_ckpt = Instant::now();
                let mut last_t = Timestamp::from_ns(0);
                // A checkpoint that cannot be written (a full disk) is reported once; mapping
                // goes on, and a resume starts from the newest one on disk.
                let mut failed_saves = 0u64;
                let mut save = |map: &mut Box<dyn MapStage>, t: Timestamp, last: bool| -> Result<(), PipelineError> {
                    if let Some(c) = if last { map.final_checkpoint() } else { map.checkpoint() } {
                        live.cloud(t, &c.centres_in_world, &c.colours);
                        let t_save = Instant::now();
                        let saved = checkpoints.save(&c.file);
                        map.checkpoint_written(t_save.elapsed());
                        match saved {
                            Ok(_) => log_push(&lq, LogItem::Map { t_ns: t, centres_in_world: c.centres_in_world, checkpoint: c.logged, last }),
                            Err(e) => {
                                failed_saves += 1;
                                if failed_saves == 1 {
                                    tracing::error!("map checkpoint not written: {e}; mapping goes on");
                                }
                            }
                        }
                    }
                    Ok(())
                };
                loop {
                    // Stopping: the queued keyframes and the final save are abandoned (the
                    // keyframes are in the log, the newest checkpoint on disk), so shutdown
                    // never waits for the mapper.
                    if stop.load(Ordering::Relaxed) {
                        return Ok(map);
                    }
                    let idle = match kq.try_pop() {
                        Some(kf) => {
                            last_t = kf.t_ns;
                            map.add_keyframe(&kf).map_err(PipelineError::Mapping)?;
                            false
                        }
                        None => !map.step().map_err(PipelineError::Mapping)?,
                    };
                    if let Some(n) = map.gaussians() {
                        progress.set_gaussians(n);
                    }
                    if last_ckpt.elapsed() >= interval {
                        last_ckpt = Instant::now();
                        save(&mut map, last_t, false)?;
                    }
                    if idle {
                        match kq.pop_timeout(Duration::from_millis(100)) {
                            Ok(Some(kf)) => {
                                last_t = kf.t_ns;
                                map.add_keyframe(&kf).map_err(PipelineError::Mapping)?;
                            }
                            Ok(None) => {}
                            Err(()) => break,
                        }
                    }
                }
                save(&mut map, last_t, true)?;
                Ok(map)
            };
            // Closed on any exit, so tracking never waits on a mapping thread that failed.
            let result = match &pool {
                Some(pool) => pool.install(run),
                None => run(),
            };
            kq_on_exit.close();
            result
        })?
    };

    // Tracking.
    let tracking = {
        let fq = frames.clone();
        let kq = keyframes.clone();
        let lq = log_q.clone();
        let sh = shared.clone();
        let announce = cfg.announce;
        let align = cfg.world_from_tracker;
        let mut tracker = tracker;
        let mut handoff = Handoff::new(cfg.handoff(), &mut tracker);
        handoff.adopt(&mut tracker, &cfg.unlogged_keyframes);
        let retrack_unlogged = cfg.retrack_unlogged.clone();
        let progress = cfg.progress.clone();
        let live = live.clone();
        let placement = cfg.placement.clone();
        spawn("tracking", move || -> Result<(Tracker, TrajectoryRecorder, Vec<Duration>, Option<usize>, Vec<Duration>), PipelineError> {
            alloc::label_current_thread(ThreadRole::Tracking);
            sh.placed.apply_here(&placement, StageThread::Tracking);
            let _span = tracing::info_span!("track").entered();
            // A run's record: an hour at 30 frames/s before it grows.
            let mut recorder = TrajectoryRecorder::with_capacity(RECORD_FRAMES, RECORD_FRAMES / 4);
            let mut latencies = Vec::with_capacity(RECORD_FRAMES);
            let (mut initialised_at, mut after_init_from): (Option<Instant>, Option<usize>) = (None, None);
            let mut track_times = Vec::with_capacity(RECORD_FRAMES);
            let to_mapping = |kf: Arc<Keyframe>| {
                progress.keyframe_handed_on();
                live.keyframe(&kf);
                if let Scheduled::QueuedDeferred(kf) = kq.push(kf) {
                    // The id, for mapping to take the keyframe from the log at the end.
                    if let Ok(mut ids) = sh.deferred_keyframes.lock() {
                        if ids.len() < ids.capacity() {
                            ids.push(kf.index);
                        }
                    }
                }
                Ok(())
            };
            let result = tracker.run_in_pool(|tracker| -> Result<(), PipelineError> {
                // The tracker's workers run where this thread does.
                if placement.tracking_cores.is_some() {
                    rayon::broadcast(|_| sh.placed.apply_here(&placement, StageThread::Tracking));
                }
                for frame in &retrack {
                    if sh.stop.load(Ordering::Relaxed) {
                        break;
                    }
                    let t0 = Instant::now();
                    let out = tracker.track(frame)?;
                    track_times.push(t0.elapsed());
                    recorder.record(&out);
                    if retrack_unlogged.contains(&frame.seq) {
                        log_push(&lq, LogItem::Pose(pose_record(&out, align.as_ref())));
                    }
                    handoff.after_frame(tracker, frame, &out, |item| log_push(&lq, item), to_mapping)?;
                }
                drop(retrack);
                while let Some((frame, arrived)) = fq.pop() {
                    if after_init_from.is_none() && initialised_at.is_some_and(|t| arrived >= t) {
                        after_init_from = Some(latencies.len());
                    }
                    let t0 = Instant::now();
                    let out = tracker.track(&frame)?;
                    if initialised_at.is_none() && out.state.is_tracked() {
                        initialised_at = Some(Instant::now());
                    }
                    track_times.push(t0.elapsed());
                    recorder.record(&out);
                    progress.frame_tracked(out.state.name(), out.segment);
                    let pose = pose_record(&out, align.as_ref());
                    log_push(&lq, LogItem::Pose(pose));
                    live.pose(&pose);
                    live.frame(&frame);
                    handoff.after_frame(tracker, &frame, &out, |item| log_push(&lq, item), to_mapping)?;
                    let lat = arrived.elapsed();
                    latencies.push(lat);
                    if let Ok(mut v) = sh.recent_ms.lock() {
                        if v.len() < v.capacity() {
                            v.push(lat.as_secs_f64() * 1e3);
                        }
                    }
                    if announce {
                        println!("tracked {} {}", out.seq, out.t_ns.t_ns());
                    }
                }
                handoff.flush(tracker, |item| log_push(&lq, item), |kf| {
                    progress.keyframe_handed_on();
                    live.keyframe(&kf);
                    kq.push_wait(kf);
                    Ok(())
                })
            });
            kq.close();
            result?;
            Ok((tracker, recorder, latencies, after_init_from, track_times))
        })?
    };

    // Capture (this function's source moves into the thread and comes back at the end). Frames
    // are filled into a fixed pool (`pool::Pool`) and shared, not copied, with tracking and the
    // log: enough slots for a full frame queue, a full log queue of frames, the keyframes
    // waiting in the lag and the frame in tracking.
    let frame_bytes = camera.width * camera.height * 3;
    let pool_slots = cfg.frame_queue + cfg.log_queue_bytes / frame_bytes.max(1) + cfg.keyframe_lag + FRAME_SLOTS_IN_FLIGHT + live.frame_slots();
    let capture = {
        let fq = frames.clone();
        let lq = log_q.clone();
        let sh = shared.clone();
        let mut pacer = cfg.pace_speed.map(|speed| Pacer { speed, start: None });
        let lossless = cfg.lossless_frames;
        let arrival_clock = cfg.arrival_clock.clone();
        let nav_known = Arc::clone(&cfg.nav_to_log.known);
        let nav_live = cfg.nav_to_log.live.clone();
        spawn("capture", move || -> (S, Option<String>) {
            let mut nav_next: Option<usize> = None;
            alloc::label_current_thread(ThreadRole::Capture);
            let _span = tracing::info_span!("capture").entered();
            // Every slot at the camera's size now (start-up), so none grows while frames flow.
            let mut pool = pool::Pool::new(pool_slots, || Frame::rgb(camera.width, camera.height));
            // Where a frame goes when every slot is held (live sources): read and dropped.
            let mut overflow = Frame::empty();
            let mut error = None;
            while !sh.stop.load(Ordering::Relaxed) {
                let mut slot = match pool.take() {
                    Some(s) => Some(s),
                    None if lossless => {
                        std::thread::sleep(Duration::from_millis(1));
                        continue;
                    }
                    None => None,
                };
                let target = match slot.as_mut() {
                    Some(s) => s.get_mut(),
                    None => &mut overflow,
                };
                match source.next_frame_into(target) {
                    Ok(true) => {
                        let Some(slot) = slot else {
                            sh.frames_no_buffer.fetch_add(1, Ordering::Relaxed);
                            tracing::trace!(seq = overflow.seq, "frame dropped (every frame buffer in use)");
                            continue;
                        };
                        let frame = slot.share();
                        if let Some(p) = pacer.as_mut() {
                            p.wait(frame.t_ns, &sh.stop);
                        }
                        arrival_clock.frame_arrived(frame.t_ns);
                        sh.frames_captured.fetch_add(1, Ordering::Relaxed);
                        sh.latest_t_ns.store(frame.t_ns.t_ns(), Ordering::Relaxed);
                        log_push(&lq, LogItem::Frame(Arc::clone(&frame)));
                        let t = frame.t_ns.t_ns();
                        let next = nav_next.get_or_insert_with(|| nav_known.partition_point(|s| s.t_ns.t_ns() < t - NAV_RELOG_NS));
                        while *next < nav_known.len() && nav_known[*next].t_ns.t_ns() <= t {
                            log_push(&lq, LogItem::Nav(nav_known[*next]));
                            *next += 1;
                        }
                        while let Some(mut s) = nav_live.as_ref().and_then(|q| q.try_pop()) {
                            if let Some(t) = arrival_clock.frame_time_ns(s.t_ns.t_ns()) {
                                s.t_ns = Timestamp::from_ns(t);
                                log_push(&lq, LogItem::Nav(s));
                            }
                        }
                        let item = (frame, Instant::now());
                        let pushed = if lossless { fq.push_wait(item, 0) } else { fq.push_at(item, 0, t) };
                        if let Pushed::QueuedDropped(old) = pushed {
                            tracing::trace!(seq = old.0.seq, "frame dropped (tracking behind)");
                        }
                    }
                    Ok(false) => break,
                    Err(e @ duv_camera::CameraError::BadFrame { .. }) => tracing::warn!("frame dropped: {e}"),
                    Err(e) => {
                        tracing::error!("capture stopped: {e}");
                        error = Some(e.to_string());
                        break;
                    }
                }
            }
            fq.close();
            (source, error)
        })?
    };

    // Health, on this thread, until tracking and mapping are done.
    let (frame_period_ms, host_budget_mb) = (cfg.frame_period_ms, cfg.host_budget_mb);
    let mut last_health = Instant::now();
    while !(tracking.is_finished() && mapping.is_finished()) {
        std::thread::sleep(Duration::from_millis(20));
        if stop_levels.is_aborted() {
            // The other stages are left where they are (the process ends with this error).
            frames.close();
            keyframes.close();
            log_q.close();
            live.close();
            let (stats, _) = join(logging, "logging")?;
            tracing::warn!(messages = stats.messages, "log closed after a second signal");
            return Err(PipelineError::Aborted { frames_captured: shared.frames_captured.load(Ordering::Relaxed) });
        }
        if last_health.elapsed() >= cfg.health_interval {
            last_health = Instant::now();
            let mut recent = std::mem::take(&mut *shared.recent_ms.lock().unwrap_or_else(|p| p.into_inner()));
            let lat = latency_of(&mut recent);
            recent.clear();
            *shared.recent_ms.lock().unwrap_or_else(|p| p.into_inner()) = recent;
            let mb = |b: usize| b as f64 / (1 << 20) as f64;
            let live = mb(duv_core::alloc::live_bytes());
            let counters = cfg.progress.snapshot();
            let h = Health {
                uptime_s: started.elapsed().as_secs_f64(),
                frames_captured: shared.frames_captured.load(Ordering::Relaxed),
                frames_dropped_no_buffer: shared.frames_no_buffer.load(Ordering::Relaxed),
                frames_tracked: counters.frames_tracked,
                keyframes: counters.keyframes,
                frame_queue: frames.stats(),
                keyframe_queue: keyframes.stats(),
                log_queue: log_q.stats(),
                track_latency_ms: lat,
                frame_budget_headroom_ms: frame_period_ms - lat.p99,
                host_live_mb: live,
                host_peak_mb: mb(duv_core::alloc::peak_bytes()),
                host_budget_mb,
                host_headroom_mb: host_budget_mb - live,
                counting_allocator: duv_core::alloc::is_installed(),
                allocations: StageAllocations::now(),
                log_failure: shared.log_failure.lock().unwrap_or_else(|p| p.into_inner()).clone(),
            };
            if let Ok(json) = serde_json::to_string(&h) {
                // Stamped with the newest frame time so it sits on the log's timeline.
                let t = Timestamp::from_ns(shared.latest_t_ns.load(Ordering::Relaxed));
                log_push(&log_q, LogItem::Health { t_ns: t, json });
            }
        }
    }
    let (source, capture_error) = join(capture, "capture")?;
    let tracked = join(tracking, "tracking")?;
    let mapped = join(mapping, "mapping")?;
    live.close();
    let live = live_thread.join();
    log_q.close();
    let (log_stats, log_error) = join(logging, "logging")?;
    let (tracker, recorder, latencies, after_init_from, track_times) = tracked?;
    let map = mapped?;
    let deferred_keyframes = std::mem::take(&mut *shared.deferred_keyframes.lock().unwrap_or_else(|p| p.into_inner()));
    let threads = shared.placed.summary();
    if let Some(e) = capture_error {
        tracing::warn!("the source ended with an error: {e}");
    }
    Ok(PipelineResult {
        source,
        tracker,
        recorder,
        latencies,
        after_init_from,
        track_times,
        frames_captured: shared.frames_captured.load(Ordering::Relaxed),
        frame_queue: frames.stats(),
        keyframe_queue: keyframes.stats(),
        log_queue: log_q.stats(),
        log: log_stats,
        log_error,
        map,
        interrupted: stop.load(Ordering::Relaxed),
        deferred_keyframes,
        threads,
        wall: started.elapsed(),
        live,
    })
}

#[allow(clippy::too_many_arguments)]
fn run_deterministic<S: FrameSource + 'static>(
    mut source: S,
    mut tracker: Tracker,
    mut map: Box<dyn MapStage>,
    cfg: &PipelineConfig,
    mut writer: SegmentWriter,
    checkpoints: CheckpointStore,
    retrack: Vec<Arc<Frame>>,
    stop: Arc<AtomicBool>,
    started: Instant,
) -> Result<PipelineResult<S>, PipelineError> {
    let align = cfg.world_from_tracker;
    let mut recorder = TrajectoryRecorder::new();
    let mut latencies = Vec::new();
    let (mut initialised, mut after_init_from) = (false, None);
    let mut track_times = Vec::new();
    let mut captured = 0u64;
    let mut log_error: Option<String> = None;
    let mut log = |writer: &mut SegmentWriter, item: LogItem| {
        if let Err(e) = writer.write(&item) {
            log_error.get_or_insert_with(|| e.to_string());
        }
    };
    let mut last_t = Timestamp::from_ns(0);
    let mut handoff = Handoff::new(cfg.handoff(), &mut tracker);
    handoff.adopt(&mut tracker, &cfg.unlogged_keyframes);
    let mut to_mapping = |kf: Arc<Keyframe>| -> Result<(), PipelineError> {
        if stop.load(Ordering::Relaxed) {
            return Ok(());
        }
        map.add_keyframe(&kf).map_err(PipelineError::Mapping)?;
        while !stop.load(Ordering::Relaxed) && map.step().map_err(PipelineError::Mapping)? {}
        Ok(())
    };
    tracker.run_in_pool(|tracker| -> Result<(), PipelineError> {
        for frame in &retrack {
            if stop.load(Ordering::Relaxed) {
                break;
            }
            let t0 = Instant::now();
            let out = tracker.track(frame)?;
            track_times.push(t0.elapsed());
            recorder.record(&out);
            if cfg.retrack_unlogged.contains(&frame.seq) {
                log(&mut writer, LogItem::Pose(pose_record(&out, align.as_ref())));
            }
            handoff.after_frame(tracker, frame, &out, |item| log(&mut writer, item), &mut to_mapping)?;
        }
        while !stop.load(Ordering::Relaxed) {
            let frame = match source.next_frame() {
                Ok(Some(f)) => f,
                Ok(None) => break,
                Err(e @ duv_camera::CameraError::BadFrame { .. }) => {
                    tracing::warn!("frame dropped: {e}");
                    continue;
                }
                Err(e) => return Err(e.into()),
            };
            captured += 1;
            last_t = frame.t_ns;
            let frame = Arc::new(frame);
            log(&mut writer, LogItem::Frame(Arc::clone(&frame)));
            if after_init_from.is_none() && initialised {
                after_init_from = Some(latencies.len());
            }
            let t0 = Instant::now();
            let out = tracker.track(&frame)?;
            initialised |= out.state.is_tracked();
            track_times.push(t0.elapsed());
            latencies.push(t0.elapsed());
            recorder.record(&out);
            log(&mut writer, LogItem::Pose(pose_record(&out, align.as_ref())));
            handoff.after_frame(tracker, &frame, &out, |item| log(&mut writer, item), &mut to_mapping)?;
        }
        handoff.flush(tracker, |item| log(&mut writer, item), &mut to_mapping)
    })?;
    drop(to_mapping);
    if let Some(c) = map.final_checkpoint() {
        match checkpoints.save(&c.file) {
            Ok(_) => log(&mut writer, LogItem::Map { t_ns: last_t, centres_in_world: c.centres_in_world, checkpoint: c.logged, last: true }),
            Err(e) => tracing::error!("map checkpoint not written: {e}"),
        }
    }
    let (log_stats, r) = writer.finish();
    if let Err(e) = r {
        log_error.get_or_insert_with(|| e.to_string());
    }
    let n = captured as usize;
    Ok(PipelineResult {
        source,
        tracker,
        recorder,
        latencies,
        after_init_from,
        track_times,
        frames_captured: captured,
        frame_queue: QueueStats { pushed: n as u64, popped: n as u64, ..Default::default() },
        keyframe_queue: QueueStats::default(),
        log_queue: QueueStats::default(),
        log: log_stats,
        log_error,
        map,
        interrupted: stop.load(Ordering::Relaxed),
        deferred_keyframes: Vec::new(),
        threads: String::new(),
        wall: started.elapsed(),
        live: None,
    })
}
