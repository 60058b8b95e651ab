//! What the tracker reports: per-frame output, states, notes, counters and keyframe views.

use super::*;

/// What the tracker reports about itself.
pub(super) struct Stats {
    pub(super) times: StageTimes,
    pub(super) counters: TrackerCounters,
}

/// Why a frame got no pose from measurements.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LostReason {
    /// Mean intensity below `min_mean_intensity` (lamps off, lens covered).
    Black,
    /// Mean intensity above `max_mean_intensity`.
    Saturated,
    /// Contrast below `min_contrast` (a turbidity burst, a sediment cloud).
    LowContrast,
    /// Too few confident flow vectors to the reference keyframe.
    LowConfidence,
    /// The motion-only BA found no pose.
    NoPose,
    /// Lost earlier and no stored keyframe matched this frame yet.
    NotRelocalised,
}

/// Tracking state reported with every pose.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case", tag = "state", content = "reason")]
pub enum TrackingState {
    /// Collecting the first keyframes; the pose is provisional (interpolated later).
    Initializing,
    /// Pose from flow and motion-only BA against a keyframe.
    Tracking,
    /// Pose recovered against a stored keyframe after being lost.
    Relocalised,
    /// No measured pose: the pose is a constant-velocity prediction, the map is untouched.
    Lost(LostReason),
}

impl TrackingState {
    /// Whether the pose of this frame was measured.
    pub fn is_tracked(self) -> bool {
        matches!(self, TrackingState::Tracking | TrackingState::Relocalised)
    }
    /// Short name for logs.
    pub fn name(self) -> &'static str {
        match self {
            TrackingState::Initializing => "initializing",
            TrackingState::Tracking => "tracking",
            TrackingState::Relocalised => "relocalised",
            TrackingState::Lost(LostReason::Black) => "lost (black frame)",
            TrackingState::Lost(LostReason::Saturated) => "lost (saturated frame)",
            TrackingState::Lost(LostReason::LowContrast) => "lost (contrast collapse)",
            TrackingState::Lost(LostReason::LowConfidence) => "lost (too little confident flow)",
            TrackingState::Lost(LostReason::NoPose) => "lost (no pose)",
            TrackingState::Lost(LostReason::NotRelocalised) => "lost (not relocalised)",
        }
    }
}

/// Why a frame has no measured pose yet while the tracker initialises: what it waited for or
/// refused, with the number against its threshold. `states.txt` and the log carry it, so a run
/// that never initialises says why on every frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum TrackNote {
    #[default]
    None,
    /// The flow to the reference keyframe was confident on too few pixels (`confident` of the
    /// pixels, `needed` the threshold, both fractions).
    InitLowConfidence { confident: f32, needed: f32 },
    /// Not enough parallax yet: mean flow to the reference keyframe below the keyframe
    /// threshold (pixels at the input resolution).
    InitSmallFlow { flow_px: f32, needed_px: f32 },
    /// The pose against the reference keyframe did not converge.
    InitPoseFailed,
    /// A keyframe was added; `keyframes` of the `needed` the initialisation takes.
    InitKeyframe { keyframes: usize, needed: usize },
    /// The initialisation started again from this frame: `failed_frames` frames in a row
    /// could not be matched to the reference keyframe (`init_restart_after`); the
    /// `dropped_keyframes` collected before were dropped.
    InitRestarted { failed_frames: usize, dropped_keyframes: usize },
    /// The initial BA ran early on the `keyframes` collected (of the `needed`
    /// `init_keyframes`): this frame did not match the reference keyframe
    /// (`init_min_keyframes`); it is tracked as the first frame after a loss.
    InitEarly { keyframes: usize, needed: usize },
    /// A new map segment starts from this frame: `failed_frames` good frames in a row could
    /// not be relocalised against any stored keyframe (`new_segment_after`).
    NewSegment { segment: u32, failed_frames: usize },
}

impl TrackNote {
    /// A short machine name (`init_low_confidence`), `None` for no note.
    pub fn kind(self) -> Option<&'static str> {
        match self {
            TrackNote::None => None,
            TrackNote::InitLowConfidence { .. } => Some("init_low_confidence"),
            TrackNote::InitSmallFlow { .. } => Some("init_small_flow"),
            TrackNote::InitPoseFailed => Some("init_pose_failed"),
            TrackNote::InitKeyframe { .. } => Some("init_keyframe"),
            TrackNote::InitRestarted { .. } => Some("init_restarted"),
            TrackNote::NewSegment { .. } => Some("new_segment"),
            TrackNote::InitEarly { .. } => Some("init_early"),
        }
    }

    /// The measured value and its threshold, where the note has them.
    pub fn value_and_limit(self) -> Option<(f64, f64)> {
        match self {
            TrackNote::InitLowConfidence { confident, needed } => Some((confident as f64, needed as f64)),
            TrackNote::InitSmallFlow { flow_px, needed_px } => Some((flow_px as f64, needed_px as f64)),
            TrackNote::InitKeyframe { keyframes, needed } | TrackNote::InitEarly { keyframes, needed } => Some((keyframes as f64, needed as f64)),
            TrackNote::InitRestarted { failed_frames, .. } | TrackNote::NewSegment { failed_frames, .. } => Some((failed_frames as f64, failed_frames as f64)),
            TrackNote::None | TrackNote::InitPoseFailed => None,
        }
    }
}

impl std::fmt::Display for TrackNote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            TrackNote::None => Ok(()),
            TrackNote::InitLowConfidence { confident, needed } => {
                write!(f, "flow to the reference keyframe confident on {:.1}% of pixels < {:.1}%", confident * 100.0, needed * 100.0)
            }
            TrackNote::InitSmallFlow { flow_px, needed_px } => write!(f, "mean flow to the reference keyframe {flow_px:.2} px <= {needed_px:.2} px (waiting for parallax)"),
            TrackNote::InitPoseFailed => f.write_str("pose against the reference keyframe did not converge"),
            TrackNote::InitKeyframe { keyframes, needed } => write!(f, "keyframe {keyframes} of the {needed} the initialisation takes"),
            TrackNote::InitRestarted { failed_frames, dropped_keyframes } => {
                write!(f, "initialisation restarted from this frame: {failed_frames} frame(s) in a row did not match the reference keyframe ({dropped_keyframes} keyframe(s) dropped)")
            }
            TrackNote::InitEarly { keyframes, needed } => {
                write!(f, "initialised early on {keyframes} of {needed} keyframes: this frame did not match the reference keyframe")
            }
            TrackNote::NewSegment { segment, failed_frames } => {
                write!(f, "map segment {segment} starts from this frame: {failed_frames} good frame(s) in a row matched no stored keyframe")
            }
        }
    }
}

/// A frame's pose relative to a keyframe, so that it follows the keyframe when the graph is
/// corrected: `world_from_cam = world_from_kf * kf_from_cam`, the translation scaled by the
/// keyframe's scale correction since `kf_scale`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameAnchor {
    pub keyframe: u64,
    pub kf_from_cam: Se3,
    /// The keyframe's `scale_correction` when the anchor was made.
    pub kf_scale: f64,
}

/// A keyframe that left the graph: from now on it is expressed relative to `parent`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvictedKeyframe {
    pub id: u64,
    pub t_ns: Timestamp,
    pub seq: u64,
    /// Its scale correction when evicted.
    pub scale_correction: f64,
    pub anchor: FrameAnchor,
}

/// What the tracker says about one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackOutput {
    pub t_ns: Timestamp,
    pub seq: u64,
    /// Current estimate (camera-to-world).
    pub world_from_cam: Se3,
    pub state: TrackingState,
    /// The keyframe the pose is measured against (`None` while initialising or lost).
    pub anchor: Option<FrameAnchor>,
    /// Id of the keyframe this frame became.
    pub new_keyframe: Option<u64>,
    /// The map segment the pose is expressed in, when reported (a later merge may move it
    /// into an older segment: the final trajectory follows the anchor keyframe).
    pub segment: u32,
    /// A keyframe evicted from the full store while inserting this one.
    pub evicted: Option<EvictedKeyframe>,
    /// A loop closure was accepted at this frame.
    pub loop_closed: bool,
    /// Why the frame has no measured pose yet (initialisation), [`TrackNote::None`] otherwise.
    pub note: TrackNote,
}

/// Accumulated wall time per stage.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimes {
    /// Image preparation and every flow estimate.
    pub flow: Duration,
    /// Motion-only, initial and local (window) BA solves.
    pub ba: Duration,
    /// Dense global BA over every keyframe (after loops, or periodic).
    pub global_ba: Duration,
    /// Depth covariance (Eq. 4).
    pub covariance: Duration,
    /// Loop detection, verification and the pose graph.
    pub loop_closure: Duration,
    pub frames: u64,
    pub keyframes: u64,
    pub loops: u64,
    pub flow_estimates: u64,
    /// Loop candidates screened at a coarse level (`FlowEstimator::screen`, not counted in
    /// `flow_estimates`).
    pub loop_screens: u64,
}

/// Counters of what happened.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TrackerCounters {
    pub keyframes_inserted: u64,
    pub keyframes_pruned: u64,
    pub keyframes_evicted: u64,
    pub loops_closed: u64,
    pub global_bas: u64,
    /// Global BAs whose apply frame came before the background worker was done (the
    /// tracking thread waited for it).
    pub global_ba_waits: u64,
    pub relocalisations: u64,
    pub lost_frames: u64,
    /// Solves that failed (the state was left as it was).
    pub ba_failures: u64,
    /// The initial BA kept its level start (`init_level_start`) over the collected estimate.
    pub init_level_start: bool,
    /// Times the initialisation started again (`init_restart_after`).
    pub init_restarts: u64,
    /// Frames whose pose was found at a turned prediction (`turn_search_deg`).
    pub turns_found: u64,
    /// Initial BAs run early on fewer than `init_keyframes` (`init_min_keyframes`).
    pub init_early: u64,
    /// New map segments started after a loss (`new_segment_after`).
    pub segments_started: u64,
    /// Merges of two segments.
    pub segments_merged: u64,
}

/// A read-only view of a keyframe.
#[derive(Clone, Copy, Debug)]
pub struct KeyframeView<'a> {
    pub id: u64,
    pub t_ns: Timestamp,
    pub seq: u64,
    /// Map segment.
    pub segment: u32,
    pub world_from_cam: Se3,
    /// Product of the pose-graph scale corrections applied so far.
    pub scale_correction: f64,
    /// Inverse depth at the depth grid, 1/m.
    pub inv_depth: &'a PlaneF32,
    /// Inverse depth variance at the depth grid, (1/m)^2 (`None` before its first covariance).
    pub variance: Option<&'a PlaneF32>,
}
