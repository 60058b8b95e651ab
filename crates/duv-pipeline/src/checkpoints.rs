//! Map checkpoint files for resume: `map-NNNNNN.ckpt`, each written to a temporary name,
//! fsynced and renamed, with a header holding its length and an FNV-1a 64 checksum. Loading
//! takes the newest file that verifies and falls back to older ones; the oldest are pruned.

use super::PipelineError;
use std::io::Write;
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"DUVCKPT1";
const HEADER: usize = 8 + 8 + 8;

fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf29ce484222325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x100000001b3);
    }
    h
}

/// A folder of checksummed checkpoints.
pub struct CheckpointStore {
    dir: PathBuf,
    keep: usize,
}

fn index_of(name: &str) -> Option<u64> {
    name.strip_prefix("map-")?.strip_suffix(".ckpt")?.parse().ok()
}

impl CheckpointStore {
    /// `keep`: how many checkpoints stay on disk (at least 2, so a corrupt newest one has a
    /// predecessor).
    pub fn new(dir: impl Into<PathBuf>, keep: usize) -> Self {
        CheckpointStore { dir: dir.into(), keep: keep.max(2) }
    }

    fn list(&self) -> Vec<(u64, PathBuf)> {
        let mut v: Vec<(u64, PathBuf)> = std::fs::read_dir(&self.dir)
            .map(|rd| rd.flatten().filter_map(|e| e.file_name().to_str().and_then(index_of).map(|i| (i, e.path()))).collect())
            .unwrap_or_default();
        v.sort();
        v
    }

    /// Writes a new checkpoint (temp, fsync, rename, fsync the folder) and prunes old ones.
    pub fn save(&self, bytes: &[u8]) -> Result<PathBuf, PipelineError> {
        let io = |p: &Path| {
            let p = p.to_path_buf();
            move |source| PipelineError::Io { path: p, source }
        };
        std::fs::create_dir_all(&self.dir).map_err(io(&self.dir))?;
        let next = self.list().last().map(|(i, _)| i + 1).unwrap_or(0);
        let path = self.dir.join(format!("map-{next:06}.ckpt"));
        let tmp = self.dir.join(format!("map-{next:06}.ckpt.tmp"));
        let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        let mut header = [0u8; HEADER];
        header[..8].copy_from_slice(MAGIC);
        header[8..16].copy_from_slice(&(bytes.len() as u64).to_le_bytes());
        header[16..24].copy_from_slice(&fnv1a64(bytes).to_le_bytes());
        if let Err(e) = f.write_all(&header).and_then(|()| f.write_all(bytes)).and_then(|()| f.sync_all()) {
            // A full disk: the partial file goes, so it does not hold on to the space.
            drop(f);
            let _ = std::fs::remove_file(&tmp);
            return Err(PipelineError::Io { path: tmp, source: e });
        }
        drop(f);
        std::fs::rename(&tmp, &path).map_err(io(&path))?;
        duv_log::writer::sync_dir(&self.dir);
        let all = self.list();
        if all.len() > self.keep {
            for (_, old) in &all[..all.len() - self.keep] {
                let _ = std::fs::remove_file(old);
            }
        }
        Ok(path)
    }

    /// Reads and verifies one checkpoint file.
    pub fn read(path: &Path) -> Result<Vec<u8>, PipelineError> {
        let bad = |problem: String| PipelineError::BadCheckpoint { path: path.to_path_buf(), problem };
        let data = std::fs::read(path).map_err(|source| PipelineError::Io { path: path.to_path_buf(), source })?;
        if data.len() < HEADER || &data[..8] != MAGIC {
            return Err(bad("not a duv checkpoint (bad header)".into()));
        }
        let len = u64::from_le_bytes(data[8..16].try_into().expect("8 bytes")) as usize;
        let saved = u64::from_le_bytes(data[16..24].try_into().expect("8 bytes"));
        if data.len() - HEADER != len {
            return Err(bad(format!("{} payload bytes, the header says {len}", data.len() - HEADER)));
        }
        let calculated = fnv1a64(&data[HEADER..]);
        if calculated != saved {
            return Err(bad(format!("checksum {calculated:#018x}, the header says {saved:#018x}")));
        }
        Ok(data[HEADER..].to_vec())
    }

    /// The newest checkpoint that verifies, with its path; corrupt ones are reported (WARN)
    /// and skipped. `None` when there is none.
    pub fn load_newest(&self) -> Option<(PathBuf, Vec<u8>)> {
        for (_, path) in self.list().into_iter().rev() {
            match Self::read(&path) {
                Ok(b) => return Some((path, b)),
                Err(e) => tracing::warn!("skipping a checkpoint: {e}"),
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corrupt_newest_falls_back_to_previous() {
        let dir = tempfile::tempdir().unwrap();
        let store = CheckpointStore::new(dir.path(), 3);
        store.save(b"first map").unwrap();
        let second = store.save(b"second map").unwrap();
        assert_eq!(store.load_newest().unwrap().1, b"second map");
        let mut bytes = std::fs::read(&second).unwrap();
        let n = bytes.len();
        bytes[n - 2] ^= 0x40;
        std::fs::write(&second, &bytes).unwrap();
        let e = CheckpointStore::read(&second).unwrap_err().to_string();
        assert!(e.contains("checksum") && e.contains("map-000001.ckpt"), "{e}");
        let (path, b) = store.load_newest().unwrap();
        assert_eq!(b, b"first map");
        assert!(path.ends_with("map-000000.ckpt"));
        // Truncated file.
        std::fs::write(&second, &bytes[..10]).unwrap();
        assert!(CheckpointStore::read(&second).is_err());
        // Pruning keeps `keep` files.
        for i in 0..5 {
            store.save(format!("map {i}").as_bytes()).unwrap();
        }
        assert_eq!(store.list().len(), 3);
        assert_eq!(store.load_newest().unwrap().1, b"map 4");
    }
}
