//! TartanAir sequences: `image_left/NNNNNN_left.png`, `pose_left.txt` (`tx ty tz qx qy qz qw`
//! per image, NED: x forward, y right, z down), `depth_left/NNNNNN_left_depth.npy` (float32
//! metres). The camera is fx = fy = 320, cx = 320, cy = 240 at 640x480.

use super::{optional_calibration, time_at_fps, Dataset, DatasetFrame, DatasetKind, DatasetSpec, DepthFormat, DepthTrack};
use crate::CameraError;
use duv_core::{PinholeCamera, Se3, StampedPose};
use duv_core::io::{parse_finite_fields, read_text, IoError};
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use std::path::{Path, PathBuf};

/// Default frame rate for time stamps `i / fps`.
pub const TARTANAIR_DEFAULT_FPS: f64 = 10.0;

/// The TartanAir camera.
fn tartanair_camera() -> PinholeCamera {
    PinholeCamera { fx: 320.0, fy: 320.0, cx: 320.0, cy: 240.0, width: 640, height: 480, distortion: None }
}

/// `M`: NED axes (x forward, y right, z down) to camera axes (x right, y down, z forward).
fn ned_to_cam_axes() -> Matrix3<f64> {
    Matrix3::new(0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0)
}

/// Converts a TartanAir NED pose (`world_ned_from_body_ned`) to our camera convention,
/// `M * T_ned * M^-1` with `M` the axis permutation (as `ned2cam` in the TartanAir tools):
/// both the world and the body axes are re-expressed, so a body moving along its own NED x
/// (forward) moves along its own camera z.
pub fn ned_to_cam(world_from_body_ned: &Se3) -> Se3 {
    let m = ned_to_cam_axes();
    let r = m * world_from_body_ned.rotation.to_rotation_matrix().into_inner() * m.transpose();
    let t = m * world_from_body_ned.translation.vector;
    let rot = Rotation3::from_matrix_unchecked(r);
    Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&rot))
}

pub(super) fn open(spec: &DatasetSpec) -> Result<Dataset, CameraError> {
    let root = &spec.dir;
    let image_dir = root.join("image_left");
    let fps = spec.fps.unwrap_or(TARTANAIR_DEFAULT_FPS);
    let images = numbered_files(&image_dir, "_left.png")?;
    if images.is_empty() {
        return Err(CameraError::Empty { path: image_dir, what: "NNNNNN_left.png images" });
    }
    let frames: Vec<DatasetFrame> =
        images.into_iter().enumerate().map(|(i, path)| DatasetFrame { t_ns: time_at_fps(i, fps), path }).collect();

    let depth_dir = root.join("depth_left");
    let depth = if depth_dir.is_dir() {
        // One depth map per image, same index: list them by name and check each exists.
        let mut depth_frames = Vec::with_capacity(frames.len());
        for f in &frames {
            let image_name = f.path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
            let path = depth_dir.join(image_name.replace("_left.png", "_left_depth.npy"));
            if !path.is_file() {
                return Err(CameraError::Dataset { path, problem: format!("missing: depth_left/ must hold a depth map for each of the {} images", frames.len()) });
            }
            depth_frames.push(DatasetFrame { t_ns: f.t_ns, path });
        }
        Some(DepthTrack { frames: depth_frames, format: DepthFormat::NpyF32Metres })
    } else {
        None
    };

    let pose_path = root.join("pose_left.txt");
    let ground_truth = if pose_path.exists() { Some(read_poses(&pose_path, &frames)?) } else { None };
    let camera = optional_calibration(spec, &root.join("calibration.txt"))?.unwrap_or_else(tartanair_camera);
    Ok(Dataset {
        kind: DatasetKind::TartanAir,
        root: root.clone(),
        camera,
        frames,
        depth,
        ground_truth,
        medium: super::optional_medium(root)?,
        body_from_cam: None,
        downsample: 1,
        source_size: None,
        nav: None, // read by open_spec, the same for every layout
        ignore_mask: None,
    })
}

/// Files `NNNNNN{suffix}` in `dir`, which must be numbered 0, 1, 2... without gaps.
fn numbered_files(dir: &Path, suffix: &str) -> Result<Vec<PathBuf>, CameraError> {
    let entries = std::fs::read_dir(dir).map_err(|e| IoError::file(dir, e))?;
    let mut numbered: Vec<(usize, PathBuf)> = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| IoError::file(dir, e))?.path();
        let Some(name) = path.file_name().and_then(|n| n.to_str()) else { continue };
        let Some(stem) = name.strip_suffix(suffix) else { continue };
        let index = stem
            .parse::<usize>()
            .ok()
            .filter(|_| stem.bytes().all(|b| b.is_ascii_digit()))
            .ok_or_else(|| CameraError::Dataset { path: path.clone(), problem: format!("name is not NNNNNN{suffix}") })?;
        numbered.push((index, path));
    }
    numbered.sort();
    if let Some(w) = numbered.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(CameraError::Dataset { path: w[1].1.clone(), problem: format!("has the same number as {}", w[0].1.display()) });
    }
    for (expected, (index, path)) in numbered.iter().enumerate() {
        if *index != expected {
            let missing = dir.join(format!("{expected:06}{suffix}"));
            let problem = format!("missing (images must be numbered from 0 without gaps; next is {})", path.display());
            return Err(CameraError::Dataset { path: missing, problem });
        }
    }
    Ok(numbered.into_iter().map(|(_, p)| p).collect())
}

/// One NED pose per image, converted to camera convention.
fn read_poses(path: &Path, frames: &[DatasetFrame]) -> Result<Vec<StampedPose>, CameraError> {
    let text = read_text(path)?;
    let mut poses = Vec::with_capacity(frames.len());
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v = parse_finite_fields(path, line_no, line, 7, "tx ty tz qx qy qz qw")?;
        let Some(frame) = frames.get(poses.len()) else {
            return Err(IoError::parse(path, line_no, format!("more poses than the {} images", frames.len())).into());
        };
        let ned = duv_core::pose::se3_from_tum([v[0], v[1], v[2], v[3], v[4], v[5], v[6]])
            .map_err(|e| IoError::parse(path, line_no, e.to_string()))?;
        poses.push(StampedPose { t_ns: frame.t_ns, world_from_cam: ned_to_cam(&ned) });
    }
    if poses.len() != frames.len() {
        return Err(IoError::invalid(path, format!("{} poses for {} images", poses.len(), frames.len())).into());
    }
    Ok(poses)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Vector3};

    #[test]
    fn forward_in_ned_is_plus_z_in_the_camera() {
        // Body yawed +90 degrees about NED z (down): heading east. It moves 1 m forward along its
        // own x, so from (1, 2, 3) to (1, 3, 3).
        let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2);
        let a = Isometry3::from_parts(Translation3::new(1.0, 2.0, 3.0), yaw);
        let b = Isometry3::from_parts(Translation3::new(1.0, 2.0, 3.0) * Translation3::from(yaw * Vector3::x()), yaw);
        assert!((b.translation.vector - Vector3::new(1.0, 3.0, 3.0)).norm() < 1e-12);
        let (ca, cb) = (ned_to_cam(&a), ned_to_cam(&b));
        // b's position in a's camera frame: straight ahead.
        let b_in_a = ca.inverse_transform_point(&Point3::from(cb.translation.vector));
        assert!((b_in_a.coords - Vector3::new(0.0, 0.0, 1.0)).norm() < 1e-12, "{b_in_a}");
        // World axes permuted too: NED (1, 2, 3) -> camera world (2, 3, 1).
        assert!((ca.translation.vector - Vector3::new(2.0, 3.0, 1.0)).norm() < 1e-12);
        // Identity stays identity; NED "down" is camera world +y.
        let id = ned_to_cam(&Isometry3::identity());
        assert!((id.to_homogeneous() - nalgebra::Matrix4::identity()).abs().max() < 1e-15);
        let down = Isometry3::translation(0.0, 0.0, 1.0);
        assert!((ned_to_cam(&down).translation.vector - Vector3::y()).norm() < 1e-15);
        // The yaw about NED down becomes a yaw about camera-world y (down).
        let axis = ca.rotation.axis().unwrap();
        assert!((axis.into_inner() - Vector3::y()).norm() < 1e-12 && (ca.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }
}
