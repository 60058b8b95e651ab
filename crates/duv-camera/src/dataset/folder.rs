//! A plain folder of PNG images with a calibration file. Time stamps come from the file stems
//! when they all are time stamps, else from a frame rate.

use super::{optional_medium, optional_trajectory, required_calibration, time_at_fps, Dataset, DatasetFrame, DatasetKind, DatasetSpec};
use crate::CameraError;
use duv_core::Timestamp;
use duv_core::io::IoError;
use std::path::PathBuf;

/// Default frame rate when the names carry no time.
pub const FOLDER_DEFAULT_FPS: f64 = 10.0;

pub(super) fn open(spec: &DatasetSpec) -> Result<Dataset, CameraError> {
    let root = &spec.dir;
    let mut images: Vec<(String, PathBuf)> = Vec::new();
    for entry in std::fs::read_dir(root).map_err(|e| IoError::file(root, e))? {
        let path = entry.map_err(|e| IoError::file(root, e))?.path();
        let is_png = path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if !is_png || !path.is_file() {
            continue;
        }
        let Some(stem) = path.file_stem().and_then(|s| s.to_str()) else {
            return Err(CameraError::Dataset { path, problem: "file name is not UTF-8".into() });
        };
        images.push((stem.to_string(), path));
    }
    if images.is_empty() {
        return Err(CameraError::Empty { path: root.clone(), what: "PNG images" });
    }
    images.sort();
    let camera = required_calibration(spec, &root.join("calibration.txt"))?;

    let stamped = if spec.fps.is_some() { None } else { stem_times(&images) };
    let frames = match stamped {
        Some(mut by_time) => {
            by_time.sort_by_key(|f| f.t_ns);
            if let Some(w) = by_time.windows(2).find(|w| w[0].t_ns == w[1].t_ns) {
                let problem = format!("has the same time stamp as {}", w[0].path.display());
                return Err(CameraError::Dataset { path: w[1].path.clone(), problem });
            }
            by_time
        }
        None => {
            let fps = spec.fps.unwrap_or(FOLDER_DEFAULT_FPS);
            images.into_iter().enumerate().map(|(i, (_, path))| DatasetFrame { t_ns: time_at_fps(i, fps), path }).collect()
        }
    };
    Ok(Dataset {
        kind: DatasetKind::Folder,
        root: root.clone(),
        camera,
        frames,
        depth: None,
        ground_truth: optional_trajectory(&root.join("groundtruth.txt"))?,
        medium: optional_medium(root)?,
        body_from_cam: None,
    })
}

/// Frames stamped from their names: all stems 19-digit integers (nanoseconds), or all decimal
/// seconds with a point (`1305031102.175304`). `None` when the names are not all one of these.
fn stem_times(images: &[(String, PathBuf)]) -> Option<Vec<DatasetFrame>> {
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if images.iter().all(|(s, _)| s.len() == 19 && digits(s)) {
        return images.iter().map(|(s, p)| Some(DatasetFrame { t_ns: Timestamp::from_ns(s.parse().ok()?), path: p.clone() })).collect();
    }
    let decimal = |s: &str| s.split_once('.').is_some_and(|(i, f)| digits(i) && digits(f));
    if images.iter().all(|(s, _)| decimal(s)) {
        return images.iter().map(|(s, p)| Some(DatasetFrame { t_ns: s.parse().ok()?, path: p.clone() })).collect();
    }
    None
}
