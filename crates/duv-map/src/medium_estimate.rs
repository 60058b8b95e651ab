//! A closed-form estimate of the water from keyframes with depth, made before the joint
//! optimisation starts: backscatter first, then attenuation across views.
//!
//! The joint optimisation of Gaussians and medium (Eq. 12-14) only sees the medium through
//! the difference between views of the same surface at different ranges; the Gaussians'
//! colours fit everything else at once, so started from a generic water it keeps most of the
//! attenuation in the albedo and moves the medium slowly. This estimate puts the medium
//! close to the truth before the first step, from the same images and depths:
//!
//! 1. **Samples.** Each keyframe is cut into blocks of `block_px` x `block_px` pixels; a block
//!    whose pixels all have confident depth (relative inverse-depth standard deviation at
//!    most `max_rel_std`) and whose ranges agree within `max_block_range_spread` is a sample:
//!    mean colour, mean range (distance along the ray, not `z`), and the world point of its
//!    centre. Pixels with inverse depth exactly 0 (nothing within range: open water) are
//!    pooled separately; their mean colour is the veiling light seen directly.
//! 2. **Backscatter** (as Sea-thru does): samples are split into `range_bins` bins of equal
//!    count by range; in each bin the darkest `dark_fraction` (by R+G+B) are nearly free of
//!    direct signal, so per channel their mean follows
//!    `B_inf (1 - exp(-beta_B r)) + J' exp(-beta_D r)` with a small residual direct term
//!    `J'`. `beta_B` is found on a log grid; `B_inf` and `J'` by non-negative least squares
//!    for each grid value; the open-water mean, when there is one, is one more point at
//!    infinite range (weight `open_water_weight` bins).
//! 3. **Attenuation** across views: with the backscatter removed, the direct signal
//!    `D = I - B_inf (1 - exp(-beta_B r))` of one surface point seen from keyframes `i` and
//!    `j` is `J exp(-beta_D r_i)` and `J exp(-beta_D r_j)` (Lambertian seabed), so
//!    `ln D_j - ln D_i = -beta_D (r_j - r_i)` whatever the albedo. Each sample is projected
//!    into the other keyframes; a pair is kept when the point is in view, not occluded (the
//!    other keyframe's range there agrees within `occlusion_tolerance`), the ranges differ by
//!    at least `min_range_difference_m` and both direct signals exceed `min_direct`; of a
//!    sample's partners only the `max_partners` with the largest range difference are kept,
//!    and of all pairs at most `max_pairs`, evenly spaced.
//!    `beta_D` is the weighted least-squares slope through the origin, reweighted three times
//!    with Tukey's biweight on the residuals (the start of step 5).
//! 4. Steps 2 and 3 alternate `rounds` times: the residual direct term of step 2 decays with
//!    the `beta_D` of step 3.
//! 5. **Joint two-view fit.** From there, per channel, `(B_inf, ln beta_B, ln beta_D)` are
//!    fitted together (Levenberg-Marquardt with the analytic Jacobian, Huber weights) to every pair:
//!    `I_j - B(r_j) = (I_i - B(r_i)) exp(-beta_D (r_j - r_i))`, as an orthogonal distance since
//!    both colours are noisy. Across many albedos at the same two ranges this line's slope is
//!    the attenuation and its offset the backscatter difference, so all three are determined
//!    without assuming anything about the albedo, given enough range difference.
//! 6. **Gate.** The fit's standard errors (Gauss-Newton covariance, scaled up by the square
//!    root of the pairs per sample, since a sample enters several pairs) decide which
//!    coefficients are [`MediumEstimate::determined`] (a `beta` at the search's bound is not),
//!    and a channel with all three is [`MediumEstimate::accepted`]. In clear water a short
//!    sequence sees the green and blue backscatter only in its nearly linear start, where
//!    `B_inf` and `beta_B` trade against each other, and the red backscatter only once it
//!    has saturated, where `beta_B` is free; the gate refuses such coefficients instead of
//!    handing the mapper wrong ones, and takes the channel's others when `B_inf` is among
//!    them ([`MediumEstimateConfig::per_coefficient`]).
//!
//! A channel without enough pairs keeps the configured initial water for `beta_D`; no
//! sample at all is an error that says what was missing. Everything is f64 and
//! deterministic. Steps 2 to 5 run for the three channels side by side on scoped threads,
//! which inherit the caller's cores and priority (the mapping thread's placement). The
//! estimate runs on the mapping thread, where no optimisation step runs meanwhile: at 640x480
//! on a 2-core machine it took 3.0-3.8 s with central differences on one thread and takes
//! 0.5-1.3 s now (`cargo run --release --example medium_estimate_time` times it).

use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use duv_core::{Keyframe, MediumParams};

/// Why no estimate could be made. The mapper then keeps its configured initial water.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MediumEstimateError {
    #[error("medium estimate config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
    #[error("medium estimate: {found} usable depth blocks in {keyframes} keyframe(s), at least {needed} needed (too little confident depth)")]
    TooFewSamples { found: usize, needed: usize, keyframes: usize },
    #[error("medium estimate: keyframe {index}: {why}")]
    BadKeyframe { index: u64, why: &'static str },
}

/// Settings of the estimate. Defaults live in [`MediumEstimateConfig::default`] and nowhere else.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MediumEstimateConfig {
    /// Side of a sample block, pixels (>= 1).
    pub block_px: usize,
    /// Only pixels whose inverse-depth standard deviation is at most this fraction of the inverse depth.
    pub max_rel_std: f64,
    /// A block is a sample when its largest and smallest range differ by at most this fraction.
    pub max_block_range_spread: f64,
    /// Range bins of the backscatter fit (equal sample counts, >= 4).
    pub range_bins: usize,
    /// Share of each bin taken as its darkest samples, in (0, 1].
    pub dark_fraction: f64,
    /// Weight of the open-water mean in the backscatter fit, in bins.
    pub open_water_weight: f64,
    /// Pairs of views whose ranges differ by less than this are not used, metres.
    pub min_range_difference_m: f64,
    /// Pairs whose direct signal is below this in either view are not used (fraction of full scale).
    pub min_direct: f64,
    /// Relative range disagreement beyond which a projected sample counts as occluded.
    pub occlusion_tolerance: f64,
    /// A coefficient of a channel's fit counts as determined only when its standard error is
    /// below this: `ln beta_D` and `ln beta_B` (relative errors)...
    pub max_rel_std_error: f64,
    /// ...and `B_inf` below this (fraction of full scale).
    pub max_b_inf_std_error: f64,
    /// Take each coefficient the fit determined, also from a channel whose other coefficients
    /// it did not, provided `B_inf` is among them ([`MediumEstimate::determined`]); off, a
    /// channel is all or nothing. In clear water the red light is gone within metres: its
    /// attenuation and veiling light are seen, but its backscatter saturates before the
    /// nearest range and its `beta_B` is free.
    pub per_coefficient: bool,
    /// Backscatter/attenuation alternations (>= 1).
    pub rounds: usize,
    /// Fewest pairs for a channel's `beta_D`.
    pub min_pairs: usize,
    /// Each sample pairs with at most this many other keyframes, those where its range
    /// differs most (>= 1). Keeps the pairs, and the estimate's time and memory, linear in the
    /// keyframes: with every partner, 16 generated 320x240 keyframes took 24 s against 0.6 s
    /// for 4.
    pub max_partners: usize,
    /// At most this many pairs enter the fits, evenly spaced over all of them (>= `min_pairs`):
    /// the estimate's time stays about that of 4 keyframes at 320x240 whatever the keyframes
    /// and image size.
    pub max_pairs: usize,
}

impl Default for MediumEstimateConfig {
    fn default() -> Self {
        MediumEstimateConfig {
            block_px: 4,
            max_rel_std: 0.2,
            max_block_range_spread: 0.1,
            range_bins: 16,
            dark_fraction: 0.02,
            open_water_weight: 4.0,
            min_range_difference_m: 0.3,
            min_direct: 0.02,
            occlusion_tolerance: 0.05,
            rounds: 3,
            min_pairs: 50,
            max_partners: 3,
            max_pairs: 60_000,
            max_rel_std_error: 0.05,
            max_b_inf_std_error: 0.02,
            per_coefficient: true,
        }
    }
}

impl MediumEstimateConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), MediumEstimateError> {
        let bad = |field: &'static str, value: f64, why: &'static str| Err(MediumEstimateError::InvalidConfig { field, value, why });
        if self.block_px == 0 || self.block_px > 64 {
            return bad("block_px", self.block_px as f64, "must be in 1..=64");
        }
        if self.range_bins < 4 || self.range_bins > 1024 {
            return bad("range_bins", self.range_bins as f64, "must be in 4..=1024");
        }
        if self.max_partners == 0 {
            return bad("max_partners", 0.0, "must be >= 1");
        }
        if self.max_pairs < self.min_pairs.max(1) {
            return bad("max_pairs", self.max_pairs as f64, "must be >= min_pairs and >= 1");
        }
        if self.rounds == 0 || self.rounds > 100 {
            return bad("rounds", self.rounds as f64, "must be in 1..=100");
        }
        if !(self.dark_fraction > 0.0 && self.dark_fraction <= 1.0) {
            return bad("dark_fraction", self.dark_fraction, "must be in (0, 1]");
        }
        for (field, v) in [
            ("max_rel_std", self.max_rel_std),
            ("max_block_range_spread", self.max_block_range_spread),
            ("open_water_weight", self.open_water_weight),
            ("min_range_difference_m", self.min_range_difference_m),
            ("min_direct", self.min_direct),
            ("occlusion_tolerance", self.occlusion_tolerance),
            ("max_rel_std_error", self.max_rel_std_error),
            ("max_b_inf_std_error", self.max_b_inf_std_error),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, v, "must be finite and >= 0");
            }
        }
        Ok(())
    }
}

/// Which coefficients of one colour channel an estimate determined, or a prior holds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Coefficients {
    pub beta_d: bool,
    pub beta_b: bool,
    pub b_inf: bool,
}

impl Coefficients {
    pub const ALL: Coefficients = Coefficients { beta_d: true, beta_b: true, b_inf: true };
    pub const NONE: Coefficients = Coefficients { beta_d: false, beta_b: false, b_inf: false };

    pub fn all(self) -> bool {
        self.beta_d && self.beta_b && self.b_inf
    }
    pub fn any(self) -> bool {
        self.beta_d || self.beta_b || self.b_inf
    }
    /// Every coefficient `other` has, this has too.
    pub fn contains(self, other: Coefficients) -> bool {
        self.bits() & other.bits() == other.bits()
    }
    /// Bit 0 `beta_D`, bit 1 `beta_B`, bit 2 `B_inf`.
    pub fn bits(self) -> u32 {
        self.beta_d as u32 | (self.beta_b as u32) << 1 | (self.b_inf as u32) << 2
    }
    /// The inverse of [`Self::bits`]; higher bits are ignored.
    pub fn from_bits(bits: u32) -> Coefficients {
        Coefficients { beta_d: bits & 1 != 0, beta_b: bits & 2 != 0, b_inf: bits & 4 != 0 }
    }
}

/// `all`, `none`, or the names joined by `+` (`beta_D+B_inf`).
impl std::fmt::Display for Coefficients {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.all() {
            return f.write_str("all");
        }
        if !self.any() {
            return f.write_str("none");
        }
        let names = [(self.beta_d, "beta_D"), (self.beta_b, "beta_B"), (self.b_inf, "B_inf")];
        let on: Vec<&str> = names.iter().filter(|(on, _)| *on).map(|(_, n)| *n).collect();
        f.write_str(&on.join("+"))
    }
}

/// Sets, per channel `c`, the coefficients `which[c]` names of `into` to those of `from`.
pub fn set_coefficients(into: &mut MediumParams, from: &MediumParams, which: [Coefficients; 3]) {
    for (c, w) in which.iter().enumerate() {
        if w.beta_d {
            into.beta_d[c] = from.beta_d[c];
        }
        if w.beta_b {
            into.beta_b[c] = from.beta_b[c];
        }
        if w.b_inf {
            into.b_inf[c] = from.b_inf[c];
        }
    }
}

/// The estimate and what it rests on.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MediumEstimate {
    /// The fitted water (use [`Self::or`]: only the [`Self::accepted`] channels are meant,
    /// and of the others only the [`Self::determined`] coefficients).
    pub medium: MediumParams,
    /// Channels R, G, B with all three coefficients [`Self::determined`].
    pub accepted: [bool; 3],
    /// Per channel, the coefficients whose standard error is within its gate and which are
    /// not at the search's bound (`beta` of 20 or 3e-4 per metre), when `B_inf` is one of
    /// them (none otherwise). With [`MediumEstimateConfig::per_coefficient`] off, all of an
    /// accepted channel's, none of another's.
    pub determined: [Coefficients; 3],
    /// Depth blocks used.
    pub samples: usize,
    /// Pixels that saw open water (inverse depth 0).
    pub open_water_pixels: usize,
    /// Range of the samples, metres (smallest, largest).
    pub range_m: (f64, f64),
    /// View pairs behind each channel's `beta_D`.
    pub attenuation_pairs: [usize; 3],
    /// Standard errors of the two-view fit: relative for `beta_D` and `beta_B` (they are
    /// fitted in log), absolute for `B_inf`.
    pub std_error: MediumParams,
    /// RMS residual of the backscatter fit per channel (fraction of full scale).
    pub backscatter_rms: [f64; 3],
}

impl MediumEstimate {
    /// The estimate with the coefficients it did not determine taken from `fallback`.
    pub fn or(&self, fallback: &MediumParams) -> MediumParams {
        let mut m = *fallback;
        set_coefficients(&mut m, &self.medium, self.determined);
        m
    }
}

/// One depth block.
#[derive(Clone, Copy, Debug)]
struct Sample {
    keyframe: usize,
    colour: [f64; 3],
    range_m: f64,
    point_in_world: Point3<f64>,
}

/// Per keyframe: range per pixel (NaN where unusable, +inf for open water) and the image as f64.
struct View<'a> {
    kf: &'a Keyframe,
    range_m: Vec<f64>,
}

fn ray_length(kf: &Keyframe, x: f64, y: f64) -> f64 {
    let c = &kf.camera;
    let (a, b) = ((x - c.cx) / c.fx, (y - c.cy) / c.fy);
    (a * a + b * b + 1.0).sqrt()
}

fn view_of<'a>(kf: &'a Keyframe, cfg: &MediumEstimateConfig) -> Result<View<'a>, MediumEstimateError> {
    if !kf.is_consistent() {
        return Err(MediumEstimateError::BadKeyframe { index: kf.index, why: "image, inverse depth and variance sizes differ from the camera's" });
    }
    if kf.camera.distortion.is_some() {
        return Err(MediumEstimateError::BadKeyframe { index: kf.index, why: "the camera must be undistorted" });
    }
    let (w, h) = (kf.camera.width, kf.camera.height);
    let mut range_m = vec![f64::NAN; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let d = kf.inv_depth.data[i] as f64;
            let var = kf.inv_depth_variance.data[i] as f64;
            if d == 0.0 {
                range_m[i] = f64::INFINITY;
            } else if d > 0.0 && d.is_finite() && var.is_finite() && var >= 0.0 && var.sqrt() <= cfg.max_rel_std * d {
                range_m[i] = ray_length(kf, x as f64, y as f64) / d;
            }
        }
    }
    Ok(View { kf, range_m })
}

/// Depth blocks of one keyframe and its open-water colour sum and count.
fn samples_of(view: &View, k: usize, cfg: &MediumEstimateConfig, out: &mut Vec<Sample>, open: &mut ([f64; 3], usize)) {
    let kf = view.kf;
    let (w, h) = (kf.camera.width, kf.camera.height);
    let b = cfg.block_px;
    for (i, r) in view.range_m.iter().enumerate() {
        if r.is_infinite() {
            for c in 0..3 {
                open.0[c] += kf.image.data[i * 3 + c] as f64 / 255.0;
            }
            open.1 += 1;
        }
    }
    for by in 0..h / b {
        'blocks: for bx in 0..w / b {
            let (mut lo, mut hi, mut sum_r, mut colour) = (f64::INFINITY, 0.0f64, 0.0, [0.0; 3]);
            for y in by * b..(by + 1) * b {
                for x in bx * b..(bx + 1) * b {
                    let i = y * w + x;
                    let r = view.range_m[i];
                    if !r.is_finite() {
                        continue 'blocks;
                    }
                    lo = lo.min(r);
                    hi = hi.max(r);
                    sum_r += r;
                    for (c, v) in colour.iter_mut().enumerate() {
                        *v += kf.image.data[i * 3 + c] as f64 / 255.0;
                    }
                }
            }
            let n = (b * b) as f64;
            let range_m = sum_r / n;
            if hi - lo > cfg.max_block_range_spread * range_m {
                continue;
            }
            let (xc, yc) = ((bx * b) as f64 + 0.5 * (b as f64 - 1.0), (by * b) as f64 + 0.5 * (b as f64 - 1.0));
            let z = range_m / ray_length(kf, xc, yc);
            let c = &kf.camera;
            let p_in_cam = Point3::new((xc - c.cx) / c.fx * z, (yc - c.cy) / c.fy * z, z);
            out.push(Sample { keyframe: k, colour: colour.map(|v| v / n), range_m, point_in_world: kf.world_from_cam * p_in_cam });
        }
    }
}

/// Backscatter curve `B_inf (1 - exp(-beta_B r))` of one channel.
#[derive(Clone, Copy, Debug)]
struct Backscatter {
    b_inf: f64,
    beta_b: f64,
}

impl Backscatter {
    fn at(&self, r: f64) -> f64 {
        if r.is_infinite() {
            self.b_inf
        } else {
            self.b_inf * (1.0 - (-self.beta_b * r).exp())
        }
    }
}

/// Log-spaced grid of `n` values from `lo` to `hi`.
fn log_grid(lo: f64, hi: f64, n: usize) -> impl Iterator<Item = f64> {
    (0..n).map(move |k| lo * (hi / lo).powf(k as f64 / (n - 1) as f64))
}

/// Non-negative least squares of `y ~ a u + b v` (weights `w`), `a <= 1`; returns `(a, b, sse)`.
fn nnls2(points: &[(f64, f64, f64, f64)]) -> (f64, f64, f64) {
    let sse = |a: f64, b: f64| points.iter().map(|&(u, v, y, w)| w * (y - a * u - b * v).powi(2)).sum::<f64>();
    let (mut suu, mut suv, mut svv, mut suy, mut svy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(u, v, y, w) in points {
        suu += w * u * u;
        suv += w * u * v;
        svv += w * v * v;
        suy += w * u * y;
        svy += w * v * y;
    }
    let mut candidates = Vec::with_capacity(4);
    let det = suu * svv - suv * suv;
    if det.abs() > 1e-12 * (suu * svv).max(1e-300) {
        let a = (suy * svv - svy * suv) / det;
        let b = (svy * suu - suy * suv) / det;
        if a >= 0.0 && a <= 1.0 && b >= 0.0 {
            candidates.push((a, b));
        }
    }
    // On the boundary: one of them at a bound, the other free (clamped).
    if suu > 0.0 {
        candidates.push(((suy / suu).clamp(0.0, 1.0), 0.0));
    }
    if svv > 0.0 {
        candidates.push((0.0, (svy / svv).max(0.0)));
        candidates.push((1.0, ((svy - suv) / svv).max(0.0)));
    }
    candidates.push((0.0, 0.0));
    candidates.into_iter().map(|(a, b)| (a, b, sse(a, b))).fold((0.0, 0.0, f64::INFINITY), |best, c| if c.2 < best.2 { c } else { best })
}

/// Per range bin: mean range and mean colour of its darkest samples.
fn dark_bins(samples: &[Sample], cfg: &MediumEstimateConfig) -> Vec<(f64, [f64; 3])> {
    let mut order: Vec<usize> = (0..samples.len()).collect();
    order.sort_by(|&a, &b| samples[a].range_m.total_cmp(&samples[b].range_m));
    let bins = cfg.range_bins.min(samples.len());
    let mut out = Vec::with_capacity(bins);
    for k in 0..bins {
        let bin = &order[k * order.len() / bins..(k + 1) * order.len() / bins];
        let mut by_brightness: Vec<usize> = bin.to_vec();
        by_brightness.sort_by(|&a, &b| samples[a].colour.iter().sum::<f64>().total_cmp(&samples[b].colour.iter().sum::<f64>()));
        let take = ((bin.len() as f64 * cfg.dark_fraction).ceil() as usize).clamp(1, bin.len());
        let (mut r, mut colour) = (0.0, [0.0; 3]);
        for &s in &by_brightness[..take] {
            r += samples[s].range_m;
            for c in 0..3 {
                colour[c] += samples[s].colour[c];
            }
        }
        out.push((r / take as f64, colour.map(|v| v / take as f64)));
    }
    out
}

/// Fits one channel's backscatter to the dark bins (and the open-water mean), with the
/// residual direct term decaying at `beta_d`; returns the curve and the RMS residual.
fn fit_backscatter(bins: &[(f64, [f64; 3])], open: Option<f64>, c: usize, beta_d: f64, open_weight: f64) -> (Backscatter, f64) {
    let mut best = (Backscatter { b_inf: 0.0, beta_b: 1.0 }, f64::INFINITY);
    let mut points: Vec<(f64, f64, f64, f64)> = Vec::with_capacity(bins.len() + 1);
    for beta_b in log_grid(0.005, 8.0, 400) {
        points.clear();
        points.extend(bins.iter().map(|&(r, col)| (1.0 - (-beta_b * r).exp(), (-beta_d * r).exp(), col[c], 1.0)));
        if let Some(v) = open {
            points.push((1.0, 0.0, v, open_weight));
        }
        let (b_inf, _, sse) = nnls2(&points);
        if sse < best.1 {
            best = (Backscatter { b_inf, beta_b }, sse);
        }
    }
    let weight: f64 = bins.len() as f64 + if open.is_some() { open_weight } else { 0.0 };
    (best.0, (best.1 / weight).sqrt())
}

/// Box mean of `image` channel values over a `side` x `side` window centred on pixel
/// `(x, y)` (clipped to the image), as fractions of full scale.
fn box_mean(kf: &Keyframe, x: usize, y: usize, side: usize) -> [f64; 3] {
    let (w, h) = (kf.camera.width, kf.camera.height);
    let half = side / 2;
    let (x0, y0) = (x.saturating_sub(half), y.saturating_sub(half));
    let (x1, y1) = ((x0 + side).min(w), (y0 + side).min(h));
    let mut colour = [0.0; 3];
    for yy in y0..y1 {
        for xx in x0..x1 {
            for (c, v) in colour.iter_mut().enumerate() {
                *v += kf.image.data[(yy * w + xx) * 3 + c] as f64 / 255.0;
            }
        }
    }
    let n = ((x1 - x0) * (y1 - y0)) as f64;
    colour.map(|v| v / n)
}

/// One surface point seen from two keyframes: ranges and colours.
#[derive(Clone, Copy, Debug)]
struct Pair {
    r: [f64; 2],
    colour: [[f64; 3]; 2],
}

/// Each sample projected into the other keyframes where it is in view and not occluded, at
/// most `max_partners` of them per sample: those where its range differs most.
fn view_pairs(views: &[View], samples: &[Sample], cfg: &MediumEstimateConfig) -> Vec<Pair> {
    let cams_from_world: Vec<_> = views.iter().map(|v| v.kf.world_from_cam.inverse()).collect();
    let mut pairs = Vec::with_capacity(samples.len() * cfg.max_partners.min(views.len().saturating_sub(1)));
    // This sample's partners: (range difference, pair), the largest differences kept.
    let mut partners: Vec<(f64, Pair)> = Vec::with_capacity(views.len());
    for s in samples {
        partners.clear();
        for (j, view) in views.iter().enumerate() {
            if j == s.keyframe {
                continue;
            }
            let p: Vector3<f64> = (cams_from_world[j] * s.point_in_world).coords;
            if p.z <= 0.0 {
                continue;
            }
            let c = &view.kf.camera;
            let (u, v) = (c.fx * p.x / p.z + c.cx, c.fy * p.y / p.z + c.cy);
            let (xi, yi) = (u.round(), v.round());
            if xi < 0.0 || yi < 0.0 || xi >= c.width as f64 || yi >= c.height as f64 {
                continue;
            }
            let (xi, yi) = (xi as usize, yi as usize);
            let r_j = p.norm();
            let seen = view.range_m[yi * c.width + xi];
            if !seen.is_finite() || (seen - r_j).abs() > cfg.occlusion_tolerance * r_j {
                continue;
            }
            if (r_j - s.range_m).abs() < cfg.min_range_difference_m {
                continue;
            }
            // The block's footprint in the other view, in pixels.
            let side = ((cfg.block_px as f64 * s.range_m / r_j).round() as usize).max(1);
            partners.push(((r_j - s.range_m).abs(), Pair { r: [s.range_m, r_j], colour: [s.colour, box_mean(view.kf, xi, yi, side)] }));
        }
        if partners.len() > cfg.max_partners {
            // Largest range difference first; ties keep keyframe order (a stable sort).
            partners.sort_by(|a, b| b.0.total_cmp(&a.0));
            partners.truncate(cfg.max_partners);
        }
        pairs.extend(partners.iter().map(|&(_, p)| p));
    }
    pairs
}

/// Robust slope `beta_D` of `ln D_j - ln D_i = -beta_D (r_j - r_i)` for channel `c`; `None`
/// with fewer than `min_pairs` usable pairs. Returns the slope and the pairs used.
fn fit_attenuation(pairs: &[Pair], bs: &Backscatter, c: usize, cfg: &MediumEstimateConfig) -> (Option<f64>, usize) {
    // (dr, dlnD, weight)
    let mut rows: Vec<(f64, f64, f64)> = Vec::with_capacity(pairs.len());
    for p in pairs {
        let d0 = p.colour[0][c] - bs.at(p.r[0]);
        let d1 = p.colour[1][c] - bs.at(p.r[1]);
        if d0 < cfg.min_direct || d1 < cfg.min_direct {
            continue;
        }
        // The variance of ln D from a fixed noise in D is ~ 1/D^2: weight by the smaller D squared.
        let w = d0.min(d1).powi(2);
        rows.push((p.r[1] - p.r[0], d1.ln() - d0.ln(), w));
    }
    if rows.len() < cfg.min_pairs.max(1) {
        return (None, rows.len());
    }
    let (num, den) = rows.iter().fold((0.0, 0.0), |(n, d), &(dr, dl, w)| (n + w * dr * dl, d + w * dr * dr));
    let mut beta = if den > 0.0 { -num / den } else { f64::NAN };
    for _ in 0..3 {
        // Tukey's biweight on the residuals, scale from their median absolute value.
        let mut abs_res: Vec<f64> = rows.iter().map(|&(dr, dl, _)| (dl + beta * dr).abs()).collect();
        let mid = abs_res.len() / 2;
        let scale = 4.685 * 1.4826 * abs_res.select_nth_unstable_by(mid, f64::total_cmp).1.max(1e-6);
        let (mut num, mut den) = (0.0, 0.0);
        for &(dr, dl, w) in &rows {
            let u = (dl + beta * dr) / scale;
            let rw = if u.abs() < 1.0 { w * (1.0 - u * u).powi(2) } else { 0.0 };
            num += rw * dr * dl;
            den += rw * dr * dr;
        }
        if den > 0.0 {
            beta = -num / den;
        }
    }
    ((beta.is_finite()).then_some(beta.max(0.0)), rows.len())
}

/// Bounds of the two-view fit's `ln beta_B` and `ln beta_D` (3.4e-4 to 20 per metre).
const LN_BETA_RANGE: (f64, f64) = (-8.0, 3.0);

/// Model of one channel: veiling light, backscatter and attenuation coefficients.
#[derive(Clone, Copy, Debug, PartialEq)]
struct ChannelModel {
    b_inf: f64,
    beta_b: f64,
    beta_d: f64,
}

impl ChannelModel {
    fn backscatter(&self) -> Backscatter {
        Backscatter { b_inf: self.b_inf, beta_b: self.beta_b }
    }
    /// Parameters of the search: `(B_inf, ln beta_B, ln beta_D)`.
    fn theta(&self) -> [f64; 3] {
        [self.b_inf, self.beta_b.ln(), self.beta_d.ln()]
    }
    fn from_theta(t: [f64; 3]) -> Self {
        let (lo, hi) = LN_BETA_RANGE;
        ChannelModel { b_inf: t[0].clamp(0.0, 1.0), beta_b: t[1].clamp(lo, hi).exp(), beta_d: t[2].clamp(lo, hi).exp() }
    }
}

/// Residuals of the two-view model for channel `c`, one per pair, plus the open-water one:
/// `I_j - B(r_j) - (I_i - B(r_i)) exp(-beta_D (r_j - r_i))`, scaled by
/// `1 / sqrt(1 + exp(-2 beta_D (r_j - r_i)))` (both colours are noisy: orthogonal distance).
fn pair_residuals(m: &ChannelModel, pairs: &[Pair], c: usize, open: Option<(f64, f64)>, out: &mut Vec<f64>) {
    out.clear();
    let bs = m.backscatter();
    out.extend(pairs.iter().map(|p| {
        let t = (-m.beta_d * (p.r[1] - p.r[0])).exp();
        (p.colour[1][c] - bs.at(p.r[1]) - (p.colour[0][c] - bs.at(p.r[0])) * t) / (1.0 + t * t).sqrt()
    }));
    if let Some((v, weight)) = open {
        out.push((m.b_inf - v) * weight.sqrt());
    }
}

/// [`pair_residuals`] at `theta` (`(B_inf, ln beta_B, ln beta_D)`, inside the search's range)
/// with their derivatives by `theta`, row by row into `jac`: one pass, three exponentials a
/// pair (central differences took 21). The unit test holds them to central differences.
fn pair_residuals_and_jacobian(theta: [f64; 3], pairs: &[Pair], c: usize, open: Option<(f64, f64)>, out: &mut Vec<f64>, jac: &mut Vec<[f64; 3]>) {
    let m = ChannelModel::from_theta(theta);
    out.clear();
    jac.clear();
    for p in pairs {
        let (r0, r1) = (p.r[0], p.r[1]);
        let (e0, e1) = ((-m.beta_b * r0).exp(), (-m.beta_b * r1).exp());
        let t = (-m.beta_d * (r1 - r0)).exp();
        let direct0 = p.colour[0][c] - m.b_inf * (1.0 - e0);
        let n = p.colour[1][c] - m.b_inf * (1.0 - e1) - direct0 * t;
        let s = (1.0 + t * t).sqrt();
        // d/dB_inf of B(r) is 1 - exp(-beta_B r); d/d(ln beta_B) is B_inf beta_B r exp(-beta_B r).
        let d_b_inf = (-(1.0 - e1) + (1.0 - e0) * t) / s;
        let d_beta_b = m.b_inf * m.beta_b * (-r1 * e1 + r0 * e0 * t) / s;
        // t = exp(-beta_D (r1 - r0)): dt/d(ln beta_D) = -beta_D (r1 - r0) t; s depends on t too.
        let dt = -m.beta_d * (r1 - r0) * t;
        let d_beta_d = -direct0 * dt / s - n * t * dt / (s * s * s);
        out.push(n / s);
        jac.push([d_b_inf, d_beta_b, d_beta_d]);
    }
    if let Some((v, weight)) = open {
        out.push((m.b_inf - v) * weight.sqrt());
        jac.push([weight.sqrt(), 0.0, 0.0]);
    }
}

/// One channel's result of steps 2 to 5.
#[derive(Clone, Copy, Debug)]
struct ChannelFit {
    rms: f64,
    used: usize,
    model: ChannelModel,
    std_error: [f64; 3],
}

/// Least squares of the two-view model over `(B_inf, ln beta_B, ln beta_D)` from `start`
/// (Levenberg-Marquardt with the analytic Jacobian and Huber weights).
fn fit_two_view(pairs: &[Pair], c: usize, open: Option<(f64, f64)>, start: ChannelModel) -> (ChannelModel, [f64; 3]) {
    let mut theta = start.theta();
    let (mut r, mut r_trial, mut abs) = (Vec::new(), Vec::new(), Vec::new());
    let mut jac = Vec::new();
    let mut lambda = 1e-3;
    let mut std = [f64::INFINITY; 3];
    let cost = |t: [f64; 3], buf: &mut Vec<f64>, huber: f64| {
        pair_residuals(&ChannelModel::from_theta(t), pairs, c, open, buf);
        buf.iter().map(|&e| if e.abs() <= huber { 0.5 * e * e } else { huber * (e.abs() - 0.5 * huber) }).sum::<f64>()
    };
    for _ in 0..40 {
        pair_residuals_and_jacobian(theta, pairs, c, open, &mut r, &mut jac);
        abs.clear();
        abs.extend(r.iter().map(|e| e.abs()));
        let mid = abs.len() / 2;
        let huber = 1.345 * 1.4826 * abs.select_nth_unstable_by(mid, f64::total_cmp).1.max(1e-9);
        let mut jtj = nalgebra::Matrix3::<f64>::zeros();
        let mut jtr = nalgebra::Vector3::<f64>::zeros();
        for (row, &e) in jac.iter().zip(&r) {
            let w = if e.abs() <= huber { 1.0 } else { huber / e.abs() };
            let j = nalgebra::Vector3::new(row[0], row[1], row[2]);
            jtj += w * j * j.transpose();
            jtr += w * j * e;
        }
        // Standard errors of the parameters at this point: sigma^2 (J^T W J)^-1.
        let (wsum, dof) = (r.iter().map(|&e| if e.abs() <= huber { e * e } else { huber * e.abs() }).sum::<f64>(), r.len().saturating_sub(3).max(1));
        if let Some(inv) = jtj.try_inverse() {
            std = [0, 1, 2].map(|k| (inv[(k, k)] * wsum / dof as f64).max(0.0).sqrt());
        }
        // The cost at theta, from the residuals just computed (the same numbers `cost` makes).
        let now = r.iter().map(|&e| if e.abs() <= huber { 0.5 * e * e } else { huber * (e.abs() - 0.5 * huber) }).sum::<f64>();
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj;
            for k in 0..3 {
                a[(k, k)] *= 1.0 + lambda;
            }
            let Some(step) = a.lu().solve(&(-jtr)) else { lambda *= 10.0; continue };
            let trial = [theta[0] + step[0], theta[1] + step[1], theta[2] + step[2]];
            if cost(trial, &mut r_trial, huber) < now {
                theta = ChannelModel::from_theta(trial).theta();
                lambda = (lambda * 0.3).max(1e-9);
                improved = true;
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (ChannelModel::from_theta(theta), std)
}

/// Estimates the water from `keyframes` (image, pose, inverse depth and variance). `beta_d_start`
/// is the attenuation assumed for the residual direct term of the first backscatter fit.
pub fn estimate_medium(keyframes: &[&Keyframe], beta_d_start: [f64; 3], cfg: &MediumEstimateConfig) -> Result<MediumEstimate, MediumEstimateError> {
    cfg.validate()?;
    let views = keyframes.iter().map(|kf| view_of(kf, cfg)).collect::<Result<Vec<_>, _>>()?;
    let mut samples = Vec::new();
    let mut open = ([0.0; 3], 0usize);
    for (k, view) in views.iter().enumerate() {
        samples_of(view, k, cfg, &mut samples, &mut open);
    }
    let needed = cfg.range_bins * 4;
    if samples.len() < needed {
        return Err(MediumEstimateError::TooFewSamples { found: samples.len(), needed, keyframes: keyframes.len() });
    }
    let open_colour = (open.1 > 0).then(|| open.0.map(|v| v / open.1 as f64));
    let bins = dark_bins(&samples, cfg);
    let mut pairs = view_pairs(&views, &samples, cfg);
    if pairs.len() > cfg.max_pairs {
        // Evenly spaced: pair floor(m len / max) for m < max, in order.
        let len = pairs.len();
        for m in 0..cfg.max_pairs {
            pairs[m] = pairs[m * len / cfg.max_pairs];
        }
        pairs.truncate(cfg.max_pairs);
    }
    // Each channel's fits (steps 2 to 5) depend on no other channel's: the three run side by
    // side on threads of their own, which inherit the calling thread's cores and priority
    // (the mapping thread's placement); each computes exactly what it would alone.
    let open_weight = cfg.open_water_weight * pairs.len() as f64 / bins.len() as f64;
    let channel = |c: usize| -> ChannelFit {
        let mut beta_d = Some(beta_d_start[c]);
        let (mut backscatter, mut rms, mut used) = (Backscatter { b_inf: 0.0, beta_b: 1.0 }, 0.0, 0);
        for _ in 0..cfg.rounds {
            let decay = beta_d.unwrap_or(beta_d_start[c]);
            (backscatter, rms) = fit_backscatter(&bins, open_colour.map(|o| o[c]), c, decay, cfg.open_water_weight);
            (beta_d, used) = fit_attenuation(&pairs, &backscatter, c, cfg);
        }
        // Joint two-view fit of all three coefficients from the closed-form start.
        let start = ChannelModel { b_inf: backscatter.b_inf, beta_b: backscatter.beta_b.max(1e-3), beta_d: beta_d.unwrap_or(beta_d_start[c]).max(1e-3) };
        let (model, std_error) = if pairs.len() >= cfg.min_pairs { fit_two_view(&pairs, c, open_colour.map(|o| (o[c], open_weight)), start) } else { (start, [f64::INFINITY; 3]) };
        ChannelFit { rms, used, model, std_error }
    };
    let fits: [ChannelFit; 3] = std::thread::scope(|scope| {
        let channel = &channel;
        // A thread that cannot be made leaves its channel to this one.
        let spawned: [Option<std::thread::ScopedJoinHandle<'_, ChannelFit>>; 3] = std::array::from_fn(|c| std::thread::Builder::new().name("medium-estimate".into()).spawn_scoped(scope, move || channel(c)).ok());
        let mut joined = spawned.into_iter().enumerate().map(|(c, h)| match h.map(|h| h.join()) {
            Some(Ok(fit)) => fit,
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            None => channel(c),
        });
        std::array::from_fn(|_| joined.next().expect("three channels"))
    });
    let rms = fits.map(|f| f.rms);
    let used = fits.map(|f| f.used);
    let models = fits.map(|f| f.model);
    let std_error = fits.map(|f| f.std_error);
    let (lo, hi) = samples.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), s| (lo.min(s.range_m), hi.max(s.range_m)));
    // Every sample enters up to one pair per other keyframe, so the pairs are not independent:
    // the standard errors are scaled as if there were one observation per sample.
    let reuse = (pairs.len() as f64 / samples.len() as f64).max(1.0).sqrt();
    let std_error = std_error.map(|s| s.map(|v| v * reuse));
    let determined: [Coefficients; 3] = std::array::from_fn(|c| {
        let (s, theta) = (std_error[c], models[c].theta());
        let inside = |ln: f64| ln > LN_BETA_RANGE.0 + 1e-6 && ln < LN_BETA_RANGE.1 - 1e-6;
        let d = Coefficients {
            b_inf: s[0] < cfg.max_b_inf_std_error,
            beta_b: s[1] < cfg.max_rel_std_error && inside(theta[1]),
            beta_d: s[2] < cfg.max_rel_std_error && inside(theta[2]),
        };
        // Nothing of a channel whose veiling light is unknown: its attenuation was fitted to
        // colours with an unknown backscatter removed (turbid blue from 4 tracked keyframes:
        // `beta_D` 0.25 against 0.75, with a standard error of 2.4 %).
        if d.all() || (cfg.per_coefficient && d.b_inf) {
            d
        } else {
            Coefficients::NONE
        }
    });
    Ok(MediumEstimate {
        accepted: determined.map(Coefficients::all),
        determined,
        medium: MediumParams {
            beta_d: models.map(|m| m.beta_d),
            beta_b: models.map(|m| m.beta_b),
            b_inf: models.map(|m| m.b_inf),
        },
        samples: samples.len(),
        open_water_pixels: open.1,
        range_m: (lo, hi),
        attenuation_pairs: used,
        std_error: MediumParams { beta_d: std_error.map(|s| s[2]), beta_b: std_error.map(|s| s[1]), b_inf: std_error.map(|s| s[0]) },
        backscatter_rms: rms,
    })
}

/// A Gaussian prior on the medium from an accepted estimate: after the estimate sets the
/// medium, the joint optimisation may refine it, but the photometric loss constrains some
/// directions of the medium only weakly (in clear water the backscatter is nearly linear in
/// range, so only `B_inf beta_B` is seen), and without a prior they drift.
///
/// Per pixel of a view and per channel `c`, the sum of the terms of the coefficients it holds:
/// `0.5 [ ((ln sigma_att - ln beta_D) / s)^2 + ((ln sigma_bs - ln beta_B) / s)^2 + ((c_med - B_inf) / s_B)^2 ]`
/// with `s = rel_std`, `s_B = b_inf_std`; the loss is `weight` times the mean over pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MediumPrior {
    pub medium: MediumParams,
    /// Per channel, the coefficients the prior holds (those the estimates determined).
    pub held: [Coefficients; 3],
    pub weight: f64,
    pub rel_std: f64,
    pub b_inf_std: f64,
}

impl MediumPrior {
    /// The prior's loss on a view's medium planes (`c_med`, `sigma_att`, `sigma_bs`, R G B
    /// each per pixel, [`super::medium`]'s layout), with its gradient added to `grad` (same layout).
    pub fn loss_and_grad<T: super::real::Real>(&self, planes9: &[T], grad: &mut [T]) -> f64 {
        use super::medium::{C_MED, MEDIUM_CHANNELS, SIGMA_ATT, SIGMA_BS};
        let pixels = planes9.len() / MEDIUM_CHANNELS;
        if pixels == 0 || self.weight == 0.0 {
            return 0.0;
        }
        let k = self.weight / pixels as f64;
        let (s2, sb2) = (self.rel_std * self.rel_std, self.b_inf_std * self.b_inf_std);
        let mut loss = 0.0;
        for (px, g) in planes9.chunks_exact(MEDIUM_CHANNELS).zip(grad.chunks_exact_mut(MEDIUM_CHANNELS)) {
            for (c, held) in self.held.iter().enumerate() {
                for (at, target, on) in [(SIGMA_ATT + c, self.medium.beta_d[c], held.beta_d), (SIGMA_BS + c, self.medium.beta_b[c], held.beta_b)] {
                    if on {
                        let v = px[at].to_f64().max(1e-12);
                        let e = v.ln() - target.ln();
                        loss += 0.5 * e * e / s2;
                        g[at] = g[at] + T::from_f64(k * e / (s2 * v));
                    }
                }
                if held.b_inf {
                    let e = px[C_MED + c].to_f64() - self.medium.b_inf[c];
                    loss += 0.5 * e * e / sb2;
                    g[C_MED + c] = g[C_MED + c] + T::from_f64(k * e / sb2);
                }
            }
        }
        k * loss
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_sim::keyframes::sim_keyframes;
    use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};

    fn generated(water: WaterPreset, pitch_down_deg: f64, frames: usize) -> (Vec<Keyframe>, MediumParams) {
        let mut cfg = SimConfig::preset(water, TrajectoryKind::Survey);
        cfg.frames = frames;
        cfg.vignetting = 0.0;
        cfg.pitch_down_deg = pitch_down_deg;
        let r = SimRenderer::new(&cfg).unwrap();
        (sim_keyframes(&r, 5, 64).into_iter().map(|s| s.keyframe).collect(), *r.medium())
    }

    #[test]
    fn the_prior_gradient_matches_central_differences() {
        let prior = MediumPrior {
            medium: MediumParams { beta_d: [0.4, 0.1, 0.08], beta_b: [0.3, 0.07, 0.05], b_inf: [0.03, 0.2, 0.45] },
            // Whole, none, and a channel whose beta_B is free.
            held: [Coefficients::ALL, Coefficients::NONE, Coefficients { beta_d: true, beta_b: false, b_inf: true }],
            weight: 0.7,
            rel_std: 0.1,
            b_inf_std: 0.02,
        };
        let mut rng = duv_core::rng::Rng::new(3);
        let planes: Vec<f64> = (0..9 * 5).map(|_| rng.range(0.02, 0.9)).collect();
        let mut grad = vec![0.0; planes.len()];
        let loss = prior.loss_and_grad(&planes, &mut grad);
        assert!(loss > 0.0);
        let mut worst = 0.0f64;
        for i in 0..planes.len() {
            let (mut p, mut m) = (planes.clone(), planes.clone());
            p[i] += 1e-6;
            m[i] -= 1e-6;
            let mut scratch = vec![0.0; planes.len()];
            let fd = (prior.loss_and_grad(&p, &mut scratch) - prior.loss_and_grad(&m, &mut scratch)) / 2e-6;
            worst = worst.max((fd - grad[i]).abs() / fd.abs().max(1e-3));
        }
        assert!(worst < 1e-6, "worst relative gradient error {worst}");
        // The green channel is not held, nor blue's beta_B: no gradient there; the rest has one.
        for px in grad.chunks_exact(9) {
            assert_eq!([px[1], px[4], px[7], px[8]], [0.0; 4]);
            assert!([px[0], px[3], px[6], px[2], px[5]].iter().all(|&g| g != 0.0), "{px:?}");
        }
        // At the prior's own water the loss is zero.
        let at: Vec<f64> = (0..5).flat_map(|_| [0.03, 0.2, 0.45, 0.4, 0.1, 0.08, 0.3, 0.07, 0.05]).collect();
        assert!(prior.loss_and_grad(&at, &mut vec![0.0; 45]).abs() < 1e-12);
    }

    #[test]
    fn the_two_view_jacobian_matches_central_differences() {
        let mut rng = duv_core::rng::Rng::new(5);
        let pairs: Vec<Pair> = (0..200)
            .map(|_| {
                let r0 = 0.5 + 6.0 * rng.uniform();
                let r1 = r0 + 4.0 * (rng.uniform() - 0.5);
                Pair { r: [r0, r1.max(0.2)], colour: [[0.0; 3].map(|_| rng.uniform()), [0.0; 3].map(|_| rng.uniform())] }
            })
            .collect();
        let (mut r, mut jac, mut plus, mut minus) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut worst = 0.0f64;
        for theta in [[0.3, -0.5, -1.2], [0.05, -2.0, 0.3], [0.8, 0.4, -2.5]] {
            for c in 0..3 {
                let open = Some((0.25, 40.0));
                pair_residuals_and_jacobian(theta, &pairs, c, open, &mut r, &mut jac);
                pair_residuals(&ChannelModel::from_theta(theta), &pairs, c, open, &mut plus);
                assert_eq!(r, plus, "the same residuals as pair_residuals, bit for bit");
                assert_eq!(jac.len(), r.len());
                for k in 0..3 {
                    let h = 1e-6;
                    let (mut tp, mut tm) = (theta, theta);
                    tp[k] += h;
                    tm[k] -= h;
                    pair_residuals(&ChannelModel::from_theta(tp), &pairs, c, open, &mut plus);
                    pair_residuals(&ChannelModel::from_theta(tm), &pairs, c, open, &mut minus);
                    for (i, row) in jac.iter().enumerate() {
                        let numeric = (plus[i] - minus[i]) / (2.0 * h);
                        let err = (row[k] - numeric).abs() / numeric.abs().max(1e-3);
                        worst = worst.max(err);
                        assert!(err < 1e-5, "theta {theta:?} channel {c} parameter {k} pair {i}: analytic {} numeric {numeric}", row[k]);
                    }
                }
            }
        }
        assert!(worst > 0.0, "the comparison ran");
    }

    #[test]
    fn turbid_and_coastal_water_are_recovered_within_15_percent_from_four_generated_keyframes() {
        for water in [WaterPreset::Turbid, WaterPreset::Coastal] {
            let (kfs, truth) = generated(water, 40.0, 20);
            assert_eq!(kfs.len(), 4);
            let refs: Vec<&Keyframe> = kfs.iter().collect();
            let e = estimate_medium(&refs, [0.3, 0.15, 0.1], &MediumEstimateConfig::default()).unwrap();
            assert_eq!(e.accepted, [true; 3], "{water:?}: {e:?}");
            let worst = e.medium.worst_rel_error(&truth);
            // Measured: turbid 0.036, coastal 0.048.
            assert!(worst < 0.15, "{water:?}: worst relative error {worst}: {:?} vs {truth:?}", e.medium);
            assert!(e.samples > 1000 && e.attenuation_pairs.iter().all(|&p| p > 1000), "{e:?}");
            // The camera is 2 m above the seabed; nothing beyond the generator's max range is a sample.
            assert!(e.range_m.0 > 1.5 && e.range_m.1 < 22.0, "{:?}", e.range_m);
        }
    }

    #[test]
    fn clear_water_is_refused_from_four_keyframes_and_recovered_from_eight() {
        // Four keyframes 0.75 m apart change the green and blue direct signal by ~5%: too
        // little to separate backscatter from albedo, and the fit says so.
        let (kfs, truth) = generated(WaterPreset::Clear, 40.0, 20);
        let refs: Vec<&Keyframe> = kfs.iter().collect();
        let e = estimate_medium(&refs, [0.3, 0.15, 0.1], &MediumEstimateConfig::default()).unwrap();
        assert!(!e.accepted[1] && !e.accepted[2], "{e:?}");
        // Their backscatter's B_inf-beta_B trade-off leaves beta_B undetermined.
        assert!(!e.determined[1].beta_b && !e.determined[2].beta_b, "{e:?}");
        assert!(e.determined.iter().all(|d| d.b_inf || !d.any()), "nothing without B_inf: {e:?}");
        let fallback = MediumParams { beta_d: [9.0; 3], beta_b: [8.0; 3], b_inf: [0.7; 3] };
        let kept = e.or(&fallback);
        for c in 0..3 {
            let d = e.determined[c];
            assert_eq!(kept.beta_d[c], if d.beta_d { e.medium.beta_d[c] } else { 9.0 });
            assert_eq!(kept.beta_b[c], if d.beta_b { e.medium.beta_b[c] } else { 8.0 });
            assert_eq!(kept.b_inf[c], if d.b_inf { e.medium.b_inf[c] } else { 0.7 });
        }
        assert_eq!(Coefficients { beta_d: true, beta_b: false, b_inf: true }.to_string(), "beta_D+B_inf");
        assert_eq!((Coefficients::ALL.to_string(), Coefficients::NONE.to_string()), ("all".into(), "none".into()));
        // A channel at a time: the same fit, nothing of a channel short of all three.
        let whole = MediumEstimateConfig { per_coefficient: false, ..MediumEstimateConfig::default() };
        let w = estimate_medium(&refs, [0.3, 0.15, 0.1], &whole).unwrap();
        assert_eq!((w.medium, w.accepted), (e.medium, e.accepted));
        for c in 0..3 {
            assert_eq!(w.determined[c], if e.accepted[c] { Coefficients::ALL } else { Coefficients::NONE });
        }
        let (kfs, _) = generated(WaterPreset::Clear, 40.0, 40);
        let refs: Vec<&Keyframe> = kfs.iter().collect();
        let e = estimate_medium(&refs, [0.3, 0.15, 0.1], &MediumEstimateConfig::default()).unwrap();
        assert_eq!(e.accepted, [true; 3], "{e:?}");
        let worst = e.medium.worst_rel_error(&truth);
        // Measured: 0.131 (beta_B blue).
        assert!(worst < 0.15, "worst relative error {worst}: {:?} vs {truth:?}", e.medium);
    }

    #[test]
    fn the_pairs_are_capped_per_sample_and_in_all_and_the_turbid_water_is_still_recovered() {
        let (kfs, truth) = generated(WaterPreset::Turbid, 40.0, 40);
        assert_eq!(kfs.len(), 8);
        let refs: Vec<&Keyframe> = kfs.iter().collect();
        let one = MediumEstimateConfig { max_partners: 1, max_pairs: usize::MAX, ..MediumEstimateConfig::default() };
        let e = estimate_medium(&refs, [0.3, 0.15, 0.1], &one).unwrap();
        assert!(e.attenuation_pairs.iter().all(|&p| p > 1000 && p <= e.samples), "{e:?}");
        let capped = MediumEstimateConfig { max_pairs: 5_000, ..MediumEstimateConfig::default() };
        let e = estimate_medium(&refs, [0.3, 0.15, 0.1], &capped).unwrap();
        assert!(e.attenuation_pairs.iter().all(|&p| p > 1000 && p <= 5_000), "{e:?}");
        let e = estimate_medium(&refs, [0.3, 0.15, 0.1], &MediumEstimateConfig::default()).unwrap();
        assert_eq!(e.accepted, [true; 3], "{e:?}");
        let worst = e.medium.worst_rel_error(&truth);
        assert!(worst < 0.15, "worst relative error {worst}: {:?} vs {truth:?}", e.medium);
        let bad = MediumEstimateConfig { max_pairs: 10, ..MediumEstimateConfig::default() };
        assert!(matches!(estimate_medium(&refs, [0.3; 3], &bad), Err(MediumEstimateError::InvalidConfig { field: "max_pairs", .. })));
    }

    #[test]
    fn keyframes_without_usable_depth_are_an_error_that_says_so() {
        let (mut kfs, _) = generated(WaterPreset::Turbid, 40.0, 10);
        for kf in &mut kfs {
            kf.inv_depth_variance.data.fill(f32::NAN);
        }
        let refs: Vec<&Keyframe> = kfs.iter().collect();
        let err = estimate_medium(&refs, [0.3; 3], &MediumEstimateConfig::default()).unwrap_err();
        assert!(matches!(err, MediumEstimateError::TooFewSamples { found: 0, keyframes: 2, .. }), "{err}");
        assert!(err.to_string().contains("confident depth"), "{err}");
        kfs[1].inv_depth.data.truncate(5);
        let refs: Vec<&Keyframe> = kfs.iter().collect();
        let err = estimate_medium(&refs, [0.3; 3], &MediumEstimateConfig::default()).unwrap_err();
        assert!(matches!(err, MediumEstimateError::BadKeyframe { index: 5, .. }), "{err}");
        let bad = MediumEstimateConfig { dark_fraction: 0.0, ..MediumEstimateConfig::default() };
        assert!(matches!(bad.validate(), Err(MediumEstimateError::InvalidConfig { field: "dark_fraction", .. })));
    }

    #[test]
    fn two_variable_nnls_matches_a_brute_force_search() {
        let mut rng = duv_core::rng::Rng::new(9);
        for _ in 0..20 {
            let points: Vec<(f64, f64, f64, f64)> = (0..12).map(|_| (rng.range(0.0, 1.0), rng.range(0.0, 1.0), rng.range(-0.2, 1.2), rng.range(0.5, 2.0))).collect();
            let (a, b, sse) = nnls2(&points);
            assert!((0.0..=1.0).contains(&a) && b >= 0.0);
            let cost = |a: f64, b: f64| points.iter().map(|&(u, v, y, w)| w * (y - a * u - b * v).powi(2)).sum::<f64>();
            assert!((cost(a, b) - sse).abs() < 1e-9);
            let mut best = f64::INFINITY;
            for i in 0..=200 {
                for j in 0..=400 {
                    best = best.min(cost(i as f64 / 200.0, j as f64 / 200.0));
                }
            }
            assert!(sse <= best + 1e-9, "nnls {sse} vs grid {best}");
        }
    }
}
