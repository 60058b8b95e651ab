//! Subcommand implementations of the `duv` binary (`anyhow` lives here and in `main`).

pub mod bench;
pub mod bench_map;
pub mod bench_replay;
pub mod bench_track;
pub mod board;
pub mod dataset;
pub mod demo;
pub mod eval;
pub mod inspect;
pub mod refine;
pub mod replay;
pub mod run;
pub mod sim;
