//! The keyframe window: edge estimation (pair flow), window BA and its covariance.

use super::*;

/// The window BA: its workspace and the slots in the window.
pub(super) struct WindowBa {
    pub(super) ba: BaWorkspace,
    pub(super) window: Vec<usize>,
}

/// Loads `window` (keyframe slots, oldest first) and the live edges between them into `ba`.
pub(super) fn load_window(ba: &mut BaWorkspace, low: &PinholeCamera, kfs: &mut KeyframeStore, edges: &EdgeStore, window: &[usize], include_loops: bool) -> Result<(), BaError> {
    ba.begin(low)?;
    for &s in window {
        let kf = &mut kfs.slots[s];
        for d in kf.inv_depth.data.iter_mut() {
            if !(d.is_finite() && *d >= MIN_INV_DEPTH) {
                *d = MIN_INV_DEPTH;
            }
        }
        ba.add_keyframe(&kf.world_from_cam, &kf.inv_depth)?;
    }
    let max_edges = ba.capacity().max_edges;
    for &e in &edges.live {
        if ba.num_edges() >= max_edges {
            break;
        }
        let ed = &edges.edges[e];
        if ed.is_loop && !include_loops {
            continue;
        }
        let (Some(a), Some(b)) = (window.iter().position(|&s| s == ed.from), window.iter().position(|&s| s == ed.to)) else { continue };
        ba.add_edge(a, b, &ed.target, &ed.weight)?;
    }
    Ok(())
}

/// Writes the solved poses and depths of `window` back to the keyframes.
pub(super) fn write_back(ba: &BaWorkspace, kfs: &mut KeyframeStore, window: &[usize]) -> Result<(), BaError> {
    for (k, &s) in window.iter().enumerate() {
        let kf = &mut kfs.slots[s];
        if let Some(p) = ba.world_from_cam(k) {
            kf.world_from_cam = p;
        }
        ba.write_inv_depth(k, &mut kf.inv_depth)?;
    }
    Ok(())
}

impl State {
    pub(super) fn ba_config(&self, iterations: usize, fixed: usize) -> BaConfig {
        BaConfig { max_iterations: iterations, fixed_poses: fixed, ..self.cfg.ba }
    }

    /// Estimates the flow of every edge in `new_edges` (seeded by the current estimate) and
    /// stores the measurements. Consecutive edges `a -> b`, `b -> a` share one pair estimate.
    pub(super) fn estimate_new_edges(&mut self) -> Result<(), TrackError> {
        let mut i = 0;
        while i < self.graph.new_edges.len() {
            i += self.estimate_new_edge_at(i)?;
        }
        Ok(())
    }

    /// Estimates `new_edges[i]` (with `new_edges[i + 1]` when that is its reverse and
    /// `pair_edges` is on); returns how many edges it measured.
    pub(super) fn estimate_new_edge_at(&mut self, i: usize) -> Result<usize, TrackError> {
        let e = self.graph.new_edges[i];
        let reverse = self.graph.new_edges.get(i + 1).copied().filter(|_| self.cfg.pair_edges && self.init.phase == Phase::Running).filter(|&r| {
            let (a, b) = (&self.graph.edges.edges[e], &self.graph.edges.edges[r]);
            a.from == b.to && a.to == b.from
        });
        match reverse {
            Some(r) => {
                // Seeded from the older keyframe's depth (refined by earlier rounds; the
                // newer one's may only be splatted).
                let (ie, ir) = (self.graph.kfs.slots[self.graph.edges.edges[e].from].id, self.graph.kfs.slots[self.graph.edges.edges[r].from].id);
                let (p, q) = if ie <= ir { (e, r) } else { (r, e) };
                self.estimate_edge_pair(p, q)?;
                Ok(2)
            }
            None => {
                self.estimate_edge(e)?;
                Ok(1)
            }
        }
    }

    /// Edge `e` and its reverse `r` from one pair estimate seeded by the flow of `e` the
    /// current estimate induces (`r` gets the inverted seed).
    pub(super) fn estimate_edge_pair(&mut self, e: usize, r: usize) -> Result<(), TrackError> {
        let (from, to) = (self.graph.edges.edges[e].from, self.graph.edges.edges[e].to);
        let (kf, kt) = (&self.graph.kfs.slots[from], &self.graph.kfs.slots[to]);
        induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &kt.world_from_cam, Some(&mut self.work.seed));
        let t0 = Instant::now();
        let seed = if self.cfg.seed_edges { Some(&self.work.seed) } else { None };
        self.work.flow.estimate_pair(&kf.frame, &kt.frame, seed, &mut self.work.res, &mut self.work.res_reverse)?;
        self.stats.times.flow += t0.elapsed();
        self.stats.times.flow_estimates += 2;
        let edge = &mut self.graph.edges.edges[e];
        write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut edge.target, &mut edge.weight);
        let edge = &mut self.graph.edges.edges[r];
        write_measurement(&mut self.work.res_reverse, &self.cfg, self.ignore.as_deref(), &mut edge.target, &mut edge.weight);
        Ok(())
    }

    /// Estimates the flow of edge `e` seeded by the flow the current estimate induces, and
    /// stores its measurement. Returns the confident fraction.
    pub(super) fn estimate_edge(&mut self, e: usize) -> Result<f32, TrackError> {
        let (from, to) = (self.graph.edges.edges[e].from, self.graph.edges.edges[e].to);
        let (kf, kt) = (&self.graph.kfs.slots[from], &self.graph.kfs.slots[to]);
        induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &kt.world_from_cam, Some(&mut self.work.seed));
        let t0 = Instant::now();
        let seed = if self.cfg.seed_edges { Some(&self.work.seed) } else { None };
        self.work.flow.estimate(&kf.frame, &kt.frame, seed, &mut self.work.res)?;
        self.stats.times.flow += t0.elapsed();
        self.stats.times.flow_estimates += 1;
        let edge = &mut self.graph.edges.edges[e];
        Ok(write_measurement(&mut self.work.res, &self.cfg, self.ignore.as_deref(), &mut edge.target, &mut edge.weight))
    }

    /// Loads the window, solves, writes back; returns the final cost. A failed solve leaves
    /// the state as it was.
    pub(super) fn solve_window(&mut self, iterations: usize, fixed: usize) -> Option<f64> {
        let t0 = Instant::now();
        let cfg = self.ba_config(iterations, fixed);
        let r = load_window(&mut self.win.ba, &self.low, &mut self.graph.kfs, &self.graph.edges, &self.win.window, false)
            .and_then(|_| self.win.ba.solve(&cfg))
            .and_then(|report| write_back(&self.win.ba, &mut self.graph.kfs, &self.win.window).map(|_| report.final_cost));
        self.stats.times.ba += t0.elapsed();
        match r {
            Ok(cost) => Some(cost),
            Err(e) => {
                tracing::debug!(error = %e, "track: window BA failed");
                self.stats.counters.ba_failures += 1;
                None
            }
        }
    }

    /// Depth variance (Eq. 4) of every window keyframe at the loaded window's estimate.
    pub(super) fn window_covariance(&mut self, fixed: usize) {
        let t0 = Instant::now();
        let cfg = self.ba_config(1, fixed);
        let r = self.win.ba.compute_covariance(&cfg);
        if r.is_ok() {
            let unit = match (self.cfg.variance_from_residuals, self.win.ba.unit_variance()) {
                (true, Some(u)) if u.is_finite() && u > 0.0 => u as f32,
                _ => 1.0,
            };
            for (k, &s) in self.win.window.iter().enumerate() {
                let kf = &mut self.graph.kfs.slots[s];
                if self.win.ba.write_inv_depth_variance(k, &mut kf.variance).is_ok() {
                    for v in kf.variance.data.iter_mut() {
                        *v *= unit;
                        if !v.is_finite() {
                            *v = f32::MAX;
                        }
                    }
                    kf.has_variance = true;
                    kf.variance_unit = unit;
                }
            }
        } else {
            self.stats.counters.ba_failures += 1;
        }
        self.stats.times.covariance += t0.elapsed();
    }

    pub(super) fn window_fixed(&self) -> usize {
        let n = self.win.window.len();
        if n >= 4 {
            n.saturating_sub(self.cfg.window_free_poses).max(2)
        } else {
            1
        }
    }
}
