//! The live camera's image: the input frame box-filtered down to the live size, into a reused
//! buffer; and the colour of a Gaussian without one (by height).

use duv_core::FrameImage;

/// The live size of a `width` x `height` frame: `scale` of it, at most `max_width` wide, the
/// aspect ratio kept, at least 1x1.
pub(crate) fn live_size(width: usize, height: usize, scale: f64, max_width: usize) -> (usize, usize) {
    let w = ((width as f64 * scale).round() as usize).min(max_width).clamp(1, width.max(1));
    let h = ((height as f64 * w as f64 / width.max(1) as f64).round() as usize).clamp(1, height.max(1));
    (w, h)
}

/// `image` box-filtered to `w` x `h` into `out` (cleared, its capacity reused): each output
/// pixel the mean of the input pixels it covers. Returns the channels (3 RGB, 1 grey).
pub(crate) fn downscale(image: &FrameImage, w: usize, h: usize, out: &mut Vec<u8>) -> usize {
    let (data, c, sw, sh): (&[u8], usize, usize, usize) = match image {
        FrameImage::Rgb8(i) => (&i.data, 3, i.width, i.height),
        FrameImage::Gray8(i) => (&i.data, 1, i.width, i.height),
    };
    out.clear();
    for y in 0..h {
        let (y0, y1) = (y * sh / h, ((y + 1) * sh / h).max(y * sh / h + 1).min(sh));
        for x in 0..w {
            let (x0, x1) = (x * sw / w, ((x + 1) * sw / w).max(x * sw / w + 1).min(sw));
            let n = ((y1 - y0) * (x1 - x0)) as u32;
            let mut sum = [0u32; 3];
            for yy in y0..y1 {
                let row = &data[(yy * sw + x0) * c..(yy * sw + x1) * c];
                for px in row.chunks_exact(c) {
                    for (s, &v) in sum.iter_mut().zip(px) {
                        *s += v as u32;
                    }
                }
            }
            for s in &sum[..c] {
                out.push(((s + n / 2) / n) as u8);
            }
        }
    }
    c
}

/// A blue (low) to yellow (high) ramp over `[lo, hi]`.
pub(crate) fn height_colour(z: f32, lo: f32, hi: f32) -> [u8; 3] {
    let t = if hi > lo { ((z - lo) / (hi - lo)).clamp(0.0, 1.0) } else { 0.5 };
    [(40.0 + 215.0 * t) as u8, (80.0 + 150.0 * t) as u8, (220.0 - 180.0 * t) as u8]
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::{ImageGray8, ImageRgb8};

    #[test]
    fn sizes_follow_scale_width_cap_and_aspect() {
        assert_eq!(live_size(640, 480, 0.5, 320), (320, 240));
        assert_eq!(live_size(1280, 720, 0.5, 320), (320, 180));
        assert_eq!(live_size(160, 120, 0.5, 320), (80, 60));
        assert_eq!(live_size(10, 10, 0.01, 320), (1, 1));
    }

    #[test]
    fn box_filter_averages_what_each_pixel_covers() {
        // 4x2 grey: left half 0/100, right half 200/250 -> 2x1: 50, 225.
        let g = ImageGray8::from_vec(4, 2, vec![0, 100, 200, 250, 0, 100, 200, 250]).unwrap();
        let mut out = Vec::new();
        assert_eq!(downscale(&FrameImage::Gray8(g), 2, 1, &mut out), 1);
        assert_eq!(out, vec![50, 225]);
        // Odd sizes (5x3 RGB to 2x2) cover every input pixel once, the mean stays.
        let mut rgb = ImageRgb8::new(5, 3);
        rgb.data.iter_mut().for_each(|v| *v = 90);
        let cap = {
            downscale(&FrameImage::Rgb8(rgb.clone()), 2, 2, &mut out);
            out.capacity()
        };
        assert_eq!(downscale(&FrameImage::Rgb8(rgb), 2, 2, &mut out), 3);
        assert_eq!(out, vec![90; 12]);
        assert_eq!(out.capacity(), cap, "the buffer is reused");
    }
}
