//! `duv demo`: the first command a newcomer runs. Generates a short underwater sequence with
//! ground truth, reads it back through the dataset reader as any user dataset would be, runs
//! the pipeline on it (tracking and mapping), prints the metrics table and writes the outputs.

use anyhow::Context;
use duv_camera::dataset::open_dataset;
use duv_camera::FrameSource;
use duv_eval::image::{psnr, ssim, SsimConvention};
use duv_core::io::png_io::read_image;
use duv_sim::{write_sequence, SimConfig, TrajectoryKind, WaterPreset};
use std::fmt::Write as _;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct DemoArgs {
    /// Output folder: `sequence/` (the generated data), `run/` (tracking outputs and the eval
    /// report with figures) and `demo.md` (the water's cost).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Frames to generate (10 fps).
    #[arg(long, default_value_t = 100)]
    frames: usize,
    /// Water type of the generated sequence.
    #[arg(long, value_enum, default_value_t = WaterPreset::Coastal)]
    water: WaterPreset,
    /// Random seed of the scene and the sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Do not show progress bars.
    #[arg(long)]
    no_progress: bool,
}

pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    let seq_dir = args.out.join("sequence");
    if seq_dir.exists() {
        std::fs::remove_dir_all(&seq_dir).with_context(|| format!("clearing {}", seq_dir.display()))?;
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;

    // 1. Generate a coastal survey with exact ground truth.
    let mut cfg = SimConfig::preset(args.water, TrajectoryKind::Survey);
    cfg.frames = args.frames;
    cfg.seed = args.seed;
    eprintln!("[1/4] generating {} frames of {} water at {}x{}", cfg.frames, args.water, cfg.width, cfg.height);
    let sim = write_sequence(&cfg, &seq_dir, !args.no_progress).context("generating the demo sequence")?;

    // 2. Read it back through the dataset reader, decoding every frame, as `duv run` will.
    eprintln!("[2/4] reading {} back through the TUM reader", seq_dir.display());
    let spec = format!("tum:{}", seq_dir.display());
    let dataset = open_dataset(&spec).with_context(|| format!("opening {spec}"))?;
    let gt_poses = dataset.ground_truth.as_ref().map_or(0, |g| g.len());
    let medium = dataset.medium;
    let frame_paths: Vec<PathBuf> = dataset.frames.iter().map(|f| f.path.clone()).collect();
    let mut source = dataset.into_source();
    let mut decoded = 0usize;
    while let Some(frame) = source.next_frame()? {
        anyhow::ensure!(frame.image.width() == cfg.width && frame.image.height() == cfg.height, "frame {} has the wrong size", frame.seq);
        decoded += 1;
    }

    // 3. Track it: `duv run --source tum:SEQUENCE --out OUT/run`, which prints and writes the
    //    eval report (ATE, RPE, AUSE of the depth uncertainty) against the ground truth.
    eprintln!("[3/4] tracking and mapping the sequence (duv run --source {spec} --out {})", args.out.join("run").display());
    // A fresh run: a log left by an earlier demo would otherwise be resumed.
    let run_dir = args.out.join("run");
    if run_dir.exists() {
        std::fs::remove_dir_all(&run_dir).with_context(|| format!("clearing {}", run_dir.display()))?;
    }
    // With the map: the Gaussian map of the seabed and the water, as `duv run` makes it.
    let mut run_args = super::run::RunArgs::with_defaults(spec.clone(), run_dir.clone(), args.no_progress);
    run_args.no_map = false;
    run_args.map_final_iterations = 50;
    super::run::run(run_args).context("tracking and mapping the demo sequence")?;

    // 4. What the water costs: each captured frame against the same view without water. A
    //    restoration (the mapper's restored image) has to beat these numbers.
    eprintln!("[4/4] scoring captured frames against the water-free views");
    let (mut psnr_sum, mut ssim_sum) = (0.0, 0.0);
    for path in &frame_paths {
        let clear_path = seq_dir.join("clear").join(path.file_name().context("frame without a file name")?);
        let captured = read_image(path)?.to_rgb8().to_rgb_f32();
        let clear = read_image(&clear_path)?.to_rgb8().to_rgb_f32();
        psnr_sum += psnr(&captured, &clear)?;
        ssim_sum += ssim(&captured, &clear, SsimConvention::Skimage)?;
    }
    let n = frame_paths.len().max(1) as f64;

    let mut table = String::new();
    let _ = writeln!(table, "| metric | value |");
    let _ = writeln!(table, "|---|---|");
    let _ = writeln!(table, "| sequence | {} water, survey, {}x{}, seed {} |", args.water, cfg.width, cfg.height, cfg.seed);
    let _ = writeln!(table, "| frames generated / decoded / ground-truth poses | {} / {} / {} |", sim.frames, decoded, gt_poses);
    let _ = writeln!(table, "| generator speed | {:.1} frames/s |", sim.frames_per_sec);
    let _ = writeln!(table, "| camera path length | {:.2} m |", sim.path_length_m);
    if let Some(m) = medium {
        let _ = writeln!(
            table,
            "| water beta_D / beta_B / B_inf (R,G,B) | {:.2?} / {:.2?} / {:.3?} |",
            m.beta_d, m.beta_b, m.b_inf
        );
    }
    match duv_map::ply::read_ply(&run_dir.join("map.ply"), 1 << 22) {
        Ok(g) => {
            let _ = writeln!(table, "| map | {} Gaussians in {} (keyframe renders in {}) |", g.len(), run_dir.join("map.ply").display(), run_dir.join("renders").display());
        }
        Err(e) => {
            let _ = writeln!(table, "| map | not exported: {e} |");
        }
    }
    if let Ok(text) = std::fs::read_to_string(run_dir.join("medium.json")) {
        if let Ok(m) = serde_json::from_str::<serde_json::Value>(&text) {
            let f = |v: &serde_json::Value| v.as_array().map_or("?".to_string(), |a| format!("[{}]", a.iter().map(|x| format!("{:.2}", x.as_f64().unwrap_or(f64::NAN))).collect::<Vec<_>>().join(", ")));
            let _ = writeln!(table, "| water the map estimated (per map unit, not metres) beta_D / beta_B / B_inf | {} / {} / {} |", f(&m["beta_D"]), f(&m["beta_B"]), f(&m["B_inf"]));
        }
    }
    let _ = writeln!(table, "| captured vs water-free: mean PSNR | {:.2} dB |", psnr_sum / n);
    let _ = writeln!(table, "| captured vs water-free: mean SSIM | {:.3} |", ssim_sum / n);
    println!("{table}");
    let md = args.out.join("demo.md");
    std::fs::write(&md, format!("# duv demo\n\n{table}")).with_context(|| format!("writing {}", md.display()))?;
    println!("wrote {}, {} and {}", seq_dir.display(), args.out.join("run").display(), md.display());
    Ok(())
}
