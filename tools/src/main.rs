//! `duv-tools`: offline jobs around duv-slam (dataset conversion).

mod convert;

use clap::{Parser, Subcommand};

/// Offline tools for duv-slam.
#[derive(Parser)]
#[command(name = "duv-tools", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Convert any readable dataset (tum, euroc, tartanair, folder) to our TUM layout.
    Convert(convert::ConvertArgs),
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Convert(a) => convert::run(a),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
