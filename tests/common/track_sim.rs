//! Runs the tracker over a sequence generated in memory and scores it: shared by
//! `tests/algorithms/tracker.rs`, `tests/tracker_alloc.rs` and `examples/track_sim.rs`.
#![allow(dead_code)]

use duv_core::{Frame, FrameImage, StampedPose};
use duv_eval::trajectory::{evaluate_trajectory, TrajectoryOptions};
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use duv_track::{FinalTrajectory, TrackOutput, Tracker, TrackerCapacity, TrackerConfig, TrajectoryRecorder};

/// A CI-sized sequence: `frames` frames of `width x height` at 10 fps.
pub fn sim_config(water: WaterPreset, trajectory: TrajectoryKind, frames: usize, width: usize, height: usize, speed_mps: f64) -> SimConfig {
    let mut cfg = SimConfig::preset(water, trajectory);
    cfg.frames = frames;
    cfg.width = width;
    cfg.height = height;
    cfg.speed_mps = speed_mps;
    cfg
}

/// Tracker parameters for small test images: the defaults (the automatic depth factor gives
/// a grid of 1/4, 40x30 at 160x120).
pub fn small_tracker_config() -> TrackerConfig {
    TrackerConfig::default()
}

pub fn capacity(threads: usize) -> TrackerCapacity {
    TrackerCapacity { max_keyframes: 64, ba_window: 8, threads }
}

/// Every frame of a sequence, rendered once.
pub fn render_all(renderer: &SimRenderer) -> Vec<Frame> {
    (0..renderer.len())
        .map(|i| {
            let f = renderer.render(i);
            Frame { t_ns: f.t_ns, seq: i as u64, image: FrameImage::Rgb8(f.rgb) }
        })
        .collect()
}

pub struct RunResult {
    pub outputs: Vec<TrackOutput>,
    pub trajectory: FinalTrajectory,
    pub ate_rmse_m: f64,
    pub ate_percent: f64,
    pub path_m: f64,
    pub tracker: Tracker,
}

/// ATE RMSE (m) and percent of path after Sim(3) alignment.
pub fn ate(gt: &[StampedPose], est: &[StampedPose]) -> (f64, f64, f64) {
    let ev = evaluate_trajectory(gt, est, &TrajectoryOptions::default(), "gt", "est").expect("trajectory evaluation");
    let r = &ev.report;
    (r.ate.stats_m.rmse, r.ate_rmse_percent_of_path.unwrap_or(f64::NAN), r.gt_path_length_m)
}

/// Tracks `frames` (rendered by `renderer`) and scores the final trajectory.
pub fn run(renderer: &SimRenderer, frames: &[Frame], cfg: &TrackerConfig, cap: TrackerCapacity) -> RunResult {
    let mut tracker = Tracker::new(renderer.camera(), cfg, cap).expect("tracker");
    let mut rec = TrajectoryRecorder::new();
    let mut outputs = Vec::with_capacity(frames.len());
    for f in frames {
        let out = tracker.track(f).expect("track");
        rec.record(&out);
        outputs.push(out);
    }
    let trajectory = rec.finish(&mut tracker);
    let (ate_rmse_m, ate_percent, path_m) = ate(&renderer.poses()[..frames.len()], &trajectory.frames);
    RunResult { outputs, trajectory, ate_rmse_m, ate_percent, path_m, tracker }
}
