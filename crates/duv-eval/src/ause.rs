//! Area under the sparsification error curve (AUSE; Ilg et al. 2018, Poggi et al. 2020),
//! the depth-uncertainty metric of the paper's Table 4, here on the mean absolute error.
//!
//! Pixels are removed in order of decreasing uncertainty; after removing the fraction
//! `f = k / N` (k = 0..N-1, the count rounded down) the MAE of the remaining pixels, divided by
//! the MAE of all pixels, is the sparsification curve. The oracle removes by decreasing true
//! error, the best any uncertainty could do. AUSE is the area between the two curves
//! (trapezoids over f in [0, (N-1)/N]); 0 is perfect. A random ordering gives a reference:
//! its curve stays near 1, so its AUSE is about the area above the oracle curve.

use super::EvalError;
use duv_core::rng::Rng;
use duv_core::PlaneF32;
use serde::{Deserialize, Serialize};

/// Most curve points accepted (the curves are stored and plotted).
pub const MAX_STEPS: usize = 100_000;

/// Parameters of the sparsification curves.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuseOptions {
    /// Number of curve points N (removed fractions 0, 1/N, ..., (N-1)/N).
    pub steps: usize,
    /// Seed of the random ordering.
    pub random_seed: u64,
}

impl Default for AuseOptions {
    fn default() -> Self {
        AuseOptions { steps: 100, random_seed: 0x5EED }
    }
}

/// Sparsification curves and their areas.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuseResult {
    /// Pixels used.
    pub count: usize,
    /// Mean absolute error of all pixels (the normalisation), in the errors' unit.
    pub mae: f64,
    /// Area between the estimate's curve and the oracle's.
    pub ause: f64,
    /// Area between the random ordering's curve and the oracle's.
    pub ause_random: f64,
    /// Removed fractions, `k / N`.
    pub fractions: Vec<f64>,
    /// Normalised MAE after removing by decreasing uncertainty.
    pub sparsification: Vec<f64>,
    /// Normalised MAE after removing by decreasing true error.
    pub oracle: Vec<f64>,
    /// Normalised MAE after removing in a seeded random order.
    pub random: Vec<f64>,
}

/// AUSE of `uncertainties` (any monotone measure: variance, standard deviation) as a predictor
/// of `errors` (absolute errors of valid pixels). Errors must be finite and non-negative,
/// uncertainties finite and positive, and not every error zero.
pub fn ause(errors: &[f64], uncertainties: &[f64], opts: &AuseOptions) -> Result<AuseResult, EvalError> {
    if errors.len() != uncertainties.len() {
        return Err(EvalError::AuseLengthMismatch { errors: errors.len(), uncertainties: uncertainties.len() });
    }
    if errors.is_empty() {
        return Err(EvalError::AuseEmpty);
    }
    if opts.steps == 0 || opts.steps > MAX_STEPS {
        return Err(EvalError::InvalidParameter { name: "AUSE steps", value: opts.steps.to_string(), reason: "must be between 1 and 100000" });
    }
    for (index, (&e, &u)) in errors.iter().zip(uncertainties).enumerate() {
        let problem = if !e.is_finite() {
            Some("error is not finite")
        } else if e < 0.0 {
            Some("error is negative (expected an absolute error)")
        } else if !u.is_finite() {
            Some("uncertainty is not finite")
        } else if u <= 0.0 {
            Some("uncertainty is not positive")
        } else {
            None
        };
        if let Some(problem) = problem {
            return Err(EvalError::AuseBadValue { index, error: e, uncertainty: u, problem });
        }
    }
    let n = errors.len();
    let total: f64 = errors.iter().sum();
    if total == 0.0 {
        return Err(EvalError::AuseZeroError);
    }
    let mae = total / n as f64;

    // Orders of removal, first removed first. Stable sorts: ties keep pixel order, so an
    // uncertainty equal to the error reproduces the oracle exactly.
    let mut by_uncertainty: Vec<usize> = (0..n).collect();
    by_uncertainty.sort_by(|&a, &b| uncertainties[b].total_cmp(&uncertainties[a]));
    let mut by_error: Vec<usize> = (0..n).collect();
    by_error.sort_by(|&a, &b| errors[b].total_cmp(&errors[a]));
    let mut shuffled: Vec<usize> = (0..n).collect();
    let mut rng = Rng::new(opts.random_seed);
    for i in (1..n).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        shuffled.swap(i, j);
    }

    let fractions: Vec<f64> = (0..opts.steps).map(|k| k as f64 / opts.steps as f64).collect();
    let sparsification = curve(errors, &by_uncertainty, opts.steps);
    let oracle = curve(errors, &by_error, opts.steps);
    let random = curve(errors, &shuffled, opts.steps);
    let dx = 1.0 / opts.steps as f64;
    Ok(AuseResult {
        count: n,
        mae,
        ause: area_between(&sparsification, &oracle, dx),
        ause_random: area_between(&random, &oracle, dx),
        fractions,
        sparsification,
        oracle,
        random,
    })
}

/// MAE of the pixels left after removing the first `floor(k n / steps)` of `order`, over the
/// MAE of all pixels (summed in the same order, so that the curve starts at exactly 1).
fn curve(errors: &[f64], order: &[usize], steps: usize) -> Vec<f64> {
    let n = order.len();
    // Suffix sums: suffix[i] = sum of the errors of order[i..], summed from the end so that the
    // tail (few pixels, late in the curve) keeps full precision.
    let mut suffix = vec![0.0; n + 1];
    for i in (0..n).rev() {
        suffix[i] = suffix[i + 1] + errors[order[i]];
    }
    let mae_all = suffix[0] / n as f64;
    (0..steps)
        .map(|k| {
            let removed = ((k as u128 * n as u128) / steps as u128) as usize;
            suffix[removed] / (n - removed) as f64 / mae_all
        })
        .collect()
}

/// Trapezoidal area of `a - b` over equally spaced points.
fn area_between(a: &[f64], b: &[f64], dx: f64) -> f64 {
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    d.windows(2).map(|w| 0.5 * (w[0] + w[1]) * dx).sum()
}

/// Valid pixels of a depth map: absolute errors against the ground truth, and the variances.
/// A pixel is valid where the ground truth is finite and positive and the estimate is not 0
/// (no estimate); non-finite estimates or variances there are kept, so [`ause`] rejects them.
pub fn depth_errors(est_depth: &PlaneF32, gt_depth: &PlaneF32, variance: &PlaneF32) -> Result<(Vec<f64>, Vec<f64>), EvalError> {
    for (name, p) in [("estimated depth", est_depth), ("depth variance", variance)] {
        if !p.same_size(gt_depth) {
            return Err(EvalError::ImageSizeMismatch {
                first: name.into(),
                second: "ground-truth depth".into(),
                first_size: [p.width, p.height],
                second_size: [gt_depth.width, gt_depth.height],
            });
        }
    }
    let mut errors = Vec::new();
    let mut uncertainties = Vec::new();
    for ((&g, &e), &v) in gt_depth.data.iter().zip(&est_depth.data).zip(&variance.data) {
        if g.is_finite() && g > 0.0 && e != 0.0 {
            errors.push((e as f64 - g as f64).abs());
            uncertainties.push(v as f64);
        }
    }
    Ok((errors, uncertainties))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn perfect_ordering_gives_exactly_zero() {
        let errors: Vec<f64> = (0..997).map(|i| ((i * 7919) % 1000) as f64 * 0.01).collect();
        // Uncertainty equal to, or any increasing function of, the error.
        for unc in [errors.iter().map(|e| e + 1.0).collect::<Vec<_>>(), errors.iter().map(|e| (e + 0.5).powi(2)).collect()] {
            let r = ause(&errors, &unc, &AuseOptions::default()).unwrap();
            assert_eq!(r.ause, 0.0);
            assert_eq!(r.sparsification, r.oracle);
            assert_eq!(r.oracle[0], 1.0);
        }
    }

    #[test]
    fn reversed_ordering_matches_the_analytic_area() {
        // Errors 1..n, uncertainty highest where the error is lowest. With n a multiple of N
        // the fraction f = k/N removes exactly r = f n pixels. Oracle: errors 1..n-r remain,
        // MAE (n-r+1)/2; reversed: errors r+1..n remain, MAE (n+r+1)/2; over the total MAE
        // (n+1)/2 the gap is 2r/(n+1) = 2 n f/(n+1), linear in f, so the trapezoids are exact:
        // AUSE = 2n/(n+1) * ((N-1)/N)^2 / 2 = n/(n+1) * ((N-1)/N)^2.
        let (n, steps) = (1000usize, 100usize);
        let errors: Vec<f64> = (1..=n).map(|i| i as f64).collect();
        let unc: Vec<f64> = errors.iter().map(|e| 1.0 / e).collect();
        let r = ause(&errors, &unc, &AuseOptions { steps, random_seed: 1 }).unwrap();
        let nf = n as f64;
        let frac = (steps as f64 - 1.0) / steps as f64;
        let expected = nf / (nf + 1.0) * frac * frac;
        assert!((r.ause - expected).abs() < 1e-12, "{} vs {expected}", r.ause);
        assert_eq!(r.fractions.len(), steps);
        assert_eq!(r.fractions[99], 0.99);
    }

    #[test]
    fn random_ordering_is_near_its_expectation() {
        // A random subset's expected MAE is the MAE of all, so the random curve's expected
        // value is 1 and its AUSE is the area above the oracle: half the reversed value.
        let n = 50_000usize;
        let errors: Vec<f64> = (1..=n).map(|i| i as f64).collect();
        let unc = vec![1.0; n];
        let r = ause(&errors, &unc, &AuseOptions { steps: 100, random_seed: 42 }).unwrap();
        let nf = n as f64;
        let expected = 0.5 * nf / (nf + 1.0) * 0.99 * 0.99;
        assert!((r.ause_random - expected).abs() < 0.01, "{} vs {expected}", r.ause_random);
        let mean_random = r.random.iter().sum::<f64>() / r.random.len() as f64;
        assert!((mean_random - 1.0).abs() < 0.01, "{mean_random}");
        // Constant uncertainty keeps pixel order, which here is the reversed oracle.
        assert!((r.ause - 2.0 * expected).abs() < 1e-9);
    }

    #[test]
    fn bad_values_are_rejected() {
        let o = AuseOptions::default();
        let bad = |e: &[f64], u: &[f64]| ause(e, u, &o).unwrap_err();
        assert!(matches!(bad(&[1.0, f64::NAN], &[1.0, 1.0]), EvalError::AuseBadValue { index: 1, .. }));
        assert!(matches!(bad(&[1.0, 2.0], &[1.0, 0.0]), EvalError::AuseBadValue { index: 1, .. }));
        assert!(matches!(bad(&[1.0, 2.0], &[-1.0, 1.0]), EvalError::AuseBadValue { index: 0, .. }));
        assert!(matches!(bad(&[1.0, 2.0], &[f64::NAN, 1.0]), EvalError::AuseBadValue { index: 0, .. }));
        assert!(matches!(bad(&[-1.0], &[1.0]), EvalError::AuseBadValue { .. }));
        assert!(matches!(bad(&[1.0], &[1.0, 2.0]), EvalError::AuseLengthMismatch { .. }));
        assert!(matches!(bad(&[], &[]), EvalError::AuseEmpty));
        assert!(matches!(bad(&[0.0, 0.0], &[1.0, 2.0]), EvalError::AuseZeroError));
        assert!(ause(&[1.0], &[1.0], &AuseOptions { steps: 0, random_seed: 0 }).is_err());
    }

    #[test]
    fn depth_errors_keep_valid_pixels() {
        let gt = PlaneF32::from_vec(3, 1, vec![2.0, 0.0, 3.0]).unwrap();
        let est = PlaneF32::from_vec(3, 1, vec![2.5, 1.0, 0.0]).unwrap();
        let var = PlaneF32::from_vec(3, 1, vec![0.1, 0.2, 0.3]).unwrap();
        let (e, u) = depth_errors(&est, &gt, &var).unwrap();
        assert_eq!(e, vec![0.5]);
        assert!((u[0] - 0.1).abs() < 1e-7);
        let wrong = PlaneF32::new(2, 1);
        assert!(matches!(depth_errors(&wrong, &gt, &var), Err(EvalError::ImageSizeMismatch { .. })));
    }
}
