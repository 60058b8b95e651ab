//! PLACEHOLDER: replaced by the owner of this subcommand.
#[derive(clap::Args)]
pub struct DemoArgs {}
pub fn run(_: DemoArgs) -> anyhow::Result<()> { anyhow::bail!("duv demo is being built") }
