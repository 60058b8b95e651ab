//! PLACEHOLDER: replaced by the owner of this subcommand.
#[derive(clap::Args)]
pub struct EvalArgs {}
pub fn run(_: EvalArgs) -> anyhow::Result<()> { anyhow::bail!("duv eval is being built") }
