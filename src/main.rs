//! `duv`: the duv-slam command line. Thin: parse, set up logging, dispatch to `cli/`.

mod cli;

use clap::{Parser, Subcommand};

/// Counts allocations and live/peak heap bytes: the host-memory budget in the health
/// telemetry, and the peak `duv bench` reports.
#[global_allocator]
static GLOBAL: duv_core::alloc::CountingAllocator = duv_core::alloc::CountingAllocator;

/// Dense underwater visual SLAM: monocular tracking with depth uncertainty and a
/// Gaussian-splat map of the seabed with the water modelled.
#[derive(Parser)]
#[command(name = "duv", version, about, long_about = None, propagate_version = true)]
struct Cli {
    /// Log filter (tracing `EnvFilter` syntax), e.g. `info`, `duv=debug`. Overrides RUST_LOG.
    #[arg(long, global = true)]
    log: Option<String>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate a short underwater sequence, run the pipeline on it, print the metrics table.
    Demo(cli::demo::DemoArgs),
    /// Track a dataset or a generated sequence: trajectory, keyframe depth and variance, map and map report, eval report.
    Run(cli::run::RunArgs),
    /// Generate an underwater sequence with exact ground truth (TUM RGB-D layout).
    Sim(cli::sim::SimArgs),
    /// Evaluate a trajectory / run against ground truth: ATE, RPE, PSNR, SSIM, AUSE, figures.
    Eval(cli::eval::EvalArgs),
    /// Export a run's keyframes, poses and map for offline splatting: COLMAP text model, nerfstudio transforms.json.
    Export(cli::export::ExportArgs),
    /// Refine a Gaussian map and the water offline from a keyframe folder, a run's MCAP log or generated keyframes.
    Refine(cli::refine::RefineArgs),
    /// Check board profiles and print the capacities they give.
    Board(cli::board::BoardArgs),
    /// Summarise an MCAP log: topics, counts, bytes and MB/s against the log budget, time span, gaps, recovered segments.
    Inspect(cli::inspect::InspectArgs),
    /// Replay a recorded MCAP log through the pipeline (recorded timing, --speed, --deterministic).
    Replay(cli::replay::ReplayArgs),
    /// Summarise a dataset folder through the readers (frames, rate, calibration, ground truth).
    Dataset(cli::dataset::DatasetArgs),
    /// Benchmark a stage on generated data: `duv bench track` (FPS, latency, ATE, AUSE, memory),
    /// `duv bench map` (PSNR/SSIM, recovered medium, ablation, ms per iteration), `duv bench
    /// replay` (soak: a log replayed in a loop, host RSS growth).
    Bench(cli::bench::BenchArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let filter = cli
        .log
        .clone()
        .or_else(|| std::env::var("RUST_LOG").ok())
        .unwrap_or_else(|| "info".to_string());
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_new(&filter).unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")))
        .with_writer(std::io::stderr)
        // Colour only on a terminal: a log redirected to a file stays plain text.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
    // The onboard commands page their fixed stores in when they are made (see
    // `prefault_large_allocations`): resident memory is flat from start-up.
    if matches!(cli.command, Command::Run(_) | Command::Replay(_) | Command::Demo(_)) {
        duv_core::alloc::prefault_large_allocations(true);
    }
    let result = match cli.command {
        Command::Demo(a) => cli::demo::run(a),
        Command::Run(a) => cli::run::run(a),
        Command::Sim(a) => cli::sim::run(a),
        Command::Eval(a) => cli::eval::run(a),
        Command::Export(a) => cli::export::run(a),
        Command::Refine(a) => cli::refine::run(a),
        Command::Board(a) => cli::board::run(a),
        Command::Dataset(a) => cli::dataset::run(a),
        Command::Inspect(a) => cli::inspect::run(a),
        Command::Replay(a) => cli::replay::run(a),
        Command::Bench(a) => cli::bench::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) if e.is::<cli::Exit>() => {
            let exit = e.downcast::<cli::Exit>().expect("checked");
            eprintln!("{}", exit.why);
            std::process::ExitCode::from(exit.code)
        }
        Err(e) => {
            eprintln!("error: {}", cli::error_line(&e));
            std::process::ExitCode::FAILURE
        }
    }
}
