//! AUV-like camera trajectories: a planar path (lawnmower lanes with semicircular turns, a
//! stadium loop, a hover drift) flown at constant speed, terrain-following at a set altitude
//! above the large-scale seabed, with a forward-looking camera pitched down and a smooth
//! roll/pitch/yaw/heave wobble.
//!
//! The path is tangent-continuous (lines meet arcs tangentially), so the velocity never jumps;
//! the altitude reference is a C2 function of position, so neither does the vertical speed.

use super::{SimConfig, TrajectoryKind, Wobble};
use duv_core::rng::Rng;
use duv_core::{Se3, StampedPose, Timestamp};
use nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// Position on the seabed plane and heading (radians from +x east, counter-clockwise).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanarState {
    pub x: f64,
    pub y: f64,
    pub heading: f64,
}

#[derive(Clone, Copy, Debug)]
enum Segment {
    Line { x0: f64, y0: f64, heading: f64, len: f64 },
    /// `turn` +1 counter-clockwise (left), -1 clockwise (right).
    Arc { cx: f64, cy: f64, radius: f64, angle0: f64, turn: f64, len: f64 },
}

impl Segment {
    fn len(&self) -> f64 {
        match *self {
            Segment::Line { len, .. } | Segment::Arc { len, .. } => len,
        }
    }
    fn eval(&self, s: f64) -> PlanarState {
        match *self {
            Segment::Line { x0, y0, heading, .. } => PlanarState { x: x0 + s * heading.cos(), y: y0 + s * heading.sin(), heading },
            Segment::Arc { cx, cy, radius, angle0, turn, .. } => {
                let a = angle0 + turn * s / radius;
                PlanarState { x: cx + radius * a.cos(), y: cy + radius * a.sin(), heading: a + turn * FRAC_PI_2 }
            }
        }
    }
}

/// A chain of tangent-continuous segments parametrised by arc length.
#[derive(Clone, Debug, Default)]
struct PlanarPath {
    segments: Vec<Segment>,
}

impl PlanarPath {
    fn end(&self) -> PlanarState {
        match self.segments.last() {
            Some(seg) => seg.eval(seg.len()),
            None => PlanarState { x: 0.0, y: 0.0, heading: 0.0 },
        }
    }
    fn line(&mut self, len: f64) {
        let e = self.end();
        self.segments.push(Segment::Line { x0: e.x, y0: e.y, heading: e.heading, len });
    }
    fn arc(&mut self, radius: f64, turn: f64, angle: f64) {
        let e = self.end();
        // The centre lies to the left (turn +1) or right (turn -1) of the heading.
        let (cx, cy) = (e.x - turn * radius * e.heading.sin(), e.y + turn * radius * e.heading.cos());
        let angle0 = (e.y - cy).atan2(e.x - cx);
        self.segments.push(Segment::Arc { cx, cy, radius, angle0, turn, len: radius * angle });
    }
    fn length(&self) -> f64 {
        self.segments.iter().map(Segment::len).sum()
    }
    /// The state at arc length `s`; past the end the path continues straight.
    fn eval(&self, mut s: f64) -> PlanarState {
        for seg in &self.segments {
            if s <= seg.len() {
                return seg.eval(s.max(0.0));
            }
            s -= seg.len();
        }
        let e = self.end();
        PlanarState { x: e.x + s * e.heading.cos(), y: e.y + s * e.heading.sin(), heading: e.heading }
    }
}

/// Shape parameters of the planned path (the scene places its structures from them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Layout {
    /// Lanes along x from x = 0 to `lane_length`, at y = 0, spacing, 2 spacing...
    Survey { lane_length: f64, spacing: f64, lanes: usize },
    /// Stadium: straights of `straight` along x at y = 0 and y = 2 radius, centred on x = 0.
    Loop { straight: f64, radius: f64 },
    /// Drift on a circle of `radius` through the origin.
    Hover { radius: f64 },
}

/// The planar part of a trajectory: one state per frame and the layout.
#[derive(Clone, Debug)]
pub struct PlanarPlan {
    pub states: Vec<PlanarState>,
    pub layout: Layout,
}

impl PlanarPlan {
    /// `(x_min, y_min, x_max, y_max)` of the camera positions.
    pub fn bounds(&self) -> (f64, f64, f64, f64) {
        self.states.iter().fold((f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY), |b, s| {
            (b.0.min(s.x), b.1.min(s.y), b.2.max(s.x), b.3.max(s.y))
        })
    }
}

/// Time stamp of frame `i`: `i / fps` seconds from 0.
pub fn timestamp(i: usize, fps: f64) -> Timestamp {
    Timestamp::from_secs_f64(i as f64 / fps)
}

/// Hover: drift speed is `speed_mps` on a circle of this radius.
const HOVER_RADIUS_M: f64 = 0.3;
/// Hover: yaw sweep amplitude and period.
const HOVER_YAW_AMPLITUDE_DEG: f64 = 50.0;
const HOVER_YAW_PERIOD_S: f64 = 30.0;
/// Loop: how far the vehicle runs past its start (at most), fraction of the path and metres.
const LOOP_OVERSHOOT_FRACTION: f64 = 0.04;
const LOOP_OVERSHOOT_MAX_M: f64 = 0.5;

/// Plans the camera's path over the seabed plane for every frame.
pub fn plan_planar(cfg: &SimConfig) -> PlanarPlan {
    let n = cfg.frames;
    let total = cfg.speed_mps * cfg.duration_secs();
    let at = |i: usize| cfg.speed_mps * i as f64 / cfg.fps;
    match cfg.trajectory {
        TrajectoryKind::Survey => {
            let spacing = cfg.lane_spacing_m;
            let radius = 0.5 * spacing;
            let mut path = PlanarPath::default();
            let mut lanes = 0;
            let mut turn = 1.0;
            loop {
                path.line(cfg.lane_length_m);
                lanes += 1;
                if path.length() >= total {
                    break;
                }
                path.arc(radius, turn, PI);
                turn = -turn;
            }
            let states = (0..n).map(|i| path.eval(at(i))).collect();
            PlanarPlan { states, layout: Layout::Survey { lane_length: cfg.lane_length_m, spacing, lanes } }
        }
        TrajectoryKind::Loop => {
            let overshoot = (LOOP_OVERSHOOT_FRACTION * total).min(LOOP_OVERSHOOT_MAX_M);
            let perimeter = total - overshoot;
            // A stadium: two straights and two semicircles; a circle when it is short.
            let mut radius = (0.12 * perimeter).clamp(0.5, 3.0);
            let mut straight = 0.5 * (perimeter - TAU * radius);
            if straight < 0.0 {
                radius = (perimeter / TAU).max(1e-6);
                straight = 0.0;
            }
            let mut path = PlanarPath::default();
            path.line(0.5 * straight);
            path.arc(radius, 1.0, PI);
            path.line(straight);
            path.arc(radius, 1.0, PI);
            path.line(0.5 * straight + overshoot + 1.0);
            let states = (0..n).map(|i| path.eval(at(i))).collect();
            PlanarPlan { states, layout: Layout::Loop { straight, radius } }
        }
        TrajectoryKind::Hover => {
            let omega = cfg.speed_mps / HOVER_RADIUS_M;
            let yaw_amp = HOVER_YAW_AMPLITUDE_DEG.to_radians();
            let states = (0..n)
                .map(|i| {
                    let t = i as f64 / cfg.fps;
                    let a = omega * t;
                    PlanarState {
                        x: HOVER_RADIUS_M * a.sin(),
                        y: HOVER_RADIUS_M * (1.0 - a.cos()),
                        heading: yaw_amp * (TAU * t / HOVER_YAW_PERIOD_S).sin(),
                    }
                })
                .collect();
            PlanarPlan { states, layout: Layout::Hover { radius: HOVER_RADIUS_M } }
        }
    }
}

/// Seeded phases of the wobble, two sinusoids per axis.
#[derive(Clone, Copy, Debug)]
pub struct WobblePhases {
    phases: [[f64; 2]; 4],
}

impl WobblePhases {
    pub fn new(seed: u64) -> Self {
        let mut rng = Rng::derive(seed, 0x0057_4F42);
        let mut phases = [[0.0; 2]; 4];
        for axis in &mut phases {
            for p in axis.iter_mut() {
                *p = rng.range(0.0, TAU);
            }
        }
        WobblePhases { phases }
    }

    /// `(roll, pitch, yaw)` in radians and heave in metres at time `t` seconds.
    pub fn sample(&self, w: &Wobble, t: f64) -> (f64, f64, f64, f64) {
        // Incommensurate period ratios per axis so the axes never lock together.
        const RATIOS: [(f64, f64); 4] = [(1.0, 0.371), (1.318, 0.457), (1.731, 0.613), (2.213, 0.529)];
        let s = |axis: usize| {
            let (a, b) = RATIOS[axis];
            let [pa, pb] = self.phases[axis];
            0.75 * (TAU * t / (w.period_s * a) + pa).sin() + 0.25 * (TAU * t / (w.period_s * b) + pb).sin()
        };
        (w.roll_deg.to_radians() * s(0), w.pitch_deg.to_radians() * s(1), w.yaw_deg.to_radians() * s(2), w.heave_m * s(3))
    }
}

/// `world_from_cam` rotation of a camera on a vehicle with heading `yaw` (from +x, CCW),
/// nose-down pitch `pitch` and roll `roll` (right side down positive), the camera pitched
/// `pitch_down` below the vehicle's forward axis. Body frame: x forward, y left, z up.
pub fn camera_rotation(yaw: f64, pitch: f64, roll: f64, pitch_down: f64) -> UnitQuaternion<f64> {
    let world_from_body = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw)
        * Rotation3::from_axis_angle(&Vector3::y_axis(), pitch)
        * Rotation3::from_axis_angle(&Vector3::x_axis(), roll);
    let (s, c) = pitch_down.sin_cos();
    // Columns: camera x (right), y (down), z (forward) in the body frame.
    let body_from_cam = Rotation3::from_matrix_unchecked(Matrix3::new(0.0, -s, c, -1.0, 0.0, 0.0, 0.0, -c, -s));
    UnitQuaternion::from_rotation_matrix(&(world_from_body * body_from_cam))
}

/// Full 6-DoF poses, one per frame: the planar plan at `altitude_m` (plus the yo-yo swing)
/// above `ground_ref(x, y)` (the smooth large-scale seabed height) plus the wobble.
pub fn poses(cfg: &SimConfig, plan: &PlanarPlan, ground_ref: impl Fn(f64, f64) -> f64) -> Vec<StampedPose> {
    let phases = WobblePhases::new(cfg.seed);
    let pitch_down = cfg.pitch_down_deg.to_radians();
    plan.states
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let t = i as f64 / cfg.fps;
            let (roll, pitch, yaw, heave) = phases.sample(&cfg.wobble, t);
            let swing = cfg.altitude_swing_m * (TAU * t / cfg.altitude_period_s).sin();
            let z = ground_ref(s.x, s.y) + cfg.altitude_m + swing + heave;
            let rotation = camera_rotation(s.heading + yaw, pitch, roll, pitch_down);
            StampedPose { t_ns: timestamp(i, cfg.fps), world_from_cam: Se3::from_parts(Translation3::new(s.x, s.y, z), rotation) }
        })
        .collect()
}

/// Sum of distances between consecutive camera positions, metres.
pub fn path_length_m(poses: &[StampedPose]) -> f64 {
    poses.windows(2).map(|w| (w[1].world_from_cam.translation.vector - w[0].world_from_cam.translation.vector).norm()).fold(0.0, |a, b| a + b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::WaterPreset;

    fn cfg(kind: TrajectoryKind) -> SimConfig {
        SimConfig { frames: 300, ..SimConfig::preset(WaterPreset::Coastal, kind) }
    }

    #[test]
    fn camera_looks_forward_and_down() {
        let q = camera_rotation(0.0, 0.0, 0.0, 40f64.to_radians());
        let z = q * Vector3::z();
        let x = q * Vector3::x();
        assert!(z.x > 0.7 && z.z < -0.6 && z.y.abs() < 1e-12, "{z:?}");
        assert!((x - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12, "right of east-facing is south: {x:?}");
        let north = camera_rotation(FRAC_PI_2, 0.0, 0.0, 0.0) * Vector3::z();
        assert!((north - Vector3::y()).norm() < 1e-12);
        // Positive roll dips the right side: the camera's x axis points below the horizon.
        assert!((camera_rotation(0.0, 0.0, 0.1, 0.0) * Vector3::x()).z < 0.0);
    }

    #[test]
    fn speed_is_constant_and_velocity_has_no_jumps() {
        for kind in [TrajectoryKind::Survey, TrajectoryKind::Loop] {
            let c = cfg(kind);
            let plan = plan_planar(&c);
            let step = c.speed_mps / c.fps;
            let v: Vec<(f64, f64)> = plan.states.windows(2).map(|w| (w[1].x - w[0].x, w[1].y - w[0].y)).collect();
            for d in &v {
                let len = (d.0 * d.0 + d.1 * d.1).sqrt();
                assert!((len - step).abs() < 0.02 * step, "{kind:?}: step {len} vs {step}");
            }
            // Consecutive displacement vectors turn by at most what the tightest arc allows.
            for w in v.windows(2) {
                let (a, b) = (w[0], w[1]);
                let turn = (a.0 * b.1 - a.1 * b.0).atan2(a.0 * b.0 + a.1 * b.1).abs();
                assert!(turn < 2.5 * step / 1.0, "{kind:?}: heading jumps by {turn}");
            }
        }
    }

    #[test]
    fn loop_returns_over_its_start_and_survey_has_lanes() {
        let c = cfg(TrajectoryKind::Loop);
        let plan = plan_planar(&c);
        let (a, b) = (plan.states[0], *plan.states.last().unwrap());
        let gap = ((a.x - b.x).powi(2) + (a.y - b.y).powi(2)).sqrt();
        assert!(gap < 1.0 && gap > 0.0, "{gap}");
        let dh = (a.heading - b.heading).rem_euclid(TAU);
        assert!(dh.min(TAU - dh) < 0.05, "same heading at the end: {dh}");
        let s = plan_planar(&cfg(TrajectoryKind::Survey));
        match s.layout {
            Layout::Survey { lanes, .. } => assert!(lanes >= 2),
            other => panic!("{other:?}"),
        }
        let (_, y0, _, y1) = s.bounds();
        assert!(y1 - y0 > 2.5, "turned onto a second lane");
    }

    #[test]
    fn wobble_is_bounded_and_hover_yaws() {
        let c = cfg(TrajectoryKind::Hover);
        let phases = WobblePhases::new(3);
        for i in 0..500 {
            let (r, p, y, h) = phases.sample(&Wobble::DEFAULT, i as f64 * 0.1);
            assert!(r.abs() <= 1.5f64.to_radians() + 1e-12 && p.abs() <= 1f64.to_radians() + 1e-12);
            assert!(y.abs() <= 1f64.to_radians() + 1e-12 && h.abs() <= 0.05 + 1e-12);
        }
        let plan = plan_planar(&c);
        let yaw_span = plan.states.iter().map(|s| s.heading).fold(f64::NEG_INFINITY, f64::max)
            - plan.states.iter().map(|s| s.heading).fold(f64::INFINITY, f64::min);
        assert!(yaw_span > 1.0, "{yaw_span}");
        let (x0, y0, x1, y1) = plan.bounds();
        assert!(x1 - x0 <= 0.61 && y1 - y0 <= 0.61);
    }
}
