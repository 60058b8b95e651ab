//! Time-stamp association of two trajectories, as evo's `sync.associate_trajectories` with
//! the `nearest_time` method (evo 1.38): walk the trajectory with fewer poses (the estimate
//! when both have as many), find the nearest stamp in the other, keep the pair when the
//! difference is at most `max_dt`. Poses of the longer trajectory may be used more than once.
//!
//! The decisions are taken on the stamps as f64 seconds, the values evo parses from the same
//! text, with evo's comparisons. Exact integer nanoseconds would be tidier but decide real
//! ties differently: in `fr2_desk` an estimate stamp lies exactly halfway between two
//! ground-truth stamps, and evo's float rounding picks the later one.

use duv_core::{StampedPose, Timestamp};

/// evo's default `max_diff`: 0.01 s.
pub const DEFAULT_MAX_DT_NS: i64 = 10_000_000;

/// Index pairs `(gt_index, est_index)` of poses within `max_dt_ns` of each other, in the order
/// of the shorter trajectory.
pub fn associate(gt: &[StampedPose], est: &[StampedPose], max_dt_ns: i64) -> Vec<(usize, usize)> {
    let gt_stamps: Vec<Timestamp> = gt.iter().map(|p| p.t_ns).collect();
    let est_stamps: Vec<Timestamp> = est.iter().map(|p| p.t_ns).collect();
    associate_stamps(&gt_stamps, &est_stamps, max_dt_ns)
}

/// [`associate`] on bare time stamps.
pub fn associate_stamps(gt: &[Timestamp], est: &[Timestamp], max_dt_ns: i64) -> Vec<(usize, usize)> {
    let est_longer = est.len() > gt.len();
    let (short, long) = if est_longer { (gt, est) } else { (est, gt) };
    // The nearest f64 to the decimal value (what Python's float() of the file's text gives).
    let max_dt_secs = max_dt_ns as f64 / 1e9;
    matching_indices(&secs_f64(short), &secs_f64(long), max_dt_secs)
        .into_iter()
        .map(|(i_short, i_long)| if est_longer { (i_short, i_long) } else { (i_long, i_short) })
        .collect()
}

/// Stamps as the nearest f64 number of seconds (correctly rounded from the exact decimal).
fn secs_f64(stamps: &[Timestamp]) -> Vec<f64> {
    stamps.iter().map(|t| t.to_string().parse::<f64>().unwrap_or_else(|_| t.as_secs_f64())).collect()
}

/// For each stamp of `short`, the nearest stamp of `long` within `max_dt`: pairs
/// `(short_index, long_index)`. With sorted `long`, evo's binary search and tie rules (a tie
/// goes to the earlier stamp; of equal stamps at or before the query, the last one); with
/// unsorted `long`, evo's linear search for the first minimum.
fn matching_indices(short: &[f64], long: &[f64], max_dt: f64) -> Vec<(usize, usize)> {
    let mut out = Vec::with_capacity(short.len());
    if long.is_empty() {
        return out;
    }
    let sorted = long.windows(2).all(|w| w[1] - w[0] >= 0.0);
    for (i, &t) in short.iter().enumerate() {
        if !sorted {
            let mut best = 0;
            for (j, s) in long.iter().enumerate() {
                if (s - t).abs() < (long[best] - t).abs() {
                    best = j;
                }
            }
            if (long[best] - t).abs() <= max_dt {
                out.push((i, best));
            }
            continue;
        }
        if t < long[0] - max_dt || t > long[long.len() - 1] + max_dt {
            continue;
        }
        // First index whose stamp is > t (numpy searchsorted side="right"), clamped.
        let upper = long.partition_point(|&s| s <= t).min(long.len() - 1);
        let diff_upper = long[upper] - t;
        let diff_lower = if upper > 0 { t - long[upper - 1] } else { f64::INFINITY };
        if diff_upper <= max_dt && diff_upper < diff_lower {
            out.push((i, upper));
        } else if diff_lower <= max_dt && diff_lower <= diff_upper {
            out.push((i, upper - 1));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stamps in milliseconds.
    fn ts(v: &[i64]) -> Vec<Timestamp> {
        v.iter().map(|&t| Timestamp(t * 1_000_000)).collect()
    }

    fn assoc(gt: &[Timestamp], est: &[Timestamp], max_dt_ms: i64) -> Vec<(usize, usize)> {
        associate_stamps(gt, est, max_dt_ms * 1_000_000)
    }

    #[test]
    fn nearest_within_max_dt_from_the_shorter_side() {
        let gt = ts(&[0, 10, 20, 30, 40, 50]);
        let est = ts(&[1, 19, 26, 44, 100]);
        // est is shorter: each est stamp finds its nearest gt stamp; 26 -> 30 (4) beats 20 (6);
        // 44 -> 40; 100 is too far.
        assert_eq!(assoc(&gt, &est, 5), vec![(0, 0), (2, 1), (3, 2), (4, 3)]);
        // Ties go to the earlier stamp.
        assert_eq!(assoc(&gt, &ts(&[5, 6]), 5), vec![(0, 0), (1, 1)]);
        // gt shorter: walk gt.
        let est_long = ts(&[0, 2, 4, 6, 8, 10, 12, 14]);
        assert_eq!(assoc(&ts(&[3, 13, 100]), &est_long, 1), vec![(0, 1), (1, 6)]);
        // Stamps before the first and after the last are matched only within max_dt.
        assert_eq!(assoc(&ts(&[10, 20, 30]), &ts(&[-3, 33]), 3), vec![(2, 1)]);
        assert!(assoc(&gt, &[], 5).is_empty());
    }

    #[test]
    fn equal_lengths_walk_the_estimate_and_unsorted_falls_back() {
        // Both length 3: evo walks the second (estimate) trajectory.
        let gt = ts(&[0, 10, 20]);
        let est = ts(&[9, 11, 12]);
        assert_eq!(assoc(&gt, &est, 5), vec![(1, 0), (1, 1), (1, 2)]);
        let unsorted = ts(&[20, 0, 10, 30]);
        assert_eq!(assoc(&unsorted, &ts(&[11, 29]), 2), vec![(2, 0), (3, 1)]);
    }

    #[test]
    fn a_decimal_tie_resolves_as_in_evo() {
        // fr2_desk: 226.310950 lies 1.65 ms from both 226.3093 and 226.3126; in f64 seconds
        // the later one is nearer, and evo pairs it.
        let p = |s: &str| s.parse::<Timestamp>().unwrap();
        let gt = vec![p("1311868226.3065"), p("1311868226.3093"), p("1311868226.3126"), p("1311868226.3160")];
        assert_eq!(associate_stamps(&gt, &[p("1311868226.310950")], DEFAULT_MAX_DT_NS), vec![(2, 0)]);
    }
}
