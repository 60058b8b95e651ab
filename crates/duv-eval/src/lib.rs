//! Metrics against ground truth, computed so that they agree with the reference tools:
//! trajectory association, Umeyama alignment, ATE and RPE as evo computes them
//! ([`sync`], [`align`], [`trajectory`]); PSNR and SSIM as scikit-image (or the 3DGS papers)
//! compute them ([`image`]); the sparsification error of depth uncertainty ([`ause`]);
//! the map's figures of a run ([`map_quality`]); and the report with its figures ([`report`]; the figures, drawn with `plotters`, only with
//! the `figures` feature, in `plot`).
//!
//! Everything takes in-memory data; only [`report::write_report`] and the `duv eval`
//! command touch files.

pub mod align;
pub mod ause;
pub mod image;
pub mod load;
pub mod map_quality;
#[cfg(feature = "figures")]
pub mod plot;
pub mod report;
pub mod stats;
pub mod sync;
pub mod trajectory;

pub use align::{umeyama, Alignment, AlignmentSummary};
pub use ause::{ause, AuseOptions, AuseResult};
pub use image::{psnr, ssim, SsimConvention};
pub use report::{build_report, write_report, AuseInput, EvalImage, EvalInputs, EvalOptions, Evaluation, ImagePair, Report};
pub use map_quality::{MapQuality, MapViewScore, RestoredScore, RestoredSummary};
pub use stats::ErrorStats;
pub use sync::{associate, DEFAULT_MAX_DT_NS};
pub use trajectory::{ate, evaluate_trajectory, rpe, AteResult, RpeResult, TrajectoryOptions};

use duv_core::io::IoError;
use std::path::PathBuf;

/// Errors of the `eval` module. Bad input is reported here, never by a panic.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Io(#[from] IoError),
    #[error("trajectory {name} has no poses")]
    EmptyTrajectory { name: String },
    #[error(
        "only {found} poses of {est} have a ground-truth pose in {gt} within {max_dt_secs} s; {needed} are needed \
         (check that both use the same clock, or raise --max-dt)"
    )]
    TooFewPairs { gt: String, est: String, max_dt_secs: f64, found: usize, needed: usize },
    #[error("{method} alignment is degenerate over {points} point pairs: {reason}")]
    DegenerateAlignment { method: Alignment, points: usize, reason: String },
    #[error("RPE over {delta} frames needs more than {delta} associated poses, found {poses}")]
    RpeDeltaTooLarge { delta: usize, poses: usize },
    #[error("images differ in size: {first} is {}x{}, {second} is {}x{}", first_size[0], first_size[1], second_size[0], second_size[1])]
    ImageSizeMismatch { first: String, second: String, first_size: [usize; 2], second_size: [usize; 2] },
    #[error("images differ in channels: {first} has {first_channels}, {second} has {second_channels}")]
    ImageChannelMismatch { first: String, second: String, first_channels: usize, second_channels: usize },
    #[error("{image}: sample {index} is {value}, not a finite number")]
    NonFiniteImage { image: String, index: usize, value: f32 },
    #[error("{image} is {width}x{height}; SSIM ({convention}) needs at least {min}x{min} pixels")]
    ImageTooSmall { image: String, width: usize, height: usize, min: usize, convention: SsimConvention },
    #[error("no image pairs: none of the PNG files in {rendered} has a namesake in {reference}")]
    NoImagePairs { rendered: PathBuf, reference: PathBuf },
    #[error("no depth maps: none of the files in {depth} has a namesake in both {variance} and {gt_depth}")]
    NoDepthTriples { depth: PathBuf, variance: PathBuf, gt_depth: PathBuf },
    #[error("AUSE needs one uncertainty per error: {errors} errors, {uncertainties} uncertainties")]
    AuseLengthMismatch { errors: usize, uncertainties: usize },
    #[error("AUSE needs at least one valid pixel")]
    AuseEmpty,
    #[error("AUSE input, pixel {index}: {problem} (error {error}, uncertainty {uncertainty})")]
    AuseBadValue { index: usize, error: f64, uncertainty: f64, problem: &'static str },
    #[error("AUSE: every error is zero, so the sparsification curves cannot be normalised")]
    AuseZeroError,
    /// A figure of the report could not be drawn.
    #[cfg(feature = "figures")]
    #[error("figure {figure}: {source}")]
    Figure { figure: &'static str, source: plot::PlotError },
    #[error("invalid {name} = {value}: {reason}")]
    InvalidParameter { name: &'static str, value: String, reason: &'static str },
    /// An error in one named input of several (an image pair, a keyframe).
    #[error("{what}: {source}")]
    In { what: String, source: Box<EvalError> },
}

impl EvalError {
    /// Wraps `self` with the name of the input it came from.
    pub fn within(self, what: impl Into<String>) -> Self {
        EvalError::In { what: what.into(), source: Box::new(self) }
    }
}

/// Serde helpers for `f64` values that may be infinite (PSNR of identical images): finite
/// values are JSON numbers, the others the strings `"inf"`, `"-inf"`, `"nan"` (JSON has no
/// infinity; `null` would lose which one it was).
pub mod f64_or_string {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else if v.is_nan() {
            s.serialize_str("nan")
        } else if *v > 0.0 {
            s.serialize_str("inf")
        } else {
            s.serialize_str("-inf")
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Repr {
            Num(f64),
            Text(String),
        }
        match Repr::deserialize(d)? {
            Repr::Num(v) => Ok(v),
            Repr::Text(t) => match t.as_str() {
                "inf" | "+inf" | "Infinity" => Ok(f64::INFINITY),
                "-inf" | "-Infinity" => Ok(f64::NEG_INFINITY),
                "nan" | "NaN" => Ok(f64::NAN),
                other => Err(serde::de::Error::custom(format!("expected a number, \"inf\", \"-inf\" or \"nan\", found {other:?}"))),
            },
        }
    }
}
