//! `duv refine`: offshore map refinement from a keyframe folder (the layout is documented in
//! `duv_core::io::keyframes`), from the keyframes in a run's MCAP log (`--mcap`, read by
//! `duv_log::keyframes`: image, pose, inverse depth and variance of every logged keyframe, up
//! to any damage; `--from-logged-map` continues the onboard map from the log's newest map
//! checkpoint), or from generated keyframes with ground-truth poses and depth
//! (`--water WATER`) so that mapping is evaluated without the tracker.
//!
//! Writes into `--out`: `map.ply` (3DGS PLY), `map.ckpt` (full mapper checkpoint),
//! `medium.json` (the medium along the first keyframe's optical axis, the generator's keys),
//! `poses.txt` (the keyframes' final poses, TUM; changed only by `--refine-poses`),
//! `renders/NNNNNN.png` (input | render | restored | depth | uncertainty) and `metrics.json`,
//! and prints the metrics table.

use std::path::PathBuf;

use anyhow::Context;
use duv_core::{ImageRgb8, Keyframe, MediumParams};
use duv_eval::image::{psnr, ssim, SsimConvention};
use duv_core::io::keyframes::read_keyframe_folder;
use duv_core::io::png_io::write_rgb8;
use duv_core::io::write_atomic;
use duv_log::{read_log_keyframes, LoggedMap, ReadLimits};
use duv_map::GpuOptions;
use duv_map::backend::MapperDevice;
use duv_map::checkpoint::{RestoreOptions, CHECKPOINT_MAGIC};
use duv_map::mapper::{Mapper, MapperCapacity, MapperConfig};
use duv_map::ply::write_ply;
use duv_map::pose_refine::PoseRefineConfig;
use duv_map::stage::render_panel;
use duv_sim::keyframes::sim_keyframes;
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};

#[derive(clap::Args)]
pub struct RefineArgs {
    /// Keyframe folder written by the tracker (calibration.txt, keyframes.txt, keyframes/), e.g.
    /// the output folder of `duv run`.
    #[arg(long, value_name = "DIR", conflicts_with = "sim", required_unless_present_any = ["sim", "mcap"])]
    keyframes: Option<PathBuf>,
    /// Instead of a keyframe folder: a run's MCAP log (`RUN/log`, `RUN`, or one segment
    /// `.mcap`). Every keyframe logged with its image, pose, inverse depth and variance is
    /// refined; a damaged log is read with its damaged ranges skipped. The poses are those logged as each
    /// keyframe left the BA window (a later loop closure is in `RUN/keyframes.txt`, which
    /// --keyframes reads).
    #[arg(long, value_name = "LOG", conflicts_with_all = ["sim", "keyframes"])]
    mcap: Option<PathBuf>,
    /// With --mcap: start from the newest map checkpoint in the log (the onboard map: its
    /// Gaussians, medium, optimiser state, keyframe poses and mapper config, with the
    /// keyframes' pixels from their own log messages) instead of a fresh map; the logged
    /// keyframes it does not hold (logged after it, dropped by the onboard mapping queue, or
    /// evicted from the onboard store) are added. The Gaussian cap is the larger of
    /// --max-gaussians and the onboard one.
    #[arg(long, requires = "mcap", conflicts_with = "config")]
    from_logged_map: bool,
    /// The true medium (a generator's `medium.json`) to score the recovered one against
    /// (with --keyframes or --mcap; --water knows its own).
    #[arg(long, value_name = "FILE")]
    medium_truth: Option<PathBuf>,
    /// Compare with --medium-truth (per metre) even when the keyframes are in map units (a run
    /// without navigation input, or a log's keyframes): the figures then mean little.
    #[arg(long, requires = "medium_truth")]
    allow_map_units: bool,
    /// Instead of a folder: generated keyframes with ground-truth poses and depth in this water.
    #[arg(long = "water", alias = "sim", value_name = "WATER", value_enum)]
    sim: Option<WaterPreset>,
    /// Generated path (with --water).
    #[arg(long, value_enum, default_value_t = TrajectoryKind::Survey)]
    trajectory: TrajectoryKind,
    /// Generated frames (with --water); every --every-th becomes a keyframe.
    #[arg(long, default_value_t = 40)]
    frames: usize,
    /// Keyframe spacing in generated frames (with --water).
    #[arg(long, default_value_t = 5)]
    every: usize,
    /// Generated image width and height (with --water).
    #[arg(long, default_value_t = 320)]
    width: usize,
    #[arg(long, default_value_t = 240)]
    height: usize,
    /// Vignetting strength of the generated images (with --water). The mapper has no vignetting
    /// model (a calibrated camera is flat-fielded first), so 0 keeps the medium identifiable.
    #[arg(long, default_value_t = 0.0)]
    vignetting: f64,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Optimisation iterations.
    #[arg(long, default_value_t = 2000)]
    iterations: u64,
    /// Gaussian capacity of the map (the board's max_gaussians).
    #[arg(long, default_value_t = 200_000)]
    max_gaussians: usize,
    /// Keyframes kept for optimisation (the board's max_keyframes).
    #[arg(long, default_value_t = 64)]
    max_keyframes: usize,
    /// Mapper config (TOML, `MapperConfig` fields); defaults otherwise.
    #[arg(long = "mapper-config", alias = "config", value_name = "FILE")]
    config: Option<PathBuf>,
    /// Seed a Gaussian every this many pixels of confident keyframe depth (overrides the
    /// config's `init_stride_px`). Offshore the cap is large, so every pixel (1) by default;
    /// onboard the boards use 2. Not with --from-logged-map (the onboard map's config holds).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=64))]
    init_stride_px: u64,
    /// Where the mapper renders (as `duv run --mapper`).
    #[arg(long, value_enum, default_value_t = MapperDevice::Auto)]
    mapper: MapperDevice,
    /// GPU memory for the Vulkan mapper, MiB (every buffer is allocated from it once).
    #[arg(long, default_value_t = 2048)]
    gpu_mb: u32,
    /// The Vulkan mapper without float atomics (reductions in a fixed order): two runs on one
    /// device give bit-identical maps.
    #[arg(long)]
    deterministic: bool,
    /// Refine the keyframe poses photometrically against the map (`map::pose_refine`: each
    /// keyframe's image aligned to the map rendered from its pose) every
    /// --refine-poses-every iterations, the first keyframe held as the anchor.
    #[arg(long)]
    refine_poses: bool,
    /// Iterations between two pose refinement rounds (with --refine-poses); none in the last ones.
    #[arg(long, default_value_t = 100, value_parser = clap::value_parser!(u64).range(1..))]
    refine_poses_every: u64,
    /// Pose refinement settings (TOML, `PoseRefineConfig` fields); defaults otherwise.
    #[arg(long, value_name = "FILE", requires = "refine_poses")]
    pose_config: Option<PathBuf>,
    /// With --water: move every keyframe but the first off its true pose by this many metres
    /// (direction drawn per keyframe, reproducible), to measure what --refine-poses recovers.
    #[arg(long, value_name = "M", requires = "sim")]
    perturb_poses_m: Option<f64>,
    /// With --water: and turn it by this many degrees (axis drawn per keyframe).
    #[arg(long, value_name = "DEG", requires = "sim")]
    perturb_poses_deg: Option<f64>,
    /// No progress bar.
    #[arg(long, alias = "quiet")]
    no_progress: bool,
}

/// A reproducible unit vector per keyframe index and purpose (splitmix64).
fn unit_vector(index: u64, salt: u64) -> nalgebra::Vector3<f64> {
    let mut x = index.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ salt;
    let mut next = || {
        x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = x;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    loop {
        let v = nalgebra::Vector3::new(next(), next(), next());
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// Position (m) and rotation (deg) difference of two poses.
fn pose_difference(a: &duv_core::Se3, b: &duv_core::Se3) -> (f64, f64) {
    let d = a.inv_mul(b);
    ((a.translation.vector - b.translation.vector).norm(), duv_core::pose::rotation_angle(&d.rotation).to_degrees())
}

#[derive(serde::Serialize)]
struct KeyframeMetrics {
    index: u64,
    psnr_db: f64,
    ssim: f64,
    restored_psnr_db: Option<f64>,
    /// How far the final pose is from the input one (m, deg).
    pose_shift_m: f64,
    pose_shift_deg: f64,
    /// With --water: the final pose against the true one (m, deg).
    pose_error_m: Option<f64>,
    pose_error_deg: Option<f64>,
}

#[derive(serde::Serialize)]
struct Metrics {
    keyframes: Vec<KeyframeMetrics>,
    mean_psnr_db: f64,
    mean_ssim: f64,
    mean_restored_psnr_db: Option<f64>,
    medium: MediumParams,
    /// The newest closed-form estimate of the medium (`MapperConfig::estimate_medium_at_keyframes`, `refine_medium_estimate_until_keyframes`).
    medium_estimate: Option<duv_map::medium_estimate::MediumEstimate>,
    medium_truth: Option<MediumParams>,
    /// Relative error of each recovered coefficient, in the order beta_D, beta_B, B_inf (R G B each).
    medium_rel_error: Option<[[f64; 3]; 3]>,
    /// (iteration, Gaussians) every 1/20 of the run.
    gaussians_over_time: Vec<(u64, usize)>,
    /// What rendered (`Mapper::render_device`).
    renderer: String,
    ms_per_iteration: f64,
    iterations: u64,
    /// With --refine-poses: rounds run, corrections accepted, keyframes the map did not cover.
    pose_refinement: Option<PoseRefinementSummary>,
    /// With --water: mean keyframe pose error against the truth before and after (m, deg).
    pose_error_before: Option<(f64, f64)>,
    pose_error_after: Option<(f64, f64)>,
}

#[derive(serde::Serialize, Default)]
struct PoseRefinementSummary {
    rounds: u64,
    accepted: usize,
    refused: usize,
    failed: usize,
}

/// The keyframes of a log, with what was left out said on stderr, and its newest map checkpoint.
fn read_log(path: &std::path::Path) -> anyhow::Result<(Vec<Keyframe>, Option<LoggedMap>)> {
    let got = read_log_keyframes(path, ReadLimits::default())?;
    for d in &got.damage {
        eprintln!("log damaged, damaged ranges skipped: {d}");
    }
    for (index, why) in &got.skipped {
        eprintln!("keyframe {index} left out: {why}");
    }
    for (from, to) in &got.renumbered {
        eprintln!("keyframe {from} logged twice (a resumed run): the later one is keyframe {to}");
    }
    eprintln!("{}: {} keyframe(s) from {} segment(s)", path.display(), got.keyframes.len(), got.segments.len());
    Ok((got.keyframes, got.newest_map))
}

/// The onboard map from the log's newest checkpoint, its keyframes' pixels from `keyframes`.
fn mapper_from_logged_map(map: Option<LoggedMap>, keyframes: &[Keyframe], capacity: MapperCapacity) -> anyhow::Result<Mapper> {
    let map = map.context("--from-logged-map: the log holds no /map/checkpoint (the run mapped nothing, or the log was cut before the first checkpoint)")?;
    let what = format!("{} /map/checkpoint at {} ns", map.segment.display(), map.log_time_ns);
    if !map.bytes.starts_with(CHECKPOINT_MAGIC) {
        anyhow::bail!("{what}: not a mapper checkpoint (a run with --no-map logs only its keyframe poses there)");
    }
    let mapper = Mapper::from_checkpoint_bytes(&map.bytes, &what, RestoreOptions { keyframes, capacity: Some(capacity) })?;
    eprintln!("{what}: {} Gaussians, {} keyframes, iteration {}", mapper.gaussians().len(), mapper.keyframe_count(), mapper.iteration());
    Ok(mapper)
}

pub fn run(a: RefineArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.sim.is_some() || (a.perturb_poses_m.is_none() && a.perturb_poses_deg.is_none()), "--perturb-poses-m and --perturb-poses-deg need --water (they are measured against the true poses)");
    anyhow::ensure!(a.refine_poses || a.pose_config.is_none(), "--pose-config needs --refine-poses");
    let mut logged_map = None;
    let (mut keyframes, clear, truth): (Vec<Keyframe>, Vec<Option<ImageRgb8>>, Option<MediumParams>) = if let Some(water) = a.sim {
        let mut cfg = SimConfig::preset(water, a.trajectory);
        cfg.frames = a.frames;
        cfg.width = a.width;
        cfg.height = a.height;
        cfg.vignetting = a.vignetting;
        let r = SimRenderer::new(&cfg).context("building the generated sequence")?;
        let kfs = sim_keyframes(&r, a.every, a.max_keyframes);
        let truth = *r.medium();
        let (k, c) = kfs.into_iter().map(|s| (s.keyframe, Some(s.clear))).unzip();
        (k, c, Some(truth))
    } else {
        let k = match (&a.mcap, &a.keyframes) {
            (Some(log), _) => {
                let (k, map) = read_log(log)?;
                logged_map = map;
                k
            }
            (None, Some(dir)) => read_keyframe_folder(dir)?,
            (None, None) => anyhow::bail!("--keyframes, --mcap or --water is required"),
        };
        let n = k.len();
        let truth = match &a.medium_truth {
            Some(p) => {
                // The truth is per metre: the keyframes must be metric too (issue 40).
                let units = match (&a.mcap, &a.keyframes) {
                    (Some(_), _) => Err("the keyframes of a log are in the tracker's map units (metric.json applies to the run folder's outputs; use --keyframes RUN)".to_string()),
                    (None, Some(dir)) => match duv_pipeline::metric::MetricRecord::read(dir)? {
                        Some(m) if m.length_unit == "m" => Ok(()),
                        Some(m) => Err(format!("{} says the run is in map units: {}", dir.join("metric.json").display(), m.why_not_metric.unwrap_or_default())),
                        None => Err(format!("{} has no metric.json: its keyframes are taken to be in map units", dir.display())),
                    },
                    (None, None) => Ok(()),
                };
                match units {
                    Ok(()) => {}
                    Err(why) if a.allow_map_units => eprintln!("--medium-truth compared against map units (--allow-map-units): {why}"),
                    Err(why) => anyhow::bail!("--medium-truth is per metre, but {why}; run with navigation input for metric keyframes, or pass --allow-map-units"),
                }
                Some(serde_json::from_str(&duv_core::io::read_text(p)?).with_context(|| format!("{}", p.display()))?)
            }
            None => None,
        };
        (k, vec![None; n], truth)
    };
    anyhow::ensure!(!keyframes.is_empty(), "no keyframes");
    let (perturb_m, perturb_deg) = (a.perturb_poses_m.unwrap_or(0.0), a.perturb_poses_deg.unwrap_or(0.0));
    anyhow::ensure!(perturb_m.is_finite() && perturb_m >= 0.0 && perturb_deg.is_finite() && perturb_deg >= 0.0, "--perturb-poses-m and --perturb-poses-deg must be finite and >= 0");
    let true_poses: Option<Vec<duv_core::Se3>> = a.sim.map(|_| keyframes.iter().map(|k| k.world_from_cam).collect());
    for kf in keyframes.iter_mut().skip(1) {
        if perturb_m > 0.0 || perturb_deg > 0.0 {
            let t = unit_vector(kf.index, 1) * perturb_m;
            let r = nalgebra::UnitQuaternion::from_scaled_axis(unit_vector(kf.index, 2) * perturb_deg.to_radians());
            kf.world_from_cam = duv_core::Se3::from_parts(nalgebra::Translation3::from(kf.world_from_cam.translation.vector + t), r * kf.world_from_cam.rotation);
        }
    }
    let input_poses: Vec<(u64, duv_core::Se3)> = keyframes.iter().map(|k| (k.index, k.world_from_cam)).collect();
    let pose_config: PoseRefineConfig = match &a.pose_config {
        Some(p) => toml::from_str(&duv_core::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
        None => PoseRefineConfig::default(),
    };
    pose_config.validate().context("--pose-config")?;
    let mut config: MapperConfig = match &a.config {
        Some(p) => toml::from_str(&duv_core::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
        None => MapperConfig::default(),
    };
    config.init_stride_px = a.init_stride_px as usize;
    let cam = keyframes[0].camera;
    let capacity = MapperCapacity { max_gaussians: a.max_gaussians, max_keyframes: a.max_keyframes.max(keyframes.len()), width: cam.width, height: cam.height };
    let mut mapper = if a.from_logged_map { mapper_from_logged_map(logged_map, &keyframes, capacity)? } else { Mapper::new(config, capacity)? };
    let renderer = mapper.use_device(a.mapper, &GpuOptions { deterministic: a.deterministic, ..GpuOptions::with_budget_mb(a.gpu_mb) })?;
    if !a.no_progress {
        eprintln!("refine: rendering with {renderer}");
    }
    // A fresh map takes every keyframe; a restored one those it does not hold.
    let held: Vec<i64> = (0..mapper.keyframe_count()).filter_map(|s| mapper.keyframe(s).map(|k| k.t_ns.t_ns())).collect();
    let mut added = 0;
    for kf in keyframes.iter().filter(|k| !held.contains(&k.t_ns.t_ns())) {
        mapper.add_keyframe(kf.clone())?;
        added += 1;
    }
    if a.from_logged_map {
        eprintln!("{added} logged keyframe(s) the map checkpoint does not hold added");
    }
    std::fs::create_dir_all(a.out.join("renders")).with_context(|| format!("creating {}", a.out.display()))?;

    let bar = if a.no_progress { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(a.iterations) };
    if let Ok(style) = indicatif::ProgressStyle::with_template("refine [{elapsed_precise}] {wide_bar} {pos}/{len} it ({per_sec}, eta {eta}) {msg}") {
        bar.set_style(style);
    }
    let mut over_time = vec![(0, mapper.gaussians().len())];
    let mut pose_summary: Option<PoseRefinementSummary> = None;
    let (mut loss_avg, mut psnr_avg) = (0.0, 0.0);
    let start = std::time::Instant::now();
    for it in 1..=a.iterations {
        let r = mapper.iterate()?;
        loss_avg = if it == 1 { r.loss.total } else { 0.95 * loss_avg + 0.05 * r.loss.total };
        psnr_avg = if it == 1 { r.psnr_db } else { 0.95 * psnr_avg + 0.05 * r.psnr_db };
        if it % 10 == 0 {
            bar.set_message(format!("loss {loss_avg:.4} psnr {psnr_avg:.2} dB, {} Gaussians", r.gaussians));
        }
        if it % (a.iterations / 20).max(1) == 0 {
            over_time.push((it, r.gaussians));
        }
        // Not in the last round's iterations: the map follows the corrected poses first.
        if a.refine_poses && it % a.refine_poses_every == 0 && it + a.refine_poses_every <= a.iterations {
            let s = pose_summary.get_or_insert_with(PoseRefinementSummary::default);
            s.rounds += 1;
            let anchor = (0..mapper.keyframe_count()).filter_map(|k| mapper.keyframe(k).map(|kf| (kf.index, k))).min().map(|(_, k)| k);
            for slot in (0..mapper.keyframe_count()).filter(|&k| Some(k) != anchor) {
                let Some(index) = mapper.keyframe(slot).map(|k| k.index) else { continue };
                let Some(&(_, input_pose)) = input_poses.iter().find(|(i, _)| *i == index) else { continue };
                match mapper.refine_keyframe_pose(slot, &input_pose, &pose_config) {
                    Ok(c) if c.accepted => s.accepted += 1,
                    Ok(_) => s.refused += 1,
                    Err(e) => {
                        tracing::debug!(slot, error = %e, "refine: pose not refined");
                        s.failed += 1;
                    }
                }
            }
        }
        bar.inc(1);
    }
    bar.finish();
    let ms_per_iteration = start.elapsed().as_secs_f64() * 1e3 / a.iterations.max(1) as f64;

    mapper.sync_from_device()?;
    write_ply(&a.out.join("map.ply"), mapper.gaussians())?;
    mapper.save_checkpoint(&a.out.join("map.ckpt"))?;
    let medium = mapper.medium_summary(&keyframes[0].world_from_cam);
    write_atomic(&a.out.join("medium.json"), serde_json::to_string_pretty(&medium)?.as_bytes())?;

    let mut per_kf = Vec::new();
    let mut final_poses = Vec::new();
    for slot in 0..mapper.keyframe_count() {
        let kf = mapper.keyframe(slot).context("keyframe")?.clone();
        let clear_img = keyframes.iter().position(|k| k.index == kf.index).and_then(|i| clear[i].clone());
        mapper.render_keyframe(slot)?;
        let input = kf.image.to_rgb_f32();
        let mut restored = duv_core::ImageRgbF32::new(kf.camera.width, kf.camera.height);
        mapper.restore_last(&input, &kf.camera, &duv_map::restore::RestoreConfig::default(), &mut restored)?;
        let out = mapper.last_render();
        let p = psnr(&out.colour, &input)?;
        let s = ssim(&out.colour, &input, SsimConvention::Skimage)?;
        let restored_psnr = match &clear_img {
            Some(c) => Some(psnr(&restored, &c.to_rgb_f32())?),
            None => None,
        };
        let panel = render_panel(&kf.image, out, &restored);
        write_rgb8(&a.out.join("renders").join(format!("{:06}.png", kf.index)), &panel)?;
        let input_pose = input_poses.iter().find(|(i, _)| *i == kf.index).map_or(kf.world_from_cam, |p| p.1);
        let (pose_shift_m, pose_shift_deg) = pose_difference(&input_pose, &kf.world_from_cam);
        let truth_pose = true_poses.as_ref().and_then(|t| keyframes.iter().position(|k| k.index == kf.index).map(|i| t[i]));
        let err = truth_pose.map(|t| pose_difference(&t, &kf.world_from_cam));
        final_poses.push(duv_core::StampedPose { t_ns: kf.t_ns, world_from_cam: kf.world_from_cam });
        per_kf.push(KeyframeMetrics { index: kf.index, psnr_db: p, ssim: s, restored_psnr_db: restored_psnr, pose_shift_m, pose_shift_deg, pose_error_m: err.map(|e| e.0), pose_error_deg: err.map(|e| e.1) });
    }
    duv_core::io::tum::write_trajectory(&a.out.join("poses.txt"), &final_poses)?;
    let n = per_kf.len() as f64;
    let mean_error = |e: Vec<(f64, f64)>| (!e.is_empty()).then(|| (e.iter().map(|v| v.0).sum::<f64>() / e.len() as f64, e.iter().map(|v| v.1).sum::<f64>() / e.len() as f64));
    let pose_error_before = true_poses.as_ref().and_then(|t| mean_error(t.iter().zip(&input_poses).map(|(t, p)| pose_difference(t, &p.1)).collect()));
    let pose_error_after = mean_error(per_kf.iter().filter_map(|k| k.pose_error_m.zip(k.pose_error_deg)).collect());
    let restored: Vec<f64> = per_kf.iter().filter_map(|k| k.restored_psnr_db).collect();
    let rel = truth.map(|t| medium.rel_error(&t));
    let metrics = Metrics {
        mean_psnr_db: per_kf.iter().map(|k| k.psnr_db).sum::<f64>() / n,
        mean_ssim: per_kf.iter().map(|k| k.ssim).sum::<f64>() / n,
        mean_restored_psnr_db: if restored.is_empty() { None } else { Some(restored.iter().sum::<f64>() / restored.len() as f64) },
        keyframes: per_kf,
        medium,
        medium_estimate: mapper.medium_estimate().cloned(),
        medium_truth: truth,
        medium_rel_error: rel,
        gaussians_over_time: over_time,
        ms_per_iteration,
        iterations: a.iterations,
        renderer,
        pose_refinement: pose_summary,
        pose_error_before,
        pose_error_after,
    };
    write_atomic(&a.out.join("metrics.json"), serde_json::to_string_pretty(&metrics)?.as_bytes())?;

    println!("keyframe   PSNR dB   SSIM    restored PSNR dB");
    for k in &metrics.keyframes {
        let r = k.restored_psnr_db.map_or("-".to_string(), |v| format!("{v:.2}"));
        println!("{:8}  {:8.2}  {:6.4}  {r}", k.index, k.psnr_db, k.ssim);
    }
    println!("mean      {:8.2}  {:6.4}  {}", metrics.mean_psnr_db, metrics.mean_ssim, metrics.mean_restored_psnr_db.map_or("-".into(), |v| format!("{v:.2}")));
    let f = |v: [f64; 3]| format!("[{:.3} {:.3} {:.3}]", v[0], v[1], v[2]);
    if let Some(e) = &metrics.medium_estimate {
        let m = &e.medium;
        let d = &e.determined;
        println!(
            "estimate  beta_D {} beta_B {} B_inf {}  ({} depth blocks, {:?} view pairs; determined for R: {}, G: {}, B: {})",
            f(m.beta_d),
            f(m.beta_b),
            f(m.b_inf),
            e.samples,
            e.attenuation_pairs,
            d[0],
            d[1],
            d[2]
        );
    }
    println!("medium    beta_D {} beta_B {} B_inf {}", f(medium.beta_d), f(medium.beta_b), f(medium.b_inf));
    if let (Some(t), Some(e)) = (truth, rel) {
        println!("truth     beta_D {} beta_B {} B_inf {}", f(t.beta_d), f(t.beta_b), f(t.b_inf));
        println!("rel.err   beta_D {} beta_B {} B_inf {}", f(e[0]), f(e[1]), f(e[2]));
    }
    if let Some(p) = &metrics.pose_refinement {
        println!("poses     {} refinement round(s): {} corrections accepted, {} refused, {} keyframes not covered enough", p.rounds, p.accepted, p.refused, p.failed);
    }
    if let (Some(b), Some(f)) = (metrics.pose_error_before, metrics.pose_error_after) {
        println!("pose err  mean {:.4} m {:.3} deg before, {:.4} m {:.3} deg after", b.0, b.1, f.0, f.1);
    }
    println!("{} Gaussians, {:.1} ms per iteration, outputs in {}", mapper.gaussians().len(), ms_per_iteration, a.out.display());
    Ok(())
}
