//! The live view's bandwidth budget: a token bucket of the board's `live.max_kb_per_s`, with a
//! reserve per class of message so that, as the tether fills, camera frames are dropped first,
//! then point clouds, then keyframe lists, and poses with their state last.
//!
//! The bucket holds at most [`BURST_S`] seconds of the rate and starts full. A camera frame,
//! a cloud or a keyframe list goes only if, after it, the bucket keeps its class's reserve
//! ([`Class::reserve`], a fraction of the bucket); the pose of a frame (pose, transform and
//! state together) goes whenever the bucket is not empty, and may take it below zero by that one
//! message. So the bytes sent over any window of `T` seconds stay within
//! `rate * (T + BURST_S)` plus one pose message, and poses are only dropped when poses alone
//! exceed the rate.

use std::time::Instant;

/// Seconds of the rate the bucket holds (the largest burst).
pub const BURST_S: f64 = 1.0;

/// What a message is, for the budget. Ordered from the last dropped to the first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Class {
    /// A frame's pose, transform and tracking state.
    Pose,
    /// The list of keyframe poses.
    Keyframes,
    /// The Gaussian centres.
    Cloud,
    /// A downscaled camera frame.
    Camera,
}

impl Class {
    pub const ALL: [Class; 4] = [Class::Pose, Class::Keyframes, Class::Cloud, Class::Camera];

    /// The fraction of the bucket a message of this class must leave behind.
    pub fn reserve(self) -> f64 {
        match self {
            Class::Pose => 0.0,
            Class::Keyframes => 0.125,
            Class::Cloud => 0.25,
            Class::Camera => 0.5,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Class::Pose => "pose",
            Class::Keyframes => "keyframes",
            Class::Cloud => "cloud",
            Class::Camera => "camera",
        }
    }
}

/// The token bucket (bytes).
#[derive(Clone, Debug)]
pub struct Budget {
    bytes_per_s: f64,
    capacity: f64,
    tokens: f64,
    last: Option<Instant>,
}

impl Budget {
    /// A full bucket for `bytes_per_s`.
    pub fn new(bytes_per_s: u64) -> Self {
        let bytes_per_s = bytes_per_s.max(1) as f64;
        let capacity = bytes_per_s * BURST_S;
        Budget { bytes_per_s, capacity, tokens: capacity, last: None }
    }

    pub fn capacity_bytes(&self) -> f64 {
        self.capacity
    }

    pub fn bytes_per_s(&self) -> f64 {
        self.bytes_per_s
    }

    /// The largest message of `class` that can ever go (a full bucket less the reserve); for a
    /// pose, the whole bucket.
    pub fn largest(&self, class: Class) -> usize {
        (self.capacity * (1.0 - class.reserve())) as usize
    }

    fn refill(&mut self, now: Instant) {
        if let Some(last) = self.last {
            let dt = now.saturating_duration_since(last).as_secs_f64();
            self.tokens = (self.tokens + dt * self.bytes_per_s).min(self.capacity);
        }
        self.last = Some(now);
    }

    /// Whether a message of `class` could go now if it were small (checked before encoding a
    /// camera frame, to skip the work).
    pub fn may_send(&mut self, class: Class, now: Instant) -> bool {
        self.refill(now);
        match class {
            Class::Pose => self.tokens > 0.0,
            _ => self.tokens > class.reserve() * self.capacity,
        }
    }

    /// Spends `bytes` for a message of `class` at `now` if the budget allows it; `false`: drop it.
    pub fn try_spend(&mut self, class: Class, bytes: usize, now: Instant) -> bool {
        self.refill(now);
        let bytes = bytes as f64;
        let ok = match class {
            Class::Pose => self.tokens > 0.0,
            _ => self.tokens - bytes >= class.reserve() * self.capacity,
        };
        if ok {
            self.tokens -= bytes;
        }
        ok
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Offered 2.6x the rate (poses alone a fifth of it) over 10 s of simulated time: what goes
    /// stays within the bound, every pose goes, and the camera loses most, then clouds, then
    /// keyframes. (A cloud is at most a quarter of the bucket, the gap between its reserve and
    /// the camera's, as `LiveServer` subsamples it.)
    #[test]
    fn drops_camera_first_then_clouds_never_poses_within_the_rate() {
        let rate = 10_000u64;
        let mut b = Budget::new(rate);
        let t0 = Instant::now();
        let sizes = [(Class::Pose, 200usize, 10u32), (Class::Keyframes, 1000, 2), (Class::Cloud, 2000, 1), (Class::Camera, 2000, 10)];
        let mut sent = [0u64; 4];
        let mut offered = [0u64; 4];
        let mut bytes = 0usize;
        // Every 10 ms: each class offers at its rate (per second: `n` messages).
        for step in 0..1000u32 {
            let now = t0 + Duration::from_millis(10 * step as u64);
            for (i, &(class, size, n)) in sizes.iter().enumerate() {
                if step % (100 / n) == 0 {
                    offered[i] += 1;
                    if b.try_spend(class, size, now) {
                        sent[i] += 1;
                        bytes += size;
                    }
                }
            }
        }
        // 10 s at 10 kB/s plus the bucket plus one pose message.
        assert!(bytes as f64 <= rate as f64 * (10.0 + BURST_S) + 200.0, "{bytes} bytes");
        assert!(bytes as f64 >= rate as f64 * 9.0, "the budget goes unused: {bytes} bytes");
        assert_eq!(sent[0], offered[0], "every pose goes (poses alone are 2 kB/s)");
        let frac = |i: usize| sent[i] as f64 / offered[i] as f64;
        assert!(frac(3) < frac(2) && frac(2) <= frac(1) && frac(1) <= 1.0, "camera {:.2}, cloud {:.2}, keyframes {:.2}", frac(3), frac(2), frac(1));
    }

    #[test]
    fn poses_alone_over_the_rate_are_dropped_and_the_debt_is_one_message() {
        let mut b = Budget::new(1000);
        let t0 = Instant::now();
        let mut sent = 0usize;
        for i in 0..100u64 {
            if b.try_spend(Class::Pose, 300, t0 + Duration::from_millis(10 * i)) {
                sent += 300;
            }
        }
        // 1 s of 1 kB/s, the bucket, one message of debt.
        assert!(sent <= 1000 + 1000 + 300, "{sent}");
        assert!(sent >= 1500, "{sent}");
        assert!(b.largest(Class::Camera) == 500 && b.largest(Class::Pose) == 1000);
    }
}
