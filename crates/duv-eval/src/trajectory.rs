//! Trajectory metrics as evo computes them: APE on the translation part (ATE) after
//! alignment, RPE over a delta in frames, and the ground truth's path length.

use super::align::{align_positions, Alignment, AlignmentSummary};
use super::stats::ErrorStats;
use super::sync::associate;
use super::EvalError;
use duv_core::pose::sim3_apply_to_pose;
use duv_core::{Se3, Sim3, StampedPose};
use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Absolute trajectory error: distance between associated positions after alignment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AteResult {
    /// Statistics of the per-pose errors, in metres.
    pub stats_m: ErrorStats,
    /// Per-pose position errors in metres, in association order (not serialised).
    #[serde(skip)]
    pub errors_m: Vec<f64>,
}

/// Relative pose error over `delta_frames` (evo `delta_unit=frames`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RpeResult {
    pub delta_frames: usize,
    /// Every pose starts a pair (`true`), or only every `delta`-th one (evo's default `false`).
    pub all_pairs: bool,
    /// Translation part of the relative error, metres.
    pub translation_m: ErrorStats,
    /// Rotation angle of the relative error, degrees.
    pub rotation_deg: ErrorStats,
}

/// ATE between associated ground-truth poses and the (already aligned) estimate.
pub fn ate(gt: &[Se3], est_aligned: &[Se3]) -> Result<AteResult, EvalError> {
    check_lengths(gt.len(), est_aligned.len())?;
    let errors_m: Vec<f64> =
        gt.iter().zip(est_aligned).map(|(g, e)| (e.translation.vector - g.translation.vector).norm()).collect();
    let stats_m = ErrorStats::from_errors(&errors_m).ok_or(EvalError::InvalidParameter {
        name: "poses",
        value: "0".into(),
        reason: "ATE needs at least one pose pair",
    })?;
    Ok(AteResult { stats_m, errors_m })
}

/// RPE between associated poses: for each pair `(i, i + delta)`,
/// `E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)` with Q the ground truth and P the estimate; the
/// translation norm and rotation angle of E. `all_pairs` starts a pair at every index;
/// otherwise at 0, delta, 2 delta, ... (evo `filter_pairs_by_index`).
pub fn rpe(gt: &[Se3], est: &[Se3], delta_frames: usize, all_pairs: bool) -> Result<RpeResult, EvalError> {
    check_lengths(gt.len(), est.len())?;
    if delta_frames == 0 {
        return Err(EvalError::InvalidParameter { name: "rpe delta", value: "0".into(), reason: "must be at least 1 frame" });
    }
    let n = gt.len();
    let starts: Vec<usize> = if all_pairs { (0..n).collect() } else { (0..n).step_by(delta_frames).collect() };
    let pairs: Vec<(usize, usize)> = starts.into_iter().map(|i| (i, i + delta_frames)).filter(|&(_, j)| j < n).collect();
    if pairs.is_empty() {
        return Err(EvalError::RpeDeltaTooLarge { delta: delta_frames, poses: n });
    }
    let mut trans = Vec::with_capacity(pairs.len());
    let mut rot = Vec::with_capacity(pairs.len());
    for (i, j) in pairs {
        let q_rel = gt[i].inverse() * gt[j];
        let p_rel = est[i].inverse() * est[j];
        let e = q_rel.inverse() * p_rel;
        trans.push(e.translation.vector.norm());
        rot.push(rotation_angle_rad(&e.rotation).to_degrees());
    }
    let stats = |v: &[f64]| ErrorStats::from_errors(v).expect("pairs is not empty");
    Ok(RpeResult { delta_frames, all_pairs, translation_m: stats(&trans), rotation_deg: stats(&rot) })
}

/// Rotation angle in [0, pi], accurate for small angles (atan2 rather than acos).
fn rotation_angle_rad(q: &UnitQuaternion<f64>) -> f64 {
    2.0 * q.imag().norm().atan2(q.scalar().abs())
}

fn check_lengths(gt: usize, est: usize) -> Result<(), EvalError> {
    if gt != est {
        return Err(EvalError::InvalidParameter {
            name: "pose counts",
            value: format!("{gt} ground truth, {est} estimated"),
            reason: "associated trajectories must have as many poses",
        });
    }
    Ok(())
}

/// Length of the polyline through `positions` (evo `arc_len`).
pub fn path_length(positions: &[Vector3<f64>]) -> f64 {
    positions.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

/// Distance travelled up to each point, starting at 0 (evo `accumulated_distances`).
pub fn accumulated_distances(positions: &[Vector3<f64>]) -> Vec<f64> {
    let mut out = Vec::with_capacity(positions.len());
    let mut d = 0.0;
    for (i, p) in positions.iter().enumerate() {
        if i > 0 {
            d += (p - positions[i - 1]).norm();
        }
        out.push(d);
    }
    out
}

/// How to compare two trajectories.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryOptions {
    /// Largest time-stamp difference of an associated pair, nanoseconds (evo `max_diff`).
    pub max_dt_ns: i64,
    pub alignment: Alignment,
    /// RPE delta in frames; 0 skips RPE.
    pub rpe_delta_frames: usize,
    /// RPE pairs start at every pose (`true`) or every `delta`-th pose.
    pub rpe_all_pairs: bool,
}

impl Default for TrajectoryOptions {
    fn default() -> Self {
        TrajectoryOptions { max_dt_ns: super::sync::DEFAULT_MAX_DT_NS, alignment: Alignment::Sim3, rpe_delta_frames: 1, rpe_all_pairs: true }
    }
}

/// The serialisable summary of a trajectory comparison.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrajectoryReport {
    pub gt_poses: usize,
    pub est_poses: usize,
    /// Associated pose pairs (the poses every metric uses).
    pub associated: usize,
    pub max_dt_secs: f64,
    /// Largest time-stamp difference among the associated pairs.
    pub largest_pair_dt_secs: f64,
    /// Time from the first to the last associated ground-truth pose.
    pub evaluated_span_secs: f64,
    pub alignment: AlignmentSummary,
    pub ate: AteResult,
    pub rpe: Option<RpeResult>,
    /// Length of the full-rate ground-truth path over the evaluated span.
    pub gt_path_length_m: f64,
    /// Length of the whole ground-truth file's path.
    pub gt_path_length_total_m: f64,
    /// ATE RMSE as a percentage of `gt_path_length_m`; absent when the path has no length.
    pub ate_rmse_percent_of_path: Option<f64>,
}

/// A trajectory comparison: the summary and the data its figures are drawn from.
#[derive(Clone, Debug)]
pub struct TrajectoryEvaluation {
    pub report: TrajectoryReport,
    /// `gt_from_est` applied to the estimate.
    pub gt_from_est: Sim3,
    /// Associated ground-truth positions.
    pub gt_positions: Vec<Vector3<f64>>,
    /// Associated estimated positions after alignment.
    pub est_positions_aligned: Vec<Vector3<f64>>,
    /// Full-rate ground-truth positions over the evaluated span.
    pub gt_path_positions: Vec<Vector3<f64>>,
    /// Distance travelled along the full-rate ground truth (from the first associated pose) at
    /// each associated pose.
    pub distance_along_m: Vec<f64>,
}

/// Associates, aligns and measures `est` against `gt`. `gt_name` and `est_name` name the
/// inputs in errors (file names, or labels for in-memory data).
pub fn evaluate_trajectory(
    gt: &[StampedPose],
    est: &[StampedPose],
    opts: &TrajectoryOptions,
    gt_name: &str,
    est_name: &str,
) -> Result<TrajectoryEvaluation, EvalError> {
    if opts.max_dt_ns < 0 {
        return Err(EvalError::InvalidParameter { name: "max dt", value: format!("{} ns", opts.max_dt_ns), reason: "must not be negative" });
    }
    for (poses, name) in [(gt, gt_name), (est, est_name)] {
        if poses.is_empty() {
            return Err(EvalError::EmptyTrajectory { name: name.to_string() });
        }
    }
    let pairs = associate(gt, est, opts.max_dt_ns);
    let needed = opts.alignment.min_points().max(if opts.rpe_delta_frames > 0 { 2 } else { 1 });
    if pairs.len() < needed {
        return Err(EvalError::TooFewPairs {
            gt: gt_name.to_string(),
            est: est_name.to_string(),
            max_dt_secs: opts.max_dt_ns as f64 * 1e-9,
            found: pairs.len(),
            needed,
        });
    }
    let gt_poses: Vec<Se3> = pairs.iter().map(|&(i, _)| gt[i].world_from_cam).collect();
    let est_poses: Vec<Se3> = pairs.iter().map(|&(_, j)| est[j].world_from_cam).collect();
    let gt_positions: Vec<Vector3<f64>> = gt_poses.iter().map(|p| p.translation.vector).collect();
    let est_positions: Vec<Vector3<f64>> = est_poses.iter().map(|p| p.translation.vector).collect();
    let gt_from_est = align_positions(&gt_positions, &est_positions, opts.alignment)?;
    let est_aligned: Vec<Se3> = est_poses.iter().map(|p| sim3_apply_to_pose(&gt_from_est, p)).collect();
    let est_positions_aligned: Vec<Vector3<f64>> = est_aligned.iter().map(|p| p.translation.vector).collect();

    let ate_result = ate(&gt_poses, &est_aligned)?;
    let rpe_result = if opts.rpe_delta_frames > 0 {
        Some(rpe(&gt_poses, &est_aligned, opts.rpe_delta_frames, opts.rpe_all_pairs)?)
    } else {
        None
    };

    let first_gt = pairs.iter().map(|p| p.0).min().unwrap_or(0);
    let last_gt = pairs.iter().map(|p| p.0).max().unwrap_or(0);
    let gt_path_positions: Vec<Vector3<f64>> = gt[first_gt..=last_gt].iter().map(|p| p.world_from_cam.translation.vector).collect();
    let all_gt: Vec<Vector3<f64>> = gt.iter().map(|p| p.world_from_cam.translation.vector).collect();
    let gt_path_length_m = path_length(&gt_path_positions);
    let largest_pair_dt_secs = pairs
        .iter()
        .map(|&(i, j)| (gt[i].t_ns.t_ns() - est[j].t_ns.t_ns()).unsigned_abs())
        .max()
        .unwrap_or(0) as f64
        * 1e-9;
    let report = TrajectoryReport {
        gt_poses: gt.len(),
        est_poses: est.len(),
        associated: pairs.len(),
        max_dt_secs: opts.max_dt_ns as f64 * 1e-9,
        largest_pair_dt_secs,
        evaluated_span_secs: gt[last_gt].t_ns.secs_since(gt[first_gt].t_ns),
        alignment: AlignmentSummary::new(opts.alignment, &gt_from_est),
        ate_rmse_percent_of_path: (gt_path_length_m > 0.0).then(|| 100.0 * ate_result.stats_m.rmse / gt_path_length_m),
        ate: ate_result,
        rpe: rpe_result,
        gt_path_length_m,
        gt_path_length_total_m: path_length(&all_gt),
    };
    // Distance along the full-rate ground truth, so that sparse (keyframe) estimates are
    // placed where the camera really was, not along the chords between keyframes.
    let along_full = accumulated_distances(&gt_path_positions);
    let distance_along_m = pairs.iter().map(|&(i, _)| along_full[i - first_gt]).collect();
    Ok(TrajectoryEvaluation {
        report,
        gt_from_est,
        distance_along_m,
        gt_positions,
        est_positions_aligned,
        gt_path_positions,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::pose::{se3_exp, sim3_from_parts};
    use duv_core::Timestamp;
    use nalgebra::{Isometry3, Translation3, Vector6};

    fn helix(n: usize) -> Vec<StampedPose> {
        (0..n)
            .map(|i| {
                let a = i as f64 * 0.1;
                let xi = Vector6::new(a.cos(), a.sin(), 0.05 * a, 0.1 * a, -0.05 * a, 0.2 * a);
                StampedPose { t_ns: Timestamp(i as i64 * 33_000_000), world_from_cam: se3_exp(&xi) }
            })
            .collect()
    }

    #[test]
    fn a_similar_copy_has_zero_error_after_sim3_alignment() {
        let gt = helix(60);
        let s = sim3_from_parts(0.4, &Isometry3::from_parts(Translation3::new(3.0, -1.0, 2.0), UnitQuaternion::from_euler_angles(0.2, 0.9, -1.3)));
        // The estimate lives in another frame at another scale, stamps off by 2 ms.
        let est: Vec<StampedPose> = gt
            .iter()
            .map(|p| StampedPose { t_ns: p.t_ns.offset_ns(2_000_000), world_from_cam: sim3_apply_to_pose(&s, &p.world_from_cam) })
            .collect();
        let ev = evaluate_trajectory(&gt, &est, &TrajectoryOptions::default(), "gt", "est").unwrap();
        let r = &ev.report;
        assert_eq!(r.associated, 60);
        assert!(r.ate.stats_m.max < 1e-9, "{:?}", r.ate.stats_m);
        let rpe = r.rpe.as_ref().unwrap();
        assert!(rpe.translation_m.max < 1e-9 && rpe.rotation_deg.max < 1e-6, "{rpe:?}");
        assert!((r.alignment.scale - 1.0 / 0.4).abs() < 1e-9);
        assert!((r.largest_pair_dt_secs - 0.002).abs() < 1e-12);
        // SE(3) cannot undo the scale: a clear error remains.
        let opts = TrajectoryOptions { alignment: Alignment::Se3, ..Default::default() };
        assert!(evaluate_trajectory(&gt, &est, &opts, "gt", "est").unwrap().report.ate.stats_m.rmse > 0.1);
    }

    #[test]
    fn rpe_pairs_follow_evo() {
        // A constant translation error on one pose shows up in the two pairs touching it.
        let gt: Vec<Se3> = (0..7).map(|i| Isometry3::translation(i as f64, 0.0, 0.0)).collect();
        let mut est = gt.clone();
        est[3] = Isometry3::translation(3.0, 0.5, 0.0);
        let all = rpe(&gt, &est, 1, true).unwrap();
        assert_eq!(all.translation_m.count, 6);
        assert!((all.translation_m.sse - 0.5).abs() < 1e-12);
        let every_second = rpe(&gt, &est, 2, false).unwrap();
        assert_eq!(every_second.translation_m.count, 3); // (0,2) (2,4) (4,6)
        assert!(matches!(rpe(&gt, &est, 7, true), Err(EvalError::RpeDeltaTooLarge { delta: 7, poses: 7 })));
        assert!(matches!(rpe(&gt, &est[..3], 1, true), Err(EvalError::InvalidParameter { .. })));
    }

    #[test]
    fn too_few_pairs_names_both_inputs() {
        let gt = helix(10);
        let est: Vec<StampedPose> = gt.iter().map(|p| StampedPose { t_ns: p.t_ns.offset_ns(20_000_000), ..*p }).collect();
        let e = evaluate_trajectory(&gt, &est, &TrajectoryOptions::default(), "gt.txt", "est.txt").unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, EvalError::TooFewPairs { found: 0, needed: 3, .. }), "{msg}");
        assert!(msg.contains("gt.txt") && msg.contains("est.txt") && msg.contains("0.01 s"), "{msg}");
        assert!(matches!(evaluate_trajectory(&gt, &[], &TrajectoryOptions::default(), "gt", "est"), Err(EvalError::EmptyTrajectory { .. })));
    }

    #[test]
    fn path_length_and_distances() {
        let pts = vec![Vector3::new(0.0, 0.0, 0.0), Vector3::new(3.0, 4.0, 0.0), Vector3::new(3.0, 4.0, 2.0)];
        assert_eq!(path_length(&pts), 7.0);
        assert_eq!(accumulated_distances(&pts), vec![0.0, 5.0, 7.0]);
    }
}
