//! EuRoC / ASL folder format: `mav0/cam0/data.csv` (`#timestamp [ns],filename`), images in
//! `mav0/cam0/data/`, intrinsics and extrinsics in `mav0/cam0/sensor.yaml`, ground truth in
//! `mav0/state_groundtruth_estimate0/data.csv` (body pose in world, quaternion w first).

use super::{check_exists, check_increasing, Dataset, DatasetFrame, DatasetKind, DatasetSpec};
use crate::CameraError;
use duv_core::{PinholeCamera, RadTan, Se3, StampedPose, Timestamp};
use duv_core::io::{read_text, IoError};
use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion};
use std::path::Path;

/// Errors of the `euroc` module that no file names yet: a `T_BS` matrix that is not a rigid
/// transform, a `[a, b, c]` list that does not parse (the caller reports them at their line of
/// `sensor.yaml`).
#[derive(Debug, thiserror::Error)]
pub enum EurocError {
    #[error("list does not start with [")]
    ListOpen,
    #[error("list is not closed with ]")]
    ListNotClosed,
    #[error("unexpected text after ]: {text:?}")]
    TextAfterList { text: String },
    #[error("empty or nested list item")]
    BadListItem,
    #[error("last row {last:?} is not [0, 0, 0, 1]")]
    BadLastRow { last: [f64; 4] },
    #[error("rotation part is not a rotation (|R^T R - I| = {orthonormality_error:.2e}, det = {determinant:.4})")]
    NotARotation { orthonormality_error: f64, determinant: f64 },
}

pub(super) fn open(spec: &DatasetSpec) -> Result<Dataset, CameraError> {
    let root = &spec.dir;
    let cam_name = spec.cam.as_deref().unwrap_or("cam0");
    let mav0 = if root.join("mav0").is_dir() { root.join("mav0") } else { root.clone() };
    let cam_dir = mav0.join(cam_name);
    let list = cam_dir.join("data.csv");
    if !list.is_file() {
        let expected = if root.join("mav0").is_dir() { list } else { root.join("mav0").join(cam_name).join("data.csv") };
        return Err(CameraError::Dataset { path: expected, problem: "not found (an EuRoC folder lists its images there)".into() });
    }
    let frames = read_image_list(&list, &cam_dir.join("data"))?;
    if frames.is_empty() {
        return Err(CameraError::Empty { path: list, what: "image lines" });
    }
    let sensor = read_sensor_yaml(&cam_dir.join("sensor.yaml"))?;
    let gt_path = mav0.join("state_groundtruth_estimate0").join("data.csv");
    let ground_truth = if gt_path.exists() { Some(read_ground_truth(&gt_path, &sensor.body_from_cam)?) } else { None };
    Ok(Dataset {
        kind: DatasetKind::Euroc,
        root: root.clone(),
        camera: sensor.camera,
        frames,
        depth: None,
        ground_truth,
        medium: super::optional_medium(root)?,
        body_from_cam: Some(sensor.body_from_cam),
        downsample: 1,
        source_size: None,
        nav: None, // read by open_spec, the same for every layout
        ignore_mask: None,
    })
}

fn parse_ns(list: &Path, line_no: usize, text: &str) -> Result<Timestamp, CameraError> {
    if text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) {
        return Err(IoError::parse(list, line_no, format!("time stamp {text:?} is not an integer number of nanoseconds")).into());
    }
    text.parse::<i64>()
        .map(Timestamp::from_ns)
        .map_err(|_| IoError::parse(list, line_no, format!("time stamp {text:?} is out of range")).into())
}

/// `timestamp,filename` lines after a `#` header; files live in `data_dir`.
fn read_image_list(list: &Path, data_dir: &Path) -> Result<Vec<DatasetFrame>, CameraError> {
    let text = read_text(list)?;
    let mut frames: Vec<DatasetFrame> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() != 2 || f[1].is_empty() {
            let found = f.iter().filter(|s| !s.is_empty()).count();
            return Err(IoError::parse(list, line_no, format!("expected 2 fields (timestamp [ns],filename), found {found}")).into());
        }
        let t_ns = parse_ns(list, line_no, f[0])?;
        check_increasing(list, line_no, frames.last().map(|p| p.t_ns), t_ns)?;
        let path = data_dir.join(f[1]);
        check_exists(list, line_no, &path)?;
        frames.push(DatasetFrame { t_ns, path });
    }
    Ok(frames)
}

/// Body poses `timestamp, p_RS_R_{x,y,z}, q_RS_{w,x,y,z}, ...` turned into camera poses
/// `world_from_cam = world_from_body * body_from_cam`.
fn read_ground_truth(path: &Path, body_from_cam: &Se3) -> Result<Vec<StampedPose>, CameraError> {
    let text = read_text(path)?;
    let mut poses: Vec<StampedPose> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() < 8 || f.iter().any(|s| s.is_empty()) {
            return Err(IoError::parse(path, line_no, format!(
                "expected at least 8 fields (timestamp, p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y, q_RS_z), found {}",
                f.iter().filter(|s| !s.is_empty()).count()
            ))
            .into());
        }
        let t_ns = parse_ns(path, line_no, f[0])?;
        check_increasing(path, line_no, poses.last().map(|p| p.t_ns), t_ns)?;
        let mut v = [0f64; 7];
        for (k, s) in f[1..8].iter().enumerate() {
            v[k] = match s.parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                _ => return Err(IoError::parse(path, line_no, format!("field {} is {s:?}, not a finite number", k + 2)).into()),
            };
        }
        // w-first in the file; TUM order is x y z w.
        let tum = [v[0], v[1], v[2], v[4], v[5], v[6], v[3]];
        let world_from_body =
            duv_core::pose::se3_from_tum(tum).map_err(|e| IoError::parse(path, line_no, e.to_string()))?;
        poses.push(StampedPose { t_ns, world_from_cam: world_from_body * body_from_cam });
    }
    if poses.is_empty() {
        return Err(CameraError::Empty { path: path.to_path_buf(), what: "ground-truth lines" });
    }
    Ok(poses)
}

/// What we take from `sensor.yaml`.
struct Sensor {
    camera: PinholeCamera,
    body_from_cam: Se3,
}

fn read_sensor_yaml(path: &Path) -> Result<Sensor, CameraError> {
    let doc = parse_yaml(path, &read_text(path)?)?;
    let invalid = |problem: String| -> CameraError { IoError::invalid(path, problem).into() };
    let get = |key: &str| doc.iter().find(|(k, _)| k == key).map(|(_, e)| e);
    let require = |key: &str| get(key).ok_or_else(|| invalid(format!("missing key `{key}`")));
    let numbers = |key: &str, entry: &YamlEntry, n: usize| -> Result<Vec<f64>, CameraError> {
        let YamlValue::List(items) = &entry.value else {
            return Err(IoError::parse(path, entry.line, format!("`{key}` must be a list [...] of {n} numbers")).into());
        };
        if items.len() != n {
            return Err(IoError::parse(path, entry.line, format!("`{key}` has {} values, expected {n}", items.len())).into());
        }
        items
            .iter()
            .map(|s| match s.parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(v),
                _ => Err(IoError::parse(path, entry.line, format!("`{key}` value {s:?} is not a finite number")).into()),
            })
            .collect()
    };
    let scalar = |key: &str, entry: &YamlEntry| -> Result<String, CameraError> {
        match &entry.value {
            YamlValue::Scalar(s) => Ok(s.clone()),
            _ => Err(IoError::parse(path, entry.line, format!("`{key}` must be a plain value")).into()),
        }
    };

    if let Some(e) = get("camera_model") {
        let model = scalar("camera_model", e)?;
        if model != "pinhole" {
            return Err(IoError::parse(path, e.line, format!("camera_model {model:?} is not supported (only pinhole)")).into());
        }
    }
    let k = numbers("intrinsics", require("intrinsics")?, 4)?;
    let res_entry = require("resolution")?;
    let res = numbers("resolution", res_entry, 2)?;
    if res.iter().any(|v| v.fract() != 0.0 || *v < 1.0) {
        return Err(IoError::parse(path, res_entry.line, format!("resolution {res:?} is not two positive whole numbers")).into());
    }
    let model_err = |source| CameraError::Calibration { path: path.to_path_buf(), source };
    let mut camera = PinholeCamera::new(k[0], k[1], k[2], k[3], res[0] as usize, res[1] as usize).map_err(model_err)?;

    let model_entry = require("distortion_model")?;
    let model = scalar("distortion_model", model_entry)?;
    if model != "radial-tangential" && model != "radtan" {
        return Err(IoError::parse(path, model_entry.line, format!("distortion_model {model:?} is not supported (only radial-tangential)")).into());
    }
    let coeff_entry = require("distortion_coefficients")?;
    let d = numbers("distortion_coefficients", coeff_entry, 4)?;
    if d.iter().any(|v| *v != 0.0) {
        camera = camera.with_distortion(RadTan { k1: d[0], k2: d[1], p1: d[2], p2: d[3], k3: 0.0 }).map_err(model_err)?;
    }

    let t_entry = require("T_BS")?;
    let YamlValue::Map(t_map) = &t_entry.value else {
        return Err(IoError::parse(path, t_entry.line, "`T_BS` must be a block with `data: [16 numbers]`").into());
    };
    for dim in ["rows", "cols"] {
        if let Some((_, e)) = t_map.iter().find(|(k, _)| k == dim) {
            if scalar(dim, e)? != "4" {
                return Err(IoError::parse(path, e.line, format!("T_BS {dim} must be 4")).into());
            }
        }
    }
    let data_entry = t_map
        .iter()
        .find(|(k, _)| k == "data")
        .map(|(_, e)| e)
        .ok_or_else(|| IoError::parse(path, t_entry.line, "T_BS has no `data` list"))?;
    let m = numbers("T_BS data", data_entry, 16)?;
    let body_from_cam = rigid_from_row_major(&m).map_err(|problem| IoError::parse(path, data_entry.line, format!("T_BS: {problem}")))?;
    Ok(Sensor { camera, body_from_cam })
}

/// A rigid transform from 16 row-major numbers; the rotation must be orthonormal to 1e-4 and
/// is re-orthonormalised (files carry about 10 digits).
fn rigid_from_row_major(m: &[f64]) -> Result<Se3, EurocError> {
    let t = Matrix4::from_row_slice(m);
    let last = [t[(3, 0)], t[(3, 1)], t[(3, 2)], t[(3, 3)]];
    if last != [0.0, 0.0, 0.0, 1.0] {
        return Err(EurocError::BadLastRow { last });
    }
    let r: Matrix3<f64> = t.fixed_view::<3, 3>(0, 0).into_owned();
    let err = (r.transpose() * r - Matrix3::identity()).abs().max();
    if err > 1e-4 || r.determinant() < 0.0 {
        return Err(EurocError::NotARotation { orthonormality_error: err, determinant: r.determinant() });
    }
    let rot = Rotation3::from_matrix_eps(&r, 1e-15, 100, Rotation3::identity());
    Ok(Isometry3::from_parts(Translation3::new(t[(0, 3)], t[(1, 3)], t[(2, 3)]), UnitQuaternion::from_rotation_matrix(&rot)))
}

/// Builds a rigid transform from a position and a w-first quaternion (EuRoC order).
#[cfg(test)]
fn pose_wxyz(p: [f64; 3], q: [f64; 4]) -> Se3 {
    use nalgebra::Quaternion;
    Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])))
}

// ---- the YAML subset of `sensor.yaml` ----

#[derive(Debug, PartialEq)]
enum YamlValue {
    Scalar(String),
    List(Vec<String>),
    Map(Vec<(String, YamlEntry)>),
}

/// Entries of a block, in file order.
type YamlBlock = Vec<(String, YamlEntry)>;

#[derive(Debug, PartialEq)]
struct YamlEntry {
    /// Line of the key, for errors.
    line: usize,
    value: YamlValue,
}

/// Parses the YAML subset the ASL sensor files use: top-level `key: value` lines, `key: [a, b]`
/// flow lists (which may span lines), and one level of indented `key: value` blocks under a
/// `key:` line. `#` starts a comment (at line start or after a space); `%YAML` directives and
/// `---` are skipped. Anything else is an error naming the line.
fn parse_yaml(path: &Path, text: &str) -> Result<Vec<(String, YamlEntry)>, CameraError> {
    let lines: Vec<&str> = text.lines().collect();
    let mut top: Vec<(String, YamlEntry)> = Vec::new();
    // The open `key:` block: its key, line and entries so far.
    let mut block: Option<(String, usize, YamlBlock)> = None;
    let mut i = 0;
    let err = |line: usize, problem: String| -> CameraError { IoError::parse(path, line, problem).into() };
    while i < lines.len() {
        let line_no = i + 1;
        let content = strip_comment(lines[i]);
        i += 1;
        if content.trim().is_empty() || (content.starts_with('%') || content.trim() == "---") {
            continue;
        }
        if content.contains('\t') {
            return Err(err(line_no, "tab characters are not allowed in YAML indentation".into()));
        }
        let indent = content.len() - content.trim_start().len();
        let (key, rest) = content
            .trim()
            .split_once(':')
            .ok_or_else(|| err(line_no, format!("expected `key: value`, found {:?}", content.trim())))?;
        let key = key.trim().to_string();
        if key.is_empty() || key.contains(char::is_whitespace) {
            return Err(err(line_no, format!("bad key {key:?}")));
        }
        let rest = rest.trim();
        let value = if rest.starts_with('[') {
            // Gather a flow list up to its closing bracket.
            let mut buf = rest.to_string();
            while !buf.contains(']') {
                if i >= lines.len() {
                    return Err(err(line_no, format!("list of `{key}` is not closed with ]")));
                }
                let next = strip_comment(lines[i]);
                if next.contains(':') {
                    return Err(err(line_no, format!("list of `{key}` is not closed with ] before line {}", i + 1)));
                }
                buf.push(' ');
                buf.push_str(next);
                i += 1;
            }
            Some(YamlValue::List(parse_flow_list(&buf).map_err(|p| err(line_no, format!("`{key}`: {p}")))?))
        } else if rest.is_empty() {
            None
        } else {
            Some(YamlValue::Scalar(rest.trim_matches(|c| c == '"' || c == '\'').to_string()))
        };
        if indent == 0 {
            if let Some((k, l, m)) = block.take() {
                top.push((k, YamlEntry { line: l, value: YamlValue::Map(m) }));
            }
            if top.iter().any(|(k, _)| *k == key) {
                return Err(err(line_no, format!("key `{key}` appears twice")));
            }
            match value {
                Some(v) => top.push((key, YamlEntry { line: line_no, value: v })),
                None => block = Some((key, line_no, Vec::new())),
            }
        } else {
            let Some((parent, _, entries)) = block.as_mut() else {
                return Err(err(line_no, format!("indented key `{key}` outside a block")));
            };
            let Some(v) = value else {
                return Err(err(line_no, format!("`{parent}.{key}` has no value (only one level of nesting is supported)")));
            };
            if entries.iter().any(|(k, _)| *k == key) {
                return Err(err(line_no, format!("key `{parent}.{key}` appears twice")));
            }
            entries.push((key, YamlEntry { line: line_no, value: v }));
        }
    }
    if let Some((k, l, m)) = block.take() {
        top.push((k, YamlEntry { line: l, value: YamlValue::Map(m) }));
    }
    Ok(top)
}

/// The part of a line before a comment (`#` at the start or after whitespace).
fn strip_comment(line: &str) -> &str {
    let bytes = line.as_bytes();
    for (k, &b) in bytes.iter().enumerate() {
        if b == b'#' && (k == 0 || bytes[k - 1].is_ascii_whitespace()) {
            return line[..k].trim_end();
        }
    }
    line.trim_end()
}

/// `[a, b, c]` (one trailing comma allowed) into its items.
fn parse_flow_list(text: &str) -> Result<Vec<String>, EurocError> {
    let t = text.trim();
    let inner = t.strip_prefix('[').ok_or(EurocError::ListOpen)?;
    let close = inner.find(']').ok_or(EurocError::ListNotClosed)?;
    if !inner[close + 1..].trim().is_empty() {
        return Err(EurocError::TextAfterList { text: inner[close + 1..].trim().to_string() });
    }
    let body = inner[..close].trim();
    if body.is_empty() {
        return Ok(Vec::new());
    }
    let body = body.strip_suffix(',').unwrap_or(body);
    let items: Vec<String> = body.split(',').map(|s| s.trim().to_string()).collect();
    if items.iter().any(|s| s.is_empty() || s.contains('[')) {
        return Err(EurocError::BadListItem);
    }
    Ok(items)
}

#[cfg(test)]
mod tests {
    use super::*;

    const EUROC_YAML: &str = "# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
";

    #[test]
    fn reads_the_real_euroc_sensor_yaml() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sensor.yaml");
        std::fs::write(&p, EUROC_YAML).unwrap();
        let s = read_sensor_yaml(&p).unwrap();
        assert_eq!((s.camera.fx, s.camera.fy, s.camera.cx, s.camera.cy), (458.654, 457.296, 367.215, 248.375));
        assert_eq!((s.camera.width, s.camera.height), (752, 480));
        let d = s.camera.distortion.unwrap();
        assert_eq!((d.k1, d.k2, d.p1, d.p2, d.k3), (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0));
        let t = s.body_from_cam.to_homogeneous();
        assert!((t[(0, 1)] + 0.999880929698).abs() < 1e-6 && (t[(1, 3)] + 0.064676986768).abs() < 1e-15);
    }

    #[test]
    fn malformed_yaml_is_an_error_with_a_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sensor.yaml");
        let cases: [(String, &str); 6] = [
            (EUROC_YAML.replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [458.654, 457.296, 367.215]"), "line 18: `intrinsics` has 3 values, expected 4"),
            (EUROC_YAML.replace("1.0]\n", "1.0\n"), "line 9: list of `data` is not closed with ] before line 15"),
            (EUROC_YAML.replace("resolution: [752, 480]\n", ""), "missing key `resolution`"),
            (EUROC_YAML.replace("radial-tangential", "equidistant"), "line 19: distortion_model \"equidistant\" is not supported"),
            (EUROC_YAML.replace("0.0, 0.0, 0.0, 1.0]", "0.0, 0.0, 0.0, 1.0, 2.0]"), "line 9: `T_BS data` has 17 values"),
            (EUROC_YAML.replace("rate_hz: 20", "rate_hz 20"), "line 15: expected `key: value`"),
        ];
        for (text, want) in cases {
            std::fs::write(&p, &text).unwrap();
            let e = read_sensor_yaml(&p).err().expect(want).to_string();
            assert!(e.contains("sensor.yaml") && e.contains(want), "want {want:?}, got {e}");
        }
        std::fs::write(&p, EUROC_YAML.replace("0.999557249008", "1.999557249008")).unwrap();
        assert!(read_sensor_yaml(&p).err().unwrap().to_string().contains("T_BS: rotation part is not a rotation"));
    }

    #[test]
    fn ground_truth_is_composed_with_t_bs() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("data.csv");
        // Body at (1, 2, 3) yawed +90 degrees about world z; camera 0.1 m along body x, with
        // camera z (forward) along body x: body_from_cam = [[0,0,1],[-1,0,0]... ] below.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        std::fs::write(&p, format!("#timestamp, p_RS_R_x [m], ...\n1000,1,2,3,{s},0,0,{s},0,0,0\n")).unwrap();
        let body_from_cam = rigid_from_row_major(&[0., 0., 1., 0.1, -1., 0., 0., 0., 0., -1., 0., 0., 0., 0., 0., 1.]).unwrap();
        let gt = read_ground_truth(&p, &body_from_cam).unwrap();
        assert_eq!(gt[0].t_ns, Timestamp(1000));
        let w = gt[0].world_from_cam;
        // Camera origin: body origin + R_wb * (0.1, 0, 0) = (1, 2.1, 3).
        assert!((w.translation.vector - nalgebra::Vector3::new(1.0, 2.1, 3.0)).norm() < 1e-12);
        // Camera forward (z) = body x = world y after the yaw.
        let fwd = w.rotation * nalgebra::Vector3::z();
        assert!((fwd - nalgebra::Vector3::y()).norm() < 1e-12, "{fwd}");
        // Camera right (x) = -body y = world +x after the yaw.
        let right = w.rotation * nalgebra::Vector3::x();
        assert!((right - nalgebra::Vector3::x()).norm() < 1e-12, "{right}");
        let expected = pose_wxyz([1.0, 2.0, 3.0], [s, 0.0, 0.0, s]) * body_from_cam;
        assert!((expected.to_homogeneous() - w.to_homogeneous()).abs().max() < 1e-15);
    }
}
