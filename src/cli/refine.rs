//! `duv refine`: offshore map refinement from a keyframe folder (the layout is documented in
//! `duv::io::keyframes`), from the keyframes in a run's MCAP log (`--mcap`, read by
//! `duv::log::keyframes`: image, pose, inverse depth and variance of every logged keyframe, up
//! to any damage; `--from-logged-map` continues the onboard map from the log's newest map
//! checkpoint), or from generated keyframes with ground-truth poses and depth
//! (`--sim WATER`) so that mapping is evaluated without the tracker.
//!
//! Writes into `--out`: `map.ply` (3DGS PLY), `map.ckpt` (full mapper checkpoint),
//! `medium.json` (the medium along the first keyframe's optical axis, the generator's keys),
//! `renders/NNNNNN.png` (input | render | restored | depth | uncertainty) and `metrics.json`,
//! and prints the metrics table.

use std::path::PathBuf;

use anyhow::Context;
use duv::core::{ImageRgb8, Keyframe, MediumParams};
use duv::eval::image::{psnr, ssim, SsimConvention};
use duv::io::keyframes::read_keyframe_folder;
use duv::io::png_io::write_rgb8;
use duv::io::write_atomic;
use duv::log::{read_log_keyframes, LoggedMap, ReadLimits};
use duv::gpu::GpuOptions;
use duv::map::vulkan::MapperDevice;
use duv::map::checkpoint::{RestoreOptions, CHECKPOINT_MAGIC};
use duv::map::mapper::{Mapper, MapperCapacity, MapperConfig};
use duv::map::ply::write_ply;
use duv::map::stage::render_panel;
use duv::sim::keyframes::sim_keyframes;
use duv::sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};

#[derive(clap::Args)]
pub struct RefineArgs {
    /// Keyframe folder written by the tracker (calibration.txt, keyframes.txt, keyframes/), e.g.
    /// the output folder of `duv run`.
    #[arg(long, value_name = "DIR", conflicts_with = "sim", required_unless_present_any = ["sim", "mcap"])]
    keyframes: Option<PathBuf>,
    /// Instead of a keyframe folder: a run's MCAP log (`RUN/log`, `RUN`, or one segment
    /// `.mcap`). Every keyframe logged with its image, pose, inverse depth and variance is
    /// refined; a damaged log is read up to the damage. The poses are those logged as each
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
    /// (with --keyframes or --mcap; --sim knows its own).
    #[arg(long, value_name = "FILE")]
    medium_truth: Option<PathBuf>,
    /// Instead of a folder: generated keyframes with ground-truth poses and depth in this water.
    #[arg(long, value_enum)]
    sim: Option<WaterPreset>,
    /// Generated path (with --sim).
    #[arg(long, value_enum, default_value_t = TrajectoryKind::Survey)]
    trajectory: TrajectoryKind,
    /// Generated frames (with --sim); every --every-th becomes a keyframe.
    #[arg(long, default_value_t = 40)]
    frames: usize,
    /// Keyframe spacing in generated frames (with --sim).
    #[arg(long, default_value_t = 5)]
    every: usize,
    /// Generated image width and height (with --sim).
    #[arg(long, default_value_t = 320)]
    width: usize,
    #[arg(long, default_value_t = 240)]
    height: usize,
    /// Vignetting strength of the generated images (with --sim). The mapper has no vignetting
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
    #[arg(long)]
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
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

#[derive(serde::Serialize)]
struct KeyframeMetrics {
    index: u64,
    psnr_db: f64,
    ssim: f64,
    restored_psnr_db: Option<f64>,
}

#[derive(serde::Serialize)]
struct Metrics {
    keyframes: Vec<KeyframeMetrics>,
    mean_psnr_db: f64,
    mean_ssim: f64,
    mean_restored_psnr_db: Option<f64>,
    medium: MediumParams,
    /// The closed-form estimate the optimisation started from (`MapperConfig::estimate_medium_at_keyframes`).
    medium_estimate: Option<duv::map::medium_estimate::MediumEstimate>,
    medium_truth: Option<MediumParams>,
    /// Relative error of each recovered coefficient, in the order beta_D, beta_B, B_inf (R G B each).
    medium_rel_error: Option<[[f64; 3]; 3]>,
    /// (iteration, Gaussians) every 1/20 of the run.
    gaussians_over_time: Vec<(u64, usize)>,
    /// What rendered (`Mapper::render_device`).
    renderer: String,
    ms_per_iteration: f64,
    iterations: u64,
}

/// The keyframes of a log, with what was left out said on stderr, and its newest map checkpoint.
fn read_log(path: &std::path::Path) -> anyhow::Result<(Vec<Keyframe>, Option<LoggedMap>)> {
    let got = read_log_keyframes(path, ReadLimits::default())?;
    for d in &got.damage {
        eprintln!("log damaged, read up to the damage: {d}");
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
    let mut logged_map = None;
    let (keyframes, clear, truth): (Vec<Keyframe>, Vec<Option<ImageRgb8>>, Option<MediumParams>) = if let Some(water) = a.sim {
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
            (None, None) => anyhow::bail!("--keyframes, --mcap or --sim is required"),
        };
        let n = k.len();
        let truth = match &a.medium_truth {
            Some(p) => Some(serde_json::from_str(&duv::io::read_text(p)?).with_context(|| format!("{}", p.display()))?),
            None => None,
        };
        (k, vec![None; n], truth)
    };
    anyhow::ensure!(!keyframes.is_empty(), "no keyframes");
    let mut config: MapperConfig = match &a.config {
        Some(p) => toml::from_str(&duv::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
        None => MapperConfig::default(),
    };
    config.init_stride_px = a.init_stride_px as usize;
    let cam = keyframes[0].camera;
    let capacity = MapperCapacity { max_gaussians: a.max_gaussians, max_keyframes: a.max_keyframes.max(keyframes.len()), width: cam.width, height: cam.height };
    let mut mapper = if a.from_logged_map { mapper_from_logged_map(logged_map, &keyframes, capacity)? } else { Mapper::new(config, capacity)? };
    let renderer = mapper.use_device(a.mapper, &GpuOptions { deterministic: a.deterministic, ..GpuOptions::with_budget_mb(a.gpu_mb) })?;
    if !a.quiet {
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

    let bar = if a.quiet { indicatif::ProgressBar::hidden() } else { indicatif::ProgressBar::new(a.iterations) };
    if let Ok(style) = indicatif::ProgressStyle::with_template("refine [{elapsed_precise}] {wide_bar} {pos}/{len} it ({per_sec}, eta {eta}) {msg}") {
        bar.set_style(style);
    }
    let mut over_time = vec![(0, mapper.gaussians().len())];
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
        bar.inc(1);
    }
    bar.finish();
    let ms_per_iteration = start.elapsed().as_secs_f64() * 1e3 / a.iterations.max(1) as f64;

    write_ply(&a.out.join("map.ply"), mapper.gaussians())?;
    mapper.save_checkpoint(&a.out.join("map.ckpt"))?;
    let medium = mapper.medium_summary(&keyframes[0].world_from_cam);
    write_atomic(&a.out.join("medium.json"), serde_json::to_string_pretty(&medium)?.as_bytes())?;

    let mut per_kf = Vec::new();
    for slot in 0..mapper.keyframe_count() {
        let kf = mapper.keyframe(slot).context("keyframe")?.clone();
        let clear_img = keyframes.iter().position(|k| k.index == kf.index).and_then(|i| clear[i].clone());
        let out = mapper.render_keyframe(slot)?;
        let input = kf.image.to_rgb_f32();
        let p = psnr(&out.colour, &input)?;
        let s = ssim(&out.colour, &input, SsimConvention::Skimage)?;
        let restored_psnr = match &clear_img {
            Some(c) => Some(psnr(&out.restored, &c.to_rgb_f32())?),
            None => None,
        };
        let panel = render_panel(&kf.image, out);
        write_rgb8(&a.out.join("renders").join(format!("{:06}.png", kf.index)), &panel)?;
        per_kf.push(KeyframeMetrics { index: kf.index, psnr_db: p, ssim: s, restored_psnr_db: restored_psnr });
    }
    let n = per_kf.len() as f64;
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
        let yes = |a: bool| if a { "yes" } else { "no" };
        println!(
            "estimate  beta_D {} beta_B {} B_inf {}  ({} depth blocks, {:?} view pairs; used for R G B: {} {} {})",
            f(m.beta_d),
            f(m.beta_b),
            f(m.b_inf),
            e.samples,
            e.attenuation_pairs,
            yes(e.accepted[0]),
            yes(e.accepted[1]),
            yes(e.accepted[2])
        );
    }
    println!("medium    beta_D {} beta_B {} B_inf {}", f(medium.beta_d), f(medium.beta_b), f(medium.b_inf));
    if let (Some(t), Some(e)) = (truth, rel) {
        println!("truth     beta_D {} beta_B {} B_inf {}", f(t.beta_d), f(t.beta_b), f(t.b_inf));
        println!("rel.err   beta_D {} beta_B {} B_inf {}", f(e[0]), f(e[1]), f(e[2]));
    }
    println!("{} Gaussians, {:.1} ms per iteration, outputs in {}", mapper.gaussians().len(), ms_per_iteration, a.out.display());
    Ok(())
}
