//! Configuration as data: board profiles (`boards/*.toml`). Strict parsing: a schema version,
//! unknown keys rejected, every budget checked, errors that name the file and the key.

pub mod board;

pub use board::{Board, BoardError};
