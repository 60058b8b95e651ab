//! The standard 3D Gaussian splatting PLY (the format of the 3DGS reference code and the
//! viewers built on it), binary little endian, one `vertex` element with these `float`
//! properties:
//!
//! ```text
//! x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_8 opacity scale_0 scale_1 scale_2
//! rot_0 rot_1 rot_2 rot_3
//! ```
//!
//! Opacity is stored as its logit, scales as natural logs, the rotation as `w x y z` (all as
//! in [`Gaussians`]); normals are zero. `f_rest` is **channel-major** in the file
//! (`f_rest_{c * 3 + k}`: channel `c`, degree-1 coefficient `k`, the 3DGS layout after its
//! transpose) and coefficient-major in [`Gaussians`] (`f_rest[k * 3 + c]`); both orders use the
//! same basis order (`-y`, `z`, `-x`). The reader accepts the properties in any order (by name)
//! and ignores extra float properties.

use std::path::Path;

use super::gaussians::{GaussianParam, Gaussians};
use duv_core::io::{write_atomic, IoError};

/// Property names in the order this writer emits them.
pub const PLY_PROPERTIES: [&str; 26] = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0", "f_rest_1", "f_rest_2", "f_rest_3", "f_rest_4", "f_rest_5", "f_rest_6",
    "f_rest_7", "f_rest_8", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
];

/// One Gaussian as the 26 file values, in [`PLY_PROPERTIES`] order.
fn to_record(p: &GaussianParam<f32>) -> [f32; 26] {
    let mut r = [0.0f32; 26];
    r[0..3].copy_from_slice(&p.mean);
    r[6..9].copy_from_slice(&p.f_dc);
    for c in 0..3 {
        for k in 0..3 {
            r[9 + c * 3 + k] = p.f_rest[k * 3 + c];
        }
    }
    r[18] = p.opacity_logit;
    r[19..22].copy_from_slice(&p.log_scale);
    r[22..26].copy_from_slice(&p.rotation);
    r
}

/// `p` moved by the similarity `to_from_map` (`x -> s R x + t`): the mean moved, the log
/// scales raised by `ln s`, the rotation turned by `R`, and the degree-1 colour coefficients
/// turned with the view direction (their basis `(-y, z, -x)` is a vector: `v = (-f2, -f0, f1)`
/// per channel becomes `R v`). Opacity and base colour do not change.
pub fn transform_gaussian(p: &GaussianParam<f32>, to_from_map: &duv_core::Sim3) -> GaussianParam<f32> {
    let mut q = p.clone();
    let s = to_from_map.scaling();
    let r = to_from_map.isometry.rotation;
    let m = to_from_map.transform_point(&nalgebra::Point3::new(p.mean[0] as f64, p.mean[1] as f64, p.mean[2] as f64));
    q.mean = [m.x as f32, m.y as f32, m.z as f32];
    for v in &mut q.log_scale {
        *v += s.ln() as f32;
    }
    let rot = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.rotation[0] as f64, p.rotation[1] as f64, p.rotation[2] as f64, p.rotation[3] as f64));
    let turned = r * rot;
    q.rotation = [turned.w as f32, turned.i as f32, turned.j as f32, turned.k as f32];
    for c in 0..3 {
        let v = nalgebra::Vector3::new(-(p.f_rest[6 + c] as f64), -(p.f_rest[c] as f64), p.f_rest[3 + c] as f64);
        let w = r * v;
        q.f_rest[c] = -w.y as f32;
        q.f_rest[3 + c] = w.z as f32;
        q.f_rest[6 + c] = -w.x as f32;
    }
    q
}

/// Encodes the map as a binary little-endian 3DGS PLY.
pub fn encode_ply(gaussians: &Gaussians) -> Vec<u8> {
    encode_ply_in(gaussians, None)
}

/// [`encode_ply`] with every Gaussian moved by `to_from_map` ([`transform_gaussian`]), e.g.
/// into metres; a `comment` line in the header says so.
pub fn encode_ply_in(gaussians: &Gaussians, to_from_map: Option<&duv_core::Sim3>) -> Vec<u8> {
    let mut out = String::from("ply\nformat binary_little_endian 1.0\n");
    if let Some(a) = to_from_map {
        out.push_str(&format!("comment duv-slam: metric (metres), {:.6} m per map unit\n", a.scaling()));
    }
    out.push_str(&format!("element vertex {}\n", gaussians.len()));
    for name in PLY_PROPERTIES {
        out.push_str(&format!("property float {name}\n"));
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    bytes.reserve(gaussians.len() * 26 * 4);
    for i in 0..gaussians.len() {
        let g = gaussians.get(i);
        let g = match to_from_map {
            Some(a) => transform_gaussian(&g, a),
            None => g,
        };
        for v in to_record(&g) {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

/// Writes the map to `path` (temporary file, fsync, rename).
pub fn write_ply(path: &Path, gaussians: &Gaussians) -> Result<(), IoError> {
    write_atomic(path, &encode_ply(gaussians))
}

/// [`write_ply`] with every Gaussian moved by `to_from_map` ([`encode_ply_in`]).
pub fn write_ply_in(path: &Path, gaussians: &Gaussians, to_from_map: Option<&duv_core::Sim3>) -> Result<(), IoError> {
    write_atomic(path, &encode_ply_in(gaussians, to_from_map))
}

/// Decodes a 3DGS PLY into a map of the given capacity (an error when it holds more).
pub fn decode_ply(path: &Path, bytes: &[u8], capacity: usize) -> Result<Gaussians, IoError> {
    let end = b"end_header\n";
    let header_len = bytes.windows(end.len()).position(|w| w == end).ok_or_else(|| IoError::invalid(path, "no end_header line"))? + end.len();
    let header = std::str::from_utf8(&bytes[..header_len]).map_err(|_| IoError::invalid(path, "header is not UTF-8"))?;
    let mut lines = header.lines();
    if lines.next() != Some("ply") {
        return Err(IoError::invalid(path, "not a PLY file"));
    }
    let mut count = None;
    let mut props: Vec<String> = Vec::new();
    let mut in_vertex = false;
    for (no, line) in lines.enumerate() {
        let f: Vec<&str> = line.split_whitespace().collect();
        match f.as_slice() {
            ["format", "binary_little_endian", _] => {}
            ["format", other, _] => return Err(IoError::invalid(path, format!("format {other} is not supported (binary_little_endian only)"))),
            ["element", "vertex", n] => {
                count = Some(n.parse::<usize>().map_err(|_| IoError::parse(path, no + 2, "bad vertex count"))?);
                in_vertex = true;
            }
            ["element", ..] => in_vertex = false,
            ["property", "float", name] if in_vertex => props.push(name.to_string()),
            ["property", ty, ..] if in_vertex => return Err(IoError::parse(path, no + 2, format!("vertex property type {ty} is not supported (float only)"))),
            _ => {}
        }
    }
    let count = count.ok_or_else(|| IoError::invalid(path, "no vertex element"))?;
    if count > capacity {
        return Err(IoError::invalid(path, format!("{count} Gaussians exceed the capacity {capacity}")));
    }
    let names = PLY_PROPERTIES;
    let mut column = [usize::MAX; 26];
    for (j, name) in names.iter().enumerate() {
        match props.iter().position(|p| p == name) {
            Some(c) => column[j] = c,
            None if (3..6).contains(&j) => {}
            None => return Err(IoError::invalid(path, format!("missing vertex property {name}"))),
        }
    }
    let stride = props.len() * 4;
    let body = &bytes[header_len..];
    if body.len() < count * stride {
        return Err(IoError::invalid(path, format!("truncated: {} data bytes, {} needed", body.len(), count * stride)));
    }
    let mut g = Gaussians::with_capacity(capacity);
    for i in 0..count {
        let rec = &body[i * stride..(i + 1) * stride];
        let val = |j: usize| {
            let c = column[j];
            if c == usize::MAX {
                0.0
            } else {
                f32::from_le_bytes([rec[c * 4], rec[c * 4 + 1], rec[c * 4 + 2], rec[c * 4 + 3]])
            }
        };
        let mut p = GaussianParam::<f32>::default();
        for k in 0..3 {
            p.mean[k] = val(k);
            p.f_dc[k] = val(6 + k);
            p.log_scale[k] = val(19 + k);
        }
        for c in 0..3 {
            for k in 0..3 {
                p.f_rest[k * 3 + c] = val(9 + c * 3 + k);
            }
        }
        p.opacity_logit = val(18);
        for k in 0..4 {
            p.rotation[k] = val(22 + k);
        }
        g.push(&p).map_err(|e| IoError::invalid(path, e.to_string()))?;
    }
    Ok(g)
}

/// Reads a 3DGS PLY file into a map of the given capacity.
pub fn read_ply(path: &Path, capacity: usize) -> Result<Gaussians, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    decode_ply(path, &bytes, capacity)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_is_exact_and_f_rest_is_channel_major() {
        let mut g = Gaussians::with_capacity(8);
        for i in 0..5 {
            let a: [f32; 23] = std::array::from_fn(|k| (i * 23 + k) as f32 * 0.37 - 3.0);
            g.push(&GaussianParam::from_array(&a)).unwrap();
        }
        let bytes = encode_ply(&g);
        let back = decode_ply(Path::new("mem.ply"), &bytes, 8).unwrap();
        assert_eq!(back.len(), 5);
        for i in 0..5 {
            assert_eq!(back.get(i), g.get(i));
        }
        // f_rest_1 in the file is the R channel's coefficient 1, ours f_rest[1 * 3 + 0].
        let header_len = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let v = |j: usize| f32::from_le_bytes(bytes[header_len + j * 4..header_len + j * 4 + 4].try_into().unwrap());
        assert_eq!(v(9 + 1), g.get(0).f_rest[3]);
        assert_eq!(v(9 + 3), g.get(0).f_rest[1]);
        assert_eq!(v(18), g.get(0).opacity_logit);
        assert!(decode_ply(Path::new("mem.ply"), &bytes, 4).is_err(), "capacity is enforced");
    }
}
