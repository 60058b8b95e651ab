//! `duv bench track`: the tracking benchmark of issue 3. Generates survey, loop and turbid
//! sequences in memory (`duv_sim`), tracks each `--runs` times with and without loop closure
//! on the tracker's own thread pool (as a tracking thread does: `Tracker::run_in_pool`), and
//! prints and writes (`bench_track.json`, `bench_track.md`) the medians: frames/s, per-stage
//! milliseconds, frame latency p50/p99/max, frames/s and latency p99/max after the monocular
//! initialisation (the bootstrap runs once per dive), ATE (m and % of path), AUSE of inverse
//! depth and of depth (the paper's) against random orderings, peak RSS and the tracker's heap
//! peak.
//!
//! Rendering the sequence and scoring it are outside every timing; the frames are held in
//! memory for all runs (their bytes are reported beside the RSS, which includes them).

use anyhow::Context;
use duv_core::{Frame, FrameImage, PlaneF32};
use duv_eval::{ause, evaluate_trajectory, AuseOptions, TrajectoryOptions};
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use duv_track::{PoseSource, Tracker, TrackerCapacity, TrackerConfig, TrackingState, TrajectoryRecorder};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(clap::Args)]
pub struct BenchTrackArgs {
    /// Sequences: `survey` (coastal survey), `loop` (coastal loop), `turbid` (turbid survey), and
    /// the hard cases: `night` (a 240-frame coastal loop lit by the vehicle's lamps, their glow
    /// in the water, marine snow: `duv sim --night`), `snow` (the survey through 400 snow
    /// particles per m^3 in daylight), `burst` (the survey with a turbidity burst, x8 for 4 s
    /// from 12 s), `burstloop` (the loop with that burst from 15 s: a new map segment, merged
    /// when the loop returns), `sandturn` (the survey's lanes 1 m apart, fast turns, over sand
    /// at a twentieth of its texture contrast), `lowfps` (the survey at 2 frames/s, 150
    /// frames). Frames with a pose, segments started and at the end; ATE over the frames with a
    /// pose, each segment aligned on its own.
    #[arg(long, value_delimiter = ',', default_value = "survey,loop,turbid")]
    sequences: Vec<String>,
    /// Input sizes, `WIDTHxHEIGHT`.
    #[arg(long, value_delimiter = ',', default_value = "320x240,640x480")]
    sizes: Vec<String>,
    /// Frames per sequence [default: the generator's preset, 300 for surveys, 400 for the loop].
    #[arg(long)]
    frames: Option<usize>,
    /// Runs per sequence, size and loop-closure setting (medians are reported).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Loop closure: `both` (with and without), `on` or `off`.
    #[arg(long, default_value = "both")]
    loop_closure: String,
    /// Board profile: capacities (keyframes, BA window) and tracking threads.
    #[arg(long, default_value = "boards/sim.toml")]
    board: PathBuf,
    /// Tracker parameters (TOML, `TrackerConfig` fields); defaults otherwise.
    #[arg(long = "tracker-config", alias = "config", value_name = "FILE")]
    config: Option<PathBuf>,
    /// Seed of the generated sequences.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Skip the AUSE (it renders the true depth of every final keyframe).
    #[arg(long)]
    no_ause: bool,
    /// Output folder for `bench_track.json` and `bench_track.md`.
    #[arg(long, default_value = "out/bench")]
    out: PathBuf,
}

/// One tracking run, scored.
#[derive(Clone, Debug, Serialize)]
struct RunMetrics {
    fps: f64,
    /// CPU time of all the process's threads per frame, ms (steadier than wall time on a
    /// loaded machine).
    cpu_ms_per_frame: f64,
    /// Mean per frame, ms.
    flow_ms: f64,
    ba_ms: f64,
    covariance_ms: f64,
    loop_closure_ms: f64,
    global_ba_ms: f64,
    latency_p50_ms: f64,
    latency_p99_ms: f64,
    latency_max_ms: f64,
    /// Frames before the first tracked pose (monocular initialisation: the tracker collects
    /// `init_keyframes` keyframes, then solves them together).
    init_frames: u64,
    /// Frames/s, latency p99 and max over the frames after initialisation (the steady state a
    /// dive spends its time in; the whole-run figures above include the bootstrap).
    fps_tracking: f64,
    latency_p99_tracking_ms: f64,
    latency_max_tracking_ms: f64,
    /// Frames with a pose estimate (measured or interpolated between measured poses, as
    /// `trajectory.txt` holds them); the ATE is over these.
    frames_with_pose: u64,
    /// Of them, measured (tracked against a keyframe).
    frames_measured: u64,
    /// Times the initialisation started again (`init_restart_after`).
    init_restarts: u64,
    /// Map segments before merging (1 + new segments started after a loss) and after (those
    /// holding the frames with a pose at the end).
    segments_started: u64,
    segments_final: u64,
    /// Over the frames with a pose, each segment aligned on its own (Sim(3)): the RMSE over
    /// all of them.
    ate_rmse_m: f64,
    /// That RMSE over the sum of the segments' paths (the ground truth's over the span each
    /// covers).
    ate_percent_of_path: f64,
    path_m: f64,
    keyframes_inserted: u64,
    loops_closed: u64,
    lost_frames: u64,
    /// Mean AUSE over the final keyframes (full resolution, MAE of inverse depth, ranked by the
    /// inverse-depth variance), NaN if skipped.
    ause: f64,
    ause_random: f64,
    /// The same on the MAE of depth in metres, as the paper's Table 4, ranked by the depth
    /// variance the inverse-depth variance implies to first order (`var / rho^4`); pixels with a
    /// non-positive inverse depth are left out.
    ause_depth: f64,
    ause_depth_random: f64,
    /// Peak resident set (VmHWM) during the run, MiB (reset before each run where the kernel allows).
    rss_peak_mib: f64,
    /// Heap peak above what was live before the tracker was built, MiB.
    tracker_heap_peak_mib: f64,
}

#[derive(Debug, Serialize)]
struct CaseResult {
    sequence: String,
    width: usize,
    height: usize,
    frames: usize,
    loop_closure: bool,
    runs: usize,
    /// Bytes of the in-memory frames (included in the RSS).
    frames_mib: f64,
    median: RunMetrics,
    all: Vec<RunMetrics>,
}

#[derive(Serialize)]
struct BenchReport {
    command: String,
    board: String,
    threads: usize,
    cpus: usize,
    rss_reset_per_run: bool,
    cases: Vec<CaseResult>,
}

fn parse_size(s: &str) -> anyhow::Result<(usize, usize)> {
    let (w, h) = s.split_once('x').with_context(|| format!("size {s:?}: expected WIDTHxHEIGHT"))?;
    Ok((w.trim().parse().with_context(|| format!("size {s:?}: width"))?, h.trim().parse().with_context(|| format!("size {s:?}: height"))?))
}

/// The generated sequence a row names: water, path and the hard conditions of a real dive.
fn sequence_config(name: &str) -> anyhow::Result<SimConfig> {
    let survey = || SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Survey);
    Ok(match name {
        "survey" => survey(),
        "loop" => SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Loop),
        "turbid" => SimConfig::preset(WaterPreset::Turbid, TrajectoryKind::Survey),
        // A lamp-lit night loop: no daylight, the lamps' pool of light and their glow in the
        // water move with the camera, marine snow crosses the view (`duv sim --night`).
        "night" => {
            let mut c = SimConfig { frames: 240, ..SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Loop) };
            c.apply_night();
            c
        }
        // Daylight survey through heavy marine snow.
        "snow" => SimConfig { snow_per_m3: 400.0, ..survey() },
        // A turbidity burst: the view fades out for a few seconds and returns.
        "burst" => SimConfig { burst: Some(duv_sim::Burst { start_s: 12.0, duration_s: 4.0, factor: 8.0 }), ..survey() },
        // The burst on the loop: tracking is lost in the middle, a new map segment starts, and
        // the loop's return over its start merges it into the first.
        "burstloop" => SimConfig { burst: Some(duv_sim::Burst { start_s: 15.0, duration_s: 4.0, factor: 8.0 }), ..SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Loop) },
        // Fast turns over nearly featureless sand: the survey's lanes 1 m apart (turns of
        // 0.5 m radius, about 6 degrees a frame) over sand at a twentieth of its texture
        // contrast (the relief's shading stays; at 320x240 ATE 0.20 % at a tenth, 6.5 % at none).
        "sandturn" => SimConfig { seabed_texture: 0.05, lane_spacing_m: 1.0, ..survey() },
        // A low frame rate: 2 frames/s, 25 cm of travel between frames.
        "lowfps" => SimConfig { fps: 2.0, frames: 150, ..survey() },
        other => anyhow::bail!("unknown sequence {other:?} (expected survey, loop, turbid, night, snow, burst, burstloop, sandturn or lowfps)"),
    })
}

fn percentile_ms(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

pub(super) fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| !x.is_nan());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Field-wise median of several runs.
fn median_metrics(runs: &[RunMetrics]) -> RunMetrics {
    let m = |f: fn(&RunMetrics) -> f64| median(runs.iter().map(f).collect());
    let mu = |f: fn(&RunMetrics) -> u64| median(runs.iter().map(|r| f(r) as f64).collect()).round() as u64;
    RunMetrics {
        fps: m(|r| r.fps),
        cpu_ms_per_frame: m(|r| r.cpu_ms_per_frame),
        flow_ms: m(|r| r.flow_ms),
        ba_ms: m(|r| r.ba_ms),
        covariance_ms: m(|r| r.covariance_ms),
        loop_closure_ms: m(|r| r.loop_closure_ms),
        global_ba_ms: m(|r| r.global_ba_ms),
        latency_p50_ms: m(|r| r.latency_p50_ms),
        latency_p99_ms: m(|r| r.latency_p99_ms),
        latency_max_ms: m(|r| r.latency_max_ms),
        init_frames: mu(|r| r.init_frames),
        fps_tracking: m(|r| r.fps_tracking),
        latency_p99_tracking_ms: m(|r| r.latency_p99_tracking_ms),
        latency_max_tracking_ms: m(|r| r.latency_max_tracking_ms),
        frames_with_pose: mu(|r| r.frames_with_pose),
        frames_measured: mu(|r| r.frames_measured),
        init_restarts: mu(|r| r.init_restarts),
        segments_started: mu(|r| r.segments_started),
        segments_final: mu(|r| r.segments_final),
        ate_rmse_m: m(|r| r.ate_rmse_m),
        ate_percent_of_path: m(|r| r.ate_percent_of_path),
        path_m: m(|r| r.path_m),
        keyframes_inserted: mu(|r| r.keyframes_inserted),
        loops_closed: mu(|r| r.loops_closed),
        lost_frames: mu(|r| r.lost_frames),
        ause: m(|r| r.ause),
        ause_random: m(|r| r.ause_random),
        ause_depth: m(|r| r.ause_depth),
        ause_depth_random: m(|r| r.ause_depth_random),
        rss_peak_mib: m(|r| r.rss_peak_mib),
        tracker_heap_peak_mib: m(|r| r.tracker_heap_peak_mib),
    }
}

/// Resets the kernel's peak-RSS mark of this process (Linux >= 4.0); false where it cannot.
fn reset_rss_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// VmHWM of this process in MiB (NaN where /proc is not there).
fn rss_peak_mib() -> f64 {
    proc_status_mib("VmHWM:")
}

/// A `kB` field of `/proc/self/status` (`VmRSS:`, `VmHWM:`) in MiB; NaN where /proc is not there.
pub(super) fn proc_status_mib(field: &str) -> f64 {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else { return f64::NAN };
    status
        .lines()
        .find_map(|l| l.strip_prefix(field))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// CPU time of every thread of this process so far, ns (`/proc/self/task/*/schedstat`; NaN
/// where that is not there). Threads that ended before the call are not counted.
fn process_cpu_ns() -> f64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else { return f64::NAN };
    let mut sum = 0.0;
    for entry in dir.flatten() {
        if let Ok(text) = std::fs::read_to_string(entry.path().join("schedstat")) {
            sum += text.split_whitespace().next().and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        }
    }
    sum
}

const MIB: f64 = 1024.0 * 1024.0;

struct Sequence {
    renderer: SimRenderer,
    frames: Vec<Frame>,
    /// True depth of frames that became keyframes, rendered on demand.
    depth: HashMap<u64, PlaneF32>,
}

fn generate(name: &str, width: usize, height: usize, frames: Option<usize>, seed: u64) -> anyhow::Result<Sequence> {
    let mut cfg = sequence_config(name)?;
    cfg.width = width;
    cfg.height = height;
    cfg.seed = seed;
    if let Some(n) = frames {
        cfg.frames = n;
    }
    let renderer = SimRenderer::new(&cfg).with_context(|| format!("sequence {name} {width}x{height}"))?;
    let frames = render_frames(&renderer);
    Ok(Sequence { renderer, frames, depth: HashMap::new() })
}

/// Every frame of a generated sequence as the tracker takes it, rendered in parallel.
pub(super) fn render_frames(renderer: &SimRenderer) -> Vec<Frame> {
    (0..renderer.len())
        .into_par_iter()
        .map(|i| {
            let f = renderer.render(i);
            Frame { t_ns: f.t_ns, seq: i as u64, image: FrameImage::Rgb8(f.rgb) }
        })
        .collect()
}

/// Tracks the sequence once and scores it.
fn run_once(seq: &mut Sequence, cfg: &TrackerConfig, cap: TrackerCapacity, with_ause: bool, rss_reset: bool) -> anyhow::Result<RunMetrics> {
    let n = seq.frames.len();
    if rss_reset {
        reset_rss_peak();
    }
    duv_core::alloc::reset_peak_bytes();
    let live0 = duv_core::alloc::live_bytes();
    let mut tracker = Tracker::new(seq.renderer.camera(), cfg, cap)?;
    let mut recorder = TrajectoryRecorder::new();
    let mut latencies: Vec<Duration> = Vec::with_capacity(n);
    let frames = &seq.frames;
    let cpu0 = process_cpu_ns();
    // Index of the first tracked frame and the wall time from its start to the end.
    let mut init_frames = None;
    let (wall, wall_tracking) = tracker.run_in_pool(|t| -> anyhow::Result<(Duration, Duration)> {
        let start = Instant::now();
        let mut start_tracking = None;
        for (i, f) in frames.iter().enumerate() {
            let t0 = Instant::now();
            let out = t.track(f)?;
            latencies.push(t0.elapsed());
            if init_frames.is_none() && out.state == TrackingState::Tracking {
                init_frames = Some(i);
                start_tracking = Some(Instant::now());
            }
            recorder.record(&out);
        }
        Ok((start.elapsed(), start_tracking.map_or(Duration::ZERO, |s| s.elapsed())))
    })?;
    let init_frames = init_frames.unwrap_or(n);
    // The first tracked frame is the one that ran the initial BA: the steady state starts after it.
    let mut steady: Vec<Duration> = latencies.get(init_frames + 1..).unwrap_or(&[]).to_vec();
    steady.sort();
    let cpu_ns = process_cpu_ns() - cpu0;
    let heap_peak = duv_core::alloc::peak_bytes().saturating_sub(live0) as f64 / MIB;
    let rss = rss_peak_mib();
    let fin = recorder.finish(&mut tracker);
    let gt = &seq.renderer.poses()[..n];
    // Scored on the frames with a pose estimate only, each map segment on its own (their
    // frames and scales differ until merged).
    let estimated: Vec<duv_core::StampedPose> = fin.estimated();
    let frames_measured = fin.sources.iter().filter(|s| **s == PoseSource::Measured).count() as u64;
    let segment_counts = fin.segment_counts();
    let (mut sq_sum, mut scored, mut path_sum) = (0.0f64, 0usize, 0.0f64);
    // The largest segment's report (its alignment scales the AUSE below).
    let mut ev = None;
    for &(segment, count) in segment_counts.iter().filter(|(_, c)| *c >= 3) {
        let e = evaluate_trajectory(gt, &fin.estimated_in(segment), &TrajectoryOptions::default(), "gt", "est").with_context(|| format!("scoring map segment {segment}"))?;
        sq_sum += e.report.ate.stats_m.rmse.powi(2) * count as f64;
        scored += count;
        path_sum += e.report.gt_path_length_m;
        if segment_counts.iter().all(|&(_, c)| c <= count) && ev.is_none() {
            ev = Some((segment, e));
        }
    }
    let largest = ev.as_ref().map(|(s, _)| *s);
    let report = ev.as_ref().map(|(_, e)| &e.report);
    let ate_rmse_all = if scored > 0 { (sq_sum / scored as f64).sqrt() } else { f64::NAN };
    let (mut ause_mean, mut ause_random) = (f64::NAN, f64::NAN);
    let (mut ause_depth_mean, mut ause_depth_random) = (f64::NAN, f64::NAN);
    if let (true, Some(report)) = (with_ause, report) {
        let scale = report.alignment.scale;
        let kfs: Vec<(u64, u64)> = tracker.keyframes().filter(|k| k.variance.is_some() && Some(k.segment) == largest).map(|k| (k.id, k.seq)).collect();
        let missing: Vec<u64> = kfs.iter().map(|k| k.1).filter(|s| !seq.depth.contains_key(s)).collect();
        let renderer = &seq.renderer;
        let rendered: Vec<(u64, PlaneF32)> = missing.par_iter().map(|&s| (s, renderer.render(s as usize).depth_m)).collect();
        seq.depth.extend(rendered);
        let cam = seq.renderer.camera();
        let mut inv = PlaneF32::new(cam.width, cam.height);
        let mut var = PlaneF32::new(cam.width, cam.height);
        // (sum of AUSE, sum of random AUSE, keyframes) for inverse depth and for depth.
        let (mut inverse_sums, mut depth_sums) = ((0.0, 0.0, 0usize), (0.0, 0.0, 0usize));
        let add = |sums: &mut (f64, f64, usize), errors: &[f64], unc: &[f64]| -> anyhow::Result<()> {
            if errors.len() >= 100 {
                let r = ause(errors, unc, &AuseOptions::default())?;
                *sums = (sums.0 + r.ause, sums.1 + r.ause_random, sums.2 + 1);
            }
            Ok(())
        };
        for &(id, s) in &kfs {
            tracker.upsample_keyframe(id, &mut inv, &mut var)?;
            let depth = &seq.depth[&s];
            let (mut errors, mut unc, mut errors_m, mut unc_m) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for ((&z, &d), &v) in depth.data.iter().zip(&inv.data).zip(&var.data) {
                if z > 0.0 && d.is_finite() && v.is_finite() && v < f32::MAX {
                    let (rho, var_rho) = (d as f64 / scale, v as f64 / (scale * scale));
                    errors.push((1.0 / z as f64 - rho).abs());
                    unc.push(var_rho);
                    let var_m = var_rho / rho.powi(4);
                    if rho > 0.0 && var_m.is_finite() && var_m > 0.0 {
                        errors_m.push((z as f64 - 1.0 / rho).abs());
                        unc_m.push(var_m);
                    }
                }
            }
            add(&mut inverse_sums, &errors, &unc)?;
            add(&mut depth_sums, &errors_m, &unc_m)?;
        }
        let mean = |s: (f64, f64, usize)| if s.2 > 0 { (s.0 / s.2 as f64, s.1 / s.2 as f64) } else { (f64::NAN, f64::NAN) };
        (ause_mean, ause_random) = mean(inverse_sums);
        (ause_depth_mean, ause_depth_random) = mean(depth_sums);
    }
    let times = tracker.times();
    let counters = tracker.counters();
    let per_frame = |d: Duration| d.as_secs_f64() * 1e3 / n as f64;
    latencies.sort();
    Ok(RunMetrics {
        fps: n as f64 / wall.as_secs_f64().max(1e-9),
        cpu_ms_per_frame: cpu_ns / 1e6 / n as f64,
        flow_ms: per_frame(times.flow),
        ba_ms: per_frame(times.ba),
        covariance_ms: per_frame(times.covariance),
        loop_closure_ms: per_frame(times.loop_closure),
        global_ba_ms: per_frame(times.global_ba),
        latency_p50_ms: percentile_ms(&latencies, 0.5),
        latency_p99_ms: percentile_ms(&latencies, 0.99),
        latency_max_ms: percentile_ms(&latencies, 1.0),
        init_frames: init_frames as u64,
        fps_tracking: steady.len() as f64 / wall_tracking.as_secs_f64().max(1e-9),
        latency_p99_tracking_ms: percentile_ms(&steady, 0.99),
        latency_max_tracking_ms: percentile_ms(&steady, 1.0),
        frames_with_pose: estimated.len() as u64,
        frames_measured,
        init_restarts: counters.init_restarts,
        segments_started: 1 + counters.segments_started,
        segments_final: segment_counts.len() as u64,
        ate_rmse_m: ate_rmse_all,
        ate_percent_of_path: if path_sum > 0.0 { 100.0 * ate_rmse_all / path_sum } else { f64::NAN },
        path_m: if scored > 0 { path_sum } else { f64::NAN },
        keyframes_inserted: counters.keyframes_inserted,
        loops_closed: counters.loops_closed,
        lost_frames: counters.lost_frames,
        ause: ause_mean,
        ause_random,
        ause_depth: ause_depth_mean,
        ause_depth_random,
        rss_peak_mib: rss,
        tracker_heap_peak_mib: if duv_core::alloc::is_installed() { heap_peak } else { f64::NAN },
    })
}

fn markdown(report: &BenchReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# duv bench track\n\n`{}`\n", report.command);
    let _ = writeln!(
        s,
        "Board `{}`, {} tracking threads, {} CPUs visible. Medians of {} run(s) per row; per-stage times are ms per frame (mean over the run); AUSE is the mean over the final keyframes (full resolution), random = the same errors in random order. RSS includes the in-memory frames ({}).\n",
        report.board,
        report.threads,
        report.cpus,
        report.cases.first().map_or(0, |c| c.runs),
        if report.rss_reset_per_run { "peak reset before each run" } else { "peak since process start" }
    );
    let _ = writeln!(s, "| sequence | size | frames | loops | FPS | CPU ms/frame | flow | BA | cov | loop | global BA | p50 ms | p99 ms | max ms | init frames | restarts | frames with pose | measured | segments started | segments at end | FPS after init | p99 ms after init | max ms after init | ATE m | ATE % path | path m | KFs | loops closed | lost | AUSE | AUSE random | AUSE of depth | AUSE of depth, random | RSS MiB | frames MiB | tracker heap MiB |");
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for c in &report.cases {
        let m = &c.median;
        let _ = writeln!(
            s,
            "| {} | {}x{} | {} | {} | {:.1} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.1} | {:.1} | {:.1} | {} | {} | {} | {} | {} | {} | {:.1} | {:.1} | {:.1} | {:.4} | {:.3} | {:.1} | {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.0} | {:.0} | {:.1} |",
            c.sequence,
            c.width,
            c.height,
            c.frames,
            if c.loop_closure { "on" } else { "off" },
            m.fps,
            m.cpu_ms_per_frame,
            m.flow_ms,
            m.ba_ms,
            m.covariance_ms,
            m.loop_closure_ms,
            m.global_ba_ms,
            m.latency_p50_ms,
            m.latency_p99_ms,
            m.latency_max_ms,
            m.init_frames,
            m.init_restarts,
            m.frames_with_pose,
            m.frames_measured,
            m.segments_started,
            m.segments_final,
            m.fps_tracking,
            m.latency_p99_tracking_ms,
            m.latency_max_tracking_ms,
            m.ate_rmse_m,
            m.ate_percent_of_path,
            m.path_m,
            m.keyframes_inserted,
            m.loops_closed,
            m.lost_frames,
            m.ause,
            m.ause_random,
            m.ause_depth,
            m.ause_depth_random,
            m.rss_peak_mib,
            c.frames_mib,
            m.tracker_heap_peak_mib
        );
    }
    s
}

pub fn run(args: BenchTrackArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.runs >= 1, "--runs must be at least 1");
    let loop_settings: Vec<bool> = match args.loop_closure.as_str() {
        "both" => vec![true, false],
        "on" => vec![true],
        "off" => vec![false],
        other => anyhow::bail!("--loop-closure {other:?}: expected both, on or off"),
    };
    let board = super::load_board(&args.board)?;
    let cap = TrackerCapacity::from_board(&board);
    let base_cfg = match &args.config {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            toml::from_str::<TrackerConfig>(&text).with_context(|| format!("{}", p.display()))?
        }
        None => TrackerConfig::default(),
    };
    let sizes = args.sizes.iter().map(|s| parse_size(s)).collect::<anyhow::Result<Vec<_>>>()?;
    for name in &args.sequences {
        sequence_config(name)?;
    }
    let rss_reset = reset_rss_peak();
    let mut cases = Vec::new();
    for name in &args.sequences {
        for &(w, h) in &sizes {
            let t0 = Instant::now();
            let mut seq = generate(name, w, h, args.frames, args.seed)?;
            let frames_mib = seq.frames.iter().map(|f| (f.image.width() * f.image.height() * 3) as f64).sum::<f64>() / MIB;
            eprintln!("bench track: {name} {w}x{h}: {} frames generated in {:.1} s", seq.frames.len(), t0.elapsed().as_secs_f64());
            for &lc in &loop_settings {
                let mut cfg = base_cfg.clone();
                cfg.loop_closure = lc;
                let mut all = Vec::with_capacity(args.runs);
                for r in 0..args.runs {
                    let m = run_once(&mut seq, &cfg, cap, !args.no_ause, rss_reset).with_context(|| format!("{name} {w}x{h} run {}", r + 1))?;
                    eprintln!(
                        "  loop closure {}: run {}/{}: {:.1} fps ({:.1} CPU ms/frame), p99 {:.1} ms; after init ({} frames): {:.1} fps, p99 {:.1} ms, max {:.1} ms; {} of {} frames with a pose ({} measured, {} init restarts, {} segments started, {} at the end), ATE {:.3}% of path over them, loops {}, AUSE {:.3} (random {:.3}), of depth {:.3} (random {:.3})",
                        if lc { "on" } else { "off" },
                        r + 1,
                        args.runs,
                        m.fps,
                        m.cpu_ms_per_frame,
                        m.latency_p99_ms,
                        m.init_frames,
                        m.fps_tracking,
                        m.latency_p99_tracking_ms,
                        m.latency_max_tracking_ms,
                        m.frames_with_pose,
                        seq.frames.len(),
                        m.frames_measured,
                        m.init_restarts,
                        m.segments_started,
                        m.segments_final,
                        m.ate_percent_of_path,
                        m.loops_closed,
                        m.ause,
                        m.ause_random,
                        m.ause_depth,
                        m.ause_depth_random
                    );
                    all.push(m);
                }
                cases.push(CaseResult {
                    sequence: name.clone(),
                    width: w,
                    height: h,
                    frames: seq.frames.len(),
                    loop_closure: lc,
                    runs: args.runs,
                    frames_mib,
                    median: median_metrics(&all),
                    all,
                });
            }
        }
    }
    let report = BenchReport {
        command: std::env::args().collect::<Vec<_>>().join(" "),
        board: args.board.display().to_string(),
        threads: cap.threads,
        cpus: std::thread::available_parallelism().map_or(0, |n| n.get()),
        rss_reset_per_run: rss_reset,
        cases,
    };
    let md = markdown(&report);
    print!("{md}");
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let json = serde_json::to_string_pretty(&report)?;
    duv_core::io::write_atomic(&args.out.join("bench_track.json"), json.as_bytes())?;
    duv_core::io::write_atomic(&args.out.join("bench_track.md"), md.as_bytes())?;
    eprintln!("wrote {} and bench_track.md", args.out.join("bench_track.json").display());
    Ok(())
}
