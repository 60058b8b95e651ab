//! Per-frame tracking against the reference keyframe: flow, motion-only BA, pose acceptance.

use super::*;

/// Per-frame flow work: the current frame and the buffers every frame reuses.
pub(super) struct FrameWork {
    pub(super) flow: FlowEstimator,
    pub(super) grey: PlaneF32,
    /// Marine snow removal (`despeckle`), its planes sized once.
    pub(super) despeckle: Option<Despeckle>,
    pub(super) cur: PreparedFrame,
    pub(super) cur_thumb: Vec<f32>,
    pub(super) res: FlowResult,
    /// The reverse direction of a pair estimate.
    pub(super) res_reverse: FlowResult,
    pub(super) seed: FlowField,
    pub(super) prev_flow: FlowField,
    pub(super) have_prev_flow: bool,
    pub(super) obs_target: Image<f32, 2>,
    pub(super) obs_weight: Image<f32, 2>,
    pub(super) scratch: Vec<f32>,
    pub(super) scratch_depth: PlaneF32,
}

/// The tracking status and the constant-velocity motion model.
pub(super) struct Motion {
    pub(super) state: TrackingState,
    /// Slot of the keyframe frames are tracked against.
    pub(super) ref_slot: usize,
    pub(super) last_pose: Se3,
    pub(super) velocity: Se3,
    pub(super) last_seq: u64,
}

impl State {
    pub(super) fn track(&mut self, frame: &Frame) -> Result<TrackOutput, TrackError> {
        let (w, h) = (self.camera.width, self.camera.height);
        if frame.image.width() != w || frame.image.height() != h {
            return Err(TrackError::FrameSize { seq: frame.seq, width: frame.image.width(), height: frame.image.height(), expected_width: w, expected_height: h });
        }
        self.stats.times.frames += 1;
        self.insert.evicted_slot = None;
        // A global BA running in the background lands when due, before this frame's work.
        self.global_ba_if_due();
        // One deferred stage of the last keyframe insertion (map work; the frame comes after).
        let mut loop_closed = false;
        // A window solve is the frame's only stage: it costs about two edge pairs.
        for k in 0..self.cfg.stages_per_frame {
            let solve = self.next_stage_is_solve();
            if k > 0 && solve {
                break;
            }
            loop_closed |= self.run_pending_stage()?;
            if solve {
                break;
            }
        }
        let frames_since = frame.seq.saturating_sub(self.motion.last_seq).max(1);
        let mut out = TrackOutput {
            t_ns: frame.t_ns,
            seq: frame.seq,
            world_from_cam: self.predict(frames_since),
            state: self.motion.state,
            anchor: None,
            new_keyframe: None,
            segment: self.segments.current,
            evicted: None,
            loop_closed,
            note: TrackNote::None,
        };
        to_grey(&frame.image, &mut self.work.grey);
        // Health check first: a bad image never reaches the flow or the map.
        let (mean, contrast) = image_health(&self.work.grey.data, w, h);
        let bad = if mean.is_nan() || mean < self.cfg.min_mean_intensity {
            Some(LostReason::Black)
        } else if mean > self.cfg.max_mean_intensity {
            Some(LostReason::Saturated)
        } else if contrast < self.cfg.min_contrast {
            Some(LostReason::LowContrast)
        } else {
            None
        };
        if let Some(reason) = bad {
            return Ok(self.lost(out, reason));
        }
        let t0 = Instant::now();
        self.despeckle_grey();
        self.work.flow.prepare_into(&self.work.grey, &mut self.work.cur)?;
        self.stats.times.flow += t0.elapsed();
        let mut out = match self.init.phase {
            Phase::Empty => {
                let s = self.start_first_keyframe(frame);
                out.world_from_cam = Se3::identity();
                out.state = TrackingState::Initializing;
                out.new_keyframe = Some(self.graph.kfs.slots[s].id);
                out.anchor = Some(FrameAnchor { keyframe: self.graph.kfs.slots[s].id, kf_from_cam: Se3::identity(), kf_scale: 1.0 });
                out
            }
            Phase::Collecting => self.track_collecting(frame, out)?,
            Phase::Running => {
                if matches!(self.motion.state, TrackingState::Lost(_)) {
                    self.relocalise(frame, out)?
                } else {
                    self.track_running(frame, out, frames_since)?
                }
            }
        };
        out.evicted = self.insert.pending_eviction.take();
        out.segment = self.segments.current;
        Ok(out)
    }

    /// Marine snow out of `work.grey` (`despeckle`), as every image the flow sees.
    pub(super) fn despeckle_grey(&mut self) {
        if let Some(d) = self.work.despeckle.as_mut() {
            let stats = d.apply(&mut self.work.grey.data).expect("despeckle planes are the frame's size");
            tracing::trace!(specks = stats.speck_pixels, replaced = stats.replaced_pixels, "track: despeckle");
        }
    }

    /// Constant-velocity prediction `frames` frames after the last pose.
    pub(super) fn predict(&self, frames: u64) -> Se3 {
        if frames <= 1 {
            return self.motion.last_pose * self.motion.velocity;
        }
        let xi = se3_log(&self.motion.velocity) * frames as f64;
        self.motion.last_pose * se3_exp(&xi)
    }

    pub(super) fn lost(&mut self, mut out: TrackOutput, reason: LostReason) -> TrackOutput {
        self.stats.counters.lost_frames += 1;
        self.motion.state = TrackingState::Lost(reason);
        out.state = self.motion.state;
        out.anchor = None;
        out
    }

    /// Flow `ref -> current` with `seed` (or none), result in `self.work.res`.
    pub(super) fn flow_ref_to_current(&mut self, slot: usize, seeded: bool, forward_backward: bool) -> Result<(), TrackError> {
        let t0 = Instant::now();
        let seed = if seeded { Some(&self.work.seed) } else { None };
        let fb = forward_backward && self.cfg.flow.forward_backward;
        self.work.flow.estimate_with(&self.graph.kfs.slots[slot].frame, &self.work.cur, seed, &mut self.work.res, fb)?;
        self.stats.times.flow += t0.elapsed();
        self.stats.times.flow_estimates += 1;
        Ok(())
    }

    pub(super) fn motion_only(&mut self, slot: usize, pose: &mut Se3) -> Result<(), BaError> {
        let t0 = Instant::now();
        let kf = &self.graph.kfs.slots[slot];
        let variance = (self.cfg.motion_depth_variance && kf.has_variance && kf.variance_unit.is_finite()).then_some(&kf.variance);
        let obs = [MotionOnlyObservation {
            world_from_keyframe: kf.world_from_cam,
            inv_depth: &kf.inv_depth,
            target_xy: &self.work.obs_target,
            weight_xy: &self.work.obs_weight,
            inv_depth_variance: variance,
            variance_of_unit_weight: kf.variance_unit,
        }];
        let cfg = BaConfig { max_iterations: self.cfg.motion_iterations, ..self.cfg.ba };
        let r = solve_motion_only(&self.low, &obs, pose, &cfg);
        self.stats.times.ba += t0.elapsed();
        r.map(|_| ())
    }

    pub(super) fn anchor_to(&self, slot: usize, pose: &Se3) -> FrameAnchor {
        let kf = &self.graph.kfs.slots[slot];
        FrameAnchor { keyframe: kf.id, kf_from_cam: kf.world_from_cam.inv_mul(pose), kf_scale: kf.scale_correction }
    }

    pub(super) fn track_running(&mut self, frame: &Frame, mut out: TrackOutput, frames_since: u64) -> Result<TrackOutput, TrackError> {
        let r = self.motion.ref_slot;
        let predicted = self.predict(frames_since);
        {
            let kf = &self.graph.kfs.slots[r];
            induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &predicted, Some(&mut self.work.seed));
        }
        self.flow_ref_to_current(r, true, self.cfg.frame_forward_backward)?;
        let conf = write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut self.work.obs_target, &mut self.work.obs_weight);
        tracing::trace!(seq = frame.seq, keyframe = self.graph.kfs.slots[r].id, conf, mean_flow_input_px = self.work.res.stats.mean_flow_input_px, "track: frame flow");
        let mut pose = predicted;
        if conf < self.cfg.min_confident_fraction {
            // A turn the motion model did not predict, or lost.
            match self.try_turns(r, &predicted)? {
                Some(p) => pose = p,
                None => return Ok(self.lost(out, LostReason::LowConfidence)),
            }
        } else if self.motion_only(r, &mut pose).is_err() {
            return Ok(self.lost(out, LostReason::NoPose));
        }
        self.accept_pose(&pose, frame.seq, frames_since);
        self.segments.failed_relocs = 0;
        self.motion.state = TrackingState::Tracking;
        out.state = TrackingState::Tracking;
        out.world_from_cam = pose;
        out.anchor = Some(self.anchor_to(r, &pose));
        let measured = self.work.res.stats.mean_flow_input_px / self.factor as f32;
        let (induced, in_view) = {
            let kf = &self.graph.kfs.slots[r];
            induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &pose, None)
        };
        let overlap = in_view.min(conf);
        if measured.max(induced) > self.cfg.keyframe_flow_px || overlap < self.cfg.keyframe_min_overlap {
            self.add_keyframe(frame, &mut out)?;
        }
        Ok(out)
    }

    /// A measured pose: updates the velocity and the last pose.
    pub(super) fn accept_pose(&mut self, pose: &Se3, seq: u64, frames_since: u64) {
        let xi = se3_log(&self.motion.last_pose.inv_mul(pose)) / frames_since.max(1) as f64;
        self.motion.velocity = se3_exp(&xi);
        self.motion.last_pose = *pose;
        self.motion.last_seq = seq;
    }
}
