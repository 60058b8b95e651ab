//! The dense global BA off the tracking thread.
//!
//! A global BA over every keyframe (after a loop closure, or periodic) is the tracker's
//! longest piece of work: about half a second over 64 keyframes at 320x240 on one core. On the
//! tracking thread it held up every frame queued behind it. With `global_ba_lag_frames > 0` it
//! runs on a worker thread of its own instead, while tracking goes on:
//!
//! - **Start** (tracking thread): the current segment's keyframes and edges are copied into the
//!   global BA's workspace ([`super::window::load_window`]), with each keyframe's id and pose
//!   at that moment, and the worker is woken.
//! - **Meanwhile** tracking, keyframe insertion and local BA go on with the map as it was.
//! - **Apply** (tracking thread), exactly `global_ba_lag_frames` frames after the start (it
//!   waits for the worker if it is not done, counted in `global_ba_waits`): every keyframe of
//!   the solve that is still live takes the solved pose, with what local BA moved it since the
//!   start on top (`solved * at_start^-1 * now`), and the solved inverse depth; a keyframe
//!   inserted since then moves with the newest solved one; the motion model follows its
//!   reference keyframe. A keyframe evicted meanwhile is skipped (its slot may hold another).
//!
//! The apply frame is counted in frames, not time, so a run and its `--deterministic` replay
//! give the same trajectory whatever the machine's load. A second global BA (another loop)
//! applies the pending one first; so do the end of the stream and
//! [`Tracker::global_bundle_adjustment`](super::Tracker::global_bundle_adjustment).
//!
//! The workspace lives in a mutex the worker holds while it solves; the tracking thread only
//! locks it to load and to apply. The worker thread is started with the tracker (its stack is
//! the only allocation) and nothing is allocated per job. Hand-written rather than a pool
//! crate's task: a rayon task would share the tracker's workers (a frame's flow would queue
//! behind BA chunks), and the job must hand a preallocated workspace back without allocating.

use super::*;
use crate::ba::BaReport;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

/// What the worker and the tracking thread share.
pub(super) struct Job {
    pub(super) ws: BaWorkspace,
    cfg: BaConfig,
    requested: bool,
    result: Option<Result<BaReport, BaError>>,
    shutdown: bool,
}

struct Shared {
    job: Mutex<Job>,
    cv: Condvar,
}

/// The global BA's workspace and, when the BA runs in the background, its worker.
pub(super) struct BackgroundBa {
    shared: Arc<Shared>,
    worker: Option<JoinHandle<()>>,
    capacity: BaCapacity,
}

fn lock(shared: &Shared) -> MutexGuard<'_, Job> {
    shared.job.lock().unwrap_or_else(|p| p.into_inner())
}

impl BackgroundBa {
    /// `background`: start a worker thread (else every solve runs on the caller's thread).
    pub(super) fn new(ws: BaWorkspace, background: bool) -> Result<Self, TrackError> {
        let capacity = ws.capacity();
        let shared = Arc::new(Shared { job: Mutex::new(Job { ws, cfg: BaConfig::default(), requested: false, result: None, shutdown: false }), cv: Condvar::new() });
        let worker = if background {
            let sh = Arc::clone(&shared);
            let handle = std::thread::Builder::new()
                .name("duv-track-gba".into())
                .spawn(move || {
                    duv_core::alloc::label_current_thread(duv_core::alloc::ThreadRole::Tracking);
                    warm_up_thread_locals();
                    let mut job = lock(&sh);
                    loop {
                        while !job.requested && !job.shutdown {
                            job = sh.cv.wait(job).unwrap_or_else(|p| p.into_inner());
                        }
                        if job.shutdown {
                            return;
                        }
                        job.requested = false;
                        let cfg = job.cfg;
                        let _span = tracing::debug_span!("track.global_ba.background").entered();
                        let r = job.ws.solve(&cfg);
                        job.result = Some(r);
                        sh.cv.notify_all();
                    }
                })
                .map_err(|e| TrackError::ThreadPool(format!("global BA worker: {e}")))?;
            Some(handle)
        } else {
            None
        };
        Ok(BackgroundBa { shared, worker, capacity })
    }

    pub(super) fn capacity(&self) -> BaCapacity {
        self.capacity
    }

    pub(super) fn in_background(&self) -> bool {
        self.worker.is_some()
    }

    /// The workspace, to load (no job may be running: the caller applied the last one).
    pub(super) fn lock(&self) -> MutexGuard<'_, Job> {
        lock(&self.shared)
    }

    /// Solves the loaded workspace on the worker.
    pub(super) fn start(&self, mut job: MutexGuard<'_, Job>, cfg: BaConfig) {
        job.cfg = cfg;
        job.result = None;
        job.requested = true;
        drop(job);
        self.shared.cv.notify_all();
    }

    /// Waits for the job started last; returns the workspace with its result, and whether the
    /// worker was still solving when this was called.
    pub(super) fn wait(&self) -> (MutexGuard<'_, Job>, Result<BaReport, BaError>, bool) {
        // The worker holds the lock while it solves: a lock that is not free at once is a wait.
        let (mut job, mut waited) = match self.shared.job.try_lock() {
            Ok(job) => (job, false),
            Err(std::sync::TryLockError::Poisoned(p)) => (p.into_inner(), false),
            Err(std::sync::TryLockError::WouldBlock) => (lock(&self.shared), true),
        };
        loop {
            if let Some(r) = job.result.take() {
                return (job, r, waited);
            }
            waited = true;
            job = self.shared.cv.wait(job).unwrap_or_else(|p| p.into_inner());
        }
    }
}

/// The matrix kernels faer calls (the `gemm` crate) keep a packing buffer per thread, made on
/// the thread's first large product: made here, at start, so that the first global BA on this
/// thread allocates nothing. A Cholesky factorisation and a product of the size of a global
/// BA's reduced camera system.
fn warm_up_thread_locals() {
    let n = 256;
    let m = faer::Mat::<f64>::from_fn(n, n, |i, j| if i == j { n as f64 } else { 1.0 / (1.0 + (i + j) as f64) });
    let product = &m * &m;
    let _ = std::hint::black_box(product.llt(faer::Side::Lower).is_ok());
}

impl Drop for BackgroundBa {
    fn drop(&mut self) {
        if let Some(handle) = self.worker.take() {
            lock(&self.shared).shutdown = true;
            self.shared.cv.notify_all();
            let _ = handle.join();
        }
    }
}

/// The global BA started and not yet applied.
pub(super) struct PendingGlobalBa {
    /// `StageTimes::frames` when it started.
    pub(super) started_frame: u64,
    pub(super) segment: u32,
    /// The solve's keyframes: (slot, id, pose at the start), in window order.
    pub(super) window: Vec<(usize, u64, Se3)>,
}

impl State {
    /// Loads and starts a global BA over the current segment's keyframes (or, without a
    /// worker, solves and applies it now). A pending one is applied first. Returns whether one
    /// was started (or ran).
    pub(super) fn global_ba(&mut self) -> bool {
        self.finish_global_ba();
        self.window_of_current_segment(usize::MAX);
        let n = self.win.window.len();
        if n < 3 || self.loops.gba.capacity().max_keyframes < n || !self.in_current_segment(self.motion.ref_slot) {
            return false;
        }
        let t0 = Instant::now();
        let cfg = self.ba_config(self.cfg.global_iterations, 1);
        let mut job = self.loops.gba.lock();
        if let Err(e) = load_window(&mut job.ws, &self.low, &mut self.graph.kfs, &self.graph.edges, &self.win.window, true) {
            drop(job);
            tracing::debug!(error = %e, "track: global BA failed to load");
            self.stats.counters.ba_failures += 1;
            self.loops.inserted_since_global = 0;
            self.stats.times.global_ba += t0.elapsed();
            return false;
        }
        let p = &mut self.loops.pending_gba;
        p.window.clear();
        for &s in &self.win.window {
            let kf = &self.graph.kfs.slots[s];
            p.window.push((s, kf.id, kf.world_from_cam));
        }
        p.started_frame = self.stats.times.frames;
        p.segment = self.segments.current;
        self.loops.inserted_since_global = 0;
        if self.loops.gba.in_background() && self.cfg.global_ba_lag_frames > 0 {
            self.loops.gba.start(job, cfg);
            self.loops.gba_running = true;
            self.stats.times.global_ba += t0.elapsed();
            return true;
        }
        let r = job.ws.solve(&cfg);
        drop(job);
        self.loops.gba_running = true;
        let applied = self.apply_global_ba(Some(r));
        self.stats.times.global_ba += t0.elapsed();
        applied
    }

    /// Applies the pending global BA when it is due (`global_ba_lag_frames` frames after its
    /// start).
    pub(super) fn global_ba_if_due(&mut self) {
        if self.loops.gba_running && self.stats.times.frames.saturating_sub(self.loops.pending_gba.started_frame) >= self.cfg.global_ba_lag_frames as u64 {
            self.finish_global_ba();
        }
    }

    /// Applies the pending global BA now (waiting for its worker). Returns whether it moved
    /// the map.
    pub(super) fn finish_global_ba(&mut self) -> bool {
        if !self.loops.gba_running {
            return false;
        }
        let t0 = Instant::now();
        let applied = self.apply_global_ba(None);
        self.stats.times.global_ba += t0.elapsed();
        applied
    }

    /// Writes a solved global BA back (see the module doc); `solved`: the result when it ran on
    /// this thread (else the worker's is waited for).
    fn apply_global_ba(&mut self, solved: Option<Result<BaReport, BaError>>) -> bool {
        self.loops.gba_running = false;
        let (job, r) = match solved {
            Some(r) => (self.loops.gba.lock(), r),
            None => {
                let (job, r, waited) = self.loops.gba.wait();
                if waited {
                    self.stats.counters.global_ba_waits += 1;
                }
                (job, r)
            }
        };
        if let Err(e) = r {
            tracing::debug!(error = %e, "track: global BA failed");
            self.stats.counters.ba_failures += 1;
            return false;
        }
        let ref_before = self.graph.kfs.slots[self.motion.ref_slot].world_from_cam;
        let p = &self.loops.pending_gba;
        let mut newest: Option<(u64, Se3)> = None;
        for (k, &(s, id, at_start)) in p.window.iter().enumerate() {
            if self.graph.kfs.position(s).is_none() || self.graph.kfs.slots[s].id != id {
                continue;
            }
            let kf = &mut self.graph.kfs.slots[s];
            let Some(solved) = job.ws.world_from_cam(k) else { continue };
            let now = kf.world_from_cam;
            let after = solved * at_start.inv_mul(&now);
            kf.world_from_cam = after;
            if let Err(e) = job.ws.write_inv_depth(k, &mut kf.inv_depth) {
                tracing::debug!(error = %e, "track: global BA depth write-back failed");
            }
            newest = Some((id, after * now.inverse()));
        }
        drop(job);
        // Keyframes inserted since the start (newer ids, same segment) move with the newest
        // solved one.
        if let Some((newest_id, correction)) = newest {
            let segment = self.loops.pending_gba.segment;
            for &s in &self.graph.kfs.order {
                let kf = &mut self.graph.kfs.slots[s];
                if kf.id > newest_id && kf.segment == segment {
                    kf.world_from_cam = correction * kf.world_from_cam;
                }
            }
        }
        let ref_after = self.graph.kfs.slots[self.motion.ref_slot].world_from_cam;
        self.motion.last_pose = ref_after * ref_before.inv_mul(&self.motion.last_pose);
        self.stats.counters.global_bas += 1;
        true
    }
}
