//! Small facts about segment files and their folder that the writer, recovery and the ROS 2 bag
//! index all need: whether a segment was finished, and a folder fsync.

use super::chunked::MAGIC;
use super::LogError;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// Whether `path` ends with the MCAP closing magic (a finished file).
pub fn is_finished(path: &Path) -> Result<bool, LogError> {
    let io = |source| LogError::Io { path: path.to_path_buf(), source };
    let mut f = File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    if len < (2 * MAGIC.len()) as u64 {
        return Ok(false);
    }
    f.seek(SeekFrom::End(-(MAGIC.len() as i64))).map_err(io)?;
    let mut tail = [0u8; 8];
    f.read_exact(&mut tail).map_err(io)?;
    Ok(tail == MAGIC)
}

/// fsyncs a directory so a rename or a new file in it survives power loss (best effort).
pub fn sync_dir(dir: &Path) {
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}
