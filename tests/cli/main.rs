//! The `duv` command line end to end in one binary (one link): every subcommand run as a process.


mod cli;
mod cli_bench;
mod cli_export;
mod cli_metric;
mod cli_run;
mod eval_cli;
#[path = "../common/python.rs"]
mod python;
