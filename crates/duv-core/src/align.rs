//! Least-squares alignment of point sets (Umeyama 1991), as evo's
//! `geometry.umeyama_alignment`: the similarity (or rigid transform) `dst ~ s R src + t`.
//! Here because both the evaluation and the pipeline (a resumed run's fallback Sim(3)) use it.

use crate::pose::sim3_from_parts;
use crate::Sim3;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// Why [`umeyama`] found no transform.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{} alignment is degenerate over {points} point pairs: {reason}", if *with_scale { "Sim(3)" } else { "SE(3)" })]
pub struct DegenerateAlignment {
    /// Whether the scale was to be estimated (Sim(3)) or fixed (SE(3)).
    pub with_scale: bool,
    pub points: usize,
    pub reason: String,
}

/// The transform `dst ~ s R src + t` minimising the squared distances (scale fixed to 1 unless
/// `with_scale`). Errors when the sets differ in length, hold non-finite values, or do not fix a
/// rotation (fewer than two non-zero singular values of the cross-covariance, as evo checks).
pub fn umeyama(src: &[Vector3<f64>], dst: &[Vector3<f64>], with_scale: bool) -> Result<Sim3, DegenerateAlignment> {
    let degenerate = |reason: String| DegenerateAlignment { with_scale, points: src.len(), reason };
    if src.len() != dst.len() {
        return Err(degenerate(format!("{} source points but {} target points", src.len(), dst.len())));
    }
    if src.is_empty() {
        return Err(degenerate("no points".into()));
    }
    if !src.iter().chain(dst).all(|p| p.iter().all(|v| v.is_finite())) {
        return Err(degenerate("a point has a non-finite coordinate".into()));
    }
    let n = src.len() as f64;
    let mean_src = src.iter().sum::<Vector3<f64>>() / n;
    let mean_dst = dst.iter().sum::<Vector3<f64>>() / n;
    let var_src = src.iter().map(|p| (p - mean_src).norm_squared()).sum::<f64>() / n;
    let mut cov = Matrix3::zeros();
    for (s, d) in src.iter().zip(dst) {
        cov += (d - mean_dst) * (s - mean_src).transpose();
    }
    cov /= n;
    // Singular values come sorted in decreasing order.
    let svd = cov.svd(true, true);
    let (u, v_t) = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => (u, v_t),
        _ => return Err(degenerate("SVD of the cross-covariance failed".into())),
    };
    let d = svd.singular_values;
    if d.iter().filter(|&&x| x > f64::EPSILON).count() < 2 {
        return Err(degenerate(format!("cross-covariance has rank < 2 (singular values {:.3e}, {:.3e}, {:.3e}): points are collinear or coincide", d[0], d[1], d[2])));
    }
    let mut s = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * v_t;
    let scale = if with_scale {
        let c = (d[0] * s[(0, 0)] + d[1] * s[(1, 1)] + d[2] * s[(2, 2)]) / var_src;
        if !(c.is_finite() && c > 0.0) {
            return Err(degenerate(format!("scale {c} is not positive")));
        }
        c
    } else {
        1.0
    };
    let t = mean_dst - scale * r * mean_src;
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Ok(sim3_from_parts(scale, &Isometry3::from_parts(Translation3::from(t), rotation)))
}

