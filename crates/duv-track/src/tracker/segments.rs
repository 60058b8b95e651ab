//! Map segments (multi-map): a new segment after a loss in new territory, and the Sim(3)
//! merge of two segments when a keyframe of one matches a keyframe of the other.
//!
//! Every keyframe carries its segment id. Segments share the keyframe store, so a new segment
//! costs no memory of its own; the window BA, the initialisation, the pose graph, the global
//! BA, eviction anchors and the depth-consistency neighbours only ever combine keyframes of
//! one segment. Loop detection and relocalisation look at every segment: a verified match
//! across segments merges them, the younger segment's keyframes moved into the older one's
//! frame and scale, so that segment 0 (the dive's first) stays the world frame.

use super::*;

/// Segment bookkeeping.
pub(super) struct Segments {
    /// The segment new keyframes join.
    pub(super) current: u32,
    /// The id the next new segment takes.
    pub(super) next: u32,
    /// Good frames in a row that could not be relocalised (`new_segment_after`).
    pub(super) failed_relocs: usize,
    /// The constant inverse depth the current segment started from (kept for a restart).
    pub(super) start_inv_depth: f32,
    /// An initial BA has run (or the tracker was seeded): a later segment collecting its
    /// first keyframes leaves the others' poses measured.
    pub(super) initialised_once: bool,
}

impl State {
    /// Whether slot `s` belongs to the current segment.
    pub(super) fn in_current_segment(&self, s: usize) -> bool {
        self.graph.kfs.slots[s].segment == self.segments.current
    }

    /// The newest `n` keyframes of the current segment, oldest first, into `win.window`.
    pub(super) fn window_of_current_segment(&mut self, n: usize) {
        self.win.window.clear();
        for &s in self.graph.kfs.order.iter().rev() {
            if self.win.window.len() >= n {
                break;
            }
            if self.graph.kfs.slots[s].segment == self.segments.current {
                self.win.window.push(s);
            }
        }
        self.win.window.reverse();
    }

    /// A lost frame that passed the image checks and matched no stored keyframe: after
    /// `new_segment_after` of them in a row, a new segment starts from this frame.
    pub(super) fn maybe_start_segment(&mut self, frame: &Frame, mut out: TrackOutput) -> Result<TrackOutput, TrackError> {
        self.segments.failed_relocs += 1;
        let failed = self.segments.failed_relocs;
        if self.cfg.new_segment_after == 0 || failed < self.cfg.new_segment_after {
            return Ok(out);
        }
        // The last insertion's stages belong to the old segment: finished first.
        self.finish_pending()?;
        let predicted = out.world_from_cam;
        // The new segment's depth starts at the last reference's median (its scale a guess
        // near the old one's, until a merge measures it).
        let r = self.motion.ref_slot;
        self.work.scratch.clear();
        self.work.scratch.extend(self.graph.kfs.slots[r].inv_depth.data.iter().copied().filter(|d| d.is_finite() && *d >= MIN_INV_DEPTH));
        let median = if self.work.scratch.is_empty() {
            self.cfg.initial_inv_depth
        } else {
            let m = self.work.scratch.len() / 2;
            *self.work.scratch.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1
        };
        let old = self.segments.current;
        self.segments.current = self.segments.next;
        self.segments.next += 1;
        self.segments.failed_relocs = 0;
        self.segments.start_inv_depth = median;
        self.stats.counters.segments_started += 1;
        let s = self.start_segment_keyframe(frame, &predicted, median);
        tracing::info!(seq = frame.seq, old, new = self.segments.current, failed, "track: new map segment ({failed} good frames in a row matched no stored keyframe)");
        out.state = TrackingState::Initializing;
        out.world_from_cam = predicted;
        out.segment = self.segments.current;
        out.new_keyframe = Some(self.graph.kfs.slots[s].id);
        out.anchor = Some(FrameAnchor { keyframe: self.graph.kfs.slots[s].id, kf_from_cam: Se3::identity(), kf_scale: 1.0 });
        out.note = TrackNote::NewSegment { segment: self.segments.current, failed_frames: failed };
        Ok(out)
    }

    /// The current frame as the first keyframe of a (new) segment at `pose` with constant
    /// inverse depth `inv_depth`: collecting starts.
    pub(super) fn start_segment_keyframe(&mut self, frame: &Frame, pose: &Se3, inv_depth: f32) -> usize {
        let s = self.insert_keyframe_slot(frame, pose);
        self.graph.kfs.slots[s].inv_depth.data.fill(inv_depth);
        self.motion.ref_slot = s;
        self.init.phase = Phase::Collecting;
        self.init.failed_in_a_row = 0;
        self.motion.state = TrackingState::Initializing;
        self.motion.last_pose = *pose;
        self.motion.velocity = Se3::identity();
        self.motion.last_seq = frame.seq;
        self.work.have_prev_flow = false;
        self.insert.pending = None;
        s
    }

    /// Merges the segments of keyframes `c` and `s`, given `world_from_s` (`s`'s pose in
    /// `c`'s segment frame, measured against `c`'s depth) and `scale` (`c`'s depth units per
    /// unit of `s`'s): the younger segment's keyframes (and the motion, when it is the current
    /// one) are moved by the Sim(3) this fixes into the older one's frame and scale, and take
    /// its id.
    pub(super) fn merge_segments(&mut self, c: usize, s: usize, world_from_s: &Se3, scale: f64) {
        let (seg_c, seg_s) = (self.graph.kfs.slots[c].segment, self.graph.kfs.slots[s].segment);
        let own_s = self.graph.kfs.slots[s].world_from_cam;
        // `moved` goes into `kept`'s frame: p_kept = anchor_kept * scale_m * anchor_moved^-1 * p_moved.
        let (kept, moved, anchor_kept, anchor_moved, ratio) =
            if seg_c <= seg_s { (seg_c, seg_s, *world_from_s, own_s, scale) } else { (seg_s, seg_c, own_s, *world_from_s, 1.0 / scale) };
        let to_kept = |pose: &Se3| anchor_kept * scale_translation(&anchor_moved.inv_mul(pose), ratio);
        let inv = (1.0 / ratio) as f32;
        let mut moved_kfs = 0usize;
        for &k in &self.graph.kfs.order {
            let kf = &mut self.graph.kfs.slots[k];
            if kf.segment != moved {
                continue;
            }
            kf.world_from_cam = to_kept(&kf.world_from_cam);
            for d in kf.inv_depth.data.iter_mut() {
                *d *= inv;
            }
            for v in kf.variance.data.iter_mut() {
                if *v < f32::MAX {
                    *v *= inv * inv;
                }
            }
            kf.scale_correction *= ratio;
            kf.segment = kept;
            moved_kfs += 1;
        }
        if self.segments.current == moved {
            self.motion.last_pose = to_kept(&self.motion.last_pose);
            self.motion.velocity = scale_translation(&self.motion.velocity, ratio);
            self.segments.current = kept;
        }
        self.stats.counters.segments_merged += 1;
        tracing::info!(kept, moved, moved_keyframes = moved_kfs, scale = ratio, "track: map segments merged");
    }

    /// Distinct segments among the live keyframes (a fixed-size scan, no allocation).
    pub(super) fn live_segments(&self) -> usize {
        let mut count = 0;
        for (i, &s) in self.graph.kfs.order.iter().enumerate() {
            let seg = self.graph.kfs.slots[s].segment;
            if !self.graph.kfs.order[..i].iter().any(|&o| self.graph.kfs.slots[o].segment == seg) {
                count += 1;
            }
        }
        count
    }
}
