//! The run's clock against the frames' clock, for inputs stamped on arrival (a live autopilot
//! stream): every captured frame gives `arrival - t_ns / speed` (speed: the playback factor of
//! a paced recording, 1 live); the smallest (the frame that waited least between its exposure
//! and the capture thread) is the offset between the clocks.

use duv_core::Timestamp;
use std::sync::atomic::{AtomicI64, Ordering};
use std::time::Instant;

#[derive(Debug)]
pub struct ArrivalClock {
    epoch: Instant,
    /// Frame seconds per run second (the playback factor; 1 for a live source).
    speed: f64,
    run_minus_frame_ns: AtomicI64,
}

impl Default for ArrivalClock {
    fn default() -> Self {
        ArrivalClock { epoch: Instant::now(), speed: 1.0, run_minus_frame_ns: AtomicI64::new(i64::MAX) }
    }
}

impl ArrivalClock {
    pub fn new() -> Self {
        Self::default()
    }

    /// A clock for frames played `speed` times faster than recorded (`--speed`).
    pub fn with_speed(speed: f64) -> Self {
        ArrivalClock { speed, ..Self::default() }
    }

    /// The run's time zero.
    pub fn epoch(&self) -> Instant {
        self.epoch
    }

    /// A frame stamped `t_ns` arrived now.
    pub fn frame_arrived(&self, t_ns: Timestamp) {
        self.frame_arrived_at(t_ns, self.epoch.elapsed().as_nanos() as i64);
    }

    fn frame_arrived_at(&self, t_ns: Timestamp, run_ns: i64) {
        self.run_minus_frame_ns.fetch_min(run_ns - (t_ns.t_ns() as f64 / self.speed) as i64, Ordering::Relaxed);
    }

    /// The frame time of run time `run_ns` (`None` before the first frame).
    pub fn frame_time_ns(&self, run_ns: i64) -> Option<i64> {
        let offset = self.run_minus_frame_ns.load(Ordering::Relaxed);
        (offset != i64::MAX).then(|| ((run_ns - offset) as f64 * self.speed) as i64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_offset_is_the_frame_that_waited_least() {
        let c = ArrivalClock::new();
        assert_eq!(c.frame_time_ns(0), None);
        // Frames at 10 Hz from t = 5 s, arriving 30, 12 and 50 ms late on a run clock started
        // 4.9 s after the frames' zero... i.e. run = t - 4.9 s + delay.
        for (i, delay_ms) in [30i64, 12, 50].into_iter().enumerate() {
            let t = 5_000_000_000 + i as i64 * 100_000_000;
            c.frame_arrived_at(Timestamp::from_ns(t), t - 4_900_000_000 + delay_ms * 1_000_000);
        }
        // A sample that arrived at run time 0.2 s happened 12 ms earlier on the frames' clock.
        assert_eq!(c.frame_time_ns(200_000_000), Some(5_100_000_000 - 12_000_000));
        // Played at half speed: run seconds are half frame seconds.
        let half = ArrivalClock::with_speed(0.5);
        half.frame_arrived_at(Timestamp::from_ns(3_000_000_000), 7_000_000_000);
        half.frame_arrived_at(Timestamp::from_ns(3_100_000_000), 7_200_000_000);
        assert_eq!(half.frame_time_ns(7_400_000_000), Some(3_200_000_000));
    }
}
