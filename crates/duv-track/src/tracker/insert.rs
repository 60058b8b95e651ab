//! Keyframe insertion, its deferred stages and eviction.

use super::*;

/// Keyframe insertion and eviction.
pub(super) struct Insertion {
    /// Deferred stages of the last keyframe insertion.
    pub(super) pending: Option<Pending>,
    pub(super) evicted_slot: Option<usize>,
    pub(super) pending_eviction: Option<EvictedKeyframe>,
}

/// What remains of a keyframe insertion: flow/BA rounds, then loop closure / global BA.
#[derive(Clone, Copy, Debug)]
pub(super) struct Pending {
    pub(super) slot: usize,
    pub(super) fixed: usize,
    /// Rounds done.
    pub(super) next_round: usize,
    /// Fine stages (`defer_insertion`): the position in `new_edges` of the next edge to
    /// estimate in this round; `new_edges.len()`: the round's BA is next.
    pub(super) next_edge: usize,
    pub(super) fine: bool,
    /// Loop search: `None` before its candidates are ranked, then the next one to verify
    /// (past the last: searched). Fine stages rank and verify before the last round's solve.
    pub(super) next_candidate: Option<usize>,
    /// A keyframe collected before initialisation: one round, `init_iterations` over every
    /// keyframe, no covariance and no loop search.
    pub(super) collecting: bool,
}

impl State {
    /// Takes a slot for the current frame (swapping its prepared pyramid in) and fills the
    /// keyframe's image data; the depth is the caller's.
    pub(super) fn insert_keyframe_slot(&mut self, frame: &Frame, pose: &Se3) -> usize {
        if self.graph.kfs.is_full() {
            self.evict();
        }
        let s = self.graph.kfs.push().expect("a slot is free after eviction");
        self.fill_keyframe_slot(s, frame.t_ns, frame.seq, pose);
        self.stats.counters.keyframes_inserted += 1;
        self.stats.times.keyframes += 1;
        s
    }

    /// Fills slot `s` from the current frame (`cur`, `grey`).
    pub(super) fn fill_keyframe_slot(&mut self, s: usize, t_ns: Timestamp, seq: u64, pose: &Se3) {
        let (w, h) = (self.camera.width, self.camera.height);
        let kf = &mut self.graph.kfs.slots[s];
        std::mem::swap(&mut kf.frame, &mut self.work.cur);
        kf.t_ns = t_ns;
        kf.seq = seq;
        kf.segment = self.segments.current;
        kf.world_from_cam = *pose;
        for (g, &v) in kf.guide.iter_mut().zip(&self.work.grey.data) {
            *g = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        }
        block_means(&self.work.grey.data, w, self.factor, &mut kf.guide_low);
        thumbnail(&self.work.grey.data, w, h, &mut kf.thumb);
    }

    /// Evicts the most redundant keyframe outside the window (the one whose neighbours are
    /// closest by induced flow); it is re-expressed relative to its predecessor, which is of
    /// its segment.
    pub(super) fn evict(&mut self) {
        let n = self.graph.kfs.len();
        let last_candidate = n.saturating_sub(self.cap.ba_window);
        let order = &self.graph.kfs.order;
        let seg = |pos: usize| self.graph.kfs.slots[order[pos]].segment;
        let mut best: Option<(f32, usize)> = None;
        for pos in 1..last_candidate.min(n.saturating_sub(1)) {
            if seg(pos - 1) != seg(pos) || seg(pos + 1) != seg(pos) {
                continue;
            }
            let (a, b) = (self.graph.kfs.order[pos - 1], self.graph.kfs.order[pos + 1]);
            let (ka, kb) = (&self.graph.kfs.slots[a], &self.graph.kfs.slots[b]);
            let (flow, overlap) = induced_flow(&self.low, &ka.world_from_cam, &ka.inv_depth, &kb.world_from_cam, None);
            let score = flow / overlap.max(0.05);
            if best.is_none_or(|(s, _)| score < s) {
                best = Some((score, pos));
            }
        }
        // Else the oldest with a predecessor of its segment, else the oldest after the first.
        let fallback = (1..last_candidate.max(2).min(n)).find(|&pos| seg(pos - 1) == seg(pos)).unwrap_or(1.min(n - 1));
        let pos = best.map(|(_, p)| p).unwrap_or(fallback);
        let s = self.graph.kfs.order[pos];
        let parent = self.graph.kfs.order[pos - 1];
        let (kp, ks) = (&self.graph.kfs.slots[parent], &self.graph.kfs.slots[s]);
        let ev = EvictedKeyframe {
            id: ks.id,
            t_ns: ks.t_ns,
            seq: ks.seq,
            scale_correction: ks.scale_correction,
            anchor: FrameAnchor { keyframe: kp.id, kf_from_cam: kp.world_from_cam.inv_mul(&ks.world_from_cam), kf_scale: kp.scale_correction },
        };
        self.graph.edges.remove_touching(s);
        self.graph.kfs.remove_at(pos);
        if self.motion.ref_slot == s {
            self.motion.ref_slot = parent;
        }
        self.insert.evicted_slot = Some(s);
        self.insert.pending_eviction = Some(ev);
        self.stats.counters.keyframes_evicted += 1;
    }

    /// Initial inverse depth of keyframe `s` from keyframe `prev`: `prev`'s points splatted
    /// into `s` (bilinear weights, weighted mean: "closest wins" would bias every new keyframe
    /// closer, and with it the scale), holes filled with the median.
    pub(super) fn splat_depth(&mut self, prev: usize, s: usize) {
        let low = self.low;
        let (w, h) = (low.width, low.height);
        let (kp, ks) = (&self.graph.kfs.slots[prev], &self.graph.kfs.slots[s]);
        let rel = ks.world_from_cam.inv_mul(&kp.world_from_cam);
        let rot = rel.rotation.to_rotation_matrix().into_inner();
        let t = rel.translation.vector;
        // Weighted sums in `scratch_depth`, weights in `scratch` (both depth-grid sized).
        self.work.scratch_depth.data.fill(0.0);
        self.work.scratch.clear();
        self.work.scratch.resize(w * h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let d = kp.inv_depth.data[y * w + x] as f64;
                let q = Vector3::new((x as f64 - low.cx) / low.fx, (y as f64 - low.cy) / low.fy, 1.0);
                let p = rot * q + t * d;
                if p.z <= 1e-6 {
                    continue;
                }
                let (u, v) = (low.fx * p.x / p.z + low.cx, low.fy * p.y / p.z + low.cy);
                let inv = (d / p.z) as f32;
                if !(inv.is_finite() && u > -1.0 && v > -1.0 && u < w as f64 && v < h as f64) {
                    continue;
                }
                let (u0, v0) = (u.floor(), v.floor());
                let (au, av) = ((u - u0) as f32, (v - v0) as f32);
                for (dy, wy) in [(0, 1.0 - av), (1, av)] {
                    for (dx, wx) in [(0, 1.0 - au), (1, au)] {
                        let (uu, vv) = (u0 as i64 + dx, v0 as i64 + dy);
                        if uu < 0 || vv < 0 || uu >= w as i64 || vv >= h as i64 {
                            continue;
                        }
                        let i = vv as usize * w + uu as usize;
                        self.work.scratch_depth.data[i] += wx * wy * inv;
                        self.work.scratch[i] += wx * wy;
                    }
                }
            }
        }
        for (d, &wgt) in self.work.scratch_depth.data.iter_mut().zip(&self.work.scratch) {
            *d = if wgt > 0.05 { *d / wgt } else { 0.0 };
        }
        self.work.scratch.clear();
        self.work.scratch.extend(self.work.scratch_depth.data.iter().copied().filter(|v| *v > 0.0));
        let fill = if self.work.scratch.is_empty() {
            kp.inv_depth.data.iter().sum::<f32>() / kp.inv_depth.data.len().max(1) as f32
        } else {
            let m = self.work.scratch.len() / 2;
            *self.work.scratch.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1
        };
        let ks = &mut self.graph.kfs.slots[s];
        for (dst, &src) in ks.inv_depth.data.iter_mut().zip(&self.work.scratch_depth.data) {
            *dst = if src > 0.0 { src } else { fill };
        }
    }

    /// Inserts the current frame as a keyframe: links, flow/BA rounds, covariance, pruning,
    /// loop closure.
    /// The frame's pose is `last_pose` (just accepted).
    pub(super) fn add_keyframe(&mut self, frame: &Frame, out: &mut TrackOutput) -> Result<(), TrackError> {
        // The previous insertion's deferred stages use the window and its new edges. They move
        // the reference keyframe, and `last_pose` with it: the new keyframe starts from the
        // re-anchored pose, not the one measured against the reference before (with keyframes
        // every two or three frames that stale pose drifted the map by 8 % of the path).
        out.loop_closed |= self.finish_pending()?;
        let pose = self.motion.last_pose;
        let prev = self.motion.ref_slot;
        let s = self.insert_keyframe_slot(frame, &pose);
        self.splat_depth(prev, s);
        self.window_of_current_segment(self.cap.ba_window);
        self.graph.new_edges.clear();
        let mut links = 0;
        for i in (0..self.win.window.len().saturating_sub(1)).rev() {
            if links >= self.cfg.edges_per_keyframe {
                break;
            }
            let c = self.win.window[i];
            let (ks, kc) = (&self.graph.kfs.slots[s], &self.graph.kfs.slots[c]);
            let (flow, overlap) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kc.world_from_cam, None);
            if c == prev || (flow <= self.cfg.edge_max_flow_px && overlap >= self.cfg.edge_min_overlap) {
                for (f, t) in [(s, c), (c, s)] {
                    if let Some(e) = self.graph.edges.add(f, t, false) {
                        self.graph.new_edges.push(e);
                    }
                }
                links += 1;
            }
        }
        let fixed = self.window_fixed();
        if self.cfg.defer_rounds && self.cfg.defer_insertion {
            // Every round deferred, one edge or one solve per stage: the keyframe's frame pays
            // only for the insertion. Pruning judges the motion-only pose and splatted depth.
            let (kp, ks) = (&self.graph.kfs.slots[prev], &self.graph.kfs.slots[s]);
            let (flow, _) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kp.world_from_cam, None);
            tracing::debug!(kf = ks.id, links, induced_flow_px = flow, "track: keyframe inserted (rounds deferred)");
            if flow < self.cfg.prune_flow_px {
                let refined = ks.world_from_cam;
                self.prune_new_keyframe(s, prev, &refined, out);
                return Ok(());
            }
            self.accept_new_keyframe(s, out, Pending { slot: s, fixed, next_round: 0, next_edge: 0, fine: true, next_candidate: None, collecting: false });
            return Ok(());
        }
        self.keyframe_round(fixed)?;
        if self.cfg.local_rounds == 1 {
            self.window_covariance(fixed);
        }
        let (kp, ks) = (&self.graph.kfs.slots[prev], &self.graph.kfs.slots[s]);
        let (flow, _) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kp.world_from_cam, None);
        let refined = ks.world_from_cam;
        tracing::debug!(kf = ks.id, links, induced_flow_px = flow, "track: keyframe inserted");
        if flow < self.cfg.prune_flow_px {
            self.prune_new_keyframe(s, prev, &refined, out);
            return Ok(());
        }
        // The remaining rounds, then loop closure or the periodic global BA: one stage per
        // following frame when deferred (latency), all now otherwise.
        self.accept_new_keyframe(s, out, Pending { slot: s, fixed, next_round: 1, next_edge: 0, fine: false, next_candidate: None, collecting: false });
        if !self.cfg.defer_rounds {
            while self.insert.pending.is_some() {
                out.loop_closed |= self.run_pending_stage()?;
            }
            let kf = &self.graph.kfs.slots[s];
            out.world_from_cam = kf.world_from_cam;
            self.motion.last_pose = kf.world_from_cam;
        }
        Ok(())
    }

    /// Too close to the previous keyframe: the frame stays a plain frame.
    pub(super) fn prune_new_keyframe(&mut self, s: usize, prev: usize, refined: &Se3, out: &mut TrackOutput) {
        self.graph.edges.remove_touching(s);
        if let Some(pos) = self.graph.kfs.position(s) {
            self.graph.kfs.remove_at(pos);
        }
        self.stats.counters.keyframes_pruned += 1;
        self.motion.last_pose = *refined;
        out.world_from_cam = *refined;
        out.anchor = Some(self.anchor_to(prev, refined));
    }

    /// Keyframe `s` becomes the reference; `pending` holds its remaining stages.
    pub(super) fn accept_new_keyframe(&mut self, s: usize, out: &mut TrackOutput, pending: Pending) {
        self.motion.ref_slot = s;
        self.loops.inserted_since_loop += 1;
        self.loops.inserted_since_global += 1;
        self.insert.pending = Some(pending);
        let kf = &self.graph.kfs.slots[s];
        out.world_from_cam = kf.world_from_cam;
        out.new_keyframe = Some(kf.id);
        out.anchor = Some(FrameAnchor { keyframe: kf.id, kf_from_cam: Se3::identity(), kf_scale: kf.scale_correction });
        self.motion.last_pose = kf.world_from_cam;
    }

    /// One flow/BA round of a keyframe insertion: re-estimate the new edges seeded by the
    /// current estimate, then solve the window.
    pub(super) fn keyframe_round(&mut self, fixed: usize) -> Result<(), TrackError> {
        self.estimate_new_edges()?;
        self.round_solve(fixed);
        Ok(())
    }

    /// The window BA of a round; the last pose follows the reference keyframe.
    pub(super) fn round_solve(&mut self, fixed: usize) {
        let r = self.motion.ref_slot;
        let before = self.graph.kfs.slots[r].world_from_cam;
        self.solve_window(self.cfg.local_iterations, fixed);
        self.motion.last_pose = self.graph.kfs.slots[r].world_from_cam * before.inv_mul(&self.motion.last_pose);
    }

    /// Runs the next deferred stage of the last insertion; true when it closed a loop.
    pub(super) fn run_pending_stage(&mut self) -> Result<bool, TrackError> {
        let Some(mut p) = self.insert.pending else { return Ok(false) };
        if p.collecting {
            // The edges, then one solve of `init_iterations` (cut into solves of
            // `local_iterations` iterations each, it lost the turbid survey's scale at
            // 320x240: 13.8 % ATE).
            if p.next_edge < self.graph.new_edges.len() {
                p.next_edge += self.estimate_new_edge_at(p.next_edge)?;
                self.insert.pending = Some(p);
            } else {
                self.solve_window(self.cfg.init_iterations, p.fixed);
                self.insert.pending = None;
            }
            return Ok(false);
        }
        if p.fine && p.next_round < self.cfg.local_rounds {
            if p.next_edge < self.graph.new_edges.len() {
                p.next_edge += self.estimate_new_edge_at(p.next_edge)?;
                let last_round = p.next_round + 1 == self.cfg.local_rounds;
                if self.cfg.loop_closure && last_round && p.next_edge >= self.graph.new_edges.len() && p.next_candidate.is_none() {
                    // The loop search goes before the last solve, into the stage the last
                    // edge pair leaves free (the solve takes a frame of its own). After the
                    // solve it took a fourth frame, and with keyframes every three or four
                    // frames it ran inside the next keyframe's frame (about 100 ms at
                    // 640x480 against 60 ms without loop closure). Ranking is a thumbnail
                    // comparison and verification is seeded by the keyframe's motion-only
                    // pose: neither needs the solve.
                    self.rank_loop_candidates(p.slot);
                    p.next_candidate = Some(0);
                }
            } else if let Some(k) = self.unverified_candidate(&p) {
                let closed = self.try_loop_candidate(p.slot, k)?;
                // After a closure the window solve still runs (the global BA moved it).
                p.next_candidate = Some(if closed { self.loops.loop_candidates.len() } else { k + 1 });
                self.insert.pending = Some(p);
                return Ok(closed);
            } else {
                self.round_solve(p.fixed);
                p.next_round += 1;
                p.next_edge = 0;
                if p.next_round == self.cfg.local_rounds {
                    self.window_covariance(p.fixed);
                    self.rounds_done(p);
                    return Ok(false);
                }
            }
            self.insert.pending = Some(p);
            return Ok(false);
        }
        if p.next_round < self.cfg.local_rounds {
            self.keyframe_round(p.fixed)?;
            p.next_round += 1;
            if p.next_round == self.cfg.local_rounds {
                self.window_covariance(p.fixed);
                self.rounds_done(p);
                return Ok(false);
            }
            self.insert.pending = Some(p);
            return Ok(false);
        }
        // Then the loop search, one candidate verified (a flow) per stage.
        if self.cfg.loop_closure {
            let next = match p.next_candidate {
                Some(k) => k,
                None => {
                    self.rank_loop_candidates(p.slot);
                    0
                }
            };
            if next < self.loops.loop_candidates.len() {
                let closed = self.try_loop_candidate(p.slot, next)?;
                if closed {
                    self.insert.pending = None;
                    return Ok(true);
                }
                if next + 1 < self.loops.loop_candidates.len() {
                    self.insert.pending = Some(Pending { next_candidate: Some(next + 1), ..p });
                    return Ok(false);
                }
            }
        }
        self.finish_insertion();
        Ok(false)
    }

    /// After the last flow/BA round of an insertion: ends it when the fine stages searched
    /// for loops before the solve; otherwise ranks the loop candidates right away (a
    /// thumbnail comparison, cheap) and ends the insertion when there is none to verify. A
    /// loop search with nothing to verify used to take a stage of its own, and after a window
    /// solve (a frame's only stage) a frame of its own; with keyframes every three frames
    /// (the end of the generated survey) that pushed the rest of the next insertion into the
    /// next keyframe's frame.
    pub(super) fn rounds_done(&mut self, mut p: Pending) {
        if self.cfg.loop_closure && p.next_candidate.is_none() {
            self.rank_loop_candidates(p.slot);
            p.next_candidate = Some(0);
            if !self.loops.loop_candidates.is_empty() {
                self.insert.pending = Some(p);
                return;
            }
        }
        self.finish_insertion();
    }

    /// The insertion's deferred work is done; a periodic global BA when due.
    pub(super) fn finish_insertion(&mut self) {
        self.insert.pending = None;
        if self.cfg.global_ba_period > 0 && self.loops.inserted_since_global >= self.cfg.global_ba_period {
            self.global_ba();
        }
    }

    /// The loop candidate of `p` to verify next, if its search has ranked candidates and not
    /// verified them all.
    pub(super) fn unverified_candidate(&self, p: &Pending) -> Option<usize> {
        p.next_candidate.filter(|&k| k < self.loops.loop_candidates.len())
    }

    /// Whether the next deferred stage is a window solve (or a whole round).
    pub(super) fn next_stage_is_solve(&self) -> bool {
        match self.insert.pending {
            Some(p) if p.collecting || (p.fine && p.next_round < self.cfg.local_rounds) => {
                p.next_edge >= self.graph.new_edges.len() && self.unverified_candidate(&p).is_none()
            }
            Some(p) => p.next_round < self.cfg.local_rounds,
            None => false,
        }
    }

    /// Runs every deferred stage.
    pub(super) fn finish_pending(&mut self) -> Result<bool, TrackError> {
        let mut closed = false;
        while self.insert.pending.is_some() {
            closed |= self.run_pending_stage()?;
        }
        Ok(closed)
    }
}
