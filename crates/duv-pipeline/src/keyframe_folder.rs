//! The run's keyframe folder, `OUT/keyframes/`, and its one writer, [`KeyframeFolder`]: the
//! layout `duv refine --keyframes` reads. Per keyframe id (`{id:06}`): `NNNNNN.png` (the
//! image), `NNNNNN_invdepth.pfm` and `NNNNNN_variance.pfm` (full-resolution inverse depth and
//! its variance).
//!
//! - The mapping stage writes a keyframe's three files as it receives the keyframe
//!   ([`KeyframeFolder::write_keyframe`], [`mapping::GaussianMapping`](super::mapping::GaussianMapping)).
//! - At the end of the run the tracker's live keyframes get their final depth files
//!   ([`KeyframeFolder::write_depth`], [`outputs::write_keyframe_depths`](super::outputs::write_keyframe_depths)).
//! - The folder remembers which keyframe images it holds: those there when it was opened (a
//!   resumed dive's, read from the folder once) and those written since. That record, not the
//!   disk, answers which keyframes mapping received: `keyframes.txt` lists them, and a resume or
//!   the end-of-run catch-up feeds mapping the logged keyframes it did not receive.
//!
//! A [`KeyframeFolder`] is a handle: clones share the folder and its record (the mapping thread
//! writes through one, the run's outputs read the record through another).

use duv_core::io::pfm::write_pfm;
use duv_core::io::png_io::write_rgb8;
use duv_core::{Keyframe, PlaneF32};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// The folder's name in a run folder.
pub const KEYFRAME_DIR: &str = "keyframes";

/// Why the keyframe folder could not be made or written.
#[derive(Debug, thiserror::Error)]
pub enum KeyframeFolderError {
    #[error("creating {path}: {source}")]
    Create { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Io(#[from] duv_core::io::IoError),
}

/// `OUT/keyframes/`, its writer and the record of the keyframe images it holds (see the module
/// docs).
#[derive(Clone, Debug)]
pub struct KeyframeFolder {
    dir: Arc<PathBuf>,
    /// Ids whose image (`NNNNNN.png`) the folder holds.
    images: Arc<Mutex<BTreeSet<u64>>>,
}

impl KeyframeFolder {
    /// Creates `out/keyframes/` if missing and reads which keyframe images it already holds
    /// (a resumed dive's).
    pub fn open(out: &Path) -> Result<KeyframeFolder, KeyframeFolderError> {
        Self::open_dir(out.join(KEYFRAME_DIR))
    }

    /// As [`KeyframeFolder::open`], for the folder `dir` itself.
    pub fn open_dir(dir: PathBuf) -> Result<KeyframeFolder, KeyframeFolderError> {
        std::fs::create_dir_all(&dir).map_err(|source| KeyframeFolderError::Create { path: dir.clone(), source })?;
        let mut images = BTreeSet::new();
        if let Ok(entries) = std::fs::read_dir(&dir) {
            for entry in entries.flatten() {
                let name = entry.file_name();
                if let Some(id) = name.to_str().and_then(image_id) {
                    // As a look-up of the path would answer (a dangling link holds no image).
                    if entry.path().exists() {
                        images.insert(id);
                    }
                }
            }
        }
        Ok(KeyframeFolder { dir: Arc::new(dir), images: Arc::new(Mutex::new(images)) })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Whether the folder holds the image of keyframe `id` (mapping received it).
    pub fn has_image(&self, id: u64) -> bool {
        self.record().contains(&id)
    }

    /// The ids whose image the folder holds, in order.
    pub fn image_ids(&self) -> Vec<u64> {
        self.record().iter().copied().collect()
    }

    /// Writes a keyframe as mapping receives it: its image, inverse depth and variance, in that
    /// order (the folder is made again if it went). A failed write stops there.
    pub fn write_keyframe(&self, kf: &Keyframe) -> Result<(), KeyframeFolderError> {
        let id = kf.index;
        let dir: &Path = &self.dir;
        std::fs::create_dir_all(dir).map_err(|source| KeyframeFolderError::Create { path: dir.to_path_buf(), source })?;
        let image = dir.join(image_name(id));
        let written = write_rgb8(&image, &kf.image);
        // An image that failed part-way (a full disk) is still a file in the folder and is
        // counted as one, as a look at the folder would.
        if written.is_ok() || image.exists() {
            self.record().insert(id);
        }
        written?;
        write_pfm(&dir.join(format!("{id:06}_invdepth.pfm")), &kf.inv_depth)?;
        write_pfm(&dir.join(format!("{id:06}_variance.pfm")), &kf.inv_depth_variance)?;
        Ok(())
    }

    /// Writes the full-resolution inverse depth and variance of keyframe `id` (over the ones
    /// written when it arrived).
    pub fn write_depth(&self, id: u64, inv_depth: &PlaneF32, variance: &PlaneF32) -> Result<(), KeyframeFolderError> {
        write_pfm(&self.dir.join(format!("{id:06}_invdepth.pfm")), inv_depth)?;
        write_pfm(&self.dir.join(format!("{id:06}_variance.pfm")), variance)?;
        Ok(())
    }

    fn record(&self) -> std::sync::MutexGuard<'_, BTreeSet<u64>> {
        self.images.lock().unwrap_or_else(|p| p.into_inner())
    }
}

fn image_name(id: u64) -> String {
    format!("{id:06}.png")
}

/// The keyframe id of an image file name, `NNNNNN.png` exactly as [`image_name`] writes it.
fn image_id(name: &str) -> Option<u64> {
    let digits = name.strip_suffix(".png")?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let id: u64 = digits.parse().ok()?;
    (image_name(id) == name).then_some(id)
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::{ImageRgb8, PinholeCamera, Se3, Timestamp};

    fn keyframe(index: u64) -> Keyframe {
        let mut image = ImageRgb8::new(4, 3);
        image.data.iter_mut().enumerate().for_each(|(i, v)| *v = i as u8);
        let mut inv_depth = PlaneF32::new(4, 3);
        inv_depth.data.fill(0.5);
        let mut inv_depth_variance = PlaneF32::new(4, 3);
        inv_depth_variance.data.fill(0.01);
        let camera = PinholeCamera::new(4.0, 4.0, 2.0, 1.5, 4, 3).unwrap();
        Keyframe { index, t_ns: Timestamp::from_ns(index as i64), image, world_from_cam: Se3::identity(), camera, inv_depth, inv_depth_variance }
    }

    #[test]
    fn image_names_round_trip_and_others_are_not_keyframes() {
        assert_eq!(image_id("000007.png"), Some(7));
        assert_eq!(image_id("1234567.png"), Some(1_234_567));
        assert_eq!(image_id("0000007.png"), None, "not a name the folder writes");
        assert_eq!(image_id("000007_invdepth.pfm"), None);
        assert_eq!(image_id("00000a.png"), None);
        assert_eq!(image_id(".png"), None);
    }

    #[test]
    fn the_record_starts_from_the_folder_and_follows_the_writes() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        std::fs::create_dir_all(out.join(KEYFRAME_DIR)).unwrap();
        std::fs::write(out.join(KEYFRAME_DIR).join("000003.png"), b"earlier").unwrap();
        std::fs::write(out.join(KEYFRAME_DIR).join("000004_invdepth.pfm"), b"depth only").unwrap();
        let folder = KeyframeFolder::open(&out).unwrap();
        assert_eq!(folder.image_ids(), vec![3]);
        let other = folder.clone();
        other.write_keyframe(&keyframe(5)).unwrap();
        assert!(folder.has_image(5) && !folder.has_image(4));
        for name in ["000005.png", "000005_invdepth.pfm", "000005_variance.pfm"] {
            assert!(folder.dir().join(name).is_file(), "{name}");
        }
        let kf = keyframe(5);
        let before = std::fs::read(folder.dir().join("000005_invdepth.pfm")).unwrap();
        let mut inv = kf.inv_depth.clone();
        inv.data.fill(2.0);
        folder.write_depth(5, &inv, &kf.inv_depth_variance).unwrap();
        assert_ne!(std::fs::read(folder.dir().join("000005_invdepth.pfm")).unwrap(), before);
        assert_eq!(KeyframeFolder::open(&out).unwrap().image_ids(), vec![3, 5]);
    }
}
