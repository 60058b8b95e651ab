//! TUM trajectory files: one pose per line, `timestamp tx ty tz qx qy qz qw`, camera-to-world,
//! `#` comments. The format every trajectory tool (evo, the TUM scripts) reads.

use super::{fields, IoError};
use crate::pose::{se3_from_tum, se3_to_tum};
use crate::{StampedPose, Timestamp};
use std::fmt::Write as _;
use std::path::Path;

/// Parses a TUM trajectory. Every data line must hold eight finite numbers and a unit quaternion;
/// time stamps must not go backwards.
pub fn parse_trajectory(path: &Path, text: &str) -> Result<Vec<StampedPose>, IoError> {
    let mut poses: Vec<StampedPose> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with("//") {
            continue;
        }
        let f: Vec<&str> = fields(line).collect();
        if f.len() != 8 {
            return Err(IoError::parse(path, line_no, format!("expected 8 fields (timestamp tx ty tz qx qy qz qw), found {}", f.len())));
        }
        let t_ns: Timestamp = f[0].parse().map_err(|e| IoError::parse(path, line_no, format!("{e}")))?;
        let mut v = [0f64; 7];
        for k in 0..7 {
            v[k] = f[k + 1]
                .parse::<f64>()
                .map_err(|_| IoError::parse(path, line_no, format!("field {} is {:?}, not a number", k + 2, f[k + 1])))?;
        }
        let world_from_cam = se3_from_tum(v).map_err(|e| IoError::parse(path, line_no, e.to_string()))?;
        if let Some(prev) = poses.last() {
            if t_ns < prev.t_ns {
                return Err(IoError::parse(path, line_no, format!("time stamp {t_ns} goes back before {}", prev.t_ns)));
            }
        }
        poses.push(StampedPose { t_ns, world_from_cam });
    }
    Ok(poses)
}

pub fn read_trajectory(path: &Path) -> Result<Vec<StampedPose>, IoError> {
    parse_trajectory(path, &super::read_text(path)?)
}

/// Formats poses as TUM text with a header comment.
pub fn format_trajectory(poses: &[StampedPose]) -> String {
    let mut s = String::from("# timestamp tx ty tz qx qy qz qw (camera-to-world; camera x right, y down, z forward)\n");
    for p in poses {
        let v = se3_to_tum(&p.world_from_cam);
        let _ = writeln!(s, "{} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}", p.t_ns, v[0], v[1], v[2], v[3], v[4], v[5], v[6]);
    }
    s
}

pub fn write_trajectory(path: &Path, poses: &[StampedPose]) -> Result<(), IoError> {
    std::fs::write(path, format_trajectory(poses)).map_err(|e| IoError::file(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trajectory_round_trip() {
        let text = "# header\n1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986\n\n1305031098.6758 1.3543 0.6306 1.6360 0.6129 0.5966 -0.3316 -0.3980\n";
        let p = Path::new("gt.txt");
        let poses = parse_trajectory(p, text).unwrap();
        assert_eq!(poses.len(), 2);
        assert_eq!(poses[0].t_ns, Timestamp(1_305_031_098_665_900_000));
        let again = parse_trajectory(p, &format_trajectory(&poses)).unwrap();
        for (a, b) in poses.iter().zip(&again) {
            assert_eq!(a.t_ns, b.t_ns);
            assert!((a.world_from_cam.to_homogeneous() - b.world_from_cam.to_homogeneous()).abs().max() < 1e-8);
        }
    }

    #[test]
    fn bad_lines_name_file_and_line() {
        let p = Path::new("groundtruth.txt");
        let e = parse_trajectory(p, "0 0 0 0 0 0 0 1\n1 nan 0 0 0 0 0 1\n").unwrap_err();
        assert_eq!(e.to_string(), format!("groundtruth.txt, line 2: pose has a non-finite value: [NaN, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]"));
        let e = parse_trajectory(p, "0 0 0 0 0 0 1\n").unwrap_err();
        assert!(e.to_string().contains("line 1: expected 8 fields"), "{e}");
        let e = parse_trajectory(p, "2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n").unwrap_err();
        assert!(e.to_string().contains("line 2") && e.to_string().contains("goes back"), "{e}");
    }
}
