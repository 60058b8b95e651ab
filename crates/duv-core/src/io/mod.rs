//! File formats shared by the readers, the generator and the evaluator: PNG images (8-bit
//! colour and grey, 16-bit depth), PFM float images, TUM trajectory text files. Every error
//! names the file, and the line where there is one.

pub mod keyframes;
pub mod le;
pub mod pfm;
pub mod png_io;
pub mod tum;

use std::path::{Path, PathBuf};

/// Errors of the `io` module.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    #[error("{path}: {source}")]
    File { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable PNG image: {reason}")]
    BadPng { path: PathBuf, reason: String },
    #[error("{path}: unsupported image format: {what}")]
    UnsupportedImage { path: PathBuf, what: String },
    #[error("{path}: not a readable PFM image: {reason}")]
    BadPfm { path: PathBuf, reason: String },
    #[error("{path}, line {line}: {problem}")]
    Parse { path: PathBuf, line: usize, problem: String },
    #[error("{path}: {problem}")]
    Invalid { path: PathBuf, problem: String },
}

impl IoError {
    pub fn file(path: &Path, source: std::io::Error) -> Self {
        IoError::File { path: path.to_path_buf(), source }
    }
    pub fn parse(path: &Path, line: usize, problem: impl Into<String>) -> Self {
        IoError::Parse { path: path.to_path_buf(), line, problem: problem.into() }
    }
    pub fn invalid(path: &Path, problem: impl Into<String>) -> Self {
        IoError::Invalid { path: path.to_path_buf(), problem: problem.into() }
    }
}

/// Reads a whole text file, naming it on failure.
pub fn read_text(path: &Path) -> Result<String, IoError> {
    std::fs::read_to_string(path).map_err(|e| IoError::file(path, e))
}

/// Writes a file through a temporary sibling and a rename, so a crash never leaves half a file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    use std::io::Write;
    let tmp = path.with_extension(format!(
        "{}.tmp",
        path.extension().and_then(|e| e.to_str()).unwrap_or("")
    ));
    let mut f = std::fs::File::create(&tmp).map_err(|e| IoError::file(&tmp, e))?;
    if let Err(e) = f.write_all(bytes).and_then(|()| f.sync_all()) {
        // A full disk: the partial file goes, so it does not hold on to the space.
        drop(f);
        let _ = std::fs::remove_file(&tmp);
        return Err(IoError::file(&tmp, e));
    }
    drop(f);
    std::fs::rename(&tmp, path).map_err(|e| IoError::file(path, e))
}

/// Splits a data line on whitespace or commas into fields, skipping empty ones.
pub fn fields(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| c.is_whitespace() || c == ',').filter(|s| !s.is_empty())
}

/// Parses `n` finite f64 fields from a data line, naming the file and line on failure.
pub fn parse_finite_fields(path: &Path, line_no: usize, line: &str, n: usize, what: &str) -> Result<Vec<f64>, IoError> {
    let vals: Vec<&str> = fields(line).collect();
    if vals.len() != n {
        return Err(IoError::parse(path, line_no, format!("expected {n} numbers ({what}), found {}", vals.len())));
    }
    vals.iter()
        .enumerate()
        .map(|(i, s)| match s.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(v) => Err(IoError::parse(path, line_no, format!("field {} ({what}) is {v}, not a finite number", i + 1))),
            Err(_) => Err(IoError::parse(path, line_no, format!("field {} ({what}) is {s:?}, not a number", i + 1))),
        })
        .collect()
}
