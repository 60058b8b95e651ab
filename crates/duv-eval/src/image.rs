//! Image quality: PSNR and SSIM for f32 images with values nominally in [0, 1].
//!
//! SSIM follows Wang et al. 2004 with an 11x11 Gaussian window (sigma 1.5), K1 = 0.01,
//! K2 = 0.03, data range 1, population covariances, computed per channel and averaged over
//! channels. Two conventions differ only at the border (see [`SsimConvention`]). The window is
//! separable, so each of the five local moments costs two 11-tap passes; the arithmetic is in
//! f64 and the passes are written as whole-row multiply-adds so that they vectorise.

use super::EvalError;
use duv_core::Image;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Side of the SSIM window, pixels.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, pixels.
pub const SSIM_SIGMA: f64 = 1.5;
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;
/// Data range of f32 images (values in [0, 1]).
pub const DATA_RANGE: f64 = 1.0;

const RADIUS: usize = SSIM_WINDOW / 2;

/// How SSIM treats the image border.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SsimConvention {
    /// scikit-image `structural_similarity(gaussian_weights=True, sigma=1.5,
    /// use_sample_covariance=False, data_range=1)`: moments filtered with mirror ('reflect')
    /// borders, then the SSIM map averaged over the valid region only (5 pixels cropped from
    /// every side). Needs images of at least 11x11.
    #[default]
    Skimage,
    /// The 3DGS / MonoGS training-code `ssim()`: an 11x11 window convolved with zero padding
    /// ('same' size), the map averaged over every pixel. Paper tables use this one; it reads
    /// slightly higher than skimage on the same images.
    Same,
}

impl fmt::Display for SsimConvention {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            SsimConvention::Skimage => "skimage",
            SsimConvention::Same => "same",
        })
    }
}

impl FromStr for SsimConvention {
    type Err = EvalError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "skimage" => Ok(SsimConvention::Skimage),
            "same" => Ok(SsimConvention::Same),
            _ => Err(EvalError::InvalidParameter { name: "SSIM convention", value: s.to_string(), reason: "expected skimage or same" }),
        }
    }
}

impl SsimConvention {
    /// Smallest image side the convention accepts.
    pub fn min_side(self) -> usize {
        match self {
            SsimConvention::Skimage => SSIM_WINDOW,
            SsimConvention::Same => 1,
        }
    }
}

fn check_pair<const C: usize>(a: &Image<f32, C>, b: &Image<f32, C>) -> Result<(), EvalError> {
    if !a.same_size(b) || a.data.len() != b.data.len() {
        return Err(EvalError::ImageSizeMismatch {
            first: "first image".into(),
            second: "second image".into(),
            first_size: [a.width, a.height],
            second_size: [b.width, b.height],
        });
    }
    for (name, img) in [("first image", a), ("second image", b)] {
        if img.data.len() != img.width * img.height * C {
            return Err(EvalError::InvalidParameter { name: "image", value: name.into(), reason: "sample count is not width * height * channels" });
        }
        if let Some((index, &value)) = img.data.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(EvalError::NonFiniteImage { image: name.into(), index, value });
        }
    }
    if a.data.is_empty() {
        return Err(EvalError::ImageTooSmall { image: "first image".into(), width: a.width, height: a.height, min: 1, convention: SsimConvention::Same });
    }
    Ok(())
}

/// Mean squared difference over all pixels and channels.
pub fn mse<const C: usize>(a: &Image<f32, C>, b: &Image<f32, C>) -> Result<f64, EvalError> {
    check_pair(a, b)?;
    let sum: f64 = a.data.iter().zip(&b.data).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum();
    Ok(sum / a.data.len() as f64)
}

/// Peak signal-to-noise ratio in dB with data range 1: `10 log10(1 / MSE)`, the MSE taken over
/// all pixels and channels (as `skimage.metrics.peak_signal_noise_ratio`). Identical images
/// give `f64::INFINITY`.
pub fn psnr<const C: usize>(a: &Image<f32, C>, b: &Image<f32, C>) -> Result<f64, EvalError> {
    let m = mse(a, b)?;
    Ok(if m == 0.0 { f64::INFINITY } else { 10.0 * (DATA_RANGE * DATA_RANGE / m).log10() })
}

/// Mean SSIM over channels (each channel's SSIM map averaged as `convention` says).
pub fn ssim<const C: usize>(a: &Image<f32, C>, b: &Image<f32, C>, convention: SsimConvention) -> Result<f64, EvalError> {
    Ok(ssim_per_channel(a, b, convention)?.iter().sum::<f64>() / C as f64)
}

/// SSIM of each channel.
pub fn ssim_per_channel<const C: usize>(a: &Image<f32, C>, b: &Image<f32, C>, convention: SsimConvention) -> Result<[f64; C], EvalError> {
    check_pair(a, b)?;
    let (w, h) = (a.width, a.height);
    let min = convention.min_side();
    if w < min || h < min {
        return Err(EvalError::ImageTooSmall { image: "first image".into(), width: w, height: h, min, convention });
    }
    let (border, (x0, x1), (y0, y1)) = match convention {
        SsimConvention::Skimage => (Border::Reflect, (RADIUS, w - RADIUS), (RADIUS, h - RADIUS)),
        SsimConvention::Same => (Border::Zero, (0, w), (0, h)),
    };
    // Independent jobs: each channel in bands of output rows. The band layout depends on the
    // image only, and partial sums are added in a fixed order, so the result does not depend
    // on the number of threads.
    let bands: Vec<(usize, usize)> = (y0..y1).step_by(BAND_ROWS).map(|s| (s, (s + BAND_ROWS).min(y1))).collect();
    let jobs: Vec<(usize, (usize, usize))> = (0..C).flat_map(|c| bands.iter().map(move |&b| (c, b))).collect();
    let plane = Plane { a: &a.data, b: &b.data, channels: C, w, h };
    let sums: Vec<f64> = jobs.par_iter().map(|&(c, rows)| ssim_band_sum(&plane, c, rows, (x0, x1), border)).collect();
    let count = ((x1 - x0) * (y1 - y0)) as f64;
    let mut out = [0.0; C];
    for (c, value) in out.iter_mut().enumerate() {
        *value = sums[c * bands.len()..(c + 1) * bands.len()].iter().sum::<f64>() / count;
    }
    Ok(out)
}

/// Output rows per parallel job (each job filters 10 extra rows of halo).
const BAND_ROWS: usize = 96;

/// Two interleaved images, one channel of which is read.
struct Plane<'a> {
    a: &'a [f32],
    b: &'a [f32],
    channels: usize,
    w: usize,
    h: usize,
}

/// Sum of the SSIM map of channel `c` over output rows `y_start..y_end` and columns
/// `x0..x1`. Streams: the five moment rows (x, y, x^2, y^2, xy) of each source row are
/// filtered horizontally once into a ring of 11 rows; each output row is the weighted sum of
/// the ring's rows. Every source row a window needs lies within 11 consecutive rows (mirrored
/// rows fall inside the window too), so a slot per row index modulo 11 never collides.
fn ssim_band_sum(p: &Plane, c: usize, (y_start, y_end): (usize, usize), (x0, x1): (usize, usize), border: Border) -> f64 {
    let (w, h) = (p.w, p.h);
    let r = RADIUS;
    let kernel = gaussian_kernel();
    let c1 = (SSIM_K1 * DATA_RANGE).powi(2);
    let c2 = (SSIM_K2 * DATA_RANGE).powi(2);
    // ring[slot][m] is a horizontally filtered moment row; ring_row[slot] says which source row.
    let mut ring = vec![vec![0.0f64; 5 * w]; SSIM_WINDOW];
    let mut ring_row = [usize::MAX; SSIM_WINDOW];
    let mut padded = vec![0.0f64; 5 * (w + 2 * r)];
    let mut moments = vec![0.0f64; 5 * w];
    let mut total = 0.0;
    for y in y_start..y_end {
        moments.iter_mut().for_each(|v| *v = 0.0);
        for (k, &wk) in kernel.iter().enumerate() {
            let yy = y as isize + k as isize - r as isize;
            let src_y = match border {
                Border::Reflect => reflect(yy, h),
                Border::Zero if yy < 0 || yy >= h as isize => continue,
                Border::Zero => yy as usize,
            };
            let slot = src_y % SSIM_WINDOW;
            if ring_row[slot] != src_y {
                filter_row(p, c, src_y, border, &kernel, &mut padded, &mut ring[slot]);
                ring_row[slot] = src_y;
            }
            for (m, v) in moments.iter_mut().zip(&ring[slot]) {
                *m += wk * v;
            }
        }
        let (ux, rest) = moments.split_at(w);
        let (uy, rest) = rest.split_at(w);
        let (uxx, rest) = rest.split_at(w);
        let (uyy, uxy) = rest.split_at(w);
        let mut row_sum = 0.0;
        for x in x0..x1 {
            let (mx, my) = (ux[x], uy[x]);
            let vx = uxx[x] - mx * mx;
            let vy = uyy[x] - my * my;
            let vxy = uxy[x] - mx * my;
            row_sum += ((2.0 * mx * my + c1) * (2.0 * vxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2));
        }
        total += row_sum;
    }
    total
}

/// The five moment rows of source row `y`, channel `c`, filtered along x into `out`
/// (`5 * w`, moment-major).
fn filter_row(p: &Plane, c: usize, y: usize, border: Border, kernel: &[f64; SSIM_WINDOW], padded: &mut [f64], out: &mut [f64]) {
    let (w, r) = (p.w, RADIUS);
    let pw = w + 2 * r;
    let row_a = &p.a[y * w * p.channels..(y + 1) * w * p.channels];
    let row_b = &p.b[y * w * p.channels..(y + 1) * w * p.channels];
    for i in 0..pw {
        let x = i as isize - r as isize;
        let src_x = match border {
            Border::Reflect => Some(reflect(x, w)),
            Border::Zero => (x >= 0 && x < w as isize).then_some(x as usize),
        };
        let (va, vb) = match src_x {
            Some(sx) => (row_a[sx * p.channels + c] as f64, row_b[sx * p.channels + c] as f64),
            None => (0.0, 0.0),
        };
        padded[i] = va;
        padded[pw + i] = vb;
        padded[2 * pw + i] = va * va;
        padded[3 * pw + i] = vb * vb;
        padded[4 * pw + i] = va * vb;
    }
    for m in 0..5 {
        let src = &padded[m * pw..(m + 1) * pw];
        let dst = &mut out[m * w..(m + 1) * w];
        dst.iter_mut().for_each(|v| *v = 0.0);
        for (k, &wk) in kernel.iter().enumerate() {
            for (o, &v) in dst.iter_mut().zip(&src[k..k + w]) {
                *o += wk * v;
            }
        }
    }
}

/// The normalised 11-tap Gaussian, `exp(-k^2 / (2 sigma^2))` for k in -5..=5 (scipy
/// `gaussian_filter1d` with truncate 3.5, and the 3DGS `gaussian(11, 1.5)`).
pub fn gaussian_kernel() -> [f64; SSIM_WINDOW] {
    let mut k = [0.0; SSIM_WINDOW];
    for (i, v) in k.iter_mut().enumerate() {
        let d = i as f64 - RADIUS as f64;
        *v = (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let sum: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    k
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Border {
    /// scipy.ndimage 'reflect': `d c b a | a b c d | d c b a`.
    Reflect,
    /// Zero padding.
    Zero,
}

/// Index `i` (may be outside `0..n`) folded into `0..n` by half-sample mirroring.
fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    let period = 2 * n;
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - 1 - m }) as usize
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::{ImageRgbF32, PlaneF32};

    fn ramp(w: usize, h: usize) -> ImageRgbF32 {
        let data = (0..w * h * 3).map(|i| ((i * 37) % 251) as f32 / 255.0).collect();
        ImageRgbF32::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn identical_images_give_infinite_psnr_and_unit_ssim() {
        let a = ramp(23, 17);
        assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
        for conv in [SsimConvention::Skimage, SsimConvention::Same] {
            assert!((ssim(&a, &a, conv).unwrap() - 1.0).abs() < 1e-12, "{conv}");
        }
    }

    #[test]
    fn constant_offset_of_a_tenth_is_20_db() {
        // Offsets of exactly 0.1 are not representable in f32; the error of 0.1 in f32 moves
        // the PSNR by ~1e-6 dB, hence the tolerance.
        let a = PlaneF32::filled(32, 24, [0.25]);
        let b = PlaneF32::filled(32, 24, [0.35]);
        let p = psnr(&a, &b).unwrap();
        assert!((p - 20.0).abs() < 1e-5, "{p}");
        // With an offset exactly representable in f32 (0.125 = 2^-3), the result is exact.
        let c = PlaneF32::filled(32, 24, [0.375]);
        assert_eq!(psnr(&a, &c).unwrap(), 10.0 * 64f64.log10());
    }

    #[test]
    fn reflect_indexing_matches_scipy() {
        let n = 4;
        let got: Vec<usize> = (-5..9).map(|i| reflect(i, n)).collect();
        // scipy 'reflect' on [a b c d]: ... b | a b c d | d c b a | a b ...
        assert_eq!(got, vec![3, 3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0, 0]);
    }

    #[test]
    fn kernel_is_normalised_and_symmetric() {
        let k = gaussian_kernel();
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for i in 0..SSIM_WINDOW {
            assert_eq!(k[i], k[SSIM_WINDOW - 1 - i]);
        }
    }

    #[test]
    fn bad_pairs_are_errors() {
        let a = ramp(20, 20);
        let b = ramp(21, 20);
        assert!(matches!(psnr(&a, &b), Err(EvalError::ImageSizeMismatch { .. })));
        let small = ramp(10, 30);
        assert!(matches!(ssim(&small, &small, SsimConvention::Skimage), Err(EvalError::ImageTooSmall { min: 11, .. })));
        assert!(ssim(&small, &small, SsimConvention::Same).is_ok());
        let mut nan = a.clone();
        nan.data[7] = f32::NAN;
        assert!(matches!(ssim(&a, &nan, SsimConvention::Skimage), Err(EvalError::NonFiniteImage { index: 7, .. })));
        let empty = ImageRgbF32::new(0, 0);
        assert!(psnr(&empty, &empty).is_err());
    }
}
