//! The map's figures of one run (`duv run`, `duv replay`, `duv demo`): how well the map
//! renders frames it was not optimised on, how close its restored (water-free) view comes to
//! the truth where the source knows it, the medium with its unit, and the map's size.
//! `duv_pipeline::map_report` scores the views; this module holds the report structures,
//! the per-view score ([`score_view`]) and the Markdown.

use super::image::{psnr, ssim, SsimConvention};
use super::EvalError;
use duv_core::{ImageRgbF32, MediumParams};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// What LPIPS needs and this build lacks.
pub const LPIPS_MISSING: &str = "LPIPS not computed: it needs the pretrained AlexNet/VGG weights, which no registry package this build uses ships";

/// Mean of `a - b` per channel over the pixels (values in [0, 1]): a colour cast shows as a
/// channel far from 0.
pub fn mean_error_rgb(a: &ImageRgbF32, b: &ImageRgbF32) -> Result<[f64; 3], EvalError> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(EvalError::ImageSizeMismatch { first: "first image".into(), second: "second image".into(), first_size: [a.width, a.height], second_size: [b.width, b.height] });
    }
    let mut sum = [0.0f64; 3];
    for (pa, pb) in a.data.chunks_exact(3).zip(b.data.chunks_exact(3)) {
        for c in 0..3 {
            sum[c] += pa[c] as f64 - pb[c] as f64;
        }
    }
    let n = (a.width * a.height).max(1) as f64;
    Ok(sum.map(|s| s / n))
}

/// The restored view of one frame against its water-free truth, next to the captured frame's
/// own score (what not restoring at all gives) and the map's albedo render.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RestoredScore {
    pub psnr_db: f64,
    pub ssim: f64,
    /// Mean restored - truth per channel (R, G, B), in [0, 1] units.
    pub mean_error_rgb: [f64; 3],
    /// The captured frame against the truth.
    pub captured_psnr_db: f64,
    pub captured_mean_error_rgb: [f64; 3],
    /// The map's albedo render (`sum w_n c_n / alpha`) against the truth.
    pub albedo_psnr_db: f64,
    pub albedo_mean_error_rgb: [f64; 3],
}

/// One scored view: the map rendered from the frame's tracked pose against the frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapViewScore {
    /// Frame sequence number.
    pub seq: u64,
    pub psnr_db: f64,
    pub ssim: f64,
    /// Share of the pixels the map covers (rendered alpha >= 0.5).
    pub coverage: f64,
    /// Mean restoration confidence (0: the captured colour kept everywhere).
    pub restore_confidence: f64,
    /// Where the source knows the water-free view.
    pub restored: Option<RestoredScore>,
}

/// Means over the scored views of [`RestoredScore`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RestoredSummary {
    pub views: usize,
    pub psnr_mean_db: f64,
    pub ssim_mean: f64,
    pub mean_error_rgb: [f64; 3],
    pub captured_psnr_mean_db: f64,
    pub captured_mean_error_rgb: [f64; 3],
    pub albedo_psnr_mean_db: f64,
    pub albedo_mean_error_rgb: [f64; 3],
    /// Views whose restored PSNR is below the captured frame's own.
    pub worse_than_captured: usize,
}

/// The map's figures (`report.json`'s `map`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapQuality {
    /// How the views were chosen (frames between keyframes, not trained on).
    pub selection: String,
    pub views: usize,
    pub psnr_mean_db: f64,
    pub ssim_mean: f64,
    pub ssim_convention: SsimConvention,
    /// Always `None` for now; [`LPIPS_MISSING`] says why.
    pub lpips_mean: Option<f64>,
    pub lpips_missing: Option<String>,
    /// Mean over the scored views of the share of pixels the map covers (alpha >= 0.5).
    pub coverage: f64,
    /// Share of the scored views of which the map covers at least half.
    pub views_covered: f64,
    pub restored: Option<RestoredSummary>,
    /// Why no restored score: the source does not know the water-free view.
    pub restored_missing: Option<String>,
    /// The medium along the newest keyframe's optical axis; coefficients per `medium_unit`.
    pub medium: MediumParams,
    /// `1/m` (metric outputs, `metric.json`) or `1/map unit`.
    pub medium_unit: String,
    pub gaussians: usize,
    pub max_gaussians: usize,
    pub iterations: u64,
    pub keyframes: usize,
    pub per_view: Vec<MapViewScore>,
    /// Render panels (input | render | restored | depth | uncertainty), relative to the run folder.
    pub panels: Vec<String>,
}

/// PSNR/SSIM of `render` against `captured`; with `clear` (the water-free truth), the
/// restored view, the captured frame and the albedo render against it.
pub fn score_view(
    render: &ImageRgbF32,
    captured: &ImageRgbF32,
    restored: &ImageRgbF32,
    albedo: &ImageRgbF32,
    clear: Option<&ImageRgbF32>,
) -> Result<(f64, f64, Option<RestoredScore>), EvalError> {
    let c = SsimConvention::Skimage;
    let (p, s) = (psnr(render, captured)?, ssim(render, captured, c)?);
    let r = match clear {
        None => None,
        Some(t) => Some(RestoredScore {
            psnr_db: psnr(restored, t)?,
            ssim: ssim(restored, t, c)?,
            mean_error_rgb: mean_error_rgb(restored, t)?,
            captured_psnr_db: psnr(captured, t)?,
            captured_mean_error_rgb: mean_error_rgb(captured, t)?,
            albedo_psnr_db: psnr(albedo, t)?,
            albedo_mean_error_rgb: mean_error_rgb(albedo, t)?,
        }),
    };
    Ok((p, s, r))
}

/// Means of the restored scores of `views` (`None` where none has one).
pub fn summarise_restored(views: &[MapViewScore]) -> Option<RestoredSummary> {
    let r: Vec<&RestoredScore> = views.iter().filter_map(|v| v.restored.as_ref()).collect();
    if r.is_empty() {
        return None;
    }
    let n = r.len() as f64;
    let mean = |f: &dyn Fn(&RestoredScore) -> f64| r.iter().map(|s| f(s)).sum::<f64>() / n;
    let mean3 = |f: &dyn Fn(&RestoredScore) -> [f64; 3]| [0, 1, 2].map(|c| r.iter().map(|s| f(s)[c]).sum::<f64>() / n);
    Some(RestoredSummary {
        views: r.len(),
        psnr_mean_db: mean(&|s| s.psnr_db),
        ssim_mean: mean(&|s| s.ssim),
        mean_error_rgb: mean3(&|s| s.mean_error_rgb),
        captured_psnr_mean_db: mean(&|s| s.captured_psnr_db),
        captured_mean_error_rgb: mean3(&|s| s.captured_mean_error_rgb),
        albedo_psnr_mean_db: mean(&|s| s.albedo_psnr_db),
        albedo_mean_error_rgb: mean3(&|s| s.albedo_mean_error_rgb),
        worse_than_captured: r.iter().filter(|s| s.psnr_db < s.captured_psnr_db).count(),
    })
}

fn rgb(v: [f64; 3]) -> String {
    format!("{:+.3} {:+.3} {:+.3}", v[0], v[1], v[2])
}

impl MapQuality {
    /// One line for the operator.
    pub fn summary(&self) -> String {
        let mut s = format!(
            "map on {} frames between keyframes: PSNR {:.2} dB, SSIM {:.4}, coverage {:.1} %",
            self.views,
            self.psnr_mean_db,
            self.ssim_mean,
            100.0 * self.coverage
        );
        if let Some(r) = &self.restored {
            let _ = write!(s, "; restored vs water-free truth {:.2} dB (captured {:.2} dB), mean error RGB {}", r.psnr_mean_db, r.captured_psnr_mean_db, rgb(r.mean_error_rgb));
        }
        s
    }

    /// The `## Map` section of `report.md`.
    pub fn markdown(&self) -> String {
        let mut s = String::from("\n## Map\n\n");
        let _ = writeln!(s, "{}.\n", self.selection);
        let _ = writeln!(s, "| figure | value |\n|---|---|");
        let _ = writeln!(s, "| views scored | {} |", self.views);
        let _ = writeln!(s, "| PSNR mean (dB), render vs frame | {:.3} |", self.psnr_mean_db);
        let _ = writeln!(s, "| SSIM mean ({}) | {:.4} |", self.ssim_convention, self.ssim_mean);
        let _ = writeln!(s, "| LPIPS | {} |", self.lpips_mean.map_or_else(|| "not computed".to_string(), |v| format!("{v:.4}")));
        let _ = writeln!(s, "| coverage (mean share of pixels with alpha >= 0.5) | {:.3} |", self.coverage);
        let _ = writeln!(s, "| views at least half covered | {:.3} |", self.views_covered);
        match &self.restored {
            Some(r) => {
                let _ = writeln!(s, "| restored vs water-free truth, PSNR (dB) / SSIM | {:.3} / {:.4} |", r.psnr_mean_db, r.ssim_mean);
                let _ = writeln!(s, "| restored mean error R G B | {} |", rgb(r.mean_error_rgb));
                let _ = writeln!(s, "| captured vs truth, PSNR (dB); mean error R G B | {:.3}; {} |", r.captured_psnr_mean_db, rgb(r.captured_mean_error_rgb));
                let _ = writeln!(s, "| map albedo vs truth, PSNR (dB); mean error R G B | {:.3}; {} |", r.albedo_psnr_mean_db, rgb(r.albedo_mean_error_rgb));
                let _ = writeln!(s, "| views restored worse than captured | {} of {} |", r.worse_than_captured, r.views);
            }
            None => {
                let _ = writeln!(s, "| restored vs truth | {} |", self.restored_missing.as_deref().unwrap_or("-"));
            }
        }
        let m = &self.medium;
        let f = |v: [f64; 3]| format!("{:.4} {:.4} {:.4}", v[0], v[1], v[2]);
        let _ = writeln!(s, "| beta_D R G B ({}) | {} |", self.medium_unit, f(m.beta_d));
        let _ = writeln!(s, "| beta_B R G B ({}) | {} |", self.medium_unit, f(m.beta_b));
        let _ = writeln!(s, "| B_inf R G B | {} |", f(m.b_inf));
        let _ = writeln!(s, "| Gaussians (cap) | {} ({}) |", self.gaussians, self.max_gaussians);
        let _ = writeln!(s, "| iterations | {} |", self.iterations);
        let _ = writeln!(s, "| keyframes mapped | {} |", self.keyframes);
        if let Some(why) = &self.lpips_missing {
            let _ = writeln!(s, "\n{why}.");
        }
        if !self.per_view.is_empty() {
            s.push_str("\n| frame | PSNR dB | SSIM | coverage | restored PSNR dB (captured) |\n|---|---|---|---|---|\n");
            for v in &self.per_view {
                let r = v.restored.map_or("-".to_string(), |r| format!("{:.2} ({:.2})", r.psnr_db, r.captured_psnr_db));
                let _ = writeln!(s, "| {} | {:.2} | {:.4} | {:.3} | {r} |", v.seq, v.psnr_db, v.ssim, v.coverage);
            }
        }
        for p in &self.panels {
            let _ = writeln!(s, "\n![{p}]({p})");
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scores_a_restoration_against_the_truth() {
        let truth = ImageRgbF32::filled(16, 16, [0.5, 0.4, 0.3]);
        let captured = ImageRgbF32::filled(16, 16, [0.2, 0.4, 0.5]);
        let restored = ImageRgbF32::filled(16, 16, [0.45, 0.4, 0.3]);
        let (p, _, r) = score_view(&captured, &captured, &restored, &captured, Some(&truth)).unwrap();
        assert_eq!(p, f64::INFINITY);
        let r = r.unwrap();
        // MSE (0.05^2)/3 -> 10 log10(3 / 0.0025) = 30.79 dB; captured (0.09 + 0.04) / 3.
        assert!((r.psnr_db - 30.792).abs() < 1e-2, "{}", r.psnr_db);
        assert!((r.captured_psnr_db - 13.632).abs() < 1e-2, "{}", r.captured_psnr_db);
        assert!((r.mean_error_rgb[0] + 0.05).abs() < 1e-6 && r.mean_error_rgb[1].abs() < 1e-6);
        assert!((r.captured_mean_error_rgb[2] - 0.2).abs() < 1e-6);
        let v = MapViewScore { seq: 3, psnr_db: p, ssim: 1.0, coverage: 1.0, restore_confidence: 1.0, restored: Some(r) };
        let worse = MapViewScore { restored: Some(RestoredScore { psnr_db: 10.0, ..r }), ..v.clone() };
        let s = summarise_restored(&[v, worse]).unwrap();
        assert_eq!((s.views, s.worse_than_captured), (2, 1));
        assert!((s.psnr_mean_db - (30.792 + 10.0) / 2.0).abs() < 1e-2);
        assert!(summarise_restored(&[]).is_none());
    }
}
