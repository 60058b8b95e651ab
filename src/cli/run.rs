//! `duv run`: track a frame source (a dataset folder or a generated `sim:` sequence), write the
//! trajectory, the keyframes and their full-resolution inverse depth and variance, and, where
//! ground truth exists, the evaluation report (ATE with Sim(3) alignment, AUSE of the depth
//! uncertainty).

use anyhow::Context;
use duv_core::config::board::Board;
use duv_core::{PlaneF32, StampedPose};
use duv_eval::report::AuseInput;
use duv_eval::{build_report, write_report, EvalInputs, EvalOptions};
use duv_camera::sim::{SimPace, SimSpec};
use duv_log::ReadLimits;
use duv_map::GpuOptions;
use duv_map::mapper::{MapperCapacity, MapperConfig};
use duv_map::backend::MapperDevice;
use duv_map::stage::{MappingBudget, MappingStage};
use duv_pipeline::mapping::StageMapping;
use duv_pipeline::source::{RunSource, Source, SourceOptions};
use duv_pipeline::dive::{part_metadata, unix_now_s, DivePart, DiveRecord, PART_METADATA};
use duv_pipeline::{resume, MapStage, NoMapping, PipelineConfig};
use duv_track::{Tracker, TrackerCapacity, TrackerConfig};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

/// What a resumed run reads back from the log: the newest `ba_window` logged keyframes seed
/// the tracker (see `pipeline::resume`); the logged frames after them are tracked again (at
/// most 64 MiB of them); the last 20 logged frames re-initialise the tracker when no keyframe
/// is usable (the fallback).
fn resume_options(board: &Board) -> resume::ResumeOptions {
    resume::ResumeOptions { relocalisation_frames: 20, seed_keyframes: board.budgets.ba_window as usize, retrack_bytes: 64 << 20 }
}

#[derive(clap::Args)]
pub struct RunArgs {
    /// Frame source: `tum:DIR`, `euroc:DIR`, `tartanair:DIR`, `folder:DIR` (dataset options as
    /// in `duv dataset`), `mcap:LOG`, a live camera (`v4l2:`, `aravis:`), or
    /// `sim:WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=realtime|none]` generated in memory,
    /// e.g. `sim:coastal`, `sim:turbid-loop,frames=50,seed=3` (water: clear, coastal, turbid;
    /// trajectory: survey, loop, hover; `frames`/`seed` as --frames/--seed; `pace=realtime` is
    /// --speed 1).
    #[arg(long)]
    source: String,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Board profile: capacities (keyframes, BA window), threads, and the sim image size.
    #[arg(long, default_value = "boards/sim.toml")]
    pub board: PathBuf,
    /// Track at most this many frames (a `sim:` source generates this many).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Disable loop closure (and with it the pose graph and the global BA after loops).
    #[arg(long)]
    no_loop_closure: bool,
    /// Tracker parameters (TOML, `TrackerConfig` fields); defaults otherwise.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Image width of a `sim:` source [default: the board's camera width].
    #[arg(long)]
    width: Option<usize>,
    /// Image height of a `sim:` source [default: the board's camera height].
    #[arg(long)]
    height: Option<usize>,
    /// Seed of a `sim:` source (its `seed=S` option wins).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// No progress line on stderr.
    #[arg(long)]
    no_progress: bool,
    /// Pace the source at its time stamps divided by this factor (1 = recorded timing).
    #[arg(long)]
    pub speed: Option<f64>,
    /// Single-threaded, no drops, seeded, and the Vulkan mapper without float atomics:
    /// bit-identical output for the same input on the same device.
    #[arg(long)]
    pub deterministic: bool,
    /// Start over: an output folder with a log is refused instead of resumed.
    #[arg(long)]
    pub no_resume: bool,
    /// Track the source further on a finished dive (by default a folder whose dive finished,
    /// its source ended, is left as it is).
    #[arg(long = "continue")]
    pub continue_dive: bool,
    /// Print `tracked SEQ T_NS` per frame and `synced SEGMENT MESSAGES BYTES` per fsync on
    /// stdout (the crash harness reads them).
    #[arg(long, hide = true)]
    announce: bool,
    /// Track only: no map, no map exports.
    #[arg(long)]
    pub no_map: bool,
    /// Mapper iterations after each keyframe handed to mapping.
    #[arg(long, default_value_t = MappingBudget::default().iterations_per_keyframe)]
    pub map_iterations: u64,
    /// Mapper iterations while the mapping thread waits for the next keyframe (at most).
    #[arg(long, default_value_t = 30)]
    pub map_idle_iterations: u64,
    /// Mapper iterations after the last frame, on the final keyframe poses.
    #[arg(long, default_value_t = 100)]
    pub map_final_iterations: u64,
    /// Mapper parameters (TOML, `MapperConfig` fields); defaults otherwise.
    #[arg(long, value_name = "FILE")]
    map_config: Option<PathBuf>,
    /// Where the mapper renders: `auto` = the Vulkan kernels on a GPU (the CPU reference when
    /// the only Vulkan device runs on the CPU, e.g. lavapipe, unless DUV_VULKAN_DEVICE names
    /// it), `vulkan` = the Vulkan kernels on any device, `cpu` = the CPU reference. No Vulkan
    /// device at all: the CPU reference with one warning. GPU memory: the board's gpu_mb.
    #[arg(long, value_enum, default_value_t = MapperDevice::Auto)]
    pub mapper: MapperDevice,
    /// Soak test: an `mcap:` source starts over at its end until this many seconds have
    /// passed, with time stamps and sequence numbers continued (`duv bench replay`).
    #[arg(long, hide = true, value_name = "SECONDS")]
    pub loop_for_s: Option<f64>,
}

fn percentile_ms(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

/// Exit status of a run whose outputs were written but whose log stopped early (a full disk).
pub const EXIT_LOG_INCOMPLETE: u8 = 3;

/// The slowest playback `--speed` takes (a recorded second then lasts about 17 minutes).
const MIN_SPEED: f64 = 1e-3;

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    // Numeric options are checked before anything is opened or written.
    if let Some(s) = args.speed {
        anyhow::ensure!(s.is_finite() && s >= MIN_SPEED, "--speed must be a finite factor >= {MIN_SPEED}, got {s}");
    }
    let started_unix_s = unix_now_s();
    // One writer per run folder, before anything in it is read or recovered.
    let _lock = duv_pipeline::lock::RunFolderLock::acquire(&args.out)?;
    let board = super::load_board(&args.board)?;
    let capacity = TrackerCapacity::from_board(&board);
    let mut cfg = match &args.config {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            toml::from_str::<TrackerConfig>(&text).with_context(|| format!("{}", p.display()))?
        }
        None => TrackerConfig::default(),
    };
    if args.no_loop_closure {
        cfg.loop_closure = false;
    }
    // A log in the output folder means a previous run stopped (or lost power) there: recover
    // it, reload the map checkpoint, relocalise, and continue in a new segment.
    let log_dir = args.out.join("log");
    if args.no_resume {
        anyhow::ensure!(duv_log::list_segments(&log_dir)?.is_empty(), "--no-resume: {} already holds a log; choose another --out", log_dir.display());
    }
    // A finished dive (its source ended, and nothing was logged after) is left as it is.
    let previous = DiveRecord::load(&args.out);
    if let Some(rec) = previous.as_ref().filter(|r| r.finished && !args.no_resume) {
        let segments = duv_log::list_segments(&log_dir)?.len() as u32;
        if segments == rec.log_segments && !args.continue_dive {
            println!(
                "{} holds a finished dive: {} frames ({}..{}), {} keyframes, {} part(s), {}; nothing changed (--continue tracks the source further)",
                args.out.display(),
                rec.frames,
                rec.first_seq.map_or("-".into(), |s| s.to_string()),
                rec.last_seq.map_or("-".into(), |s| s.to_string()),
                rec.keyframes,
                rec.parts.len(),
                rec.end
            );
            return Ok(());
        }
    }
    // Room for the final outputs, whatever the log does to the disk.
    let reserve = duv_pipeline::outputs::DiskReserve::claim(&args.out);
    let mut resume_state = if args.no_resume { None } else { resume::prepare(&args.out, ReadLimits::default(), &resume_options(&board))? };
    if let Some(r) = &mut resume_state {
        r.history.take_ends(previous.as_ref());
    }
    // The source goes on after the last logged frame; logged frames without a pose are
    // tracked from the log (no frame is logged twice).
    let start = match &resume_state {
        Some(r) if !args.source.starts_with("mcap:") => match (r.poses_recorded > 0, r.last_frame_seq) {
            (true, f) => f.unwrap_or(0).max(r.last_seq) as usize + 1,
            (false, Some(f)) => f as usize + 1,
            (false, None) => 0,
        },
        _ => 0,
    };
    let source_options = SourceOptions { frames: args.frames, width: args.width, height: args.height, seed: args.seed, loop_for_s: args.loop_for_s };
    let source = Source::open(&args.source, &source_options, &board, start)?;
    let camera = source.camera();
    let plan = duv_pipeline::budget::plan(&board, camera.width, camera.height)?;
    let mut tracker = Tracker::new(&camera, &cfg, capacity)?;
    let kf_dir = args.out.join("keyframes");
    std::fs::create_dir_all(&kf_dir).with_context(|| format!("creating {}", kf_dir.display()))?;
    let grid = tracker.depth_camera();
    eprintln!(
        "duv run: {} -> {} (depth grid {}x{}, 1/{}; {} keyframes, BA window {}, {} threads; host plan {:.1} of {} MiB)",
        source.describe(),
        args.out.display(),
        grid.width,
        grid.height,
        tracker.depth_factor(),
        capacity.max_keyframes,
        capacity.ba_window,
        capacity.threads,
        plan.total_bytes as f64 / (1 << 20) as f64,
        board.budgets.host_mb
    );

    // A `sim:` spec's `pace=realtime` is `--speed 1`.
    let sim_pace = args.source.strip_prefix("sim:").map(|rest| SimSpec::parse(&args.source, rest)).transpose()?.and_then(|s| s.pace);
    let speed = match sim_pace {
        Some(SimPace::Realtime) => Some(args.speed.unwrap_or(1.0)),
        Some(SimPace::None) => {
            anyhow::ensure!(args.speed.is_none(), "{}: pace=none and --speed disagree", args.source);
            None
        }
        None => args.speed,
    };
    let mut pcfg = PipelineConfig::from_board(&board, args.out.clone());
    pcfg.pace_speed = speed;
    pcfg.deterministic = args.deterministic;
    // Recorded and generated sources lose nothing by waiting; paced replay behaves live.
    pcfg.lossless_frames = speed.is_none();
    pcfg.announce = args.announce;
    let one = |k: &str, v: String| [(k.to_string(), v)].into_iter().collect();
    pcfg.log.metadata.push(("duv.tracker_config".into(), one("toml", toml::to_string(&cfg).unwrap_or_default())));
    pcfg.log.metadata.push(("duv.run".into(), one("source", args.source.clone())));
    let c = camera;
    duv_core::io::write_atomic(&args.out.join("calibration.txt"), format!("{} {} {} {} {} {}\n", c.fx, c.fy, c.cx, c.cy, c.width, c.height).as_bytes())?;
    let mut map: Box<dyn MapStage> = if args.no_map {
        Box::new(NoMapping::default())
    } else {
        let map_config: MapperConfig = match &args.map_config {
            Some(p) => toml::from_str(&duv_core::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
            None => MapperConfig::default(),
        };
        let budget = MappingBudget { iterations_per_keyframe: args.map_iterations, ..MappingBudget::default() };
        let stage = MappingStage::new(map_config, MapperCapacity::from_board(&board, camera.width, camera.height), budget)?;
        let scratch = args.out.join("checkpoints").join("map-scratch.ckpt");
        std::fs::create_dir_all(args.out.join("checkpoints"))?;
        let mut mapping = StageMapping::new(stage, kf_dir.clone(), scratch, args.map_idle_iterations, args.map_final_iterations);
        let gpu = GpuOptions { deterministic: args.deterministic, ..GpuOptions::with_budget_mb(board.budgets.gpu_mb) };
        let renderer = mapping.use_device(args.mapper, gpu).map_err(|e| anyhow::anyhow!("mapper (--mapper {:?}): {e}", args.mapper))?;
        eprintln!("mapper renders with {renderer}");
        Box::new(mapping)
    };
    let mut retrack = Vec::new();
    let mut start_how = "fresh".to_string();
    if let Some(r) = &mut resume_state {
        for rep in &r.recovered {
            match &rep.left_in_place {
                None => eprintln!(
                    "recovered {}: {} messages kept in intact chunks, {} damaged range(s) skipped, {} of {} bytes ({})",
                    rep.segment.display(),
                    rep.messages_kept,
                    rep.skipped_ranges,
                    rep.bytes_after,
                    rep.bytes_before,
                    rep.damage
                ),
                Some(why) => eprintln!("NOT RECOVERED {}: {why}; left as it is, {} messages readable ({})", rep.segment.display(), rep.messages_kept, rep.damage),
            }
        }
        if let Some((path, bytes)) = &r.checkpoint {
            map.restore(bytes).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            eprintln!("map checkpoint {} reloaded", path.display());
        }
        // The logged keyframes the map was not fed before it stopped (after its newest
        // checkpoint), one at a time from the log: the map covers every logged keyframe.
        if !args.no_map && !r.history.keyframes.is_empty() {
            let newest = map.newest_keyframe();
            let refed = duv_pipeline::mapping::feed_unmapped_keyframes(map.as_mut(), &log_dir, &kf_dir, newest);
            if let Some(e) = &refed.problem {
                eprintln!("MAP: the logged keyframes were not all fed again: {e}");
            }
            if refed.keyframes > 0 {
                eprintln!("map: {} logged keyframe(s) the map did not cover fed again (after {})", refed.keyframes, newest.map_or("the start".to_string(), |n| format!("keyframe {n}, the checkpoint's newest")));
            }
        }
        match resume::relocalise(&mut tracker, r)? {
            resume::Relocalisation::Seeded { keyframes, frames, newest_keyframe_seq, retrack: again } => {
                let seeds = if let (true, Some(w)) = (keyframes > 0, r.window_seq) {
                    format!("the {keyframes} keyframes of the tracker window logged at frame {w}")
                } else if keyframes > 0 {
                    format!("{keyframes} logged keyframes")
                } else { format!("{frames} logged frames at their recorded poses (no keyframe in the log)") };
                eprintln!(
                    "resumed after frame {} ({} poses recorded): tracker seeded with {seeds}, newest at frame {newest_keyframe_seq}, in the recorded frame and scale; tracking {} logged frames again",
                    r.last_seq,
                    r.poses_recorded,
                    again.len()
                );
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
            resume::Relocalisation::Restarted { from_seq, retrack: again } => {
                eprintln!(
                    "resumed after frame {} ({} poses recorded): stopped during its initialisation (no keyframe in the log); tracking the {} logged frames from frame {from_seq}, where the tracker started, again",
                    r.last_seq,
                    r.poses_recorded,
                    again.len()
                );
                retrack = again;
                start_how = format!("resumed after frame {}: its initialisation tracked again from frame {from_seq}", r.last_seq);
            }
            resume::Relocalisation::Aligned { world_from_tracker, why } => {
                eprintln!(
                    "resumed after frame {} ({} poses recorded): {why}; re-initialised on {} logged frames and aligned by Sim(3), scale {:.4} (the scale of this fallback drifts)",
                    r.last_seq,
                    r.poses_recorded,
                    r.recent.len(),
                    world_from_tracker.scaling()
                );
                pcfg.world_from_tracker = Some(world_from_tracker);
                start_how = format!("resumed after frame {}: re-initialised and aligned by Sim(3), scale {:.4}", r.last_seq, world_from_tracker.scaling());
            }
            resume::Relocalisation::NewFrame { why } => {
                eprintln!("resumed after frame {}: {why}; relocalisation failed, continuing in a new frame", r.last_seq);
                start_how = format!("resumed after frame {}: in a new frame ({why})", r.last_seq);
            }
        }
    }
    if let Some(r) = &mut resume_state {
        if !args.source.starts_with("mcap:") && !r.unposed.is_empty() {
            eprintln!("tracking {} frame(s) logged after the last recorded pose from the log (frames {}..{})", r.unposed.len(), r.unposed[0].seq, r.unposed[r.unposed.len() - 1].seq);
            retrack.append(&mut r.unposed);
        }
        pcfg.retrack_unlogged = retrack.iter().map(|f| f.seq).filter(|s| !r.history.frames.contains_key(s)).collect();
    }
    let part = resume_state.as_ref().map_or(0, |r| r.history.next_part());
    pcfg.log.metadata.push((PART_METADATA.into(), part_metadata(part, &start_how)));
    // From here SIGINT/SIGTERM stop the run in order (the log closes first), a second one at
    // once.
    let stop = duv_pipeline::Stop::on_signals()?;
    let total = source.len();
    let run_source = RunSource { inner: source, camera, spec: args.source.clone() };
    if !args.no_progress {
        eprintln!("tracking {} frames...", if total == usize::MAX { "all".to_string() } else { total.saturating_sub(start).to_string() });
    }
    let stopped_by = |stop: &duv_pipeline::Stop, what: &str| super::Exit { code: stop.exit_code().unwrap_or(130), why: format!("stopped by signal {}: {what}", stop.signal().unwrap_or(0)) };
    let result = match duv_pipeline::run(run_source, tracker, map, &pcfg, retrack, stop.clone()) {
        Err(e @ duv_pipeline::PipelineError::Aborted { .. }) => {
            return Err(stopped_by(&stop, &format!("{e}; the outputs were not written (a resume rebuilds them from the log)")).into());
        }
        r => r?,
    };
    let source = result.source.inner;
    let tracker = result.tracker;
    let recorder = result.recorder;
    let mut map = result.map;
    let latencies = result.track_times;
    let frames_done = recorder.frames().len();
    // State changes, as the tracking thread saw them.
    let mut last_state = None;
    for f in recorder.frames() {
        if last_state != Some(f.state) {
            eprintln!("frame {:>6}: {}", f.seq, f.state.name());
            last_state = Some(f.state);
        }
    }
    if let Some(line) = duv_pipeline::outputs::init_summary(recorder.frames()) {
        eprintln!("{line}");
    }
    let track_time: Duration = latencies.iter().sum();
    let mut inv = PlaneF32::new(camera.width, camera.height);
    let mut var = PlaneF32::new(camera.width, camera.height);
    println!(
        "pipeline: {} frames captured, {} tracked, {} dropped (frame queue), {} keyframes dropped (mapping queue), {} log records dropped; log {} messages in {} segment(s){}{}",
        result.frames_captured,
        frames_done,
        result.frame_queue.dropped,
        result.keyframe_queue.dropped,
        result.log_queue.dropped,
        result.log.messages,
        result.log.segments,
        result.log_error.as_ref().map(|e| format!("; LOGGING STOPPED: {e}")).unwrap_or_default(),
        if result.interrupted { "; interrupted" } else { "" }
    );
    let history = resume_state.as_ref().map(|r| &r.history).filter(|h| !h.frames.is_empty());
    if frames_done == 0 && history.is_none() {
        if result.interrupted {
            println!("stopped before the first frame was tracked");
            if stop.exit_code().is_some() {
                return Err(stopped_by(&stop, "before the first frame was tracked").into());
            }
            return Ok(());
        }
        anyhow::bail!("the source delivered no frame");
    }
    if frames_done == 0 {
        println!("nothing left to track after frame {}: the outputs are written from the log", start.saturating_sub(1));
    } else {
        let mut e2e: Vec<Duration> = result.latencies.clone();
        e2e.sort();
        println!("frame-in to pose-out latency median {:.1} ms, p99 {:.1} ms", percentile_ms(&e2e, 0.5), percentile_ms(&e2e, 0.99));
        let wall_s = result.wall.as_secs_f64().max(1e-9);
        let per_frame = result.log.bytes as f64 / result.frames_captured.max(1) as f64;
        let fps = 1e3 / pcfg.frame_period_ms;
        println!(
            "log {:.1} MB: {per_frame:.0} bytes per captured frame (all topics), {:.1} MB/s at the board's {fps:.0} frames/s ({:.2} MB/s over the {wall_s:.1} s run)",
            result.log.bytes as f64 / 1e6,
            per_frame * fps / 1e6,
            result.log.bytes as f64 / 1e6 / wall_s
        );
    }

    // Final trajectory, keyframes, their depth maps and states of the whole dive: one writer,
    // this process's poses in the recorded frame over what earlier processes logged.
    // Keyframes the full keyframe queue kept from mapping are in the log: the map gets them
    // now, before its final optimisation, so it covers every logged keyframe.
    // Only this run's dropped keyframes, from this run's segments (an earlier run's are fed
    // when the dive is resumed).
    if !args.no_map && !result.interrupted && !result.dropped_keyframes.is_empty() {
        let dropped: std::collections::BTreeSet<u64> = result.dropped_keyframes.iter().copied().collect();
        let earlier: std::collections::BTreeSet<u32> = resume_state.as_ref().map(|r| r.history.parts.values().flat_map(|p| p.segments.iter().copied()).collect()).unwrap_or_default();
        let mut refed = duv_pipeline::mapping::Refed::default();
        for (index, segment) in duv_log::list_segments(&log_dir)?.into_iter().filter(|(i, _)| !earlier.contains(i)) {
            let r = duv_pipeline::mapping::feed_logged_keyframes(map.as_mut(), &segment, |id| dropped.contains(&id) && !kf_dir.join(format!("{id:06}.png")).exists());
            refed.keyframes += r.keyframes;
            if let Some(e) = r.problem {
                refed.problem.get_or_insert(format!("segment {index}: {e}"));
            }
        }
        if let Some(e) = &refed.problem {
            eprintln!("MAP: the logged keyframes were not all mapped: {e}");
        }
        if refed.keyframes > 0 {
            println!("map: {} logged keyframe(s) the keyframe queue had dropped mapped before the final optimisation", refed.keyframes);
        }
    }
    // The room kept since the start, for the dive's record (small files first).
    reserve.release();
    let fin = duv_pipeline::outputs::finish_trajectory(&recorder, &tracker, pcfg.world_from_tracker.as_ref());
    let written = duv_pipeline::outputs::write_tracking_outputs(&args.out, &fin, recorder.frames(), &latencies, &tracker, !args.no_map, history)?;
    let live = written.live.clone();
    // dive.json: the parts of the dive and how each ended.
    let end = match stop.signal() {
        Some(sig) if result.interrupted => format!("stopped by signal {sig}"),
        _ if result.interrupted => "stopped".to_string(),
        _ => "source ended".to_string(),
    };
    let segments_now = duv_log::list_segments(&log_dir)?;
    let mut parts: Vec<DivePart> = resume_state.as_ref().map(|r| r.history.parts.values().cloned().collect()).unwrap_or_default();
    let earlier: std::collections::BTreeSet<u32> = parts.iter().flat_map(|p| p.segments.iter().copied()).collect();
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
        first_seq: written.first_seq,
        last_seq: written.last_seq,
        keyframes: written.keyframes,
        log_segments: segments_now.len() as u32,
        parts,
    };
    // Written before the map export (large, it may not fit a full disk) and marked finished
    // only after it: a run stopped during the export is resumed, not taken as finished.
    if let Err(e) = (DiveRecord { finished: false, ..record.clone() }).write(&args.out) {
        eprintln!("dive.json not written: {e}");
    }
    // A full disk here is reported, not an error: the files above are the dive's record.
    if let Err(e) = duv_pipeline::outputs::write_keyframe_depths(&args.out, &tracker, &mut inv, &mut var) {
        eprintln!("KEYFRAME DEPTH FILES NOT ALL WRITTEN: {e}");
    }
    // The map: final keyframe poses, a last optimisation, the exports.
    let final_poses: Vec<(u64, duv_core::Se3)> = fin.keyframes.iter().map(|k| (k.id, k.world_from_cam)).collect();
    // A failed export (e.g. a full disk) is reported, like a stopped log; the tracking outputs
    // and the report still follow.
    match map.finish(&final_poses, &args.out, !result.interrupted) {
        Ok(Some(summary)) => println!("{summary}"),
        Ok(None) => {}
        Err(e) => eprintln!("MAP NOT EXPORTED: {e}"),
    }
    if record.finished {
        if let Err(e) = record.write(&args.out) {
            eprintln!("dive.json not written: {e}");
        }
    }
    println!(
        "dive: {} frames in trajectory.txt ({} from earlier parts), {} keyframes, part {part} of {}",
        written.frames,
        written.frames_from_log,
        written.keyframes,
        record.parts.len()
    );
    if frames_done == 0 {
        if result.interrupted && stop.exit_code().is_some() {
            return Err(stopped_by(&stop, "outputs written from the log").into());
        }
        return Ok(());
    }

    // Timing.
    let times = tracker.times();
    let counters = tracker.counters();
    let n = frames_done as f64;
    let mut latencies_sorted = latencies.clone();
    latencies_sorted.sort();
    let secs = track_time.as_secs_f64();
    println!(
        "tracked {frames_done} frames in {secs:.2} s: {:.1} frames/s (tracker only), latency median {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        n / secs.max(1e-9),
        percentile_ms(&latencies_sorted, 0.5),
        percentile_ms(&latencies_sorted, 0.99),
        percentile_ms(&latencies_sorted, 1.0)
    );
    println!(
        "per frame: flow {:.2} ms, BA {:.2} ms, covariance {:.2} ms, loop closure {:.2} ms ({} flow estimates, {} loop screens)",
        times.flow.as_secs_f64() * 1e3 / n,
        times.ba.as_secs_f64() * 1e3 / n,
        times.covariance.as_secs_f64() * 1e3 / n,
        times.loop_closure.as_secs_f64() * 1e3 / n,
        times.flow_estimates,
        times.loop_screens
    );
    println!(
        "keyframes: {} inserted, {} pruned, {} evicted, {} live; loops closed {}; global BAs {}; lost frames {}; relocalisations {}",
        counters.keyframes_inserted,
        counters.keyframes_pruned,
        counters.keyframes_evicted,
        live.len(),
        counters.loops_closed,
        counters.global_bas,
        counters.lost_frames,
        counters.relocalisations
    );

    if let Some(e) = &result.log_error {
        if stop.exit_code().is_none() {
            return Err(super::Exit { code: EXIT_LOG_INCOMPLETE, why: format!("the outputs are written, but the log is incomplete: logging stopped: {e}") }.into());
        }
    }
    if result.interrupted {
        if let Some(code) = stop.exit_code() {
            return Err(super::Exit { code, why: stopped_by(&stop, "outputs written; the map was exported without its final optimisation, no evaluation").why }.into());
        }
    }
    // Evaluation against ground truth. A trajectory too short to align (a run stopped during
    // initialisation) is reported, not a failed run: its outputs are all written by now.
    if let Some(gt) = source.ground_truth() {
        if let Err(e) = evaluate(&args, &source, &tracker, &gt, &written.trajectory, &live, &mut inv, &mut var) {
            eprintln!("evaluation skipped: {e:#}");
        }
    }
    Ok(())
}

/// The eval report of a finished run against the source's ground truth (ATE, AUSE of the
/// keyframes whose true depth the source has), printed and written to `OUT/eval`.
#[allow(clippy::too_many_arguments)]
fn evaluate(
    args: &RunArgs,
    source: &Source,
    tracker: &Tracker,
    gt: &[StampedPose],
    frames: &[StampedPose],
    live: &[(u64, u64)],
    inv: &mut PlaneF32,
    var: &mut PlaneF32,
) -> anyhow::Result<()> {
    {
        let options = EvalOptions::default();
        let gt_name = format!("{} ground truth", args.source);
        let est_name = args.out.join("trajectory.txt").display().to_string();
        let base = EvalInputs { gt_name, est_name, gt, est: frames, images: &[], images_source: None, ause: &[], ause_source: None, options };
        let first = build_report(&base)?;
        let scale = first.report.trajectory.alignment.scale;
        let mut ause: Vec<AuseInput> = Vec::new();
        for &(id, seq) in live {
            let Some(depth) = source.depth(seq) else { continue };
            tracker.upsample_keyframe(id, inv, var)?;
            let (mut errors, mut uncertainties) = (Vec::new(), Vec::new());
            for ((&z, &d), &v) in depth.data.iter().zip(&inv.data).zip(&var.data) {
                if z > 0.0 && d.is_finite() && v.is_finite() && v < f32::MAX {
                    errors.push((1.0 / z as f64 - d as f64 / scale).abs());
                    uncertainties.push(v as f64 / (scale * scale));
                }
            }
            if errors.len() >= 100 {
                ause.push(AuseInput { name: format!("keyframe {id:06}"), errors, uncertainties });
            }
        }
        let evaluation = if ause.is_empty() {
            first
        } else {
            build_report(&EvalInputs { ause: &ause, ause_source: Some("keyframe inverse depth vs ground truth, variance as uncertainty".into()), ..base })?
        };
        let eval_dir = args.out.join("eval");
        write_report(&evaluation, &eval_dir).with_context(|| format!("writing the report to {}", eval_dir.display()))?;
        print!("{}", evaluation.report.metrics_table());
        println!("wrote {}", eval_dir.display());
    }
    Ok(())
}

impl RunArgs {
    /// The arguments `duv run --source SOURCE --out OUT` would get, everything else default
    /// (used by `duv demo`).
    pub fn with_defaults(source: String, out: PathBuf, no_progress: bool) -> Self {
        RunArgs {
            source,
            out,
            board: PathBuf::from("boards/sim.toml"),
            frames: None,
            no_loop_closure: false,
            config: None,
            width: None,
            height: None,
            seed: 1,
            no_progress,
            speed: None,
            deterministic: false,
            no_resume: false,
            continue_dive: false,
            announce: false,
            no_map: true,
            map_iterations: MappingBudget::default().iterations_per_keyframe,
            map_idle_iterations: 30,
            map_final_iterations: 100,
            map_config: None,
            mapper: MapperDevice::Auto,
            loop_for_s: None,
        }
    }
}
