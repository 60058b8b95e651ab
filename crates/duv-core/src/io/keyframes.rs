//! The keyframe folder: what the tracker writes for offline refinement (`duv refine`) and the
//! mapper reads back.
//!
//! ```text
//! calibration.txt               fx fy cx cy width height      (one line, undistorted pinhole)
//! keyframes.txt                 index timestamp tx ty tz qx qy qz qw   (one line per keyframe;
//!                               timestamp in seconds, pose world_from_cam, TUM order; '#'
//!                               starts a comment)
//! keyframes/NNNNNN.png          the image, 8-bit RGB (or grey), NNNNNN = index, 6 digits
//! keyframes/NNNNNN_invdepth.pfm inverse depth 1/z along the optical axis, 1/m; 0 = unknown
//! keyframes/NNNNNN_variance.pfm variance of the inverse depth, (1/m)^2
//! ```

use std::path::Path;

use super::pfm::{read_pfm, write_pfm};
use super::png_io::{read_image, write_rgb8};
use super::{parse_finite_fields, read_text, write_atomic, IoError};
use crate::pose::se3_from_tum;
use crate::{Keyframe, PinholeCamera, Timestamp};

fn image_path(dir: &Path, index: u64, suffix: &str) -> std::path::PathBuf {
    dir.join("keyframes").join(format!("{index:06}{suffix}"))
}

/// Writes keyframes (all with the same camera) as a keyframe folder.
pub fn write_keyframe_folder(dir: &Path, keyframes: &[Keyframe]) -> Result<(), IoError> {
    std::fs::create_dir_all(dir.join("keyframes")).map_err(|e| IoError::file(dir, e))?;
    let Some(first) = keyframes.first() else {
        return Err(IoError::invalid(dir, "no keyframes to write"));
    };
    let c = first.camera;
    write_atomic(&dir.join("calibration.txt"), format!("{} {} {} {} {} {}\n", c.fx, c.fy, c.cx, c.cy, c.width, c.height).as_bytes())?;
    let mut list = String::from("# index timestamp tx ty tz qx qy qz qw\n");
    for kf in keyframes {
        let t = kf.world_from_cam.translation.vector;
        let q = kf.world_from_cam.rotation.coords;
        list.push_str(&format!("{} {:.9} {} {} {} {} {} {} {}\n", kf.index, kf.t_ns.as_secs_f64(), t.x, t.y, t.z, q.x, q.y, q.z, q.w));
        write_rgb8(&image_path(dir, kf.index, ".png"), &kf.image)?;
        write_pfm(&image_path(dir, kf.index, "_invdepth.pfm"), &kf.inv_depth)?;
        write_pfm(&image_path(dir, kf.index, "_variance.pfm"), &kf.inv_depth_variance)?;
    }
    write_atomic(&dir.join("keyframes.txt"), list.as_bytes())
}

/// Reads a keyframe folder; every file is checked against the calibration's size.
pub fn read_keyframe_folder(dir: &Path) -> Result<Vec<Keyframe>, IoError> {
    let calib_path = dir.join("calibration.txt");
    let text = read_text(&calib_path)?;
    let line = text.lines().enumerate().find(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let Some((no, line)) = line else {
        return Err(IoError::invalid(&calib_path, "no calibration line"));
    };
    let v = parse_finite_fields(&calib_path, no + 1, line, 6, "fx fy cx cy width height")?;
    let camera = PinholeCamera::new(v[0], v[1], v[2], v[3], v[4] as usize, v[5] as usize).map_err(|e| IoError::parse(&calib_path, no + 1, e.to_string()))?;
    let list_path = dir.join("keyframes.txt");
    let text = read_text(&list_path)?;
    let mut out = Vec::new();
    for (no, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let v = parse_finite_fields(&list_path, no + 1, l, 9, "index timestamp tx ty tz qx qy qz qw")?;
        if v[0] < 0.0 || v[0].fract() != 0.0 {
            return Err(IoError::parse(&list_path, no + 1, format!("index {} is not a non-negative integer", v[0])));
        }
        let index = v[0] as u64;
        let world_from_cam = se3_from_tum([v[2], v[3], v[4], v[5], v[6], v[7], v[8]]).map_err(|e| IoError::parse(&list_path, no + 1, e.to_string()))?;
        let img_path = image_path(dir, index, ".png");
        let image = read_image(&img_path)?.to_rgb8();
        let inv_depth = read_pfm(&image_path(dir, index, "_invdepth.pfm"))?;
        let inv_depth_variance = read_pfm(&image_path(dir, index, "_variance.pfm"))?;
        let kf = Keyframe { index, t_ns: Timestamp::from_secs_f64(v[1]), image, world_from_cam, camera, inv_depth, inv_depth_variance };
        if !kf.is_consistent() {
            return Err(IoError::invalid(&img_path, format!("keyframe {index}: image or depth size differs from calibration {}x{}", camera.width, camera.height)));
        }
        out.push(kf);
    }
    if out.is_empty() {
        return Err(IoError::invalid(&list_path, "no keyframes listed"));
    }
    Ok(out)
}
