//! `duv replay LOG`: recorded frames through the same pipeline as `duv run` (tracking, mapping
//! and logging), at recorded timing, `--speed X` faster, or `--deterministic` (single-threaded,
//! the Vulkan mapper without float atomics: bit-identical trajectory and map on one device).

use duv_map::backend::MapperDevice;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct ReplayArgs {
    /// A log folder (`RUN/log` or `RUN`) or one `.mcap` file.
    #[arg(value_name = "LOG")]
    path: PathBuf,
    /// Output folder of the replayed run (log, trajectory, keyframes).
    #[arg(long)]
    out: PathBuf,
    /// Board profile.
    #[arg(long, default_value = "boards/sim.toml")]
    board: PathBuf,
    /// Replay speed relative to the recorded timing (2 = twice as fast).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// As fast as possible, single-threaded, no drops: bit-identical output for the same log.
    #[arg(long)]
    deterministic: bool,
    /// Replay at most this many frames.
    #[arg(long)]
    frames: Option<usize>,
    /// No progress line on stderr.
    #[arg(long)]
    no_progress: bool,
    /// Track only, as `duv run --no-map`.
    #[arg(long)]
    no_map: bool,
    /// Where the mapper renders, as `duv run --mapper`.
    #[arg(long, value_enum, default_value_t = MapperDevice::Auto)]
    mapper: MapperDevice,
    /// Mapper iterations per keyframe, as `duv run --map-iterations` [default: duv run's].
    #[arg(long)]
    map_iterations: Option<u64>,
    /// Mapper iterations after the last frame, as `duv run --map-final-iterations` [default: duv run's].
    #[arg(long)]
    map_final_iterations: Option<u64>,
}

pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.speed.is_finite() && args.speed >= 1e-3, "--speed must be a finite factor >= 0.001, got {}", args.speed);
    let mut run = super::run::RunArgs::with_defaults(format!("mcap:{}", args.path.display()), args.out, args.no_progress);
    run.board = args.board;
    run.frames = args.frames;
    run.deterministic = args.deterministic;
    run.speed = if args.deterministic { None } else { Some(args.speed) };
    run.no_resume = true;
    run.no_map = args.no_map;
    run.mapper = args.mapper;
    if let Some(n) = args.map_iterations {
        run.map_iterations = n;
    }
    if let Some(n) = args.map_final_iterations {
        run.map_final_iterations = n;
    }
    super::run::run(run)
}
