//! Tracking stage: dense correspondences between frames (flow) and the bundle adjustment that
//! turns them into keyframe poses, inverse depth maps and their uncertainty (paper §3.1).
//! Tracking never imports another stage; what it hands on (poses, keyframes with depth and
//! variance) are plain `core` types.
//!
//! # The tracker ([`Tracker`])
//! A DROID-SLAM-like factor graph with the classical flow of [`flow`] in the place of RAFT:
//! nodes are keyframes (pose, prepared image pyramid, inverse depth at 1/`depth_factor` of
//! the input, its variance), edges are flow measurements between keyframes (pooled targets
//! and per-axis confidences, the diagonal of `Sigma^-1` of Eq. 1).
//!
//! - *Every frame*: grey conversion into a preallocated plane, a health check (black,
//!   saturated, contrast collapse), marine snow taken out ([`despeckle`]: small bright specks
//!   replaced by the grey-scale opening), the pyramid, then flow from the reference keyframe seeded
//!   by the flow the constant-velocity prediction induces (reprojecting the keyframe's depth
//!   grid; with the forward-backward check unless `frame_forward_backward` is off), and a
//!   motion-only BA against the keyframe: every frame gets a
//!   pose. When that flow is not confident (or after a loss), the prediction is tried again
//!   turned about the camera's vertical axis (`turn_search_deg`, +-1 and +-2 steps): a fast
//!   turn at a low frame rate that the constant-velocity model does not predict. With `motion_depth_variance` (the default) each keyframe pixel's flow weights are
//!   deflated by its depth's Eq. 4 variance, propagated through the projection at the
//!   predicted pose, so depth that no edge measured (the prior alone holds it) does not pull
//!   the pose.
//! - *Keyframes*: when the mean flow from the reference keyframe exceeds
//!   `keyframe_flow_px` (depth-grid pixels, as DROID measures it). The new keyframe's depth
//!   starts as the previous keyframe's splatted into it; it is linked (two directed edges
//!   each) to up to `edges_per_keyframe` window keyframes whose induced flow and overlap say
//!   they see the same scene. Then `local_rounds` rounds of: re-estimate the new edges' flow
//!   seeded by the current BA estimate (after initialisation both edges of a link come from
//!   one pair estimate seeded from the older keyframe, `pair_edges`), run `local_iterations` Gauss-Newton iterations over
//!   the sliding window (`ba_window` newest keyframes; all but the newest `window_free_poses`
//!   poses fixed, at least two: gauge and scale; every depth free).
//!   The depth variance of every window keyframe follows from Eq. 4. A new keyframe whose
//!   refined induced flow to its predecessor is under `prune_flow_px` (after the first round)
//!   is dropped again. By default (`defer_rounds` and `defer_insertion`) the keyframe's own
//!   frame only inserts it; the rounds (one edge pair or one window solve with Eq. 4 per
//!   stage, with the loop search, one candidate per stage, between the last round's edge
//!   pairs and its solve), then the periodic global BA, run `stages_per_frame` stages at the
//!   start of each following frame (a window solve is a frame's only stage), so no frame
//!   pays for a whole insertion. A new keyframe first finishes what is left of the previous one and
//!   starts from the frame's pose re-anchored to the solved reference.
//! - *Measurements*: pooled flow targets within `border_margin_px` of the image border get no
//!   weight: the cell's pixels that left the view bias its pooled mean, and with forward
//!   motion that bias stretched the map by a few percent per keyframe. Optionally
//!   (`border_taper_px`, off by default: it helped the survey and broke the turbid one) the
//!   weights fall off quadratically within a distance of either image's border.
//! - *Initialisation*: the first keyframe starts from constant inverse depth (the weak depth
//!   prior sets the scale, the first pose is fixed); each of the next `init_keyframes - 1`
//!   gets a motion-only pose, splatted depth, links, and a BA over everything collected so
//!   far (staged like an insertion: one edge per stage, then the solve); then, on the frame
//!   that adds the last one, `init_rounds` flow/BA rounds of `init_iterations` iterations over
//!   all (not staged: about 1.3 s at 640x480, once). With `init_level_start` (the default),
//!   when that solve ends above `init_level_start_rms_px` of RMS residual, the same rounds
//!   run again from a second start, every keyframe at the first one's attitude with constant
//!   inverse depth, and the start whose solve ends at the lower cost per unit of flow weight
//!   is kept (the other one's poses, depths and measurements are
//!   restored from a [`snapshot`]): incremental growth from constant depth over a near-planar
//!   seabed can settle in the other two-view solution, a camera pitching steadily over a
//!   seabed bent to match, which later keyframes continue. An initialisation cannot hang:
//!   after `init_restart_after` frames in a row that do not match the reference keyframe (flow
//!   confident on too few pixels, or no pose), the keyframes collected so far are dropped and
//!   the current frame starts it again ([`TrackNote::InitRestarted`]); until the initial BA
//!   has run no keyframe is handed on and no pose counts as measured ([`PoseSource`]).
//! - *Capacity*: `max_keyframes` slots; when full, the most redundant keyframe outside the
//!   window (its neighbours closest by induced flow) is evicted and re-expressed relative to
//!   its predecessor ([`EvictedKeyframe`]).
//! - *Loop closure*: after each insertion, old keyframes (all but the newest
//!   `loop_exclude_recent`) are ranked by thumbnail NCC; the best `loop_candidates` are
//!   verified by flow seeded from the current estimate (mean flow magnitude and confident
//!   fraction, as the paper thresholds mean flow). An
//!   accepted loop gives a relative pose (motion-only BA against the old keyframe's depth) and
//!   a relative scale (median depth ratio), a loop edge, a Sim(3) pose graph over every
//!   keyframe (scale drift corrected, depths rescaled), then a dense global BA over every
//!   keyframe and edge.
//! - *Lost tracking*: a bad image, too few confident flow vectors or a failed motion-only BA
//!   make the frame [`TrackingState::Lost`] with a predicted pose; nothing of it reaches the
//!   map. The next good frame tries the reference keyframe with the prediction, then the
//!   stored keyframes by thumbnail NCC, verified by flow and motion-only BA.
//! - *Map segments (multi-map)*: after `new_segment_after` good frames in a row that match no
//!   stored keyframe, a new segment starts from the current frame as a new initialisation
//!   (first pose the prediction, depth the last reference's median) and tracking goes on in
//!   it ([`TrackNote::NewSegment`]). Every keyframe and [`TrackOutput`] carries its segment;
//!   window, initialisation, pose graph, global BA, eviction anchors and depth-consistency
//!   neighbours combine one segment's keyframes only. Loop detection ranks every other
//!   segment's keyframes as well: a verified match across segments (unseeded flow,
//!   motion-only pose against the other keyframe's depth, median depth ratio) merges them with
//!   that Sim(3), the younger segment moved into the older one's frame and scale, then a
//!   global BA over the merged segment. Relocalisation against another segment's keyframe
//!   continues tracking in that segment. Keyframes are handed on ([`Tracker::next_final_keyframe`])
//!   only from segment 0, the world frame the map is built in; a keyframe of another segment
//!   when it is due is not handed on, so a segment that merges into segment 0 later is mapped
//!   from the merge on (`tracker/segments.rs`).
//!
//! - *Resume*: [`Tracker::seed`] starts a new tracker from keyframes an earlier run logged
//!   (recorded ids, poses, images, inverse depth averaged down to the depth grid, variance),
//!   linked and measured as an insertion links them but not re-solved: their recorded poses
//!   are the oldest, fixed poses of the next windows, so tracking continues in the recorded
//!   frame and scale.
//!
//! Full-resolution depth and variance come from joint bilateral upsampling guided by the
//! keyframe image ([`Tracker::upsample_keyframe`]). Optionally (`upsample_surface_gap`, off
//! by default), where a pixel's depth-grid neighbours straddle an occlusion boundary (a step
//! between their sorted inverse depths larger than that fraction of their weighted median),
//! the depth averages only the surface the weighted median is on rather than blending a depth
//! between the two. The variance adds the weighted spread of
//! the depths it mixed (`upsample_spread_gain`) and a border term, `1 + (border_variance_px /
//! d)^2` with `d` the distance to the image border in depth-grid pixels: Eq. 4 is the noise
//! the flow weights carry, and the flow near the border is also biased, which the Hessian
//! cannot see (on the 320x240 survey the border term took the AUSE from 0.26 to 0.17). A
//! texture term (`texture_variance`) multiplies each depth-grid cell's variance by the
//! keyframe's geometric-mean grey-level variance over the cell's own: a flat cell's depth is
//! interpolated from its neighbours, not measured, which the pooled flow weights cannot see
//! (turbid survey at 320x240: AUSE 0.218 to 0.155). Last, a multi-view consistency term
//! (`track/consistency.rs`, `consistency_neighbours`): the keyframes up to 3 before and after
//! give second estimates of the keyframe's depth wherever they see it, and the mean squared
//! disagreement over them and the 3x3 cells around is blended in as `var^0.15 d2^0.85`.
//! Regional biases (haze flattening the far seabed, little parallax around the focus of
//! expansion) are invisible to Eq. 4 but not to another keyframe's depth: turbid survey at
//! 640x480 AUSE 0.247 to 0.159, the others 0.14-0.155 to 0.08-0.10. None of these terms
//! enters the depth-grid variance that the motion-only BA weighs by.
//!
//! # Memory
//! [`Tracker::new`] allocates the keyframe slots, edge table, flow buffers, both BA
//! workspaces and the pose graph from [`TrackerCapacity`]; see `tests/tracker_alloc.rs` for
//! what is proven allocation-free.

pub mod ba;
mod config;
mod consistency;
pub mod despeckle;
pub mod flow;
mod graph;
mod keyframes;
pub mod metric;
mod snapshot;
mod tracker;
mod trajectory;
mod upsample;

pub use config::{ConfigError, TrackerCapacity, TrackerConfig};
pub use tracker::{
    depth_grid_camera, EvictedKeyframe, FrameAnchor, KeyframeView, LostReason, ResumePoint, SeedFrame, SeedKeyframe, StageTimes, TrackError,
    TrackNote, TrackOutput, Tracker, TrackerCounters, TrackerSeed, TrackingState,
};
pub use trajectory::{FinalKeyframe, FinalTrajectory, PoseSource, RecordedFrame, TrajectoryRecorder, MAX_INTERPOLATION_GAP_S};
