//! `duv eval`: a trajectory (and optionally rendered images and depth uncertainty) against
//! ground truth. Prints the metrics table and writes `report.json`, `report.md` and figures
//! (the figures only in a build with the `figures` feature; without it the report says so).

use anyhow::Context;
use clap::ValueEnum;
use duv_eval::load::{ground_truth_file, load_depth_inputs, load_image_pairs};
use duv_eval::report::{AuseInput, ImagePair};
use duv_eval::trajectory::TrajectoryOptions;
use duv_eval::{build_report, write_report, Alignment, AuseOptions, EvalInputs, EvalOptions, SsimConvention};
use duv_core::io::tum::read_trajectory;
use std::path::PathBuf;

#[derive(Clone, Copy, Debug, ValueEnum)]
enum AlignArg {
    /// Rotation, translation and scale (monocular estimates).
    Sim3,
    /// Rotation and translation.
    Se3,
    /// The estimate as it is.
    None,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum SsimArg {
    /// scikit-image: mirrored borders, border band of 5 px left out of the mean.
    Skimage,
    /// 3DGS/MonoGS papers: zero padding, every pixel in the mean.
    Same,
}

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("estimate").required(true).args(["est", "run"])))]
pub struct EvalArgs {
    /// Ground truth: a TUM trajectory file, or a dataset folder holding `groundtruth.txt`.
    #[arg(long, value_name = "FILE_OR_DATASET_DIR")]
    gt: PathBuf,
    /// Estimated trajectory (TUM format: timestamp tx ty tz qx qy qz qw).
    #[arg(long, value_name = "TRAJ_FILE")]
    est: Option<PathBuf>,
    /// A run folder: shortcut for `--est DIR/trajectory.txt`; its map segments that never
    /// merged into the first (`trajectory-segment-N.txt`) are scored too, each aligned on its
    /// own (`segments.md`, `segments.json`).
    #[arg(long, value_name = "DIR")]
    run: Option<PathBuf>,
    /// Alignment of the estimate before ATE/RPE.
    #[arg(long, value_enum, default_value_t = AlignArg::Sim3)]
    align: AlignArg,
    /// With `--align se3` or `none`: compare an estimate in map units (its folder's
    /// `metric.json` says so, or it has none) against the metric ground truth anyway.
    #[arg(long)]
    allow_map_units: bool,
    /// Largest time-stamp difference of an associated pose pair, seconds.
    #[arg(long, default_value_t = 0.01, value_name = "SECS")]
    max_dt: f64,
    /// RPE delta in frames (0 skips RPE).
    #[arg(long, default_value_t = 1, value_name = "FRAMES")]
    rpe_delta: usize,
    /// Start RPE pairs only at every delta-th pose (evo's default) rather than at every pose.
    #[arg(long)]
    rpe_consecutive: bool,
    /// Folder of rendered PNG images, paired by file name with --reference.
    #[arg(long, requires = "reference", value_name = "DIR")]
    rendered: Option<PathBuf>,
    /// Folder of reference PNG images (the captured frames).
    #[arg(long, requires = "rendered", value_name = "DIR")]
    reference: Option<PathBuf>,
    /// SSIM border convention.
    #[arg(long, value_enum, default_value_t = SsimArg::Skimage)]
    ssim: SsimArg,
    /// Folder of estimated depth maps (PFM, or 16-bit PNG) for AUSE, paired by file stem with
    /// --variance and --gt-depth.
    #[arg(long, requires_all = ["variance", "gt_depth"], value_name = "DIR")]
    depth: Option<PathBuf>,
    /// Folder of depth variance maps (PFM).
    #[arg(long, requires = "depth", value_name = "DIR")]
    variance: Option<PathBuf>,
    /// Folder of ground-truth depth maps (PFM, or 16-bit PNG).
    #[arg(long, requires = "depth", value_name = "DIR")]
    gt_depth: Option<PathBuf>,
    /// Units per metre of 16-bit PNG depth (TUM: 5000).
    #[arg(long, default_value_t = 5000.0)]
    depth_scale: f64,
    /// Points on the sparsification curves.
    #[arg(long, default_value_t = 100)]
    ause_steps: usize,
    /// Output folder for report.json, report.md and the figures (created if needed; figures need a build with the `figures` feature).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.max_dt.is_finite() && args.max_dt >= 0.0, "--max-dt must be a non-negative number of seconds, got {}", args.max_dt);
    let gt_path = ground_truth_file(&args.gt);
    let est_path = match (&args.est, &args.run) {
        (Some(est), _) => est.clone(),
        (None, Some(run)) => run.join("trajectory.txt"),
        (None, None) => anyhow::bail!("give --est TRAJ_FILE or --run DIR"),
    };
    let gt = read_trajectory(&gt_path)?;
    let est = read_trajectory(&est_path)?;
    // Without a scale in the alignment, an unscaled estimate cannot be compared with metres.
    if !matches!(args.align, AlignArg::Sim3) {
        let dir = est_path.parent().unwrap_or(std::path::Path::new("."));
        let units = duv_pipeline::metric::MetricRecord::read(dir)?;
        let metric = units.as_ref().is_some_and(|m| m.length_unit == "m");
        if !metric {
            let why = match &units {
                Some(m) => format!("{} says it is in map units ({})", dir.join("metric.json").display(), m.why_not_metric.as_deref().unwrap_or("")),
                None => format!("{} has no metric.json beside it, so it is taken to be in map units", est_path.display()),
            };
            if args.allow_map_units {
                eprintln!("comparing map units with the metric ground truth (--allow-map-units): {why}");
            } else {
                anyhow::bail!("--align {} keeps the estimate's scale, but {why}; use --align sim3, a run with navigation input, or --allow-map-units", if matches!(args.align, AlignArg::Se3) { "se3" } else { "none" });
            }
        }
    }

    let mut images: Vec<ImagePair> = Vec::new();
    let mut images_source = None;
    if let (Some(rendered), Some(reference)) = (&args.rendered, &args.reference) {
        let (pairs, unmatched) = load_image_pairs(rendered, reference)?;
        if !unmatched.is_empty() {
            tracing::warn!("{} rendered image(s) have no reference in {} and are skipped: {}", unmatched.len(), reference.display(), unmatched.join(", "));
        }
        images_source = Some(format!("{} vs {}", rendered.display(), reference.display()));
        images = pairs;
    }
    let mut ause: Vec<AuseInput> = Vec::new();
    let mut ause_source = None;
    if let (Some(depth), Some(variance), Some(gt_depth)) = (&args.depth, &args.variance, &args.gt_depth) {
        let (inputs, skipped) = load_depth_inputs(depth, variance, gt_depth, args.depth_scale)?;
        if !skipped.is_empty() {
            tracing::warn!("{} depth map(s) lack a variance or ground-truth map and are skipped: {}", skipped.len(), skipped.join(", "));
        }
        ause_source = Some(format!("{} (variance {}, ground truth {})", depth.display(), variance.display(), gt_depth.display()));
        ause = inputs;
    }

    let options = EvalOptions {
        trajectory: TrajectoryOptions {
            max_dt_ns: (args.max_dt * 1e9).round() as i64,
            alignment: match args.align {
                AlignArg::Sim3 => Alignment::Sim3,
                AlignArg::Se3 => Alignment::Se3,
                AlignArg::None => Alignment::None,
            },
            rpe_delta_frames: args.rpe_delta,
            rpe_all_pairs: !args.rpe_consecutive,
        },
        ssim: match args.ssim {
            SsimArg::Skimage => SsimConvention::Skimage,
            SsimArg::Same => SsimConvention::Same,
        },
        ause: AuseOptions { steps: args.ause_steps, ..Default::default() },
    };
    let inputs = EvalInputs {
        gt_name: gt_path.display().to_string(),
        est_name: est_path.display().to_string(),
        gt: &gt,
        est: &est,
        images: &images,
        images_source,
        ause: &ause,
        ause_source,
        options,
    };
    let trajectory_options = inputs.options.trajectory.clone();
    let evaluation = build_report(&inputs)?;
    let mut written = write_report(&evaluation, &args.out).with_context(|| format!("writing the report to {}", args.out.display()))?;
    print!("{}", evaluation.report.metrics_table());
    if let Some(run) = &args.run {
        let main = SegmentScore { segment: 0, file: est_path.display().to_string(), poses: est.len(), ate_rmse_m: evaluation.report.trajectory.ate.stats_m.rmse, gt_path_m: evaluation.report.trajectory.gt_path_length_m };
        if let Some(paths) = score_segments(run, &gt, &trajectory_options, main, &args.out)? {
            written.extend(paths);
        }
    }
    println!("\nwrote {}", written.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "));
    if let Some(why) = &evaluation.report.figures_not_drawn {
        println!("{why}");
    }
    Ok(())
}

/// One map segment's score.
#[derive(serde::Serialize)]
struct SegmentScore {
    segment: u32,
    file: String,
    poses: usize,
    ate_rmse_m: f64,
    gt_path_m: f64,
}

/// The map segments of run folder `run` that never merged into segment 0
/// (`trajectory-segment-N.txt`), each aligned to the ground truth on its own, with `main`
/// (segment 0, scored above): `segments.md` and `segments.json` in `out`, and a table on
/// stdout. `None` when the run has no such segment.
fn score_segments(run: &std::path::Path, gt: &[duv_core::StampedPose], options: &TrajectoryOptions, main: SegmentScore, out: &std::path::Path) -> anyhow::Result<Option<Vec<PathBuf>>> {
    let mut files: Vec<(u32, PathBuf)> = std::fs::read_dir(run)
        .with_context(|| format!("listing {}", run.display()))?
        .flatten()
        .filter_map(|e| {
            let name = e.file_name();
            let n = name.to_str()?.strip_prefix("trajectory-segment-")?.strip_suffix(".txt")?.parse().ok()?;
            Some((n, e.path()))
        })
        .collect();
    if files.is_empty() {
        return Ok(None);
    }
    files.sort();
    if options.alignment != Alignment::Sim3 {
        println!("\nmap segments {}: not scored (each has its own frame and scale; only --align sim3 compares them)", files.iter().map(|f| f.0.to_string()).collect::<Vec<_>>().join(", "));
        return Ok(None);
    }
    let mut scores = vec![main];
    for (segment, path) in files {
        let est = read_trajectory(&path)?;
        if est.len() < 3 {
            println!("{}: {} pose(s), too few to align", path.display(), est.len());
            continue;
        }
        let ev = duv_eval::trajectory::evaluate_trajectory(gt, &est, options, "gt", &path.display().to_string()).with_context(|| format!("scoring {}", path.display()))?;
        scores.push(SegmentScore { segment, file: path.display().to_string(), poses: est.len(), ate_rmse_m: ev.report.ate.stats_m.rmse, gt_path_m: ev.report.gt_path_length_m });
    }
    let poses: usize = scores.iter().map(|s| s.poses).sum();
    let rmse = (scores.iter().map(|s| s.ate_rmse_m.powi(2) * s.poses as f64).sum::<f64>() / poses.max(1) as f64).sqrt();
    let path: f64 = scores.iter().map(|s| s.gt_path_m).sum();
    let mut md = String::from("| map segment | file | poses | ATE RMSE (m) | ground-truth path (m) |\n|---|---|---|---|---|\n");
    for s in &scores {
        md.push_str(&format!("| {} | {} | {} | {:.6} | {:.3} |\n", s.segment, s.file, s.poses, s.ate_rmse_m, s.gt_path_m));
    }
    md.push_str(&format!("| all, each aligned on its own | | {poses} | {rmse:.6} | {path:.3} |\n"));
    print!("\n{md}");
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let (md_path, json_path) = (out.join("segments.md"), out.join("segments.json"));
    std::fs::write(&md_path, &md).with_context(|| format!("writing {}", md_path.display()))?;
    let json = serde_json::json!({ "segments": scores, "poses": poses, "ate_rmse_m": rmse, "gt_path_m": path, "alignment": "sim3 per segment" });
    std::fs::write(&json_path, serde_json::to_string_pretty(&json)?).with_context(|| format!("writing {}", json_path.display()))?;
    Ok(Some(vec![md_path, json_path]))
}
