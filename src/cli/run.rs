//! `duv run`: track a frame source (a dataset folder or a generated `sim:` sequence), map it,
//! write the trajectory, the keyframe folder (`duv::io::keyframes` layout: calibration, poses,
//! images, full-resolution inverse depth and variance, so `duv refine --keyframes OUT` reads a
//! finished run), the map exports, and, where ground truth exists, the evaluation report (ATE
//! with Sim(3) alignment, AUSE of the depth uncertainty).
//!
//! Mapping runs on the main thread between frames (the threaded pipeline drives the same
//! [`MappingStage`] from its mapping thread): a keyframe goes to the mapper once `ba_window`
//! newer keyframes exist and it has a depth covariance (its depth and pose have been through
//! the window BA by then), or when it is evicted, or at the end of the run; each keyframe buys `--map-iterations` iterations.
//! At the end the mapper takes the final keyframe poses, runs `--map-final-iterations` more and
//! exports `map.ply`, `map.ckpt`, `medium.json` and `renders/`.

use anyhow::Context;
use duv::camera::dataset::{open_dataset, Dataset, DATASET_KINDS};
use duv::camera::{open_source, FrameSource};
use duv::config::board::Board;
use duv::core::pose::se3_to_tum;
use duv::core::{Frame, FrameImage, ImageRgb8, Keyframe, PinholeCamera, PlaneF32, StampedPose, Timestamp};
use duv::eval::report::AuseInput;
use duv::eval::{build_report, write_report, EvalInputs, EvalOptions};
use duv::io::pfm::write_pfm;
use duv::io::png_io::write_rgb8;
use duv::map::mapper::{MapperCapacity, MapperConfig};
use duv::map::stage::{MappingBudget, MappingStage};
use duv::sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use duv::track::{KeyframeView, TrackOutput, Tracker, TrackerCapacity, TrackerConfig, TrackingState, TrajectoryRecorder};
use std::collections::VecDeque;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(clap::Args)]
pub struct RunArgs {
    /// Frame source: `tum:DIR`, `euroc:DIR`, `tartanair:DIR`, `folder:DIR` (dataset options as
    /// in `duv dataset`), `sim:WATER[-TRAJECTORY]` generated in memory, e.g. `sim:coastal`,
    /// `sim:turbid-loop` (water: clear, coastal, turbid; trajectory: survey, loop, hover), or a
    /// live camera `v4l2:/dev/video0,calib=FILE`, `aravis:ID,calib=FILE` (board settings).
    #[arg(long)]
    source: String,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Board profile: capacities (keyframes, BA window), threads, and the sim image size.
    #[arg(long, default_value = "boards/sim.toml")]
    board: PathBuf,
    /// Track at most this many frames (a `sim:` source generates this many).
    #[arg(long)]
    frames: Option<usize>,
    /// Disable loop closure (and with it the pose graph and the global BA after loops).
    #[arg(long)]
    no_loop_closure: bool,
    /// Tracker parameters (TOML, `TrackerConfig` fields); defaults otherwise.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Image width of a `sim:` source [default: the board's camera width].
    #[arg(long)]
    width: Option<usize>,
    /// Image height of a `sim:` source [default: the board's camera height].
    #[arg(long)]
    height: Option<usize>,
    /// Seed of a `sim:` source.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// No progress line on stderr.
    #[arg(long)]
    no_progress: bool,
    /// Track only: no map, no map exports.
    #[arg(long)]
    no_map: bool,
    /// Mapper iterations after each keyframe handed to mapping.
    #[arg(long, default_value_t = MappingBudget::default().iterations_per_keyframe)]
    map_iterations: u64,
    /// Mapper iterations after the last frame, on the final keyframe poses.
    #[arg(long, default_value_t = 100)]
    map_final_iterations: u64,
    /// Mapper parameters (TOML, `MapperConfig` fields); defaults otherwise.
    #[arg(long, value_name = "FILE")]
    map_config: Option<PathBuf>,
}

/// Where frames come from, with what ground truth.
enum Source {
    Sim { renderer: Box<SimRenderer>, next: usize, count: usize },
    Dataset { dataset: Box<Dataset>, next: usize, count: usize, undistort: Option<(duv::core::camera::UndistortMap, ImageRgb8)> },
    /// Live cameras (`v4l2:`, `aravis:`) and every other kind `camera::open_source` knows.
    Live { source: Box<dyn FrameSource>, next: usize, count: usize },
}

/// `WATER[-TRAJECTORY]` of a `sim:` spec.
fn parse_sim_preset(spec: &str) -> anyhow::Result<(WaterPreset, TrajectoryKind)> {
    let mut parts = spec.splitn(2, '-');
    let water = match parts.next().unwrap_or("") {
        "clear" => WaterPreset::Clear,
        "coastal" => WaterPreset::Coastal,
        "turbid" => WaterPreset::Turbid,
        w => anyhow::bail!("sim:{spec}: unknown water {w:?} (expected clear, coastal or turbid)"),
    };
    let trajectory = match parts.next() {
        None | Some("survey") => TrajectoryKind::Survey,
        Some("loop") => TrajectoryKind::Loop,
        Some("hover") => TrajectoryKind::Hover,
        Some(t) => anyhow::bail!("sim:{spec}: unknown trajectory {t:?} (expected survey, loop or hover)"),
    };
    Ok((water, trajectory))
}

impl Source {
    fn open(args: &RunArgs, board: &Board) -> anyhow::Result<Source> {
        if let Some(preset) = args.source.strip_prefix("sim:") {
            let (water, trajectory) = parse_sim_preset(preset)?;
            let mut cfg = SimConfig::preset(water, trajectory);
            cfg.width = args.width.unwrap_or(board.camera.width as usize);
            cfg.height = args.height.unwrap_or(board.camera.height as usize);
            if let Some(n) = args.frames {
                cfg.frames = n;
            }
            cfg.seed = args.seed;
            let renderer = SimRenderer::new(&cfg).with_context(|| format!("source {}", args.source))?;
            let count = renderer.len();
            return Ok(Source::Sim { renderer: Box::new(renderer), next: 0, count });
        }
        anyhow::ensure!(args.width.is_none() && args.height.is_none(), "--width/--height apply to sim: sources only");
        if !DATASET_KINDS.split(", ").any(|k| args.source.split(':').next() == Some(k)) {
            let source = open_source(&args.source, board)?;
            return Ok(Source::Live { source, next: 0, count: args.frames.unwrap_or(usize::MAX) });
        }
        let dataset = open_dataset(&args.source)?;
        let count = args.frames.unwrap_or(usize::MAX).min(dataset.frames.len());
        let undistort = dataset.camera.distortion.is_some().then(|| {
            let map = dataset.camera.undistort_map();
            let buf = ImageRgb8::new(dataset.camera.width, dataset.camera.height);
            (map, buf)
        });
        Ok(Source::Dataset { dataset: Box::new(dataset), next: 0, count, undistort })
    }

    /// Camera of the frames handed to the tracker (undistorted).
    fn camera(&self) -> PinholeCamera {
        match self {
            Source::Sim { renderer, .. } => *renderer.camera(),
            Source::Dataset { dataset, .. } => dataset.camera.undistorted(),
            Source::Live { source, .. } => *source.camera(),
        }
    }

    fn len(&self) -> usize {
        match self {
            Source::Sim { count, .. } | Source::Dataset { count, .. } | Source::Live { count, .. } => *count,
        }
    }

    /// The next frame; `Ok(None)` at the end. A dataset frame that cannot be decoded is
    /// reported and skipped.
    fn next(&mut self) -> anyhow::Result<Option<Frame>> {
        match self {
            Source::Sim { renderer, next, count } => {
                if *next >= *count {
                    return Ok(None);
                }
                let f = renderer.render(*next);
                let frame = Frame { t_ns: f.t_ns, seq: *next as u64, image: FrameImage::Rgb8(f.rgb) };
                *next += 1;
                Ok(Some(frame))
            }
            Source::Dataset { dataset, next, count, undistort } => loop {
                if *next >= *count {
                    return Ok(None);
                }
                let i = *next;
                *next += 1;
                match dataset.load_frame(i) {
                    Ok(mut frame) => {
                        if let Some((map, buf)) = undistort {
                            let rgb = frame.image.to_rgb8();
                            map.apply_rgb8(&rgb, buf);
                            frame.image = FrameImage::Rgb8(buf.clone());
                        }
                        return Ok(Some(frame));
                    }
                    Err(e) => tracing::warn!("skipping a frame: {e}"),
                }
            },
            Source::Live { source, next, count } => {
                if *next >= *count {
                    return Ok(None);
                }
                *next += 1;
                Ok(source.next_frame()?)
            }
        }
    }

    fn ground_truth(&self) -> Option<Vec<StampedPose>> {
        match self {
            Source::Sim { renderer, count, .. } => Some(renderer.poses()[..*count].to_vec()),
            Source::Dataset { dataset, .. } => dataset.ground_truth.clone(),
            Source::Live { source, .. } => source.ground_truth().map(<[_]>::to_vec),
        }
    }

    /// Ground-truth depth (metres, 0 = none) of frame `seq`, where the source has it.
    fn depth(&self, seq: u64) -> Option<PlaneF32> {
        match self {
            Source::Sim { renderer, .. } => Some(renderer.render(seq as usize).depth_m),
            Source::Dataset { dataset, .. } => dataset.load_depth_for_frame(seq as usize).ok().flatten(),
            Source::Live { .. } => None,
        }
    }

    fn describe(&self) -> String {
        match self {
            Source::Sim { renderer, count, .. } => {
                let c = renderer.config();
                format!("sim {:?} water, {:?} path, {count} frames {}x{}", c.water, c.trajectory, c.width, c.height)
            }
            Source::Dataset { dataset, .. } => dataset.describe(),
            Source::Live { source, .. } => source.describe(),
        }
    }
}

/// Writes a keyframe's upsampled inverse depth and variance as PFM.
fn write_keyframe_maps(tracker: &Tracker, id: u64, dir: &Path, inv: &mut PlaneF32, var: &mut PlaneF32) -> anyhow::Result<()> {
    tracker.upsample_keyframe(id, inv, var)?;
    write_pfm(&dir.join(format!("{id:06}_invdepth.pfm")), inv)?;
    write_pfm(&dir.join(format!("{id:06}_variance.pfm")), var)?;
    Ok(())
}

/// A keyframe waiting to be handed to mapping: its image (the tracker keeps none).
struct PendingKeyframe {
    id: u64,
    t_ns: Timestamp,
    image: ImageRgb8,
}

/// The mapping side of `duv run`: the stage and the keyframes not yet handed over.
struct RunMapper {
    stage: MappingStage,
    pending: VecDeque<PendingKeyframe>,
    /// Keyframes handed over once this many newer ones exist.
    lag: usize,
    camera: PinholeCamera,
    fed: usize,
    time: Duration,
}

impl RunMapper {
    /// Hands keyframe `p` to mapping with the tracker's current pose and upsampled depth, if
    /// the tracker still knows it (a pruned keyframe is dropped).
    fn feed(&mut self, tracker: &Tracker, p: PendingKeyframe, pose: Option<duv::core::Se3>) -> anyhow::Result<()> {
        let live = tracker.keyframes().find(|k| k.id == p.id).map(|k| k.world_from_cam);
        let Some(world_from_cam) = pose.or(live) else { return Ok(()) };
        let mut inv_depth = PlaneF32::new(self.camera.width, self.camera.height);
        let mut inv_depth_variance = PlaneF32::new(self.camera.width, self.camera.height);
        tracker.upsample_keyframe(p.id, &mut inv_depth, &mut inv_depth_variance)?;
        let kf = Keyframe { index: p.id, t_ns: p.t_ns, image: p.image, world_from_cam, camera: self.camera, inv_depth, inv_depth_variance };
        let t0 = Instant::now();
        let step = self.stage.on_keyframe(kf).with_context(|| format!("mapping keyframe {}", p.id))?;
        self.time += t0.elapsed();
        self.fed += 1;
        tracing::debug!(keyframe = p.id, added = step.added, iterations = step.iterations, "map.keyframe");
        Ok(())
    }
}

fn tum_line(t_ns: duv::core::Timestamp, pose: &duv::core::Se3) -> String {
    let v = se3_to_tum(pose);
    format!("{:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}", t_ns.as_secs_f64(), v[0], v[1], v[2], v[3], v[4], v[5], v[6])
}

fn percentile_ms(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let board = Board::load(&args.board)?;
    let capacity = TrackerCapacity::from_board(&board);
    let mut cfg = match &args.config {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            toml::from_str::<TrackerConfig>(&text).with_context(|| format!("{}", p.display()))?
        }
        None => TrackerConfig::default(),
    };
    if args.no_loop_closure {
        cfg.loop_closure = false;
    }
    let mut source = Source::open(&args, &board)?;
    let camera = source.camera();
    let mut tracker = Tracker::new(&camera, &cfg, capacity)?;
    let kf_dir = args.out.join("keyframes");
    std::fs::create_dir_all(&kf_dir).with_context(|| format!("creating {}", kf_dir.display()))?;
    let c = camera;
    duv::io::write_atomic(&args.out.join("calibration.txt"), format!("{} {} {} {} {} {}\n", c.fx, c.fy, c.cx, c.cy, c.width, c.height).as_bytes())?;
    let mut mapping = if args.no_map {
        None
    } else {
        let map_config: MapperConfig = match &args.map_config {
            Some(p) => toml::from_str(&duv::io::read_text(p)?).with_context(|| format!("{}", p.display()))?,
            None => MapperConfig::default(),
        };
        let budget = MappingBudget { iterations_per_keyframe: args.map_iterations, ..MappingBudget::default() };
        let stage = MappingStage::new(map_config, MapperCapacity::from_board(&board, camera.width, camera.height), budget)?;
        let lag = capacity.ba_window.max(1);
        Some(RunMapper { stage, pending: VecDeque::with_capacity(capacity.max_keyframes + 1), lag, camera, fed: 0, time: Duration::ZERO })
    };
    let grid = tracker.depth_camera();
    eprintln!(
        "duv run: {} -> {} (depth grid {}x{}, 1/{}; {} keyframes, BA window {}, {} threads)",
        source.describe(),
        args.out.display(),
        grid.width,
        grid.height,
        tracker.depth_factor(),
        capacity.max_keyframes,
        capacity.ba_window,
        capacity.threads
    );

    let total = source.len();
    let mut recorder = TrajectoryRecorder::new();
    let mut latencies: Vec<Duration> = Vec::with_capacity(total.min(1 << 20));
    let mut inv = PlaneF32::new(camera.width, camera.height);
    let mut var = PlaneF32::new(camera.width, camera.height);
    let mut last_state: Option<TrackingState> = None;
    let mut frames_done = 0usize;
    let progress_every = Duration::from_millis(500);
    let mut last_progress = Instant::now();
    let mut track_time = Duration::ZERO;
    while let Some(frame) = source.next()? {
        let t0 = Instant::now();
        let out: TrackOutput = tracker.track(&frame)?;
        let dt = t0.elapsed();
        track_time += dt;
        latencies.push(dt);
        recorder.record(&out);
        frames_done += 1;
        if let Some(id) = out.new_keyframe {
            let image = frame.image.to_rgb8();
            write_rgb8(&kf_dir.join(format!("{id:06}.png")), &image)?;
            if let Some(m) = mapping.as_mut() {
                m.pending.push_back(PendingKeyframe { id, t_ns: frame.t_ns, image });
            }
        }
        if out.evicted.is_some() {
            if let Some(ev) = tracker.evicted_keyframe() {
                write_keyframe_maps(&tracker, ev.id, &kf_dir, &mut inv, &mut var)?;
                if let Some(m) = mapping.as_mut() {
                    if let Some(i) = m.pending.iter().position(|p| p.id == ev.id) {
                        if let Some(p) = m.pending.remove(i) {
                            let pose = ev.world_from_cam;
                            m.feed(&tracker, p, Some(pose))?;
                        }
                    }
                }
            }
        }
        if let Some(m) = mapping.as_mut() {
            // The oldest pending keyframe goes once it has a depth covariance (before the
            // tracker's initialisation it has none, and the mapper would seed nothing from it).
            while m.pending.len() > m.lag {
                let ready = m.pending.front().is_some_and(|p| tracker.keyframes().find(|k| k.id == p.id).is_none_or(|k| k.variance.is_some()));
                if !ready {
                    break;
                }
                if let Some(p) = m.pending.pop_front() {
                    m.feed(&tracker, p, None)?;
                }
            }
        }
        if last_state != Some(out.state) {
            eprintln!("\rframe {:>6}: {}{:30}", out.seq, out.state.name(), "");
            last_state = Some(out.state);
        }
        if out.loop_closed {
            eprintln!("\rframe {:>6}: loop closed{:30}", out.seq, "");
        }
        if !args.no_progress && (last_progress.elapsed() >= progress_every || frames_done == total) {
            last_progress = Instant::now();
            let fps = frames_done as f64 / track_time.as_secs_f64().max(1e-9);
            eprint!("\rframe {frames_done}/{total}  keyframes {}  {:.1} frames/s  {}   ", tracker.num_keyframes(), fps, out.state.name());
        }
    }
    if !args.no_progress {
        eprintln!();
    }
    anyhow::ensure!(frames_done > 0, "the source delivered no frame");

    // Final trajectory and keyframes.
    let fin = recorder.finish(&tracker);
    duv::io::tum::write_trajectory(&args.out.join("trajectory.txt"), &fin.frames)?;
    let mut kf_text = String::from("# keyframe_id timestamp tx ty tz qx qy qz qw\n");
    for k in &fin.keyframes {
        let _ = writeln!(kf_text, "{} {}", k.id, tum_line(k.t_ns, &k.world_from_cam));
    }
    duv::io::write_atomic(&args.out.join("keyframes.txt"), kf_text.as_bytes())?;
    let live: Vec<(u64, u64)> = tracker.keyframes().map(|k: KeyframeView| (k.id, k.seq)).collect();
    for &(id, _) in &live {
        write_keyframe_maps(&tracker, id, &kf_dir, &mut inv, &mut var)?;
    }
    if let Some(m) = mapping.as_mut() {
        while let Some(p) = m.pending.pop_front() {
            m.feed(&tracker, p, None)?;
        }
        // Final poses (after loop closures and global BA), then the final optimisation.
        for k in &fin.keyframes {
            m.stage.set_keyframe_pose(k.id, k.world_from_cam)?;
        }
        let t0 = Instant::now();
        if m.fed > 0 {
            m.stage.optimise(args.map_final_iterations, None)?;
        }
        m.time += t0.elapsed();
        let iterations = m.stage.mapper().iteration();
        if m.fed > 0 {
            m.stage.export(&args.out).with_context(|| format!("exporting the map to {}", args.out.display()))?;
        }
        let medium = m.stage.medium_summary();
        println!(
            "mapped {} keyframes: {} iterations in {:.2} s ({:.1} ms per iteration), {} Gaussians (cap {})",
            m.fed,
            iterations,
            m.time.as_secs_f64(),
            m.time.as_secs_f64() * 1e3 / iterations.max(1) as f64,
            m.stage.mapper().gaussians().len(),
            m.stage.mapper().capacity().max_gaussians
        );
        let f = |v: [f64; 3]| format!("[{:.3} {:.3} {:.3}]", v[0], v[1], v[2]);
        println!("medium along the last keyframe's axis: beta_D {} beta_B {} B_inf {}", f(medium.beta_d), f(medium.beta_b), f(medium.b_inf));
    }
    let mut states_text = String::from("# seq timestamp state tracker_ms\n");
    for ((f, s), dt) in recorder.frames().iter().zip(&fin.states).zip(&latencies) {
        let _ = writeln!(states_text, "{} {:.9} {} {:.3}", f.seq, f.t_ns.as_secs_f64(), s.name().replace(' ', "_"), dt.as_secs_f64() * 1e3);
    }
    duv::io::write_atomic(&args.out.join("states.txt"), states_text.as_bytes())?;

    // Timing.
    let times = tracker.times();
    let counters = tracker.counters();
    let n = frames_done as f64;
    let mut latencies_sorted = latencies.clone();
    latencies_sorted.sort();
    let secs = track_time.as_secs_f64();
    println!(
        "tracked {frames_done} frames in {secs:.2} s: {:.1} frames/s (tracker only), latency median {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        n / secs.max(1e-9),
        percentile_ms(&latencies_sorted, 0.5),
        percentile_ms(&latencies_sorted, 0.99),
        percentile_ms(&latencies_sorted, 1.0)
    );
    println!(
        "per frame: flow {:.2} ms, BA {:.2} ms, covariance {:.2} ms, loop closure {:.2} ms ({} flow estimates)",
        times.flow.as_secs_f64() * 1e3 / n,
        times.ba.as_secs_f64() * 1e3 / n,
        times.covariance.as_secs_f64() * 1e3 / n,
        times.loop_closure.as_secs_f64() * 1e3 / n,
        times.flow_estimates
    );
    println!(
        "keyframes: {} inserted, {} pruned, {} evicted, {} live; loops closed {}; global BAs {}; lost frames {}; relocalisations {}",
        counters.keyframes_inserted,
        counters.keyframes_pruned,
        counters.keyframes_evicted,
        live.len(),
        counters.loops_closed,
        counters.global_bas,
        counters.lost_frames,
        counters.relocalisations
    );

    // Evaluation against ground truth.
    if let Some(gt) = source.ground_truth() {
        let options = EvalOptions::default();
        let gt_name = format!("{} ground truth", args.source);
        let est_name = args.out.join("trajectory.txt").display().to_string();
        let base = EvalInputs { gt_name, est_name, gt: &gt, est: &fin.frames, images: &[], images_source: None, ause: &[], ause_source: None, options };
        let first = build_report(&base)?;
        let scale = first.report.trajectory.alignment.scale;
        let mut ause: Vec<AuseInput> = Vec::new();
        for &(id, seq) in &live {
            let Some(depth) = source.depth(seq) else { continue };
            tracker.upsample_keyframe(id, &mut inv, &mut var)?;
            let (mut errors, mut uncertainties) = (Vec::new(), Vec::new());
            for ((&z, &d), &v) in depth.data.iter().zip(&inv.data).zip(&var.data) {
                if z > 0.0 && d.is_finite() && v.is_finite() && v < f32::MAX {
                    errors.push((1.0 / z as f64 - d as f64 / scale).abs());
                    uncertainties.push(v as f64 / (scale * scale));
                }
            }
            if errors.len() >= 100 {
                ause.push(AuseInput { name: format!("keyframe {id:06}"), errors, uncertainties });
            }
        }
        let evaluation = if ause.is_empty() {
            first
        } else {
            build_report(&EvalInputs { ause: &ause, ause_source: Some("keyframe inverse depth vs ground truth, variance as uncertainty".into()), ..base })?
        };
        let eval_dir = args.out.join("eval");
        write_report(&evaluation, &eval_dir).with_context(|| format!("writing the report to {}", eval_dir.display()))?;
        print!("{}", evaluation.report.metrics_table());
        println!("wrote {}", eval_dir.display());
    }
    Ok(())
}

impl RunArgs {
    /// The arguments `duv run --source SOURCE --out OUT --no-map` would get, everything else
    /// default (used by `duv demo`, which scores tracking; mapping is `duv refine`'s there).
    pub fn with_defaults(source: String, out: PathBuf, no_progress: bool) -> Self {
        RunArgs {
            source,
            out,
            board: PathBuf::from("boards/sim.toml"),
            frames: None,
            no_loop_closure: false,
            config: None,
            width: None,
            height: None,
            seed: 1,
            no_progress,
            no_map: true,
            map_iterations: MappingBudget::default().iterations_per_keyframe,
            map_final_iterations: 100,
            map_config: None,
        }
    }
}
