//! Pixel-format conversion of raw camera buffers (V4L2, Aravis) into our frame images.
//!
//! Every conversion writes into a caller-owned image that is reused from frame to frame, so
//! the raw layouts (YUYV, GREY, RGB24, Bayer RG8) convert without allocating once the image
//! has its size. A buffer that does not hold a whole frame is an error, never a panic: the
//! caller drops the frame and counts it. MJPEG goes through `zune-jpeg` (pure Rust), whose
//! decoder allocates its own working memory per frame.

use duv_core::{ImageGray8, ImageRgb8};

/// A raw layout a camera delivers, as named in driver buffers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RawFormat {
    /// Packed 4:2:2 `Y0 U Y1 V`, BT.601 limited range (the V4L2 default for YUYV).
    Yuyv,
    /// 8-bit grey.
    Grey,
    /// 8-bit R, G, B interleaved.
    Rgb24,
    /// 8-bit Bayer mosaic, first row `R G R G`, second row `G B G B`.
    BayerRg8,
    /// Motion JPEG: one baseline JPEG per frame (UVC cameras often omit the Huffman tables).
    Mjpeg,
}

impl RawFormat {
    pub fn name(self) -> &'static str {
        match self {
            RawFormat::Yuyv => "YUYV",
            RawFormat::Grey => "GREY",
            RawFormat::Rgb24 => "RGB24",
            RawFormat::BayerRg8 => "BayerRG8",
            RawFormat::Mjpeg => "MJPEG",
        }
    }

    /// Bytes per pixel of a raw layout (`None` for compressed MJPEG).
    pub fn bytes_per_pixel(self) -> Option<usize> {
        match self {
            RawFormat::Yuyv => Some(2),
            RawFormat::Grey | RawFormat::BayerRg8 => Some(1),
            RawFormat::Rgb24 => Some(3),
            RawFormat::Mjpeg => None,
        }
    }

    /// True when frames of this format become grey images ([`ImageGray8`]).
    pub fn is_grey(self) -> bool {
        self == RawFormat::Grey
    }
}

/// Why a camera buffer could not be converted. The frame is dropped, the stream continues.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PixelError {
    /// The buffer is shorter than `height` rows of `stride_bytes` (the last row only needs
    /// its pixels).
    #[error("{format} buffer of {got} bytes is too short for {width}x{height} (stride {stride_bytes}): needs {needed}")]
    Size { format: &'static str, width: usize, height: usize, stride_bytes: usize, got: usize, needed: usize },
    /// The stride is smaller than one row of pixels.
    #[error("{format}: stride {stride_bytes} bytes is shorter than a row of {width} pixels")]
    Stride { format: &'static str, width: usize, stride_bytes: usize },
    /// YUYV and Bayer layouts need an even width (and Bayer an even height).
    #[error("{format}: {width}x{height} must have even dimensions")]
    OddSize { format: &'static str, width: usize, height: usize },
    /// The JPEG does not end with an EOI marker: the transfer was cut short.
    #[error("MJPEG frame of {got} bytes is truncated (no end-of-image marker)")]
    TruncatedJpeg { got: usize },
    #[error("MJPEG frame does not decode: {problem}")]
    Jpeg { problem: String },
    #[error("MJPEG frame is {width}x{height}, the stream was configured for {expected_width}x{expected_height}")]
    JpegSize { width: usize, height: usize, expected_width: usize, expected_height: usize },
    /// A grey format was converted into a colour image or the reverse.
    #[error("{format} cannot be converted into a {target} image")]
    Target { format: &'static str, target: &'static str },
}

/// Checks that `src` holds `height` rows of `stride_bytes` with `row_bytes` of pixels each.
fn check_layout(format: RawFormat, src: &[u8], width: usize, height: usize, stride_bytes: usize) -> Result<(), PixelError> {
    let row_bytes = width * format.bytes_per_pixel().unwrap_or(0);
    let name = format.name();
    if stride_bytes < row_bytes {
        return Err(PixelError::Stride { format: name, width, stride_bytes });
    }
    let needed = if height == 0 { 0 } else { (height - 1) * stride_bytes + row_bytes };
    if src.len() < needed {
        return Err(PixelError::Size { format: name, width, height, stride_bytes, got: src.len(), needed });
    }
    Ok(())
}

/// Resizes `dst` to `width x height` (allocates only when the pixel count grows).
fn fit<const C: usize>(dst: &mut duv_core::Image<u8, C>, width: usize, height: usize) {
    dst.width = width;
    dst.height = height;
    dst.data.resize(width * height * C, 0);
}

#[inline]
fn clamp_u8(v: i32) -> u8 {
    v.clamp(0, 255) as u8
}

/// BT.601 limited-range YCbCr to RGB in 8.8 fixed point (the usual integer form).
#[inline]
pub fn ycbcr601_to_rgb(y: u8, cb: u8, cr: u8) -> [u8; 3] {
    let c = 298 * (y as i32 - 16);
    let d = cb as i32 - 128;
    let e = cr as i32 - 128;
    [
        clamp_u8((c + 409 * e + 128) >> 8),
        clamp_u8((c - 100 * d - 208 * e + 128) >> 8),
        clamp_u8((c + 516 * d + 128) >> 8),
    ]
}

/// YUYV (`Y0 Cb Y1 Cr` per pixel pair) to RGB.
pub fn yuyv_to_rgb8(src: &[u8], width: usize, height: usize, stride_bytes: usize, dst: &mut ImageRgb8) -> Result<(), PixelError> {
    if !width.is_multiple_of(2) {
        return Err(PixelError::OddSize { format: "YUYV", width, height });
    }
    check_layout(RawFormat::Yuyv, src, width, height, stride_bytes)?;
    fit(dst, width, height);
    for y in 0..height {
        let row = &src[y * stride_bytes..y * stride_bytes + width * 2];
        let out = &mut dst.data[y * width * 3..(y + 1) * width * 3];
        for (quad, px) in row.chunks_exact(4).zip(out.chunks_exact_mut(6)) {
            let (y0, cb, y1, cr) = (quad[0], quad[1], quad[2], quad[3]);
            px[..3].copy_from_slice(&ycbcr601_to_rgb(y0, cb, cr));
            px[3..].copy_from_slice(&ycbcr601_to_rgb(y1, cb, cr));
        }
    }
    Ok(())
}

/// 8-bit grey rows (with stride) into a grey image.
pub fn grey_to_gray8(src: &[u8], width: usize, height: usize, stride_bytes: usize, dst: &mut ImageGray8) -> Result<(), PixelError> {
    check_layout(RawFormat::Grey, src, width, height, stride_bytes)?;
    fit(dst, width, height);
    for y in 0..height {
        dst.data[y * width..(y + 1) * width].copy_from_slice(&src[y * stride_bytes..y * stride_bytes + width]);
    }
    Ok(())
}

/// Packed RGB24 rows (with stride) into an RGB image.
pub fn rgb24_to_rgb8(src: &[u8], width: usize, height: usize, stride_bytes: usize, dst: &mut ImageRgb8) -> Result<(), PixelError> {
    check_layout(RawFormat::Rgb24, src, width, height, stride_bytes)?;
    fit(dst, width, height);
    let row_bytes = width * 3;
    for y in 0..height {
        dst.data[y * row_bytes..(y + 1) * row_bytes].copy_from_slice(&src[y * stride_bytes..y * stride_bytes + row_bytes]);
    }
    Ok(())
}

/// Bayer RG8 to RGB, one colour per 2x2 cell: every pixel of a cell gets the cell's R, the
/// mean of its two G and its B. Colour at half resolution, no interpolation across cells
/// (no zipper artefacts at edges, which matter more to dense flow than colour resolution).
pub fn bayer_rg8_to_rgb8(src: &[u8], width: usize, height: usize, stride_bytes: usize, dst: &mut ImageRgb8) -> Result<(), PixelError> {
    if !width.is_multiple_of(2) || !height.is_multiple_of(2) {
        return Err(PixelError::OddSize { format: "BayerRG8", width, height });
    }
    check_layout(RawFormat::BayerRg8, src, width, height, stride_bytes)?;
    fit(dst, width, height);
    for cy in 0..height / 2 {
        let top = &src[2 * cy * stride_bytes..];
        let bottom = &src[(2 * cy + 1) * stride_bytes..];
        for cx in 0..width / 2 {
            let r = top[2 * cx];
            let g = (top[2 * cx + 1] as u16 + bottom[2 * cx] as u16).div_ceil(2) as u8;
            let b = bottom[2 * cx + 1];
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let i = ((2 * cy + dy) * width + 2 * cx + dx) * 3;
                dst.data[i..i + 3].copy_from_slice(&[r, g, b]);
            }
        }
    }
    Ok(())
}

/// Decodes one MJPEG frame into `dst`, which must come out `width x height`.
///
/// A frame whose data does not end with the EOI marker (`FF D9`, trailing zero padding
/// allowed) is refused as truncated before decoding: decoders otherwise fill a cut-off frame
/// with grey and report success.
pub fn mjpeg_to_rgb8(src: &[u8], width: usize, height: usize, dst: &mut ImageRgb8) -> Result<(), PixelError> {
    let end = src.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
    let data = &src[..end];
    if data.len() < 4 || data[data.len() - 2..] != [0xFF, 0xD9] || data[..2] != [0xFF, 0xD8] {
        return Err(PixelError::TruncatedJpeg { got: src.len() });
    }
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    // UVC cameras leave out the Huffman tables (the MJPEG convention: the standard tables of
    // JPEG Annex K apply). The decoder applies them when an `AVI1` APP0 segment says the data
    // is MJPEG, so a frame without tables gets that segment in front.
    let patched: Vec<u8>;
    let data = if has_huffman_tables(data) {
        data
    } else {
        const AVI1_APP0: [u8; 9] = [0xFF, 0xE0, 0x00, 0x07, b'A', b'V', b'I', b'1', 0x00];
        patched = [&data[..2], &AVI1_APP0[..], &data[2..]].concat();
        &patched
    };
    let options = DecoderOptions::new_safe().jpeg_set_out_colorspace(ColorSpace::RGB).set_strict_mode(true);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(data, options);
    decoder.decode_headers().map_err(|e| PixelError::Jpeg { problem: format!("{e:?}") })?;
    let (w, h) = decoder.dimensions().unwrap_or((0, 0));
    if w != width || h != height {
        return Err(PixelError::JpegSize { width: w, height: h, expected_width: width, expected_height: height });
    }
    fit(dst, width, height);
    decoder.decode_into(&mut dst.data).map_err(|e| PixelError::Jpeg { problem: format!("{e:?}") })?;
    Ok(())
}

/// True when a DHT segment (`FF C4`) comes before the first start of scan (`FF DA`).
fn has_huffman_tables(jpeg: &[u8]) -> bool {
    let mut i = 2;
    while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
        match jpeg[i + 1] {
            0xFF => i += 1, // fill byte
            0xC4 => return true,
            0xDA => return false,
            _ => i += 2 + u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]) as usize,
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    /// RGB -> BT.601 limited-range YCbCr (the inverse of [`ycbcr601_to_rgb`]), for test input.
    fn rgb_to_ycbcr601(rgb: [u8; 3]) -> [u8; 3] {
        let [r, g, b] = rgb.map(|v| v as f64);
        let y = 16.0 + (65.738 * r + 129.057 * g + 25.064 * b) / 256.0;
        let cb = 128.0 + (-37.945 * r - 74.494 * g + 112.439 * b) / 256.0;
        let cr = 128.0 + (112.439 * r - 94.154 * g - 18.285 * b) / 256.0;
        [y, cb, cr].map(|v| v.round().clamp(0.0, 255.0) as u8)
    }

    #[test]
    fn ycbcr_reference_colours() {
        // Limited range: Y 16 is black, 235 white; (81, 90, 240) is pure red.
        assert_eq!(ycbcr601_to_rgb(16, 128, 128), [0, 0, 0]);
        assert_eq!(ycbcr601_to_rgb(235, 128, 128), [255, 255, 255]);
        assert_eq!(ycbcr601_to_rgb(126, 128, 128), [128, 128, 128]);
        let red = ycbcr601_to_rgb(81, 90, 240);
        assert!(red[0] >= 253 && red[1] <= 2 && red[2] <= 2, "{red:?}");
        // Round trip through the forward transform within 2 levels over a colour grid.
        for r in (0..=255).step_by(51) {
            for g in (0..=255).step_by(51) {
                for b in (0..=255).step_by(51) {
                    let [y, cb, cr] = rgb_to_ycbcr601([r as u8, g as u8, b as u8]);
                    let back = ycbcr601_to_rgb(y, cb, cr);
                    for (c, want) in back.iter().zip([r, g, b]) {
                        assert!((*c as i32 - want).abs() <= 2, "rgb {r},{g},{b} -> {back:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn yuyv_with_padding_stride() {
        // 4x2 image, stride 12 bytes (8 of pixels + 4 padding filled with garbage).
        let (w, h, stride) = (4, 2, 12);
        let pairs = [[235u8, 128, 16, 128], [81, 90, 81, 240], [126, 128, 126, 128], [16, 128, 235, 128]];
        let mut src = vec![0xAAu8; stride * h];
        for (i, q) in pairs.iter().enumerate() {
            let (row, col) = (i / 2, i % 2);
            src[row * stride + col * 4..row * stride + col * 4 + 4].copy_from_slice(q);
        }
        let mut dst = ImageRgb8::new(0, 0);
        yuyv_to_rgb8(&src, w, h, stride, &mut dst).unwrap();
        assert_eq!((dst.width, dst.height), (4, 2));
        assert_eq!(dst.pixel(0, 0), [255, 255, 255]);
        assert_eq!(dst.pixel(1, 0), [0, 0, 0]);
        // Second pair shares Cb=90, Cr=240 (red chroma) at Y=81: both pixels red.
        assert!(dst.pixel(2, 0)[0] > 250 && dst.pixel(3, 0)[1] < 3);
        assert_eq!(dst.pixel(0, 1), [128, 128, 128]);
        assert_eq!(dst.pixel(3, 1), [255, 255, 255]);
        // Wrong sizes are errors: truncated buffer, odd width, stride below a row.
        assert!(matches!(yuyv_to_rgb8(&src[..stride + 7], w, h, stride, &mut dst), Err(PixelError::Size { needed: 20, got: 19, .. })));
        assert!(matches!(yuyv_to_rgb8(&src, 3, 2, stride, &mut dst), Err(PixelError::OddSize { .. })));
        assert!(matches!(yuyv_to_rgb8(&src, w, h, 6, &mut dst), Err(PixelError::Stride { .. })));
        // The last row needs only its pixels, not the padding.
        assert!(yuyv_to_rgb8(&src[..stride + 8], w, h, stride, &mut dst).is_ok());
    }

    #[test]
    fn grey_and_rgb24_copy_rows_without_padding() {
        let src: Vec<u8> = (0..15).collect(); // 3 rows of stride 5, 4 pixels each
        let mut g = ImageGray8::new(0, 0);
        grey_to_gray8(&src, 4, 3, 5, &mut g).unwrap();
        assert_eq!(g.data, vec![0, 1, 2, 3, 5, 6, 7, 8, 10, 11, 12, 13]);
        assert!(matches!(grey_to_gray8(&src[..13], 4, 3, 5, &mut g), Err(PixelError::Size { needed: 14, .. })));

        let src: Vec<u8> = (0..14).collect(); // 2 rows of stride 7, 2 RGB pixels each
        let mut c = ImageRgb8::new(0, 0);
        rgb24_to_rgb8(&src, 2, 2, 7, &mut c).unwrap();
        assert_eq!(c.data, vec![0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 12]);
        assert!(rgb24_to_rgb8(&src, 3, 2, 7, &mut c).is_err());
    }

    #[test]
    fn bayer_cells_take_their_own_colour() {
        // 4x2 mosaic: cell 0 R=200 G=100,50 B=10; cell 1 R=0 G=255,255 B=255.
        let src = [200u8, 100, 0, 255, 50, 10, 255, 255];
        let mut c = ImageRgb8::new(0, 0);
        bayer_rg8_to_rgb8(&src, 4, 2, 4, &mut c).unwrap();
        for (x, y) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            assert_eq!(c.pixel(x, y), [200, 75, 10]);
        }
        for (x, y) in [(2, 0), (3, 0), (2, 1), (3, 1)] {
            assert_eq!(c.pixel(x, y), [0, 255, 255]);
        }
        assert!(matches!(bayer_rg8_to_rgb8(&src, 4, 3, 4, &mut c), Err(PixelError::OddSize { .. })));
        assert!(matches!(bayer_rg8_to_rgb8(&src[..7], 4, 2, 4, &mut c), Err(PixelError::Size { .. })));
    }

    /// 32x16 test JPEGs (written with Pillow): bars red, green, blue, white over black,
    /// grey 128, yellow, cyan, 8 pixels wide each.
    const BARS_444: &[u8] = include_bytes!("../../../tests/fixtures/camera/bars_32x16.jpg");
    const BARS_422: &[u8] = include_bytes!("../../../tests/fixtures/camera/bars_422.jpg");
    /// `BARS_422` with its Huffman tables removed, as UVC cameras send MJPEG.
    const BARS_422_NO_DHT: &[u8] = include_bytes!("../../../tests/fixtures/camera/bars_422_no_dht.jpg");

    fn assert_bars(img: &ImageRgb8, tolerance: i32) {
        let top = [[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]];
        let bottom = [[0, 0, 0], [128, 128, 128], [255, 255, 0], [0, 255, 255]];
        for (bar, (t, b)) in top.iter().zip(bottom.iter()).enumerate() {
            // Bar centres, away from the chroma blur at bar edges.
            for (y, want) in [(3, t), (12, b)] {
                let got = img.pixel(bar * 8 + 4, y);
                for c in 0..3 {
                    assert!((got[c] as i32 - want[c]).abs() <= tolerance, "bar {bar} y {y}: {got:?} vs {want:?}");
                }
            }
        }
    }

    #[test]
    fn mjpeg_decodes_with_and_without_huffman_tables() {
        let mut img = ImageRgb8::new(0, 0);
        mjpeg_to_rgb8(BARS_444, 32, 16, &mut img).unwrap();
        assert_eq!((img.width, img.height), (32, 16));
        assert_bars(&img, 6);
        mjpeg_to_rgb8(BARS_422, 32, 16, &mut img).unwrap();
        assert_bars(&img, 12);
        let mut no_dht = ImageRgb8::new(0, 0);
        assert!(has_huffman_tables(BARS_422) && !has_huffman_tables(BARS_422_NO_DHT));
        mjpeg_to_rgb8(BARS_422_NO_DHT, 32, 16, &mut no_dht).unwrap();
        // The default tables are the ones the encoder used: the same pixels.
        assert_eq!(no_dht, img);
        // Zero padding after the EOI marker (drivers round buffers up) is accepted.
        let mut padded = BARS_444.to_vec();
        padded.extend_from_slice(&[0; 100]);
        mjpeg_to_rgb8(&padded, 32, 16, &mut img).unwrap();
        assert_bars(&img, 6);
    }

    #[test]
    fn corrupt_mjpeg_is_an_error_not_a_panic() {
        let mut img = ImageRgb8::new(0, 0);
        // Cut at every length: each one is refused, none panics.
        for cut in 0..BARS_444.len() - 1 {
            let r = mjpeg_to_rgb8(&BARS_444[..cut], 32, 16, &mut img);
            assert!(r.is_err(), "a JPEG cut at {cut} bytes decoded");
        }
        assert!(matches!(mjpeg_to_rgb8(&BARS_444[..400], 32, 16, &mut img), Err(PixelError::TruncatedJpeg { got: 400 })));
        // Wrong size for the stream.
        assert!(matches!(mjpeg_to_rgb8(BARS_444, 64, 16, &mut img), Err(PixelError::JpegSize { width: 32, height: 16, .. })));
        // Garbage with valid start and end markers, and scan data overwritten with noise.
        let garbage = [0xFF, 0xD8, 1, 2, 3, 4, 5, 0xFF, 0xD9];
        assert!(mjpeg_to_rgb8(&garbage, 32, 16, &mut img).is_err());
        let mut noisy = BARS_444.to_vec();
        let n = noisy.len();
        for (i, b) in noisy[n / 2..n - 2].iter_mut().enumerate() {
            *b = (i * 37 % 251) as u8;
        }
        let _ = mjpeg_to_rgb8(&noisy, 32, 16, &mut img); // may decode to noise; must not panic
    }
}
