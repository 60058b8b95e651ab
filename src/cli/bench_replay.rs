//! `duv bench replay`: the soak test of the onboard runtime. A recorded log is replayed in a
//! loop through the whole pipeline (capture, tracking, mapping, logging threads) at recorded
//! timing for a fixed wall-clock time while this process's resident set is sampled once a
//! second; the growth of the RSS after warm-up is the figure (target <= 2 % over 10 minutes).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;

use super::bench_track::{median, proc_status_mib};
use super::run::RunArgs;

#[derive(clap::Args)]
pub struct BenchReplayArgs {
    /// The recorded log (a run folder, its `log/` or one `.mcap`). Without it a `sim:coastal`
    /// dive of `--record-frames` frames is recorded first (into `OUT/recorded`).
    #[arg(long, value_name = "LOG")]
    log: Option<PathBuf>,
    /// Frames of the dive recorded when no `--log` is given.
    #[arg(long, default_value_t = 300)]
    record_frames: usize,
    /// Wall-clock length of the replay loop, minutes.
    #[arg(long, default_value_t = 10.0)]
    minutes: f64,
    /// Samples before this many seconds are warm-up, not counted in the growth.
    #[arg(long, default_value_t = 60.0)]
    warm_up_s: f64,
    /// Replay speed relative to the recorded timing.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Track only (no mapping thread work).
    #[arg(long)]
    no_map: bool,
    /// Board profile.
    #[arg(long, default_value = "boards/sim.toml")]
    board: PathBuf,
    /// Output folder: `rss.csv`, `bench_replay.json`, `bench_replay.md`, the replayed run.
    #[arg(long, default_value = "out/bench-replay")]
    out: PathBuf,
}

/// The soak figures.
#[derive(Debug, serde::Serialize)]
struct ReplayReport {
    log: String,
    board: String,
    speed: f64,
    mapping: bool,
    /// The whole command (loop, final mapping, exports) and the loop alone.
    wall_s: f64,
    loop_s: f64,
    samples: usize,
    warm_up_s: f64,
    /// Median RSS over the first minute after warm-up, MiB.
    rss_start_mib: f64,
    /// Median RSS over the last minute, MiB.
    rss_end_mib: f64,
    rss_growth_percent: f64,
    rss_max_mib: f64,
    /// Peak RSS of the process (VmHWM), MiB.
    rss_peak_mib: f64,
    /// Live heap bytes (the counting allocator), the same windows, MiB.
    heap_start_mib: f64,
    heap_end_mib: f64,
    heap_growth_percent: f64,
}

/// Median of the samples with `t` in `[from, to)`.
fn window_median(samples: &[(f64, f64)], from: f64, to: f64) -> f64 {
    median(samples.iter().filter(|(t, _)| *t >= from && *t < to).map(|s| s.1).collect())
}

/// RSS growth from the first minute after warm-up to the last minute: (start, end, percent).
fn growth(samples: &[(f64, f64)], warm_up_s: f64) -> (f64, f64, f64) {
    let end_t = samples.last().map_or(0.0, |s| s.0);
    let window = 60.0f64.min((end_t - warm_up_s) / 2.0).max(1.0);
    let start = window_median(samples, warm_up_s, warm_up_s + window);
    let end = window_median(samples, end_t - window, end_t + 1.0);
    (start, end, 100.0 * (end - start) / start)
}

pub fn run(args: BenchReplayArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.minutes.is_finite() && args.minutes > 0.0, "--minutes must be > 0, got {}", args.minutes);
    anyhow::ensure!(args.warm_up_s >= 0.0 && args.warm_up_s < args.minutes * 60.0, "--warm-up-s must be in [0, minutes * 60)");
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    // As `duv run` on the vehicle: large stores paged in when made.
    duv_core::alloc::prefault_large_allocations(true);
    let log = match &args.log {
        Some(l) => l.clone(),
        None => {
            let rec = args.out.join("recorded");
            if rec.join("log").exists() {
                eprintln!("bench replay: reusing the recorded dive in {}", rec.display());
            } else {
                let mut r = RunArgs::with_defaults("sim:coastal".into(), rec.clone(), true);
                r.board = args.board.clone();
                r.frames = Some(args.record_frames);
                r.no_resume = true;
                super::run::run(r).context("recording the dive to replay")?;
            }
            rec
        }
    };
    let replayed = args.out.join("replayed");
    if replayed.exists() {
        std::fs::remove_dir_all(&replayed).with_context(|| format!("clearing {}", replayed.display()))?;
    }
    let mut r = RunArgs::with_defaults(format!("mcap:{}", log.display()), replayed, true);
    r.board = args.board.clone();
    r.speed = Some(args.speed);
    r.no_resume = true;
    r.no_map = args.no_map;
    r.loop_for_s = Some(args.minutes * 60.0);

    // RSS once a second from a thread of this process.
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = {
        let stop = stop.clone();
        std::thread::Builder::new().name("rss-sampler".into()).spawn(move || {
            let t0 = Instant::now();
            let mut samples: Vec<(f64, f64, f64)> = Vec::with_capacity(4096);
            while !stop.load(Ordering::Relaxed) {
                let heap_mib = duv_core::alloc::live_bytes() as f64 / (1u64 << 20) as f64;
                samples.push((t0.elapsed().as_secs_f64(), proc_status_mib("VmRSS:"), heap_mib));
                let next = Duration::from_secs(samples.len() as u64);
                while !stop.load(Ordering::Relaxed) && t0.elapsed() < next {
                    std::thread::sleep(Duration::from_millis(50));
                }
            }
            samples
        })?
    };
    let started = Instant::now();
    let outcome = super::run::run(r);
    let wall_s = started.elapsed().as_secs_f64();
    stop.store(true, Ordering::Relaxed);
    let samples = sampler.join().map_err(|_| anyhow::anyhow!("the RSS sampler panicked"))?;
    outcome.context("the replay loop")?;

    let mut csv = String::from("t_s,rss_mib,heap_live_mib\n");
    for (t, m, h) in &samples {
        csv.push_str(&format!("{t:.3},{m:.3},{h:.3}\n"));
    }
    std::fs::write(args.out.join("rss.csv"), csv)?;
    anyhow::ensure!(samples.iter().all(|s| s.1.is_finite()), "no /proc/self/status here: RSS cannot be sampled");
    // The loop's own samples: after it the run maps its final iterations and exports.
    let loop_s = args.minutes * 60.0;
    let in_loop: Vec<(f64, f64)> = samples.iter().filter(|s| s.0 <= loop_s).map(|s| (s.0, s.1)).collect();
    let heap: Vec<(f64, f64)> = samples.iter().filter(|s| s.0 <= loop_s).map(|s| (s.0, s.2)).collect();
    let (rss_start_mib, rss_end_mib, rss_growth_percent) = growth(&in_loop, args.warm_up_s);
    let (heap_start_mib, heap_end_mib, heap_growth_percent) =
        if duv_core::alloc::is_installed() { growth(&heap, args.warm_up_s) } else { (f64::NAN, f64::NAN, f64::NAN) };
    let report = ReplayReport {
        log: log.display().to_string(),
        board: args.board.display().to_string(),
        speed: args.speed,
        mapping: !args.no_map,
        wall_s,
        loop_s,
        samples: in_loop.len(),
        warm_up_s: args.warm_up_s,
        rss_start_mib,
        rss_end_mib,
        rss_growth_percent,
        rss_max_mib: in_loop.iter().map(|s| s.1).fold(f64::NAN, f64::max),
        rss_peak_mib: proc_status_mib("VmHWM:"),
        heap_start_mib,
        heap_end_mib,
        heap_growth_percent,
    };
    let md = format!(
        "| loop s | samples | RSS after warm-up (MiB) | RSS at the end (MiB) | RSS growth | max RSS (MiB) | live heap after warm-up / at the end (MiB) | heap growth |\n|---|---|---|---|---|---|---|---|\n| {:.0} | {} | {:.1} | {:.1} | {:+.2} % | {:.1} | {:.1} / {:.1} | {:+.2} % |\n",
        report.loop_s,
        report.samples,
        report.rss_start_mib,
        report.rss_end_mib,
        report.rss_growth_percent,
        report.rss_max_mib,
        report.heap_start_mib,
        report.heap_end_mib,
        report.heap_growth_percent
    );
    std::fs::write(args.out.join("bench_replay.json"), serde_json::to_string_pretty(&report)?)?;
    std::fs::write(args.out.join("bench_replay.md"), &md)?;
    print!("{md}");
    println!("wrote {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growth_compares_the_first_minute_after_warm_up_with_the_last() {
        // A slow leak: 100 + 0.01 MiB per second over 600 s, one sample a second.
        let samples: Vec<(f64, f64)> = (0..600).map(|t| (t as f64, 100.0 + 0.01 * t as f64)).collect();
        let (start, end, pct) = growth(&samples, 60.0);
        // Medians over t = 60..119 s (89.5 s: 100.895) and the last minute, 539..599 s (569 s).
        assert!((start - 100.895).abs() < 1e-9, "{start}");
        assert!((end - 105.69).abs() < 1e-9, "{end}");
        assert!((pct - 100.0 * (end - start) / start).abs() < 1e-12);
        assert!(pct > 4.0 && pct < 5.0, "{pct}");
        // A warm-up spike does not count.
        let mut spiky = samples.clone();
        for s in spiky.iter_mut().take(30) {
            s.1 = 500.0;
        }
        assert_eq!(growth(&spiky, 60.0), (start, end, pct));
    }
}
