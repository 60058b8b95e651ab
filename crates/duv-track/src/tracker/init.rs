//! Initialisation: collecting the first keyframes and the initial BA.

use super::*;

/// Initialisation: which insertion path keyframes take, and the initial BA's first solution
/// while the second start is tried.
pub(super) struct Init {
    pub(super) phase: Phase,
    pub(super) init_snapshot: WindowSnapshot,
    /// Frames in a row, while collecting, that did not match the reference keyframe.
    pub(super) failed_in_a_row: usize,
}

impl State {
    pub(super) fn track_collecting(&mut self, frame: &Frame, mut out: TrackOutput) -> Result<TrackOutput, TrackError> {
        out.state = TrackingState::Initializing;
        self.motion.state = TrackingState::Initializing;
        let r = self.motion.ref_slot;
        if self.work.have_prev_flow {
            self.work.seed.dx.data.copy_from_slice(&self.work.prev_flow.dx.data);
            self.work.seed.dy.data.copy_from_slice(&self.work.prev_flow.dy.data);
        }
        self.flow_ref_to_current(r, self.work.have_prev_flow, true)?;
        let mut conf = write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut self.work.obs_target, &mut self.work.obs_weight);
        if conf < self.cfg.min_confident_fraction {
            // A turn between frames (a low frame rate): the flow seeded turned.
            if let Some(c) = self.collecting_turns(r)? {
                conf = c;
            }
        }
        if conf < self.cfg.min_confident_fraction {
            // Nothing to trust: wait for a better frame, or start again from this one.
            self.work.have_prev_flow = false;
            out.note = TrackNote::InitLowConfidence { confident: conf, needed: self.cfg.min_confident_fraction };
            return self.init_failed_frame(frame, out);
        }
        self.work.prev_flow.dx.data.copy_from_slice(&self.work.res.pooled.flow.dx.data);
        self.work.prev_flow.dy.data.copy_from_slice(&self.work.res.pooled.flow.dy.data);
        self.work.have_prev_flow = true;
        let mean_flow = self.work.res.stats.mean_flow_input_px / self.factor as f32;
        if mean_flow <= self.cfg.keyframe_flow_px {
            self.init.failed_in_a_row = 0;
            out.note = TrackNote::InitSmallFlow { flow_px: mean_flow * self.factor as f32, needed_px: self.cfg.keyframe_flow_px * self.factor as f32 };
            return Ok(out);
        }
        // A new keyframe. The previous one's staged solve first (its stages usually ran on the
        // frames in between): the pose and the splat below use the solved reference.
        self.finish_pending()?;
        // A first pose against the reference's (constant or solved) depth.
        let mut pose = self.graph.kfs.slots[r].world_from_cam;
        if self.motion_only(r, &mut pose).is_err() {
            self.stats.counters.ba_failures += 1;
            out.note = TrackNote::InitPoseFailed;
            return self.init_failed_frame(frame, out);
        }
        self.init.failed_in_a_row = 0;
        let prev = r;
        let s = self.insert_keyframe_slot(frame, &pose);
        self.splat_depth(prev, s);
        // Incremental initialisation: link the new keyframe and refine everything collected
        // so far, so that each new keyframe starts from a better map than constant depth.
        // (Only this segment's keyframes: while collecting they are the newest ones.)
        self.graph.new_edges.clear();
        self.window_of_current_segment(usize::MAX);
        let n = self.win.window.len();
        for back in 1..=self.cfg.edges_per_keyframe.min(n - 1) {
            let c = self.win.window[n - 1 - back];
            for (f, t) in [(s, c), (c, s)] {
                if let Some(e) = self.graph.edges.add(f, t, false) {
                    self.graph.new_edges.push(e);
                }
            }
        }
        let initialising = n >= self.cfg.init_keyframes;
        if self.cfg.defer_rounds && self.cfg.defer_insertion && !initialising {
            // Staged like an insertion: one edge per stage, then the solve over everything
            // collected, on the following frames. The initial BA itself is not staged.
            self.insert.pending = Some(Pending { slot: s, fixed: 1, next_round: 0, next_edge: 0, fine: true, next_candidate: None, collecting: true });
        } else {
            self.estimate_new_edges()?;
            self.solve_window(self.cfg.init_iterations, 1);
        }
        self.motion.ref_slot = s;
        self.work.have_prev_flow = false;
        self.motion.last_pose = pose;
        self.motion.last_seq = frame.seq;
        out.world_from_cam = pose;
        out.new_keyframe = Some(self.graph.kfs.slots[s].id);
        out.anchor = Some(FrameAnchor { keyframe: self.graph.kfs.slots[s].id, kf_from_cam: Se3::identity(), kf_scale: 1.0 });
        if initialising {
            self.initialise()?;
            out.state = TrackingState::Tracking;
        } else {
            out.note = TrackNote::InitKeyframe { keyframes: n, needed: self.cfg.init_keyframes };
        }
        out.world_from_cam = self.graph.kfs.slots[s].world_from_cam;
        self.motion.last_pose = out.world_from_cam;
        Ok(out)
    }

    /// While collecting there is no map to predict from: the flow from keyframe `r` is tried
    /// again seeded by the flow a pure turn about the camera's vertical axis by +-1 and +-2
    /// `turn_search_deg` induces (a rotation's flow does not depend on depth), added to the
    /// previous frame's flow when there is one. The confident fraction of the first turn whose
    /// flow is confident on `loop_min_confident_fraction` of the pixels (a guessed seed must
    /// earn more than the plain one: below that, seeds found matches in a view never seen);
    /// its measurement is left in the frame buffers.
    fn collecting_turns(&mut self, r: usize) -> Result<Option<f32>, TrackError> {
        let step = (self.cfg.turn_search_deg as f64).to_radians();
        if step <= 0.0 {
            return Ok(None);
        }
        let need = self.cfg.min_confident_fraction.max(self.cfg.loop_min_confident_fraction);
        for k in [1.0, -1.0, 2.0, -2.0] {
            let turn = Se3::from_parts(Translation3::identity(), nalgebra::UnitQuaternion::from_axis_angle(&Vector3::y_axis(), k * step));
            {
                let kf = &self.graph.kfs.slots[r];
                induced_flow(&self.low, &Se3::identity(), &kf.inv_depth, &turn, Some(&mut self.work.seed));
            }
            if self.work.have_prev_flow {
                for (s, p) in self.work.seed.dx.data.iter_mut().zip(&self.work.prev_flow.dx.data) {
                    *s += p;
                }
                for (s, p) in self.work.seed.dy.data.iter_mut().zip(&self.work.prev_flow.dy.data) {
                    *s += p;
                }
            }
            self.flow_ref_to_current(r, true, true)?;
            let conf = write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut self.work.obs_target, &mut self.work.obs_weight);
            if conf >= need {
                self.stats.counters.turns_found += 1;
                tracing::debug!(turn_deg = k * step.to_degrees(), conf, "track: initialisation flow found at a turned seed");
                return Ok(Some(conf));
            }
        }
        Ok(None)
    }

    /// A collecting frame that did not match the reference keyframe: after
    /// `init_restart_after` of them in a row, the keyframes collected so far are dropped and
    /// this frame becomes the first keyframe of a new start.
    fn init_failed_frame(&mut self, frame: &Frame, mut out: TrackOutput) -> Result<TrackOutput, TrackError> {
        // Enough keyframes to start from: the initial BA now, and this frame as after a loss.
        let collected = self.graph.kfs.order.iter().rev().take_while(|&&s| self.in_current_segment(s)).count();
        if self.cfg.init_min_keyframes > 0 && collected >= self.cfg.init_min_keyframes {
            self.finish_pending()?;
            self.initialise()?;
            self.stats.counters.init_early += 1;
            tracing::info!(seq = frame.seq, collected, "track: initialised early on the keyframes collected (this frame did not match the reference keyframe)");
            let frames_since = frame.seq.saturating_sub(self.motion.last_seq).max(1);
            out.world_from_cam = self.predict(frames_since);
            out.note = TrackNote::InitEarly { keyframes: collected, needed: self.cfg.init_keyframes };
            self.motion.state = TrackingState::Lost(LostReason::LowConfidence);
            return self.relocalise(frame, out);
        }
        self.init.failed_in_a_row += 1;
        let failed = self.init.failed_in_a_row;
        if self.cfg.init_restart_after == 0 || failed < self.cfg.init_restart_after {
            return Ok(out);
        }
        self.insert.pending = None;
        // This segment's keyframes (the newest ones while collecting); other segments stay.
        let mut dropped = 0;
        while let Some(&s) = self.graph.kfs.order.last() {
            if !self.in_current_segment(s) {
                break;
            }
            self.graph.edges.remove_touching(s);
            self.graph.kfs.remove_at(self.graph.kfs.len() - 1);
            dropped += 1;
        }
        tracing::info!(seq = frame.seq, failed, dropped, "track: initialisation restarted ({failed} frames in a row did not match the reference keyframe)");
        self.graph.new_edges.clear();
        self.win.window.clear();
        self.init.failed_in_a_row = 0;
        self.stats.counters.init_restarts += 1;
        let s = if self.segments.current == 0 {
            self.start_first_keyframe(frame)
        } else {
            // A later segment starts again where it was predicted, at its depth.
            let inv_depth = self.segments.start_inv_depth;
            let pose = out.world_from_cam;
            self.start_segment_keyframe(frame, &pose, inv_depth)
        };
        out.world_from_cam = self.graph.kfs.slots[s].world_from_cam;
        out.new_keyframe = Some(self.graph.kfs.slots[s].id);
        out.anchor = Some(FrameAnchor { keyframe: self.graph.kfs.slots[s].id, kf_from_cam: Se3::identity(), kf_scale: 1.0 });
        out.note = TrackNote::InitRestarted { failed_frames: failed, dropped_keyframes: dropped };
        Ok(out)
    }

    /// The current frame as the first keyframe (identity pose, constant inverse depth):
    /// collecting starts.
    pub(super) fn start_first_keyframe(&mut self, frame: &Frame) -> usize {
        let pose = Se3::identity();
        let s = self.insert_keyframe_slot(frame, &pose);
        self.graph.kfs.slots[s].inv_depth.data.fill(self.cfg.initial_inv_depth);
        self.motion.ref_slot = s;
        self.init.phase = Phase::Collecting;
        self.motion.state = TrackingState::Initializing;
        self.motion.last_pose = pose;
        self.motion.velocity = Se3::identity();
        self.motion.last_seq = frame.seq;
        self.work.have_prev_flow = false;
        s
    }

    /// Monocular initialisation: link the collected keyframes, then alternate flow and BA with
    /// many iterations from constant inverse depth.
    pub(super) fn initialise(&mut self) -> Result<(), TrackError> {
        // The current segment's keyframes (every keyframe for the first segment).
        self.window_of_current_segment(usize::MAX);
        let n = self.win.window.len();
        self.graph.new_edges.clear();
        for pos in 1..n {
            for back in 1..=self.cfg.edges_per_keyframe.min(pos) {
                let (a, b) = (self.win.window[pos], self.win.window[pos - back]);
                for (f, t) in [(a, b), (b, a)] {
                    if let Some(e) = self.graph.edges.add(f, t, false) {
                        self.graph.new_edges.push(e);
                    }
                }
            }
        }
        let collected = self.initial_rounds()?;
        let rms = self.cfg.init_level_start_rms_px as f64;
        let try_level = self.cfg.init_level_start && collected.is_none_or(|c| c > 0.5 * rms * rms);
        if try_level && self.init.init_snapshot.save(&self.graph.kfs, &self.graph.edges, &self.win.window, &self.graph.new_edges) {
            self.level_start();
            let level = self.initial_rounds()?;
            let keep_level = match (collected, level) {
                (Some(c), Some(l)) => l < c,
                (None, Some(_)) => true,
                _ => false,
            };
            tracing::debug!(collected, level, keep_level, "track: initial BA from the collected and the level start");
            if !keep_level {
                self.init.init_snapshot.restore(&mut self.graph.kfs, &mut self.graph.edges, &self.win.window, &self.graph.new_edges);
                // The covariance below is taken on the loaded window.
                if let Err(e) = load_window(&mut self.win.ba, &self.low, &mut self.graph.kfs, &self.graph.edges, &self.win.window, false) {
                    tracing::debug!(error = %e, "track: reloading the initial window failed");
                }
            }
            self.stats.counters.init_level_start = keep_level;
        }
        self.window_covariance(1);
        self.init.phase = Phase::Running;
        self.segments.initialised_once = true;
        self.motion.state = TrackingState::Tracking;
        let newest = self.win.window[n - 1];
        self.motion.ref_slot = newest;
        let last = &self.graph.kfs.slots[newest];
        let before = &self.graph.kfs.slots[self.win.window[n - 2]];
        let frames = last.seq.saturating_sub(before.seq).max(1) as f64;
        self.motion.velocity = se3_exp(&(se3_log(&before.world_from_cam.inv_mul(&last.world_from_cam)) / frames));
        self.motion.last_pose = last.world_from_cam;
        self.motion.last_seq = last.seq;
        self.loops.inserted_since_loop = 0;
        self.loops.inserted_since_global = 0;
        Ok(())
    }

    /// `init_rounds` flow/BA rounds over the window (first pose fixed); the final cost per
    /// unit of flow weight of the new edges (`None` if the last solve failed).
    pub(super) fn initial_rounds(&mut self) -> Result<Option<f64>, TrackError> {
        let mut cost = None;
        for _ in 0..self.cfg.init_rounds {
            self.estimate_new_edges()?;
            cost = self.solve_window(self.cfg.init_iterations, 1);
        }
        let weight: f64 = self.graph.new_edges.iter().map(|&e| self.graph.edges.edges[e].weight.data.iter().map(|&w| w as f64).sum::<f64>()).sum();
        Ok(cost.filter(|_| weight > 0.0).map(|c| c / weight))
    }

    /// The second start of the initial BA (`init_level_start`): every window keyframe at the
    /// first one's attitude, positions kept, every inverse depth the window's median.
    pub(super) fn level_start(&mut self) {
        let Some(&first) = self.win.window.first() else { return };
        let attitude = self.graph.kfs.slots[first].world_from_cam.rotation;
        self.work.scratch.clear();
        for &s in &self.win.window {
            self.work.scratch.extend(self.graph.kfs.slots[s].inv_depth.data.iter().copied().filter(|d| d.is_finite() && *d >= MIN_INV_DEPTH));
        }
        let median = if self.work.scratch.is_empty() {
            self.cfg.initial_inv_depth
        } else {
            let m = self.work.scratch.len() / 2;
            *self.work.scratch.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1
        };
        for &s in &self.win.window {
            let kf = &mut self.graph.kfs.slots[s];
            kf.world_from_cam = Se3::from_parts(kf.world_from_cam.translation, attitude);
            kf.inv_depth.data.fill(median);
        }
    }
}
