//! What tracking hands on after each frame: the keyframes the tracker emits as final for
//! mapping and the log (after [`PipelineConfig::keyframe_lag`](super::PipelineConfig) newer
//! ones, so their depth went through the window BA: [`Tracker::next_final_keyframe`] writes
//! them into our pooled slots, we add the image and the resume alignment), and, every
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
    /// The frames of the keyframes the tracker has not emitted yet, in its order.
    frames: VecDeque<(u64, Arc<Frame>)>,
    keyframe_lag: usize,
    keyframes: Pool<Keyframe>,
    window: WindowLog,
    align: Option<Sim3>,
}

impl Handoff {
    /// Pools sized for `tracker`'s camera and depth grid; turns on `tracker`'s keyframe
    /// emission after `cfg.keyframe_lag` newer keyframes.
    pub(super) fn new(cfg: HandoffConfig, tracker: &mut Tracker) -> Self {
        tracker.emit_keyframes_after(cfg.keyframe_lag);
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
            frames: VecDeque::with_capacity(tracker.capacity().max_keyframes + 1),
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
    pub(super) fn adopt(&mut self, tracker: &mut Tracker, keyframes: &[(u64, Arc<Frame>)]) {
        for (id, frame) in keyframes {
            self.frames.push_back((*id, Arc::clone(frame)));
        }
        tracker.emit_held_keyframes(keyframes.iter().map(|(id, _)| *id));
    }

    /// After `tracker` tracked `frame` (`out`): each keyframe now due goes to `log` and then to
    /// `keyframe`; a window record, when one is due, to `log`.
    pub(super) fn after_frame(
        &mut self,
        tracker: &mut Tracker,
        frame: &Arc<Frame>,
        out: &TrackOutput,
        mut log: impl FnMut(LogItem),
        mut keyframe: impl FnMut(Arc<Keyframe>) -> Result<(), PipelineError>,
    ) -> Result<(), PipelineError> {
        if let duv_track::TrackNote::InitRestarted { .. } = out.note {
            // The keyframes collected before the restart will never be emitted: their frames go.
            self.frames.retain(|(id, _)| tracker.keyframes_waiting().any(|w| w == *id));
        }
        if let Some(id) = out.new_keyframe {
            self.frames.push_back((id, Arc::clone(frame)));
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
    pub(super) fn flush(&mut self, tracker: &mut Tracker, mut log: impl FnMut(LogItem), mut keyframe: impl FnMut(Arc<Keyframe>) -> Result<(), PipelineError>) -> Result<(), PipelineError> {
        // A global BA still in the background lands before the last keyframes go.
        tracker.finish_global_ba();
        while let Some(kf) = self.pop_ready(tracker, true) {
            log(LogItem::Keyframe(Arc::clone(&kf)));
            keyframe(kf)?;
        }
        Ok(())
    }

    /// The next keyframe the tracker emits as final (all waiting ones when `flush`), with its
    /// image and the alignment applied, in a pooled buffer.
    fn pop_ready(&mut self, tracker: &mut Tracker, flush: bool) -> Option<Arc<Keyframe>> {
        if tracker.keyframes_waiting().len() <= if flush { 0 } else { self.keyframe_lag } {
            // Nothing due: no buffer taken.
            return None;
        }
        let mut fresh = None;
        let mut slot = self.keyframes.take();
        let kf = match slot.as_mut() {
            Some(s) => s.get_mut(),
            None => {
                tracing::debug!("every keyframe buffer is held downstream; a fresh one");
                fresh.insert(blank_keyframe(tracker.camera()))
            }
        };
        let emitted = tracker.next_final_keyframe(flush, kf);
        // The frames of keyframes the tracker skipped (no longer held, no depth) go too.
        let waiting = tracker.keyframes_waiting().len();
        let mut frame = None;
        while self.frames.len() > waiting {
            let (id, f) = self.frames.pop_front()?;
            if Some(id) == emitted {
                frame = Some(f);
            }
        }
        let Some(frame) = frame else {
            if let Some(id) = emitted {
                tracing::warn!("keyframe {id}: emitted by the tracker but its frame is not held; not handed on");
            }
            return None;
        };
        finish_keyframe(&frame, self.align.as_ref(), kf);
        Some(match (slot, fresh) {
            (Some(s), _) => s.share(),
            (None, Some(f)) => Arc::new(f),
            (None, None) => unreachable!("a keyframe buffer was taken or made above"),
        })
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

/// Completes keyframe `kf` as the tracker emitted it: its frame's image and time, and the
/// resume alignment `world_from_tracker` applied to its pose and depth.
fn finish_keyframe(frame: &Frame, world_from_tracker: Option<&Sim3>, kf: &mut Keyframe) {
    kf.world_from_cam = apply(world_from_tracker, &kf.world_from_cam);
    if let Some(a) = world_from_tracker {
        // Inverse depth scales with 1/s, its variance with 1/s^2.
        let s = a.scaling() as f32;
        kf.inv_depth.data.iter_mut().for_each(|d| *d /= s);
        kf.inv_depth_variance.data.iter_mut().for_each(|v| *v /= s * s);
    }
    copy_rgb(&frame.image, &mut kf.image);
    kf.t_ns = frame.t_ns;
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
/// of frame time, only after measured frames (not during initialisation or while lost). Only
/// map segment 0's (the dive's world frame, the one the map is built in): a resume continues
/// in it, and a vehicle that was elsewhere starts a new segment from there.
struct WindowLog {
    keyframes: usize,
    interval_ns: i64,
    last_t_ns: Option<i64>,
    pool: Pool<TrackerWindow>,
}

impl WindowLog {
    fn due(&mut self, tracker: &Tracker, out: &TrackOutput, align: Option<&Sim3>) -> Option<Arc<TrackerWindow>> {
        let n = tracker.keyframes().filter(|k| k.segment == 0).count();
        if self.keyframes == 0 || n < 2 || !out.state.is_tracked() || out.segment != 0 {
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
        for (k, wk) in tracker.keyframes().filter(|k| k.segment == 0).skip(n - live).zip(w.keyframes.iter_mut()) {
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
