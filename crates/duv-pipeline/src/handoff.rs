//! What tracking hands on after each frame: the keyframes that are due for mapping and the
//! log (after [`PipelineConfig::keyframe_lag`](super::PipelineConfig) newer ones, so their
//! depth went through the window BA), and, every
//! [`PipelineConfig::window_interval`](super::PipelineConfig) of frame time, the tracker's
//! newest keyframes as a [`TrackerWindow`] for the log (what a resume seeds a tracker with).
//! One type for the threaded and the deterministic pipeline and for frames tracked again on
//! resume, so all three hand on the same things.
//!
//! Both are written into fixed pools ([`Pool`]) allocated here at start-up and shared with
//! mapping and the log by reference count: handing them on allocates nothing. A keyframe that
//! finds every slot held (mapping and the log both far behind) gets a fresh buffer instead:
//! nothing is lost, and the allocation shows in the tracking stage's count.

use super::pool::Pool;
use super::{apply, PipelineError};
use duv_core::{Frame, FrameImage, ImageRgb8, Keyframe, PinholeCamera, PlaneF32, Se3, Sim3, Timestamp};
use duv_log::{LogItem, TrackerWindow, WindowKeyframe};
use duv_track::{TrackOutput, Tracker};
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

/// Sizes of what tracking hands on.
pub(super) struct HandoffConfig {
    /// Newer keyframes a keyframe waits for.
    pub keyframe_lag: usize,
    /// Keyframe buffers (the keyframe queue, one in mapping, those in the log queue).
    pub keyframe_slots: usize,
    /// Newest keyframes in a window record (0: no window records).
    pub window_keyframes: usize,
    pub window_interval: Duration,
    pub align: Option<Sim3>,
}

pub(super) struct Handoff {
    lag: VecDeque<(u64, Arc<Frame>)>,
    keyframe_lag: usize,
    keyframes: Pool<Keyframe>,
    window: WindowLog,
    align: Option<Sim3>,
}

impl Handoff {
    /// Pools sized for `tracker`'s camera and depth grid.
    pub(super) fn new(cfg: HandoffConfig, tracker: &Tracker) -> Self {
        let cam = *tracker.camera();
        let grid = *tracker.depth_camera();
        let blank_window = || TrackerWindow {
            seq: 0,
            t_ns: Timestamp::from_ns(0),
            keyframes: (0..cfg.window_keyframes)
                .map(|_| WindowKeyframe { id: 0, seq: 0, t_ns: Timestamp::from_ns(0), world_from_cam: Se3::identity(), inv_depth: PlaneF32::new(grid.width, grid.height), variance: PlaneF32::new(grid.width, grid.height), has_variance: false })
                .collect(),
        };
        Handoff {
            lag: VecDeque::with_capacity(cfg.keyframe_lag + 1),
            keyframe_lag: cfg.keyframe_lag,
            keyframes: Pool::new(cfg.keyframe_slots, || blank_keyframe(&cam)),
            // One being logged, one waiting, one to fill.
            window: WindowLog {
                keyframes: cfg.window_keyframes,
                interval_ns: cfg.window_interval.as_nanos().min(i64::MAX as u128) as i64,
                last_t_ns: None,
                pool: Pool::new(if cfg.window_keyframes > 0 { 3 } else { 1 }, blank_window),
            },
            align: cfg.align,
        }
    }

    /// Keyframes the tracker already holds that are still to be handed on (a resume's, see
    /// [`PipelineConfig::unlogged_keyframes`](super::PipelineConfig)), oldest first.
    pub(super) fn adopt(&mut self, keyframes: &[(u64, Arc<Frame>)]) {
        for (id, frame) in keyframes {
            self.lag.push_back((*id, Arc::clone(frame)));
        }
    }

    /// After `tracker` tracked `frame` (`out`): each keyframe now due goes to `log` and then to
    /// `keyframe`; a window record, when one is due, to `log`.
    pub(super) fn after_frame(
        &mut self,
        tracker: &Tracker,
        frame: &Arc<Frame>,
        out: &TrackOutput,
        mut log: impl FnMut(LogItem),
        mut keyframe: impl FnMut(Arc<Keyframe>) -> Result<(), PipelineError>,
    ) -> Result<(), PipelineError> {
        if let Some(id) = out.new_keyframe {
            self.lag.push_back((id, Arc::clone(frame)));
        }
        while let Some(kf) = self.pop_ready(tracker, false) {
            log(LogItem::Keyframe(Arc::clone(&kf)));
            keyframe(kf)?;
        }
        if let Some(w) = self.window.due(tracker, out, self.align.as_ref()) {
            log(LogItem::Window(w));
        }
        Ok(())
    }

    /// End of the stream: every keyframe still waiting, to `log` and then `keyframe`.
    pub(super) fn flush(&mut self, tracker: &Tracker, mut log: impl FnMut(LogItem), mut keyframe: impl FnMut(Arc<Keyframe>) -> Result<(), PipelineError>) -> Result<(), PipelineError> {
        while let Some(kf) = self.pop_ready(tracker, true) {
            log(LogItem::Keyframe(Arc::clone(&kf)));
            keyframe(kf)?;
        }
        Ok(())
    }

    /// The next keyframe due (all of them when `flush`), with the tracker's current depth,
    /// variance and pose; keyframes the tracker no longer holds are skipped.
    fn pop_ready(&mut self, tracker: &Tracker, flush: bool) -> Option<Arc<Keyframe>> {
        while self.lag.len() > if flush { 0 } else { self.keyframe_lag } {
            let (id, frame) = self.lag.pop_front()?;
            let mut fresh = None;
            let mut slot = self.keyframes.take();
            let kf = match slot.as_mut() {
                Some(s) => s.get_mut(),
                None => {
                    tracing::debug!("keyframe {id}: every keyframe buffer is held downstream; a fresh one");
                    fresh.insert(blank_keyframe(tracker.camera()))
                }
            };
            if fill_keyframe(tracker, &frame, id, self.align.as_ref(), kf) {
                return Some(match (slot, fresh) {
                    (Some(s), _) => s.share(),
                    (None, Some(f)) => Arc::new(f),
                    (None, None) => unreachable!("a keyframe buffer was taken or made above"),
                });
            }
        }
        None
    }
}

/// A black keyframe buffer at the camera's size.
fn blank_keyframe(cam: &PinholeCamera) -> Keyframe {
    Keyframe {
        index: 0,
        t_ns: Timestamp::from_ns(0),
        image: ImageRgb8::new(cam.width, cam.height),
        world_from_cam: Se3::identity(),
        camera: *cam,
        inv_depth: PlaneF32::new(cam.width, cam.height),
        inv_depth_variance: PlaneF32::new(cam.width, cam.height),
    }
}

/// Writes keyframe `id` of the tracker at full resolution (for mapping and the log) into `kf`
/// without allocating; `false` when the tracker no longer holds it or it has no depth yet.
fn fill_keyframe(tracker: &Tracker, frame: &Frame, id: u64, world_from_tracker: Option<&Sim3>, kf: &mut Keyframe) -> bool {
    let Some(view) = tracker.keyframes().find(|k| k.id == id) else { return false };
    let world_from_cam = apply(world_from_tracker, &view.world_from_cam);
    if let Err(e) = tracker.upsample_keyframe(id, &mut kf.inv_depth, &mut kf.inv_depth_variance) {
        tracing::debug!("keyframe {id}: no depth yet: {e}");
        return false;
    }
    if let Some(a) = world_from_tracker {
        // Inverse depth scales with 1/s, its variance with 1/s^2.
        let s = a.scaling() as f32;
        kf.inv_depth.data.iter_mut().for_each(|d| *d /= s);
        kf.inv_depth_variance.data.iter_mut().for_each(|v| *v /= s * s);
    }
    copy_rgb(&frame.image, &mut kf.image);
    kf.index = id;
    kf.t_ns = frame.t_ns;
    kf.world_from_cam = world_from_cam;
    kf.camera = *tracker.camera();
    true
}

/// `image` as RGB into `out` (grey repeated over the channels), reusing its buffer.
fn copy_rgb(image: &FrameImage, out: &mut ImageRgb8) {
    out.width = image.width();
    out.height = image.height();
    out.data.clear();
    match image {
        FrameImage::Rgb8(i) => out.data.extend_from_slice(&i.data),
        FrameImage::Gray8(i) => {
            for &g in &i.data {
                out.data.extend_from_slice(&[g, g, g]);
            }
        }
    }
}

/// The window records: the newest `keyframes` of the tracker, at most once per `interval_ns`
/// of frame time, only after measured frames (not during initialisation or while lost).
struct WindowLog {
    keyframes: usize,
    interval_ns: i64,
    last_t_ns: Option<i64>,
    pool: Pool<TrackerWindow>,
}

impl WindowLog {
    fn due(&mut self, tracker: &Tracker, out: &TrackOutput, align: Option<&Sim3>) -> Option<Arc<TrackerWindow>> {
        let n = tracker.num_keyframes();
        if self.keyframes == 0 || n < 2 || !out.state.is_tracked() {
            return None;
        }
        let t = out.t_ns.t_ns();
        // A clock that jumps back (a new recording) starts the interval again.
        if self.last_t_ns.is_some_and(|l| t >= l && t - l < self.interval_ns) {
            return None;
        }
        // Every record still held by the log queue: skip this one (the next comes in time).
        let mut slot = self.pool.take()?;
        self.last_t_ns = Some(t);
        let w = slot.get_mut();
        w.seq = out.seq;
        w.t_ns = out.t_ns;
        // Inverse depth scales with 1/s, its variance with 1/s^2.
        let s = align.map_or(1.0, |a| a.scaling() as f32);
        let copy_scaled = |from: &PlaneF32, to: &mut PlaneF32, by: f32| {
            to.width = from.width;
            to.height = from.height;
            to.data.clear();
            to.data.extend(from.data.iter().map(|v| v * by));
        };
        let live = n.min(self.keyframes);
        for (k, wk) in tracker.keyframes().skip(n - live).zip(w.keyframes.iter_mut()) {
            wk.id = k.id;
            wk.seq = k.seq;
            wk.t_ns = k.t_ns;
            wk.world_from_cam = apply(align, &k.world_from_cam);
            copy_scaled(k.inv_depth, &mut wk.inv_depth, 1.0 / s);
            wk.has_variance = k.variance.is_some();
            if let Some(v) = k.variance {
                copy_scaled(v, &mut wk.variance, 1.0 / (s * s));
            }
        }
        // The records keep `self.keyframes` entries; a window not yet full logs the first `live`.
        let record = slot.share();
        if live == self.keyframes {
            Some(record)
        } else {
            Some(Arc::new(TrackerWindow { seq: record.seq, t_ns: record.t_ns, keyframes: record.keyframes[..live].to_vec() }))
        }
    }
}
