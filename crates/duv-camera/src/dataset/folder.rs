//! A plain folder of PNG, JPEG or TIFF images (in the folder or its `images/`) with a calibration
//! file or a field-of-view guess. Time stamps come from the file stems when they all are time
//! stamps (nanoseconds, seconds, or a video time `HH_MM_SS.mmm` after a common prefix), else
//! from a frame rate.

use super::{is_image_file, optional_medium, optional_trajectory, required_calibration, time_at_fps, Dataset, DatasetFrame, DatasetKind, DatasetSpec};
use crate::CameraError;
use duv_core::Timestamp;
use duv_core::io::IoError;
use std::path::PathBuf;

/// Default frame rate when the names carry no time.
pub const FOLDER_DEFAULT_FPS: f64 = 10.0;

pub(super) fn open(spec: &DatasetSpec) -> Result<Dataset, CameraError> {
    let root = &spec.dir;
    let mut images = list_images(root)?;
    let nested = root.join("images");
    if images.is_empty() && nested.is_dir() {
        images = list_images(&nested)?;
    }
    if images.is_empty() {
        return Err(CameraError::Empty { path: root.clone(), what: "PNG, JPEG or TIFF images (here or in images/)" });
    }
    images.sort();
    let camera = required_calibration(spec, &root.join("calibration.txt"), Some(images[0].1.as_path()))?;

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
        downsample: 1,
        source_size: None,
        nav: None, // read by open_spec, the same for every layout
        ignore_mask: None,
    })
}

/// The PNG and JPEG files in `dir` as (stem, path).
fn list_images(dir: &std::path::Path) -> Result<Vec<(String, PathBuf)>, CameraError> {
    let mut images = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| IoError::file(dir, e))? {
        let path = entry.map_err(|e| IoError::file(dir, e))?.path();
        if !is_image_file(&path) || !path.is_file() {
            continue;
        }
        let Some(stem) = path.file_stem().and_then(|s| s.to_str()) else {
            return Err(CameraError::Dataset { path, problem: "file name is not UTF-8".into() });
        };
        images.push((stem.to_string(), path));
    }
    Ok(images)
}

/// Seconds of a video time `HH_MM_SS` or `HH_MM_SS.fff` at the end of `stem`, with what comes
/// before it.
fn video_time(stem: &str) -> Option<(&str, f64)> {
    let (whole, frac) = match stem.rsplit_once('.') {
        Some((w, f)) if !f.is_empty() && f.bytes().all(|b| b.is_ascii_digit()) => (w, Some(f)),
        _ => (stem, None),
    };
    let b = whole.as_bytes();
    if b.len() < 8 {
        return None;
    }
    let tail = &whole[whole.len() - 8..];
    let t = tail.as_bytes();
    let two = |i: usize| (t[i].is_ascii_digit() && t[i + 1].is_ascii_digit()).then(|| ((t[i] - b'0') * 10 + (t[i + 1] - b'0')) as f64);
    if t[2] != b'_' || t[5] != b'_' {
        return None;
    }
    let (h, m, sec) = (two(0)?, two(3)?, two(6)?);
    if m >= 60.0 || sec >= 60.0 {
        return None;
    }
    let frac = frac.map_or(Some(0.0), |f| format!("0.{f}").parse::<f64>().ok())?;
    Some((&whole[..whole.len() - 8], h * 3600.0 + m * 60.0 + sec + frac))
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
    // Video times after one common prefix (`frame_00_01_05.250`).
    let times: Option<Vec<(&str, f64)>> = images.iter().map(|(s, _)| video_time(s)).collect();
    let times = times?;
    if times.iter().any(|(prefix, _)| *prefix != times[0].0) {
        return None;
    }
    Some(images.iter().zip(&times).map(|((_, p), (_, secs))| DatasetFrame { t_ns: Timestamp::from_ns((secs * 1e9).round() as i64), path: p.clone() }).collect())
}

#[cfg(test)]
mod tests {
    use super::video_time;

    #[test]
    fn video_times_in_file_names() {
        assert_eq!(video_time("frame_00_00_21.000"), Some(("frame_", 21.0)));
        assert_eq!(video_time("frame_01_02_03.250"), Some(("frame_", 3723.25)));
        assert_eq!(video_time("00_10_00"), Some(("", 600.0)));
        assert_eq!(video_time("frame_00_61_00.000"), None);
        assert_eq!(video_time("frame_0000"), None);
        assert_eq!(video_time("image"), None);
    }
}
