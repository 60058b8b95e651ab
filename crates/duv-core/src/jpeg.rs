//! Baseline JPEG encoding of frames (ITU T.81, JFIF), allocation-free: the logging thread of a
//! board that logs JPEG (`[log] frame_encoding = "jpeg"`) encodes every input frame, and the
//! live view its downscaled camera, so the encoder works MCU by MCU straight from the frame's
//! pixels into the caller's reused output buffer, with its quantisation and Huffman tables
//! built once per quality.
//!
//! Colour frames are YCbCr, 4:4:4 from quality 90 up (colour-true frames for offshore
//! refinement: chroma edges stay sharp) and 4:2:0 below (16x16 MCUs: four luma blocks, one
//! Cb, one Cr, chroma the mean of each 2x2); grey frames one component; the quantisation tables are the Annex K
//! tables scaled by quality as libjpeg does, the Huffman tables the Annex K typical tables.
//! Edges are padded by repeating the last row and column.
//!
//! Hand-written because no crate met the onboard constraint: the `jpeg-encoder` crate (with
//! its AVX2 code) encoded a 640x480 frame in 6.2 ms against 7.2 ms here, but allocated per
//! frame, and the logging thread must not allocate once warm (`tests/pipeline_alloc.rs`);
//! `zune-jpeg` decodes the logged frames.

/// Why a frame cannot be encoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum JpegError {
    #[error("quality {0} is outside 1..=100")]
    Quality(u8),
    #[error("{width}x{height} is outside the JPEG limits (1..=65535 each)")]
    Size { width: usize, height: usize },
    #[error("{got} pixel bytes for a {width}x{height} image with {channels} channel(s)")]
    Pixels { got: usize, width: usize, height: usize, channels: usize },
}

/// Annex K.1 luminance quantisation table, in natural (row-major) order.
const LUMA_QUANT: [u16; 64] = [
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55, 14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51, 87, 80, 62, 18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104,
    113, 92, 49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99,
];
/// Annex K.1 chrominance quantisation table, natural order.
const CHROMA_QUANT: [u16; 64] = [
    17, 18, 24, 47, 99, 99, 99, 99, 18, 21, 26, 66, 99, 99, 99, 99, 24, 26, 56, 99, 99, 99, 99, 99, 47, 66, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
    99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99, 99,
];
/// Zig-zag scan: the natural index of the k-th coefficient.
const ZIGZAG: [usize; 64] = [
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5, 12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14, 21, 28, 35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51, 58, 59,
    52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
];

// Annex K.3 typical Huffman tables: code counts per length 1..=16, then the symbols.
const DC_LUMA_BITS: [u8; 16] = [0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0];
const DC_LUMA_VALS: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
const DC_CHROMA_BITS: [u8; 16] = [0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0];
const DC_CHROMA_VALS: [u8; 12] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
const AC_LUMA_BITS: [u8; 16] = [0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7d];
const AC_LUMA_VALS: [u8; 162] = [
    0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61, 0x07, 0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xa1, 0x08, 0x23, 0x42, 0xb1, 0xc1, 0x15, 0x52, 0xd1,
    0xf0, 0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0a, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x25, 0x26, 0x27, 0x28, 0x29, 0x2a, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45, 0x46, 0x47,
    0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x83, 0x84, 0x85, 0x86,
    0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba,
    0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe1, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8, 0xe9, 0xea, 0xf1, 0xf2, 0xf3,
    0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
];
const AC_CHROMA_BITS: [u8; 16] = [0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77];
const AC_CHROMA_VALS: [u8; 162] = [
    0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61, 0x71, 0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xa1, 0xb1, 0xc1, 0x09, 0x23, 0x33, 0x52,
    0xf0, 0x15, 0x62, 0x72, 0xd1, 0x0a, 0x16, 0x24, 0x34, 0xe1, 0x25, 0xf1, 0x17, 0x18, 0x19, 0x1a, 0x26, 0x27, 0x28, 0x29, 0x2a, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45, 0x46,
    0x47, 0x48, 0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x82, 0x83, 0x84,
    0x85, 0x86, 0x87, 0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6, 0xb7, 0xb8,
    0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8, 0xe9, 0xea, 0xf2, 0xf3,
    0xf4, 0xf5, 0xf6, 0xf7, 0xf8, 0xf9, 0xfa,
];

/// Output scale of the AAN factorisation per frequency: 1, then sqrt(2) cos(k pi / 16).
const AAN_SCALE: [f64; 8] = [1.0, 1.387_039_845, 1.306_562_965, 1.175_875_602, 1.0, 0.785_694_958, 0.541_196_100, 0.275_899_379];

/// One 8-point forward DCT of the Arai-Agui-Nakajima factorisation (5 multiplications) on
/// `d[0], d[step], ..., d[7 step]`, in place; output k is the DCT-II coefficient times
/// `AAN_SCALE[k]` (and the JPEG normalisation left to the quantiser).
#[inline]
fn aan_8(d: &mut [f32; 64], at: usize, step: usize) {
    let i = |k: usize| at + k * step;
    let (t0, t7) = (d[i(0)] + d[i(7)], d[i(0)] - d[i(7)]);
    let (t1, t6) = (d[i(1)] + d[i(6)], d[i(1)] - d[i(6)]);
    let (t2, t5) = (d[i(2)] + d[i(5)], d[i(2)] - d[i(5)]);
    let (t3, t4) = (d[i(3)] + d[i(4)], d[i(3)] - d[i(4)]);
    // Even part.
    let (t10, t13, t11, t12) = (t0 + t3, t0 - t3, t1 + t2, t1 - t2);
    d[i(0)] = t10 + t11;
    d[i(4)] = t10 - t11;
    let z1 = (t12 + t13) * std::f32::consts::FRAC_1_SQRT_2;
    d[i(2)] = t13 + z1;
    d[i(6)] = t13 - z1;
    // Odd part.
    let (t10, t11, t12) = (t4 + t5, t5 + t6, t6 + t7);
    let z5 = (t10 - t12) * 0.382_683_43;
    let z2 = 0.541_196_1 * t10 + z5;
    let z4 = 1.306_563 * t12 + z5;
    let z3 = t11 * std::f32::consts::FRAC_1_SQRT_2;
    let (z11, z13) = (t7 + z3, t7 - z3);
    d[i(5)] = z13 + z2;
    d[i(3)] = z13 - z2;
    d[i(1)] = z11 + z4;
    d[i(7)] = z11 - z4;
}

/// 2-D forward DCT of a level-shifted block (rows, then columns), outputs scaled as
/// [`aan_8`] says in each direction.
fn fdct_aan(block: &mut [f32; 64]) {
    for y in 0..8 {
        aan_8(block, y * 8, 1);
    }
    for x in 0..8 {
        aan_8(block, x, 8);
    }
}

/// A Huffman table as (code, length) per symbol.
#[derive(Clone, Copy)]
struct HuffCodes {
    code: [u16; 256],
    len: [u8; 256],
}

impl HuffCodes {
    /// The canonical codes of Annex C from code counts per length and symbols.
    fn new(bits: &[u8; 16], vals: &[u8]) -> Self {
        let mut t = HuffCodes { code: [0; 256], len: [0; 256] };
        let mut code: u16 = 0;
        let mut k = 0;
        for (l, &n) in bits.iter().enumerate() {
            for _ in 0..n {
                t.code[vals[k] as usize] = code;
                t.len[vals[k] as usize] = l as u8 + 1;
                code += 1;
                k += 1;
            }
            code <<= 1;
        }
        t
    }
}

/// Entropy-coded bits with 0xFF byte stuffing.
struct BitWriter<'a> {
    out: &'a mut Vec<u8>,
    acc: u32,
    n: u32,
}

impl BitWriter<'_> {
    #[inline]
    fn put(&mut self, bits: u32, len: u32) {
        if len == 0 {
            return;
        }
        self.acc = (self.acc << len) | (bits & ((1u32 << len) - 1));
        self.n += len;
        while self.n >= 8 {
            let b = (self.acc >> (self.n - 8)) as u8;
            self.out.push(b);
            if b == 0xFF {
                self.out.push(0);
            }
            self.n -= 8;
        }
        self.acc &= (1u32 << self.n).wrapping_sub(1);
    }

    /// Pads the last byte with 1 bits.
    fn finish(&mut self) {
        if self.n > 0 {
            let pad = 8 - self.n;
            self.put((1 << pad) - 1, pad);
        }
    }
}

/// Bit length of |v| (the JPEG magnitude category) and the bits that code v.
#[inline]
fn magnitude(v: i32) -> (u32, u32) {
    let a = v.unsigned_abs();
    let cat = 32 - a.leading_zeros();
    let bits = if v < 0 { (v - 1) as u32 } else { v as u32 };
    (cat, bits)
}

/// The baseline JPEG encoder: tables for one quality, built once.
pub struct JpegEncoder {
    quality: u8,
    /// Quantisation tables (luma, chroma) in natural order, as written.
    quant: [[u16; 64]; 2],
    /// 1 / quantiser, folded with the scale of [`fdct_aan`]'s outputs, natural order.
    inv_quant: [[f32; 64]; 2],
    dc: [HuffCodes; 2],
    ac: [HuffCodes; 2],
}

impl JpegEncoder {
    pub fn new(quality: u8) -> Result<Self, JpegError> {
        if !(1..=100).contains(&quality) {
            return Err(JpegError::Quality(quality));
        }
        let q = quality as u32;
        let scale = if q < 50 { 5000 / q } else { 200 - 2 * q };
        let scaled = |base: &[u16; 64]| base.map(|b| ((b as u32 * scale + 50) / 100).clamp(1, 255) as u16);
        let quant = [scaled(&LUMA_QUANT), scaled(&CHROMA_QUANT)];
        let inv_quant = quant.map(|t| {
            let mut inv = [0f32; 64];
            for (k, v) in inv.iter_mut().enumerate() {
                *v = (1.0 / (t[k] as f64 * 8.0 * AAN_SCALE[k / 8] * AAN_SCALE[k % 8])) as f32;
            }
            inv
        });
        Ok(JpegEncoder {
            quality,
            quant,
            inv_quant,
            dc: [HuffCodes::new(&DC_LUMA_BITS, &DC_LUMA_VALS), HuffCodes::new(&DC_CHROMA_BITS, &DC_CHROMA_VALS)],
            ac: [HuffCodes::new(&AC_LUMA_BITS, &AC_LUMA_VALS), HuffCodes::new(&AC_CHROMA_BITS, &AC_CHROMA_VALS)],
        })
    }

    pub fn quality(&self) -> u8 {
        self.quality
    }

    /// Whether colour frames are 4:2:0 (below quality 90) rather than 4:4:4.
    pub fn subsample_chroma(&self) -> bool {
        self.quality < 90
    }

    /// Encodes interleaved 8-bit pixels (`channels` 3: RGB, 1: grey) into `out` (cleared
    /// first; its capacity is reused, so a warm buffer makes this allocation-free).
    pub fn encode(&self, pixels: &[u8], width: usize, height: usize, channels: usize, out: &mut Vec<u8>) -> Result<(), JpegError> {
        if width == 0 || height == 0 || width > 65535 || height > 65535 || !(channels == 1 || channels == 3) {
            return Err(JpegError::Size { width, height });
        }
        if pixels.len() != width * height * channels {
            return Err(JpegError::Pixels { got: pixels.len(), width, height, channels });
        }
        out.clear();
        self.write_headers(width, height, channels, out);
        let mut bw = BitWriter { out, acc: 0, n: 0 };
        let mut pred = [0i32; 3];
        // The first channel's byte of pixel (x, y), edges repeated.
        let at = |x: usize, y: usize| (y.min(height - 1) * width + x.min(width - 1)) * channels;
        let rgb = |i: usize| (pixels[i] as f32, pixels[i + 1] as f32, pixels[i + 2] as f32);
        let mut block = [0f32; 64];
        if channels == 1 {
            for by in (0..height).step_by(8) {
                for bx in (0..width).step_by(8) {
                    for y in 0..8 {
                        for x in 0..8 {
                            block[y * 8 + x] = pixels[at(bx + x, by + y)] as f32 - 128.0;
                        }
                    }
                    self.code_block(&mut block, 0, &mut pred[0], &mut bw);
                }
            }
        } else if self.subsample_chroma() {
            let ycc = |x: usize, y: usize| {
                let (r, g, b) = rgb(at(x, y));
                (0.299 * r + 0.587 * g + 0.114 * b, -0.168_736 * r - 0.331_264 * g + 0.5 * b, 0.5 * r - 0.418_688 * g - 0.081_312 * b)
            };
            let mut cb = [0f32; 64];
            let mut cr = [0f32; 64];
            for my in (0..height).step_by(16) {
                for mx in (0..width).step_by(16) {
                    cb.fill(0.0);
                    cr.fill(0.0);
                    for (oy, ox) in [(0, 0), (0, 8), (8, 0), (8, 8)] {
                        for y in 0..8 {
                            for x in 0..8 {
                                let (px, py) = (mx + ox + x, my + oy + y);
                                let (l, b, r) = ycc(px, py);
                                block[y * 8 + x] = l - 128.0;
                                let k = ((oy + y) / 2) * 8 + (ox + x) / 2;
                                cb[k] += 0.25 * b;
                                cr[k] += 0.25 * r;
                            }
                        }
                        self.code_block(&mut block, 0, &mut pred[0], &mut bw);
                    }
                    self.code_block(&mut cb, 1, &mut pred[1], &mut bw);
                    self.code_block(&mut cr, 1, &mut pred[2], &mut bw);
                }
            }
        } else {
            let mut cb = [0f32; 64];
            let mut cr = [0f32; 64];
            for by in (0..height).step_by(8) {
                for bx in (0..width).step_by(8) {
                    for y in 0..8 {
                        for x in 0..8 {
                            let (r, g, b) = rgb(at(bx + x, by + y));
                            block[y * 8 + x] = 0.299 * r + 0.587 * g + 0.114 * b - 128.0;
                            cb[y * 8 + x] = -0.168_736 * r - 0.331_264 * g + 0.5 * b;
                            cr[y * 8 + x] = 0.5 * r - 0.418_688 * g - 0.081_312 * b;
                        }
                    }
                    self.code_block(&mut block, 0, &mut pred[0], &mut bw);
                    self.code_block(&mut cb, 1, &mut pred[1], &mut bw);
                    self.code_block(&mut cr, 1, &mut pred[2], &mut bw);
                }
            }
        }
        bw.finish();
        out.extend_from_slice(&[0xFF, 0xD9]);
        Ok(())
    }

    /// DCT, quantisation and Huffman coding of one level-shifted block (`table` 0 luma, 1 chroma).
    fn code_block(&self, block: &mut [f32; 64], table: usize, pred: &mut i32, bw: &mut BitWriter<'_>) {
        fdct_aan(block);
        let mut q = [0i32; 64];
        for (k, v) in q.iter_mut().enumerate() {
            // Rounded half away from zero; `as` truncates (f32::round is a libm call here).
            let x = block[k] * self.inv_quant[table][k];
            *v = (x + 0.5f32.copysign(x)) as i32;
        }
        let (dc, ac) = (&self.dc[table], &self.ac[table]);
        let diff = q[0] - *pred;
        *pred = q[0];
        let (cat, bits) = magnitude(diff);
        bw.put(dc.code[cat as usize] as u32, dc.len[cat as usize] as u32);
        bw.put(bits, cat);
        let mut run = 0u32;
        for &n in &ZIGZAG[1..] {
            let v = q[n];
            if v == 0 {
                run += 1;
                continue;
            }
            while run >= 16 {
                bw.put(ac.code[0xF0] as u32, ac.len[0xF0] as u32);
                run -= 16;
            }
            let (cat, bits) = magnitude(v);
            let sym = ((run << 4) | cat) as usize;
            bw.put(ac.code[sym] as u32, ac.len[sym] as u32);
            bw.put(bits, cat);
            run = 0;
        }
        if run > 0 {
            bw.put(ac.code[0] as u32, ac.len[0] as u32);
        }
    }

    fn write_headers(&self, width: usize, height: usize, channels: usize, out: &mut Vec<u8>) {
        out.extend_from_slice(&[0xFF, 0xD8]);
        // JFIF APP0: version 1.1, no units, 1:1 density, no thumbnail.
        out.extend_from_slice(&[0xFF, 0xE0, 0, 16, b'J', b'F', b'I', b'F', 0, 1, 1, 0, 0, 1, 0, 1, 0, 0]);
        let tables = if channels == 3 { 2 } else { 1 };
        let len = 2 + 65 * tables;
        out.extend_from_slice(&[0xFF, 0xDB, (len >> 8) as u8, len as u8]);
        for (t, table) in self.quant.iter().enumerate().take(tables) {
            out.push(t as u8);
            for &n in &ZIGZAG {
                out.push(table[n] as u8);
            }
        }
        let len = 8 + 3 * channels;
        out.extend_from_slice(&[0xFF, 0xC0, (len >> 8) as u8, len as u8, 8, (height >> 8) as u8, height as u8, (width >> 8) as u8, width as u8, channels as u8]);
        if channels == 3 {
            let luma_sampling = if self.subsample_chroma() { 0x22 } else { 0x11 };
            out.extend_from_slice(&[1, luma_sampling, 0, 2, 0x11, 1, 3, 0x11, 1]);
        } else {
            out.extend_from_slice(&[1, 0x11, 0]);
        }
        let huff: [(u8, &[u8; 16], &[u8]); 4] = [(0x00, &DC_LUMA_BITS, &DC_LUMA_VALS), (0x10, &AC_LUMA_BITS, &AC_LUMA_VALS), (0x01, &DC_CHROMA_BITS, &DC_CHROMA_VALS), (0x11, &AC_CHROMA_BITS, &AC_CHROMA_VALS)];
        for (class_id, bits, vals) in huff.iter().take(2 * tables) {
            let len = 2 + 1 + 16 + vals.len();
            out.extend_from_slice(&[0xFF, 0xC4, (len >> 8) as u8, len as u8, *class_id]);
            out.extend_from_slice(*bits);
            out.extend_from_slice(vals);
        }
        let len = 6 + 2 * channels;
        out.extend_from_slice(&[0xFF, 0xDA, (len >> 8) as u8, len as u8, channels as u8]);
        if channels == 3 {
            out.extend_from_slice(&[1, 0x00, 2, 0x11, 3, 0x11]);
        } else {
            out.extend_from_slice(&[1, 0x00]);
        }
        out.extend_from_slice(&[0, 63, 0]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(bytes: &[u8]) -> (Vec<u8>, usize, usize) {
        let mut d = zune_jpeg::JpegDecoder::new(bytes);
        let px = d.decode().expect("our JPEG decodes");
        let (w, h) = d.dimensions().unwrap();
        (px, w, h)
    }

    fn psnr(a: &[u8], b: &[u8]) -> f64 {
        let mse = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / a.len() as f64;
        10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
    }

    /// A smooth colour field with some texture, sizes that are not multiples of 16.
    fn test_image(w: usize, h: usize) -> Vec<u8> {
        let mut v = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f32 / w as f32, y as f32 / h as f32);
                let t = ((x as f32 * 0.3).sin() * (y as f32 * 0.2).cos() * 20.0) as i32;
                v.push((40.0 + 150.0 * fx) as i32 as u8);
                v.push(((90.0 + 100.0 * fy) as i32 + t).clamp(0, 255) as u8);
                v.push((200.0 - 80.0 * fx * fy) as i32 as u8);
            }
        }
        v
    }

    #[test]
    fn colour_and_grey_frames_decode_close_to_the_input_at_any_size() {
        let mut out = Vec::new();
        for (w, h, q) in [(1, 1, 90), (17, 9, 90), (64, 48, 90), (100, 75, 90), (1, 1, 80), (17, 9, 80), (37, 23, 80), (100, 75, 80)] {
            let enc = JpegEncoder::new(q).unwrap();
            let img = test_image(w, h);
            enc.encode(&img, w, h, 3, &mut out).unwrap();
            assert_eq!(&out[..2], &[0xFF, 0xD8]);
            assert_eq!(&out[out.len() - 2..], &[0xFF, 0xD9]);
            let (px, dw, dh) = decode(&out);
            assert_eq!((dw, dh), (w, h));
            let p = psnr(&px, &img);
            assert!(p > 30.0, "{w}x{h} quality {q}: {p:.1} dB");
            let grey: Vec<u8> = img.chunks(3).map(|c| c[1]).collect();
            enc.encode(&grey, w, h, 1, &mut out).unwrap();
            let mut d = zune_jpeg::JpegDecoder::new_with_options(&out, zune_jpeg::zune_core::options::DecoderOptions::default().jpeg_set_out_colorspace(zune_jpeg::zune_core::colorspace::ColorSpace::Luma));
            let px = d.decode().unwrap();
            let p = psnr(&px, &grey);
            assert!(p > 35.0, "grey {w}x{h}: {p:.1} dB");
        }
    }

    #[test]
    fn the_fast_dct_matches_the_direct_formula() {
        // F(u, v) = C(u) C(v) / 4 sum_x sum_y f(x, y) cos((2x+1) u pi / 16) cos((2y+1) v pi / 16),
        // in f64, against the AAN outputs divided by their scale.
        let mut rng = 12345u64;
        for _ in 0..20 {
            let mut block = [0f32; 64];
            for v in block.iter_mut() {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                *v = ((rng >> 33) % 256) as f32 - 128.0;
            }
            let input = block;
            fdct_aan(&mut block);
            let c = |u: usize| if u == 0 { std::f64::consts::FRAC_1_SQRT_2 } else { 1.0 };
            for v in 0..8 {
                for u in 0..8 {
                    let mut sum = 0.0;
                    for y in 0..8 {
                        for x in 0..8 {
                            let cx = ((2 * x + 1) as f64 * u as f64 * std::f64::consts::PI / 16.0).cos();
                            let cy = ((2 * y + 1) as f64 * v as f64 * std::f64::consts::PI / 16.0).cos();
                            sum += input[y * 8 + x] as f64 * cx * cy;
                        }
                    }
                    let exact = 0.25 * c(u) * c(v) * sum;
                    let fast = block[v * 8 + u] as f64 / (8.0 * AAN_SCALE[u] * AAN_SCALE[v]);
                    assert!((fast - exact).abs() < 1e-3 * (1.0 + exact.abs()), "({u}, {v}): {fast} vs {exact}");
                }
            }
        }
    }

    #[test]
    fn sharp_colour_edges_survive_at_quality_90() {
        // A blue checkerboard of 8-pixel squares over grey ramps: 4:4:4 keeps the chroma edges.
        let (w, h) = (37, 23);
        let mut img = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                img.extend_from_slice(&[(x * 255 / w) as u8, (y * 255 / h) as u8, if (x / 8 + y / 8) % 2 == 0 { 60 } else { 190 }]);
            }
        }
        let mut out = Vec::new();
        JpegEncoder::new(90).unwrap().encode(&img, w, h, 3, &mut out).unwrap();
        let blue = |v: &[u8]| v.iter().skip(2).step_by(3).copied().collect::<Vec<u8>>();
        let p = psnr(&blue(&decode(&out).0), &blue(&img));
        // Measured: 45.7 dB with 4:4:4; 4:2:0 gave 23 dB (the decoder's chroma upsampling
        // blurs each edge over two pixels).
        eprintln!("blue channel at quality 90: {p:.1} dB");
        assert!(p > 33.0, "blue channel {p:.1} dB");
    }

    #[test]
    fn quality_trades_size_for_fidelity_and_bad_input_is_refused() {
        let (w, h) = (96, 64);
        let img = test_image(w, h);
        let mut sizes = Vec::new();
        let mut psnrs = Vec::new();
        for q in [20, 60, 95] {
            let mut out = Vec::new();
            JpegEncoder::new(q).unwrap().encode(&img, w, h, 3, &mut out).unwrap();
            psnrs.push(psnr(&decode(&out).0, &img));
            sizes.push(out.len());
        }
        assert!(sizes[0] < sizes[1] && sizes[1] < sizes[2], "{sizes:?}");
        assert!(psnrs[0] < psnrs[1] && psnrs[1] < psnrs[2], "{psnrs:?}");
        assert_eq!(JpegEncoder::new(0).err(), Some(JpegError::Quality(0)));
        let enc = JpegEncoder::new(90).unwrap();
        let mut out = Vec::new();
        assert!(matches!(enc.encode(&img[..10], w, h, 3, &mut out), Err(JpegError::Pixels { .. })));
        assert!(matches!(enc.encode(&[], 0, 0, 3, &mut out), Err(JpegError::Size { .. })));
    }
}
