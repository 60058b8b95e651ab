//! What tracking hands on after each frame: the keyframes that are due for mapping and the
//! log (after [`PipelineConfig::keyframe_lag`](super::PipelineConfig) newer ones, so their
//! depth went through the window BA), and, every
//! [`PipelineConfig::window_interval`](super::PipelineConfig) of frame time, the tracker's
//! newest keyframes as a [`TrackerWindow`] for the log (what a resume seeds a tracker with).
//! One type for the threaded and the deterministic pipeline and for frames tracked again on
//! resume, so all three hand on the same things.

use super::{apply, PipelineError};
use crate::core::{Frame, Keyframe, PlaneF32, Sim3};
use crate::log::{LogItem, TrackerWindow, WindowKeyframe};
use crate::track::{TrackOutput, Tracker};
use std::collections::VecDeque;
use std::time::Duration;

pub(super) struct Handoff {
    lag: KeyframeLag,
    window: WindowLog,
    align: Option<Sim3>,
}

impl Handoff {
    /// `keyframe_lag`: newer keyframes a keyframe waits for; `window_keyframes` newest
    /// keyframes logged every `window_interval` (0: none).
    pub(super) fn new(
        keyframe_lag: usize,
        window_keyframes: usize,
        window_interval: Duration,
        align: Option<Sim3>,
    ) -> Self {
        Handoff {
            lag: KeyframeLag {
                lag: keyframe_lag,
                pending: VecDeque::with_capacity(keyframe_lag + 1),
            },
            window: WindowLog {
                keyframes: window_keyframes,
                interval_ns: window_interval.as_nanos().min(i64::MAX as u128) as i64,
                last_t_ns: None,
            },
            align,
        }
    }

    /// After `tracker` tracked `frame` (`out`): each keyframe now due goes to `log` and then to
    /// `keyframe`; a window record, when one is due, to `log`.
    pub(super) fn after_frame(
        &mut self,
        tracker: &Tracker,
        frame: &Frame,
        out: &TrackOutput,
        mut log: impl FnMut(LogItem),
        mut keyframe: impl FnMut(Keyframe) -> Result<(), PipelineError>,
    ) -> Result<(), PipelineError> {
        if let Some(id) = out.new_keyframe {
            self.lag.pending.push_back((id, frame.clone()));
        }
        while let Some(kf) = self.lag.pop_ready(tracker, self.align.as_ref(), false) {
            log(LogItem::Keyframe(Box::new(kf.clone())));
            keyframe(kf)?;
        }
        if let Some(w) = self.window.due(tracker, out, self.align.as_ref()) {
            log(LogItem::Window(Box::new(w)));
        }
        Ok(())
    }

    /// End of the stream: every keyframe still waiting, to `log` and then `keyframe`.
    pub(super) fn flush(
        &mut self,
        tracker: &Tracker,
        mut log: impl FnMut(LogItem),
        mut keyframe: impl FnMut(Keyframe) -> Result<(), PipelineError>,
    ) -> Result<(), PipelineError> {
        while let Some(kf) = self.lag.pop_ready(tracker, self.align.as_ref(), true) {
            log(LogItem::Keyframe(Box::new(kf.clone())));
            keyframe(kf)?;
        }
        Ok(())
    }
}

/// The window records: the newest `keyframes` of the tracker, at most once per `interval_ns`
/// of frame time, only after measured frames (not during initialisation or while lost).
struct WindowLog {
    keyframes: usize,
    interval_ns: i64,
    last_t_ns: Option<i64>,
}

impl WindowLog {
    fn due(
        &mut self,
        tracker: &Tracker,
        out: &TrackOutput,
        align: Option<&Sim3>,
    ) -> Option<TrackerWindow> {
        let n = tracker.num_keyframes();
        if self.keyframes == 0 || n < 2 || !out.state.is_tracked() {
            return None;
        }
        let t = out.t_ns.t_ns();
        // A clock that jumps back (a new recording) starts the interval again.
        if self
            .last_t_ns
            .is_some_and(|l| t >= l && t - l < self.interval_ns)
        {
            return None;
        }
        self.last_t_ns = Some(t);
        // Inverse depth scales with 1/s, its variance with 1/s^2.
        let s = align.map_or(1.0, |a| a.scaling() as f32);
        let scaled = |p: &PlaneF32, by: f32| {
            let mut q = p.clone();
            if by != 1.0 {
                q.data.iter_mut().for_each(|v| *v *= by);
            }
            q
        };
        let keyframes = tracker
            .keyframes()
            .skip(n.saturating_sub(self.keyframes))
            .map(|k| WindowKeyframe {
                id: k.id,
                seq: k.seq,
                t_ns: k.t_ns,
                world_from_cam: apply(align, &k.world_from_cam),
                inv_depth: scaled(k.inv_depth, 1.0 / s),
                variance: k.variance.map(|v| scaled(v, 1.0 / (s * s))),
            })
            .collect();
        Some(TrackerWindow {
            seq: out.seq,
            t_ns: out.t_ns,
            keyframes,
        })
    }
}

/// Inserted keyframes waiting for `lag` newer ones.
struct KeyframeLag {
    lag: usize,
    pending: VecDeque<(u64, Frame)>,
}

impl KeyframeLag {
    /// The next keyframe due (all of them when `flush`), with the tracker's current depth,
    /// variance and pose; keyframes the tracker no longer holds are skipped.
    fn pop_ready(
        &mut self,
        tracker: &Tracker,
        align: Option<&Sim3>,
        flush: bool,
    ) -> Option<Keyframe> {
        while self.pending.len() > if flush { 0 } else { self.lag } {
            let (id, frame) = self.pending.pop_front()?;
            if let Some(kf) = keyframe_of(tracker, &frame, id, align) {
                return Some(kf);
            }
        }
        None
    }
}

/// A keyframe of the tracker at full resolution, for mapping and the log.
fn keyframe_of(
    tracker: &Tracker,
    frame: &Frame,
    id: u64,
    world_from_tracker: Option<&Sim3>,
) -> Option<Keyframe> {
    let cam = *tracker.camera();
    let view = tracker.keyframes().find(|k| k.id == id)?;
    let world_from_cam = apply(world_from_tracker, &view.world_from_cam);
    let mut inv = PlaneF32::new(cam.width, cam.height);
    let mut var = PlaneF32::new(cam.width, cam.height);
    if let Err(e) = tracker.upsample_keyframe(id, &mut inv, &mut var) {
        tracing::debug!("keyframe {id}: no depth yet: {e}");
        return None;
    }
    if let Some(a) = world_from_tracker {
        // Inverse depth scales with 1/s, its variance with 1/s^2.
        let s = a.scaling() as f32;
        inv.data.iter_mut().for_each(|d| *d /= s);
        var.data.iter_mut().for_each(|v| *v /= s * s);
    }
    Some(Keyframe {
        index: id,
        t_ns: frame.t_ns,
        image: frame.image.to_rgb8(),
        world_from_cam,
        camera: cam,
        inv_depth: inv,
        inv_depth_variance: var,
    })
}
