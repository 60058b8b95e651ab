//! PNG reading and writing with the `png` crate.

use super::IoError;
use crate::{FrameImage, Image, ImageGray16, ImageGray8, ImageRgb8};
use std::io::{BufReader, BufWriter};
use std::path::Path;

struct Decoded {
    width: usize,
    height: usize,
    color: png::ColorType,
    bit_depth: png::BitDepth,
    bytes: Vec<u8>,
}

fn decode(path: &Path, transformations: png::Transformations) -> Result<Decoded, IoError> {
    let file = std::fs::File::open(path).map_err(|e| IoError::file(path, e))?;
    let mut decoder = png::Decoder::new(BufReader::new(file));
    decoder.set_transformations(transformations);
    let bad = |e: png::DecodingError| IoError::BadPng { path: path.to_path_buf(), reason: e.to_string() };
    let mut reader = decoder.read_info().map_err(bad)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| IoError::BadPng { path: path.to_path_buf(), reason: "image too large".into() })?;
    let mut bytes = vec![0u8; size];
    let info = reader.next_frame(&mut bytes).map_err(bad)?;
    bytes.truncate(info.buffer_size());
    Ok(Decoded { width: info.width as usize, height: info.height as usize, color: info.color_type, bit_depth: info.bit_depth, bytes })
}

/// Reads an 8-bit image as delivered: colour (alpha dropped, palettes expanded) or grey;
/// 16-bit images are reduced to their high byte.
pub fn read_image(path: &Path) -> Result<FrameImage, IoError> {
    let d = decode(path, png::Transformations::EXPAND | png::Transformations::STRIP_16)?;
    let n = d.width * d.height;
    let unsupported = |what: String| IoError::UnsupportedImage { path: path.to_path_buf(), what };
    if d.bit_depth != png::BitDepth::Eight {
        return Err(unsupported(format!("bit depth {:?} after expansion", d.bit_depth)));
    }
    match d.color {
        png::ColorType::Rgb => Ok(FrameImage::Rgb8(Image { width: d.width, height: d.height, data: d.bytes })),
        png::ColorType::Rgba => {
            let data = d.bytes.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect::<Vec<_>>();
            Ok(FrameImage::Rgb8(Image { width: d.width, height: d.height, data }))
        }
        png::ColorType::Grayscale => Ok(FrameImage::Gray8(Image { width: d.width, height: d.height, data: d.bytes })),
        png::ColorType::GrayscaleAlpha => {
            let data = d.bytes.chunks_exact(2).map(|p| p[0]).collect::<Vec<_>>();
            debug_assert_eq!(data.len(), n);
            Ok(FrameImage::Gray8(Image { width: d.width, height: d.height, data }))
        }
        other => Err(unsupported(format!("colour type {other:?}"))),
    }
}

/// Reads a single-channel 16-bit PNG (e.g. TUM depth, metres x 5000).
pub fn read_gray16(path: &Path) -> Result<ImageGray16, IoError> {
    let d = decode(path, png::Transformations::IDENTITY)?;
    if d.color != png::ColorType::Grayscale || d.bit_depth != png::BitDepth::Sixteen {
        return Err(IoError::UnsupportedImage {
            path: path.to_path_buf(),
            what: format!("expected 16-bit grey, found {:?} {:?}", d.color, d.bit_depth),
        });
    }
    let data = d.bytes.chunks_exact(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();
    Ok(Image { width: d.width, height: d.height, data })
}

fn encode(path: &Path, width: usize, height: usize, color: png::ColorType, depth: png::BitDepth, bytes: &[u8]) -> Result<(), IoError> {
    let file = std::fs::File::create(path).map_err(|e| IoError::file(path, e))?;
    let mut enc = png::Encoder::new(BufWriter::new(file), width as u32, height as u32);
    enc.set_color(color);
    enc.set_depth(depth);
    // Fast compression: the generator writes thousands of frames.
    enc.set_compression(png::Compression::Fast);
    let err = |e: png::EncodingError| IoError::invalid(path, format!("PNG encoding failed: {e}"));
    let mut writer = enc.write_header().map_err(err)?;
    writer.write_image_data(bytes).map_err(err)?;
    writer.finish().map_err(err)
}

pub fn write_rgb8(path: &Path, img: &ImageRgb8) -> Result<(), IoError> {
    encode(path, img.width, img.height, png::ColorType::Rgb, png::BitDepth::Eight, &img.data)
}

pub fn write_gray8(path: &Path, img: &ImageGray8) -> Result<(), IoError> {
    encode(path, img.width, img.height, png::ColorType::Grayscale, png::BitDepth::Eight, &img.data)
}

pub fn write_gray16(path: &Path, img: &ImageGray16) -> Result<(), IoError> {
    let bytes: Vec<u8> = img.data.iter().flat_map(|v| v.to_be_bytes()).collect();
    encode(path, img.width, img.height, png::ColorType::Grayscale, png::BitDepth::Sixteen, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_rgb_grey_and_depth() {
        let dir = tempfile::tempdir().unwrap();
        let rgb = ImageRgb8 { width: 3, height: 2, data: (0..18).map(|v| (v * 13) as u8).collect() };
        let p = dir.path().join("c.png");
        write_rgb8(&p, &rgb).unwrap();
        assert_eq!(read_image(&p).unwrap(), FrameImage::Rgb8(rgb));
        let grey = ImageGray8 { width: 2, height: 2, data: vec![0, 1, 254, 255] };
        write_gray8(&p, &grey).unwrap();
        assert_eq!(read_image(&p).unwrap(), FrameImage::Gray8(grey));
        let depth = ImageGray16 { width: 2, height: 1, data: vec![5000, 65535] };
        write_gray16(&p, &depth).unwrap();
        assert_eq!(read_gray16(&p).unwrap(), depth);
        assert!(matches!(read_image(&p), Err(IoError::UnsupportedImage { .. }) | Ok(FrameImage::Gray8(_))));
    }

    #[test]
    fn garbage_is_a_named_error() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("broken.png");
        std::fs::write(&p, b"\x89PNG\r\n\x1a\nnot really").unwrap();
        let e = read_image(&p).unwrap_err();
        assert!(matches!(e, IoError::BadPng { .. }));
        assert!(e.to_string().contains("broken.png"), "{e}");
        let missing = read_image(&dir.path().join("nope.png")).unwrap_err();
        assert!(missing.to_string().contains("nope.png"));
    }
}
