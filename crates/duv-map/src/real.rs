//! The scalar type of the CPU references: `f32` in the runtime (what the GPU kernels store and
//! compute with), `f64` for the finite-difference gradient checks (house habit 4). Every
//! forward and backward pass of [`super::medium`] and [`super::loss`] is written once,
//! generic over [`Real`], so the check exercises the same code the runtime runs.

use std::fmt::{Debug, Display};
use std::iter::Sum;
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Sub, SubAssign};

/// A floating-point scalar: `f32` or `f64`.
pub trait Real:
    Copy
    + Default
    + PartialOrd
    + Debug
    + Display
    + Send
    + Sync
    + 'static
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + DivAssign
    + Sum
    + serde::Serialize
    + serde::de::DeserializeOwned
{
    const ZERO: Self;
    const ONE: Self;
    fn from_f64(v: f64) -> Self;
    fn to_f64(self) -> f64;
    fn exp(self) -> Self;
    fn ln(self) -> Self;
    fn ln_1p(self) -> Self;
    fn sqrt(self) -> Self;
    fn abs(self) -> Self;
    fn sin(self) -> Self;
    fn cos(self) -> Self;
    fn max(self, other: Self) -> Self;
    fn min(self, other: Self) -> Self;
    fn is_finite(self) -> bool;
    /// `1` for positive, `-1` for negative, `0` for zero (unlike `f32::signum`).
    fn sign(self) -> Self;
}

macro_rules! impl_real {
    ($t:ty) => {
        impl Real for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            #[inline(always)]
            fn from_f64(v: f64) -> Self {
                v as $t
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn exp(self) -> Self {
                <$t>::exp(self)
            }
            #[inline(always)]
            fn ln(self) -> Self {
                <$t>::ln(self)
            }
            #[inline(always)]
            fn ln_1p(self) -> Self {
                <$t>::ln_1p(self)
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline(always)]
            fn abs(self) -> Self {
                <$t>::abs(self)
            }
            #[inline(always)]
            fn sin(self) -> Self {
                <$t>::sin(self)
            }
            #[inline(always)]
            fn cos(self) -> Self {
                <$t>::cos(self)
            }
            #[inline(always)]
            fn max(self, other: Self) -> Self {
                <$t>::max(self, other)
            }
            #[inline(always)]
            fn min(self, other: Self) -> Self {
                <$t>::min(self, other)
            }
            #[inline(always)]
            fn is_finite(self) -> bool {
                <$t>::is_finite(self)
            }
            #[inline(always)]
            fn sign(self) -> Self {
                if self > 0.0 {
                    1.0
                } else if self < 0.0 {
                    -1.0
                } else {
                    0.0
                }
            }
        }
    };
}

impl_real!(f32);
impl_real!(f64);

/// `ln(1 + e^x)`, without overflow for large `x`.
#[inline(always)]
pub fn softplus<T: Real>(x: T) -> T {
    if x > T::from_f64(20.0) {
        x + (-x).exp()
    } else {
        x.exp().ln_1p()
    }
}

/// `1 / (1 + e^-x)`, the derivative of [`softplus`].
#[inline(always)]
pub fn sigmoid<T: Real>(x: T) -> T {
    if x >= T::ZERO {
        T::ONE / (T::ONE + (-x).exp())
    } else {
        let e = x.exp();
        e / (T::ONE + e)
    }
}

/// Inverse of [`softplus`] for `y > 0`: `ln(e^y - 1) = y + ln(1 - e^-y)`.
pub fn softplus_inverse(y: f64) -> f64 {
    y + (-(-y).exp()).ln_1p()
}

/// Inverse of [`sigmoid`] for `y` in (0, 1).
pub fn logit(y: f64) -> f64 {
    (y / (1.0 - y)).ln()
}

/// Dot product with eight partial sums, so that it vectorises (a plain float fold does not).
#[inline(always)]
pub fn dot<T: Real>(a: &[T], b: &[T]) -> T {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [T::ZERO; 8];
    let chunks = n / 8;
    for k in 0..chunks {
        let (ca, cb) = (&a[k * 8..k * 8 + 8], &b[k * 8..k * 8 + 8]);
        for l in 0..8 {
            acc[l] += ca[l] * cb[l];
        }
    }
    let mut tail = T::ZERO;
    for i in chunks * 8..n {
        tail += a[i] * b[i];
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

/// `y += a * x`, elementwise.
#[inline(always)]
pub fn axpy<T: Real>(a: T, x: &[T], y: &mut [T]) {
    for (yi, &xi) in y.iter_mut().zip(x) {
        *yi += a * xi;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn activations_and_inverses() {
        for y in [1e-4, 0.1, 0.35, 2.0, 30.0] {
            assert!((softplus(softplus_inverse(y)) - y).abs() < 1e-12 * y.max(1.0), "{y}");
        }
        for y in [0.01, 0.3, 0.99] {
            assert!((sigmoid(logit(y)) - y).abs() < 1e-14);
        }
        assert_eq!(softplus(1000.0f32), 1000.0);
        assert!(softplus(-1000.0f64) >= 0.0);
        assert_eq!(sigmoid(-1000.0f32), 0.0);
        let a: Vec<f64> = (0..19).map(|i| i as f64 * 0.5).collect();
        let b: Vec<f64> = (0..19).map(|i| 1.0 - i as f64).collect();
        let plain: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
        assert!((dot(&a, &b) - plain).abs() < 1e-12);
    }
}
