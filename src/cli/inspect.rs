//! `duv inspect LOG`: topics, counts, bytes and MB/s per topic against the run's log budget, time span, gaps and recovered segments of a log folder
//! (or one `.mcap` file).

use duv_log::{inspect_log, ReadLimits};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct InspectArgs {
    /// A log folder (`RUN/log` or `RUN`) or one segment file.
    #[arg(value_name = "LOG")]
    path: PathBuf,
    /// Largest record the reader buffers, MiB (a damaged file cannot make it allocate more).
    #[arg(long, default_value_t = 64)]
    max_record_mb: usize,
}

pub fn run(args: InspectArgs) -> anyhow::Result<()> {
    let path = if args.path.is_dir() && !args.path.join("segment-000000.mcap").exists() && args.path.join("log").is_dir() { args.path.join("log") } else { args.path.clone() };
    let summary = inspect_log(&path, ReadLimits { max_record_bytes: args.max_record_mb << 20 })?;
    print!("{}", summary.render());
    Ok(())
}
