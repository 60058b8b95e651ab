//! Relocalisation against stored keyframes after a loss.

use super::*;

/// Relocalisation: stored keyframes ranked against the current frame (NCC, slot), best first.
pub(super) struct Reloc {
    pub(super) candidates: Vec<(f32, usize)>,
}

/// Frames after the last pose during which a lost frame still tries turned predictions.
const TURN_SEARCH_FRAMES: u64 = 3;

impl State {
    /// Lost: try the reference keyframe with the predicted pose, then appearance candidates.
    pub(super) fn relocalise(&mut self, frame: &Frame, mut out: TrackOutput) -> Result<TrackOutput, TrackError> {
        let w = self.camera.width;
        thumbnail(&self.work.grey.data, w, self.camera.height, &mut self.work.cur_thumb);
        // The reference keyframe first, seeded by the prediction (a short outage).
        let r = self.motion.ref_slot;
        let predicted = out.world_from_cam;
        {
            let kf = &self.graph.kfs.slots[r];
            induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &predicted, Some(&mut self.work.seed));
        }
        if let Some(pose) = self.try_relocalise_against(r, Some(predicted))? {
            return Ok(self.relocalised(out, r, pose, frame.seq));
        }
        // A turn is a short failure: tried only within a few frames of the last pose (a long
        // loss would pay four more flows a frame for nothing).
        if frame.seq.saturating_sub(self.motion.last_seq) <= TURN_SEARCH_FRAMES {
            if let Some(pose) = self.try_turns(r, &predicted)? {
                return Ok(self.relocalised(out, r, pose, frame.seq));
            }
        }
        self.rank_candidates(None, self.graph.kfs.len(), false, self.cfg.reloc_min_ncc);
        for k in 0..self.reloc.candidates.len() {
            let c = self.reloc.candidates[k].1;
            if c == r {
                continue;
            }
            if let Some(pose) = self.try_relocalise_against(c, None)? {
                return Ok(self.relocalised(out, c, pose, frame.seq));
            }
        }
        out.world_from_cam = predicted;
        let out = self.lost(out, LostReason::NotRelocalised);
        // Relocalisation against every stored keyframe failed: new territory after a while.
        self.maybe_start_segment(frame, out)
    }

    /// Flow from keyframe `c` (seeded by `self.work.seed` when `predicted` is given) and
    /// motion-only BA; the pose when the match is verified.
    pub(super) fn try_relocalise_against(&mut self, c: usize, predicted: Option<Se3>) -> Result<Option<Se3>, TrackError> {
        self.flow_ref_to_current(c, predicted.is_some(), true)?;
        let conf = write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut self.work.obs_target, &mut self.work.obs_weight);
        let mean_flow = self.work.res.stats.mean_flow_input_px / self.factor as f32;
        if conf < self.cfg.min_confident_fraction.max(self.cfg.loop_min_confident_fraction) || mean_flow > self.cfg.reloc_max_flow_px {
            return Ok(None);
        }
        let mut pose = predicted.unwrap_or(self.graph.kfs.slots[c].world_from_cam);
        if self.motion_only(c, &mut pose).is_err() {
            return Ok(None);
        }
        Ok(Some(pose))
    }

    /// `predicted` turned about the camera's vertical (y) axis by +-1 and +-2 `turn_search_deg`
    /// (see its doc): the first turn whose flow from keyframe `r`, seeded by it, is confident
    /// on `loop_min_confident_fraction` of the pixels and whose motion-only BA converges.
    /// The measurement of the turn taken is left in the frame buffers.
    pub(super) fn try_turns(&mut self, r: usize, predicted: &Se3) -> Result<Option<Se3>, TrackError> {
        let step = (self.cfg.turn_search_deg as f64).to_radians();
        if step <= 0.0 {
            return Ok(None);
        }
        let need = self.cfg.min_confident_fraction.max(self.cfg.loop_min_confident_fraction);
        for k in [1.0, -1.0, 2.0, -2.0] {
            let turn = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::y_axis(), k * step);
            let hypothesis = Se3::from_parts(predicted.translation, predicted.rotation * turn);
            {
                let kf = &self.graph.kfs.slots[r];
                induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &hypothesis, Some(&mut self.work.seed));
            }
            self.flow_ref_to_current(r, true, true)?;
            let conf = write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut self.work.obs_target, &mut self.work.obs_weight);
            if conf < need {
                continue;
            }
            let mut pose = hypothesis;
            if self.motion_only(r, &mut pose).is_ok() {
                self.stats.counters.turns_found += 1;
                tracing::debug!(turn_deg = k * step.to_degrees(), conf, "track: pose found at a turned prediction");
                return Ok(Some(pose));
            }
        }
        Ok(None)
    }

    pub(super) fn relocalised(&mut self, mut out: TrackOutput, c: usize, pose: Se3, seq: u64) -> TrackOutput {
        // Tracking goes on in the keyframe's segment (an older one, when the vehicle came back).
        let segment = self.graph.kfs.slots[c].segment;
        if segment != self.segments.current {
            tracing::info!(seq, from = self.segments.current, to = segment, "track: relocalised into another map segment");
            self.segments.current = segment;
        }
        self.segments.failed_relocs = 0;
        self.motion.ref_slot = c;
        self.motion.velocity = Se3::identity();
        self.motion.last_pose = pose;
        self.motion.last_seq = seq;
        self.motion.state = TrackingState::Relocalised;
        self.stats.counters.relocalisations += 1;
        out.state = TrackingState::Relocalised;
        out.world_from_cam = pose;
        out.anchor = Some(self.anchor_to(c, &pose));
        out
    }
}
