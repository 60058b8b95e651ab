//! What a running dive has done so far, for a progress line on the operator's terminal:
//! counters the stage threads set as they go (relaxed atomics: no lock, no allocation, never
//! waited on) and any other thread reads as a [`ProgressSnapshot`].

use std::sync::atomic::{AtomicU32, AtomicU64, AtomicU8, Ordering};

/// The tracking state names a snapshot reports, by code (0: no frame tracked yet).
const STATES: [&str; 5] = ["starting", "initializing", "tracking", "relocalised", "lost"];

/// Counters of a running dive, shared between the stage threads and whoever shows them.
#[derive(Debug, Default)]
pub struct RunProgress {
    frames_tracked: AtomicU64,
    /// Frames the source will deliver, 0 when not known (a live camera, a replay loop).
    frames_expected: AtomicU64,
    state: AtomicU8,
    segment: AtomicU32,
    keyframes: AtomicU64,
    /// Gaussians in the map plus one (0: no mapping stage reported yet).
    gaussians_plus_one: AtomicU64,
}

/// One reading of [`RunProgress`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProgressSnapshot {
    pub frames_tracked: u64,
    pub frames_expected: Option<u64>,
    /// `starting`, `initializing`, `tracking`, `relocalised` or `lost`.
    pub state: &'static str,
    /// The map segment of the newest pose.
    pub segment: u32,
    /// Keyframes handed to mapping.
    pub keyframes: u64,
    /// Gaussians in the map, `None` without a mapping stage (or before its first report).
    pub gaussians: Option<u64>,
}

impl RunProgress {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn set_frames_expected(&self, frames: Option<u64>) {
        self.frames_expected.store(frames.unwrap_or(0), Ordering::Relaxed);
    }

    /// A frame was tracked into `state` (a [`duv_track::TrackingState`] name: `lost (...)`
    /// counts as `lost`) in map segment `segment`.
    pub fn frame_tracked(&self, state: &str, segment: u32) {
        let code = STATES.iter().position(|s| state.starts_with(s)).unwrap_or(0) as u8;
        self.state.store(code, Ordering::Relaxed);
        self.segment.store(segment, Ordering::Relaxed);
        self.frames_tracked.fetch_add(1, Ordering::Relaxed);
    }

    pub fn keyframe_handed_on(&self) {
        self.keyframes.fetch_add(1, Ordering::Relaxed);
    }

    pub fn set_gaussians(&self, gaussians: usize) {
        self.gaussians_plus_one.store(gaussians as u64 + 1, Ordering::Relaxed);
    }

    pub fn snapshot(&self) -> ProgressSnapshot {
        let expected = self.frames_expected.load(Ordering::Relaxed);
        let gaussians = self.gaussians_plus_one.load(Ordering::Relaxed);
        ProgressSnapshot {
            frames_tracked: self.frames_tracked.load(Ordering::Relaxed),
            frames_expected: (expected > 0).then_some(expected),
            state: STATES[self.state.load(Ordering::Relaxed) as usize % STATES.len()],
            segment: self.segment.load(Ordering::Relaxed),
            keyframes: self.keyframes.load(Ordering::Relaxed),
            gaussians: gaussians.checked_sub(1).filter(|_| gaussians > 0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_snapshot_reads_what_the_stages_set() {
        let p = RunProgress::new();
        let s = p.snapshot();
        assert_eq!((s.frames_tracked, s.frames_expected, s.state, s.keyframes, s.gaussians), (0, None, "starting", 0, None));
        p.set_frames_expected(Some(300));
        p.frame_tracked("initializing", 0);
        p.frame_tracked("tracking", 0);
        p.frame_tracked("lost (not relocalised)", 0);
        p.frame_tracked("tracking", 2);
        p.keyframe_handed_on();
        p.set_gaussians(0);
        let s = p.snapshot();
        assert_eq!((s.frames_tracked, s.frames_expected, s.state, s.segment, s.keyframes, s.gaussians), (4, Some(300), "tracking", 2, 1, Some(0)));
        p.frame_tracked("lost (black frame)", 2);
        p.set_gaussians(12_345);
        let s = p.snapshot();
        assert_eq!((s.state, s.gaussians), ("lost", Some(12_345)));
    }
}
