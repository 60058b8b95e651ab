//! PLACEHOLDER: replaced by the owner of this subcommand.
#[derive(clap::Args)]
pub struct DatasetArgs {}
pub fn run(_: DatasetArgs) -> anyhow::Result<()> { anyhow::bail!("duv dataset is being built") }
