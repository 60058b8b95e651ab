//! `duv bench ...`: figures that take minutes, one subcommand per stage.

#[derive(clap::Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    command: BenchCommand,
}

#[derive(clap::Subcommand)]
enum BenchCommand {
    /// Mapping figures on generated sequences: PSNR/SSIM, recovered medium, ablation, ms/iteration, Gaussians over time.
    Map(super::bench_map::BenchMapArgs),
}

pub fn run(a: BenchArgs) -> anyhow::Result<()> {
    match a.command {
        BenchCommand::Map(m) => super::bench_map::run(m),
    }
}
