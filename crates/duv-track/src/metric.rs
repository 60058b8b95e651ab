//! Metres from the vehicle's navigation sensors (issue 40): the similarity that takes the
//! tracker's map frame (monocular: unknown scale, arbitrary orientation) to a metric,
//! gravity-aligned world (z up, the origin at the sea surface above the first frame).
//!
//! Each sensor observes what it can, and each estimate says how well it did:
//! - **Attitude** (AHRS, camera-to-world): the world's up direction seen in the map. Every
//!   frame gives `up_in_map = map_from_cam * cam_from_world * z`; their robust mean fixes roll
//!   and pitch. A drifting heading does not matter (only the up axis is used); the heading is
//!   taken from the AHRS's circular mean so the world's x axis roughly points where it says.
//! - **Pressure depth**: the camera's height in the map (`up · p`) against `-depth_m`, a line
//!   whose slope is the scale. Only observable with vertical motion: like every sensor's, the
//!   estimate is used only when its uncertainty is at most 5 % of it.
//! - **Altitude** (altimeter, DVL bottom lock): the range along gravity to the seabed in map
//!   units against `altitude_m`: at each keyframe where the down ray meets its image (a
//!   downward camera), else (a camera looking ahead never sees below itself) at each frame,
//!   from the seabed heights the keyframes saw there earlier or later (a horizontal grid of
//!   their depth points).
//! - **DVL velocity** (camera frame, over ground): the metric displacement between keyframes
//!   (velocity rotated into the map by the tracked attitude, integrated) against the map
//!   displacement.
//!
//! The estimates are combined by inverse variance after their outliers are dropped (Huber-like
//! reweighting for the lines, median and MAD for ratios). This is a fit over the whole
//! trajectory: it makes the outputs metric but does not correct scale drift within a run.

use crate::KeyframeView;
use duv_core::nav::NavSample;
use duv_core::{PinholeCamera, PlaneF32, Se3, Sim3, Timestamp};
use nalgebra::{Rotation3, Translation3, UnitQuaternion, Vector3};

/// Errors of the metric alignment.
#[derive(Debug, thiserror::Error)]
pub enum MetricError {
    #[error("metric alignment: no navigation sample within {max_dt_ms} ms of any tracked frame")]
    NoOverlap { max_dt_ms: f64 },
    #[error("metric alignment: {n} attitude samples matched to frames, {needed} needed for gravity")]
    TooFewAttitudes { n: usize, needed: usize },
    #[error("metric alignment: no sensor observed the scale ({why})")]
    NoScale { why: String },
    /// The aligned path does not follow the depth sensor: the tracking itself went wrong (the
    /// scale of a wrong path is no scale).
    #[error("metric alignment: the aligned camera heights miss the pressure depth by {rms_m:.2} m RMS over {frames} frames (at most {limit_m:.2} m): the tracked path does not follow the vehicle")]
    Inconsistent { rms_m: f64, frames: usize, limit_m: f64 },
    /// [`dead_reckon`] over a gap that ends before it starts.
    #[error("dead reckoning: the gap runs backwards ({from_s:.3} s to {to_s:.3} s)")]
    Backwards { from_s: f64, to_s: f64 },
    /// [`dead_reckon`]: no DVL velocity with an attitude over `hole_s` seconds of the gap (a
    /// hole in the samples, or none at its start or end).
    #[error("dead reckoning: no DVL velocity with an attitude for {hole_s:.2} s from {at_s:.3} s (at most {max_hole_s:.2} s)")]
    Hole { at_s: f64, hole_s: f64, max_hole_s: f64 },
}

/// Settings of the alignment.
#[derive(Clone, Copy, Debug)]
pub struct MetricOptions {
    /// A nav sample matches a frame within this time (interpolated between two samples that
    /// bracket the frame within it).
    pub max_dt_ns: i64,
    /// Attitude samples needed for gravity.
    pub min_attitudes: usize,
    /// A sensor's scale is used only when its one-sigma uncertainty is at most this fraction
    /// of it (the depth line needs vertical motion against the sensor's noise).
    pub max_relative_sigma: f64,
    /// Depth sensor noise assumed when its residuals cannot tell (m).
    pub depth_sigma_floor_m: f64,
    /// How far the up direction found from the attitudes may be off (deg, one sigma): the
    /// depth line's prior on the tilt it fits.
    pub tilt_prior_deg: f64,
    /// Altitude samples (keyframes) needed for an altitude scale.
    pub min_altitudes: usize,
    /// Keyframe pairs with DVL velocity needed for a velocity scale.
    pub min_velocity_pairs: usize,
    /// The aligned heights must follow the pressure depth within this RMS (m), or the
    /// alignment is refused ([`MetricError::Inconsistent`]).
    pub max_depth_rms_m: f64,
}

impl Default for MetricOptions {
    fn default() -> Self {
        MetricOptions { max_dt_ns: 100_000_000, min_attitudes: 5, max_relative_sigma: 0.05, depth_sigma_floor_m: 0.01, tilt_prior_deg: 1.0, min_altitudes: 3, min_velocity_pairs: 3, max_depth_rms_m: 0.25 }
    }
}

/// One sensor's scale: metres per map unit.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ScaleEstimate {
    pub metres_per_unit: f64,
    /// One-sigma uncertainty of `metres_per_unit`.
    pub sigma: f64,
    /// Samples used (after outliers were dropped).
    pub used: usize,
    /// Samples dropped as outliers.
    pub rejected: usize,
}

/// The map-to-metric similarity and how it was found.
#[derive(Clone, Copy, Debug)]
pub struct MetricAlignment {
    /// `p_in_metric = metric_from_map * p_in_map`: scale, gravity (z up), heading, origin.
    pub metric_from_map: Sim3,
    /// The combined scale (metres per map unit) and its sigma.
    pub scale: ScaleEstimate,
    pub from_depth: Option<ScaleEstimate>,
    pub from_altitude: Option<ScaleEstimate>,
    pub from_velocity: Option<ScaleEstimate>,
    /// Frames with an attitude sample, and the RMS angle (deg) between their up directions and
    /// the estimate (the AHRS's roll/pitch noise plus the tracker's rotation error).
    pub attitudes: usize,
    pub tilt_rms_deg: f64,
}

/// A tracked frame's pose in the map.
#[derive(Clone, Copy, Debug)]
pub struct MapFrame {
    pub t_ns: Timestamp,
    pub world_from_cam: Se3,
}

/// A keyframe's depth, as the alignment reads it (the tracker's depth grid is enough).
#[derive(Clone, Copy, Debug)]
pub struct MapKeyframe<'a> {
    pub t_ns: Timestamp,
    pub world_from_cam: Se3,
    pub inv_depth: &'a PlaneF32,
    /// The intrinsics of `inv_depth`.
    pub camera: PinholeCamera,
}

impl<'a> MapKeyframe<'a> {
    /// A tracker keyframe on the tracker's depth grid (`camera`: `Tracker::depth_camera`).
    pub fn from_view(view: &KeyframeView<'a>, camera: PinholeCamera) -> Self {
        MapKeyframe { t_ns: view.t_ns, world_from_cam: view.world_from_cam, inv_depth: view.inv_depth, camera }
    }
}

/// The nav samples near `t` (sorted by time): the value of `get` interpolated linearly between
/// the samples before and after `t` that have one, both within `max_dt_ns`; or the nearer one
/// when only one side has it.
fn interpolate<T: Copy>(nav: &[NavSample], t: Timestamp, max_dt_ns: i64, get: impl Fn(&NavSample) -> Option<T>, lerp: impl Fn(T, T, f64) -> T) -> Option<T> {
    let t = t.t_ns();
    let i = nav.partition_point(|s| s.t_ns.t_ns() <= t);
    let before = nav[..i].iter().rev().take_while(|s| t - s.t_ns.t_ns() <= max_dt_ns).find_map(|s| get(s).map(|v| (s.t_ns.t_ns(), v)));
    let after = nav[i..].iter().take_while(|s| s.t_ns.t_ns() - t <= max_dt_ns).find_map(|s| get(s).map(|v| (s.t_ns.t_ns(), v)));
    match (before, after) {
        (Some((ta, a)), Some((tb, b))) if tb > ta => Some(lerp(a, b, (t - ta) as f64 / (tb - ta) as f64)),
        (Some((_, a)), _) => Some(a),
        (None, Some((_, b))) => Some(b),
        (None, None) => None,
    }
}

fn lerp_f64(a: f64, b: f64, w: f64) -> f64 {
    a + (b - a) * w
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Median and a robust sigma (1.4826 MAD) of `v`.
fn median_mad(v: &[f64]) -> (f64, f64) {
    let mut w = v.to_vec();
    let m = median(&mut w);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
    (m, 1.4826 * median(&mut dev))
}

/// How many times the standard error of a mean of `v` (in time order) must grow because its
/// samples are not independent: `sqrt((1 + r) / (1 - r))` for the lag-1 autocorrelation `r`
/// (the tracker's errors drift slowly along the path, so neighbouring frames err alike).
fn correlation_inflation(v: &[f64]) -> f64 {
    let n = v.len();
    if n < 3 {
        return 1.0;
    }
    let mean = v.iter().sum::<f64>() / n as f64;
    let var: f64 = v.iter().map(|x| (x - mean) * (x - mean)).sum();
    if var <= 0.0 {
        return 1.0;
    }
    let cov: f64 = v.windows(2).map(|w| (w[0] - mean) * (w[1] - mean)).sum();
    let r = (cov / var).clamp(0.0, 0.99);
    ((1.0 + r) / (1.0 - r)).sqrt()
}

/// Contiguous blocks of the path the depth line's jackknife leaves out one at a time.
const JACKKNIFE_BLOCKS: usize = 10;

/// A robust ratio: the median of `ratios` after those beyond 3 robust sigmas are dropped,
/// with the standard error of the mean of the rest (grown for their correlation).
fn robust_ratio(ratios: &[f64]) -> Option<ScaleEstimate> {
    let finite: Vec<f64> = ratios.iter().copied().filter(|r| r.is_finite() && *r > 0.0).collect();
    if finite.is_empty() {
        return None;
    }
    let (m, s) = median_mad(&finite);
    let keep: Vec<f64> = finite.iter().copied().filter(|r| (r - m).abs() <= 3.0 * s.max(1e-12 * m.abs())).collect();
    let n = keep.len();
    let mean = keep.iter().sum::<f64>() / n as f64;
    let var = if n > 1 { keep.iter().map(|r| (r - mean) * (r - mean)).sum::<f64>() / (n - 1) as f64 } else { mean * mean };
    let (median_kept, _) = median_mad(&keep);
    let sigma = (var / n as f64).sqrt() * 1.2533 * correlation_inflation(&keep);
    Some(ScaleEstimate { metres_per_unit: median_kept, sigma, used: n, rejected: ratios.len() - n })
}

/// Estimates the map-to-metric similarity from the tracked `frames`, the `keyframes`' depth and
/// the `nav` samples (sorted by time; the reader guarantees it).
pub fn estimate_metric_alignment(frames: &[MapFrame], keyframes: &[MapKeyframe<'_>], nav: &[NavSample], opts: &MetricOptions) -> Result<MetricAlignment, MetricError> {
    let dt = opts.max_dt_ns;
    // Gravity: every frame with an attitude says where up is in the map.
    let mut ups = Vec::with_capacity(frames.len());
    let mut yaw_pairs = Vec::with_capacity(frames.len());
    let mut any = false;
    for f in frames {
        let q = interpolate(nav, f.t_ns, dt, |s| s.world_from_cam_rot, |a, b, w| a.slerp(&b, w));
        any |= q.is_some() || interpolate(nav, f.t_ns, dt, |s| s.depth_m, lerp_f64).is_some();
        let Some(world_from_cam_rot) = q else { continue };
        let up_in_cam = world_from_cam_rot.inverse() * Vector3::z();
        ups.push(f.world_from_cam.rotation * up_in_cam);
        yaw_pairs.push((world_from_cam_rot, f.world_from_cam.rotation));
    }
    if !any {
        return Err(MetricError::NoOverlap { max_dt_ms: dt as f64 / 1e6 });
    }
    if ups.len() < opts.min_attitudes {
        return Err(MetricError::TooFewAttitudes { n: ups.len(), needed: opts.min_attitudes });
    }
    let up_in_map = robust_mean_direction(&ups);
    let tilt_rms_deg = (ups.iter().map(|u| u.angle(&up_in_map).powi(2)).sum::<f64>() / ups.len() as f64).sqrt().to_degrees();
    // The rotation taking the map's up to z, then the heading that best matches the AHRS's.
    let level = UnitQuaternion::rotation_between(&up_in_map, &Vector3::z()).unwrap_or_else(|| UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI));
    let (mut sin_sum, mut cos_sum) = (0.0, 0.0);
    for (world_from_cam_rot, map_from_cam_rot) in &yaw_pairs {
        let fwd_world = world_from_cam_rot * Vector3::z();
        let fwd_level = level * (map_from_cam_rot * Vector3::z());
        let (a, b) = (fwd_world.y.atan2(fwd_world.x), fwd_level.y.atan2(fwd_level.x));
        let horizontal = fwd_world.xy().norm().min(fwd_level.xy().norm());
        sin_sum += horizontal * (a - b).sin();
        cos_sum += horizontal * (a - b).cos();
    }
    let heading = if sin_sum == 0.0 && cos_sum == 0.0 { 0.0 } else { sin_sum.atan2(cos_sum) };
    let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), heading) * level;

    // Scale from pressure depth: -depth = s * height + c.
    let mut heights = Vec::new();
    let mut horizontal = Vec::new();
    let mut depths = Vec::new();
    let e1 = up_in_map.cross(&if up_in_map.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
    let e2 = up_in_map.cross(&e1);
    for f in frames {
        if let Some(d) = interpolate(nav, f.t_ns, dt, |s| s.depth_m, lerp_f64) {
            let p = f.world_from_cam.translation.vector;
            heights.push(up_in_map.dot(&p));
            horizontal.push([e1.dot(&p), e2.dot(&p)]);
            depths.push(d);
        }
    }
    let from_depth = depth_line(&heights, &horizontal, &depths, opts);

    // Scale from altitude: the metric altitude over the map-unit range to the seabed below
    // the camera: where the down ray is in a keyframe's view, read there; otherwise (a camera
    // looking ahead) from the seabed heights every keyframe saw, under where the camera later
    // (or earlier) was.
    let mut alt_ratios = Vec::new();
    for k in keyframes {
        let Some(alt_m) = interpolate(nav, k.t_ns, dt, |s| s.altitude_m, lerp_f64) else { continue };
        if let Some(alt_map) = altitude_along_ray(k, &up_in_map) {
            alt_ratios.push(alt_m / alt_map);
        }
    }
    if alt_ratios.len() < opts.min_altitudes {
        let grid = SeabedGrid::build(keyframes, &up_in_map);
        for f in frames {
            let Some(alt_m) = interpolate(nav, f.t_ns, dt, |s| s.altitude_m, lerp_f64) else { continue };
            if let Some(alt_map) = grid.as_ref().and_then(|g| g.altitude_of(&f.world_from_cam.translation.vector)) {
                alt_ratios.push(alt_m / alt_map);
            }
        }
    }
    let certain = |e: &ScaleEstimate| e.sigma <= opts.max_relative_sigma * e.metres_per_unit;
    let from_altitude = (alt_ratios.len() >= opts.min_altitudes).then(|| robust_ratio(&alt_ratios)).flatten().filter(certain);

    // Scale from DVL velocity: metric displacement between consecutive keyframes' times
    // (velocity rotated into the map by each frame's tracked attitude) over the map's.
    let mut vel_ratios = Vec::new();
    let mut k0: Option<usize> = None;
    let is_key = |t: Timestamp| keyframes.iter().any(|k| k.t_ns == t);
    let mut metric_disp = Vector3::zeros();
    let mut covered = true;
    for (i, f) in frames.iter().enumerate() {
        if let Some(start) = k0 {
            let prev = &frames[i - 1];
            let step_s = (f.t_ns.t_ns() - prev.t_ns.t_ns()) as f64 * 1e-9;
            match interpolate(nav, prev.t_ns, dt, |s| s.vel_cam_mps, |a, b, w| a + (b - a) * w) {
                Some(v) => metric_disp += prev.world_from_cam.rotation * v * step_s,
                None => covered = false,
            }
            if is_key(f.t_ns) {
                let map_disp = f.world_from_cam.translation.vector - frames[start].world_from_cam.translation.vector;
                if covered && map_disp.norm() > 0.0 && metric_disp.norm() > 0.0 {
                    // Both in the map's orientation: project the metric one on the map's.
                    vel_ratios.push(metric_disp.dot(&map_disp) / map_disp.norm_squared());
                }
                k0 = Some(i);
                metric_disp = Vector3::zeros();
                covered = true;
            }
        } else if is_key(f.t_ns) {
            k0 = Some(i);
        }
    }
    let from_velocity = (vel_ratios.len() >= opts.min_velocity_pairs).then(|| robust_ratio(&vel_ratios)).flatten().filter(certain);

    let estimates: Vec<ScaleEstimate> = [from_depth, from_altitude, from_velocity].into_iter().flatten().filter(|e| e.metres_per_unit.is_finite() && e.metres_per_unit > 0.0).collect();
    if estimates.is_empty() {
        return Err(MetricError::NoScale {
            why: format!(
                "{} frames with depth (heights span {:.3} map units), {} keyframes with altitude, {} keyframe pairs with velocity",
                depths.len(),
                span(&heights),
                alt_ratios.len(),
                vel_ratios.len()
            ),
        });
    }
    let scale = combine(&estimates);
    let s = scale.metres_per_unit;
    // Origin: the first frame's x, y; z such that the camera is at -depth.
    let first = frames.first().map(|f| rot * f.world_from_cam.translation.vector * s).unwrap_or_default();
    let mut z_off: Vec<f64> = heights.iter().zip(&depths).map(|(h, d)| -d - s * h).collect();
    let tz = if z_off.is_empty() { -first.z } else { median(&mut z_off) };
    // Check: the aligned heights against the depth sensor.
    // A long path's tilt error leaks into its heights (1 % of its extent is half a degree).
    if !heights.is_empty() {
        let rms_m = (heights.iter().zip(&depths).map(|(h, d)| (s * h + tz + d).powi(2)).sum::<f64>() / heights.len() as f64).sqrt();
        let (lo, hi) = horizontal.iter().fold(([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]), |(lo, hi), a| ([lo[0].min(a[0]), lo[1].min(a[1])], [hi[0].max(a[0]), hi[1].max(a[1])]));
        let extent_m = s * ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2)).sqrt();
        let limit_m = opts.max_depth_rms_m.max(0.01 * extent_m);
        if !(rms_m <= limit_m) {
            return Err(MetricError::Inconsistent { rms_m, frames: heights.len(), limit_m });
        }
    }
    let metric_from_map = Sim3::from_parts(Translation3::new(-first.x, -first.y, tz), rot, s);
    Ok(MetricAlignment { metric_from_map, scale, from_depth, from_altitude, from_velocity, attitudes: ups.len(), tilt_rms_deg })
}

fn span(v: &[f64]) -> f64 {
    let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| (lo.min(x), hi.max(x)));
    if v.is_empty() {
        0.0
    } else {
        hi - lo
    }
}

/// The unit direction closest to all of `dirs` after the ones more than 3 robust sigmas off
/// the first mean are dropped.
fn robust_mean_direction(dirs: &[Vector3<f64>]) -> Vector3<f64> {
    let mean = dirs.iter().sum::<Vector3<f64>>().normalize();
    let angles: Vec<f64> = dirs.iter().map(|d| d.angle(&mean)).collect();
    let (m, s) = median_mad(&angles);
    let limit = m + 3.0 * s.max(1e-3);
    let kept: Vector3<f64> = dirs.iter().zip(&angles).filter(|(_, a)| **a <= limit).map(|(d, _)| *d).sum();
    if kept.norm() > 0.0 {
        kept.normalize()
    } else {
        mean
    }
}

/// The depth line `-depth = s * height + b . horizontal + c` by least squares, with outliers
/// (beyond 3 robust sigmas of the residual) dropped. `b` takes up the error of the up
/// direction (the AHRS's tilt noise and the tracker's rotation error make a long horizontal
/// path leak into the heights: half a degree over 10 m is 9 cm, as much as a terrain-following
/// survey's depth changes); it is held near 0 by a prior of `tilt_prior_deg` on the tilt,
/// so a straight path does not make it free. `None` when the scale is too uncertain.
fn depth_line(heights: &[f64], horizontal: &[[f64; 2]], depths: &[f64], opts: &MetricOptions) -> Option<ScaleEstimate> {
    let n = heights.len();
    if n < 5 {
        return None;
    }
    // Centred, so the intercept drops out of the normal equations.
    let solve = |keep: &[bool], s_prior: f64, sigma_d: f64| -> Option<(nalgebra::Vector3<f64>, f64, nalgebra::Matrix3<f64>, usize)> {
        let m = keep.iter().filter(|k| **k).count();
        if m < 5 {
            return None;
        }
        let mean = |f: &dyn Fn(usize) -> f64| (0..n).filter(|&i| keep[i]).map(f).sum::<f64>() / m as f64;
        let (mh, mx, my, md) = (mean(&|i| heights[i]), mean(&|i| horizontal[i][0]), mean(&|i| horizontal[i][1]), mean(&|i| -depths[i]));
        let mut ata = nalgebra::Matrix3::<f64>::zeros();
        let mut atb = Vector3::<f64>::zeros();
        for i in (0..n).filter(|&i| keep[i]) {
            let a = Vector3::new(heights[i] - mh, horizontal[i][0] - mx, horizontal[i][1] - my);
            ata += a * a.transpose();
            atb += a * (-depths[i] - md);
        }
        // The tilt prior: b ~ N(0, (s * tilt)^2) against noise sigma_d per sample.
        let tilt = opts.tilt_prior_deg.to_radians();
        let lambda = (sigma_d / (s_prior.abs().max(1e-9) * tilt)).powi(2);
        ata[(1, 1)] += lambda;
        ata[(2, 2)] += lambda;
        let inv = ata.try_inverse()?;
        let x = inv * atb;
        let c = md - x.x * mh - x.y * mx - x.z * my;
        Some((x, c, inv, m))
    };
    let residuals = |x: &Vector3<f64>, c: f64| -> Vec<f64> { (0..n).map(|i| -depths[i] - (x.x * heights[i] + x.y * horizontal[i][0] + x.z * horizontal[i][1] + c)).collect() };
    let mut keep = vec![true; n];
    // First without the tilt terms mattering (a loose prior), then with the prior at the
    // scale found, dropping outliers.
    let (mut x, mut c, mut inv, mut m) = solve(&keep, 1e6, opts.depth_sigma_floor_m)?;
    let mut sigma_d = opts.depth_sigma_floor_m;
    for _ in 0..3 {
        let res = residuals(&x, c);
        let (_, sig) = median_mad(&res);
        sigma_d = sig.max(opts.depth_sigma_floor_m);
        keep = res.iter().map(|r| r.abs() <= 3.0 * sigma_d).collect();
        (x, c, inv, m) = solve(&keep, x.x, sigma_d)?;
    }
    let s = x.x;
    let kept_residuals: Vec<f64> = residuals(&x, c).into_iter().zip(&keep).filter(|(_, k)| **k).map(|(r, _)| r).collect();
    let formal = sigma_d * inv[(0, 0)].sqrt() * correlation_inflation(&kept_residuals);
    // The tracker's height errors drift along the path under the sensor's white noise, where
    // the residuals' correlation does not show them: the spread of the slope with each tenth
    // of the path left out (a delete-a-block jackknife) does.
    let blocks = JACKKNIFE_BLOCKS.min(m / 5);
    let mut slopes = Vec::with_capacity(blocks);
    if blocks >= 3 {
        let kept_index: Vec<usize> = (0..n).filter(|&i| keep[i]).collect();
        for b in 0..blocks {
            let (lo, hi) = (b * kept_index.len() / blocks, (b + 1) * kept_index.len() / blocks);
            let mut k2 = keep.clone();
            for &i in &kept_index[lo..hi] {
                k2[i] = false;
            }
            if let Some((xb, ..)) = solve(&k2, s, sigma_d) {
                slopes.push(xb.x);
            }
        }
    }
    let jackknife = if slopes.len() >= 3 {
        let k = slopes.len() as f64;
        let mean = slopes.iter().sum::<f64>() / k;
        ((k - 1.0) / k * slopes.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>()).sqrt()
    } else {
        0.0
    };
    let sigma = formal.max(jackknife);
    if !(s > 0.0) || sigma > opts.max_relative_sigma * s {
        return None;
    }
    Some(ScaleEstimate { metres_per_unit: s, sigma, used: m, rejected: n - m })
}

/// The seabed's range below keyframe `k` along gravity, in map units, where the down ray meets
/// the image: the inverse depth there (median of a 5x5 window).
fn altitude_along_ray(k: &MapKeyframe<'_>, up_in_map: &Vector3<f64>) -> Option<f64> {
    let down_in_cam = k.world_from_cam.rotation.inverse() * (-up_in_map);
    let (w, h) = (k.inv_depth.width, k.inv_depth.height);
    if down_in_cam.z <= 0.2 {
        return None;
    }
    let uv = k.camera.project(&down_in_cam)?;
    let (u, v) = (uv.x.round() as i64, uv.y.round() as i64);
    if !(u >= 2 && v >= 2 && u + 2 < w as i64 && v + 2 < h as i64) {
        return None;
    }
    let mut vals = Vec::with_capacity(25);
    for y in v - 2..=v + 2 {
        for x in u - 2..=u + 2 {
            let d = k.inv_depth.data[y as usize * w + x as usize];
            if d > 0.0 && d.is_finite() {
                vals.push(1.0 / d as f64);
            }
        }
    }
    if vals.len() < 13 {
        return None;
    }
    // The ray's point at optical depth z lies z / cos(angle) along the (unit) ray.
    Some(median(&mut vals) / down_in_cam.z)
}

/// The seabed's height (along gravity, map units) on a horizontal grid, from the points of
/// every keyframe's depth; cells a few hundredths of the typical viewing range wide.
struct SeabedGrid {
    level: Rotation3<f64>,
    cell: f64,
    heights: std::collections::HashMap<(i64, i64), Vec<f64>>,
}

impl SeabedGrid {
    fn build(keyframes: &[MapKeyframe<'_>], up_in_map: &Vector3<f64>) -> Option<SeabedGrid> {
        let level = Rotation3::rotation_between(up_in_map, &Vector3::z())?;
        let mut points = Vec::new();
        let mut ranges = Vec::new();
        for k in keyframes {
            let (w, h) = (k.inv_depth.width, k.inv_depth.height);
            let step = (w.max(h) / 64).max(1);
            for y in (0..h).step_by(step) {
                for x in (0..w).step_by(step) {
                    let d = k.inv_depth.data[y * w + x];
                    if !(d > 0.0 && d.is_finite()) {
                        continue;
                    }
                    let Some(ray) = k.camera.unproject(&nalgebra::Vector2::new(x as f64, y as f64)) else { continue };
                    let p_cam = ray * (1.0 / d as f64 / ray.z);
                    ranges.push(p_cam.norm());
                    points.push(level * (k.world_from_cam * nalgebra::Point3::from(p_cam)).coords);
                }
            }
        }
        if points.len() < 100 {
            return None;
        }
        let cell = 0.03 * median(&mut ranges);
        let mut heights: std::collections::HashMap<(i64, i64), Vec<f64>> = std::collections::HashMap::new();
        for p in &points {
            heights.entry(((p.x / cell).floor() as i64, (p.y / cell).floor() as i64)).or_default().push(p.z);
        }
        Some(SeabedGrid { level, cell, heights })
    }

    /// The camera at `p_in_map` over the seabed below it (map units), where the grid saw it.
    fn altitude_of(&self, p_in_map: &Vector3<f64>) -> Option<f64> {
        let q = self.level * p_in_map;
        let cell = self.heights.get(&((q.x / self.cell).floor() as i64, (q.y / self.cell).floor() as i64))?;
        if cell.len() < 3 {
            return None;
        }
        let mut z = cell.clone();
        let alt = q.z - median(&mut z);
        (alt > 0.0).then_some(alt)
    }
}

/// Inverse-variance mean of the estimates that agree with the most certain one (within 3 sigma
/// of their combined difference); the rest are left out.
fn combine(estimates: &[ScaleEstimate]) -> ScaleEstimate {
    let best = estimates.iter().copied().min_by(|a, b| (a.sigma / a.metres_per_unit).total_cmp(&(b.sigma / b.metres_per_unit))).expect("at least one estimate");
    let agree: Vec<&ScaleEstimate> = estimates
        .iter()
        .filter(|e| (e.metres_per_unit - best.metres_per_unit).abs() <= 3.0 * (e.sigma * e.sigma + best.sigma * best.sigma).sqrt().max(1e-9 * best.metres_per_unit))
        .collect();
    let (mut sw, mut swx) = (0.0, 0.0);
    for e in &agree {
        let w = 1.0 / (e.sigma * e.sigma).max(1e-18);
        sw += w;
        swx += w * e.metres_per_unit;
    }
    ScaleEstimate {
        metres_per_unit: swx / sw,
        sigma: (1.0 / sw).sqrt(),
        used: agree.iter().map(|e| e.used).sum(),
        rejected: estimates.len() - agree.len(),
    }
}

/// `pose` in the metric world.
pub fn metric_pose(align: &MetricAlignment, world_from_cam: &Se3) -> Se3 {
    duv_core::pose::sim3_apply_to_pose(&align.metric_from_map, world_from_cam)
}

/// The displacement (world frame of the AHRS, metres) the navigation gives between `from` and
/// `to`: each DVL velocity (camera frame, over ground) rotated into the world by the attitude
/// at its time (interpolated within `max_dt_ns`), integrated as a piecewise-linear function of
/// time; before the first and after the last sample it is held. An error when the velocity
/// with an attitude leaves a hole longer than `max_hole_ns` in `[from, to]`, its ends
/// included: dead reckoning through a DVL dropout is a guess, not an estimate.
///
/// Its error grows with the distance (the DVL's scale error, about 1 %) and with the AHRS's
/// heading error over the gap; the world frame is the AHRS's, which is the one
/// [`estimate_metric_alignment`] turns a map segment's heading to.
pub fn dead_reckon(nav: &[NavSample], from: Timestamp, to: Timestamp, max_dt_ns: i64, max_hole_ns: i64) -> Result<Vector3<f64>, MetricError> {
    let (t0, t1) = (from.t_ns(), to.t_ns());
    if t1 < t0 {
        return Err(MetricError::Backwards { from_s: from.as_secs_f64(), to_s: to.as_secs_f64() });
    }
    let lo = nav.partition_point(|s| s.t_ns.t_ns() < t0.saturating_sub(max_hole_ns));
    let hi = nav.partition_point(|s| s.t_ns.t_ns() <= t1.saturating_add(max_hole_ns));
    // (t, world velocity) of every sample near the gap that has both.
    let points: Vec<(i64, Vector3<f64>)> = nav[lo..hi]
        .iter()
        .filter_map(|s| {
            let v = s.vel_cam_mps?;
            let q = s.world_from_cam_rot.or_else(|| interpolate(nav, s.t_ns, max_dt_ns, |n| n.world_from_cam_rot, |a, b, w| a.slerp(&b, w)))?;
            Some((s.t_ns.t_ns(), q * v))
        })
        .collect();
    let hole = |at: i64, len: i64| MetricError::Hole { at_s: at as f64 * 1e-9, hole_s: len as f64 * 1e-9, max_hole_s: max_hole_ns as f64 * 1e-9 };
    let (Some(first), Some(last)) = (points.first(), points.last()) else {
        return Err(hole(t0, t1 - t0 + 2 * max_hole_ns));
    };
    if first.0 - t0 > max_hole_ns {
        return Err(hole(t0, first.0 - t0));
    }
    if t1 - last.0 > max_hole_ns {
        return Err(hole(last.0, t1 - last.0));
    }
    if let Some(w) = points.windows(2).find(|w| w[1].0 - w[0].0 > max_hole_ns && w[1].0 > t0 && w[0].0 < t1) {
        return Err(hole(w[0].0, w[1].0 - w[0].0));
    }
    // The velocity at t: linear between samples, held beyond them.
    let at = |t: i64| -> Vector3<f64> {
        let i = points.partition_point(|p| p.0 <= t);
        match (i.checked_sub(1).map(|j| points[j]), points.get(i)) {
            (Some(a), Some(b)) if b.0 > a.0 => a.1 + (b.1 - a.1) * ((t - a.0) as f64 / (b.0 - a.0) as f64),
            (Some(a), _) => a.1,
            (None, Some(b)) => b.1,
            (None, None) => Vector3::zeros(),
        }
    };
    // Trapezoids between the knots inside [t0, t1] (exact for a piecewise-linear velocity).
    let mut knots: Vec<i64> = std::iter::once(t0).chain(points.iter().map(|p| p.0).filter(|&t| t > t0 && t < t1)).chain(std::iter::once(t1)).collect();
    knots.dedup();
    Ok(knots.windows(2).map(|w| (at(w[0]) + at(w[1])) * (0.5 * (w[1] - w[0]) as f64 * 1e-9)).sum())
}
