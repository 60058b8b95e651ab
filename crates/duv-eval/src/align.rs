//! Least-squares alignment of point sets (Umeyama 1991), as evo's
//! `geometry.umeyama_alignment`: the similarity (or rigid transform) `dst ~ s R src + t`.
//! Monocular estimates have no metric scale, so their default is Sim(3).

use super::EvalError;
use duv_core::Sim3;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Which transform aligns the estimate to the ground truth before errors are taken.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    /// Rotation, translation and scale (monocular estimates).
    #[default]
    Sim3,
    /// Rotation and translation.
    Se3,
    /// None: the estimate is taken as it is.
    None,
}

impl Alignment {
    /// Whether the scale is estimated.
    pub fn with_scale(self) -> bool {
        self == Alignment::Sim3
    }
    /// Fewest point pairs that determine the transform (non-collinear points).
    pub fn min_points(self) -> usize {
        match self {
            Alignment::None => 1,
            Alignment::Se3 | Alignment::Sim3 => 3,
        }
    }
}

impl fmt::Display for Alignment {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Alignment::Sim3 => "Sim(3)",
            Alignment::Se3 => "SE(3)",
            Alignment::None => "no",
        })
    }
}

impl FromStr for Alignment {
    type Err = EvalError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "sim3" => Ok(Alignment::Sim3),
            "se3" => Ok(Alignment::Se3),
            "none" => Ok(Alignment::None),
            _ => Err(EvalError::InvalidParameter { name: "alignment", value: s.to_string(), reason: "expected sim3, se3 or none" }),
        }
    }
}

/// The alignment found, in a form for reports: `p_in_gt = scale * R * p_in_est + t`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AlignmentSummary {
    pub method: Alignment,
    /// Scale applied to the estimate (1 unless Sim(3)).
    pub scale: f64,
    /// Rotation as a unit quaternion `[qx, qy, qz, qw]`.
    pub rotation_xyzw: [f64; 4],
    /// Translation in ground-truth units (metres).
    pub translation_m: [f64; 3],
}

impl AlignmentSummary {
    pub fn new(method: Alignment, gt_from_est: &Sim3) -> Self {
        let q = gt_from_est.isometry.rotation.quaternion();
        let t = gt_from_est.isometry.translation.vector;
        AlignmentSummary { method, scale: gt_from_est.scaling(), rotation_xyzw: [q.i, q.j, q.k, q.w], translation_m: [t.x, t.y, t.z] }
    }
}

/// The transform `dst ~ s R src + t` minimising the squared distances (scale fixed to 1 unless
/// `with_scale`): [`duv_core::align::umeyama`] with the error as [`EvalError`].
pub fn umeyama(src: &[Vector3<f64>], dst: &[Vector3<f64>], with_scale: bool) -> Result<Sim3, EvalError> {
    duv_core::align::umeyama(src, dst, with_scale).map_err(|e| EvalError::DegenerateAlignment {
        method: if e.with_scale { Alignment::Sim3 } else { Alignment::Se3 },
        points: e.points,
        reason: e.reason,
    })
}

/// The alignment `gt_from_est` of `method` mapping the estimated positions onto the ground truth.
pub fn align_positions(gt: &[Vector3<f64>], est: &[Vector3<f64>], method: Alignment) -> Result<Sim3, EvalError> {
    match method {
        Alignment::None => Ok(Sim3::identity()),
        Alignment::Se3 => umeyama(est, gt, false),
        Alignment::Sim3 => umeyama(est, gt, true),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::pose::sim3_from_parts;
    use duv_core::rng::Rng;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    fn cloud(n: usize, seed: u64) -> Vec<Vector3<f64>> {
        let mut rng = Rng::new(seed);
        (0..n).map(|_| Vector3::new(rng.range(-2.0, 2.0), rng.range(-1.0, 1.0), rng.range(0.0, 3.0))).collect()
    }

    #[test]
    fn recovers_a_known_similarity_exactly() {
        let src = cloud(50, 1);
        let truth = sim3_from_parts(
            0.37,
            &Isometry3::from_parts(Translation3::new(1.0, -2.0, 0.5), UnitQuaternion::from_euler_angles(0.3, -1.1, 2.5)),
        );
        let dst: Vec<_> = src.iter().map(|p| truth.transform_point(&(*p).into()).coords).collect();
        let found = umeyama(&src, &dst, true).unwrap();
        assert!((found.to_homogeneous() - truth.to_homogeneous()).abs().max() < 1e-12);
        // Without scale: rotation still recovered, scale 1.
        let rigid = umeyama(&src, &dst, false).unwrap();
        assert_eq!(rigid.scaling(), 1.0);
        assert!(rigid.isometry.rotation.angle_to(&truth.isometry.rotation) < 1e-12);
    }

    #[test]
    fn reflection_is_never_returned() {
        // A mirrored target: the best proper rotation, determinant +1.
        let src = cloud(20, 2);
        let dst: Vec<_> = src.iter().map(|p| Vector3::new(-p.x, p.y, p.z)).collect();
        let found = umeyama(&src, &dst, true).unwrap();
        let r = found.isometry.rotation.to_rotation_matrix();
        assert!((r.matrix().determinant() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let line: Vec<_> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(matches!(umeyama(&line, &line, true), Err(EvalError::DegenerateAlignment { .. })));
        let one = vec![Vector3::new(1.0, 2.0, 3.0)];
        assert!(matches!(umeyama(&one, &one, false), Err(EvalError::DegenerateAlignment { .. })));
        let mut bad = cloud(5, 3);
        bad[2].y = f64::NAN;
        assert!(matches!(umeyama(&bad, &cloud(5, 3), true), Err(EvalError::DegenerateAlignment { .. })));
        assert!(matches!(umeyama(&cloud(5, 3), &cloud(4, 3), true), Err(EvalError::DegenerateAlignment { .. })));
        assert!(matches!(umeyama(&[], &[], true), Err(EvalError::DegenerateAlignment { .. })));
        assert_eq!("SE3".parse::<Alignment>().unwrap(), Alignment::Se3);
        assert!("affine".parse::<Alignment>().is_err());
    }
}
