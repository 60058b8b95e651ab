//! Rigid and similarity transforms. Names say which frame maps to which:
//! `p_in_world = world_from_cam * p_in_cam`. The TUM convention (`tx ty tz qx qy qz qw`,
//! Hamilton quaternion, camera-to-world) is the text form everywhere.

use nalgebra::{Isometry3, Matrix3, Quaternion, Similarity3, Translation3, UnitQuaternion, Vector3, Vector6};

/// A rigid transform in SE(3), e.g. `world_from_cam`.
pub type Se3 = Isometry3<f64>;
/// A similarity transform in Sim(3) (rotation, translation, positive scale).
pub type Sim3 = Similarity3<f64>;

/// Why seven numbers are not a pose.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("pose has a non-finite value: {values:?}")]
    NonFinite { values: [f64; 7] },
    #[error("quaternion has norm {norm}, expected close to 1")]
    BadQuaternion { norm: f64 },
}

/// Builds a pose from TUM order `[tx, ty, tz, qx, qy, qz, qw]`. Quaternions within 1% of unit
/// norm are normalised (files carry 4-7 decimals); anything further off is an error.
pub fn se3_from_tum(v: [f64; 7]) -> Result<Se3, PoseError> {
    if !v.iter().all(|x| x.is_finite()) {
        return Err(PoseError::NonFinite { values: v });
    }
    let q = Quaternion::new(v[6], v[3], v[4], v[5]);
    let norm = q.norm();
    if (norm - 1.0).abs() > 1e-2 {
        return Err(PoseError::BadQuaternion { norm });
    }
    Ok(Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), UnitQuaternion::from_quaternion(q)))
}

/// TUM order `[tx, ty, tz, qx, qy, qz, qw]`, with `qw >= 0` for a canonical text form.
pub fn se3_to_tum(pose: &Se3) -> [f64; 7] {
    let t = pose.translation.vector;
    let mut q = *pose.rotation.quaternion();
    if q.w < 0.0 {
        q = -q;
    }
    [t.x, t.y, t.z, q.i, q.j, q.k, q.w]
}

/// The cross-product matrix `[v]x`.
pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// SO(3) exponential of a rotation vector.
pub fn so3_exp(omega: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_scaled_axis(*omega)
}

/// SE(3) exponential of a twist `xi = [v; omega]` (translation part first).
pub fn se3_exp(xi: &Vector6<f64>) -> Se3 {
    let v = xi.fixed_rows::<3>(0).into_owned();
    let omega = xi.fixed_rows::<3>(3).into_owned();
    let theta = omega.norm();
    let w = hat(&omega);
    let (a, b) = if theta < 1e-8 {
        (0.5 - theta * theta / 24.0, 1.0 / 6.0 - theta * theta / 120.0)
    } else {
        ((1.0 - theta.cos()) / (theta * theta), (theta - theta.sin()) / (theta * theta * theta))
    };
    let left_jacobian = Matrix3::identity() + a * w + b * w * w;
    Isometry3::from_parts(Translation3::from(left_jacobian * v), so3_exp(&omega))
}

/// SE(3) logarithm, inverse of [`se3_exp`] for rotation angles below pi.
pub fn se3_log(pose: &Se3) -> Vector6<f64> {
    let omega = pose.rotation.scaled_axis();
    let theta = omega.norm();
    let w = hat(&omega);
    let c = if theta < 1e-8 {
        1.0 / 12.0 + theta * theta / 720.0
    } else {
        (1.0 - theta * theta.sin() / (2.0 * (1.0 - theta.cos()))) / (theta * theta)
    };
    // V^-1 = I - w/2 + c w^2 with c = (1 - theta sin(theta) / (2 (1 - cos theta))) / theta^2.
    let v_inv = Matrix3::identity() - 0.5 * w + c * w * w;
    let v = v_inv * pose.translation.vector;
    Vector6::new(v.x, v.y, v.z, omega.x, omega.y, omega.z)
}

/// Sim(3) from a scale and a rigid transform: `x -> s * R x + t`.
pub fn sim3_from_parts(scale: f64, rigid: &Se3) -> Sim3 {
    Similarity3::from_isometry(*rigid, scale)
}

/// Applies a Sim(3) alignment to a camera pose: the rotation and the position move, the
/// camera keeps unit scale (`world'_from_cam = S * world_from_cam` with the scale taken out).
pub fn sim3_apply_to_pose(align: &Sim3, world_from_cam: &Se3) -> Se3 {
    let p = align.transform_point(&world_from_cam.translation.vector.into());
    Isometry3::from_parts(Translation3::from(p.coords), align.isometry.rotation * world_from_cam.rotation)
}

/// Angle of a rotation in radians, in [0, pi].
pub fn rotation_angle(q: &UnitQuaternion<f64>) -> f64 {
    q.angle()
}


/// A pose with its tracking state, as the tracker reported it live: what the log and the live
/// view take from tracking (here, so that neither stage imports the other).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseRecord {
    pub t_ns: crate::Timestamp,
    pub seq: u64,
    pub world_from_cam: Se3,
    /// Short state name (`tracking`, `lost (black frame)`, ...).
    pub state: &'static str,
    /// Whether the pose was measured (tracking or relocalised).
    pub tracked: bool,
    /// The keyframe the pose was measured against.
    pub keyframe: Option<u64>,
    /// Id of the keyframe this frame became.
    pub new_keyframe: Option<u64>,
    pub loop_closed: bool,
    /// The map segment the pose is in (a new one after a loss; 0 is the dive's first).
    pub segment: u32,
    /// Why the frame has no measured pose yet (`init_low_confidence`, `init_small_flow`,
    /// `init_pose_failed`, `init_keyframe`), with the measured value and its threshold.
    pub why: Option<&'static str>,
    pub value: Option<f64>,
    pub limit: Option<f64>,
}

/// The JSON schema of the tracking state record (`duv.TrackingState`, [`TrackingStateRef`]).
pub const TRACKING_STATE_SCHEMA: &str = r#"{"title":"duv.TrackingState","type":"object","properties":{"seq":{"type":"integer"},"t_ns":{"type":"integer"},"state":{"type":"string"},"tracked":{"type":"boolean"},"keyframe":{"type":["integer","null"]},"new_keyframe":{"type":["integer","null"]},"loop_closed":{"type":"boolean"},"segment":{"type":"integer"},"why":{"type":"string"},"value":{"type":"number"},"limit":{"type":"number"}}}"#;

/// The tracking state of a [`PoseRecord`] as its JSON record (`duv.TrackingState`: the log's
/// `/slam/state`, the live view's), borrowed.
#[derive(serde::Serialize)]
pub struct TrackingStateRef<'a> {
    seq: u64,
    t_ns: i64,
    state: &'a str,
    tracked: bool,
    keyframe: Option<u64>,
    new_keyframe: Option<u64>,
    loop_closed: bool,
    segment: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    why: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    value: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    limit: Option<f64>,
}

impl PoseRecord {
    /// Its tracking state record (everything but the pose).
    pub fn state_record(&self) -> TrackingStateRef<'_> {
        TrackingStateRef {
            seq: self.seq,
            t_ns: self.t_ns.t_ns(),
            state: self.state,
            tracked: self.tracked,
            keyframe: self.keyframe,
            new_keyframe: self.new_keyframe,
            loop_closed: self.loop_closed,
            segment: self.segment,
            why: self.why,
            value: self.value,
            limit: self.limit,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tum_round_trip_and_sign_canonical() {
        let v = [1.0, -2.0, 3.0, 0.1, -0.2, 0.3, -0.927_361_849_549_570_4];
        let p = se3_from_tum(v).unwrap();
        let back = se3_to_tum(&p);
        assert!(back[6] > 0.0);
        let p2 = se3_from_tum(back).unwrap();
        assert!((p.to_homogeneous() - p2.to_homogeneous()).abs().max() < 1e-12);
        assert!((back[0] - 1.0).abs() < 1e-15);
    }

    #[test]
    fn tum_rejects_nan_and_bad_quaternion() {
        assert!(matches!(se3_from_tum([0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0, 1.0]), Err(PoseError::NonFinite { .. })));
        assert!(matches!(se3_from_tum([0.0; 7]), Err(PoseError::BadQuaternion { .. })));
    }

    #[test]
    fn exp_log_round_trip() {
        for xi in [
            Vector6::new(0.1, -0.2, 0.3, 0.4, -0.5, 0.6),
            Vector6::new(1.0, 2.0, 3.0, 1e-10, 0.0, -1e-10),
            Vector6::new(-0.5, 0.0, 2.0, 0.0, 2.5, 0.0),
        ] {
            let back = se3_log(&se3_exp(&xi));
            assert!((back - xi).norm() < 1e-9, "{xi:?} -> {back:?}");
        }
    }

    #[test]
    fn exp_matches_matrix_exponential_translation() {
        // Pure translation: exp is a translation by v.
        let p = se3_exp(&Vector6::new(1.0, 2.0, 3.0, 0.0, 0.0, 0.0));
        assert!((p.translation.vector - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-15);
        // Pure rotation about z by 90 degrees.
        let r = se3_exp(&Vector6::new(0.0, 0.0, 0.0, 0.0, 0.0, std::f64::consts::FRAC_PI_2));
        let x = r * nalgebra::Point3::new(1.0, 0.0, 0.0);
        assert!((x.coords - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn sim3_alignment_moves_pose() {
        let align = sim3_from_parts(2.0, &Isometry3::translation(1.0, 0.0, 0.0));
        let pose = Isometry3::translation(0.0, 1.0, 0.0);
        let moved = sim3_apply_to_pose(&align, &pose);
        assert!((moved.translation.vector - Vector3::new(1.0, 2.0, 0.0)).norm() < 1e-12);
    }
}
