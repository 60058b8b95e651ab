//! The live view's edge (`duv run --live-view`, a build with the `live-view` feature): what
//! tracking and mapping hand to the `live` thread, which owns the `duv-live` server.
//!
//! | from | item | policy |
//! |---|---|---|
//! | tracking | every frame's pose and state | bounded queue (`live.queue`), refuse and count when full |
//! | tracking | a frame every 1/`live.image_hz` s of frame time, shared not copied | the same, and at most [`LIVE_FRAMES_IN_FLIGHT`] held by the live thread (the frame pool has that many more slots) |
//! | tracking | each keyframe's pose as it goes to mapping | the same |
//! | mapping | the Gaussian centres at each map checkpoint | the same |
//!
//! Tracking never waits: a push that finds the queue full drops the item and counts it; the
//! live thread's bandwidth budget drops more (camera first) and counts those. Nothing on the
//! tracking side allocates. Without the feature, [`LiveFeed::start`] refuses a live view and
//! the feed does nothing.

use super::PipelineError;
use duv_core::config::board::LiveSettings;
use duv_core::{Frame, Keyframe, Timestamp};
use duv_log::PoseRecord;
use serde::Serialize;
use std::sync::Arc;

/// Frames the live thread may hold at once (taken from the frame pool, which has that many
/// more slots when the live view is on).
pub const LIVE_FRAMES_IN_FLIGHT: usize = 2;

/// What the live view did in a run (the printed summary's `live view:` line).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct LiveReport {
    /// Where it served (`HOST:PORT`).
    pub addr: String,
    pub messages_sent: u64,
    pub bytes_sent: u64,
    pub poses_sent: u64,
    pub frames_sent: u64,
    pub keyframe_lists_sent: u64,
    pub clouds_sent: u64,
    /// Items the full live queue refused (or frames skipped because the live thread held
    /// [`LIVE_FRAMES_IN_FLIGHT`] already).
    pub dropped_queue: u64,
    /// Items the bandwidth budget dropped, per class.
    pub dropped_budget_poses: u64,
    pub dropped_budget_frames: u64,
    pub dropped_budget_keyframe_lists: u64,
    pub dropped_budget_clouds: u64,
    /// Items that came while no client watched (nothing sent).
    pub unwatched: u64,
    /// The most clients at once.
    pub clients_max: usize,
}

impl std::fmt::Display for LiveReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "live view ws://{}: {} messages ({:.1} kB) sent to at most {} client(s): {} poses, {} frames, {} keyframe lists, {} clouds; dropped {} (queue), {} frames, {} clouds, {} keyframe lists, {} poses (bandwidth); {} unwatched",
            self.addr,
            self.messages_sent,
            self.bytes_sent as f64 / 1e3,
            self.clients_max,
            self.poses_sent,
            self.frames_sent,
            self.keyframe_lists_sent,
            self.clouds_sent,
            self.dropped_queue,
            self.dropped_budget_frames,
            self.dropped_budget_clouds,
            self.dropped_budget_keyframe_lists,
            self.dropped_budget_poses,
            self.unwatched
        )
    }
}

#[cfg(feature = "live-view")]
mod on {
    use super::*;
    use crate::queue::{BoundedQueue, FullPolicy, Pushed};
    use duv_live::{LiveItem, LiveServer};
    use std::sync::atomic::{AtomicI64, AtomicU64, AtomicUsize, Ordering};

    pub(super) struct Shared {
        pub queue: BoundedQueue<LiveItem>,
        pub frames_in_flight: AtomicUsize,
        pub frames_skipped: AtomicU64,
        pub last_frame_t_ns: AtomicI64,
        pub frame_interval_ns: i64,
    }

    impl Shared {
        pub fn push(&self, item: LiveItem) {
            if let Pushed::Refused(LiveItem::Frame(_)) | Pushed::Closed(LiveItem::Frame(_)) = self.queue.push(item, 0) {
                self.frames_in_flight.fetch_sub(1, Ordering::Relaxed);
            }
        }

        pub fn frame(&self, frame: &Arc<Frame>) {
            if self.frame_interval_ns <= 0 {
                return;
            }
            let t = frame.t_ns.t_ns();
            let last = self.last_frame_t_ns.load(Ordering::Relaxed);
            // Due every interval of frame time (a clock that jumps back starts again).
            if last != i64::MIN && t >= last && t - last < self.frame_interval_ns {
                return;
            }
            // A due frame the live thread has no place for is skipped (counted), and the next
            // is due an interval later, as if it had gone.
            self.last_frame_t_ns.store(t, Ordering::Relaxed);
            if self.frames_in_flight.fetch_add(1, Ordering::Relaxed) >= LIVE_FRAMES_IN_FLIGHT {
                self.frames_in_flight.fetch_sub(1, Ordering::Relaxed);
                self.frames_skipped.fetch_add(1, Ordering::Relaxed);
                return;
            }
            self.push(LiveItem::Frame(Arc::clone(frame)));
        }
    }


    pub(super) fn start(settings: &LiveSettings) -> Result<(Arc<Shared>, std::thread::JoinHandle<LiveReport>), PipelineError> {
        let server = LiveServer::start(settings).map_err(|e| PipelineError::Live { problem: e.to_string() })?;
        let shared = Arc::new(Shared {
            queue: BoundedQueue::new("live", settings.queue as usize, 0, FullPolicy::DropNewest),
            frames_in_flight: AtomicUsize::new(0),
            frames_skipped: AtomicU64::new(0),
            last_frame_t_ns: AtomicI64::new(i64::MIN),
            frame_interval_ns: if settings.image_hz > 0.0 { (1e9 / settings.image_hz) as i64 } else { 0 },
        });
        let sh = shared.clone();
        let mut server = server;
        let thread = crate::spawn("live", move || {
            let _span = tracing::info_span!("live").entered();
            let addr = server.local_addr().to_string();
            while let Some(item) = sh.queue.pop() {
                server.publish(&item);
                let frame = matches!(item, LiveItem::Frame(_));
                // The frame's pool slot goes back before the count says so.
                drop(item);
                if frame {
                    sh.frames_in_flight.fetch_sub(1, Ordering::Relaxed);
                }
            }
            let s = server.stop();
            let q = sh.queue.stats();
            LiveReport {
                addr,
                messages_sent: s.messages_sent,
                bytes_sent: s.bytes_sent,
                poses_sent: s.sent.pose,
                frames_sent: s.sent.camera,
                keyframe_lists_sent: s.sent.keyframes,
                clouds_sent: s.sent.cloud,
                dropped_queue: q.dropped + sh.frames_skipped.load(Ordering::Relaxed),
                dropped_budget_poses: s.dropped_budget.pose,
                dropped_budget_frames: s.dropped_budget.camera,
                dropped_budget_keyframe_lists: s.dropped_budget.keyframes,
                dropped_budget_clouds: s.dropped_budget.cloud,
                unwatched: s.unwatched,
                clients_max: s.clients_max,
            }
        })?;
        Ok((shared, thread))
    }
}

/// The tracking and mapping threads' side of the live view: cheap to clone, does nothing when
/// the live view is off.
#[derive(Clone, Default)]
pub struct LiveFeed {
    #[cfg(feature = "live-view")]
    shared: Option<Arc<on::Shared>>,
}

/// The live thread, joined at the end of the run.
#[derive(Default)]
pub struct LiveThread {
    #[cfg(feature = "live-view")]
    thread: Option<std::thread::JoinHandle<LiveReport>>,
}

impl LiveFeed {
    /// Starts the live view's server and thread for `settings`; `None`: off.
    pub fn start(settings: Option<&LiveSettings>) -> Result<(LiveFeed, LiveThread), PipelineError> {
        let Some(settings) = settings else { return Ok((LiveFeed::default(), LiveThread::default())) };
        #[cfg(feature = "live-view")]
        {
            let (shared, thread) = on::start(settings)?;
            Ok((LiveFeed { shared: Some(shared) }, LiveThread { thread: Some(thread) }))
        }
        #[cfg(not(feature = "live-view"))]
        {
            let _ = settings;
            Err(PipelineError::Live { problem: "this build lacks the `live-view` feature (cargo build --features live-view)".into() })
        }
    }

    /// Extra frame pool slots the live view may hold.
    pub fn frame_slots(&self) -> usize {
        #[cfg(feature = "live-view")]
        if self.shared.is_some() {
            return LIVE_FRAMES_IN_FLIGHT;
        }
        0
    }

    /// A tracked frame's pose and state (tracking thread).
    pub fn pose(&self, _p: &PoseRecord) {
        #[cfg(feature = "live-view")]
        if let Some(s) = &self.shared {
            s.push(duv_live::LiveItem::Pose(*_p));
        }
    }

    /// An input frame, taken when the board's `live.image_hz` says one is due (tracking thread).
    pub fn frame(&self, _frame: &Arc<Frame>) {
        #[cfg(feature = "live-view")]
        if let Some(s) = &self.shared {
            s.frame(_frame);
        }
    }

    /// A keyframe handed to mapping (tracking thread).
    pub fn keyframe(&self, _kf: &Keyframe) {
        #[cfg(feature = "live-view")]
        if let Some(s) = &self.shared {
            s.push(duv_live::LiveItem::Keyframe { id: _kf.index, t_ns: _kf.t_ns, world_from_cam: _kf.world_from_cam });
        }
    }

    /// The Gaussian centres of a map checkpoint and their colours (mapping thread; copied).
    pub fn cloud(&self, _t_ns: Timestamp, _centres_in_world: &[[f32; 3]], _colours: &[[u8; 3]]) {
        #[cfg(feature = "live-view")]
        if let Some(s) = &self.shared {
            s.push(duv_live::LiveItem::Cloud { t_ns: _t_ns, centres_in_world: _centres_in_world.to_vec(), colours: _colours.to_vec() });
        }
    }

    /// End of stream: the live thread sends what is queued and stops the server.
    pub fn close(&self) {
        #[cfg(feature = "live-view")]
        if let Some(s) = &self.shared {
            s.queue.close();
        }
    }
}

impl LiveThread {
    /// Waits for the live thread (after [`LiveFeed::close`]): its report, `None` when off.
    pub fn join(self) -> Option<LiveReport> {
        #[cfg(feature = "live-view")]
        if let Some(t) = self.thread {
            return t.join().ok();
        }
        None
    }
}

#[cfg(all(test, feature = "live-view"))]
mod tests {
    use super::on::Shared;
    use super::*;
    use crate::queue::{BoundedQueue, FullPolicy};
    use duv_core::{FrameImage, ImageRgb8, Se3};
    use std::sync::atomic::{AtomicI64, AtomicU64, AtomicUsize, Ordering};

    fn shared(queue: usize, image_hz: f64) -> Shared {
        Shared {
            queue: BoundedQueue::new("live", queue, 0, FullPolicy::DropNewest),
            frames_in_flight: AtomicUsize::new(0),
            frames_skipped: AtomicU64::new(0),
            last_frame_t_ns: AtomicI64::new(i64::MIN),
            frame_interval_ns: (1e9 / image_hz) as i64,
        }
    }

    fn frame(t_ms: i64) -> Arc<Frame> {
        Arc::new(Frame { t_ns: Timestamp::from_ns(t_ms * 1_000_000), seq: t_ms as u64, image: FrameImage::Rgb8(ImageRgb8::new(4, 4)) })
    }

    fn pose(seq: u64) -> PoseRecord {
        PoseRecord { t_ns: Timestamp::from_ns(seq as i64), seq, world_from_cam: Se3::identity(), state: "tracking", tracked: true, keyframe: None, new_keyframe: None, loop_closed: false, segment: 0, why: None, value: None, limit: None }
    }

    /// A full queue refuses and counts (the tracking side never waits); a refused frame gives its
    /// in-flight place back.
    #[test]
    fn a_full_queue_refuses_and_counts() {
        let s = shared(4, 10.0);
        for i in 0..10 {
            s.push(duv_live::LiveItem::Pose(pose(i)));
        }
        let q = s.queue.stats();
        assert_eq!((q.pushed, q.dropped, q.depth), (4, 6, 4));
        s.frame(&frame(0));
        assert_eq!((s.queue.stats().dropped, s.frames_in_flight.load(Ordering::Relaxed)), (7, 0));
    }

    /// Frames at 30 Hz of frame time with `image_hz` 10: one in three is taken; at most
    /// [`LIVE_FRAMES_IN_FLIGHT`] are held by the live thread, the others are skipped and counted.
    #[test]
    fn frames_follow_image_hz_and_the_in_flight_limit() {
        let s = shared(64, 10.0);
        for k in 0..9 {
            s.frame(&frame(k * 33 + 1));
        }
        // Frames at 1, 34, ..., 265 ms: due at 1, 133 and 265 ms (100 ms is only 99 ms after 1);
        // the first two are taken, the third finds both places held and is skipped.
        assert_eq!(s.queue.stats().pushed, LIVE_FRAMES_IN_FLIGHT as u64);
        assert_eq!(s.frames_in_flight.load(Ordering::Relaxed), LIVE_FRAMES_IN_FLIGHT);
        assert_eq!(s.frames_skipped.load(Ordering::Relaxed), 1);
        // The live thread is done with one: the next due frame is taken.
        drop(s.queue.try_pop());
        s.frames_in_flight.fetch_sub(1, Ordering::Relaxed);
        s.frame(&frame(1000));
        assert_eq!(s.queue.stats().pushed, 3);
    }
}
