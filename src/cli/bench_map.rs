//! `duv bench map`: the mapping figures of issue 4 on generated sequences, with ground-truth
//! poses and depth (the generator's keyframes, `duv_sim::keyframes`) or, with `--poses
//! tracked`, with the tracker's: the sequence is tracked first and its final keyframes (poses
//! after the last BA, inverse depth and variance upsampled as `duv run` writes them) are
//! mapped, moved into the ground-truth frame by the Sim(3) of the trajectory's ATE alignment so
//! that the medium is scored in metres and the mapper's metric limits (split and prune sizes)
//! mean metres, as they do for the generator's keyframes.
//!
//! Per water (default clear and turbid) and per variant: keyframe PSNR/SSIM of the render
//! against the input, PSNR of the restored image against the water-free view, the same on
//! the frames halfway between consecutive keyframes (views the map was not optimised on,
//! rendered from the tracker's poses for them with `--poses tracked`, else the true ones;
//! with `--novel-altitude-m`, also from those frames' positions flown at another altitude),
//! the keyframes' rendered depth against the true depth of their images, the recovered
//! `beta_D`/`beta_B`/`B_inf` along the first keyframe's axis against the generator's
//! `medium.json`, ms per iteration and the Gaussian count over time. Variants (the paper's
//! Tables 5-6): `full`, `no_medium` (medium fixed at ~zero: plain 3DGS), `one_coefficient`
//! (`sigma_bs = sigma_att`), `no_mahalanobis`, `no_kl`. The ablation runs on `--ablation-water`
//! only; the other waters run `full` and `no_medium`. Writes `report.json` and `report.md` and
//! the render panels of every run into `--out`. `--altitude-swing-m` flies the survey with a
//! yo-yo altitude profile, so the map sees the seabed from several ranges per direction.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use duv_core::MediumParams;
use duv_eval::image::{psnr, ssim, SsimConvention};
use duv_core::io::write_atomic;
use duv_map::GpuOptions;
use duv_map::backend::MapperDevice;
use duv_map::mapper::{Mapper, MapperCapacity, MapperConfig};
use duv_map::pose_refine::PoseRefineConfig;
use duv_map::render::DepthMode;
use duv_eval::map_quality::{summarise_restored, RestoredSummary};
use duv_map::render::MediumPlanes;
use duv_map::restore::{restore_captured, RestoreConfig};
use duv_pipeline::map_report::{score_views, ScoreView};
use duv_sim::keyframes::sim_keyframes;
use duv_sim::keyframes::SimKeyframe;
use duv_sim::{SimConfig, SimFrame, SimRenderer, TrajectoryKind, WaterPreset};
use duv_core::{Keyframe, PlaneF32, Se3};
use duv_eval::{evaluate_trajectory, TrajectoryOptions};
use duv_track::{Tracker, TrackerCapacity, TrackerConfig, TrajectoryRecorder};

/// Where the mapped keyframes' poses and depth come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PoseSource {
    /// The generator's: every --every-th frame, exact pose and depth.
    Gt,
    /// The tracker's final keyframes over the generated frames, aligned to the ground truth by Sim(3).
    Tracked,
}

#[derive(clap::Args)]
pub struct BenchMapArgs {
    /// Output folder (report.json, report.md, renders per run).
    #[arg(long, default_value = "out/bench-map")]
    out: PathBuf,
    /// Waters to run (`full` and `no_medium` each).
    #[arg(long = "water", alias = "waters", value_name = "WATER,...", value_enum, value_delimiter = ',', default_values_t = [WaterPreset::Clear, WaterPreset::Turbid])]
    waters: Vec<WaterPreset>,
    /// The water of the full ablation (all five variants).
    #[arg(long, value_enum, default_value_t = WaterPreset::Turbid)]
    ablation_water: WaterPreset,
    /// Generated frames; every --every-th is a keyframe.
    #[arg(long, default_value_t = 40)]
    frames: usize,
    #[arg(long, default_value_t = 5)]
    every: usize,
    #[arg(long, default_value_t = 320)]
    width: usize,
    #[arg(long, default_value_t = 240)]
    height: usize,
    /// Optimisation iterations per run.
    #[arg(long, default_value_t = 600)]
    iterations: u64,
    /// Wall-clock budget of each run's optimisation, seconds, instead of --iterations: the
    /// PSNR a mapper reaches in a fixed time (half the budget shared while keyframes arrive,
    /// the rest after; the report gives the iterations done).
    #[arg(long)]
    seconds: Option<f64>,
    /// Gaussian cap of the map.
    #[arg(long, default_value_t = 50_000)]
    max_gaussians: usize,
    /// Mapper config (TOML, `MapperConfig` fields) for the `full` variant; the others change one thing.
    #[arg(long = "mapper-config", alias = "config", value_name = "FILE")]
    config: Option<PathBuf>,
    /// Seed a Gaussian every this many pixels of keyframe depth (overrides the config's
    /// `init_stride_px`; 2 as onboard by default, 1 as `duv refine` with a larger --max-gaussians).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=64))]
    init_stride_px: Option<u64>,
    /// Vignetting strength of the generated images. The mapper has no vignetting model (a
    /// calibrated camera is flat-fielded first), and the generator's gain also darkens the
    /// backscatter, which only a weaker medium fits: 0 keeps the medium identifiable.
    #[arg(long, default_value_t = 0.0)]
    vignetting: f64,
    /// Where the mapper renders (as `duv run --mapper`); the report names the renderer.
    #[arg(long, value_enum, default_value_t = MapperDevice::Auto)]
    mapper: MapperDevice,
    /// GPU memory for the Vulkan mapper, MiB.
    #[arg(long, default_value_t = 2048)]
    gpu_mb: u32,
    /// Only these variants (comma-separated); all by default.
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Keyframe poses and depth: the generator's (`gt`) or the tracker's (`tracked`: the
    /// frames are tracked first; --every is then unused, the tracker picks its keyframes).
    #[arg(long, value_enum, default_value_t = PoseSource::Gt)]
    poses: PoseSource,
    /// Board profile of the tracker's capacities (with --poses tracked).
    #[arg(long, default_value = "boards/sim.toml")]
    board: PathBuf,
    /// Refine the keyframe poses photometrically against the map (as `duv refine
    /// --refine-poses`) every this many iterations once every keyframe is in, the first keyframe
    /// held; 0 = never. The report gives the keyframes' mean pose error against the truth (pose
    /// relative to the first keyframe) before and after.
    #[arg(long, default_value_t = 0)]
    refine_poses_every: u64,
    /// Tracker parameters (TOML, `TrackerConfig` fields) for --poses tracked; defaults otherwise.
    #[arg(long, value_name = "FILE")]
    tracker_config: Option<PathBuf>,
    /// Also score views of the same survey flown at this altitude instead of the generator's
    /// 2 m (metres, in [0.3, 20]), at the held-out frames' positions and true poses: ranges
    /// the map never saw the seabed from. Ground-truth poses only (a tracked map's alignment
    /// leaves the roll about the path open).
    #[arg(long, value_name = "M")]
    novel_altitude_m: Option<f64>,
    /// Fly the generated survey with a yo-yo altitude profile (as `duv sim --altitude-swing`):
    /// the altitude swings this far above and below 2 m, so the map sees the seabed from
    /// different ranges (metres; 0 = constant altitude).
    #[arg(long, value_name = "M", default_value_t = 0.0)]
    altitude_swing_m: f64,
    /// Period of the yo-yo altitude profile, seconds.
    #[arg(long, value_name = "S", default_value_t = 10.0)]
    altitude_period_s: f64,
}

/// How the tracker did on a sequence whose keyframes were mapped (--poses tracked).
#[derive(Clone, Copy, Debug, serde::Serialize)]
struct TrackedSummary {
    /// Keyframes the tracker kept to the end with depth maps (the ones mapped).
    keyframes: usize,
    /// ATE RMSE after Sim(3) alignment, metres and % of path length.
    ate_rmse_m: f64,
    ate_percent_of_path: f64,
    /// Scale of the alignment (metres per tracker unit).
    scale: f64,
    /// Share of the keyframe pixels with true depth that have a tracked depth and variance.
    depth_coverage: f64,
    /// Medians over those pixels of the relative inverse-depth error `|d - d_true| / d_true`
    /// and of the relative standard deviation the tracker gave `sqrt(var) / d`.
    median_rel_error: f64,
    median_rel_std: f64,
    /// Share of those pixels whose relative standard deviation is within the mapper's
    /// seeding limit (`MapperConfig::init_max_rel_std`).
    seedable: f64,
    /// Share of those seedable pixels whose relative error is above 5 % (mostly bands along
    /// occlusion boundaries, where the upsampling meets two surfaces).
    seedable_over_5pct: f64,
    /// 90th percentile of the relative error over all pixels with a tracked depth.
    p90_rel_error: f64,
}

impl TrackedSummary {
    fn describe(&self) -> String {
        format!(
            "{} keyframes with depth, ATE {:.3} m ({:.3}% of path), Sim(3) scale {:.4}; depth on {:.1}% of the pixels, median relative error {:.3}, median relative std {:.3}, {:.1}% within the seeding limit ({:.1}% of those more than 5% off), 90th percentile relative error {:.3}",
            self.keyframes,
            self.ate_rmse_m,
            self.ate_percent_of_path,
            self.scale,
            100.0 * self.depth_coverage,
            self.median_rel_error,
            self.median_rel_std,
            100.0 * self.seedable,
            100.0 * self.seedable_over_5pct,
            self.p90_rel_error
        )
    }
}

/// The tracker's keyframes in the ground-truth frame, its summary, and every frame's final
/// tracked pose in that frame (by frame index).
type Tracked = (Vec<SimKeyframe>, TrackedSummary, Vec<Se3>);

/// Tracks every frame of `renderer` and returns the final keyframes that still have depth
/// maps, in the ground-truth frame: poses through the ATE's Sim(3) `gt_from_est`, inverse
/// depth divided by its scale and variance by its square.
fn tracked_keyframes(renderer: &SimRenderer, cfg: &TrackerConfig, cap: TrackerCapacity, seed_max_rel_std: f64) -> anyhow::Result<Tracked> {
    let frames = super::bench_track::render_frames(renderer);
    let mut tracker = Tracker::new(renderer.camera(), cfg, cap)?;
    let mut recorder = TrajectoryRecorder::new();
    tracker.run_in_pool(|t| -> anyhow::Result<()> {
        for f in &frames {
            let out = t.track(f)?;
            recorder.record(&out);
        }
        Ok(())
    })?;
    let fin = recorder.finish(&mut tracker);
    let gt = &renderer.poses()[..frames.len()];
    let ev = evaluate_trajectory(gt, &fin.frames, &TrajectoryOptions::default(), "ground truth", "tracked").context("aligning the tracked trajectory")?;
    let align = ev.gt_from_est;
    let scale = ev.report.alignment.scale;
    anyhow::ensure!(fin.frames.len() == frames.len(), "the tracker returned {} poses for {} frames", fin.frames.len(), frames.len());
    let frame_poses: Vec<Se3> = fin.frames.iter().map(|f| duv_core::pose::sim3_apply_to_pose(&align, &f.world_from_cam)).collect();
    let cam = *renderer.camera();
    let mut out = Vec::new();
    let (mut with_truth, mut rel_errors, mut rel_stds) = (0usize, Vec::new(), Vec::new());
    for k in fin.keyframes.iter().filter(|k| k.live) {
        if !tracker.keyframes().any(|v| v.id == k.id && v.variance.is_some()) {
            continue;
        }
        let mut inv_depth = PlaneF32::new(cam.width, cam.height);
        let mut inv_depth_variance = PlaneF32::new(cam.width, cam.height);
        tracker.upsample_keyframe(k.id, &mut inv_depth, &mut inv_depth_variance)?;
        let inv_scale = (1.0 / scale) as f32;
        for d in inv_depth.data.iter_mut() {
            *d *= inv_scale;
        }
        for v in inv_depth_variance.data.iter_mut() {
            if *v < f32::MAX {
                *v *= inv_scale * inv_scale;
            }
        }
        let f = renderer.render(k.seq as usize);
        for ((&z, &d), &v) in f.depth_m.data.iter().zip(&inv_depth.data).zip(&inv_depth_variance.data) {
            if z > 0.0 && z.is_finite() {
                with_truth += 1;
                if d > 0.0 && d.is_finite() && v < f32::MAX {
                    rel_errors.push((d as f64 * z as f64 - 1.0).abs());
                    rel_stds.push((v as f64).sqrt() / d as f64);
                }
            }
        }
        out.push(SimKeyframe {
            keyframe: Keyframe {
                index: k.seq,
                t_ns: k.t_ns,
                image: f.rgb,
                world_from_cam: duv_core::pose::sim3_apply_to_pose(&align, &k.world_from_cam),
                camera: cam,
                inv_depth,
                inv_depth_variance,
            },
            clear: f.clear,
        });
    }
    let ate = &ev.report.ate;
    let depth_coverage = rel_errors.len() as f64 / with_truth.max(1) as f64;
    let seedable_count = rel_stds.iter().filter(|&&s| s <= seed_max_rel_std).count();
    let seedable = seedable_count as f64 / rel_stds.len().max(1) as f64;
    let seedable_over = rel_stds.iter().zip(&rel_errors).filter(|(&s, &e)| s <= seed_max_rel_std && e > 0.05).count();
    let seedable_over_5pct = seedable_over as f64 / seedable_count.max(1) as f64;
    let p90_rel_error = {
        let mut e = rel_errors.clone();
        e.sort_by(f64::total_cmp);
        e.get(e.len() * 9 / 10).copied().unwrap_or(f64::NAN)
    };
    let summary = TrackedSummary {
        keyframes: out.len(),
        ate_rmse_m: ate.stats_m.rmse,
        ate_percent_of_path: ev.report.ate_rmse_percent_of_path.unwrap_or(f64::NAN),
        scale,
        depth_coverage,
        median_rel_error: super::bench_track::median(rel_errors),
        median_rel_std: super::bench_track::median(rel_stds),
        seedable,
        seedable_over_5pct,
        p90_rel_error,
    };
    Ok((out, summary, frame_poses))
}

#[derive(serde::Serialize)]
struct RunResult {
    water: String,
    variant: String,
    /// The generated survey's yo-yo altitude swing and period (`--altitude-swing-m`; 0 = flat).
    altitude_swing_m: f64,
    altitude_period_s: f64,
    keyframes: usize,
    iterations: u64,
    mean_psnr_db: f64,
    mean_ssim: f64,
    mean_restored_psnr_db: f64,
    /// The keyframes' restored views against the water-free truth, with the captured frames'
    /// own scores, the map albedo's and the mean colour error per channel.
    keyframes_restored: Option<RestoredSummary>,
    /// The keyframes restored with the generator's medium instead of the map's (same range):
    /// the gap to `mean_restored_psnr_db` is what the medium estimate costs.
    restored_true_medium_psnr_db: f64,
    /// The keyframes' rendered depth against the true depth.
    depth: DepthScore,
    /// The same scores on the frames halfway between consecutive keyframes, which the map
    /// was not optimised on ([`heldout_frames`]).
    heldout: Option<HeldOut>,
    /// The same at the held-out frames flown at `--novel-altitude-m` (metres, scores).
    novel_altitude: Option<(f64, HeldOut)>,
    medium: MediumParams,
    medium_truth: MediumParams,
    /// |recovered - truth| / truth, rows beta_D, beta_B, B_inf; columns R G B.
    medium_rel_error: [[f64; 3]; 3],
    ms_per_iteration: f64,
    gaussians_over_time: Vec<(u64, usize)>,
    /// What rendered (`Mapper::render_device`).
    renderer: String,
    /// `gt` or `tracked` (`--poses`).
    poses: &'static str,
    /// The tracker's run (with --poses tracked).
    tracked: Option<TrackedSummary>,
    /// Mean keyframe pose error against the truth (m, deg), each keyframe's pose relative to
    /// the first's, as mapped and at the end (they differ with --refine-poses-every).
    pose_error_in: (f64, f64),
    pose_error_out: (f64, f64),
}

/// The rendered depth (Eq. 11) of the keyframes, each from the pose it is mapped at, against
/// the true depth of the keyframe's image, over the pixels where the true ray hit the scene.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
struct DepthScore {
    /// Share of those pixels the map covers (rendered alpha >= 0.5).
    coverage: f64,
    /// Median of `|z - z_true| / z_true` over the covered pixels.
    median_rel_error: f64,
    /// Share of the covered pixels within 5 % of the true depth.
    within_5pct: f64,
}

/// [`DepthScore`] of one view, as (covered pixels, pixels with truth), relative errors pushed
/// onto `errors`. `depth` is in the mapper's [`DepthMode`].
fn depth_errors(depth: &PlaneF32, alpha: &PlaneF32, true_z_m: &PlaneF32, mode: DepthMode, errors: &mut Vec<f64>) -> (usize, usize) {
    let (mut covered, mut truth) = (0, 0);
    for ((&d, &a), &z_true) in depth.data.iter().zip(&alpha.data).zip(&true_z_m.data) {
        if !(z_true > 0.0 && z_true.is_finite()) {
            continue;
        }
        truth += 1;
        let z = match mode {
            DepthMode::InverseDepth => 1.0 / d as f64,
            DepthMode::Depth => d as f64,
        };
        if a >= 0.5 && d > 0.0 && z.is_finite() {
            covered += 1;
            errors.push((z - z_true as f64).abs() / z_true as f64);
        }
    }
    (covered, truth)
}

fn depth_score(errors: &mut [f64], covered: usize, truth: usize) -> DepthScore {
    if errors.is_empty() {
        return DepthScore::default();
    }
    errors.sort_by(f64::total_cmp);
    DepthScore {
        coverage: covered as f64 / truth.max(1) as f64,
        median_rel_error: errors[errors.len() / 2],
        within_5pct: errors.iter().filter(|e| **e <= 0.05).count() as f64 / errors.len() as f64,
    }
}

/// Scores of the held-out views.
#[derive(Clone, Copy, Debug, serde::Serialize)]
struct HeldOut {
    views: usize,
    mean_psnr_db: f64,
    mean_ssim: f64,
    mean_restored_psnr_db: f64,
    restored: Option<RestoredSummary>,
}

/// The generated frames halfway between consecutive keyframes that are at least two frames
/// apart, views of the same survey the map never optimised on, each with the pose it is
/// rendered from: the tracker's (`tracked_poses`, by frame index, in the map's frame), as the
/// keyframes are mapped at theirs, else the true one.
fn heldout_frames(renderer: &SimRenderer, kfs: &[SimKeyframe], tracked_poses: Option<&[Se3]>) -> Vec<(SimFrame, Se3)> {
    kfs.windows(2)
        .filter_map(|w| {
            let (a, b) = (w[0].keyframe.index as usize, w[1].keyframe.index as usize);
            let i = (a + b) / 2;
            if b < a + 2 || b >= renderer.len() {
                return None;
            }
            let f = renderer.render(i);
            let pose = match tracked_poses {
                Some(p) => *p.get(i)?,
                None => f.world_from_cam,
            };
            Some((f, pose))
        })
        .collect()
}

/// Mean PSNR/SSIM of the renders from each view's pose against its image, and of the
/// restored view against its water-free image (the run's [`score_views`]); `None` without views.
fn score_bench_views(mapper: &mut Mapper, camera: &duv_core::PinholeCamera, views: &[(SimFrame, Se3)], restore: &RestoreConfig) -> anyhow::Result<Option<HeldOut>> {
    let views: Vec<ScoreView> = views.iter().enumerate().map(|(i, (f, pose))| ScoreView { seq: i as u64, world_from_cam: *pose, captured: f.rgb.clone(), clear: Some(f.clear.clone()) }).collect();
    let scores = score_views(mapper, camera, &views, restore, None)?;
    let n = scores.len() as f64;
    let restored = summarise_restored(&scores);
    Ok((!scores.is_empty()).then(|| HeldOut {
        views: scores.len(),
        mean_psnr_db: scores.iter().map(|v| v.psnr_db).sum::<f64>() / n,
        mean_ssim: scores.iter().map(|v| v.ssim).sum::<f64>() / n,
        mean_restored_psnr_db: restored.map_or(f64::NAN, |r| r.psnr_mean_db),
        restored,
    }))
}

const VARIANTS: [&str; 5] = ["full", "no_medium", "one_coefficient", "no_mahalanobis", "no_kl"];

fn variant_config(base: &MapperConfig, variant: &str) -> MapperConfig {
    let mut c = base.clone();
    match variant {
        "no_medium" => {
            c.medium.init_c_med = [1e-4; 3];
            c.medium.init_sigma_att = [1e-6; 3];
            c.medium.init_sigma_bs = [1e-6; 3];
            c.medium.head_init_scale = 0.0;
            c.optimise_medium = false;
            c.init_compensate_medium = false;
        }
        "one_coefficient" => c.single_medium_coefficient = true,
        "no_mahalanobis" => c.loss.mahalanobis_weight = 0.0,
        "no_kl" => c.loss.kl_weight = 0.0,
        _ => {}
    }
    c
}

fn water_name(w: WaterPreset) -> &'static str {
    match w {
        WaterPreset::Clear => "clear",
        WaterPreset::Coastal => "coastal",
        WaterPreset::Turbid => "turbid",
    }
}

pub fn run(a: BenchMapArgs) -> anyhow::Result<()> {
    let mut base: MapperConfig = match &a.config {
        Some(p) => toml::from_str(&duv_core::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
        None => MapperConfig::default(),
    };
    if let Some(stride) = a.init_stride_px {
        base.init_stride_px = stride as usize;
    }
    let mut waters = a.waters.clone();
    if !waters.contains(&a.ablation_water) {
        waters.push(a.ablation_water);
    }
    let tracker = match a.poses {
        PoseSource::Gt => None,
        PoseSource::Tracked => {
            let cfg = match &a.tracker_config {
                Some(p) => toml::from_str::<TrackerConfig>(&duv_core::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
                None => TrackerConfig::default(),
            };
            Some((cfg, TrackerCapacity::from_board(&super::load_board(&a.board)?)))
        }
    };
    if a.novel_altitude_m.is_some() && tracker.is_some() {
        anyhow::bail!("--novel-altitude-m needs --poses gt: a tracked map's Sim(3) alignment leaves the roll about the path open, so true poses of other views do not fit it");
    }
    let mut results = Vec::new();
    for &water in &waters {
        let mut cfg = SimConfig::preset(water, TrajectoryKind::Survey);
        cfg.frames = a.frames;
        cfg.width = a.width;
        cfg.height = a.height;
        cfg.vignetting = a.vignetting;
        cfg.altitude_swing_m = a.altitude_swing_m;
        cfg.altitude_period_s = a.altitude_period_s;
        let renderer = SimRenderer::new(&cfg).context("building the generated sequence")?;
        let truth = *renderer.medium();
        let renderer_poses = renderer.poses().to_vec();
        let (kfs, tracked, frame_poses) = match &tracker {
            None => (sim_keyframes(&renderer, a.every, usize::MAX), None, None),
            Some((tcfg, cap)) => {
                let (k, t, poses) = tracked_keyframes(&renderer, tcfg, *cap, base.init_max_rel_std).with_context(|| format!("tracking the {} survey", water_name(water)))?;
                println!("{:8} tracked: {}", water_name(water), t.describe());
                (k, Some(t), Some(poses))
            }
        };
        anyhow::ensure!(!kfs.is_empty(), "no keyframes (with --poses tracked: the tracker kept none with depth; more --frames?)");
        let heldout = heldout_frames(&renderer, &kfs, frame_poses.as_deref());
        // The true depth (z, metres; 0 where the ray hit nothing) of each keyframe's image,
        // from the pose it was taken at. Not from the tracker's aligned pose: the alignment
        // leaves the roll about the path open, and the map is rendered in the tracker's frame.
        let true_depth: Vec<PlaneF32> = kfs.iter().map(|s| renderer.depth_at(&renderer.pose(s.keyframe.index as usize).world_from_cam)).collect();
        let novel: Vec<(SimFrame, Se3)> = match a.novel_altitude_m {
            None => Vec::new(),
            Some(altitude_m) => {
                let flown = SimRenderer::new(&SimConfig { altitude_m, altitude_swing_m: 0.0, ..cfg.clone() }).context("--novel-altitude-m: building the survey at that altitude")?;
                heldout_frames(&flown, &kfs, None)
            }
        };
        let variants: Vec<&str> = VARIANTS
            .iter()
            .copied()
            .filter(|v| water == a.ablation_water || matches!(*v, "full" | "no_medium"))
            .filter(|v| a.only.is_empty() || a.only.iter().any(|o| o == v))
            .collect();
        for variant in variants {
            let config = variant_config(&base, variant);
            let cam = kfs[0].keyframe.camera;
            let capacity = MapperCapacity { max_gaussians: a.max_gaussians, max_keyframes: kfs.len(), width: cam.width, height: cam.height };
            let mut mapper = Mapper::new(config, capacity)?;
            let renderer = mapper.use_device(a.mapper, &GpuOptions::with_budget_mb(a.gpu_mb))?;
            println!("{:8} {:16} renders with {renderer}", water_name(water), variant);
            // Keyframes arrive one by one with iterations in between, as in `duv run`.
            let per_kf = a.iterations / (2 * kfs.len() as u64).max(1);
            let mut over_time = vec![(0u64, 0usize)];
            let start = Instant::now();
            for (k, s) in kfs.iter().enumerate() {
                mapper.add_keyframe(s.keyframe.clone())?;
                match a.seconds {
                    // Keyframe k's share ends at (k+1)/(2n) of the budget.
                    Some(budget_s) => {
                        let until_s = budget_s * (k + 1) as f64 / (2 * kfs.len()) as f64;
                        while start.elapsed().as_secs_f64() < until_s {
                            mapper.iterate()?;
                        }
                    }
                    None => {
                        for _ in 0..per_kf {
                            mapper.iterate()?;
                        }
                    }
                }
                over_time.push((mapper.iteration(), mapper.gaussians().len()));
            }
            if let Some(budget_s) = a.seconds {
                while start.elapsed().as_secs_f64() < budget_s {
                    mapper.iterate()?;
                }
            }
            let rest = match a.seconds {
                Some(_) => 0,
                None => a.iterations.saturating_sub(mapper.iteration()),
            };
            let every = (rest / 10).max(1);
            let pose_cfg = PoseRefineConfig::default();
            for i in 1..=rest {
                mapper.iterate()?;
                if i % every == 0 {
                    over_time.push((mapper.iteration(), mapper.gaussians().len()));
                }
                if a.refine_poses_every > 0 && i % a.refine_poses_every == 0 && i + a.refine_poses_every <= rest {
                    for (slot, s) in kfs.iter().enumerate().skip(1) {
                        if let Err(e) = mapper.refine_keyframe_pose(slot, &s.keyframe.world_from_cam, &pose_cfg) {
                            tracing::debug!(slot, error = %e, "bench map: pose not refined");
                        }
                    }
                }
            }
            // Relative to the first keyframe (the held one): the Sim(3) of the tracked
            // trajectory aligns positions, and on a straight survey leaves the roll about the
            // path open.
            let pose_error = |pose: &dyn Fn(usize) -> duv_core::Se3| {
                let (mut et, mut er) = (0.0, 0.0);
                let (t0, p0) = (renderer_poses[kfs[0].keyframe.index as usize].world_from_cam, pose(0));
                for (slot, s) in kfs.iter().enumerate().skip(1) {
                    let t = t0.inv_mul(&renderer_poses[s.keyframe.index as usize].world_from_cam);
                    let p = p0.inv_mul(&pose(slot));
                    et += (p.translation.vector - t.translation.vector).norm();
                    er += duv_core::pose::rotation_angle(&t.inv_mul(&p).rotation).to_degrees();
                }
                let n = (kfs.len() - 1).max(1) as f64;
                (et / n, er / n)
            };
            let pose_error_in = pose_error(&|slot| kfs[slot].keyframe.world_from_cam);
            let pose_error_out = pose_error(&|slot| mapper.keyframe(slot).map_or(kfs[slot].keyframe.world_from_cam, |k| k.world_from_cam));
            let ms_per_iteration = start.elapsed().as_secs_f64() * 1e3 / mapper.iteration().max(1) as f64;
            let dir = a.out.join(format!("{}-{variant}", water_name(water)));
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            let (mut p_sum, mut s_sum, mut t_sum) = (0.0, 0.0, 0.0);
            let (mut depth_errs, mut covered, mut with_truth) = (Vec::new(), 0, 0);
            let depth_mode = mapper.config().render.depth_mode;
            let restore = RestoreConfig::default();
            let cam = kfs[0].keyframe.camera;
            let truth_planes = MediumPlanes::uniform(cam.width, cam.height, truth.b_inf.map(|v| v as f32), truth.beta_d.map(|v| v as f32), truth.beta_b.map(|v| v as f32));
            let mut with_truth_medium = duv_core::ImageRgbF32::new(cam.width, cam.height);
            for (slot, s) in kfs.iter().enumerate() {
                let out = mapper.render_keyframe(slot)?;
                let (c, t) = depth_errors(&out.depth, &out.alpha, &true_depth[slot], depth_mode, &mut depth_errs);
                (covered, with_truth) = (covered + c, with_truth + t);
                let input = s.keyframe.image.to_rgb_f32();
                p_sum += psnr(&out.colour, &input)?;
                s_sum += ssim(&out.colour, &input, SsimConvention::Skimage)?;
                // The same restoration with the generator's medium: what the medium estimate costs.
                restore_captured(&input, out, &truth_planes, &cam, depth_mode, &restore, &mut with_truth_medium)?;
                t_sum += psnr(&with_truth_medium, &s.clear.to_rgb_f32())?;
            }
            let n = kfs.len() as f64;
            // The restored view (and the render panels) through the run's own scoring.
            let kf_views: Vec<ScoreView> = kfs.iter().map(|s| ScoreView { seq: s.keyframe.index, world_from_cam: s.keyframe.world_from_cam, captured: s.keyframe.image.clone(), clear: Some(s.clear.clone()) }).collect();
            let kf_scores = score_views(&mut mapper, &cam, &kf_views, &restore, Some(&dir))?;
            let keyframes_restored = summarise_restored(&kf_scores);
            let heldout_metrics = score_bench_views(&mut mapper, &cam, &heldout, &restore)?;
            let novel_metrics = score_bench_views(&mut mapper, &cam, &novel, &restore)?;
            let medium = mapper.medium_summary(&kfs[0].keyframe.world_from_cam);
            let r = RunResult {
                water: water_name(water).into(),
                variant: variant.into(),
                altitude_swing_m: cfg.altitude_swing_m,
                altitude_period_s: cfg.altitude_period_s,
                keyframes: kfs.len(),
                iterations: mapper.iteration(),
                mean_psnr_db: p_sum / n,
                mean_ssim: s_sum / n,
                mean_restored_psnr_db: keyframes_restored.map_or(f64::NAN, |r| r.psnr_mean_db),
                keyframes_restored,
                restored_true_medium_psnr_db: t_sum / n,
                depth: depth_score(&mut depth_errs, covered, with_truth),
                heldout: heldout_metrics,
                novel_altitude: novel_metrics.map(|m| (a.novel_altitude_m.unwrap_or(f64::NAN), m)),
                medium,
                medium_truth: truth,
                medium_rel_error: medium.rel_error(&truth),
                ms_per_iteration,
                gaussians_over_time: over_time,
                renderer,
                poses: match a.poses {
                    PoseSource::Gt => "gt",
                    PoseSource::Tracked => "tracked",
                },
                tracked,
                pose_error_in,
                pose_error_out,
            };
            if a.refine_poses_every > 0 {
                println!("{:8} {:16} keyframe pose error {:.4} m {:.3} deg as mapped, {:.4} m {:.3} deg refined", r.water, r.variant, pose_error_in.0, pose_error_in.1, pose_error_out.0, pose_error_out.1);
            }
            println!(
                "{:8} {:16} PSNR {:6.2} dB  SSIM {:.4}  restored PSNR {:6.2} dB  max medium rel.err {:.3}  {} its  {:.1} ms/it  {} Gaussians",
                r.water,
                r.variant,
                r.mean_psnr_db,
                r.mean_ssim,
                r.mean_restored_psnr_db,
                r.medium.worst_rel_error(&r.medium_truth),
                r.iterations,
                r.ms_per_iteration,
                mapper.gaussians().len()
            );
            println!(
                "{:8} {:16} rendered depth: {:.1} % within 5 % of the truth, median rel.err {:.4}, coverage {:.1} %",
                r.water,
                r.variant,
                100.0 * r.depth.within_5pct,
                r.depth.median_rel_error,
                100.0 * r.depth.coverage
            );
            if let Some(h) = &r.heldout {
                println!("{:8} {:16} held-out views ({}): PSNR {:6.2} dB  SSIM {:.4}  restored PSNR {:6.2} dB", r.water, r.variant, h.views, h.mean_psnr_db, h.mean_ssim, h.mean_restored_psnr_db);
            }
            let rs = |what: &str, x: &Option<RestoredSummary>| {
                if let Some(x) = x {
                    println!(
                        "{:8} {:16} {what} vs water-free truth: restored {:6.2} dB (err RGB {:+.3} {:+.3} {:+.3}), captured {:6.2} dB (err {:+.3} {:+.3} {:+.3}), map albedo {:6.2} dB (err {:+.3} {:+.3} {:+.3}); {} of {} worse than captured",
                        r.water, r.variant, x.psnr_mean_db, x.mean_error_rgb[0], x.mean_error_rgb[1], x.mean_error_rgb[2], x.captured_psnr_mean_db, x.captured_mean_error_rgb[0], x.captured_mean_error_rgb[1], x.captured_mean_error_rgb[2],
                        x.albedo_psnr_mean_db, x.albedo_mean_error_rgb[0], x.albedo_mean_error_rgb[1], x.albedo_mean_error_rgb[2], x.worse_than_captured, x.views
                    );
                }
            };
            rs("keyframes", &r.keyframes_restored);
            rs("held-out", &r.heldout.and_then(|h| h.restored));
            println!("{:8} {:16} keyframes restored with the generator's medium: {:6.2} dB", r.water, r.variant, r.restored_true_medium_psnr_db);
            if let Some((alt, h)) = &r.novel_altitude {
                println!("{:8} {:16} views from {alt} m ({}): PSNR {:6.2} dB  SSIM {:.4}  restored PSNR {:6.2} dB", r.water, r.variant, h.views, h.mean_psnr_db, h.mean_ssim, h.mean_restored_psnr_db);
            }
            if let Some(g) = mapper.gpu() {
                println!(
                    "{:8} {:16} GPU arena peak {:.1} MiB of {} MiB; per-kernel GPU ms per iteration:",
                    r.water,
                    r.variant,
                    g.arena_peak_bytes() as f64 / (1 << 20) as f64,
                    g.arena_capacity_bytes() >> 20
                );
                let its = r.iterations.max(1);
                println!("    host side per iteration: {}", g.host_stats().describe_per(its));
                for (k, d, ms) in g.profile().rows() {
                    println!("    {:<48} {:8.3} ms ({} dispatches)", k.name(), ms / its as f64, d / its);
                }
            }
            results.push(r);
            // Keep the report current while the next run works.
            write_reports(&a, base.init_stride_px, &results)?;
        }
    }
    println!("wrote {}", a.out.display());
    Ok(())
}

fn write_reports(a: &BenchMapArgs, init_stride_px: usize, results: &[RunResult]) -> anyhow::Result<()> {
    write_atomic(&a.out.join("report.json"), serde_json::to_string_pretty(results)?.as_bytes())?;
    let mut md = format!(
        "# duv bench map\n\n{}x{}, {} frames, {}, {}, {}, cap {} Gaussians, seeded every {} px.\n\n",
        a.width,
        a.height,
        a.frames,
        if a.altitude_swing_m > 0.0 {
            format!("altitude 2 m +- {} m (yo-yo, {} s period)", a.altitude_swing_m, a.altitude_period_s)
        } else {
            "altitude 2 m".into()
        },
        match a.poses {
            PoseSource::Gt => format!("every {}th a keyframe (ground-truth poses and depth)", a.every),
            PoseSource::Tracked => "the tracker's keyframes, poses and depth (aligned to the ground truth by Sim(3))".into(),
        },
        match a.seconds {
            Some(s) => format!("{s} s of optimisation per run"),
            None => format!("{} iterations", a.iterations),
        },
        a.max_gaussians,
        init_stride_px
    );
    md.push_str("| water | variant | PSNR dB | SSIM | restored PSNR dB | held-out PSNR dB / SSIM (restored) | depth within 5 % (median rel.err, coverage) | beta_D rel.err | beta_B rel.err | B_inf rel.err | ms/it | Gaussians |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    let f = |v: [f64; 3]| format!("{:.2} {:.2} {:.2}", v[0], v[1], v[2]);
    for r in results {
        let _ = writeln!(
            md,
            "| {} | {} | {:.2} | {:.4} | {:.2} | {} | {:.3} ({:.4}, {:.3}) | {} | {} | {} | {:.1} | {} |",
            r.water,
            r.variant,
            r.mean_psnr_db,
            r.mean_ssim,
            r.mean_restored_psnr_db,
            r.heldout.map_or("-".into(), |h| format!("{:.2} / {:.4} ({:.2}), {} views", h.mean_psnr_db, h.mean_ssim, h.mean_restored_psnr_db, h.views)),
            r.depth.within_5pct,
            r.depth.median_rel_error,
            r.depth.coverage,
            f(r.medium_rel_error[0]),
            f(r.medium_rel_error[1]),
            f(r.medium_rel_error[2]),
            r.ms_per_iteration,
            r.gaussians_over_time.last().map_or(0, |g| g.1)
        );
    }
    for r in results {
        if let Some((alt, h)) = &r.novel_altitude {
            let _ = writeln!(md, "\n{} {}: views from {alt} m altitude ({}): PSNR {:.2} dB, SSIM {:.4}, restored PSNR {:.2} dB.", r.water, r.variant, h.views, h.mean_psnr_db, h.mean_ssim, h.mean_restored_psnr_db);
        }
    }
    let mut tracked: Vec<(&str, TrackedSummary)> = results.iter().filter_map(|r| r.tracked.map(|t| (r.water.as_str(), t))).collect();
    tracked.dedup_by_key(|t| t.0);
    for (water, t) in tracked {
        let _ = writeln!(md, "\nTracked {water}: {}.", t.describe());
    }
    let mut renderers: Vec<&str> = results.iter().map(|r| r.renderer.as_str()).collect();
    renderers.dedup();
    let _ = writeln!(md, "\nRendered with: {}", renderers.join("; "));
    write_atomic(&a.out.join("report.md"), md.as_bytes())?;
    Ok(())
}
