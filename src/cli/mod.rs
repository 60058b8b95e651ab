//! Subcommand implementations of the `duv` binary (`anyhow` lives here and in `main`).

pub mod bench;
pub mod bench_map;
pub mod bench_replay;
pub mod bench_track;
pub mod board;
pub mod dataset;
pub mod demo;
pub mod eval;
pub mod export;
pub mod inspect;
pub mod refine;
pub mod replay;
pub mod run;
pub mod sim;

/// A command that ended early but in order (stopped by a signal after writing its outputs):
/// `main` prints `why` and exits with `code` (130 after SIGINT, 143 after SIGTERM, as a shell
/// reports a process a signal ended).
#[derive(Debug)]
pub struct Exit {
    pub code: u8,
    pub why: String,
}

impl std::fmt::Display for Exit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.why)
    }
}

impl std::error::Error for Exit {}

/// The default `--board`, relative to the working directory.
pub const DEFAULT_BOARD: &str = "boards/sim.toml";
/// The default board as built into the binary, so `duv run` works from any folder.
const BUILT_IN_SIM_BOARD: &str = include_str!("../../boards/sim.toml");

/// Loads `--board PATH`; the default path, when it is not there (a run started outside the
/// repository), is the copy of `boards/sim.toml` built into the binary.
pub fn load_board(path: &std::path::Path) -> anyhow::Result<duv_core::config::board::Board> {
    if path == std::path::Path::new(DEFAULT_BOARD) && !path.exists() {
        tracing::debug!("{DEFAULT_BOARD} not found here: the built-in copy");
        return Ok(duv_core::config::board::Board::parse(std::path::Path::new("<built-in boards/sim.toml>"), BUILT_IN_SIM_BOARD)?);
    }
    Ok(duv_core::config::board::Board::load(path)?)
}

/// The error and its causes as one line, `outer: cause: ...`, leaving out a cause whose text
/// the line already ends with (our error types print their source in their own message, as
/// `path: No such file or directory`, and anyhow's `{:#}` would print it twice).
pub fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if line.ends_with(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

#[cfg(test)]
mod tests {
    use super::error_line;

    #[test]
    fn error_line_prints_each_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file or directory (os error 2)");
        let e = anyhow::Error::new(duv_core::io::IoError::file(std::path::Path::new("boards/x.toml"), io)).context("loading the board");
        assert_eq!(error_line(&e), "loading the board: boards/x.toml: No such file or directory (os error 2)");
        let plain = anyhow::anyhow!("inner").context("outer");
        assert_eq!(error_line(&plain), "outer: inner");
    }
}
