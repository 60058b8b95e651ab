//! Simulated navigation sensors (issue 40): what an AUV's pressure sensor, altimeter, DVL and
//! AHRS would report along the generated path, one [`NavSample`] per frame at the frame's time
//! (so `nav.csv` lines up with `rgb.txt`).
//!
//! Truth, from the ground-truth poses (`world_from_cam`, world z up) and the scene:
//! - depth: `SURFACE_Z_M - z_cam`, the sea surface at [`SURFACE_Z_M`] = 25 m above the
//!   generator's seabed reference (z about 0), so the seabed lies at about 25 m depth and the
//!   camera at the default 2 m altitude at about 23 m (the seabed tilts by up to a few per
//!   cent, so long lanes change this by metres);
//! - altitude: the vertical range from the camera down to whatever lies below it (seabed, pipe
//!   or wreck), as an altimeter or a DVL's bottom lock measures it;
//! - velocity: the camera's velocity over ground in its own frame (x right, y down,
//!   z forward), from central differences of the poses (one-sided at the ends;
//!   [`true_vel_cam_mps`]);
//! - attitude: the camera-to-world rotation.
//!
//! Noise ([`NavNoise::default`], every draw from [`duv_core::rng::Rng`] streams derived from
//! the seed, one per sensor, so switching one sensor's noise off leaves the others' unchanged):
//! - pressure depth: white, sigma 1 cm;
//! - altitude: white, sigma 3 cm; no sample above the bottom-lock range of 30 m, and 2 % of
//!   samples dropped at random;
//! - DVL velocity: scale error +1 % (reads fast), white noise sigma 1 cm/s per axis; no
//!   sample without bottom lock (above 30 m), and 2 % dropped at random;
//! - AHRS: roll and pitch error (a tilt about a horizontal world axis) white, sigma 0.3
//!   degrees per axis; heading error drifting linearly at 3 degrees per minute plus a random
//!   walk of 0.1 degrees per square-root second, starting at 0 at the first frame.
//!
//! [`NavNoise::none`] gives exact sensors (the truth).

use super::render::SimRenderer;
use super::SimError;
use duv_core::nav::NavSample;
use duv_core::rng::Rng;
use duv_core::StampedPose;
use nalgebra::{UnitQuaternion, Vector3};

/// Height of the sea surface in the generator's world frame, metres (z up, seabed reference
/// about z = 0): depth = `SURFACE_Z_M - z`.
pub const SURFACE_Z_M: f64 = 25.0;

/// Stream id of the navigation noise (mixed with the seed and the sensor).
const NAV_STREAM: u64 = 0x4E41_5600;

/// Noise of the simulated navigation sensors; see the module documentation for the defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavNoise {
    /// Pressure depth noise, standard deviation, metres.
    pub depth_sigma_m: f64,
    /// Altimeter noise, standard deviation, metres.
    pub altitude_sigma_m: f64,
    /// Bottom-lock range of the altimeter and the DVL, metres: above it neither reports
    /// (`f64::INFINITY`: always in range).
    pub bottom_lock_max_m: f64,
    /// Probability that an altitude sample is missing, in [0, 1].
    pub altitude_dropout: f64,
    /// Probability that a velocity sample is missing, in [0, 1].
    pub velocity_dropout: f64,
    /// DVL scale error: it reports `(1 + e)` times the true velocity.
    pub velocity_scale_error: f64,
    /// DVL noise per axis, standard deviation, m/s.
    pub velocity_sigma_mps: f64,
    /// AHRS roll and pitch noise per axis, standard deviation, degrees.
    pub roll_pitch_sigma_deg: f64,
    /// AHRS heading drift, degrees per minute (linear in time from the first sample).
    pub heading_drift_deg_per_min: f64,
    /// AHRS heading random walk, degrees per square-root second.
    pub heading_walk_deg_per_sqrt_s: f64,
}

impl Default for NavNoise {
    /// Realistic sensors of a small AUV (see the module documentation).
    fn default() -> Self {
        NavNoise {
            depth_sigma_m: 0.01,
            altitude_sigma_m: 0.03,
            bottom_lock_max_m: 30.0,
            altitude_dropout: 0.02,
            velocity_dropout: 0.02,
            velocity_scale_error: 0.01,
            velocity_sigma_mps: 0.01,
            roll_pitch_sigma_deg: 0.3,
            heading_drift_deg_per_min: 3.0,
            heading_walk_deg_per_sqrt_s: 0.1,
        }
    }
}

impl NavNoise {
    /// Exact sensors: every sample is the truth, none missing.
    pub fn none() -> Self {
        NavNoise {
            depth_sigma_m: 0.0,
            altitude_sigma_m: 0.0,
            bottom_lock_max_m: f64::INFINITY,
            altitude_dropout: 0.0,
            velocity_dropout: 0.0,
            velocity_scale_error: 0.0,
            velocity_sigma_mps: 0.0,
            roll_pitch_sigma_deg: 0.0,
            heading_drift_deg_per_min: 0.0,
            heading_walk_deg_per_sqrt_s: 0.0,
        }
    }

    /// Checks every field; the first problem is the error, naming it (`nav.depth_sigma_m`).
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |field: &'static str, value: f64, expected: &'static str| -> Result<(), SimError> { Err(SimError::InvalidConfig { field, value: value.to_string(), expected }) };
        for (field, v) in [
            ("nav.depth_sigma_m", self.depth_sigma_m),
            ("nav.altitude_sigma_m", self.altitude_sigma_m),
            ("nav.velocity_sigma_mps", self.velocity_sigma_mps),
            ("nav.roll_pitch_sigma_deg", self.roll_pitch_sigma_deg),
            ("nav.heading_walk_deg_per_sqrt_s", self.heading_walk_deg_per_sqrt_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(field, v, "a finite non-negative standard deviation");
            }
        }
        for (field, v) in [("nav.altitude_dropout", self.altitude_dropout), ("nav.velocity_dropout", self.velocity_dropout)] {
            if !(0.0..=1.0).contains(&v) {
                return bad(field, v, "a probability in [0, 1]");
            }
        }
        if self.bottom_lock_max_m.is_nan() || self.bottom_lock_max_m <= 0.0 {
            return bad("nav.bottom_lock_max_m", self.bottom_lock_max_m, "a positive range in metres (inf: unlimited)");
        }
        if !(self.velocity_scale_error.is_finite() && self.velocity_scale_error.abs() < 0.5) {
            return bad("nav.velocity_scale_error", self.velocity_scale_error, "a fraction in (-0.5, 0.5)");
        }
        if !self.heading_drift_deg_per_min.is_finite() {
            return bad("nav.heading_drift_deg_per_min", self.heading_drift_deg_per_min, "a finite drift in degrees per minute");
        }
        Ok(())
    }
}

/// The navigation samples of a renderer's sequence, one per frame, with `noise` drawn from
/// `seed` (the sim writes them with the config's seed). Deterministic.
pub fn simulate(renderer: &SimRenderer, noise: &NavNoise, seed: u64) -> Result<Vec<NavSample>, SimError> {
    let altitudes: Vec<Option<f64>> = (0..renderer.len()).map(|i| renderer.altitude_m(i)).collect();
    simulate_from(renderer.poses(), &altitudes, noise, seed)
}

/// [`simulate`] from the poses and the true altitude of each (`None`: nothing below).
pub fn simulate_from(poses: &[StampedPose], altitude_m: &[Option<f64>], noise: &NavNoise, seed: u64) -> Result<Vec<NavSample>, SimError> {
    noise.validate()?;
    if altitude_m.len() != poses.len() {
        return Err(SimError::InvalidConfig { field: "altitude_m", value: altitude_m.len().to_string(), expected: "one altitude per pose" });
    }
    let mut depth_rng = Rng::derive(seed, NAV_STREAM + 1);
    let mut altitude_rng = Rng::derive(seed, NAV_STREAM + 2);
    let mut velocity_rng = Rng::derive(seed, NAV_STREAM + 3);
    let mut attitude_rng = Rng::derive(seed, NAV_STREAM + 4);
    let t0 = poses.first().map(|p| p.t_ns);
    let mut heading_walk_rad = 0.0;
    let mut samples = Vec::with_capacity(poses.len());
    for (i, p) in poses.iter().enumerate() {
        let z = p.world_from_cam.translation.vector.z;
        let depth_m = SURFACE_Z_M - z + noise.depth_sigma_m * depth_rng.normal();

        // One normal and one uniform per sample whatever happens, so the stream stays aligned.
        let (n, u) = (altitude_rng.normal(), altitude_rng.uniform());
        let in_lock = altitude_m[i].filter(|&a| a <= noise.bottom_lock_max_m);
        let altitude = in_lock.filter(|_| u >= noise.altitude_dropout).map(|a| (a + noise.altitude_sigma_m * n).max(0.0));

        let (nv, u) = (Vector3::new(velocity_rng.normal(), velocity_rng.normal(), velocity_rng.normal()), velocity_rng.uniform());
        let vel = true_vel_cam_mps(poses, i)
            .filter(|_| in_lock.is_some() && u >= noise.velocity_dropout)
            .map(|v| v * (1.0 + noise.velocity_scale_error) + nv * noise.velocity_sigma_mps);

        let t_s = t0.map_or(0.0, |t0| p.t_ns.secs_since(t0));
        if i > 0 {
            let dt = p.t_ns.secs_since(poses[i - 1].t_ns).max(0.0);
            heading_walk_rad += noise.heading_walk_deg_per_sqrt_s.to_radians() * dt.sqrt() * attitude_rng.normal();
        }
        let tilt = Vector3::new(attitude_rng.normal(), attitude_rng.normal(), 0.0) * noise.roll_pitch_sigma_deg.to_radians();
        let heading_rad = noise.heading_drift_deg_per_min.to_radians() / 60.0 * t_s + heading_walk_rad;
        let world_error = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), heading_rad) * UnitQuaternion::from_scaled_axis(tilt);
        let attitude = world_error * p.world_from_cam.rotation;

        samples.push(NavSample { t_ns: p.t_ns, depth_m: Some(depth_m), altitude_m: altitude, vel_cam_mps: vel, world_from_cam_rot: Some(attitude) });
    }
    Ok(samples)
}

/// True velocity of the camera of pose `i` over ground in its own frame (x right, y down,
/// z forward), m/s: the central difference of the neighbouring positions (one-sided at the
/// ends) rotated into the camera of pose `i`. `None` for a single pose or equal time stamps.
pub fn true_vel_cam_mps(poses: &[StampedPose], i: usize) -> Option<Vector3<f64>> {
    let (a, b) = (i.saturating_sub(1), (i + 1).min(poses.len().checked_sub(1)?));
    let dt = poses[b].t_ns.secs_since(poses[a].t_ns);
    if dt <= 0.0 {
        return None;
    }
    let v_world = (poses[b].world_from_cam.translation.vector - poses[a].world_from_cam.translation.vector) / dt;
    Some(poses[i].world_from_cam.rotation.inverse() * v_world)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{SimConfig, TrajectoryKind, WaterPreset};

    /// 600 frames (60 s at 10 Hz) of the survey, with a yo-yo altitude of 2 +- 1.5 m.
    fn renderer() -> SimRenderer {
        let cfg = SimConfig {
            frames: 600,
            width: 16,
            height: 12,
            max_range_m: 4.0,
            altitude_swing_m: 1.5,
            altitude_period_s: 30.0,
            ..SimConfig::preset(WaterPreset::Clear, TrajectoryKind::Survey)
        };
        SimRenderer::new(&cfg).unwrap()
    }

    fn rms(v: &[f64]) -> f64 {
        (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
    }

    fn mean(v: &[f64]) -> f64 {
        v.iter().sum::<f64>() / v.len() as f64
    }

    #[test]
    fn exact_sensors_are_the_truth() {
        let r = renderer();
        let nav = simulate(&r, &NavNoise::none(), 1).unwrap();
        assert_eq!(nav.len(), 600);
        for (i, (s, p)) in nav.iter().zip(r.poses()).enumerate() {
            assert_eq!(s.t_ns, p.t_ns);
            let z = p.world_from_cam.translation.vector.z;
            assert_eq!(s.depth_m, Some(SURFACE_Z_M - z));
            assert_eq!(s.altitude_m, r.altitude_m(i));
            assert_eq!(s.world_from_cam_rot, Some(p.world_from_cam.rotation));
            // Survey at 0.5 m/s, camera pitched 40 degrees down: mostly forward and down in
            // the camera frame (z forward: cos 40 * 0.5 = 0.38; y down: sin 40 * 0.5 = 0.32
            // on flat ground), plus the yo-yo's climb of up to 2 pi 1.5 / 30 = 0.31 m/s.
            let v = s.vel_cam_mps.unwrap();
            assert!(v.norm() > 0.3 && v.norm() < 0.8, "frame {i}: {v}");
        }
        // Depth: seabed reference about z = 0, the camera 0.5 to 3.5 m above it.
        let depths: Vec<f64> = nav.iter().map(|s| s.depth_m.unwrap()).collect();
        let (lo, hi) = depths.iter().fold((f64::MAX, f64::MIN), |(a, b), &d| (a.min(d), b.max(d)));
        assert!(lo > 19.0 && hi < 26.0 && hi - lo > 2.5, "{lo} {hi}");
        // Velocity from central differences: at frame 100 (a straight lane, mid yo-yo) the
        // speed over ground is the lane speed combined with the climb rate.
        let v = nav[100].vel_cam_mps.unwrap();
        let climb = 2.0 * std::f64::consts::PI * 1.5 / 30.0 * (2.0 * std::f64::consts::PI * 10.0 / 30.0).cos();
        assert!((v.norm() - (0.25 + climb * climb).sqrt()).abs() < 0.03, "{v} climb {climb}");
    }

    #[test]
    fn noisy_sensors_agree_with_the_truth_within_their_noise() {
        let r = renderer();
        let truth = simulate(&r, &NavNoise::none(), 1).unwrap();
        let noise = NavNoise::default();
        let nav = simulate(&r, &noise, 1).unwrap();
        let n = nav.len();

        let dd: Vec<f64> = nav.iter().zip(&truth).map(|(a, b)| a.depth_m.unwrap() - b.depth_m.unwrap()).collect();
        assert!((rms(&dd) - 0.01).abs() < 0.002 && mean(&dd).abs() < 0.002, "depth rms {} mean {}", rms(&dd), mean(&dd));

        let pairs: Vec<(f64, f64)> = nav.iter().zip(&truth).filter_map(|(a, b)| Some((a.altitude_m?, b.altitude_m?))).collect();
        let da: Vec<f64> = pairs.iter().map(|(a, b)| a - b).collect();
        assert!((rms(&da) - 0.03).abs() < 0.005, "altitude rms {}", rms(&da));
        // 2 % random dropouts of 600: between 3 and 25.
        let dropped = n - pairs.len();
        assert!((3..=25).contains(&dropped), "{dropped} altitude dropouts");

        // Velocity: 1 % fast, 1 cm/s noise per axis.
        let mut scale = Vec::new();
        let mut resid = Vec::new();
        for (a, b) in nav.iter().zip(&truth) {
            if let (Some(va), Some(vb)) = (a.vel_cam_mps, b.vel_cam_mps) {
                scale.push(va.dot(&vb) / vb.norm_squared());
                resid.extend((va - vb * 1.01).iter().copied());
            }
        }
        assert!((mean(&scale) - 1.01).abs() < 0.003, "scale {}", mean(&scale));
        assert!((rms(&resid) - 0.01).abs() < 0.002, "velocity noise {}", rms(&resid));
        assert!((3..=25).contains(&(n - scale.len())), "{} velocity dropouts", n - scale.len());

        // Attitude: the tilt (gravity direction in the camera) is off by the roll/pitch noise,
        // sqrt(2) x 0.3 degrees rms; the heading drifts 3 degrees per minute (59.9 s: 3.0).
        let up = Vector3::z_axis();
        let mut tilt_deg = Vec::new();
        for (a, b) in nav.iter().zip(&truth) {
            let (qa, qb) = (a.world_from_cam_rot.unwrap(), b.world_from_cam_rot.unwrap());
            let up_a = qa.inverse() * up;
            let up_b = qb.inverse() * up;
            tilt_deg.push(up_a.angle(&up_b).to_degrees());
        }
        let tilt_rms = rms(&tilt_deg);
        assert!((tilt_rms - 0.3 * 2f64.sqrt()).abs() < 0.05, "tilt rms {tilt_rms}");
        let heading_deg = |k: usize| {
            let e = nav[k].world_from_cam_rot.unwrap() * truth[k].world_from_cam_rot.unwrap().inverse();
            let (_, _, yaw) = e.euler_angles();
            yaw.to_degrees()
        };
        assert!(heading_deg(0).abs() < 1.0, "{}", heading_deg(0));
        // Drift 3.0 degrees plus a walk of 0.1 x sqrt(60) = 0.8 degrees rms.
        let last = heading_deg(n - 1);
        assert!((last - 3.0).abs() < 2.5, "heading error after 60 s {last}");
    }

    #[test]
    fn altimeter_and_dvl_drop_out_above_their_range() {
        let r = renderer();
        // Bottom lock only to 2 m: the yo-yo (0.5 to 3.5 m) goes in and out of range.
        let noise = NavNoise { bottom_lock_max_m: 2.0, ..NavNoise::none() };
        let nav = simulate(&r, &noise, 1).unwrap();
        let mut above = 0;
        for (i, s) in nav.iter().enumerate() {
            let a = r.altitude_m(i).unwrap();
            if a > 2.0 {
                above += 1;
                assert!(s.altitude_m.is_none() && s.vel_cam_mps.is_none(), "frame {i} at {a} m");
            } else {
                assert_eq!(s.altitude_m, Some(a));
                assert!(s.vel_cam_mps.is_some());
            }
            assert!(s.depth_m.is_some() && s.world_from_cam_rot.is_some());
        }
        assert!(above > 150 && above < 450, "{above} of 600 above 2 m");
    }

    #[test]
    fn same_seed_same_samples_other_seed_differs() {
        let r = renderer();
        let a = simulate(&r, &NavNoise::default(), 7).unwrap();
        let b = simulate(&r, &NavNoise::default(), 7).unwrap();
        let c = simulate(&r, &NavNoise::default(), 8).unwrap();
        assert_eq!(a, b);
        assert_ne!(a[10].depth_m, c[10].depth_m);
        // Switching off one sensor's noise leaves the others' draws alone.
        let d = simulate(&r, &NavNoise { depth_sigma_m: 0.0, ..NavNoise::default() }, 7).unwrap();
        for (x, y) in a.iter().zip(&d) {
            assert_eq!((x.altitude_m, x.vel_cam_mps, x.world_from_cam_rot), (y.altitude_m, y.vel_cam_mps, y.world_from_cam_rot));
        }
    }

    #[test]
    fn bad_noise_names_the_field() {
        for (noise, field) in [
            (NavNoise { depth_sigma_m: f64::NAN, ..NavNoise::default() }, "nav.depth_sigma_m"),
            (NavNoise { altitude_dropout: 1.5, ..NavNoise::default() }, "nav.altitude_dropout"),
            (NavNoise { bottom_lock_max_m: 0.0, ..NavNoise::default() }, "nav.bottom_lock_max_m"),
            (NavNoise { velocity_scale_error: f64::INFINITY, ..NavNoise::default() }, "nav.velocity_scale_error"),
        ] {
            let e = noise.validate().unwrap_err();
            assert!(e.to_string().contains(field), "{e}");
        }
        NavNoise::none().validate().unwrap();
    }
}
