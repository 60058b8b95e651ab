//! One dive run from start to written outputs, the whole of `duv run` (and `duv replay`,
//! `duv demo`) below its command line: [`run_dive`].
//!
//! In order: lock the run folder ([`lock`](super::lock)); read the board and the tracker and
//! mapper parameters; leave a finished dive as it is ([`DiveRecord`]); keep room for the final
//! outputs ([`DiskReserve`]); read what a stopped run left ([`resume::prepare`]); open the
//! source after the frames already logged; set up the tracker and the mapping stage (the map
//! checkpoint reloaded, the logged keyframes it does not cover fed again, the tracker
//! relocalised: seeded, restarted, Sim(3)-aligned or in a new frame); run the pipeline
//! ([`run`](super::run)) with SIGINT/SIGTERM as the stop ([`Stop::on_signals`]); then map the
//! keyframes the full keyframe queue refused (from this run's segments), write the outputs of
//! the whole dive ([`outputs`](super::outputs)), `dive.json`, the keyframes' depth files and
//! the map export.
//!
//! What happens is reported as it happens through the caller's `progress` callback
//! ([`Progress`]: each one line, for the operator or for the results); what the caller prints
//! at the end, evaluates or turns into an exit status comes back in the [`DiveOutcome`].
//! Ground-truth evaluation is the caller's (this crate does not depend on `duv-eval`).

use super::dive::{part_metadata, unix_now_s, DivePart, DiveRecord, PART_METADATA};
use super::keyframe_folder::{KeyframeFolder, KeyframeFolderError};
use super::lock::{LockError, RunFolderLock};
use super::metric::MetricRecord;
use super::mapping::{feed_logged_keyframes, feed_unmapped_keyframes, Refed, GaussianMapping};
use super::outputs::{finish_trajectory, init_summary, write_keyframe_depths, write_tracking_outputs, DiskReserve, OutputError, OutputFrames, WrittenOutputs};
use super::resume::{self, Relocalisation};
use super::source::{RunSource, RunSourceError, Source, SourceOptions};
use super::{MapStage, MapStageError, NoMapping, PipelineConfig, PipelineError, Stop};
use duv_camera::sim::{SimPace, SimSpec};
use duv_core::config::board::{Board, BoardError, LogFormatSetting};
use duv_core::PlaneF32;
use duv_log::{ReadLimits, RecoveryReport};
use duv_map::backend::MapperDevice;
use duv_map::mapper::{MapperCapacity, MapperConfig};
use duv_map::stage::{MappingBudget, MappingStage};
use duv_map::GpuOptions;
use duv_track::{Tracker, TrackerCapacity, TrackerConfig};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

/// Where the board profile comes from; it is read once the run folder is locked.
#[derive(Clone, Debug)]
pub enum BoardFile {
    /// A profile file.
    Path(PathBuf),
    /// `path` when it is there, otherwise `text`, a copy of it built into the caller, named
    /// `name` in messages (the default board of a run started outside the repository).
    PathOr { path: PathBuf, name: PathBuf, text: String },
}

impl BoardFile {
    pub fn load(&self) -> Result<Board, BoardError> {
        match self {
            BoardFile::Path(path) => Board::load(path),
            BoardFile::PathOr { path, name, text } => {
                if path.exists() {
                    return Board::load(path);
                }
                tracing::debug!("{} not found here: the built-in copy", path.display());
                Board::parse(name, text)
            }
        }
    }
}

/// The mapping stage of a dive run (`duv run` without `--no-map`).
#[derive(Clone, Debug)]
pub struct MappingOptions {
    /// Mapper parameters (TOML, `MapperConfig` fields); `None`: the defaults.
    pub config: Option<PathBuf>,
    /// Mapper iterations after each keyframe handed to mapping.
    pub iterations_per_keyframe: u64,
    /// Mapper iterations while the mapping thread waits for the next keyframe (at most).
    pub idle_iterations: u64,
    /// Mapper iterations after the last frame, on the final keyframe poses.
    pub final_iterations: u64,
    /// Where the mapper renders.
    pub device: MapperDevice,
}

/// What a dive run does: `duv run`'s options as data.
#[derive(Clone, Debug)]
pub struct DiveOptions {
    /// The frame source (`--source`: `sim:...`, a dataset, `mcap:LOG`, a camera).
    pub source: String,
    /// The run folder (created if missing): log, checkpoints, keyframes, outputs.
    pub out: PathBuf,
    pub board: BoardFile,
    /// Tracker parameters (TOML, `TrackerConfig` fields); `None`: the defaults.
    pub tracker_config: Option<PathBuf>,
    /// `false`: loop closure off, whatever the tracker parameters say.
    pub loop_closure: bool,
    /// Frames, `sim:` image size and seed, replay loop.
    pub source_options: SourceOptions,
    /// Pace the source at its time stamps divided by this factor (checked by the caller).
    pub speed: Option<f64>,
    /// Single-threaded, no drops, seeded: bit-identical output.
    pub deterministic: bool,
    /// Resume a run folder that holds a log; `false`: such a folder is refused.
    pub resume: bool,
    /// Track the source further on a finished dive (otherwise it is left as it is).
    pub continue_dive: bool,
    /// Print `tracked SEQ T_NS` per frame and `synced SEGMENT MESSAGES BYTES` per fsync on
    /// stdout (the crash harness reads them).
    pub announce: bool,
    /// The mapping stage; `None`: track only, no map.
    pub mapping: Option<MappingOptions>,
    /// Use the source's navigation sensors for metric outputs (`metric.json`, [`super::metric`]);
    /// `false`: map units, as without them.
    pub use_nav: bool,
    /// Counters the stages set as they go (a progress line reads them); `None`: not shown.
    pub progress: Option<Arc<super::RunProgress>>,
    /// Navigation input besides the source's own (`--nav`): `mavlink:[udpin:]HOST:PORT[,...]`,
    /// the autopilot's stream received during the run, or a `nav.csv` file.
    pub nav_input: Option<String>,
    /// The log's message schemas instead of the board's `[log] format` (`--log-format`).
    pub log_format: Option<LogFormatSetting>,
    /// The live view (`--live-view [ADDR]`): `Some(None)` on the board's `live.bind`,
    /// `Some(Some(addr))` on `addr`; `None`: off.
    pub live_view: Option<Option<String>>,
}

/// Why a dive run failed. The messages are the ones the command line prints.
#[derive(Debug, thiserror::Error)]
pub enum DiveError {
    #[error(transparent)]
    Lock(#[from] LockError),
    #[error(transparent)]
    Board(#[from] BoardError),
    /// A parameter file (`--config`) that cannot be read.
    #[error("reading {path}")]
    ReadConfig { path: PathBuf, source: std::io::Error },
    /// A parameter file (`--config`, `--map-config`) that does not parse.
    #[error("{path}")]
    Config { path: PathBuf, source: toml::de::Error },
    #[error("--no-resume: {} already holds a log; choose another --out", log_dir.display())]
    HoldsLog { log_dir: PathBuf },
    /// A `sim:` spec's `pace=none` with a speed.
    #[error("{spec}: pace=none and --speed disagree")]
    PaceDisagrees { spec: String },
    /// The mapper's device could not be opened.
    #[error("mapper (--mapper {device:?}): {error}")]
    MapperDevice { device: MapperDevice, error: MapStageError },
    /// A map checkpoint that does not restore.
    #[error("{}: {error}", path.display())]
    Checkpoint { path: PathBuf, error: MapStageError },
    /// `--live-view ADDR` that the board's `[live]` checks refuse.
    #[error("--live-view {value}: {why}")]
    LiveView { value: String, why: &'static str },
    /// The source ended before its first frame.
    #[error("the source delivered no frame")]
    NoFrame,
    /// A second signal stopped the run at once: the log is closed, no output was written.
    /// `exit_code`: the shell's status for the first signal.
    #[error("stopped by signal {signal}: {error}; the outputs were not written (a resume rebuilds them from the log)")]
    Aborted { signal: i32, exit_code: u8, error: PipelineError },
    #[error(transparent)]
    Log(#[from] duv_log::LogError),
    #[error(transparent)]
    Source(#[from] RunSourceError),
    #[error(transparent)]
    Camera(#[from] duv_camera::CameraError),
    #[error(transparent)]
    Track(#[from] duv_track::TrackError),
    #[error(transparent)]
    Mapper(#[from] duv_map::stage::StageError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error(transparent)]
    KeyframeFolder(#[from] KeyframeFolderError),
    #[error(transparent)]
    Output(#[from] OutputError),
    #[error(transparent)]
    File(#[from] duv_core::io::IoError),
    /// A folder of the run that could not be made.
    #[error(transparent)]
    Folder(std::io::Error),
    /// `--nav`: a MAVLink stream that cannot be received.
    #[error("--nav {0}")]
    NavStream(#[from] duv_camera::mavlink_nav::MavlinkNavError),
    /// `--nav FILE`: a navigation file that does not read.
    #[error("--nav: {0}")]
    NavFile(#[from] duv_core::nav::NavError),
}

/// One line of what a dive run is doing, reported as it happens (its `Display` is the line;
/// [`Progress::is_result`] says whether it belongs with the results or with the operator's
/// messages).
#[derive(Debug)]
pub enum Progress<'a> {
    /// The run is set up.
    Started { source: &'a str, out: &'a Path, depth_grid: (usize, usize), depth_factor: usize, capacity: TrackerCapacity, host_plan_bytes: usize, host_mb: u32 },
    /// The renderer the mapper uses.
    MapperRenders { renderer: &'a str },
    /// A log segment of the stopped run, recovered or left as it was.
    Recovered(&'a RecoveryReport),
    /// The newest good map checkpoint was restored.
    CheckpointReloaded { path: &'a Path },
    /// Resume: the logged keyframes the map did not cover were fed again (`after`: the
    /// checkpoint's newest keyframe).
    Refed { keyframes: usize, after: Option<u64> },
    /// Resume: feeding them stopped early.
    RefedProblem { problem: &'a str },
    /// Resume: the tracker was seeded with `seeds` (in words).
    ResumedSeeded { last_seq: u64, poses_recorded: u64, seeds: &'a str, newest_keyframe_seq: u64, retrack: usize },
    /// Resume: the stopped run's initialisation is tracked again from `from_seq`.
    ResumedRestarted { last_seq: u64, poses_recorded: u64, from_seq: u64, retrack: usize },
    /// Resume, fallback: re-initialised on `frames` logged frames and aligned by Sim(3).
    ResumedAligned { last_seq: u64, poses_recorded: u64, why: &'a str, frames: usize, scale: f64 },
    /// Resume: relocalisation failed, the run goes on in a new frame.
    ResumedNewFrame { last_seq: u64, why: &'a str },
    /// Resume: logged frames without a recorded pose are tracked from the log.
    TrackingUnposed { frames: usize, first_seq: u64, last_seq: u64 },
    /// The live view serves on `bind` (from the start of tracking).
    LiveView { bind: &'a str },
    /// What the live view sent and dropped.
    LiveViewEnded(&'a super::live::LiveReport),
    /// Tracking starts (`None`: the source has no end). The one progress line a quiet caller
    /// leaves out.
    Tracking { frames: Option<usize> },
    /// The tracking state changed at frame `seq`.
    State { seq: u64, state: &'static str },
    /// What the initialisation waited for.
    InitWaited { summary: &'a str },
    /// The pipeline ended: frames, drops, log.
    PipelineEnded {
        frames_captured: u64,
        frames_tracked: usize,
        frames_dropped: u64,
        keyframes_dropped: u64,
        /// Keyframes the full keyframe queue deferred to the end of the run.
        keyframes_deferred: u64,
        log_records_dropped: u64,
        log_messages: u64,
        log_segments: u32,
        log_error: Option<&'a str>,
        interrupted: bool,
    },
    /// Resume with nothing left to track: the outputs come from the log.
    NothingLeft { after_seq: usize },
    /// Frame-in to pose-out latency of this run's frames.
    /// `after_init`: over the frames captured after the tracker's first measured pose (those
    /// that did not wait for the initial BA): frames, p99 and max.
    Latency { median_ms: f64, p99_ms: f64, after_init: Option<(usize, f64, f64)> },
    /// What the log took.
    /// `budget_mb_per_s`: the board's `[log] max_mb_per_s`; `maps_skipped` of `maps_offered`
    /// map checkpoints were left out of the log to keep it.
    LogRate { log_bytes: u64, frames_captured: u64, frames_per_s: f64, wall_s: f64, budget_mb_per_s: Option<f64>, maps_skipped: u64, maps_offered: u64 },
    /// The keyframes the full keyframe queue deferred were mapped from the log.
    CaughtUp { keyframes: usize },
    /// Where the stage threads ran ([`super::placement::PlacementReport::summary`]).
    Threads { summary: &'a str },
    /// Mapping them stopped early.
    CatchUpProblem { problem: &'a str },
    /// `dive.json` could not be written.
    DiveRecordNotWritten { error: &'a duv_core::io::IoError },
    /// The keyframes' depth files could not all be written.
    DepthFilesNotWritten { error: &'a OutputError },
    /// The map's summary after its export.
    MapExported { summary: &'a str },
    /// The map export failed.
    MapNotExported { error: &'a MapStageError },
    /// The map's figures on frames between keyframes ([`super::map_report`]).
    MapScored { summary: &'a str },
    /// Scoring the map failed.
    MapNotScored { error: &'a super::map_report::MapReportError },
    /// The unit of the outputs ([`MetricRecord::summary`]).
    Units { summary: &'a str },
    /// What a live navigation stream delivered.
    NavStream { summary: &'a str },
    /// `metric.json` could not be written.
    MetricNotWritten { error: &'a duv_core::io::IoError },
}

impl Progress<'_> {
    /// A line of the run's results (stdout); the others are the operator's messages (stderr).
    pub fn is_result(&self) -> bool {
        matches!(
            self,
            Progress::PipelineEnded { .. }
                | Progress::NothingLeft { .. }
                | Progress::Latency { .. }
                | Progress::LogRate { .. }
                | Progress::CaughtUp { .. }
                | Progress::Threads { .. }
                | Progress::MapExported { .. }
                | Progress::MapScored { .. }
                | Progress::Units { .. }
                | Progress::NavStream { .. }
                | Progress::LiveViewEnded(_)
        )
    }
}

impl std::fmt::Display for Progress<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Progress::Started { source, out, depth_grid, depth_factor, capacity, host_plan_bytes, host_mb } => write!(
                f,
                "duv run: {source} -> {} (depth grid {}x{}, 1/{depth_factor}; {} keyframes, BA window {}, {} threads; host plan {:.1} of {host_mb} MiB)",
                out.display(),
                depth_grid.0,
                depth_grid.1,
                capacity.max_keyframes,
                capacity.ba_window,
                capacity.threads,
                *host_plan_bytes as f64 / (1 << 20) as f64,
            ),
            Progress::MapperRenders { renderer } => write!(f, "mapper renders with {renderer}"),
            Progress::Recovered(rep) => match &rep.left_in_place {
                None => write!(
                    f,
                    "recovered {}: {} messages kept in intact chunks, {} damaged range(s) skipped, {} of {} bytes ({})",
                    rep.segment.display(),
                    rep.messages_kept,
                    rep.skipped_ranges,
                    rep.bytes_after,
                    rep.bytes_before,
                    rep.damage
                ),
                Some(why) => write!(f, "NOT RECOVERED {}: {why}; left as it is, {} messages readable ({})", rep.segment.display(), rep.messages_kept, rep.damage),
            },
            Progress::CheckpointReloaded { path } => write!(f, "map checkpoint {} reloaded", path.display()),
            Progress::Refed { keyframes, after } => write!(
                f,
                "map: {keyframes} logged keyframe(s) the map did not cover fed again (after {})",
                after.map_or("the start".to_string(), |n| format!("keyframe {n}, the checkpoint's newest"))
            ),
            Progress::RefedProblem { problem } => write!(f, "MAP: the logged keyframes were not all fed again: {problem}"),
            Progress::ResumedSeeded { last_seq, poses_recorded, seeds, newest_keyframe_seq, retrack } => write!(
                f,
                "resumed after frame {last_seq} ({poses_recorded} poses recorded): tracker seeded with {seeds}, newest at frame {newest_keyframe_seq}, in the recorded frame and scale; tracking {retrack} logged frames again"
            ),
            Progress::ResumedRestarted { last_seq, poses_recorded, from_seq, retrack } => write!(
                f,
                "resumed after frame {last_seq} ({poses_recorded} poses recorded): stopped during its initialisation (no keyframe in the log); tracking the {retrack} logged frames from frame {from_seq}, where the tracker started, again"
            ),
            Progress::ResumedAligned { last_seq, poses_recorded, why, frames, scale } => write!(
                f,
                "resumed after frame {last_seq} ({poses_recorded} poses recorded): {why}; re-initialised on {frames} logged frames and aligned by Sim(3), scale {scale:.4} (the scale of this fallback drifts)"
            ),
            Progress::ResumedNewFrame { last_seq, why } => write!(f, "resumed after frame {last_seq}: {why}; relocalisation failed, continuing in a new frame"),
            Progress::TrackingUnposed { frames, first_seq, last_seq } => {
                write!(f, "tracking {frames} frame(s) logged after the last recorded pose from the log (frames {first_seq}..{last_seq})")
            }
            Progress::LiveView { bind } => write!(f, "live view on ws://{bind} (Foxglove: open a connection, Foxglove WebSocket, ws://<vehicle>:<port>)"),
            Progress::LiveViewEnded(report) => write!(f, "{report}"),
            Progress::Tracking { frames } => write!(f, "tracking {} frames...", frames.map_or("all".to_string(), |n| n.to_string())),
            Progress::State { seq, state } => write!(f, "frame {seq:>6}: {state}"),
            Progress::InitWaited { summary } => f.write_str(summary),
            Progress::PipelineEnded {
                frames_captured,
                frames_tracked,
                frames_dropped,
                keyframes_dropped,
                keyframes_deferred,
                log_records_dropped,
                log_messages,
                log_segments,
                log_error,
                interrupted,
            } => write!(
                f,
                "pipeline: {frames_captured} frames captured, {frames_tracked} tracked, {frames_dropped} dropped (frame queue), {keyframes_dropped} keyframes dropped and {keyframes_deferred} deferred (mapping queue), {log_records_dropped} log records dropped; log {log_messages} messages in {log_segments} segment(s){}{}",
                log_error.map(|e| format!("; LOGGING STOPPED: {e}")).unwrap_or_default(),
                if *interrupted { "; interrupted" } else { "" }
            ),
            Progress::NothingLeft { after_seq } => write!(f, "nothing left to track after frame {after_seq}: the outputs are written from the log"),
            Progress::Latency { median_ms, p99_ms, after_init } => {
                write!(f, "frame-in to pose-out latency median {median_ms:.1} ms, p99 {p99_ms:.1} ms")?;
                match after_init {
                    Some((n, p99, max)) => write!(f, "; frames captured after initialisation ({n}): p99 {p99:.1} ms, max {max:.1} ms"),
                    None => Ok(()),
                }
            }
            Progress::LogRate { log_bytes, frames_captured, frames_per_s: fps, wall_s, budget_mb_per_s, maps_skipped, maps_offered } => {
                let per_frame = *log_bytes as f64 / (*frames_captured).max(1) as f64;
                let mb_s = per_frame * fps / 1e6;
                let budget = match budget_mb_per_s {
                    Some(b) if mb_s <= *b => format!("; budget {b} MB/s: under by {:.2}", b - mb_s),
                    Some(b) => format!("; budget {b} MB/s: OVER by {:.2}", mb_s - b),
                    None => "; no budget ([log] max_mb_per_s)".to_string(),
                };
                write!(
                    f,
                    "log {:.1} MB: {per_frame:.0} bytes per captured frame (all topics), {mb_s:.2} MB/s at the board's {fps:.0} frames/s ({:.2} MB/s over the {wall_s:.1} s run){budget}; map checkpoints logged {} of {maps_offered}, {maps_skipped} skipped for the budget",
                    *log_bytes as f64 / 1e6,
                    *log_bytes as f64 / 1e6 / wall_s,
                    maps_offered - maps_skipped,
                )
            }
            Progress::CaughtUp { keyframes } => write!(f, "map: {keyframes} logged keyframe(s) the keyframe queue had deferred mapped before the final optimisation"),
            Progress::Threads { summary } => f.write_str(summary),
            Progress::CatchUpProblem { problem } => write!(f, "MAP: the logged keyframes were not all mapped: {problem}"),
            Progress::DiveRecordNotWritten { error } => write!(f, "dive.json not written: {error}"),
            Progress::DepthFilesNotWritten { error } => write!(f, "KEYFRAME DEPTH FILES NOT ALL WRITTEN: {error}"),
            Progress::MapExported { summary } => f.write_str(summary),
            Progress::MapNotExported { error } => write!(f, "MAP NOT EXPORTED: {error}"),
            Progress::MapScored { summary } => write!(f, "{summary} (map/report.md)"),
            Progress::MapNotScored { error } => write!(f, "map not scored: {error}"),
            Progress::Units { summary } => write!(f, "{summary}"),
            Progress::NavStream { summary } => write!(f, "{summary}"),
            Progress::MetricNotWritten { error } => write!(f, "metric.json not written: {error}"),
        }
    }
}

/// How a dive run ended without an error.
pub enum DiveOutcome {
    /// The run folder holds a finished dive (its source ended, nothing was logged after) and
    /// continuing was not asked for: nothing changed.
    AlreadyFinished { record: DiveRecord },
    /// Stopped before the first frame was tracked, with nothing logged to write outputs from.
    /// `stop`: the signals that stopped it ([`Stop::exit_code`]).
    StoppedBeforeFirstFrame { stop: Stop },
    /// The dive's outputs are written.
    Written(Box<WrittenDive>),
}

/// A dive run whose outputs are written: what the caller prints, evaluates and exits with.
pub struct WrittenDive {
    /// The run folder's lock, held until this is dropped (the caller may write into the folder,
    /// e.g. an evaluation report).
    pub folder_lock: RunFolderLock,
    /// The source, for its ground truth.
    pub source: Source,
    /// The tracker at the end (times, counters, the live keyframes' depth).
    pub tracker: Tracker,
    /// What `trajectory.txt` and `keyframes.txt` hold (the whole dive).
    pub outputs: WrittenOutputs,
    /// `dive.json` as written (or as it would have been: the parts and how each ended).
    pub record: DiveRecord,
    /// This process's part of the dive.
    pub part: u32,
    /// Frames this process tracked from the source (0: a resume with nothing left to track,
    /// the outputs written from the log).
    pub frames_tracked: usize,
    /// Tracker-only time of every frame this process tracked (frames tracked again included).
    pub track_times: Vec<Duration>,
    /// Ended by a stop, not by the end of the source (the map exported without its final
    /// optimisation).
    pub interrupted: bool,
    /// The signals (first one: [`Stop::signal`], [`Stop::exit_code`]).
    pub stop: Stop,
    /// Why logging stopped early (a full disk): the log is incomplete.
    pub log_error: Option<String>,
    /// The map's figures (`map/report.json`), where the run mapped and finished.
    pub map_quality: Option<duv_eval::MapQuality>,
}

/// The `p` quantile (0..1) of sorted durations, milliseconds (0 for none).
pub fn percentile_ms(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

/// What a resumed run reads back from the log: the newest `ba_window` logged keyframes seed
/// the tracker (see [`resume`]); the logged frames after them are tracked again (at most 64 MiB
/// of them); the last 20 logged frames re-initialise the tracker when no keyframe is usable
/// (the fallback).
fn resume_options(board: &Board) -> resume::ResumeOptions {
    resume::ResumeOptions { relocalisation_frames: 20, seed_keyframes: board.budgets.ba_window as usize, retrack_bytes: 64 << 20 }
}

/// Runs a dive into `opts.out`: sets it up (resuming what the folder holds), tracks and maps the
/// source until it ends or a signal stops it, and writes the outputs of the whole dive (see the
/// module docs). `progress` gets each line of what happens as it happens.
// An error ends the run once: the size of `DiveError` (it carries the stages' errors) costs nothing.
#[allow(clippy::result_large_err)]
pub fn run_dive(opts: DiveOptions, progress: &mut dyn FnMut(&Progress)) -> Result<DiveOutcome, DiveError> {
    let started_unix_s = unix_now_s();
    // One writer per run folder, before anything in it is read or recovered.
    let folder_lock = RunFolderLock::acquire(&opts.out)?;
    let mut board = opts.board.load()?;
    if let Some(format) = opts.log_format {
        board.log.format = format;
    }
    let capacity = TrackerCapacity::from_board(&board);
    let mut cfg = match &opts.tracker_config {
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|source| DiveError::ReadConfig { path: p.clone(), source })?;
            toml::from_str::<TrackerConfig>(&text).map_err(|source| DiveError::Config { path: p.clone(), source })?
        }
        None => TrackerConfig::default(),
    };
    if !opts.loop_closure {
        cfg.loop_closure = false;
    }
    // A log in the output folder means a previous run stopped (or lost power) there: recover
    // it, reload the map checkpoint, relocalise, and continue in a new segment.
    let log_dir = opts.out.join("log");
    if !opts.resume && !duv_log::list_segments(&log_dir)?.is_empty() {
        return Err(DiveError::HoldsLog { log_dir });
    }
    // A finished dive (its source ended, and nothing was logged after) is left as it is.
    let previous = DiveRecord::load(&opts.out);
    if let Some(rec) = previous.as_ref().filter(|r| r.finished && opts.resume) {
        let segments = duv_log::list_segments(&log_dir)?.len() as u32;
        if segments == rec.log_segments && !opts.continue_dive {
            return Ok(DiveOutcome::AlreadyFinished { record: rec.clone() });
        }
    }
    // Room for the final outputs, whatever the log does to the disk.
    let reserve = DiskReserve::claim(&opts.out);
    let mut resume_state = if opts.resume { resume::prepare(&opts.out, ReadLimits::default(), &resume_options(&board))? } else { None };
    if let Some(r) = &mut resume_state {
        r.history.take_ends(previous.as_ref());
    }
    // The source goes on after the last logged frame; logged frames without a pose are
    // tracked from the log (no frame is logged twice).
    let start = match &resume_state {
        Some(r) if !opts.source.starts_with("mcap:") => match (r.poses_recorded > 0, r.last_frame_seq) {
            (true, f) => f.unwrap_or(0).max(r.last_seq) as usize + 1,
            (false, Some(f)) => f as usize + 1,
            (false, None) => 0,
        },
        _ => 0,
    };
    let source = Source::open(&opts.source, &opts.source_options, &board, start)?;
    let camera = source.camera();
    let plan = super::budget::plan(&board, camera.width, camera.height)?;
    let mut tracker = Tracker::new(&camera, &cfg, capacity)?;
    if let Some(mask) = source.ignore_mask() {
        tracker.set_ignore_mask(mask)?;
    }
    let keyframe_folder = KeyframeFolder::open(&opts.out)?;
    let grid = tracker.depth_camera();
    progress(&Progress::Started {
        source: &source.describe(),
        out: &opts.out,
        depth_grid: (grid.width, grid.height),
        depth_factor: tracker.depth_factor(),
        capacity,
        host_plan_bytes: plan.total_bytes,
        host_mb: board.budgets.host_mb,
    });

    // A `sim:` spec's `pace=realtime` is `--speed 1`.
    let sim_pace = opts.source.strip_prefix("sim:").map(|rest| SimSpec::parse(&opts.source, rest)).transpose()?.and_then(|s| s.pace);
    let speed = match sim_pace {
        Some(SimPace::Realtime) => Some(opts.speed.unwrap_or(1.0)),
        Some(SimPace::None) => {
            if opts.speed.is_some() {
                return Err(DiveError::PaceDisagrees { spec: opts.source.clone() });
            }
            None
        }
        None => opts.speed,
    };
    let mut pcfg = PipelineConfig::from_board(&board, opts.out.clone());
    pcfg.pace_speed = speed;
    pcfg.deterministic = opts.deterministic;
    // Recorded and generated sources lose nothing by waiting; paced replay behaves live.
    pcfg.lossless_frames = speed.is_none();
    pcfg.announce = opts.announce;
    pcfg.arrival_clock = Arc::new(super::clock::ArrivalClock::with_speed(speed.unwrap_or(1.0)));
    if let Some(p) = &opts.progress {
        pcfg.progress = p.clone();
    }
    if let Some(addr) = &opts.live_view {
        let mut live = board.live.clone();
        if let Some(addr) = addr {
            live.bind = addr.clone();
            live.validate().map_err(|(_, value, why)| DiveError::LiveView { value, why })?;
        }
        pcfg.live = Some(live);
    }
    let one = |k: &str, v: String| [(k.to_string(), v)].into_iter().collect();
    pcfg.log.metadata.push(("duv.tracker_config".into(), one("toml", toml::to_string(&cfg).unwrap_or_default())));
    pcfg.log.metadata.push(("duv.run".into(), one("source", opts.source.clone())));
    let c = camera;
    duv_core::io::write_atomic(&opts.out.join("calibration.txt"), format!("{} {} {} {} {} {}\n", c.fx, c.fy, c.cx, c.cy, c.width, c.height).as_bytes())?;
    let mut map: Box<dyn MapStage> = match &opts.mapping {
        None => Box::new(NoMapping::default()),
        Some(m) => {
            let map_config: MapperConfig = match &m.config {
                Some(p) => toml::from_str(&duv_core::io::read_text(p)?).map_err(|source| DiveError::Config { path: p.clone(), source })?,
                None => MapperConfig::default(),
            };
            let budget = MappingBudget { iterations_per_keyframe: m.iterations_per_keyframe, ..MappingBudget::default() };
            let stage = MappingStage::new(map_config, MapperCapacity::from_board(&board, camera.width, camera.height), budget)?;
            let scratch = opts.out.join("checkpoints").join("map-scratch.ckpt");
            std::fs::create_dir_all(opts.out.join("checkpoints")).map_err(DiveError::Folder)?;
            let mut mapping = GaussianMapping::new(stage, keyframe_folder.clone(), scratch, m.idle_iterations, m.final_iterations);
            let gpu = GpuOptions { deterministic: opts.deterministic, ..GpuOptions::with_budget_mb(board.budgets.gpu_mb) };
            let renderer = mapping.use_device(m.device, gpu).map_err(|error| DiveError::MapperDevice { device: m.device, error })?;
            progress(&Progress::MapperRenders { renderer: &renderer });
            Box::new(mapping)
        }
    };
    let mut retrack = Vec::new();
    let mut start_how = "fresh".to_string();
    if let Some(r) = &mut resume_state {
        for rep in &r.recovered {
            progress(&Progress::Recovered(rep));
        }
        if let Some((path, bytes)) = &r.checkpoint {
            map.restore(bytes).map_err(|error| DiveError::Checkpoint { path: path.clone(), error })?;
            progress(&Progress::CheckpointReloaded { path });
        }
        // The logged keyframes the map was not fed before it stopped (after its newest
        // checkpoint), one at a time from the log: the map covers every logged keyframe.
        if opts.mapping.is_some() && !r.history.keyframes.is_empty() {
            let newest = map.newest_keyframe();
            let refed = feed_unmapped_keyframes(map.as_mut(), &log_dir, &keyframe_folder, newest);
            if let Some(e) = &refed.problem {
                progress(&Progress::RefedProblem { problem: e });
            }
            if refed.keyframes > 0 {
                progress(&Progress::Refed { keyframes: refed.keyframes, after: newest });
            }
        }
        match resume::relocalise(&mut tracker, r)? {
            Relocalisation::Seeded { keyframes, frames, newest_keyframe_seq, retrack: again } => {
                let seeds = if let (true, Some(w)) = (keyframes > 0, r.window_seq) {
                    format!("the {keyframes} keyframes of the tracker window logged at frame {w}")
                } else if keyframes > 0 {
                    format!("{keyframes} logged keyframes")
                } else {
                    format!("{frames} logged frames at their recorded poses (no keyframe in the log)")
                };
                progress(&Progress::ResumedSeeded { last_seq: r.last_seq, poses_recorded: r.poses_recorded, seeds: &seeds, newest_keyframe_seq, retrack: again.len() });
                retrack = again;
                start_how = format!("resumed after frame {}: seeded with {seeds}", r.last_seq);
                // The seeded keyframes the log does not hold (they were waiting to be handed
                // on when the run stopped) go to mapping and the log first.
                let newest_logged = r.history.keyframes.keys().next_back().copied();
                for (seq, k) in &r.keyframes {
                    if newest_logged.is_none_or(|n| k.index > n) {
                        let frame = duv_core::Frame { t_ns: k.t_ns, seq: *seq, image: duv_core::FrameImage::Rgb8(k.image.clone()) };
                        pcfg.unlogged_keyframes.push((k.index, Arc::new(frame)));
                    }
                }
            }
            Relocalisation::Restarted { from_seq, retrack: again } => {
                progress(&Progress::ResumedRestarted { last_seq: r.last_seq, poses_recorded: r.poses_recorded, from_seq, retrack: again.len() });
                retrack = again;
                start_how = format!("resumed after frame {}: its initialisation tracked again from frame {from_seq}", r.last_seq);
            }
            Relocalisation::Aligned { world_from_tracker, why } => {
                progress(&Progress::ResumedAligned {
                    last_seq: r.last_seq,
                    poses_recorded: r.poses_recorded,
                    why: &why,
                    frames: r.recent.len(),
                    scale: world_from_tracker.scaling(),
                });
                pcfg.world_from_tracker = Some(world_from_tracker);
                start_how = format!("resumed after frame {}: re-initialised and aligned by Sim(3), scale {:.4}", r.last_seq, world_from_tracker.scaling());
            }
            Relocalisation::NewFrame { why } => {
                progress(&Progress::ResumedNewFrame { last_seq: r.last_seq, why: &why });
                start_how = format!("resumed after frame {}: in a new frame ({why})", r.last_seq);
            }
        }
    }
    if let Some(r) = &mut resume_state {
        if !opts.source.starts_with("mcap:") && !r.unposed.is_empty() {
            progress(&Progress::TrackingUnposed { frames: r.unposed.len(), first_seq: r.unposed[0].seq, last_seq: r.unposed[r.unposed.len() - 1].seq });
            retrack.append(&mut r.unposed);
        }
        pcfg.retrack_unlogged = retrack.iter().map(|f| f.seq).filter(|s| !r.history.frames.contains_key(s)).collect();
    }
    let part = resume_state.as_ref().map_or(0, |r| r.history.next_part());
    pcfg.log.metadata.push((PART_METADATA.into(), part_metadata(part, &start_how)));
    // From here SIGINT/SIGTERM stop the run in order (the log closes first), a second one at
    // once.
    let stop = Stop::on_signals()?;
    let total = source.len();
    // Navigation input, logged on `/nav/sample` as the run goes: `--nav FILE` read now (its
    // errors before any frame), the source's own (a dataset's nav.csv, the generator's
    // sensors, a logged one on replay), or a `--nav mavlink:` stream received from now on.
    let mut nav_stream = None;
    let mut known_nav: Option<Vec<duv_core::nav::NavSample>> = None;
    if opts.use_nav {
        match opts.nav_input.as_deref() {
            Some(spec) if spec.starts_with("mavlink:") => {
                let parsed = duv_camera::mavlink_nav::MavlinkNavSpec::parse(spec)?;
                let live = Arc::new(super::queue::BoundedQueue::new("nav", NAV_LIVE_QUEUE, 0, super::queue::FullPolicy::DropOldest));
                pcfg.nav_to_log.live = Some(live.clone());
                let tap: duv_camera::mavlink_nav::NavTap = Box::new(move |s| {
                    let _ = live.push(s, 0);
                });
                nav_stream = Some(duv_camera::mavlink_nav::NavReceiver::start(parsed, board.nav.body_from_cam(), board.nav.max_samples as usize, pcfg.arrival_clock.epoch(), Some(tap))?);
            }
            Some(file) => {
                let track = duv_core::nav::read_nav_csv(Path::new(file))?;
                if track.rejected.total() > 0 {
                    progress(&Progress::NavStream { summary: &format!("--nav {file}: {} samples, {}", track.samples.len(), track.rejected.describe()) });
                }
                known_nav = Some(track.samples);
            }
            None => known_nav = source.nav()?,
        }
    }
    pcfg.nav_to_log.known = known_nav.as_deref().unwrap_or_default().into();
    let run_source = RunSource { inner: source, camera, spec: opts.source.clone() };
    if let Some(live) = &pcfg.live {
        progress(&Progress::LiveView { bind: &live.bind });
    }
    let frames_expected = (total != usize::MAX).then(|| total.saturating_sub(start));
    pcfg.progress.set_frames_expected(frames_expected.map(|n| n as u64));
    progress(&Progress::Tracking { frames: frames_expected });
    let result = match super::run(run_source, tracker, map, &pcfg, retrack, stop.clone()) {
        Err(error @ PipelineError::Aborted { .. }) => {
            return Err(DiveError::Aborted { signal: stop.signal().unwrap_or(0), exit_code: stop.exit_code().unwrap_or(130), error });
        }
        r => r?,
    };
    let source = result.source.inner;
    let mut tracker = result.tracker;
    let recorder = result.recorder;
    let mut map = result.map;
    let track_times = result.track_times;
    let frames_done = recorder.frames().len();
    // State changes, as the tracking thread saw them.
    let mut last_state = None;
    for f in recorder.frames() {
        if last_state != Some(f.state) {
            progress(&Progress::State { seq: f.seq, state: f.state.name() });
            last_state = Some(f.state);
        }
    }
    if let Some(line) = init_summary(recorder.frames()) {
        progress(&Progress::InitWaited { summary: &line });
    }
    progress(&Progress::PipelineEnded {
        frames_captured: result.frames_captured,
        frames_tracked: frames_done,
        frames_dropped: result.frame_queue.dropped,
        keyframes_dropped: result.keyframe_queue.dropped,
        keyframes_deferred: result.keyframe_queue.deferred,
        log_records_dropped: result.log_queue.dropped,
        log_messages: result.log.messages,
        log_segments: result.log.segments,
        log_error: result.log_error.as_deref(),
        interrupted: result.interrupted,
    });
    if let Some(live) = &result.live {
        progress(&Progress::LiveViewEnded(live));
    }
    if !result.threads.is_empty() {
        progress(&Progress::Threads { summary: &result.threads });
    }
    let history = resume_state.as_ref().map(|r| &r.history).filter(|h| !h.frames.is_empty());
    if frames_done == 0 && history.is_none() {
        if result.interrupted {
            return Ok(DiveOutcome::StoppedBeforeFirstFrame { stop });
        }
        return Err(DiveError::NoFrame);
    }
    if frames_done == 0 {
        progress(&Progress::NothingLeft { after_seq: start.saturating_sub(1) });
    } else {
        let mut e2e: Vec<Duration> = result.latencies.clone();
        let after_init = result.after_init_from.filter(|&i| i < e2e.len()).map(|i| {
            let mut steady = e2e[i..].to_vec();
            steady.sort();
            (steady.len(), percentile_ms(&steady, 0.99), percentile_ms(&steady, 1.0))
        });
        e2e.sort();
        progress(&Progress::Latency { median_ms: percentile_ms(&e2e, 0.5), p99_ms: percentile_ms(&e2e, 0.99), after_init });
        progress(&Progress::LogRate {
            log_bytes: result.log.bytes,
            frames_captured: result.frames_captured,
            frames_per_s: 1e3 / pcfg.frame_period_ms,
            wall_s: result.wall.as_secs_f64().max(1e-9),
            budget_mb_per_s: pcfg.log.max_mb_per_s,
            maps_skipped: result.log.maps_skipped,
            maps_offered: result.log.maps_logged + result.log.maps_skipped,
        });
    }

    // Final trajectory, keyframes, their depth maps and states of the whole dive: one writer,
    // this process's poses in the recorded frame over what earlier processes logged.
    // Keyframes the full keyframe queue deferred are in the log: the map gets them now,
    // before its final optimisation, so it covers every logged keyframe (`keyframe_queue`).
    // Only this run's deferred keyframes, from this run's segments (an earlier run's are fed
    // when the dive is resumed).
    if opts.mapping.is_some() && !result.interrupted && !result.deferred_keyframes.is_empty() {
        let dropped: BTreeSet<u64> = result.deferred_keyframes.iter().copied().collect();
        let earlier: BTreeSet<u32> = resume_state.as_ref().map(|r| r.history.parts.values().flat_map(|p| p.segments.iter().copied()).collect()).unwrap_or_default();
        let mut refed = Refed::default();
        for (index, segment) in duv_log::list_segments(&log_dir)?.into_iter().filter(|(i, _)| !earlier.contains(i)) {
            let r = feed_logged_keyframes(map.as_mut(), &segment, |id| dropped.contains(&id) && !keyframe_folder.has_image(id));
            refed.keyframes += r.keyframes;
            if let Some(e) = r.problem {
                refed.problem.get_or_insert(format!("segment {index}: {e}"));
            }
        }
        if let Some(e) = &refed.problem {
            progress(&Progress::CatchUpProblem { problem: e });
        }
        if refed.keyframes > 0 {
            progress(&Progress::CaughtUp { keyframes: refed.keyframes });
        }
    }
    // The room kept since the start, for the dive's record (small files first).
    reserve.release();
    let fin = finish_trajectory(&recorder, &mut tracker, pcfg.world_from_tracker.as_ref());
    // Metres when the source has navigation input and a sensor observed the scale.
    let nav = if !opts.use_nav {
        None
    } else if let Some(rx) = nav_stream {
        let spec = opts.nav_input.clone().unwrap_or_default();
        match pcfg.arrival_clock.frame_time_ns(0) {
            Some(_) => {
                let clock = pcfg.arrival_clock.clone();
                let got = rx.finish(|r| clock.frame_time_ns(r).unwrap_or(r));
                progress(&Progress::NavStream { summary: &mavlink_summary(&spec, &got) });
                (!got.track.samples.is_empty()).then_some(got.track.samples)
            }
            None => None,
        }
    } else {
        known_nav
    };
    // A resumed dive: the samples the earlier processes logged as well (a stream's are nowhere
    // else); repeated times are kept once.
    let logged_nav = resume_state.as_ref().map(|r| &r.history.nav).filter(|n| opts.use_nav && !n.is_empty());
    let nav = match (nav, logged_nav) {
        (Some(mut now), Some(logged)) => {
            now.extend_from_slice(logged);
            Some(duv_core::nav::validate_samples(now).samples)
        }
        (None, Some(logged)) => Some(duv_core::nav::validate_samples(logged.clone()).samples),
        (nav, None) => nav,
    };
    let (mut units, metric_from_world) = match &nav {
        None if !opts.use_nav => (MetricRecord::map_units("navigation input turned off (--no-nav)", 0), None),
        None if opts.nav_input.is_some() => (MetricRecord::map_units(format!("--nav {} delivered no usable navigation sample", opts.nav_input.as_deref().unwrap_or_default()), 0), None),
        None => (MetricRecord::map_units("the source has no navigation input (nav.csv beside a dataset, nav=FILE, or sim:...,nav=on)", 0), None),
        Some(samples) => match super::metric::estimate_for_dive(samples, &fin, history, &tracker, pcfg.world_from_tracker.as_ref()) {
            Ok(a) => (MetricRecord::metric(&a, samples.len()), Some(a.metric_from_map)),
            Err(e) => (MetricRecord::map_units(e.to_string(), samples.len()), None),
        },
    };
    // Segments that never merged by sight, placed in the metric world by the navigation.
    let mut output_frames = OutputFrames { world: metric_from_world, joined: BTreeMap::new() };
    if let (Some(samples), Some(world)) = (&nav, &metric_from_world) {
        let (joined, not) = super::metric::join_segments(samples, &fin, history, &tracker, pcfg.world_from_tracker.as_ref(), world);
        for (m, record) in joined {
            output_frames.joined.insert(record.segment, m);
            units.joined_segments.push(record);
        }
        units.segments_not_joined = not;
    }
    progress(&Progress::Units { summary: &units.summary() });
    if let Err(e) = units.write(&opts.out) {
        progress(&Progress::MetricNotWritten { error: &e });
    }
    map.set_output_frame(metric_from_world);
    let mapped = opts.mapping.is_some().then_some(&keyframe_folder);
    let written = write_tracking_outputs(&opts.out, &fin, recorder.frames(), &track_times, &tracker, mapped, history, &output_frames)?;
    // dive.json: the parts of the dive and how each ended.
    let end = match stop.signal() {
        Some(sig) if result.interrupted => format!("stopped by signal {sig}"),
        _ if result.interrupted => "stopped".to_string(),
        _ => "source ended".to_string(),
    };
    let segments_now = duv_log::list_segments(&log_dir)?;
    let mut parts: Vec<DivePart> = resume_state.as_ref().map(|r| r.history.parts.values().cloned().collect()).unwrap_or_default();
    let earlier: BTreeSet<u32> = parts.iter().flat_map(|p| p.segments.iter().copied()).collect();
    let mine_seqs = recorder.frames().iter().map(|f| f.seq);
    parts.push(DivePart {
        part,
        pid: std::process::id(),
        started_unix_s,
        start: start_how.clone(),
        end: Some(end.clone()),
        segments: segments_now.iter().map(|(i, _)| *i).filter(|i| !earlier.contains(i)).collect(),
        poses_logged: frames_done as u64,
        first_seq: mine_seqs.clone().min(),
        last_seq: mine_seqs.max(),
    });
    let record = DiveRecord {
        finished: !result.interrupted,
        end,
        frames: written.frames,
        frames_with_pose: written.frames_with_pose,
        map_segments: written.segments.clone(),
        first_seq: written.first_seq,
        last_seq: written.last_seq,
        keyframes: written.keyframes,
        log_segments: segments_now.len() as u32,
        parts,
    };
    // Written before the map export (large, it may not fit a full disk) and marked finished
    // only after it: a run stopped during the export is resumed, not taken as finished.
    if let Err(e) = (DiveRecord { finished: false, ..record.clone() }).write(&opts.out) {
        progress(&Progress::DiveRecordNotWritten { error: &e });
    }
    // A full disk here is reported, not an error: the files above are the dive's record.
    let (mut inv, mut var) = (PlaneF32::new(camera.width, camera.height), PlaneF32::new(camera.width, camera.height));
    // The keyframes' depth is the tracker's; metric, it takes the resume's scale too.
    let depth_to_metric = metric_from_world.map(|m| {
        let s = m.scaling() * pcfg.world_from_tracker.map_or(1.0, |a| a.scaling());
        duv_core::Sim3::from_parts(nalgebra::Translation3::identity(), nalgebra::UnitQuaternion::identity(), s)
    });
    if let Err(e) = write_keyframe_depths(&keyframe_folder, &tracker, &mut inv, &mut var, depth_to_metric.as_ref()) {
        progress(&Progress::DepthFilesNotWritten { error: &e });
    }
    // The map: final keyframe poses, a last optimisation, the exports.
    // (Segment 0's: the map holds no other segment's keyframes.)
    let final_poses: Vec<(u64, duv_core::Se3)> = fin.keyframes.iter().filter(|k| k.segment == 0).map(|k| (k.id, k.world_from_cam)).collect();
    // A failed export (e.g. a full disk) is reported, like a stopped log; the tracking outputs
    // and the report still follow.
    match map.finish(&final_poses, &opts.out, !result.interrupted) {
        Ok(Some(summary)) => progress(&Progress::MapExported { summary: &summary }),
        Ok(None) => {}
        Err(e) => progress(&Progress::MapNotExported { error: &e }),
    }
    // The map's figures on frames between keyframes (a finished run only: a stopped one
    // exports the map as it is and goes).
    let map_quality = if result.interrupted {
        None
    } else {
        let posed: Vec<(u64, duv_core::Se3)> = recorder
            .frames()
            .iter()
            .zip(&fin.frames)
            .enumerate()
            .filter(|(i, _)| fin.sources.get(*i).is_some_and(|s| s.has_pose()) && fin.segments.get(*i) == Some(&0))
            .map(|(_, (r, p))| (r.seq, p.world_from_cam))
            .collect();
        let mut posed = posed;
        posed.sort_by_key(|p| p.0);
        let kf_seqs: BTreeSet<u64> = fin.keyframes.iter().filter(|k| k.segment == 0).map(|k| k.seq).collect();
        match super::map_report::score_run_map(map.as_mut(), &source, &opts.out, &posed, &kf_seqs, &camera, metric_from_world.as_ref()) {
            Ok(q) => q,
            Err(e) => {
                progress(&Progress::MapNotScored { error: &e });
                None
            }
        }
    };
    if let Some(q) = &map_quality {
        progress(&Progress::MapScored { summary: &q.summary() });
    }
    if record.finished {
        if let Err(e) = record.write(&opts.out) {
            progress(&Progress::DiveRecordNotWritten { error: &e });
        }
    }
    Ok(DiveOutcome::Written(Box::new(WrittenDive {
        folder_lock,
        source,
        tracker,
        outputs: written,
        record,
        part,
        frames_tracked: frames_done,
        track_times,
        interrupted: result.interrupted,
        stop,
        log_error: result.log_error,
        map_quality,
    })))
}

/// Live navigation samples waiting for the capture thread to log them (a few seconds of a
/// fast autopilot stream).
const NAV_LIVE_QUEUE: usize = 1024;

/// One line on what a MAVLink stream delivered: messages, samples by sensor, rejections.
fn mavlink_summary(spec: &str, got: &duv_camera::mavlink_nav::MavlinkNav) -> String {
    let c = &got.counts;
    let depth = match got.depth_source {
        Some(k) => format!("depth from {k:?} ({} of {} depth messages)", got.track.samples.iter().filter(|s| s.depth_m.is_some()).count(), c.depth.iter().sum::<u64>()),
        None => "no depth".to_string(),
    };
    let span = match (got.track.samples.first(), got.track.samples.last()) {
        (Some(a), Some(b)) => format!(" ({:.2} to {:.2} s on the frames' clock)", a.t_ns.t_ns() as f64 * 1e-9, b.t_ns.t_ns() as f64 * 1e-9),
        _ => String::new(),
    };
    format!(
        "navigation stream {spec}: {} messages in {} datagrams; {depth}, {} attitudes, {} altitudes, {} DVL velocities ({} below the confidence floor); {} samples kept{span}{}{}",
        c.messages,
        c.datagrams,
        c.attitude,
        c.altitude,
        c.velocity,
        c.low_confidence,
        got.track.samples.len(),
        if got.track.rejected.total() > 0 { format!(", {}", got.track.rejected.describe()) } else { String::new() },
        if c.over_capacity > 0 { format!(", {} past the board's [nav] max_samples", c.over_capacity) } else { String::new() },
    )
}
