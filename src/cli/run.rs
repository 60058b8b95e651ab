//! `duv run`: track a frame source (a dataset folder or a generated `sim:` sequence), write the
//! trajectory, the keyframes and their full-resolution inverse depth and variance, and, where
//! ground truth exists, the evaluation report (ATE with Sim(3) alignment, AUSE of the depth
//! uncertainty).
//!
//! The run itself is `duv_pipeline::run_dive`: this file turns the arguments into its options,
//! prints what it reports, evaluates against the ground truth and maps the outcome to the exit
//! status. `duv replay` and `duv demo` run their dives through [`run`].

use anyhow::Context;
use duv_core::config::board::LogFormatSetting;
use duv_core::{PlaneF32, StampedPose};
use duv_eval::report::AuseInput;
use duv_eval::{build_report, write_report, Alignment, EvalInputs, EvalOptions, TrajectoryOptions};
use duv_map::backend::MapperDevice;
use duv_map::stage::MappingBudget;
use duv_pipeline::dive_run::{percentile_ms, BoardFile, MappingOptions, WrittenDive};
use duv_pipeline::source::{Source, SourceOptions};
use duv_pipeline::{run_dive, DiveError, DiveOptions, DiveOutcome, Progress, ProgressSnapshot, RunProgress, Stop};
use std::io::IsTerminal;
use std::sync::Arc;
use duv_track::Tracker;
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(clap::Args)]
pub struct RunArgs {
    /// Frame source: `tum:DIR`, `euroc:DIR`, `tartanair:DIR`, `folder:DIR` (dataset options as
    /// in `duv dataset`), `mcap:LOG`, a ROS 2 bag
    /// (`rosbag:DIR_OR_MCAP[,image=/topic][,camera_info=/topic][,calib=FILE][,fov=DEG]
    /// [,depth=/topic][,altitude=/topic][,dvl=/topic][,imu=/topic][,water_density=KG_M3]
    /// [,surface_pressure=PA]`: CDR images, CameraInfo and navigation topics), a live camera
    /// (`v4l2:`, `aravis:`), or
    /// `sim:WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=realtime|none][,nav=on][,lamps=on]
    /// [,backscatter=S][,snow=N][,seabed=C][,burst=START:DURATION[:FACTOR]][,night=on]` generated in
    /// memory, e.g. `sim:coastal`, `sim:turbid-loop,frames=50,seed=3`,
    /// `sim:coastal-loop,night=on` (water: clear, coastal, turbid; trajectory: survey, loop,
    /// hover; `frames`/`seed` as --frames/--seed; `pace=realtime` is --speed 1; `nav=on` adds
    /// the generator's navigation sensors; the scene options as `duv sim`'s --lamps,
    /// --lamp-backscatter, --snow, --seabed-texture, --burst, --night).
    /// With navigation input (a dataset's `nav.csv`, `nav=FILE`, `nav=on`, a bag's navigation
    /// topics) the outputs are in
    /// metres; `metric.json` says which unit a run folder is in.
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
    #[arg(long = "tracker-config", alias = "config", value_name = "FILE")]
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
    /// Track only: no map, no map exports, no map report. With a map, a finished run scores it
    /// on up to 8 frames between keyframes (one render each) into DIR/map/report.{json,md}.
    #[arg(long)]
    pub no_map: bool,
    /// Ignore the source's navigation sensors: outputs in map units, as a camera alone gives.
    #[arg(long, conflicts_with = "nav")]
    pub no_nav: bool,
    /// Navigation input besides the source's own: the vehicle's autopilot over MAVLink,
    /// `mavlink:udpin:HOST:PORT[,depth=auto|pressure2|pressure|global_position|vfr_hud]
    /// [,surface_pa=101325][,density=1025][,min_confidence=0.5]` (received during the run,
    /// stamped on arrival; the camera's mounting is the board's `[nav] camera_rpy_deg`), or a
    /// `nav.csv` file on the frames' clock.
    #[arg(long, value_name = "SPEC")]
    pub nav: Option<String>,
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
    #[arg(long = "mapper-config", alias = "map-config", value_name = "FILE")]
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
    /// Serve a live view for Foxglove (WebSocket) on ADDR (`HOST:PORT`) or, without ADDR, on the
    /// board's `[live] bind`: pose, tracking state, a downscaled camera, keyframes and Gaussian
    /// centres within the board's bandwidth cap. Needs a build with the `live-view` feature.
    #[arg(long, value_name = "ADDR", num_args = 0..=1)]
    pub live_view: Option<Option<String>>,
    /// The log's message schemas [default: the board's `[log] format`]: `foxglove` (protobuf,
    /// opens in Foxglove) or `ros2` (a ROS 2 bag in rosbag2's layout: CDR messages, metadata.yaml).
    #[arg(long, value_enum)]
    pub log_format: Option<LogFormatArg>,
}

/// `--log-format`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormatArg {
    Foxglove,
    Ros2,
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
    if args.live_view.is_some() && !cfg!(feature = "live-view") {
        anyhow::bail!("--live-view: this build lacks the `live-view` feature (build with `cargo build --features live-view`)");
    }
    if let Some(Some(addr)) = &args.live_view {
        anyhow::ensure!(addr.parse::<std::net::SocketAddr>().is_ok(), "--live-view {addr:?}: must be HOST:PORT with a numeric address, e.g. 0.0.0.0:8765");
    }
    let no_progress = args.no_progress;
    let mut options = args.dive_options();
    // The progress line: on a terminal only (never into a file or a pipe), off with --no-progress.
    let line = (!no_progress && std::io::stderr().is_terminal()).then(|| {
        let counters = Arc::new(RunProgress::new());
        options.progress = Some(counters.clone());
        ProgressLine::start(counters)
    });
    let outcome = run_dive(options, &mut |p: &Progress| {
        if no_progress && matches!(p, Progress::Tracking { .. }) {
            return;
        }
        if p.is_result() {
            println!("{p}");
        } else if let Some(line) = &line {
            line.bar.suspend(|| eprintln!("{p}"));
        } else {
            eprintln!("{p}");
        }
    });
    if let Some(line) = line {
        line.finish();
    }
    let dive = match outcome {
        Ok(DiveOutcome::Written(dive)) => dive,
        Ok(DiveOutcome::AlreadyFinished { record: rec }) => {
            println!(
                "{} holds a finished dive: {} frames ({}..{}, {} with a pose estimate), {} keyframes, {} part(s), {}; nothing changed (--continue tracks the source further)",
                args.out.display(),
                rec.frames,
                rec.first_seq.map_or("-".into(), |s| s.to_string()),
                rec.last_seq.map_or("-".into(), |s| s.to_string()),
                rec.frames_with_pose,
                rec.keyframes,
                rec.parts.len(),
                rec.end
            );
            return Ok(());
        }
        Ok(DiveOutcome::StoppedBeforeFirstFrame { stop }) => {
            println!("stopped before the first frame was tracked");
            if stop.exit_code().is_some() {
                return Err(stopped_by(&stop, "before the first frame was tracked").into());
            }
            return Ok(());
        }
        Err(e @ DiveError::Aborted { exit_code, .. }) => return Err(super::Exit { code: exit_code, why: e.to_string() }.into()),
        Err(e) => return Err(e.into()),
    };
    // Held until the evaluation report is written.
    let WrittenDive { folder_lock: _lock, source, tracker, outputs: written, record, part, frames_tracked: frames_done, track_times: latencies, interrupted, stop, log_error, map_quality } = *dive;
    let in_world: u64 = written.segments.iter().filter(|s| s.0 == 0 || written.joined.contains(&s.0)).map(|s| s.1).sum();
    let joined: Vec<String> = written.segments.iter().filter(|s| written.joined.contains(&s.0)).map(|(s, n)| format!("{n} of map segment {s}")).collect();
    let others: Vec<String> = written.segments.iter().filter(|s| s.0 != 0 && !written.joined.contains(&s.0)).map(|(s, n)| format!("{n} in trajectory-segment-{s}.txt")).collect();
    println!(
        "dive: {} frames ({} from earlier parts), {} with a pose estimate ({in_world} in trajectory.txt{}{}){}, {} keyframes, part {part} of {}",
        written.frames,
        written.frames_from_log,
        written.frames_with_pose,
        if joined.is_empty() { String::new() } else { format!(", of them {}, joined by navigation", joined.join(", ")) },
        if others.is_empty() { String::new() } else { format!(", {}: map segments that never merged into the first", others.join(", ")) },
        if written.frames_with_pose < written.frames { "; the others: pose none in states.txt" } else { "" },
        written.keyframes,
        record.parts.len()
    );
    if frames_done == 0 {
        if interrupted && stop.exit_code().is_some() {
            return Err(stopped_by(&stop, "outputs written from the log").into());
        }
        return Ok(());
    }

    // Timing.
    let track_time: Duration = latencies.iter().sum();
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
        written.live.len(),
        counters.loops_closed,
        counters.global_bas,
        counters.lost_frames,
        counters.relocalisations
    );
    if counters.segments_started > 0 {
        println!(
            "map segments: {} started after a loss, {} merged; {} keyframe(s) of segments other than 0 not mapped",
            counters.segments_started,
            counters.segments_merged,
            tracker.keyframes_of_other_segments()
        );
    }

    if let Some(e) = &log_error {
        if stop.exit_code().is_none() {
            return Err(super::Exit { code: EXIT_LOG_INCOMPLETE, why: format!("the outputs are written, but the log is incomplete: logging stopped: {e}") }.into());
        }
    }
    if interrupted {
        if let Some(code) = stop.exit_code() {
            return Err(super::Exit { code, why: stopped_by(&stop, "outputs written; the map was exported without its final optimisation, no evaluation").why }.into());
        }
    }
    // Evaluation against ground truth. A trajectory too short to align (a run stopped during
    // initialisation) is reported, not a failed run: its outputs are all written by now.
    if let Some(gt) = source.ground_truth() {
        if let Err(e) = evaluate(&args, &source, &tracker, &gt, &written.trajectory, &written.live, map_quality.as_ref()) {
            eprintln!("evaluation skipped: {e:#}");
        }
    }
    Ok(())
}

/// How a run stopped by a signal exits: the shell's status for the signal (130 without one).
fn stopped_by(stop: &Stop, what: &str) -> super::Exit {
    super::Exit { code: stop.exit_code().unwrap_or(130), why: format!("stopped by signal {}: {what}", stop.signal().unwrap_or(0)) }
}

/// The eval report of a finished run against the source's ground truth (ATE, AUSE of the
/// keyframes whose true depth the source has), printed and written to `OUT/eval`.
fn evaluate(args: &RunArgs, source: &Source, tracker: &Tracker, gt: &[StampedPose], frames: &[StampedPose], live: &[(u64, u64)], map: Option<&duv_eval::MapQuality>) -> anyhow::Result<()> {
    {
        let camera = source.camera();
        let (mut inv, mut var) = (PlaneF32::new(camera.width, camera.height), PlaneF32::new(camera.width, camera.height));
        let options = EvalOptions::default();
        let gt_name = format!("{} ground truth", args.source);
        let est_name = args.out.join("trajectory.txt").display().to_string();
        let base = EvalInputs { gt_name, est_name, gt, est: frames, images: &[], images_source: None, ause: &[], ause_source: None, options };
        let first = build_report(&base)?;
        let scale = first.report.trajectory.alignment.scale;
        // Metric outputs (metric.json): the trajectory is in metres, the tracker's depth is not.
        let units = duv_pipeline::metric::MetricRecord::read(&args.out)?;
        let metres_per_unit = units.as_ref().and_then(|m| m.metres_per_map_unit).unwrap_or(1.0);
        if units.as_ref().is_some_and(|m| m.length_unit == "m") {
            let o = base.options;
            let se3 = build_report(&EvalInputs { options: EvalOptions { trajectory: TrajectoryOptions { alignment: Alignment::Se3, ..o.trajectory }, ..o }, ..base.clone() })?;
            let t = &se3.report.trajectory;
            println!(
                "metric: ATE with SE(3) alignment (no scale) {:.4} m RMSE, {} of path; scale error (the Sim(3) scale - 1) {:+.2} %",
                t.ate.stats_m.rmse,
                t.ate_rmse_percent_of_path.map_or("n/a".into(), |p| format!("{p:.3} %")),
                100.0 * (scale - 1.0)
            );
        }
        let scale = scale * metres_per_unit;
        let mut ause: Vec<AuseInput> = Vec::new();
        for &(id, seq) in live {
            let Some(depth) = source.depth(seq) else { continue };
            tracker.upsample_keyframe(id, &mut inv, &mut var)?;
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
        let mut evaluation = if ause.is_empty() {
            first
        } else {
            build_report(&EvalInputs { ause: &ause, ause_source: Some("keyframe inverse depth vs ground truth, variance as uncertainty".into()), ..base })?
        };
        if let Some(m) = map {
            // The map's renders of the frames between keyframes are the report's images; its
            // panels lie in the run folder, one up from `eval/`.
            let report = &mut evaluation.report;
            report.images = duv_eval::report::ImageReport::from_map_quality(m, camera.width, camera.height);
            report.inputs.images = Some(format!("the map rendered at {} frames between keyframes (tracked poses) vs those frames, ../map/report.json", m.views));
            report.map = Some(duv_eval::MapQuality { panels: m.panels.iter().map(|p| format!("../{p}")).collect(), ..m.clone() });
        }
        let eval_dir = args.out.join("eval");
        write_report(&evaluation, &eval_dir).with_context(|| format!("writing the report to {}", eval_dir.display()))?;
        print!("{}", evaluation.report.metrics_table());
        println!("wrote {}", eval_dir.display());
    }
    Ok(())
}

impl RunArgs {
    /// What the run does, as the pipeline takes it (the board, the parameter files and the
    /// folder are read by the run, after it locks the folder).
    fn dive_options(&self) -> DiveOptions {
        // The default board, when it is not there (a run started outside the repository), is
        // the copy built into the binary (as `super::load_board`).
        let board = if self.board == Path::new(super::DEFAULT_BOARD) {
            BoardFile::PathOr { path: self.board.clone(), name: PathBuf::from("<built-in boards/sim.toml>"), text: super::BUILT_IN_SIM_BOARD.to_string() }
        } else {
            BoardFile::Path(self.board.clone())
        };
        DiveOptions {
            source: self.source.clone(),
            out: self.out.clone(),
            board,
            tracker_config: self.config.clone(),
            loop_closure: !self.no_loop_closure,
            source_options: SourceOptions { frames: self.frames, width: self.width, height: self.height, seed: self.seed, loop_for_s: self.loop_for_s },
            speed: self.speed,
            deterministic: self.deterministic,
            resume: !self.no_resume,
            continue_dive: self.continue_dive,
            announce: self.announce,
            use_nav: !self.no_nav,
            progress: None,
            nav_input: self.nav.clone(),
            log_format: self.log_format.map(|f| match f {
                LogFormatArg::Foxglove => LogFormatSetting::Foxglove,
                LogFormatArg::Ros2 => LogFormatSetting::Ros2,
            }),
            live_view: self.live_view.clone(),
            mapping: (!self.no_map).then(|| MappingOptions {
                config: self.map_config.clone(),
                iterations_per_keyframe: self.map_iterations,
                idle_iterations: self.map_idle_iterations,
                final_iterations: self.map_final_iterations,
                device: self.mapper,
            }),
        }
    }

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
            no_nav: false,
            nav: None,
            map_iterations: MappingBudget::default().iterations_per_keyframe,
            map_idle_iterations: 30,
            map_final_iterations: 100,
            map_config: None,
            mapper: MapperDevice::Auto,
            loop_for_s: None,
            log_format: None,
            live_view: None,
        }
    }
}

/// `duv run`'s progress line on stderr: frames tracked (of how many), the tracking state and
/// map segment, frames per second, keyframes handed to mapping and the map's Gaussians, redrawn
/// a few times a second from the pipeline's counters while the run goes on.
struct ProgressLine {
    bar: indicatif::ProgressBar,
    done: Arc<std::sync::atomic::AtomicBool>,
    redraw: Option<std::thread::JoinHandle<()>>,
}

impl ProgressLine {
    fn start(counters: Arc<RunProgress>) -> Self {
        let bar = indicatif::ProgressBar::new_spinner();
        if let Ok(style) = indicatif::ProgressStyle::with_template("run [{elapsed_precise}] {pos}{msg}") {
            bar.set_style(style);
        }
        bar.set_message(progress_text(&counters.snapshot(), Duration::ZERO));
        let done = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (b, d) = (bar.clone(), done.clone());
        let redraw = std::thread::Builder::new()
            .name("progress".into())
            .spawn(move || {
                let started = std::time::Instant::now();
                while !d.load(std::sync::atomic::Ordering::Relaxed) {
                    let p = counters.snapshot();
                    b.set_position(p.frames_tracked);
                    b.set_message(progress_text(&p, started.elapsed()));
                    std::thread::sleep(Duration::from_millis(250));
                }
            })
            .ok();
        ProgressLine { bar, done, redraw }
    }

    fn finish(mut self) {
        self.done.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(h) = self.redraw.take() {
            let _ = h.join();
        }
        self.bar.finish_and_clear();
    }
}

/// The part of the progress line after the frame count, e.g. `/300 frames, tracking (segment 0),
/// 41.3 FPS, 17 keyframes, map 12345 Gaussians`.
fn progress_text(p: &ProgressSnapshot, elapsed: Duration) -> String {
    let of = p.frames_expected.map_or(String::new(), |n| format!("/{n}"));
    let segment = if p.segment > 0 { format!(" (segment {})", p.segment) } else { String::new() };
    let fps = if elapsed.as_secs_f64() > 0.0 { p.frames_tracked as f64 / elapsed.as_secs_f64() } else { 0.0 };
    let map = p.gaussians.map_or(String::new(), |g| format!(", map {g} Gaussians"));
    format!("{of} frames, {}{segment}, {fps:.1} FPS, {} keyframes{map}", p.state, p.keyframes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_progress_text_names_every_figure() {
        let counters = RunProgress::new();
        counters.set_frames_expected(Some(300));
        for _ in 0..60 {
            counters.frame_tracked("tracking", 1);
        }
        counters.keyframe_handed_on();
        counters.set_gaussians(12_345);
        let text = progress_text(&counters.snapshot(), Duration::from_secs(2));
        assert_eq!(text, "/300 frames, tracking (segment 1), 30.0 FPS, 1 keyframes, map 12345 Gaussians");
        let none = RunProgress::new();
        assert_eq!(progress_text(&none.snapshot(), Duration::ZERO), " frames, starting, 0.0 FPS, 0 keyframes");
    }
}
