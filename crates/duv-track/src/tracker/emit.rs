//! Keyframes handed on once their depth is final. A keyframe's depth keeps changing while it
//! is in the window BA; after `lag` newer keyframes were inserted it has been through that
//! many window solves and is handed on: [`Tracker::next_final_keyframe`] writes its pose, its
//! camera and its full-resolution inverse depth and variance into a [`Keyframe`] the caller
//! owns (a pooled slot), so nothing downstream reaches into the keyframe store. The tracker
//! keeps no colour image; the caller fills `image` (and may replace `t_ns` with its frame's).
//! Only map segment 0's keyframes are handed on; another segment's is skipped when due
//! ([`Tracker::keyframes_of_other_segments`]).
//!
//! Off until [`Tracker::emit_keyframes_after`] is called: a tracker used alone (benches,
//! tests) keeps no queue. The queue is allocated with the tracker ([`TrackerCapacity`]'s
//! `max_keyframes` entries); a caller that never takes keyframes loses the oldest ids, counted.

use super::*;
use duv_core::Keyframe;
use std::collections::VecDeque;

/// The ids of inserted keyframes waiting for `lag` newer ones, oldest first.
pub(super) struct Emission {
    lag: Option<usize>,
    waiting: VecDeque<u64>,
    capacity: usize,
    overflowed: u64,
    /// Due keyframes not handed on because they were of a segment other than 0.
    skipped_other_segment: u64,
}

impl Emission {
    pub(super) fn new(capacity: usize) -> Self {
        Emission { lag: None, waiting: VecDeque::with_capacity(capacity + 1), capacity: capacity.max(1), overflowed: 0, skipped_other_segment: 0 }
    }

    /// Keyframe `id` was inserted.
    pub(super) fn inserted(&mut self, id: u64) {
        if self.lag.is_none() {
            return;
        }
        if self.waiting.len() >= self.capacity {
            self.waiting.pop_front();
            self.overflowed += 1;
            tracing::warn!("keyframe emission: {} waiting keyframes, the oldest is dropped (nobody takes them)", self.capacity);
        }
        self.waiting.push_back(id);
    }

    /// Keeps the waiting ids `keep` accepts.
    pub(super) fn retain(&mut self, keep: impl Fn(u64) -> bool) {
        self.waiting.retain(|&id| keep(id));
    }
}

impl Tracker {
    /// Hands keyframes on once `lag` newer keyframes were inserted after them
    /// ([`Tracker::next_final_keyframe`]). Keyframes inserted before the call are not queued.
    pub fn emit_keyframes_after(&mut self, lag: usize) {
        self.emit.lag = Some(lag);
    }

    /// Queues keyframes the tracker already holds (seeded on resume, not yet handed on), oldest
    /// first, as if they had just been inserted. Only after [`Tracker::emit_keyframes_after`].
    pub fn emit_held_keyframes(&mut self, ids: impl IntoIterator<Item = u64>) {
        for id in ids {
            self.emit.inserted(id);
        }
    }

    /// Keyframes waiting to be final, oldest first.
    pub fn keyframes_waiting(&self) -> impl ExactSizeIterator<Item = u64> + '_ {
        self.emit.waiting.iter().copied()
    }

    /// The next keyframe whose depth is final (with `flush`, the oldest waiting one, final or
    /// not: the end of the stream), written into `out` (`index`, `t_ns`, `world_from_cam` in the
    /// tracker's frame, `camera`, `inv_depth` and `inv_depth_variance` at the input
    /// resolution) without allocating once `out`'s planes have that size; `None` when none is
    /// due, and always before the tracker is initialised. Keyframes the tracker no longer holds, or without depth yet, are skipped.
    pub fn next_final_keyframe(&mut self, flush: bool, out: &mut Keyframe) -> Option<u64> {
        let lag = self.emit.lag?;
        if flush {
            // The end of the stream: a global BA still in the background lands first.
            self.st.finish_global_ba();
        }
        // Before the initial BA the poses are provisional and the initialisation may start
        // again without them: nothing is handed on yet.
        if !self.is_initialised() {
            return None;
        }
        // Due: the waiting keyframes with at least `lag` newer ones (all with `flush`), oldest
        // first. Only segment 0's are handed on (the map is built in its frame): a keyframe of
        // another segment when it is due is skipped (its frame is not held back for a merge
        // that may never come: the caller's frame pool would run dry).
        while self.emit.waiting.len() > if flush { 0 } else { lag } {
            let id = self.emit.waiting.pop_front()?;
            let Some((segment, world_from_cam, t_ns)) = self.keyframes().find(|k| k.id == id).map(|k| (k.segment, k.world_from_cam, k.t_ns)) else { continue };
            if segment != 0 {
                self.emit.skipped_other_segment += 1;
                continue;
            }
            if let Err(e) = self.upsample_keyframe(id, &mut out.inv_depth, &mut out.inv_depth_variance) {
                tracing::debug!("keyframe {id}: no depth yet: {e}");
                continue;
            }
            out.index = id;
            out.t_ns = t_ns;
            out.world_from_cam = world_from_cam;
            out.camera = *self.camera();
            return Some(id);
        }
        None
    }

    /// Waiting keyframes dropped because nobody took them (see the module docs).
    pub fn keyframes_overflowed(&self) -> u64 {
        self.emit.overflowed
    }

    /// Due keyframes not handed on because they were of a map segment other than 0 (the map
    /// is segment 0's; a segment that merges into it later has its keyframes from then on
    /// handed on).
    pub fn keyframes_of_other_segments(&self) -> u64 {
        self.emit.skipped_other_segment
    }
}
