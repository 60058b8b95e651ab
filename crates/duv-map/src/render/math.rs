//! Scalar arithmetic shared by the f32 pipeline and the f64 reference: the per-Gaussian and
//! per-pixel maths is written once over [`Real`] (the crate's one scalar trait, also the
//! medium's and the losses') and instantiated for both; 3x3 / 2x3 matrix helpers on plain
//! arrays, the layout a WGSL kernel would use.

pub use crate::real::Real;


/// Row-major 3x3 matrix.
pub type Mat3<T> = [[T; 3]; 3];

#[inline(always)]
pub fn mat3_mul<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> Mat3<T> {
    let mut out = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    out
}

#[inline(always)]
pub fn mat3_transpose<T: Real>(a: &Mat3<T>) -> Mat3<T> {
    [[a[0][0], a[1][0], a[2][0]], [a[0][1], a[1][1], a[2][1]], [a[0][2], a[1][2], a[2][2]]]
}

/// `a * b^T`.
#[inline(always)]
pub fn mat3_mul_bt<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> Mat3<T> {
    mat3_mul(a, &mat3_transpose(b))
}

/// `a^T * b`.
#[inline(always)]
pub fn mat3_mul_at<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> Mat3<T> {
    mat3_mul(&mat3_transpose(a), b)
}

#[inline(always)]
pub fn mat3_vec<T: Real>(a: &Mat3<T>, v: &[T; 3]) -> [T; 3] {
    [
        a[0][0] * v[0] + a[0][1] * v[1] + a[0][2] * v[2],
        a[1][0] * v[0] + a[1][1] * v[1] + a[1][2] * v[2],
        a[2][0] * v[0] + a[2][1] * v[1] + a[2][2] * v[2],
    ]
}

/// `a^T v`.
#[inline(always)]
pub fn mat3_t_vec<T: Real>(a: &Mat3<T>, v: &[T; 3]) -> [T; 3] {
    [
        a[0][0] * v[0] + a[1][0] * v[1] + a[2][0] * v[2],
        a[0][1] * v[0] + a[1][1] * v[1] + a[2][1] * v[2],
        a[0][2] * v[0] + a[1][2] * v[1] + a[2][2] * v[2],
    ]
}

/// Rotation matrix of a unit quaternion `(w, x, y, z)` (Hamilton convention).
#[inline(always)]
pub fn quat_to_mat3<T: Real>(q: &[T; 4]) -> Mat3<T> {
    let (w, x, y, z) = (q[0], q[1], q[2], q[3]);
    let one = T::ONE;
    let two = T::from_f64(2.0);
    [
        [one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y)],
        [two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x)],
        [two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y)],
    ]
}

/// Gradient of a loss with respect to the unit quaternion `q`, given its gradient `g` with
/// respect to the rotation matrix `quat_to_mat3(q)` (treating the nine entries as free).
#[inline(always)]
pub fn quat_to_mat3_backward<T: Real>(q: &[T; 4], g: &Mat3<T>) -> [T; 4] {
    let (w, x, y, z) = (q[0], q[1], q[2], q[3]);
    let two = T::from_f64(2.0);
    let dw = -z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1];
    let dx = y * g[0][1] + z * g[0][2] + y * g[1][0] - two * x * g[1][1] - w * g[1][2] + z * g[2][0] + w * g[2][1] - two * x * g[2][2];
    let dy = -two * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] - w * g[2][0] + z * g[2][1] - two * y * g[2][2];
    let dz = -two * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - two * z * g[1][1] + y * g[1][2] + x * g[2][0] + y * g[2][1];
    [two * dw, two * dx, two * dy, two * dz]
}

/// Logistic sigmoid, written so neither branch overflows.
#[inline(always)]
pub fn sigmoid<T: Real>(x: T) -> T {
    if x >= T::ZERO {
        T::ONE / (T::ONE + (-x).exp())
    } else {
        let e = x.exp();
        e / (T::ONE + e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_matrix_backward_matches_central_differences() {
        let q = [0.8f64, -0.3, 0.4, 0.33];
        let g = [[0.3, -1.2, 0.5], [0.7, 0.1, -0.4], [-0.9, 0.2, 0.6]];
        let analytic = quat_to_mat3_backward(&q, &g);
        let loss = |q: &[f64; 4]| {
            let r = quat_to_mat3(q);
            (0..3).flat_map(|i| (0..3).map(move |j| (i, j))).map(|(i, j)| r[i][j] * g[i][j]).sum::<f64>()
        };
        for k in 0..4 {
            let h = 1e-6;
            let (mut a, mut b) = (q, q);
            a[k] += h;
            b[k] -= h;
            let num = (loss(&a) - loss(&b)) / (2.0 * h);
            assert!((num - analytic[k]).abs() < 1e-8, "{k}: {num} vs {}", analytic[k]);
        }
    }

    #[test]
    fn sigmoid_is_stable() {
        assert_eq!(sigmoid(-1000.0f32), 0.0);
        assert_eq!(sigmoid(1000.0f32), 1.0);
        assert!((sigmoid(0.3f64) - 1.0 / (1.0 + (-0.3f64).exp())).abs() < 1e-15);
    }
}
