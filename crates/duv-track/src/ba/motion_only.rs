//! Motion-only BA: the pose of one frame (typically a non-keyframe) against fixed keyframes
//! with fixed inverse depths, so that every frame gets a pose. Same residual, robust weights,
//! damping and perturbation convention as the window solve; only the frame's 6 dofs move.
//! Fixed-size (stack) linear algebra: allocation-free.

use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};

use super::linearize::{d_uv_d_inv_depth, huber_cost, huber_weight, predict, relative, reproject_ray};
use super::solve::{damping_after_accept, damping_after_reject, Termination};
use super::{BaConfig, BaError, Intrinsics};
use duv_core::pose::se3_exp;
use duv_core::{Image, PinholeCamera, PlaneF32, Se3};

/// One fixed keyframe seen from the frame: for every keyframe pixel, where it lands in the
/// frame (flow-corrected target) and how much to trust each coordinate.
#[derive(Clone, Copy, Debug)]
pub struct MotionOnlyObservation<'a> {
    /// Pose of the (fixed) keyframe.
    pub world_from_keyframe: Se3,
    /// The keyframe's (fixed) inverse depth, 1/m, at the camera's resolution.
    pub inv_depth: &'a PlaneF32,
    /// Target position of each keyframe pixel in the frame, low-res pixels (x, y).
    pub target_xy: &'a Image<f32, 2>,
    /// Confidences `(w_x, w_y) >= 0` of the targets (diagonal inverse covariance).
    pub weight_xy: &'a Image<f32, 2>,
    /// Variance of the keyframe's inverse depth, (1/m)^2, at the camera's resolution (`None`:
    /// the depth is taken as exact). The fixed depth's error enters every residual: each
    /// pixel's weights become `w / (1 + w j^2 var / s0)`, `j` the pixel's image motion per
    /// unit of inverse depth at the initial pose and `s0` = `variance_of_unit_weight`, so a
    /// pixel whose depth no keyframe measurement supports stops pulling the pose. An infinite
    /// or `f32::MAX` variance (unknown depth) gives the pixel no weight.
    pub inv_depth_variance: Option<&'a PlaneF32>,
    /// The variance a weight of 1 stands for, in the units of `inv_depth_variance` and
    /// squared pixels (the window BA's a posteriori variance of unit weight when the variance
    /// was scaled by it; 1 when the weights are inverse pixel variances).
    pub variance_of_unit_weight: f32,
}

/// Summary of a motion-only solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MotionOnlyReport {
    pub iterations: usize,
    pub accepted: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub termination: Termination,
    /// Covariance of the frame pose (inverse of the undamped 6x6 Hessian at the estimate),
    /// right-perturbation tangent space `[v; omega]`.
    pub covariance: Matrix6<f64>,
}

/// Refines `world_from_frame` (initial guess in, estimate out) by damped Gauss-Newton
/// against fixed keyframes. Uses `config`'s iteration, Huber, damping and tolerance fields
/// (`fixed_poses` and the depth fields do not apply). Measurements are checked first; a bad
/// one is an error naming the observation's index (in the `edge` or `keyframe` field) and
/// the pixel. A final Hessian that cannot be inverted (too few measurements) is
/// [`BaError::SingularSystem`], and `world_from_frame` is then left unchanged.
pub fn solve_motion_only(camera: &PinholeCamera, observations: &[MotionOnlyObservation<'_>], world_from_frame: &mut Se3, config: &BaConfig) -> Result<MotionOnlyReport, BaError> {
    let _span = tracing::debug_span!("track.ba.motion_only", observations = observations.len()).entered();
    config.validate()?;
    let intr = Intrinsics::from_camera(camera)?;
    validate(&intr, observations)?;
    let finite_pose = world_from_frame.translation.vector.iter().chain(world_from_frame.rotation.coords.iter()).all(|v| v.is_finite());
    if !finite_pose {
        return Err(BaError::NonFiniteFramePose);
    }
    let mut pose = *world_from_frame;
    // Depth uncertainty is propagated at the initial pose, so the weights stay fixed while the
    // pose moves (weights that follow the pose would reward moves that inflate them).
    let initial = *world_from_frame;
    let (mut h, mut b, mut cost) = normal_equations(&intr, observations, &initial, &pose, config);
    if h.diagonal().iter().all(|v| *v == 0.0) {
        return Err(BaError::NoMeasurements);
    }
    let initial_cost = cost;
    let mut lambda = config.initial_damping;
    let mut report = MotionOnlyReport { iterations: 0, accepted: 0, initial_cost, final_cost: cost, termination: Termination::MaxIterations, covariance: Matrix6::zeros() };
    while report.iterations < config.max_iterations {
        report.iterations += 1;
        let mut damped = h;
        for r in 0..6 {
            damped[(r, r)] *= 1.0 + lambda;
        }
        let Some(chol) = damped.cholesky() else {
            lambda = damping_after_reject(lambda, config);
            if lambda > config.max_damping {
                report.termination = Termination::DampingLimit;
                break;
            }
            continue;
        };
        let step = chol.solve(&b);
        if step.iter().all(|v| v.abs() < config.step_tolerance) {
            report.termination = Termination::Converged;
            break;
        }
        let mut trial = pose * se3_exp(&step);
        trial.rotation.renormalize();
        let trial_cost = cost_at(&intr, observations, &initial, &trial, config);
        if trial_cost.is_finite() && trial_cost < cost {
            let decrease = (cost - trial_cost) / cost.max(f64::MIN_POSITIVE);
            pose = trial;
            report.accepted += 1;
            lambda = damping_after_accept(lambda, config);
            (h, b, cost) = normal_equations(&intr, observations, &initial, &pose, config);
            if decrease < config.cost_tolerance {
                report.termination = Termination::Converged;
                break;
            }
        } else {
            lambda = damping_after_reject(lambda, config);
            if lambda > config.max_damping {
                report.termination = Termination::DampingLimit;
                break;
            }
        }
    }
    report.final_cost = cost;
    report.covariance = h.try_inverse().ok_or(BaError::SingularSystem { dim: 6, pivot: 0, damping: 0.0 })?;
    *world_from_frame = pose;
    Ok(report)
}

fn validate(intr: &Intrinsics, observations: &[MotionOnlyObservation<'_>]) -> Result<(), BaError> {
    if observations.is_empty() {
        return Err(BaError::NoMeasurements);
    }
    let (w, hgt) = (intr.width, intr.height);
    for (e, o) in observations.iter().enumerate() {
        let t = &o.world_from_keyframe;
        if !t.translation.vector.iter().chain(t.rotation.coords.iter()).all(|v| v.is_finite()) {
            return Err(BaError::NonFinitePose { keyframe: e });
        }
        let d = o.inv_depth;
        if d.width != w || d.height != hgt || d.data.len() != w * hgt {
            return Err(BaError::DepthSizeMismatch { keyframe: e, width: d.width, height: d.height, expected_width: w, expected_height: hgt });
        }
        if let Some(v) = o.inv_depth_variance {
            if v.width != w || v.height != hgt || v.data.len() != w * hgt {
                return Err(BaError::VarianceSizeMismatch { keyframe: e, width: v.width, height: v.height, expected_width: w, expected_height: hgt });
            }
            if let Some(pixel) = v.data.iter().position(|x| x.is_nan() || *x < 0.0) {
                return Err(BaError::BadVariance { keyframe: e, pixel, value: v.data[pixel] });
            }
            if !(o.variance_of_unit_weight.is_finite() && o.variance_of_unit_weight > 0.0) {
                return Err(BaError::BadVarianceOfUnitWeight { keyframe: e, value: o.variance_of_unit_weight });
            }
        }
        if let Some(pixel) = d.data.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(BaError::BadInverseDepth { keyframe: e, pixel, value: d.data[pixel] });
        }
        for m in [o.target_xy, o.weight_xy] {
            if m.width != w || m.height != hgt || m.data.len() != 2 * w * hgt {
                return Err(BaError::MeasurementSizeMismatch { edge: e, width: m.width, height: m.height, expected_width: w, expected_height: hgt });
            }
        }
        for (pixel, (t, wt)) in o.target_xy.data.chunks_exact(2).zip(o.weight_xy.data.chunks_exact(2)).enumerate() {
            if !(t[0].is_finite() && t[1].is_finite()) {
                return Err(BaError::NonFiniteTarget { edge: e, pixel, x: t[0], y: t[1] });
            }
            if !(wt[0].is_finite() && wt[1].is_finite() && wt[0] >= 0.0 && wt[1] >= 0.0) {
                return Err(BaError::BadWeight { edge: e, pixel, wx: wt[0], wy: wt[1] });
            }
        }
    }
    Ok(())
}

/// The weights of pixel `p` of `o`, deflated by its depth variance (see
/// [`MotionOnlyObservation::inv_depth_variance`]) with the depth Jacobian at the initial
/// relative pose `(rot0, t0)`.
#[inline]
fn pixel_weights(intr: &Intrinsics, o: &MotionOnlyObservation<'_>, p: usize, rot0: &Matrix3<f64>, t0: &Vector3<f64>) -> (f64, f64) {
    let (wx, wy) = (o.weight_xy.data[2 * p] as f64, o.weight_xy.data[2 * p + 1] as f64);
    let Some(variance) = o.inv_depth_variance else { return (wx, wy) };
    if wx == 0.0 && wy == 0.0 {
        return (0.0, 0.0);
    }
    let var = variance.data[p];
    if !(var.is_finite() && var < f32::MAX) {
        return (0.0, 0.0);
    }
    let Some(j) = d_uv_d_inv_depth(intr, intr.ray(p), o.inv_depth.data[p] as f64, rot0, t0) else { return (wx, wy) };
    let v = var as f64 / o.variance_of_unit_weight as f64;
    (wx / (1.0 + wx * j.x * j.x * v), wy / (1.0 + wy * j.y * j.y * v))
}

/// `H = sum J^T W J`, `b = sum J^T W r` for the frame pose (`J = d uv / d xi_frame`), and the
/// cost; weights deflated by the depth variance at the `initial` frame pose.
fn normal_equations(intr: &Intrinsics, observations: &[MotionOnlyObservation<'_>], initial: &Se3, world_from_frame: &Se3, config: &BaConfig) -> (Matrix6<f64>, Vector6<f64>, f64) {
    let (mut h, mut b, mut cost) = (Matrix6::zeros(), Vector6::zeros(), 0.0);
    let k = config.huber_threshold;
    for o in observations {
        let (rot, t) = relative(&o.world_from_keyframe, world_from_frame);
        let (rot0, t0) = relative(&o.world_from_keyframe, initial);
        for p in 0..intr.width * intr.height {
            let (wx, wy) = pixel_weights(intr, o, p, &rot0, &t0);
            if wx == 0.0 && wy == 0.0 {
                continue;
            }
            let Some(rp) = reproject_ray(intr, intr.ray(p), o.inv_depth.data[p] as f64, &rot, &t) else { continue };
            let (rx, ry) = (o.target_xy.data[2 * p] as f64 - rp.uv.x, o.target_xy.data[2 * p + 1] as f64 - rp.uv.y);
            let s = (wx * rx * rx + wy * ry * ry).sqrt();
            cost += huber_cost(s, k);
            let rw = huber_weight(s, k);
            let j0: Vector6<f64> = rp.d_uv_d_pose_j.row(0).transpose();
            let j1: Vector6<f64> = rp.d_uv_d_pose_j.row(1).transpose();
            h.ger(rw * wx, &j0, &j0, 1.0);
            h.ger(rw * wy, &j1, &j1, 1.0);
            b += j0 * (rw * wx * rx) + j1 * (rw * wy * ry);
        }
    }
    (h, b, cost)
}

fn cost_at(intr: &Intrinsics, observations: &[MotionOnlyObservation<'_>], initial: &Se3, world_from_frame: &Se3, config: &BaConfig) -> f64 {
    let k = config.huber_threshold;
    let mut cost = 0.0;
    for o in observations {
        let (rot, t) = relative(&o.world_from_keyframe, world_from_frame);
        let (rot0, t0) = relative(&o.world_from_keyframe, initial);
        for p in 0..intr.width * intr.height {
            let (wx, wy) = pixel_weights(intr, o, p, &rot0, &t0);
            if wx == 0.0 && wy == 0.0 {
                continue;
            }
            let Some(uv) = predict(intr, intr.ray(p), o.inv_depth.data[p] as f64, &rot, &t) else { continue };
            let (rx, ry) = (o.target_xy.data[2 * p] as f64 - uv[0], o.target_xy.data[2 * p + 1] as f64 - uv[1]);
            cost += huber_cost((wx * rx * rx + wy * ry * ry).sqrt(), k);
        }
    }
    cost
}

