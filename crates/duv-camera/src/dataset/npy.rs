//! Minimal NumPy `.npy` reader and writer for 2-D little-endian float32 arrays (TartanAir
//! depth). Strict: any other dtype, Fortran order, a shape that is not 2-D or a data size that
//! does not match the shape is an error naming the file.

use crate::CameraError;
use duv_core::PlaneF32;
use duv_core::io::IoError;
use std::path::Path;

const MAGIC: &[u8] = b"\x93NUMPY";

/// Reads a C-order `<f4` array of shape `(height, width)`.
pub fn read_npy_f32(path: &Path) -> Result<PlaneF32, CameraError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    parse_npy_f32(path, &bytes)
}

/// Parses the bytes of a `.npy` file (`path` names it in errors).
pub fn parse_npy_f32(path: &Path, bytes: &[u8]) -> Result<PlaneF32, CameraError> {
    let bad = |problem: String| CameraError::BadNpy { path: path.to_path_buf(), problem };
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(bad("missing the \\x93NUMPY magic".into()));
    }
    let (header_len, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(bad("truncated header".into()));
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(bad(format!("format version {v}.{} is not supported", bytes[7]))),
    };
    let end = start.checked_add(header_len).filter(|&e| e <= bytes.len()).ok_or_else(|| bad("truncated header".into()))?;
    let header = std::str::from_utf8(&bytes[start..end]).map_err(|_| bad("header is not text".into()))?;
    let h = parse_header(header).map_err(|p| bad(format!("header {:?}: {p}", header.trim_end())))?;
    if h.descr != "<f4" {
        return Err(bad(format!("dtype {:?} is not little-endian float32 ('<f4')", h.descr)));
    }
    if h.fortran_order {
        return Err(bad("Fortran-order arrays are not supported".into()));
    }
    let [height, width] = h.shape[..] else {
        return Err(bad(format!("shape {:?} is not 2-D", h.shape)));
    };
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(4)).ok_or_else(|| bad("shape overflows".into()))?;
    let data_bytes = &bytes[end..];
    if data_bytes.len() != need {
        return Err(bad(format!("shape ({height}, {width}) needs {need} bytes of data, found {}", data_bytes.len())));
    }
    let data = data_bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    Ok(PlaneF32 { width, height, data })
}

/// Writes a plane as a version 1.0 `.npy` of dtype `<f4` and shape `(height, width)`.
pub fn write_npy_f32(path: &Path, plane: &PlaneF32) -> Result<(), CameraError> {
    let dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}), }}", plane.height, plane.width);
    // Pad with spaces so that the data starts on a 64-byte boundary; the header ends in '\n'.
    let unpadded = MAGIC.len() + 4 + dict.len() + 1;
    let padding = (64 - unpadded % 64) % 64;
    let header = format!("{dict}{}\n", " ".repeat(padding));
    let mut bytes = Vec::with_capacity(unpadded + padding + plane.data.len() * 4);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in &plane.data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, bytes).map_err(|e| IoError::file(path, e).into())
}

#[derive(Debug, PartialEq)]
struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Parses the header dict: `{'descr': '<f4', 'fortran_order': False, 'shape': (h, w), }`.
fn parse_header(text: &str) -> Result<Header, String> {
    let mut p = Cursor { s: text.as_bytes(), i: 0 };
    p.expect(b'{')?;
    let (mut descr, mut fortran_order, mut shape) = (None, None, None);
    loop {
        p.ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.string()?;
        p.ws();
        p.expect(b':')?;
        p.ws();
        match key.as_str() {
            "descr" if descr.is_none() => descr = Some(p.string()?),
            "fortran_order" if fortran_order.is_none() => fortran_order = Some(p.boolean()?),
            "shape" if shape.is_none() => shape = Some(p.tuple()?),
            other => return Err(format!("unexpected or repeated key {other:?}")),
        }
        p.ws();
        if !p.eat(b',') {
            p.ws();
            p.expect(b'}')?;
            break;
        }
    }
    p.ws();
    if p.i != p.s.len() {
        return Err("text after the closing brace".into());
    }
    Ok(Header {
        descr: descr.ok_or("no 'descr'")?,
        fortran_order: fortran_order.ok_or("no 'fortran_order'")?,
        shape: shape.ok_or("no 'shape'")?,
    })
}

struct Cursor<'a> {
    s: &'a [u8],
    i: usize,
}

impl Cursor<'_> {
    fn ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }
    fn eat(&mut self, c: u8) -> bool {
        let hit = self.s.get(self.i) == Some(&c);
        if hit {
            self.i += 1;
        }
        hit
    }
    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("expected {:?} at byte {}", c as char, self.i))
        }
    }
    fn string(&mut self) -> Result<String, String> {
        let q = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("expected a quoted string at byte {}", self.i)),
        };
        self.i += 1;
        let start = self.i;
        while self.i < self.s.len() && self.s[self.i] != q {
            self.i += 1;
        }
        if self.i >= self.s.len() {
            return Err("unterminated string".into());
        }
        let out = String::from_utf8_lossy(&self.s[start..self.i]).into_owned();
        self.i += 1;
        Ok(out)
    }
    fn boolean(&mut self) -> Result<bool, String> {
        let rest = &self.s[self.i..];
        if rest.starts_with(b"True") {
            self.i += 4;
            Ok(true)
        } else if rest.starts_with(b"False") {
            self.i += 5;
            Ok(false)
        } else {
            Err(format!("expected True or False at byte {}", self.i))
        }
    }
    fn tuple(&mut self) -> Result<Vec<usize>, String> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        loop {
            self.ws();
            if self.eat(b')') {
                return Ok(dims);
            }
            let start = self.i;
            while self.i < self.s.len() && self.s[self.i].is_ascii_digit() {
                self.i += 1;
            }
            let digits = std::str::from_utf8(&self.s[start..self.i]).unwrap_or("");
            dims.push(digits.parse::<usize>().map_err(|_| format!("expected a dimension at byte {start}"))?);
            self.ws();
            if !self.eat(b',') {
                self.ws();
                self.expect(b')')?;
                return Ok(dims);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_numpy_header() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.npy");
        let plane = PlaneF32 { width: 3, height: 2, data: vec![0.5, 1.0, -2.0, f32::INFINITY, 3.25, 1e-7] };
        write_npy_f32(&p, &plane).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!((bytes.len() - 6 * 4) % 64, 0);
        assert_eq!(read_npy_f32(&p).unwrap(), plane);
        // The exact header numpy 1.x writes for np.zeros((2, 3), np.float32).
        let h = parse_header("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }                                                            \n").unwrap();
        assert_eq!(h, Header { descr: "<f4".into(), fortran_order: false, shape: vec![2, 3] });
        assert_eq!(parse_header("{'descr': '<f4', 'fortran_order': False, 'shape': (5,)}").unwrap().shape, vec![5]);
    }

    #[test]
    fn rejects_what_it_cannot_read() {
        let p = Path::new("x.npy");
        let plane = PlaneF32 { width: 2, height: 2, data: vec![1.0; 4] };
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("ok.npy");
        write_npy_f32(&f, &plane).unwrap();
        let good = std::fs::read(&f).unwrap();
        let swap = |from: &str, to: &str| {
            assert_eq!(from.len(), to.len());
            let at = good.windows(from.len()).position(|w| w == from.as_bytes()).unwrap();
            let mut b = good.clone();
            b[at..at + to.len()].copy_from_slice(to.as_bytes());
            b
        };
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (swap("<f4", "<f8"), "dtype \"<f8\" is not little-endian float32"),
            (swap("False", "True "), "Fortran-order"),
            (swap("(2, 2)", "(4,)  "), "shape [4] is not 2-D"),
            (good[..good.len() - 1].to_vec(), "needs 16 bytes of data, found 15"),
            (b"PK\x03\x04".to_vec(), "magic"),
            (swap("'descr'", "'dtype'"), "unexpected or repeated key"),
        ];
        for (bytes, want) in cases {
            let e = parse_npy_f32(p, &bytes).unwrap_err().to_string();
            assert!(e.starts_with("x.npy: not a readable .npy array") && e.contains(want), "want {want:?}: {e}");
        }
    }
}
