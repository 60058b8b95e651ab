//! The tracking -> mapping edge: keyframes are scheduled, never dropped (ARCHITECTURE.md,
//! "Threads and queues").
//!
//! Tracking must never wait for mapping, and a CPU mapper on a small board takes seconds per
//! keyframe, so the queue between them fills. Its written policy:
//!
//! 1. **Push never blocks.** While there is room a keyframe is queued behind the others.
//! 2. **Full: the keyframe whose view its neighbours cover best is deferred**, not the newest
//!    refused. The queued keyframes form a chain along the path: the last keyframe mapping took
//!    (the anchor), the queued ones in order, the new one. Taking keyframe `i` out leaves a gap
//!    between its two neighbours; the one whose neighbours lie closest together in
//!    [`view_distance`] (the smallest gap left behind) is taken out, ties to the oldest. The new
//!    keyframe is always queued: nothing after it covers its view yet. The oldest queued one,
//!    before mapping has taken any keyframe, has no neighbour before it and is kept too (it
//!    starts the map). So a burst keeps keyframes spread over the whole stretch of path it
//!    covers, a hovering vehicle's repeats go first, and no region waits behind an old one.
//! 3. **A deferred keyframe still reaches the map.** Tracking logs every keyframe before it
//!    hands it on; the deferred ids are kept ([`PipelineResult::deferred_keyframes`]), and at
//!    the end of a run that was not stopped the mapper takes every deferred keyframe from the
//!    log before its final optimisation. A stopped run's deferred keyframes have no image in
//!    the keyframe folder, so a resume feeds them (`feed_unmapped_keyframes`). Counted as
//!    `deferred` in [`QueueStats`]; `dropped` stays 0.
//! 4. **Mapping takes the oldest first**, the order the vehicle saw them: the map grows along
//!    the path and the newest region is at most the queue's capacity behind.
//!
//! [`PipelineResult::deferred_keyframes`]: super::PipelineResult::deferred_keyframes

use super::queue::{closest_neighbours, QueueStats};
use duv_core::{Keyframe, Se3};
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

/// Where a keyframe looks from, for [`view_distance`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub world_from_cam: Se3,
    /// The keyframe's typical inverse depth (the mean over its valid pixels, map units); 1
    /// when it has none.
    pub inv_depth: f64,
}

impl View {
    /// `kf`'s pose and the mean of its valid (finite, positive) inverse depths.
    pub fn of(kf: &Keyframe) -> Self {
        let (sum, n) = kf.inv_depth.data.iter().filter(|d| d.is_finite() && **d > 0.0).fold((0.0f64, 0usize), |(s, n), d| (s + *d as f64, n + 1));
        View { world_from_cam: kf.world_from_cam, inv_depth: if n > 0 { sum / n as f64 } else { 1.0 } }
    }
}

/// How far apart two views look, in radians: the baseline over the scene's typical depth
/// (the parallax a point at that depth shows; scale-free, so the same in map units and in
/// metres) plus the rotation between the two cameras. 0: the same view.
pub fn view_distance(a: &View, b: &View) -> f64 {
    let baseline = (a.world_from_cam.translation.vector - b.world_from_cam.translation.vector).norm();
    let inv_depth = 0.5 * (a.inv_depth + b.inv_depth);
    baseline * inv_depth + a.world_from_cam.rotation.angle_to(&b.world_from_cam.rotation)
}

/// Which of `queued` (oldest first) to defer so that `newest` fits: the one whose neighbours
/// (`anchor`, the last keyframe mapping took, before the first) lie closest together; ties to
/// the oldest. The first has no neighbour before it without an anchor: it is kept unless it is
/// the only one.
pub fn choose_deferred<'a>(anchor: Option<&'a View>, queued: impl ExactSizeIterator<Item = &'a View>, newest: &'a View) -> usize {
    closest_neighbours(anchor, queued, newest, view_distance)
}

/// What a push did.
#[derive(Debug)]
pub enum Scheduled {
    Queued,
    /// Queued after deferring this (older) keyframe to the end of the run.
    QueuedDeferred(Arc<Keyframe>),
    /// The queue is closed.
    Closed(Arc<Keyframe>),
}

struct State {
    items: VecDeque<(Arc<Keyframe>, View)>,
    /// The last keyframe mapping took.
    anchor: Option<View>,
    closed: bool,
    stats: QueueStats,
}

/// The bounded tracking -> mapping queue with the deferral policy of the module doc. Its
/// storage is allocated once, at construction.
pub struct KeyframeQueue {
    capacity: usize,
    state: Mutex<State>,
    not_empty: Condvar,
    not_full: Condvar,
}

impl KeyframeQueue {
    /// A queue of at most `capacity` keyframes (at least 1).
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(1);
        KeyframeQueue {
            capacity,
            state: Mutex::new(State { items: VecDeque::with_capacity(capacity), anchor: None, closed: false, stats: QueueStats::default() }),
            not_empty: Condvar::new(),
            not_full: Condvar::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues `kf`; when full, defers the queued keyframe the policy picks. Never blocks.
    pub fn push(&self, kf: Arc<Keyframe>) -> Scheduled {
        let view = View::of(&kf);
        let mut g = self.lock();
        if g.closed {
            return Scheduled::Closed(kf);
        }
        let mut deferred = None;
        if g.items.len() >= self.capacity {
            let i = choose_deferred(g.anchor.as_ref(), g.items.iter().map(|(_, v)| v), &view);
            deferred = g.items.remove(i).map(|(k, _)| k);
            g.stats.deferred += 1;
        }
        g.items.push_back((kf, view));
        g.stats.pushed += 1;
        g.stats.max_depth = g.stats.max_depth.max(g.items.len());
        drop(g);
        self.not_empty.notify_one();
        match deferred {
            Some(k) => Scheduled::QueuedDeferred(k),
            None => Scheduled::Queued,
        }
    }

    /// Queues `kf`, waiting for room (the end of the stream, when tracking has nothing left to
    /// do); `false` when the queue was closed.
    pub fn push_wait(&self, kf: Arc<Keyframe>) -> bool {
        let view = View::of(&kf);
        let mut g = self.lock();
        while !g.closed && g.items.len() >= self.capacity {
            g = self.not_full.wait(g).unwrap_or_else(|p| p.into_inner());
        }
        if g.closed {
            return false;
        }
        g.items.push_back((kf, view));
        g.stats.pushed += 1;
        g.stats.max_depth = g.stats.max_depth.max(g.items.len());
        drop(g);
        self.not_empty.notify_one();
        true
    }

    fn take(&self, g: &mut State) -> Option<Arc<Keyframe>> {
        let (kf, view) = g.items.pop_front()?;
        g.anchor = Some(view);
        g.stats.popped += 1;
        self.not_full.notify_one();
        Some(kf)
    }

    /// The oldest keyframe, if one is queued.
    pub fn try_pop(&self) -> Option<Arc<Keyframe>> {
        let mut g = self.lock();
        self.take(&mut g)
    }

    /// The oldest keyframe, waiting up to `timeout`: `Ok(None)` on timeout, `Err(())` once the
    /// queue is closed and empty.
    #[allow(clippy::result_unit_err)]
    pub fn pop_timeout(&self, timeout: Duration) -> Result<Option<Arc<Keyframe>>, ()> {
        let mut g = self.lock();
        if g.items.is_empty() && !g.closed {
            g = self.not_empty.wait_timeout(g, timeout).unwrap_or_else(|p| p.into_inner()).0;
        }
        match self.take(&mut g) {
            Some(kf) => Ok(Some(kf)),
            None if g.closed => Err(()),
            None => Ok(None),
        }
    }

    /// End of stream: pushes are refused, the consumer drains what is queued.
    pub fn close(&self) {
        self.lock().closed = true;
        self.not_empty.notify_all();
        self.not_full.notify_all();
    }

    pub fn stats(&self) -> QueueStats {
        let g = self.lock();
        QueueStats { depth: g.items.len(), ..g.stats }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::{ImageRgb8, PinholeCamera, PlaneF32, Timestamp};
    use nalgebra::{Translation3, UnitQuaternion};

    /// A keyframe `index` at `x` (map units) along the path, yawed `yaw_rad`, looking at a scene
    /// 2 units away (inverse depth 0.5).
    fn keyframe(index: u64, x: f64, yaw_rad: f64) -> Arc<Keyframe> {
        let cam = PinholeCamera::new(100.0, 100.0, 8.0, 6.0, 16, 12).unwrap();
        let mut inv_depth = PlaneF32::new(16, 12);
        inv_depth.data.iter_mut().for_each(|d| *d = 0.5);
        Arc::new(Keyframe {
            index,
            t_ns: Timestamp::from_ns(index as i64),
            image: ImageRgb8::new(16, 12),
            world_from_cam: Se3::from_parts(Translation3::new(x, 0.0, 0.0), UnitQuaternion::from_euler_angles(0.0, yaw_rad, 0.0)),
            camera: cam,
            inv_depth,
            inv_depth_variance: PlaneF32::new(16, 12),
        })
    }

    fn drain(q: &KeyframeQueue) -> Vec<u64> {
        std::iter::from_fn(|| q.try_pop()).map(|k| k.index).collect()
    }

    /// The largest step along the path between consecutive keyframes of `ids` (x = 0.1 * id).
    fn max_gap(ids: &[u64]) -> f64 {
        ids.windows(2).map(|w| (w[1] - w[0]) as f64 * 0.1).fold(0.0, f64::max)
    }

    #[test]
    fn view_distance_is_parallax_plus_rotation() {
        let a = View::of(&keyframe(0, 0.0, 0.0));
        assert_eq!(a.inv_depth, 0.5);
        // 0.4 units of baseline at 2 units of depth: 0.2 rad.
        assert!((view_distance(&a, &View::of(&keyframe(1, 0.4, 0.0))) - 0.2).abs() < 1e-12);
        // A 0.3 rad yaw in place.
        assert!((view_distance(&a, &View::of(&keyframe(1, 0.0, 0.3))) - 0.3).abs() < 1e-9);
        // Scale-free: the same path at twice the scale (depth doubled too) is as far.
        let mut far = (*keyframe(2, 0.8, 0.0)).clone();
        far.inv_depth.data.iter_mut().for_each(|d| *d = 0.25);
        let mut origin = (*keyframe(0, 0.0, 0.0)).clone();
        origin.inv_depth.data.iter_mut().for_each(|d| *d = 0.25);
        assert!((view_distance(&View::of(&origin), &View::of(&far)) - 0.2).abs() < 1e-12);
    }

    /// A burst of 40 keyframes 0.1 apart into a queue of 4 that mapping does not touch: none
    /// dropped, 36 deferred, the newest queued, and the 4 queued spread over the whole 3.9-unit
    /// stretch: 0, 17, 33, 39, the largest gap 1.7 units (evenly spread: 1.3; refusing the
    /// newest would have kept 0..=3 and left 3.6 units unmapped until the end).
    #[test]
    fn a_burst_keeps_keyframes_spread_over_the_whole_path() {
        let q = KeyframeQueue::new(4);
        let mut deferred = Vec::new();
        for i in 0..40 {
            if let Scheduled::QueuedDeferred(k) = q.push(keyframe(i, 0.1 * i as f64, 0.0)) {
                deferred.push(k.index);
            }
        }
        let s = q.stats();
        assert_eq!((s.pushed, s.dropped, s.deferred, s.depth, s.max_depth), (40, 0, 36, 4, 4));
        let kept = drain(&q);
        assert_eq!((kept[0], kept[3]), (0, 39), "{kept:?}");
        assert_eq!(kept, vec![0, 17, 33, 39]);
        assert!(max_gap(&kept) <= 1.7 + 1e-9, "{kept:?}: gap {}", max_gap(&kept));
        // Every keyframe is either queued or deferred (fed from the log at the end): none lost.
        let mut all: Vec<u64> = kept.iter().chain(&deferred).copied().collect();
        all.sort();
        assert_eq!(all, (0..40).collect::<Vec<_>>());
    }

    /// A mapper that takes one keyframe for every 3 tracking hands on (a CPU mapper on 2
    /// cores) over a 60-keyframe path: what it maps during the run never leaves more than 0.6
    /// units (6 keyframe spacings) between consecutive keyframes, nothing is dropped, and
    /// mapped + deferred is every keyframe exactly once.
    #[test]
    fn a_slow_mapper_maps_the_path_without_holes() {
        let q = KeyframeQueue::new(4);
        let (mut mapped, mut deferred) = (Vec::new(), Vec::new());
        for i in 0..60u64 {
            if let Scheduled::QueuedDeferred(k) = q.push(keyframe(i, 0.1 * i as f64, 0.0)) {
                deferred.push(k.index);
            }
            if i % 3 == 2 {
                mapped.extend(q.try_pop().map(|k| k.index));
            }
        }
        q.close();
        mapped.extend(drain(&q));
        let s = q.stats();
        assert_eq!((s.dropped, s.deferred, s.popped), (0, deferred.len() as u64, mapped.len() as u64));
        assert_eq!((mapped[0], *mapped.last().unwrap()), (0, 59));
        assert!(mapped.windows(2).all(|w| w[0] < w[1]), "oldest first: {mapped:?}");
        assert!(max_gap(&mapped) <= 0.6 + 1e-9, "{mapped:?}: gap {}", max_gap(&mapped));
        let mut all: Vec<u64> = mapped.iter().chain(&deferred).copied().collect();
        all.sort();
        assert_eq!(all, (0..60).collect::<Vec<_>>());
    }

    /// A vehicle hovering (8 keyframes at one spot, yawing 0.01 rad each) and then moving on (8
    /// more, 0.1 apart): the hover's repeats are deferred first; of the 4 queued, one is from
    /// the hover.
    #[test]
    fn hover_repeats_are_deferred_first() {
        let q = KeyframeQueue::new(4);
        for i in 0..16u64 {
            let (x, yaw) = if i < 8 { (0.0, 0.01 * i as f64) } else { (0.1 * (i - 7) as f64, 0.07) };
            q.push(keyframe(i, x, yaw));
        }
        let kept = drain(&q);
        assert_eq!(kept.iter().filter(|i| **i < 8).count(), 1, "{kept:?}");
        assert_eq!(*kept.last().unwrap(), 15);
        assert_eq!(q.stats().dropped, 0);
    }

    #[test]
    fn close_drains_then_ends_and_push_wait_waits_for_room() {
        let q = Arc::new(KeyframeQueue::new(1));
        assert!(matches!(q.push(keyframe(0, 0.0, 0.0)), Scheduled::Queued));
        let q2 = q.clone();
        let waiter = std::thread::spawn(move || q2.push_wait(keyframe(1, 0.1, 0.0)));
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(q.try_pop().map(|k| k.index), Some(0));
        assert!(waiter.join().unwrap());
        q.close();
        assert!(matches!(q.push(keyframe(2, 0.2, 0.0)), Scheduled::Closed(_)));
        assert_eq!(q.pop_timeout(Duration::from_millis(1)).unwrap().map(|k| k.index), Some(1));
        assert!(q.pop_timeout(Duration::from_millis(1)).is_err());
    }
}
