//! Resume seeding: a tracker started from logged keyframes.

use super::*;

/// A keyframe an earlier run recorded, to seed a new tracker with ([`Tracker::seed`]): the
/// keyframe as the pipeline logged it (id, time, image, pose in the recorded world frame,
/// full-resolution inverse depth and variance) and the frame number of its image.
#[derive(Clone, Copy, Debug)]
pub struct SeedKeyframe<'a> {
    pub seq: u64,
    pub keyframe: &'a duv_core::Keyframe,
}

/// Where a seeded tracker picks the motion up: the pose of frame `seq` and the motion per
/// frame (`velocity = prev_from_cam`, what the constant-velocity prediction applies).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ResumePoint {
    pub seq: u64,
    pub world_from_cam: Se3,
    pub velocity: Se3,
}

/// A frame an earlier run recorded a measured pose for, without depth, to seed a new tracker
/// with ([`Tracker::seed`]): it becomes a keyframe at its recorded pose, its depth triangulated
/// from the recorded poses.
#[derive(Clone, Copy, Debug)]
pub struct SeedFrame<'a> {
    pub frame: &'a Frame,
    pub world_from_cam: Se3,
}

/// What [`Tracker::seed`] starts a tracker from.
#[derive(Clone, Copy, Debug)]
pub struct TrackerSeed<'a> {
    /// Recorded keyframes, oldest first (ids increasing); their poses and depths set the
    /// frame and the scale the tracker continues in.
    pub keyframes: &'a [SeedKeyframe<'a>],
    /// Recorded frames with measured poses, newer than every keyframe, oldest first.
    pub frames: &'a [SeedFrame<'a>],
    /// Where tracking continues; `None`: at the newest keyframe, with the mean motion per frame
    /// between the two newest.
    pub resume: Option<ResumePoint>,
    /// New keyframes get ids from here on at least (ids an earlier run gave out but did not
    /// log), and always after the newest seeded id.
    pub next_keyframe_id: u64,
}

impl State {
    /// See [`Tracker::seed`].
    pub(super) fn seed(&mut self, seed: &TrackerSeed<'_>) -> Result<(), TrackError> {
        if self.init.phase != Phase::Empty || self.graph.kfs.len() > 0 {
            return Err(TrackError::NotEmpty);
        }
        let (w, h) = (self.camera.width, self.camera.height);
        let seeds = seed.keyframes;
        if seeds.len() + seed.frames.len() < 2 && seed.keyframes.is_empty() {
            return Err(TrackError::NoSeedKeyframes);
        }
        if seed.frames.len() > self.cap.ba_window {
            return Err(TrackError::Capacity { field: "ba_window", value: self.cap.ba_window, problem: "fewer than the frames to seed" });
        }
        for sf in seed.frames {
            let f = sf.frame;
            if f.image.width() != w || f.image.height() != h {
                return Err(TrackError::FrameSize { seq: f.seq, width: f.image.width(), height: f.image.height(), expected_width: w, expected_height: h });
            }
            if duv_core::pose::se3_to_tum(&sf.world_from_cam).iter().any(|x| !x.is_finite()) {
                return Err(TrackError::BadSeedKeyframe { id: f.seq, problem: "seed frame pose not finite" });
            }
        }
        if seeds.len() + seed.frames.len() > self.graph.kfs.capacity() {
            return Err(TrackError::Capacity { field: "max_keyframes", value: self.graph.kfs.capacity(), problem: "fewer than the keyframes to seed" });
        }
        let mut prev_id: Option<u64> = None;
        for sk in seeds {
            let k = sk.keyframe;
            let id = k.index;
            for (what, width, height) in [("image", k.image.width, k.image.height), ("inverse depth", k.inv_depth.width, k.inv_depth.height), ("variance", k.inv_depth_variance.width, k.inv_depth_variance.height)] {
                if width != w || height != h {
                    return Err(TrackError::SeedSize { id, what, width, height, expected_width: w, expected_height: h });
                }
            }
            if !k.is_consistent() {
                return Err(TrackError::BadSeedKeyframe { id, problem: "a plane's data does not match its size" });
            }
            let v = duv_core::pose::se3_to_tum(&k.world_from_cam);
            if v.iter().any(|x| !x.is_finite()) {
                return Err(TrackError::BadSeedKeyframe { id, problem: "pose not finite" });
            }
            if prev_id.is_some_and(|p| id <= p) {
                return Err(TrackError::BadSeedKeyframe { id, problem: "ids must increase (oldest first)" });
            }
            prev_id = Some(id);
        }
        for sk in seeds {
            let k = sk.keyframe;
            rgb_to_grey(&k.image, &mut self.work.grey);
            self.despeckle_grey();
            let t0 = Instant::now();
            self.work.flow.prepare_into(&self.work.grey, &mut self.work.cur)?;
            self.stats.times.flow += t0.elapsed();
            let s = self.graph.kfs.push_with_id(k.index).expect("ids increase and a slot is free");
            self.fill_keyframe_slot(s, k.t_ns, sk.seq, &k.world_from_cam);
            let kf = &mut self.graph.kfs.slots[s];
            plane_block_means(&k.inv_depth, self.factor, &mut kf.inv_depth, MIN_INV_DEPTH);
            for d in kf.inv_depth.data.iter_mut() {
                *d = d.max(MIN_INV_DEPTH);
            }
            plane_block_means(&k.inv_depth_variance, self.factor, &mut kf.variance, f32::MAX);
            kf.has_variance = true;
            // The recorded variance is metric; the unit weight it was scaled by is not logged.
            kf.variance_unit = f32::NAN;
        }
        self.graph.kfs.reserve_ids_below(seed.next_keyframe_id);
        for sf in seed.frames {
            to_grey(&sf.frame.image, &mut self.work.grey);
            self.despeckle_grey();
            let t0 = Instant::now();
            self.work.flow.prepare_into(&self.work.grey, &mut self.work.cur)?;
            self.stats.times.flow += t0.elapsed();
            let s = self.graph.kfs.push().expect("a slot is free");
            self.fill_keyframe_slot(s, sf.frame.t_ns, sf.frame.seq, &sf.world_from_cam);
            // Depth: the previous seed's splatted in, or constant (triangulated below).
            match self.graph.kfs.len() {
                1 => self.graph.kfs.slots[s].inv_depth.data.fill(self.cfg.initial_inv_depth),
                n => self.splat_depth(self.graph.kfs.order[n - 2], s),
            }
        }
        // Links as an insertion makes them: each keyframe to up to `edges_per_keyframe` older
        // ones that see the same scene, both directions, measured from one pair estimate.
        self.init.phase = Phase::Running;
        self.segments.initialised_once = true;
        self.graph.new_edges.clear();
        let n = self.graph.kfs.len();
        for pos in 1..n {
            let s = self.graph.kfs.order[pos];
            let mut links = 0;
            for back in 1..=pos {
                if links >= self.cfg.edges_per_keyframe {
                    break;
                }
                let c = self.graph.kfs.order[pos - back];
                let (ks, kc) = (&self.graph.kfs.slots[s], &self.graph.kfs.slots[c]);
                let (flow, overlap) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kc.world_from_cam, None);
                if back == 1 || (flow <= self.cfg.edge_max_flow_px && overlap >= self.cfg.edge_min_overlap) {
                    for (f, t) in [(s, c), (c, s)] {
                        if let Some(e) = self.graph.edges.add(f, t, false) {
                            self.graph.new_edges.push(e);
                        }
                    }
                    links += 1;
                }
            }
        }
        self.estimate_new_edges()?;
        // Depth from the recorded poses: flow/BA rounds over the newest seeds with every
        // pose fixed (depth only). Seed frames have none yet; seeded keyframes have their
        // logged depth, but the newest may have been logged before the rounds an insertion
        // spreads over the next frames had run (frames tracked against it then drifted by
        // up to 0.7 cm per frame in the crash harness until the next keyframe).
        self.win.window.clear();
        self.win.window.extend_from_slice(&self.graph.kfs.order[n.saturating_sub(self.cap.ba_window)..]);
        let fixed = self.win.window.len();
        self.solve_window(self.cfg.init_iterations, fixed);
        for _ in 1..self.cfg.init_rounds {
            self.estimate_new_edges()?;
            self.solve_window(self.cfg.init_iterations, fixed);
        }
        self.window_covariance(fixed);
        self.graph.new_edges.clear();
        let newest = self.graph.kfs.newest().expect("seeded");
        self.motion.ref_slot = newest;
        self.motion.state = TrackingState::Tracking;
        self.work.have_prev_flow = false;
        self.loops.inserted_since_loop = 0;
        self.loops.inserted_since_global = 0;
        self.insert.pending = None;
        match seed.resume {
            Some(r) => {
                self.motion.last_pose = r.world_from_cam;
                self.motion.last_seq = r.seq;
                self.motion.velocity = r.velocity;
            }
            None => {
                let last = &self.graph.kfs.slots[newest];
                self.motion.last_pose = last.world_from_cam;
                self.motion.last_seq = last.seq;
                self.motion.velocity = Se3::identity();
                if n >= 2 {
                    let before = &self.graph.kfs.slots[self.graph.kfs.order[n - 2]];
                    let frames = last.seq.saturating_sub(before.seq).max(1) as f64;
                    self.motion.velocity = se3_exp(&(se3_log(&before.world_from_cam.inv_mul(&last.world_from_cam)) / frames));
                }
            }
        }
        Ok(())
    }
}
