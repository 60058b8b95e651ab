//! Procedural underwater-looking images with known motion, for the flow tests and benchmarks:
//! multi-scale value noise and a few soft blobs (rocks) as scene radiance, viewed through
//! water (per-channel attenuation and a blue-green veil growing with range, far at the top),
//! with sensor noise and 8-bit quantisation. Motion is applied by bilinear resampling of a
//! canvas larger than the view, so new content enters where the view moves.

use duv_core::rng::Rng;
use duv_core::{Image, ImageRgbF32, PlaneF32};

/// Lattice spacings (pixels) and amplitudes of the value-noise octaves.
const OCTAVES: [(f32, f32); 5] = [(64.0, 0.30), (32.0, 0.22), (16.0, 0.16), (8.0, 0.12), (4.0, 0.08)];

/// One octave of value noise: random lattice values, C1 (smoothstep) interpolation.
struct ValueNoise {
    spacing: f32,
    nx: usize,
    values: Vec<f32>,
}

impl ValueNoise {
    fn new(width: usize, height: usize, spacing: f32, rng: &mut Rng) -> Self {
        let nx = (width as f32 / spacing) as usize + 3;
        let ny = (height as f32 / spacing) as usize + 3;
        let values = (0..nx * ny).map(|_| rng.range(-1.0, 1.0) as f32).collect();
        ValueNoise { spacing, nx, values }
    }
    fn at(&self, x: f32, y: f32) -> f32 {
        let (gx, gy) = (x / self.spacing, y / self.spacing);
        let (ix, iy) = (gx.floor(), gy.floor());
        let s = |t: f32| t * t * (3.0 - 2.0 * t);
        let (tx, ty) = (s(gx - ix), s(gy - iy));
        let (ix, iy) = (ix as usize, iy as usize);
        let v = |i: usize, j: usize| self.values[j * self.nx + i];
        let top = v(ix, iy) + tx * (v(ix + 1, iy) - v(ix, iy));
        let bottom = v(ix, iy + 1) + tx * (v(ix + 1, iy + 1) - v(ix, iy + 1));
        top + ty * (bottom - top)
    }
}

/// Scene radiance on a `width x height` canvas, linear RGB in [0, 1]: sandy, mottled ground
/// with a few darker or lighter rocks.
pub fn radiance(width: usize, height: usize, seed: u64) -> ImageRgbF32 {
    let mut rng = Rng::new(seed);
    let octaves: Vec<(ValueNoise, f32)> =
        OCTAVES.iter().map(|&(s, a)| (ValueNoise::new(width, height, s, &mut rng), a)).collect();
    let tint = ValueNoise::new(width, height, 40.0, &mut rng);
    let blobs: Vec<([f32; 2], f32, [f32; 3])> = (0..(width * height / 6000).max(3))
        .map(|_| {
            let c = [rng.range(0.0, width as f64) as f32, rng.range(0.0, height as f64) as f32];
            let r = rng.range(6.0, 22.0) as f32;
            let k = rng.range(0.25, 0.95) as f32;
            (c, r, [k, k * 0.95, k * 0.85])
        })
        .collect();
    let mut img = ImageRgbF32::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let (xf, yf) = (x as f32, y as f32);
            let l = 0.55 + octaves.iter().map(|(n, a)| a * n.at(xf, yf)).sum::<f32>();
            let t = 0.08 * tint.at(xf, yf);
            let mut rgb = [l * (0.80 + t), l * 0.70, l * (0.55 - t)];
            for &(c, r, col) in &blobs {
                let d = ((xf - c[0]).powi(2) + (yf - c[1]).powi(2)).sqrt();
                let m = ((r + 2.0 - d) / 4.0).clamp(0.0, 1.0);
                let m = m * m * (3.0 - 2.0 * m);
                let shade = 0.85 + 0.3 * (l - 0.55);
                for k in 0..3 {
                    rgb[k] += m * (col[k] * shade - rgb[k]);
                }
            }
            img.set_pixel(x, y, rgb.map(|v| v.clamp(0.0, 1.0)));
        }
    }
    img
}

/// Water between camera and scene, `I = J exp(-beta r) + veil (1 - exp(-beta r))` per
/// channel, the range `r` growing linearly from the bottom row (near) to the top row (far).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Water {
    /// Attenuation per metre, R G B.
    pub beta_per_m: [f32; 3],
    /// Veiling light (backscatter at infinite range), R G B.
    pub veil: [f32; 3],
    pub range_near_m: f32,
    pub range_far_m: f32,
}

impl Default for Water {
    fn default() -> Self {
        Water { beta_per_m: [0.45, 0.14, 0.10], veil: [0.05, 0.30, 0.40], range_near_m: 1.5, range_far_m: 6.0 }
    }
}

/// Applies `water` in image space (the veil is fixed to the view, as range is).
pub fn through_water(img: &mut ImageRgbF32, water: &Water) {
    let (w, h) = (img.width, img.height);
    for y in 0..h {
        let a = 1.0 - y as f32 / (h.max(2) - 1) as f32;
        let r = water.range_near_m + a * (water.range_far_m - water.range_near_m);
        let t: [f32; 3] = std::array::from_fn(|k| (-water.beta_per_m[k] * r).exp());
        for x in 0..w {
            let p = img.pixel(x, y);
            img.set_pixel(x, y, std::array::from_fn(|k| p[k] * t[k] + water.veil[k] * (1.0 - t[k])));
        }
    }
}

/// A `width x height` view of `canvas`: view pixel `(x, y)` shows canvas point
/// `view_to_canvas(x, y) + (margin, margin)`, sampled bilinearly (clamped at the canvas edge).
pub fn render(
    canvas: &ImageRgbF32,
    margin: usize,
    width: usize,
    height: usize,
    view_to_canvas: impl Fn(f32, f32) -> (f32, f32),
) -> ImageRgbF32 {
    let (cw, ch) = (canvas.width, canvas.height);
    let m = margin as f32;
    let mut out = ImageRgbF32::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let (sx, sy) = view_to_canvas(x as f32, y as f32);
            let (sx, sy) = ((sx + m).clamp(0.0, (cw - 1) as f32), (sy + m).clamp(0.0, (ch - 1) as f32));
            let (x0, y0) = ((sx as usize).min(cw - 2), (sy as usize).min(ch - 2));
            let (ax, ay) = (sx - x0 as f32, sy - y0 as f32);
            let p00 = canvas.pixel(x0, y0);
            let p10 = canvas.pixel(x0 + 1, y0);
            let p01 = canvas.pixel(x0, y0 + 1);
            let p11 = canvas.pixel(x0 + 1, y0 + 1);
            out.set_pixel(
                x,
                y,
                std::array::from_fn(|k| {
                    let top = p00[k] + ax * (p10[k] - p00[k]);
                    let bottom = p01[k] + ax * (p11[k] - p01[k]);
                    top + ay * (bottom - top)
                }),
            );
        }
    }
    out
}

/// A photometric change between two views: contrast scaled about 0.5, then a per-channel gain
/// and offset (colour cast), plus a veil growing linearly to `haze_top` at the top row.
pub fn photometric_change(img: &mut ImageRgbF32, contrast: f32, gain: [f32; 3], offset: [f32; 3], haze_top: [f32; 3]) {
    let h = img.height;
    for y in 0..h {
        let a = 1.0 - y as f32 / (h.max(2) - 1) as f32;
        for x in 0..img.width {
            let p = img.pixel(x, y);
            img.set_pixel(
                x,
                y,
                std::array::from_fn(|k| gain[k] * (0.5 + contrast * (p[k] - 0.5)) + offset[k] + a * haze_top[k]),
            );
        }
    }
}

/// Paints a flat (textureless) rectangle `[x0, x1) x [y0, y1)`.
pub fn flat_rect(img: &mut ImageRgbF32, x0: usize, y0: usize, x1: usize, y1: usize, rgb: [f32; 3]) {
    for y in y0..y1.min(img.height) {
        for x in x0..x1.min(img.width) {
            img.set_pixel(x, y, rgb);
        }
    }
}

/// What the camera delivers: Gaussian noise of `noise_sigma`, 8-bit quantisation, grey in [0, 1].
pub fn camera_gray(img: &ImageRgbF32, noise_sigma: f32, seed: u64) -> PlaneF32 {
    let mut rng = Rng::new(seed);
    let noisy = Image {
        width: img.width,
        height: img.height,
        data: img.data.iter().map(|&v| v + noise_sigma * rng.normal() as f32).collect(),
    };
    noisy.to_rgb8().to_gray_f32()
}
