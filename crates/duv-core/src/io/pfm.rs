//! PFM (portable float map) images: the float format numpy, OpenCV (`cv2.imread(path,
//! cv2.IMREAD_UNCHANGED)`) and most image tools read. Rows are stored bottom to top.

use super::IoError;
use crate::PlaneF32;
use std::path::Path;

/// Writes a one-channel little-endian PFM (`Pf`, scale -1).
pub fn write_pfm(path: &Path, plane: &PlaneF32) -> Result<(), IoError> {
    let mut bytes = format!("Pf\n{} {}\n-1.0\n", plane.width, plane.height).into_bytes();
    bytes.reserve(plane.data.len() * 4);
    for y in (0..plane.height).rev() {
        for v in plane.row(y) {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).map_err(|e| IoError::file(path, e))
}

/// Reads a one-channel PFM of either byte order.
pub fn read_pfm(path: &Path) -> Result<PlaneF32, IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    let bad = |reason: &str| IoError::BadPfm { path: path.to_path_buf(), reason: reason.to_string() };
    // Header: three whitespace-separated tokens after the magic, then one whitespace byte.
    let mut tokens = Vec::new();
    let mut pos = 0;
    while tokens.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos {
            return Err(bad("truncated header"));
        }
        tokens.push(std::str::from_utf8(&bytes[start..pos]).map_err(|_| bad("header is not text"))?.to_string());
    }
    pos += 1;
    if tokens[0] != "Pf" {
        return Err(bad(&format!("magic {:?} is not a one-channel PFM (Pf)", tokens[0])));
    }
    let width: usize = tokens[1].parse().map_err(|_| bad("bad width"))?;
    let height: usize = tokens[2].parse().map_err(|_| bad("bad height"))?;
    let scale: f32 = tokens[3].parse().map_err(|_| bad("bad scale"))?;
    let little = scale < 0.0;
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(4)).ok_or_else(|| bad("size overflows"))?;
    if bytes.len() < pos + need {
        return Err(bad(&format!("expected {need} bytes of pixels, found {}", bytes.len().saturating_sub(pos))));
    }
    let mut data = vec![0f32; width * height];
    for (i, chunk) in bytes[pos..pos + need].chunks_exact(4).enumerate() {
        let b = [chunk[0], chunk[1], chunk[2], chunk[3]];
        let v = if little { f32::from_le_bytes(b) } else { f32::from_be_bytes(b) };
        let (x, y_from_bottom) = (i % width, i / width);
        data[(height - 1 - y_from_bottom) * width + x] = v;
    }
    Ok(PlaneF32 { width, height, data })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pfm_round_trip_keeps_row_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.pfm");
        let plane = PlaneF32 { width: 3, height: 2, data: vec![0.5, 1.0, -2.0, f32::INFINITY, 3.25, 1e-7] };
        write_pfm(&p, &plane).unwrap();
        let back = read_pfm(&p).unwrap();
        assert_eq!(back, plane);
        std::fs::write(&p, b"Pf\n3 2\n-1.0\n\0\0").unwrap();
        assert!(matches!(read_pfm(&p), Err(IoError::BadPfm { .. })));
    }
}
