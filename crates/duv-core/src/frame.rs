//! Images and frames: 8-bit RGB and grey images as delivered by cameras, f32 planes for
//! computation, and a time-stamped [`Frame`].

use super::time::Timestamp;

/// A row-major image of `C` interleaved channels with samples of type `T`.
#[derive(Clone, Debug, PartialEq)]
pub struct Image<T, const C: usize> {
    pub width: usize,
    pub height: usize,
    /// `width * height * C` samples, row-major, channels interleaved.
    pub data: Vec<T>,
}

/// 8-bit sRGB-encoded colour image, channels R, G, B.
pub type ImageRgb8 = Image<u8, 3>;
/// 8-bit grey image.
pub type ImageGray8 = Image<u8, 1>;
/// 16-bit single-channel image (e.g. TUM depth, metres x 5000).
pub type ImageGray16 = Image<u16, 1>;
/// Linear f32 colour image, channels R, G, B, nominally in [0, 1].
pub type ImageRgbF32 = Image<f32, 3>;
/// One f32 plane (grey intensity, depth, inverse depth, variance...).
pub type PlaneF32 = Image<f32, 1>;

impl<T: Copy + Default, const C: usize> Image<T, C> {
    /// An image filled with `T::default()`.
    pub fn new(width: usize, height: usize) -> Self {
        Image { width, height, data: vec![T::default(); width * height * C] }
    }
    pub fn filled(width: usize, height: usize, value: [T; C]) -> Self {
        let mut data = Vec::with_capacity(width * height * C);
        for _ in 0..width * height {
            data.extend_from_slice(&value);
        }
        Image { width, height, data }
    }
    /// Wraps `data`; `None` when its length is not `width * height * C`.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Option<Self> {
        (data.len() == width * height * C).then_some(Image { width, height, data })
    }
    pub const CHANNELS: usize = C;

    pub fn pixel_count(&self) -> usize {
        self.width * self.height
    }
    #[inline]
    pub fn index(&self, x: usize, y: usize) -> usize {
        (y * self.width + x) * C
    }
    #[inline]
    pub fn pixel(&self, x: usize, y: usize) -> [T; C] {
        let i = self.index(x, y);
        let mut out = [T::default(); C];
        out.copy_from_slice(&self.data[i..i + C]);
        out
    }
    #[inline]
    pub fn set_pixel(&mut self, x: usize, y: usize, value: [T; C]) {
        let i = self.index(x, y);
        self.data[i..i + C].copy_from_slice(&value);
    }
    pub fn row(&self, y: usize) -> &[T] {
        let w = self.width * C;
        &self.data[y * w..(y + 1) * w]
    }
    pub fn same_size<U, const D: usize>(&self, other: &Image<U, D>) -> bool {
        self.width == other.width && self.height == other.height
    }
}

impl PlaneF32 {
    /// Bilinear sample at continuous pixel coordinates (pixel centres at integers);
    /// `None` outside `[0, w-1] x [0, h-1]`.
    pub fn sample_bilinear(&self, x: f32, y: f32) -> Option<f32> {
        if !(x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f32 && y <= (self.height - 1) as f32) {
            return None;
        }
        let x0 = (x.floor() as usize).min(self.width.saturating_sub(2));
        let y0 = (y.floor() as usize).min(self.height.saturating_sub(2));
        let ax = x - x0 as f32;
        let ay = y - y0 as f32;
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        let p = |xx, yy| self.data[yy * self.width + xx];
        let top = p(x0, y0) * (1.0 - ax) + p(x1, y0) * ax;
        let bottom = p(x0, y1) * (1.0 - ax) + p(x1, y1) * ax;
        Some(top * (1.0 - ay) + bottom * ay)
    }
}

/// ITU-R BT.601 luma weights, the usual choice for camera grey conversion.
pub const LUMA_WEIGHTS: [f32; 3] = [0.299, 0.587, 0.114];

impl ImageRgb8 {
    pub fn to_gray8(&self) -> ImageGray8 {
        let data = self
            .data
            .chunks_exact(3)
            .map(|p| {
                let v = LUMA_WEIGHTS[0] * p[0] as f32 + LUMA_WEIGHTS[1] * p[1] as f32 + LUMA_WEIGHTS[2] * p[2] as f32;
                v.round().clamp(0.0, 255.0) as u8
            })
            .collect();
        Image { width: self.width, height: self.height, data }
    }
    /// Grey intensity in [0, 1] as an f32 plane.
    pub fn to_gray_f32(&self) -> PlaneF32 {
        let data = self
            .data
            .chunks_exact(3)
            .map(|p| (LUMA_WEIGHTS[0] * p[0] as f32 + LUMA_WEIGHTS[1] * p[1] as f32 + LUMA_WEIGHTS[2] * p[2] as f32) / 255.0)
            .collect();
        Image { width: self.width, height: self.height, data }
    }
    /// Channels scaled to [0, 1] (no gamma decoding: cameras and datasets deliver display values).
    pub fn to_rgb_f32(&self) -> ImageRgbF32 {
        Image { width: self.width, height: self.height, data: self.data.iter().map(|&v| v as f32 / 255.0).collect() }
    }
}

impl ImageGray8 {
    pub fn to_rgb8(&self) -> ImageRgb8 {
        Image { width: self.width, height: self.height, data: self.data.iter().flat_map(|&v| [v, v, v]).collect() }
    }
    pub fn to_gray_f32(&self) -> PlaneF32 {
        Image { width: self.width, height: self.height, data: self.data.iter().map(|&v| v as f32 / 255.0).collect() }
    }
}

impl ImageRgbF32 {
    /// Quantises to 8 bits with rounding; values are clamped to [0, 1] first, NaN becomes 0.
    pub fn to_rgb8(&self) -> ImageRgb8 {
        Image { width: self.width, height: self.height, data: self.data.iter().map(|&v| unit_to_u8(v)).collect() }
    }
}

impl PlaneF32 {
    pub fn to_gray8(&self) -> ImageGray8 {
        Image { width: self.width, height: self.height, data: self.data.iter().map(|&v| unit_to_u8(v)).collect() }
    }
}

#[inline]
pub fn unit_to_u8(v: f32) -> u8 {
    if v.is_nan() {
        0
    } else {
        (v.clamp(0.0, 1.0) * 255.0).round() as u8
    }
}

/// What a camera or dataset delivers: colour or grey.
#[derive(Clone, Debug, PartialEq)]
pub enum FrameImage {
    Rgb8(ImageRgb8),
    Gray8(ImageGray8),
}

impl FrameImage {
    pub fn width(&self) -> usize {
        match self {
            FrameImage::Rgb8(i) => i.width,
            FrameImage::Gray8(i) => i.width,
        }
    }
    pub fn height(&self) -> usize {
        match self {
            FrameImage::Rgb8(i) => i.height,
            FrameImage::Gray8(i) => i.height,
        }
    }
    pub fn to_rgb8(&self) -> ImageRgb8 {
        match self {
            FrameImage::Rgb8(i) => i.clone(),
            FrameImage::Gray8(i) => i.to_rgb8(),
        }
    }
    pub fn to_gray_f32(&self) -> PlaneF32 {
        match self {
            FrameImage::Rgb8(i) => i.to_gray_f32(),
            FrameImage::Gray8(i) => i.to_gray_f32(),
        }
    }
}

/// One image from a source with its capture time and a running sequence number.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Capture time (driver or dataset time stamp).
    pub t_ns: Timestamp,
    /// 0-based index in the order the source delivered frames.
    pub seq: u64,
    pub image: FrameImage,
}

impl Frame {
    /// A 0x0 RGB frame at time 0: a buffer for `FrameSource::next_frame_into` to fill.
    pub fn empty() -> Frame {
        Frame::rgb(0, 0)
    }

    /// A black `width x height` RGB frame at time 0 (a buffer of that size to fill).
    pub fn rgb(width: usize, height: usize) -> Frame {
        Frame { t_ns: Timestamp::from_ns(0), seq: 0, image: FrameImage::Rgb8(ImageRgb8 { width, height, data: vec![0; width * height * 3] }) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_sampling_interpolates_and_bounds() {
        let img = PlaneF32::from_vec(2, 2, vec![0.0, 1.0, 2.0, 3.0]).unwrap();
        assert_eq!(img.sample_bilinear(0.0, 0.0), Some(0.0));
        assert_eq!(img.sample_bilinear(1.0, 1.0), Some(3.0));
        assert!((img.sample_bilinear(0.5, 0.5).unwrap() - 1.5).abs() < 1e-6);
        assert_eq!(img.sample_bilinear(-0.1, 0.0), None);
        assert_eq!(img.sample_bilinear(0.0, 1.01), None);
        assert_eq!(img.sample_bilinear(f32::NAN, 0.0), None);
    }

    #[test]
    fn grey_conversion_uses_luma() {
        let img = ImageRgb8::from_vec(2, 1, vec![255, 0, 0, 0, 0, 255]).unwrap();
        assert_eq!(img.to_gray8().data, vec![76, 29]);
        assert!(ImageRgb8::from_vec(2, 2, vec![0; 3]).is_none());
    }
}
