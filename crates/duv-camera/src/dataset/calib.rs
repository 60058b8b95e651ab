//! Our `calibration.txt` and `medium.json` files.
//!
//! `calibration.txt` holds one data line `fx fy cx cy width height`, optionally followed by the
//! radial-tangential coefficients `k1 k2 p1 p2 k3` (11 numbers); blank lines and lines starting
//! with `#` are ignored. `medium.json` is `{"beta_D":[r,g,b],"beta_B":[r,g,b],"B_inf":[r,g,b]}`.

use crate::CameraError;
use duv_core::{MediumParams, PinholeCamera, RadTan};
use duv_core::io::{fields, parse_finite_fields, read_text, IoError};
use std::fmt::Write as _;
use std::path::Path;

const CALIB_FIELDS: &str = "fx fy cx cy width height [k1 k2 p1 p2 k3]";

/// Reads a `calibration.txt`; a missing file is an error naming it.
pub fn read_calibration(path: &Path) -> Result<PinholeCamera, CameraError> {
    parse_calibration(path, &read_text(path)?)
}

/// Parses the text of a `calibration.txt` (`path` names it in errors).
pub fn parse_calibration(path: &Path, text: &str) -> Result<PinholeCamera, CameraError> {
    let mut camera = None;
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if camera.is_some() {
            return Err(IoError::parse(path, line_no, "a second data line; the file holds one camera").into());
        }
        let n = fields(line).count();
        if n != 6 && n != 11 {
            return Err(IoError::parse(path, line_no, format!("expected 6 or 11 numbers ({CALIB_FIELDS}), found {n}")).into());
        }
        let v = parse_finite_fields(path, line_no, line, n, CALIB_FIELDS)?;
        let size = |k: usize, name: &str| -> Result<usize, CameraError> {
            let x = v[k];
            if x.fract() != 0.0 || !(1.0..=1e6).contains(&x) {
                return Err(IoError::parse(path, line_no, format!("{name} {x} is not a positive whole number of pixels")).into());
            }
            Ok(x as usize)
        };
        let (width, height) = (size(4, "width")?, size(5, "height")?);
        let model_err = |source| CameraError::Calibration { path: path.to_path_buf(), source };
        let mut cam = PinholeCamera::new(v[0], v[1], v[2], v[3], width, height).map_err(model_err)?;
        if n == 11 {
            let d = RadTan { k1: v[6], k2: v[7], p1: v[8], p2: v[9], k3: v[10] };
            cam = cam.with_distortion(d).map_err(model_err)?;
        }
        camera = Some(cam);
    }
    camera.ok_or_else(|| IoError::invalid(path, format!("no data line; expected `{CALIB_FIELDS}`")).into())
}

/// Formats a camera as `calibration.txt` text (11 numbers when it has distortion). Values are
/// written in Rust's shortest round-trip form, so reading back gives the same camera.
pub fn format_calibration(camera: &PinholeCamera) -> String {
    let c = camera;
    let mut s = format!("# {CALIB_FIELDS}\n{} {} {} {} {} {}", c.fx, c.fy, c.cx, c.cy, c.width, c.height);
    if let Some(d) = c.distortion {
        let _ = write!(s, " {} {} {} {} {}", d.k1, d.k2, d.p1, d.p2, d.k3);
    }
    s.push('\n');
    s
}

/// Reads and checks `medium.json`: finite non-negative coefficients, `B_inf` in [0, 1].
pub fn read_medium(path: &Path) -> Result<MediumParams, CameraError> {
    let text = read_text(path)?;
    let m: MediumParams =
        serde_json::from_str(&text).map_err(|e| IoError::parse(path, e.line(), format!("medium parameters: {e}")))?;
    let checks: [(&str, [f64; 3], f64); 3] = [("beta_D", m.beta_d, f64::INFINITY), ("beta_B", m.beta_b, f64::INFINITY), ("B_inf", m.b_inf, 1.0)];
    for (name, values, max) in checks {
        if !values.iter().all(|v| v.is_finite() && *v >= 0.0 && *v <= max) {
            let range = if max == 1.0 { "in [0, 1]" } else { "finite and >= 0" };
            return Err(CameraError::Dataset { path: path.to_path_buf(), problem: format!("{name} {values:?} must be {range}") });
        }
    }
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_round_trip_and_errors() {
        let p = Path::new("calibration.txt");
        let cam = parse_calibration(p, "# fx fy cx cy w h\n\n320 321.5 319.5 239.5 640 480\n").unwrap();
        assert_eq!((cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height), (320.0, 321.5, 319.5, 239.5, 640, 480));
        assert!(cam.distortion.is_none());
        let d = cam.with_distortion(RadTan { k1: -0.28, k2: 0.07, p1: 1.9e-4, p2: 1.76e-5, k3: 0.0 }).unwrap();
        assert_eq!(parse_calibration(p, &format_calibration(&d)).unwrap(), d);
        assert_eq!(parse_calibration(p, &format_calibration(&cam)).unwrap(), cam);

        let e = parse_calibration(p, "# c\n320 320 319.5 239.5 640\n").unwrap_err();
        assert_eq!(e.to_string(), format!("calibration.txt, line 2: expected 6 or 11 numbers ({CALIB_FIELDS}), found 5"));
        let e = parse_calibration(p, "320 320 319.5 239.5 640.5 480\n").unwrap_err();
        assert!(e.to_string().contains("line 1: width 640.5"), "{e}");
        let e = parse_calibration(p, "-1 320 319.5 239.5 640 480\n").unwrap_err();
        assert!(matches!(e, CameraError::Calibration { .. }), "{e}");
        let e = parse_calibration(p, "1 1 1 1 8 6\n1 1 1 1 8 6\n").unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");
        let e = parse_calibration(p, "# nothing\n").unwrap_err();
        assert!(e.to_string().starts_with("calibration.txt: no data line"), "{e}");
    }

    #[test]
    fn medium_is_checked() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("medium.json");
        std::fs::write(&p, r#"{"beta_D":[0.4,0.1,0.05],"beta_B":[0.3,0.1,0.06],"B_inf":[0.05,0.3,0.4]}"#).unwrap();
        let m = read_medium(&p).unwrap();
        assert_eq!(m.beta_d, [0.4, 0.1, 0.05]);
        std::fs::write(&p, "{\"beta_D\":[0.4,0.1,0.05],\n\"beta_B\":[0.3,0.1],\"B_inf\":[0.05,0.3,0.4]}").unwrap();
        let e = read_medium(&p).unwrap_err();
        assert!(e.to_string().contains("medium.json, line 2"), "{e}");
        std::fs::write(&p, r#"{"beta_D":[0.4,0.1,0.05],"beta_B":[0.3,0.1,0.06],"B_inf":[0.05,1.3,0.4]}"#).unwrap();
        assert!(read_medium(&p).unwrap_err().to_string().contains("B_inf"));
    }
}
