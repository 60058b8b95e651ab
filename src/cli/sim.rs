//! PLACEHOLDER: replaced by the owner of this subcommand.
#[derive(clap::Args)]
pub struct SimArgs {}
pub fn run(_: SimArgs) -> anyhow::Result<()> { anyhow::bail!("duv sim is being built") }
