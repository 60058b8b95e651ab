//! Summary statistics of an error sequence, the set evo reports (`rmse`, `mean`, `median`,
//! `std` (population), `min`, `max`, `sse`).

use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ErrorStats {
    /// Number of error values.
    pub count: usize,
    pub rmse: f64,
    pub mean: f64,
    /// Middle value; the mean of the two middle values for an even count (as numpy).
    pub median: f64,
    /// Population standard deviation (divides by `count`, as `np.std`).
    pub std: f64,
    pub min: f64,
    pub max: f64,
    /// Sum of squared errors.
    pub sse: f64,
}

impl ErrorStats {
    /// Statistics of `errors`; `None` when it is empty. Non-finite values propagate.
    pub fn from_errors(errors: &[f64]) -> Option<Self> {
        if errors.is_empty() {
            return None;
        }
        let n = errors.len() as f64;
        let sum: f64 = errors.iter().sum();
        let sse: f64 = errors.iter().map(|e| e * e).sum();
        let mean = sum / n;
        let var = errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let mid = sorted.len() / 2;
        let median = if sorted.len() % 2 == 1 { sorted[mid] } else { 0.5 * (sorted[mid - 1] + sorted[mid]) };
        Some(ErrorStats {
            count: errors.len(),
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[sorted.len() - 1],
            sse,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_hand_computed_values() {
        let s = ErrorStats::from_errors(&[3.0, 1.0, 4.0, 2.0]).unwrap();
        assert_eq!(s.count, 4);
        assert_eq!(s.mean, 2.5);
        assert_eq!(s.median, 2.5);
        assert_eq!(s.min, 1.0);
        assert_eq!(s.max, 4.0);
        assert_eq!(s.sse, 30.0);
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15);
        assert_eq!(ErrorStats::from_errors(&[5.0, 1.0, 3.0]).unwrap().median, 3.0);
        assert!(ErrorStats::from_errors(&[]).is_none());
    }
}
