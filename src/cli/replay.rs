//! `duv replay LOG`: recorded frames through the same pipeline, at recorded timing, `--speed X`
//! faster, or `--deterministic` (single-threaded, bit-identical output).

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
}

pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.speed.is_finite() && args.speed > 0.0, "--speed must be > 0, got {}", args.speed);
    let mut run = super::run::RunArgs::with_defaults(format!("mcap:{}", args.path.display()), args.out, args.no_progress);
    run.board = args.board;
    run.frames = args.frames;
    run.deterministic = args.deterministic;
    run.speed = if args.deterministic { None } else { Some(args.speed) };
    run.no_resume = true;
    super::run::run(run)
}
