//! NumPy `.npy` reading and writing of 2-D little-endian float32 arrays (TartanAir depth),
//! through the `npyz` crate: it parses the preamble (magic, format version 1, 2 or 3) and the
//! header dict, reads the data and writes whole files. On top of it this module is as strict
//! as numpy's own reader, and stricter about what it accepts: a header whose keys are not
//! exactly `descr`, `fortran_order` and `shape` (npyz ignores extra keys and keeps the last of
//! a repeated one, so the dict is checked with `py_literal`, the parser npyz uses), any dtype
//! but `<f4`, Fortran order, a shape that is not 2-D or data that is not exactly the shape's
//! size is an error naming the file.

use crate::CameraError;
use duv_core::PlaneF32;
use duv_core::io::IoError;
use npyz::{DType, NpyFile, NpyHeader, Order, TypeStr, WriterBuilder};
use py_literal::Value;
use std::io::ErrorKind;
use std::path::Path;

/// Errors of the `npy` module: why bytes are not a readable array. The reader returns them
/// as [`CameraError::BadNpy`], with the file's path.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    /// What npyz refused before the header text: the `\x93NUMPY` magic, the format version.
    #[error(transparent)]
    Preamble(std::io::Error),
    #[error("truncated header")]
    TruncatedHeader,
    /// A header dict npyz could not read (not a dict, a key missing, a value of the wrong kind).
    #[error("header {text:?}: {source}")]
    Header { text: String, source: std::io::Error },
    /// A key numpy does not write, or one of its keys twice.
    #[error("header {text:?}: unexpected or repeated key {key:?}")]
    Key { text: String, key: String },
    #[error("dtype {descr:?} is not little-endian float32 ('<f4')")]
    Dtype { descr: String },
    #[error("Fortran-order arrays are not supported")]
    FortranOrder,
    #[error("shape {shape:?} is not 2-D")]
    NotTwoD { shape: Vec<u64> },
    #[error("shape {shape:?} overflows")]
    ShapeOverflow { shape: Vec<u64> },
    #[error("shape ({height}, {width}) needs {need} bytes of data, found {found}")]
    DataSize { height: usize, width: usize, need: usize, found: usize },
    #[error("data: {0}")]
    Data(#[source] std::io::Error),
}

/// The keys of a `.npy` header dict, each exactly once.
const KEYS: [&str; 3] = ["descr", "fortran_order", "shape"];

/// Reads a C-order `<f4` array of shape `(height, width)`.
pub fn read_npy_f32(path: &Path) -> Result<PlaneF32, CameraError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    parse_npy_f32(path, &bytes)
}

/// Parses the bytes of a `.npy` file (`path` names it in errors).
pub fn parse_npy_f32(path: &Path, bytes: &[u8]) -> Result<PlaneF32, CameraError> {
    decode(bytes).map_err(|e| CameraError::BadNpy { path: path.to_path_buf(), problem: e.to_string() })
}

fn decode(bytes: &[u8]) -> Result<PlaneF32, NpyError> {
    let (header, data) = read_header(bytes)?;
    let h = Header::of(&header);
    if h.descr != "<f4" {
        return Err(NpyError::Dtype { descr: h.descr });
    }
    if h.fortran_order {
        return Err(NpyError::FortranOrder);
    }
    let shape = header.shape();
    let &[rows, cols] = shape else {
        return Err(NpyError::NotTwoD { shape: shape.to_vec() });
    };
    let overflow = || NpyError::ShapeOverflow { shape: shape.to_vec() };
    let (height, width) = (usize::try_from(rows).map_err(|_| overflow())?, usize::try_from(cols).map_err(|_| overflow())?);
    let need = width.checked_mul(height).and_then(|n| n.checked_mul(4)).ok_or_else(overflow)?;
    if data.len() != need {
        return Err(NpyError::DataSize { height, width, need, found: data.len() });
    }
    let data = NpyFile::with_header(header, data).into_vec::<f32>().map_err(NpyError::Data)?;
    Ok(PlaneF32 { width, height, data })
}

/// npyz's header of `bytes` and the data after it, the dict's keys checked as numpy checks
/// them.
fn read_header(bytes: &[u8]) -> Result<(NpyHeader, &[u8]), NpyError> {
    let mut rest = bytes;
    let parsed = NpyHeader::from_reader(&mut rest);
    // npyz reads the magic and version (8 bytes), the header length (2 bytes in version 1,
    // 4 in versions 2 and 3), then the header text: what it has read past those is the text.
    let read = bytes.len() - rest.len();
    let text_start = if bytes.get(6) == Some(&1) { 10 } else { 12 };
    let text = bytes.get(text_start..read).map(String::from_utf8_lossy);
    match parsed {
        Ok(header) => {
            if let Some(text) = &text {
                check_keys(text)?;
            }
            Ok((header, rest))
        }
        Err(e) if e.kind() == ErrorKind::UnexpectedEof => Err(NpyError::TruncatedHeader),
        Err(source) => match text {
            Some(text) => {
                check_keys(&text)?;
                Err(NpyError::Header { text: text.trim_end().to_string(), source })
            }
            None => Err(NpyError::Preamble(source)),
        },
    }
}

/// numpy's rule, which npyz does not keep: the dict holds exactly [`KEYS`], each once. Text
/// that is not a dict passes here; npyz says what is wrong with it.
fn check_keys(text: &str) -> Result<(), NpyError> {
    let Ok(Value::Dict(pairs)) = text.trim_end().parse::<Value>() else {
        return Ok(());
    };
    let mut seen = [false; KEYS.len()];
    for (key, _) in &pairs {
        let slot = match key {
            Value::String(k) => KEYS.iter().position(|&known| known == k),
            _ => None,
        };
        match slot {
            Some(i) if !seen[i] => seen[i] = true,
            _ => {
                let key = match key {
                    Value::String(k) => k.clone(),
                    other => other.to_string(),
                };
                return Err(NpyError::Key { text: text.trim_end().to_string(), key });
            }
        }
    }
    Ok(())
}

/// Writes a plane as a `.npy` of dtype `<f4` and shape `(height, width)` (format version 1.0,
/// the data aligned to 64 bytes, as numpy writes it).
pub fn write_npy_f32(path: &Path, plane: &PlaneF32) -> Result<(), CameraError> {
    let io = |e| CameraError::from(IoError::file(path, e));
    let f4: TypeStr = "<f4".parse().expect("'<f4' is a numpy type string");
    let shape = [plane.height as u64, plane.width as u64];
    let mut bytes = Vec::with_capacity(128 + 4 * plane.data.len());
    let mut writer = npyz::WriteOptions::<f32>::new().dtype(DType::new_scalar(f4)).shape(&shape).writer(&mut bytes).begin_nd().map_err(io)?;
    writer.extend(plane.data.iter().copied()).map_err(io)?;
    writer.finish().map_err(io)?;
    std::fs::write(path, bytes).map_err(io)
}

/// What this module needs of a header: npyz's dtype (as its type string), order and shape.
#[derive(Debug, PartialEq)]
struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<u64>,
}

impl Header {
    fn of(h: &NpyHeader) -> Header {
        let descr = match h.dtype() {
            DType::Plain(ty) => ty.to_string(),
            other => other.descr(),
        };
        Header { descr, fortran_order: h.order() == Order::Fortran, shape: h.shape().to_vec() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reads a header dict's text through npyz, framed as a version 1.0 file.
    fn parse_header(text: &str) -> Result<Header, NpyError> {
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend_from_slice(&(text.len() as u16).to_le_bytes());
        bytes.extend_from_slice(text.as_bytes());
        read_header(&bytes).map(|(h, _)| Header::of(&h))
    }

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
        // npyz writes the shape as numpy writes a tuple's repr in Python 2: `(2, 2, )`.
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (swap("<f4", "<f8"), "dtype \"<f8\" is not little-endian float32"),
            (swap("False", "True "), "Fortran-order"),
            (swap("(2, 2, )", "(4,)    "), "shape [4] is not 2-D"),
            (good[..good.len() - 1].to_vec(), "needs 16 bytes of data, found 15"),
            (b"PK\x03\x04".to_vec(), "magic"),
            (swap("'descr'", "'dtype'"), "unexpected or repeated key"),
        ];
        for (bytes, want) in cases {
            let e = parse_npy_f32(p, &bytes).unwrap_err().to_string();
            assert!(e.starts_with("x.npy: not a readable .npy array") && e.contains(want), "want {want:?}: {e}");
        }
    }

    #[test]
    fn header_keys_versions_and_lengths_are_checked() {
        // An extra key (npyz alone ignores it) and a repeated one (npyz alone keeps the last).
        let extra = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), 'extra': 1, }";
        let repeated = "{'descr': '<f8', 'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }";
        for (text, want) in [(extra, "extra"), (repeated, "descr")] {
            let e = parse_header(text).unwrap_err();
            assert!(matches!(&e, NpyError::Key { key, .. } if key == want), "{e}");
        }
        // A key missing: npyz's message, with the header.
        let e = parse_header("{'descr': '<f4', 'fortran_order': False}").unwrap_err();
        assert!(matches!(e, NpyError::Header { .. }) && e.to_string().contains("'shape'"), "{e}");
        // A header length past the end of the file.
        let mut cut = b"\x93NUMPY\x01\x00".to_vec();
        cut.extend_from_slice(&100u16.to_le_bytes());
        cut.extend_from_slice(b"{'descr': '<f4'");
        assert!(matches!(read_header(&cut), Err(NpyError::TruncatedHeader)));
        // Format version 2.0 (a 4-byte header length) reads like 1.0; version 4 is refused.
        let text = "{'descr': '<f4', 'fortran_order': False, 'shape': (1, 2), }\n";
        let mut v2 = b"\x93NUMPY\x02\x00".to_vec();
        v2.extend_from_slice(&(text.len() as u32).to_le_bytes());
        v2.extend_from_slice(text.as_bytes());
        v2.extend_from_slice(&1.5f32.to_le_bytes());
        v2.extend_from_slice(&(-2.0f32).to_le_bytes());
        assert_eq!(decode(&v2).unwrap(), PlaneF32 { width: 2, height: 1, data: vec![1.5, -2.0] });
        v2[6] = 4;
        assert!(matches!(decode(&v2), Err(NpyError::Preamble(_))));
    }
}
