//! TUM RGB-D layout: `rgb.txt` / `depth.txt` (`TIMESTAMP PATH` lines after `#` comments, paths
//! relative to the folder), `groundtruth.txt` (TUM trajectory), `calibration.txt` (required,
//! ours), `medium.json` (optional, ours), `nav.csv` (optional, ours: navigation sensors, read
//! by `open_spec` for every layout).

use super::{
    check_exists, check_increasing, optional_medium, optional_trajectory, required_calibration, Dataset, DatasetFrame,
    DatasetKind, DatasetSpec, DepthFormat, DepthTrack, TUM_DEPTH_UNITS_PER_METRE,
};
use crate::CameraError;
use duv_core::Timestamp;
use duv_core::io::{fields, read_text, IoError};
use std::path::Path;

pub(super) fn open(spec: &DatasetSpec) -> Result<Dataset, CameraError> {
    let root = &spec.dir;
    let rgb_list = root.join("rgb.txt");
    if !rgb_list.is_file() {
        return Err(CameraError::Dataset { path: rgb_list, problem: "not found (a TUM-layout folder lists its images there)".into() });
    }
    let frames = read_list(&rgb_list, root)?;
    if frames.is_empty() {
        return Err(CameraError::Empty { path: rgb_list, what: "image lines" });
    }
    let camera = required_calibration(spec, &root.join("calibration.txt"), frames.first().map(|f| f.path.as_path()))?;
    let depth_list = root.join("depth.txt");
    let depth = if depth_list.exists() {
        let units_per_metre = spec.depth_scale.unwrap_or(TUM_DEPTH_UNITS_PER_METRE);
        Some(DepthTrack { frames: read_list(&depth_list, root)?, format: DepthFormat::PngU16 { units_per_metre } })
    } else {
        None
    };
    Ok(Dataset {
        kind: DatasetKind::Tum,
        root: root.clone(),
        camera,
        frames,
        depth,
        ground_truth: optional_trajectory(&root.join("groundtruth.txt"))?,
        medium: optional_medium(root)?,
        body_from_cam: None,
        downsample: 1,
        source_size: None,
        nav: None, // read by open_spec, the same for every layout
        ignore_mask: None,
    })
}

/// Reads a `TIMESTAMP PATH` list; every named file must exist, time stamps must increase.
fn read_list(list: &Path, root: &Path) -> Result<Vec<DatasetFrame>, CameraError> {
    let text = read_text(list)?;
    let mut frames: Vec<DatasetFrame> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = fields(line).collect();
        if f.len() != 2 {
            return Err(IoError::parse(list, line_no, format!("expected 2 fields (timestamp path), found {}", f.len())).into());
        }
        let t_ns: Timestamp = f[0].parse().map_err(|e| IoError::parse(list, line_no, format!("{e}")))?;
        check_increasing(list, line_no, frames.last().map(|p| p.t_ns), t_ns)?;
        let path = root.join(f[1]);
        check_exists(list, line_no, &path)?;
        frames.push(DatasetFrame { t_ns, path });
    }
    Ok(frames)
}
