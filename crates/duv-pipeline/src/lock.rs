//! One writer per run folder: an advisory lock (`flock`, through `std::fs::File::try_lock`) on
//! `DIR/duv.lock`, held for the life of the process. A second `duv run` or `duv replay` on the
//! same folder is refused with the holder's process id instead of "recovering" (rewriting)
//! the first one's live log segment. The lock is the kernel's: it goes with the process, so a
//! process killed with `kill -9` or by a power cut leaves no stale lock, only a stale file
//! whose process id is overwritten by the next holder.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// The lock file in a run folder.
pub const LOCK_FILE: &str = "duv.lock";

/// Why the run folder could not be locked.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// Another process holds the folder.
    #[error("run folder {dir} is in use by process {holder} (lock {path}); one writer per folder: wait for it, stop it, or choose another --out")]
    Held { dir: PathBuf, path: PathBuf, holder: String },
}

/// The held lock of a run folder; released when dropped (or when the process ends).
#[derive(Debug)]
pub struct RunFolderLock {
    _file: File,
    path: PathBuf,
}

impl RunFolderLock {
    /// Locks `dir` (created if missing) for this process, or says which process holds it.
    pub fn acquire(dir: &Path) -> Result<RunFolderLock, LockError> {
        let path = dir.join(LOCK_FILE);
        let io = |source| LockError::Io { path: path.clone(), source };
        std::fs::create_dir_all(dir).map_err(|source| LockError::Io { path: dir.to_path_buf(), source })?;
        let mut file = OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                let holder = if holder.is_empty() { "(unknown)".to_string() } else { holder.to_string() };
                return Err(LockError::Held { dir: dir.to_path_buf(), path, holder });
            }
            Err(TryLockError::Error(e)) => return Err(io(e)),
        }
        // Ours: record who holds it (a stale id from a dead holder is overwritten).
        file.set_len(0).map_err(io)?;
        file.seek(SeekFrom::Start(0)).map_err(io)?;
        writeln!(file, "{}", std::process::id()).map_err(io)?;
        file.flush().map_err(io)?;
        Ok(RunFolderLock { _file: file, path })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_with_the_first_ones_id_and_a_released_lock_is_taken() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("dive");
        let first = RunFolderLock::acquire(&run).unwrap();
        let text = std::fs::read_to_string(first.path()).unwrap();
        assert_eq!(text.trim(), std::process::id().to_string());
        // flock locks belong to the open file description: a second open in this process
        // conflicts as another process's would.
        let e = RunFolderLock::acquire(&run).unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, LockError::Held { .. }) && msg.contains(&std::process::id().to_string()) && msg.contains("in use"), "{msg}");
        drop(first);
        // A stale file (its holder gone) is taken over.
        std::fs::write(run.join(LOCK_FILE), "999999999\n").unwrap();
        let again = RunFolderLock::acquire(&run).unwrap();
        assert_eq!(std::fs::read_to_string(again.path()).unwrap().trim(), std::process::id().to_string());
    }
}
