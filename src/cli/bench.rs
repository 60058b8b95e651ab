//! `duv bench STAGE`: benchmarks of whole stages on generated data (medians of several runs;
//! figures that take minutes).

#[derive(clap::Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    stage: BenchStage,
}

#[derive(clap::Subcommand)]
enum BenchStage {
    /// Tracking: FPS, per-stage ms, frame latency, ATE with and without loop closure, AUSE, memory.
    Track(super::bench_track::BenchTrackArgs),
    /// Mapping figures on generated sequences: PSNR/SSIM (keyframes and held-out views), recovered medium, ablation, ms/iteration, Gaussians over time.
    Map(super::bench_map::BenchMapArgs),
    /// Soak test: a recorded log replayed in a loop through the whole pipeline for minutes; host RSS growth after warm-up.
    Replay(super::bench_replay::BenchReplayArgs),
}

pub fn run(args: BenchArgs) -> anyhow::Result<()> {
    match args.stage {
        BenchStage::Track(a) => super::bench_track::run(a),
        BenchStage::Map(m) => super::bench_map::run(m),
        BenchStage::Replay(r) => super::bench_replay::run(r),
    }
}
