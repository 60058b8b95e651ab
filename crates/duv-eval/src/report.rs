//! The evaluation report: every metric of one run against its ground truth, built from
//! in-memory data ([`build_report`], what `duv demo` and `duv run` call) and written as
//! `report.json`, `report.md` and PNG figures ([`write_report`], what `duv eval` calls).
//! The figures are drawn only with the `figures` feature; without it the report lists none and
//! says why ([`FIGURES_NOT_BUILT`]).

use super::ause::{ause, AuseOptions};
use super::image::{psnr, ssim, SsimConvention};
#[cfg(feature = "figures")]
use super::plot::{self, Chart, Series, Style};
use super::trajectory::{evaluate_trajectory, TrajectoryEvaluation, TrajectoryOptions, TrajectoryReport};
use super::EvalError;
use duv_core::{FrameImage, ImageRgbF32, PlaneF32, StampedPose};
#[cfg(feature = "figures")]
use duv_core::{io::png_io, ImageRgb8};
use duv_core::io::{write_atomic, IoError};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Every option of an evaluation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalOptions {
    pub trajectory: TrajectoryOptions,
    pub ssim: SsimConvention,
    pub ause: AuseOptions,
}

/// An image for PSNR/SSIM: colour or grey, f32 in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub enum EvalImage {
    Rgb(ImageRgbF32),
    Gray(PlaneF32),
}

impl EvalImage {
    pub fn size(&self) -> [usize; 2] {
        match self {
            EvalImage::Rgb(i) => [i.width, i.height],
            EvalImage::Gray(i) => [i.width, i.height],
        }
    }
    pub fn channels(&self) -> usize {
        match self {
            EvalImage::Rgb(_) => 3,
            EvalImage::Gray(_) => 1,
        }
    }
}

impl From<&FrameImage> for EvalImage {
    /// 8-bit values scaled to [0, 1]; colour stays colour, grey stays grey.
    fn from(f: &FrameImage) -> Self {
        match f {
            FrameImage::Rgb8(i) => EvalImage::Rgb(i.to_rgb_f32()),
            FrameImage::Gray8(i) => EvalImage::Gray(i.to_gray_f32()),
        }
    }
}

/// A rendered image and the reference it should reproduce.
#[derive(Clone, Debug)]
pub struct ImagePair {
    /// Short name in the report (the file name, or a keyframe id).
    pub name: String,
    /// Where each image came from, for error messages (paths, or labels).
    pub rendered_label: String,
    pub reference_label: String,
    pub rendered: EvalImage,
    pub reference: EvalImage,
}

impl ImagePair {
    pub fn new(name: impl Into<String>, rendered: EvalImage, reference: EvalImage) -> Self {
        let name = name.into();
        ImagePair { rendered_label: format!("rendered {name}"), reference_label: format!("reference {name}"), name, rendered, reference }
    }

    /// PSNR (dB) and SSIM of the pair.
    pub fn scores(&self, convention: SsimConvention) -> Result<(f64, f64), EvalError> {
        let (a, b) = (&self.rendered, &self.reference);
        if a.size() != b.size() {
            return Err(EvalError::ImageSizeMismatch {
                first: self.rendered_label.clone(),
                second: self.reference_label.clone(),
                first_size: a.size(),
                second_size: b.size(),
            });
        }
        let named = |e: EvalError| match e {
            EvalError::NonFiniteImage { image, index, value } => EvalError::NonFiniteImage {
                image: if image == "first image" { self.rendered_label.clone() } else { self.reference_label.clone() },
                index,
                value,
            },
            EvalError::ImageTooSmall { width, height, min, convention, .. } => {
                EvalError::ImageTooSmall { image: self.rendered_label.clone(), width, height, min, convention }
            }
            other => other.within(format!("{} vs {}", self.rendered_label, self.reference_label)),
        };
        match (a, b) {
            (EvalImage::Rgb(x), EvalImage::Rgb(y)) => Ok((psnr(x, y).map_err(named)?, ssim(x, y, convention).map_err(named)?)),
            (EvalImage::Gray(x), EvalImage::Gray(y)) => Ok((psnr(x, y).map_err(named)?, ssim(x, y, convention).map_err(named)?)),
            _ => Err(EvalError::ImageChannelMismatch {
                first: self.rendered_label.clone(),
                second: self.reference_label.clone(),
                first_channels: a.channels(),
                second_channels: b.channels(),
            }),
        }
    }
}

/// Per-pixel depth errors and uncertainties of one keyframe (valid pixels only).
#[derive(Clone, Debug, PartialEq)]
pub struct AuseInput {
    pub name: String,
    pub errors: Vec<f64>,
    pub uncertainties: Vec<f64>,
}

/// What to evaluate. Names label the inputs in the report and in errors.
#[derive(Clone, Debug)]
pub struct EvalInputs<'a> {
    pub gt_name: String,
    pub est_name: String,
    pub gt: &'a [StampedPose],
    pub est: &'a [StampedPose],
    pub images: &'a [ImagePair],
    /// Where the images came from (e.g. `rendered/ vs reference/`), for the report.
    pub images_source: Option<String>,
    pub ause: &'a [AuseInput],
    pub ause_source: Option<String>,
    pub options: EvalOptions,
}

/// Names of what was evaluated.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReportInputs {
    pub ground_truth: String,
    pub estimate: String,
    pub images: Option<String>,
    pub depth: Option<String>,
}

/// PSNR and SSIM of one image pair.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageScore {
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// `"inf"` for identical images.
    #[serde(with = "super::f64_or_string")]
    pub psnr_db: f64,
    pub ssim: f64,
}

/// Image metrics over all pairs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageReport {
    pub ssim_convention: SsimConvention,
    pub pairs: usize,
    /// Mean of the per-image PSNRs; `"inf"` when any pair is identical.
    #[serde(with = "super::f64_or_string")]
    pub psnr_mean_db: f64,
    pub ssim_mean: f64,
    /// Pairs whose images are identical (PSNR infinite).
    pub identical: usize,
    pub per_image: Vec<ImageScore>,
}

impl ImageReport {
    /// The map report's scored views as image scores (`images` of `report.json`); `None`
    /// without views. `width x height`: the frames' size (RGB).
    pub fn from_map_quality(q: &super::map_quality::MapQuality, width: usize, height: usize) -> Option<ImageReport> {
        if q.per_view.is_empty() {
            return None;
        }
        let per_image: Vec<ImageScore> =
            q.per_view.iter().map(|v| ImageScore { name: format!("frame {:06}", v.seq), width, height, channels: 3, psnr_db: v.psnr_db, ssim: v.ssim }).collect();
        Some(ImageReport {
            ssim_convention: q.ssim_convention,
            pairs: per_image.len(),
            psnr_mean_db: q.psnr_mean_db,
            ssim_mean: q.ssim_mean,
            identical: per_image.iter().filter(|s| s.psnr_db == f64::INFINITY).count(),
            per_image,
        })
    }
}

/// AUSE of one keyframe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuseScore {
    pub name: String,
    pub pixels: usize,
    pub mae: f64,
    pub ause: f64,
    pub ause_random: f64,
}

/// AUSE over keyframes: per-keyframe areas, their mean, and the mean curves (whose areas are
/// the mean areas, the curves being averaged pointwise).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuseReport {
    pub keyframes: usize,
    pub ause_mean: f64,
    pub ause_random_mean: f64,
    pub fractions: Vec<f64>,
    pub sparsification_mean: Vec<f64>,
    pub oracle_mean: Vec<f64>,
    pub random_mean: Vec<f64>,
    pub per_keyframe: Vec<AuseScore>,
}

/// Everything `report.json` holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Report {
    /// Program and version that wrote the report.
    pub generator: String,
    pub inputs: ReportInputs,
    pub options: EvalOptions,
    pub trajectory: TrajectoryReport,
    pub images: Option<ImageReport>,
    pub ause: Option<AuseReport>,
    /// The map's figures (held-out views, restored view, medium, size) where the run mapped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map: Option<super::map_quality::MapQuality>,
    /// Figure files written beside the report.
    pub figures: Vec<String>,
    /// Why no figures were drawn, where none were: a build without the `figures` feature.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub figures_not_drawn: Option<String>,
}

/// A finished evaluation: the report and the data behind its figures.
#[derive(Clone, Debug)]
pub struct Evaluation {
    pub report: Report,
    pub trajectory: TrajectoryEvaluation,
}

pub const FIGURE_TRAJECTORY: &str = "trajectory_top.png";
pub const FIGURE_ATE: &str = "ate_along_path.png";
pub const FIGURE_SPARSIFICATION: &str = "sparsification.png";

/// What the report says in place of its figures when the program was built without them.
pub const FIGURES_NOT_BUILT: &str = "Figures were not drawn: this binary was built without the `figures` feature \
     (to draw them, install it with `cargo install --path . --features figures`).";

/// Computes every metric the inputs allow.
pub fn build_report(inputs: &EvalInputs) -> Result<Evaluation, EvalError> {
    let opts = &inputs.options;
    let trajectory = evaluate_trajectory(inputs.gt, inputs.est, &opts.trajectory, &inputs.gt_name, &inputs.est_name)?;

    let images = if inputs.images.is_empty() {
        None
    } else {
        let mut per_image = Vec::with_capacity(inputs.images.len());
        for pair in inputs.images {
            let (psnr_db, ssim) = pair.scores(opts.ssim)?;
            let [width, height] = pair.rendered.size();
            per_image.push(ImageScore { name: pair.name.clone(), width, height, channels: pair.rendered.channels(), psnr_db, ssim });
        }
        let n = per_image.len() as f64;
        Some(ImageReport {
            ssim_convention: opts.ssim,
            pairs: per_image.len(),
            psnr_mean_db: per_image.iter().map(|s| s.psnr_db).sum::<f64>() / n,
            ssim_mean: per_image.iter().map(|s| s.ssim).sum::<f64>() / n,
            identical: per_image.iter().filter(|s| s.psnr_db == f64::INFINITY).count(),
            per_image,
        })
    };

    let ause_report = if inputs.ause.is_empty() {
        None
    } else {
        let mut results = Vec::with_capacity(inputs.ause.len());
        for a in inputs.ause {
            results.push((a.name.clone(), ause(&a.errors, &a.uncertainties, &opts.ause).map_err(|e| e.within(format!("depth {}", a.name)))?));
        }
        let k = results.len() as f64;
        let mean_curve = |f: &dyn Fn(&super::AuseResult) -> &Vec<f64>| -> Vec<f64> {
            let len = f(&results[0].1).len();
            (0..len).map(|i| results.iter().map(|(_, r)| f(r)[i]).sum::<f64>() / k).collect()
        };
        Some(AuseReport {
            keyframes: results.len(),
            ause_mean: results.iter().map(|(_, r)| r.ause).sum::<f64>() / k,
            ause_random_mean: results.iter().map(|(_, r)| r.ause_random).sum::<f64>() / k,
            fractions: results[0].1.fractions.clone(),
            sparsification_mean: mean_curve(&|r| &r.sparsification),
            oracle_mean: mean_curve(&|r| &r.oracle),
            random_mean: mean_curve(&|r| &r.random),
            per_keyframe: results
                .iter()
                .map(|(name, r)| AuseScore { name: name.clone(), pixels: r.count, mae: r.mae, ause: r.ause, ause_random: r.ause_random })
                .collect(),
        })
    };

    let (figures, figures_not_drawn) = if cfg!(feature = "figures") {
        let mut figures = vec![FIGURE_TRAJECTORY.to_string(), FIGURE_ATE.to_string()];
        if ause_report.is_some() {
            figures.push(FIGURE_SPARSIFICATION.to_string());
        }
        (figures, None)
    } else {
        (Vec::new(), Some(FIGURES_NOT_BUILT.to_string()))
    };
    let report = Report {
        generator: format!("duv eval {}", env!("CARGO_PKG_VERSION")),
        inputs: ReportInputs {
            ground_truth: inputs.gt_name.clone(),
            estimate: inputs.est_name.clone(),
            images: inputs.images_source.clone().or_else(|| images.as_ref().map(|i| format!("{} in-memory pairs", i.pairs))),
            depth: inputs.ause_source.clone().or_else(|| ause_report.as_ref().map(|a| format!("{} in-memory keyframes", a.keyframes))),
        },
        options: *opts,
        trajectory: trajectory.report.clone(),
        images,
        ause: ause_report,
        map: None,
        figures,
        figures_not_drawn,
    };
    Ok(Evaluation { report, trajectory })
}

fn fmt_num(v: f64, decimals: usize) -> String {
    if v.is_finite() {
        format!("{v:.decimals$}")
    } else if v > 0.0 {
        "inf".into()
    } else if v < 0.0 {
        "-inf".into()
    } else {
        "nan".into()
    }
}

impl Report {
    /// The metrics as a Markdown table (what `duv eval` prints).
    pub fn metrics_table(&self) -> String {
        let t = &self.trajectory;
        let a = &t.ate.stats_m;
        let mut rows: Vec<(String, String)> = vec![
            ("poses: ground truth / estimate / associated".into(), format!("{} / {} / {} (max dt {} s)", t.gt_poses, t.est_poses, t.associated, t.max_dt_secs)),
            (
                "alignment".into(),
                match t.alignment.method {
                    super::Alignment::Sim3 => format!("Sim(3) Umeyama, scale {:.6}", t.alignment.scale),
                    super::Alignment::Se3 => "SE(3) Umeyama".into(),
                    super::Alignment::None => "none".into(),
                },
            ),
            ("ATE RMSE (m)".into(), fmt_num(a.rmse, 6)),
            ("ATE mean / median (m)".into(), format!("{} / {}", fmt_num(a.mean, 6), fmt_num(a.median, 6))),
            ("ATE max / std (m)".into(), format!("{} / {}", fmt_num(a.max, 6), fmt_num(a.std, 6))),
            ("ground-truth path, evaluated span (m)".into(), format!("{} ({} s)", fmt_num(t.gt_path_length_m, 3), fmt_num(t.evaluated_span_secs, 2))),
            ("ATE RMSE / path length".into(), t.ate_rmse_percent_of_path.map_or("n/a (no path)".into(), |p| format!("{}%", fmt_num(p, 3)))),
        ];
        if let Some(r) = &t.rpe {
            let pairs = if r.all_pairs { "all pairs" } else { "consecutive pairs" };
            rows.push((
                format!("RPE translation, {} frame(s), {pairs}: RMSE / mean (m)", r.delta_frames),
                format!("{} / {}", fmt_num(r.translation_m.rmse, 6), fmt_num(r.translation_m.mean, 6)),
            ));
            rows.push((
                format!("RPE rotation, {} frame(s): RMSE / mean (deg)", r.delta_frames),
                format!("{} / {}", fmt_num(r.rotation_deg.rmse, 4), fmt_num(r.rotation_deg.mean, 4)),
            ));
        }
        if let Some(i) = &self.images {
            let identical = if i.identical > 0 { format!(" ({} of {} pairs identical)", i.identical, i.pairs) } else { String::new() };
            rows.push((format!("PSNR mean over {} images (dB)", i.pairs), format!("{}{identical}", fmt_num(i.psnr_mean_db, 3))));
            rows.push((format!("SSIM mean ({} convention)", i.ssim_convention), fmt_num(i.ssim_mean, 4)));
        }
        if let Some(u) = &self.ause {
            rows.push((format!("AUSE (MAE), mean over {} keyframes", u.keyframes), fmt_num(u.ause_mean, 4)));
            rows.push(("AUSE of a random ordering".into(), fmt_num(u.ause_random_mean, 4)));
        }
        let w = rows.iter().map(|r| r.0.len()).max().unwrap_or(6).max(6);
        let v = rows.iter().map(|r| r.1.len()).max().unwrap_or(5).max(5);
        let mut s = format!("| {:w$} | {:v$} |\n|{}|{}|\n", "metric", "value", "-".repeat(w + 2), "-".repeat(v + 2));
        for (k, val) in rows {
            let _ = writeln!(s, "| {k:w$} | {val:v$} |");
        }
        s
    }

    /// The whole `report.md`.
    pub fn markdown(&self) -> String {
        let mut s = String::from("# Evaluation report\n\n");
        let _ = writeln!(s, "Written by {}.\n", self.generator);
        let _ = writeln!(s, "- ground truth: `{}`", self.inputs.ground_truth);
        let _ = writeln!(s, "- estimate: `{}`", self.inputs.estimate);
        if let Some(i) = &self.inputs.images {
            let _ = writeln!(s, "- images: `{i}`");
        }
        if let Some(d) = &self.inputs.depth {
            let _ = writeln!(s, "- depth: `{d}`");
        }
        let _ = writeln!(
            s,
            "\nATE and RPE as evo computes them (nearest time stamps within max dt, Umeyama alignment of positions); \
             SSIM with an 11x11 Gaussian window (sigma 1.5), {} convention; AUSE on the MAE with {} steps.\n",
            self.options.ssim, self.options.ause.steps
        );
        s.push_str(&self.metrics_table());
        if let Some(i) = &self.images {
            s.push_str("\n## Images\n\n| image | size | PSNR (dB) | SSIM |\n|---|---|---|---|\n");
            for p in &i.per_image {
                let _ = writeln!(s, "| {} | {}x{}x{} | {} | {} |", p.name, p.width, p.height, p.channels, fmt_num(p.psnr_db, 3), fmt_num(p.ssim, 4));
            }
        }
        if let Some(u) = &self.ause {
            s.push_str("\n## Depth uncertainty\n\n| keyframe | pixels | MAE | AUSE | AUSE random |\n|---|---|---|---|---|\n");
            for k in &u.per_keyframe {
                let _ = writeln!(s, "| {} | {} | {} | {} | {} |", k.name, k.pixels, fmt_num(k.mae, 4), fmt_num(k.ause, 4), fmt_num(k.ause_random, 4));
            }
        }
        if let Some(m) = &self.map {
            s.push_str(&m.markdown());
        }
        s.push_str("\n## Figures\n\n");
        for f in &self.figures {
            let _ = writeln!(s, "![{f}]({f})\n");
        }
        if let Some(why) = &self.figures_not_drawn {
            let _ = writeln!(s, "{why}");
        }
        s
    }
}

#[cfg(feature = "figures")]
const FIG_W: usize = 1000;
#[cfg(feature = "figures")]
const FIG_H: usize = 750;

#[cfg(feature = "figures")]
impl Evaluation {
    /// The figures, by file name (only with the `figures` feature).
    pub fn figures(&self) -> Result<Vec<(&'static str, ImageRgb8)>, EvalError> {
        let draw = |figure: &'static str, chart: &Chart| {
            chart.render(FIG_W, FIG_H).map(|img| (figure, img)).map_err(|source| EvalError::Figure { figure, source })
        };
        let t = &self.trajectory;
        let r = &self.report.trajectory;
        let axes = plot::top_view_axes(&t.gt_path_positions);
        let gt_xy = plot::project(&t.gt_path_positions, &axes);
        let est_xy = plot::project(&t.est_positions_aligned, &axes);
        let aligned = match r.alignment.method {
            super::Alignment::Sim3 => "Sim(3) aligned",
            super::Alignment::Se3 => "SE(3) aligned",
            super::Alignment::None => "not aligned",
        };
        let mut series = vec![Series::line("ground truth", gt_xy.clone(), plot::BLACK, 2.0), Series::line(format!("estimate ({aligned})"), est_xy.clone(), plot::BLUE, 2.0)];
        if est_xy.len() <= 300 {
            series.push(Series { label: String::new(), points: est_xy.clone(), color: plot::BLUE, width_px: 5.0, style: Style::Dots });
        }
        series.push(Series { label: "start".into(), points: gt_xy.first().map(|p| vec![*p]).unwrap_or_default(), color: plot::GREEN, width_px: 11.0, style: Style::Dots });
        let top = Chart {
            title: format!("Trajectory, top view: ATE RMSE {} m over {} poses", fmt_num(r.ate.stats_m.rmse, 4), r.associated),
            x_label: "first principal axis (m)".into(),
            y_label: "second principal axis (m)".into(),
            series,
            equal_aspect: true,
            ..Default::default()
        };

        // Errors in centimetres unless they reach a metre.
        let max_err = r.ate.stats_m.max.max(r.ate.stats_m.rmse);
        let (unit, per_m) = if max_err < 1.0 { ("cm", 100.0) } else { ("m", 1.0) };
        let err_pts: Vec<[f64; 2]> = t.distance_along_m.iter().zip(&r.ate.errors_m).map(|(&d, &e)| [d, e * per_m]).collect();
        let x_end = t.distance_along_m.iter().copied().fold(0.0, f64::max);
        let rmse = r.ate.stats_m.rmse * per_m;
        let mut ate_series = vec![Series::line("position error", err_pts.clone(), plot::RED, 2.0)];
        if err_pts.len() <= 300 {
            ate_series.push(Series { label: String::new(), points: err_pts.clone(), color: plot::RED, width_px: 5.0, style: Style::Dots });
        }
        ate_series.push(
            Series::line(format!("RMSE {} {unit}", fmt_num(rmse, if per_m > 1.0 { 2 } else { 4 })), vec![[0.0, rmse], [x_end, rmse]], plot::GREY, 2.0)
                .with_style(Style::Dashed),
        );
        let ate = Chart {
            title: format!("ATE along the path ({} associated poses)", r.associated),
            x_label: "distance travelled along the ground truth (m)".into(),
            y_label: format!("position error ({unit})"),
            series: ate_series,
            x_range: Some((0.0, if x_end > 0.0 { x_end } else { 1.0 })),
            y_range: Some((0.0, if max_err > 0.0 { 1.1 * max_err * per_m } else { 1.0 })),
            ..Default::default()
        };
        let mut out = vec![draw(FIGURE_TRAJECTORY, &top)?, draw(FIGURE_ATE, &ate)?];

        if let Some(u) = &self.report.ause {
            let pts = |ys: &[f64]| u.fractions.iter().zip(ys).map(|(&x, &y)| [x, y]).collect::<Vec<_>>();
            let y_max = u.sparsification_mean.iter().chain(&u.random_mean).chain(&u.oracle_mean).fold(1.0f64, |m, &v| if v.is_finite() { m.max(v) } else { m });
            let chart = Chart {
                title: format!("Sparsification of depth error (MAE), mean of {} keyframe(s)", u.keyframes),
                x_label: "fraction of pixels removed".into(),
                y_label: "MAE of the rest / MAE of all".into(),
                series: vec![
                    Series::line(format!("by uncertainty: AUSE {}", fmt_num(u.ause_mean, 3)), pts(&u.sparsification_mean), plot::BLUE, 2.5),
                    Series::line("by true error (oracle)", pts(&u.oracle_mean), plot::GREEN, 2.5),
                    Series::line(format!("random order: AUSE {}", fmt_num(u.ause_random_mean, 3)), pts(&u.random_mean), plot::ORANGE, 2.5)
                        .with_style(Style::Dashed),
                ],
                x_range: Some((0.0, 1.0)),
                y_range: Some((0.0, 1.08 * y_max)),
                ..Default::default()
            };
            out.push(draw(FIGURE_SPARSIFICATION, &chart)?);
        }
        Ok(out)
    }
}

/// Writes `report.json`, `report.md` and the figures into `out_dir` (created if needed);
/// returns the paths written. Without the `figures` feature no figure is drawn, and
/// `report.md` says so ([`Report::figures_not_drawn`]).
pub fn write_report(eval: &Evaluation, out_dir: &Path) -> Result<Vec<PathBuf>, EvalError> {
    std::fs::create_dir_all(out_dir).map_err(|e| IoError::file(out_dir, e))?;
    let mut written = Vec::new();
    let json = serde_json::to_string_pretty(&eval.report)
        .map_err(|e| IoError::invalid(&out_dir.join("report.json"), format!("cannot serialise the report: {e}")))?;
    let json_path = out_dir.join("report.json");
    write_atomic(&json_path, format!("{json}\n").as_bytes())?;
    written.push(json_path);
    let md_path = out_dir.join("report.md");
    write_atomic(&md_path, eval.report.markdown().as_bytes())?;
    written.push(md_path);
    #[cfg(feature = "figures")]
    for (name, img) in eval.figures()? {
        let path = out_dir.join(name);
        png_io::write_rgb8(&path, &img)?;
        written.push(path);
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::pose::se3_exp;
    use duv_core::Timestamp;
    use nalgebra::Vector6;

    fn poses(n: usize, wobble: f64) -> Vec<StampedPose> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.2;
                let xi = Vector6::new(a.cos() + wobble * (3.0 * a).sin(), a.sin(), 0.1 * a, 0.0, 0.1, a);
                StampedPose { t_ns: Timestamp(i as i64 * 50_000_000), world_from_cam: se3_exp(&xi) }
            })
            .collect()
    }

    #[test]
    fn in_memory_report_round_trips_through_json() {
        let gt = poses(40, 0.0);
        let est = poses(40, 0.01);
        let img = ImageRgbF32::from_vec(16, 12, (0..16 * 12 * 3).map(|i| (i % 17) as f32 / 17.0).collect()).unwrap();
        let mut other = img.clone();
        other.data[5] += 0.25;
        let images = vec![
            ImagePair::new("same", EvalImage::Rgb(img.clone()), EvalImage::Rgb(img.clone())),
            ImagePair::new("changed", EvalImage::Rgb(other), EvalImage::Rgb(img)),
        ];
        let ause_in = vec![AuseInput { name: "kf0".into(), errors: (1..=200).map(f64::from).collect(), uncertainties: (1..=200).map(f64::from).collect() }];
        let inputs = EvalInputs {
            gt_name: "gt".into(),
            est_name: "est".into(),
            gt: &gt,
            est: &est,
            images: &images,
            images_source: None,
            ause: &ause_in,
            ause_source: None,
            options: EvalOptions::default(),
        };
        let ev = build_report(&inputs).unwrap();
        let r = &ev.report;
        let imgs = r.images.as_ref().unwrap();
        assert_eq!((imgs.pairs, imgs.identical), (2, 1));
        assert_eq!(imgs.psnr_mean_db, f64::INFINITY);
        assert!(imgs.per_image[1].psnr_db.is_finite() && imgs.per_image[1].ssim < 1.0);
        assert_eq!(r.ause.as_ref().unwrap().ause_mean, 0.0);
        #[cfg(feature = "figures")]
        assert_eq!(r.figures.len(), 3);
        #[cfg(not(feature = "figures"))]
        assert!(r.figures.is_empty() && r.figures_not_drawn.as_deref() == Some(FIGURES_NOT_BUILT));
        let json = serde_json::to_string(r).unwrap();
        assert!(json.contains("\"psnr_db\":\"inf\""), "{json}");
        // Reads back (serde_json parses floats to within an ulp; per-pose errors are not stored).
        let back: Report = serde_json::from_str(&json).unwrap();
        assert_eq!(back.images.as_ref().unwrap().per_image[0].psnr_db, f64::INFINITY);
        assert_eq!(back.figures, r.figures);
        assert_eq!(back.figures_not_drawn, r.figures_not_drawn);
        assert!((back.trajectory.ate.stats_m.rmse - r.trajectory.ate.stats_m.rmse).abs() < 1e-15);
        assert_eq!(back.options, r.options);
        let table = r.metrics_table();
        assert!(table.contains("ATE RMSE") && table.contains("inf (1 of 2 pairs identical)"), "{table}");
        // Figures render at full size.
        #[cfg(feature = "figures")]
        {
            let figs = ev.figures().unwrap();
            assert_eq!(figs.len(), 3);
            assert!(figs.iter().all(|(_, f)| f.width == FIG_W && f.height == FIG_H));
        }
    }

    fn small_evaluation(with_ause: bool) -> Evaluation {
        let gt = poses(40, 0.0);
        let est = poses(40, 0.02);
        let ause_in = vec![AuseInput { name: "kf0".into(), errors: (1..=200).map(f64::from).collect(), uncertainties: (1..=200).rev().map(f64::from).collect() }];
        let inputs = EvalInputs {
            gt_name: "gt".into(),
            est_name: "est".into(),
            gt: &gt,
            est: &est,
            images: &[],
            images_source: None,
            ause: if with_ause { &ause_in } else { &[] },
            ause_source: None,
            options: EvalOptions::default(),
        };
        build_report(&inputs).unwrap()
    }

    /// Without the `figures` feature the report is still written, lists no figures and says why
    /// (in report.json and report.md).
    #[cfg(not(feature = "figures"))]
    #[test]
    fn without_the_feature_the_report_says_why_there_are_no_figures() {
        let ev = small_evaluation(true);
        let dir = tempfile::tempdir().unwrap();
        let written = write_report(&ev, dir.path()).unwrap();
        let names: Vec<String> = written.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["report.json", "report.md"]);
        assert!(!dir.path().join(FIGURE_TRAJECTORY).exists());
        let md = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
        assert!(md.contains("## Figures") && md.contains("`figures` feature") && md.contains("--features figures"), "{md}");
        assert!(!md.contains(".png"), "{md}");
        let back: Report = serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap()).unwrap();
        assert!(back.figures.is_empty());
        assert_eq!(back.figures_not_drawn.as_deref(), Some(FIGURES_NOT_BUILT));
    }

    /// With the feature, every listed figure is written as a PNG of the figure size, and each
    /// has the colours of its series.
    #[cfg(feature = "figures")]
    #[test]
    fn figures_are_written_as_pngs_with_their_series() {
        let ev = small_evaluation(true);
        assert!(ev.report.figures_not_drawn.is_none());
        let md = ev.report.markdown();
        assert!(md.contains("![trajectory_top.png](trajectory_top.png)") && !md.contains("`figures` feature"), "{md}");
        let dir = tempfile::tempdir().unwrap();
        let written = write_report(&ev, dir.path()).unwrap();
        assert_eq!(written.len(), 5);
        let has = |img: &ImageRgb8, c: plot::Rgb| img.data.chunks_exact(3).filter(|p| p.iter().zip(&c).all(|(a, b)| a.abs_diff(*b) <= 8)).count();
        for (name, colours) in [
            (FIGURE_TRAJECTORY, vec![plot::BLUE, plot::GREEN]),
            (FIGURE_ATE, vec![plot::RED, plot::GREY]),
            (FIGURE_SPARSIFICATION, vec![plot::BLUE, plot::GREEN, plot::ORANGE]),
        ] {
            assert!(ev.report.figures.iter().any(|f| f == name), "{name}");
            let img = png_io::read_image(&dir.path().join(name)).unwrap();
            let duv_core::FrameImage::Rgb8(img) = img else { panic!("{name} is not RGB") };
            assert_eq!((img.width, img.height), (FIG_W, FIG_H), "{name}");
            for c in colours {
                assert!(has(&img, c) > 50, "{name}: colour {c:?} appears on {} pixels", has(&img, c));
            }
            // Text (title, labels) is drawn: dark pixels in the title band at the top.
            let dark_title = (0..40).flat_map(|y| (0..FIG_W).map(move |x| (x, y))).filter(|&(x, y)| img.pixel(x, y).iter().all(|&v| v < 90)).count();
            assert!(dark_title > 200, "{name}: {dark_title} dark pixels in the title band");
        }
        // Without AUSE input there is no sparsification figure.
        let ev = small_evaluation(false);
        assert_eq!(ev.report.figures, [FIGURE_TRAJECTORY, FIGURE_ATE]);
        assert_eq!(ev.figures().unwrap().len(), 2);
    }

    #[test]
    fn errors_name_the_input() {
        let gt = poses(10, 0.0);
        let bad_ause = vec![AuseInput { name: "kf7".into(), errors: vec![1.0, 2.0], uncertainties: vec![1.0, f64::NAN] }];
        let inputs = EvalInputs {
            gt_name: "gt".into(),
            est_name: "est".into(),
            gt: &gt,
            est: &gt,
            images: &[],
            images_source: None,
            ause: &bad_ause,
            ause_source: None,
            options: EvalOptions::default(),
        };
        let e = build_report(&inputs).unwrap_err().to_string();
        assert!(e.contains("kf7") && e.contains("pixel 1") && e.contains("not finite"), "{e}");
        let a = ImageRgbF32::new(12, 12);
        let b = ImageRgbF32::new(13, 12);
        let pair = ImagePair::new("x.png", EvalImage::Rgb(a), EvalImage::Rgb(b));
        let e = pair.scores(SsimConvention::Skimage).unwrap_err().to_string();
        assert!(e.contains("rendered x.png is 12x12") && e.contains("reference x.png is 13x12"), "{e}");
    }
}
