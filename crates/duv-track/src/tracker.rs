//! The tracker: frames in, a pose for every frame and keyframes with inverse depth and
//! variance out (paper §3.1). See the [module docs](super) for the method.

use super::ba::{solve_motion_only, BaCapacity, BaConfig, BaError, BaWorkspace, MotionOnlyObservation};
use super::config::{ConfigError, TrackerCapacity, TrackerConfig};
use super::flow::{FlowError, FlowEstimator, FlowField, FlowResult, PreparedFrame};
use super::graph::{sim3_relative, sim3_split, EdgeStore, PoseConstraint, PoseGraph};
use super::keyframes::{block_means, image_health, ncc, thumbnail, Keyframe, KeyframeStore, THUMB_N};
use super::snapshot::WindowSnapshot;
use super::consistency::{blend_consistency, consistency_grid, ConsistencyScratch};
use super::upsample::{border_variance, joint_bilateral, texture_variance, UpsampleParams};
use duv_core::frame::LUMA_WEIGHTS;
use duv_core::pose::{se3_exp, se3_log};
use duv_core::{Frame, FrameImage, Image, PinholeCamera, PlaneF32, Se3, Timestamp};
use nalgebra::{Translation3, Vector3};
use std::time::{Duration, Instant};

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
        }
    }

    /// The measured value and its threshold, where the note has them.
    pub fn value_and_limit(self) -> Option<(f64, f64)> {
        match self {
            TrackNote::InitLowConfidence { confident, needed } => Some((confident as f64, needed as f64)),
            TrackNote::InitSmallFlow { flow_px, needed_px } => Some((flow_px as f64, needed_px as f64)),
            TrackNote::InitKeyframe { keyframes, needed } => Some((keyframes as f64, needed as f64)),
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
    pub relocalisations: u64,
    pub lost_frames: u64,
    /// Solves that failed (the state was left as it was).
    pub ba_failures: u64,
    /// The initial BA kept its level start (`init_level_start`) over the collected estimate.
    pub init_level_start: bool,
}

/// A read-only view of a keyframe.
#[derive(Clone, Copy, Debug)]
pub struct KeyframeView<'a> {
    pub id: u64,
    pub t_ns: Timestamp,
    pub seq: u64,
    pub world_from_cam: Se3,
    /// Product of the pose-graph scale corrections applied so far.
    pub scale_correction: f64,
    /// Inverse depth at the depth grid, 1/m.
    pub inv_depth: &'a PlaneF32,
    /// Inverse depth variance at the depth grid, (1/m)^2 (`None` before its first covariance).
    pub variance: Option<&'a PlaneF32>,
}

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

/// Errors of the tracker. Bad frames are not errors: they are reported as a lost state.
#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("tracker capacity: {field} = {value}: {problem}")]
    Capacity { field: &'static str, value: usize, problem: &'static str },
    #[error("tracker camera: {0}")]
    Camera(#[from] duv_core::CameraModelError),
    #[error("tracker camera has lens distortion: give undistorted images and PinholeCamera::undistorted()")]
    DistortedCamera,
    #[error("frame {seq}: image is {width}x{height}, the tracker was built for {expected_width}x{expected_height}")]
    FrameSize { seq: u64, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("flow: {0}")]
    Flow(#[from] FlowError),
    #[error("bundle adjustment: {0}")]
    Ba(#[from] BaError),
    #[error("thread pool: {0}")]
    ThreadPool(String),
    #[error("no keyframe with id {id}")]
    NoSuchKeyframe { id: u64 },
    #[error("output planes must be {expected_width}x{expected_height}, got {width}x{height}")]
    OutputSize { width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("seed: the tracker has tracked frames already (seed a new tracker)")]
    NotEmpty,
    #[error("seed: no keyframe to seed with")]
    NoSeedKeyframes,
    #[error("seed keyframe {id}: {what} is {width}x{height}, the tracker was built for {expected_width}x{expected_height}")]
    SeedSize { id: u64, what: &'static str, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("seed keyframe {id}: {problem}")]
    BadSeedKeyframe { id: u64, problem: &'static str },
}

/// Dense monocular tracker. Everything is allocated by [`Tracker::new`]; see the module docs
/// for what is allocation-free afterwards.
pub struct Tracker {
    pool: std::sync::Arc<rayon::ThreadPool>,
    st: State,
}

/// Which keyframe-insertion path a new keyframe takes.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// No keyframe yet.
    Empty,
    /// Collecting the first keyframes.
    Collecting,
    /// Initialised: local BA per keyframe.
    Running,
}

struct State {
    cfg: TrackerConfig,
    /// Input pixels per depth pixel (resolved).
    factor: usize,
    cap: TrackerCapacity,
    camera: PinholeCamera,
    low: PinholeCamera,
    flow: FlowEstimator,
    grey: PlaneF32,
    cur: PreparedFrame,
    cur_thumb: Vec<f32>,
    res: FlowResult,
    /// The reverse direction of a pair estimate.
    res_reverse: FlowResult,
    seed: FlowField,
    prev_flow: FlowField,
    have_prev_flow: bool,
    obs_target: Image<f32, 2>,
    obs_weight: Image<f32, 2>,
    scratch: Vec<f32>,
    scratch_depth: PlaneF32,
    kfs: KeyframeStore,
    edges: EdgeStore,
    ba: BaWorkspace,
    gba: BaWorkspace,
    pg: PoseGraph,
    window: Vec<usize>,
    new_edges: Vec<usize>,
    candidates: Vec<(f32, usize)>,
    /// Loop candidates of the pending insertion (NCC, slot), best first; verified one per
    /// stage (relocalisation ranks into `candidates`, so a loss between stages keeps them).
    loop_candidates: Vec<(f32, usize)>,
    phase: Phase,
    state: TrackingState,
    ref_slot: usize,
    last_pose: Se3,
    velocity: Se3,
    last_seq: u64,
    inserted_since_loop: usize,
    /// Level of the loop candidates' screen (one above the finest; `None`: no screen, when it
    /// is turned off or the estimator has no such level).
    loop_screen_level: Option<usize>,
    inserted_since_global: usize,
    times: StageTimes,
    counters: TrackerCounters,
    evicted_slot: Option<usize>,
    pending_eviction: Option<EvictedKeyframe>,
    /// Deferred stages of the last keyframe insertion.
    pending: Option<Pending>,
    /// The initial BA's first solution while the second start is tried.
    init_snapshot: WindowSnapshot,
    /// Workspace of the variance's consistency term (`upsample_keyframe` takes `&self`).
    consistency: std::sync::Mutex<ConsistencyScratch>,
}

/// What remains of a keyframe insertion: flow/BA rounds, then loop closure / global BA.
#[derive(Clone, Copy, Debug)]
struct Pending {
    slot: usize,
    fixed: usize,
    /// Rounds done.
    next_round: usize,
    /// Fine stages (`defer_insertion`): the position in `new_edges` of the next edge to
    /// estimate in this round; `new_edges.len()`: the round's BA is next.
    next_edge: usize,
    fine: bool,
    /// Loop search: `None` before its candidates are ranked, then the next one to verify
    /// (past the last: searched). Fine stages rank and verify before the last round's solve.
    next_candidate: Option<usize>,
    /// A keyframe collected before initialisation: one round, `init_iterations` over every
    /// keyframe, no covariance and no loop search.
    collecting: bool,
}

/// Inverse depth floor when loading a keyframe into BA (1/m).
const MIN_INV_DEPTH: f32 = 1e-3;

impl Tracker {
    /// Builds a tracker for undistorted `camera` images, sizing every buffer from `capacity`.
    pub fn new(camera: &PinholeCamera, config: &TrackerConfig, capacity: TrackerCapacity) -> Result<Self, TrackError> {
        config.validate()?;
        // Flow and BA settings are refused here, at start, by name: inside a solve a bad value
        // would only stop the tracker from initialising.
        config.flow.validate()?;
        config.ba.validate()?;
        camera.validate()?;
        if camera.distortion.is_some() {
            return Err(TrackError::DistortedCamera);
        }
        let cap = capacity;
        if cap.ba_window < 2 {
            return Err(TrackError::Capacity { field: "ba_window", value: cap.ba_window, problem: "must be at least 2" });
        }
        if cap.max_keyframes < cap.ba_window + 2 {
            return Err(TrackError::Capacity { field: "max_keyframes", value: cap.max_keyframes, problem: "must be at least ba_window + 2" });
        }
        if config.init_keyframes > cap.ba_window {
            return Err(TrackError::Capacity { field: "ba_window", value: cap.ba_window, problem: "must hold init_keyframes" });
        }
        if cap.threads == 0 {
            return Err(TrackError::Capacity { field: "threads", value: 0, problem: "must be at least 1" });
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cap.threads)
            .thread_name(|i| format!("duv-track-{i}"))
            .start_handler(|_| duv_core::alloc::label_current_thread(duv_core::alloc::ThreadRole::Tracking))
            .build()
            .map_err(|e| TrackError::ThreadPool(e.to_string()))?;
        let st = pool.install(|| State::new(camera, config, cap))?;
        Ok(Tracker { pool: std::sync::Arc::new(pool), st })
    }

    /// Tracks one frame. Frames of the wrong size are an error; black, saturated or
    /// featureless frames are reported as [`TrackingState::Lost`] and leave the map untouched.
    ///
    /// Called from outside the tracker's pool, each call enters it (`ThreadPool::install`),
    /// which goes through rayon's injector queue: that allocates a small block every 63 calls.
    /// The tracking thread of a pipeline runs its loop inside the pool with
    /// [`run_in_pool`](Self::run_in_pool) instead, and then nothing is allocated per frame.
    pub fn track(&mut self, frame: &Frame) -> Result<TrackOutput, TrackError> {
        if self.pool.current_thread_index().is_some() {
            return self.st.track(frame);
        }
        let st = &mut self.st;
        self.pool.install(|| st.track(frame))
    }

    /// Seeds a new tracker with keyframes an earlier run recorded (resume after a power cut):
    /// they take their recorded ids, poses, images and inverse depth (averaged down to the
    /// depth grid) with their variance, are linked as an insertion links them (flow measured
    /// now), their depth is re-solved over the window with every pose held as recorded (the
    /// newest may have been logged before its deferred rounds ran), and the tracker starts
    /// tracking against the newest. Their poses are the gauge of the window BA while they are
    /// in the window (its oldest poses are held fixed), so the tracker continues in the
    /// recorded frame and scale. Everything is checked before anything changes: an error leaves the tracker
    /// empty and usable.
    pub fn seed(&mut self, seed: &TrackerSeed<'_>) -> Result<(), TrackError> {
        let st = &mut self.st;
        self.pool.install(|| st.seed(seed))
    }

    /// Runs `f` on one of the tracker's pool threads, so that the [`track`](Self::track) calls
    /// it makes enter no queue (a tracking thread's whole loop goes here).
    pub fn run_in_pool<R: Send>(&mut self, f: impl FnOnce(&mut Tracker) -> R + Send) -> R {
        let pool = std::sync::Arc::clone(&self.pool);
        pool.install(|| f(self))
    }

    /// The full-resolution camera.
    pub fn camera(&self) -> &PinholeCamera {
        &self.st.camera
    }
    /// The camera of the depth grid.
    pub fn depth_camera(&self) -> &PinholeCamera {
        &self.st.low
    }
    /// The configuration in use (`depth_factor` resolved).
    pub fn config(&self) -> &TrackerConfig {
        &self.st.cfg
    }
    /// Input pixels per depth-grid pixel.
    pub fn depth_factor(&self) -> usize {
        self.st.factor
    }
    pub fn capacity(&self) -> TrackerCapacity {
        self.st.cap
    }
    pub fn state(&self) -> TrackingState {
        self.st.state
    }
    pub fn times(&self) -> StageTimes {
        self.st.times
    }
    pub fn counters(&self) -> TrackerCounters {
        self.st.counters
    }
    /// Live keyframes, oldest first.
    pub fn keyframes(&self) -> impl Iterator<Item = KeyframeView<'_>> {
        self.st.kfs.order.iter().map(|&s| view(&self.st.kfs.slots[s]))
    }
    /// Number of live keyframes.
    pub fn num_keyframes(&self) -> usize {
        self.st.kfs.len()
    }
    /// The keyframe evicted by the last [`track`](Self::track) call, readable until the next.
    pub fn evicted_keyframe(&self) -> Option<KeyframeView<'_>> {
        self.st.evicted_slot.map(|s| view(&self.st.kfs.slots[s]))
    }
    /// Live edges as `(from id, to id, is_loop)`.
    pub fn edges(&self) -> impl Iterator<Item = (u64, u64, bool)> + '_ {
        let st = &self.st;
        st.edges.live.iter().map(move |&e| {
            let ed = &st.edges.edges[e];
            (st.kfs.slots[ed.from].id, st.kfs.slots[ed.to].id, ed.is_loop)
        })
    }

    /// Upsamples keyframe `id`'s inverse depth and variance (live, or the one just evicted) to
    /// the input resolution by joint bilateral upsampling guided by its image, the variance
    /// with its texture, border and multi-view consistency terms (module docs). Variance is
    /// written as infinity-free: pixels without a variance yet get `f32::MAX`. The consistency
    /// term reads the neighbouring keyframes as they are now, so a keyframe upsampled again
    /// after newer ones arrived can change.
    pub fn upsample_keyframe(&self, id: u64, inv_depth: &mut PlaneF32, variance: &mut PlaneF32) -> Result<(), TrackError> {
        let st = &self.st;
        let slot = st.kfs.slot_of(id).or(st.evicted_slot.filter(|&s| st.kfs.slots[s].id == id)).ok_or(TrackError::NoSuchKeyframe { id })?;
        let (w, h) = (st.camera.width, st.camera.height);
        for p in [&*inv_depth, &*variance] {
            if p.width != w || p.height != h || p.data.len() != w * h {
                return Err(TrackError::OutputSize { width: p.width, height: p.height, expected_width: w, expected_height: h });
            }
        }
        let kf = &st.kfs.slots[slot];
        let cfg = &st.cfg;
        let params = UpsampleParams {
            sigma_px: cfg.upsample_sigma_px,
            sigma_intensity: cfg.upsample_sigma_intensity,
            spread_gain: cfg.upsample_spread_gain,
            surface_gap: cfg.upsample_surface_gap,
        };
        self.pool.install(|| {
            if kf.has_variance {
                joint_bilateral(&kf.guide, &kf.guide_low, st.factor, &params, &kf.inv_depth, inv_depth, Some((&kf.variance, variance)));
                if cfg.texture_variance {
                    texture_variance(variance, &kf.guide, st.factor, (kf.guide_low.width, kf.guide_low.height));
                }
                border_variance(variance, st.factor, cfg.border_variance_px);
                if cfg.consistency_neighbours > 0 && cfg.consistency_exponent > 0.0 {
                    // A poisoned lock only means another call panicked mid-way: the scratch is
                    // rewritten from scratch here.
                    let mut scratch = st.consistency.lock().unwrap_or_else(|e| e.into_inner());
                    let neighbours = st.consistency_neighbours(kf.id, cfg.consistency_neighbours).map(|s| (st.kfs.slots[s].world_from_cam, &st.kfs.slots[s].inv_depth));
                    consistency_grid(&st.low, &kf.world_from_cam, &kf.inv_depth, neighbours, cfg.consistency_radius_cells, &mut scratch);
                    blend_consistency(variance, &scratch.mean, st.factor, cfg.consistency_exponent);
                }
            } else {
                joint_bilateral(&kf.guide, &kf.guide_low, st.factor, &params, &kf.inv_depth, inv_depth, None);
                variance.data.fill(f32::MAX);
            }
        });
        Ok(())
    }

    /// Runs a dense global BA over every live keyframe now (what the loop closure does after
    /// its pose graph). Returns whether it ran.
    pub fn global_bundle_adjustment(&mut self) -> bool {
        let st = &mut self.st;
        self.pool.install(|| st.global_ba())
    }
}

fn view(kf: &Keyframe) -> KeyframeView<'_> {
    KeyframeView {
        id: kf.id,
        t_ns: kf.t_ns,
        seq: kf.seq,
        world_from_cam: kf.world_from_cam,
        scale_correction: kf.scale_correction,
        inv_depth: &kf.inv_depth,
        variance: kf.has_variance.then_some(&kf.variance),
    }
}

/// The depth-grid camera: `cell` input pixels per pixel, pixel centres as in the flow grids.
pub fn depth_grid_camera(camera: &PinholeCamera, cell: usize) -> PinholeCamera {
    let c = cell as f64;
    PinholeCamera {
        fx: camera.fx / c,
        fy: camera.fy / c,
        cx: (camera.cx - 0.5 * (c - 1.0)) / c,
        cy: (camera.cy - 0.5 * (c - 1.0)) / c,
        width: camera.width / cell,
        height: camera.height / cell,
        distortion: None,
    }
}

/// Reprojection of depth-grid pixels of keyframe `i` into `j`: the mean flow magnitude over
/// pixels landing in view, and the fraction landing in view. Writes the flow into `seed` when
/// given (out-of-view pixels keep their flow; pixels behind `j` get zero).
fn induced_flow(low: &PinholeCamera, world_from_i: &Se3, inv_depth: &PlaneF32, world_from_j: &Se3, mut seed: Option<&mut FlowField>) -> (f32, f32) {
    let rel = world_from_j.inv_mul(world_from_i);
    let rot = rel.rotation.to_rotation_matrix().into_inner();
    let t = rel.translation.vector;
    let (w, h) = (low.width, low.height);
    let (mut sum, mut n_in) = (0.0f64, 0usize);
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let q = Vector3::new((x as f64 - low.cx) / low.fx, (y as f64 - low.cy) / low.fy, 1.0);
            let d = inv_depth.data[p] as f64;
            let pt = rot * q + t * d;
            let (mut u, mut v) = (0.0f32, 0.0f32);
            if pt.z > 1e-6 {
                let uu = low.fx * pt.x / pt.z + low.cx;
                let vv = low.fy * pt.y / pt.z + low.cy;
                u = (uu - x as f64) as f32;
                v = (vv - y as f64) as f32;
                if uu >= -0.5 && vv >= -0.5 && uu < w as f64 - 0.5 && vv < h as f64 - 0.5 {
                    sum += ((u * u + v * v) as f64).sqrt();
                    n_in += 1;
                }
            }
            if let Some(s) = seed.as_deref_mut() {
                s.dx.data[p] = u;
                s.dy.data[p] = v;
            }
        }
    }
    let n = (w * h).max(1);
    ((sum / n_in.max(1) as f64) as f32, n_in as f32 / n as f32)
}

/// Copies the pooled flow into BA measurements (targets in depth-grid pixels, weights scaled
/// by `weight_scale`) and returns the confident fraction (mean of the two weights above
/// `confident_weight`). Targets closer than `border_margin_px` to the border get no weight:
/// some of the cell's pixels may have left the view, and the pooled mean of those that stayed
/// is biased towards the smaller flows (with forward motion this stretched the map a few
/// percent per keyframe). Within `border_taper_px` of either image's border (source pixel or
/// target, past the margin) the weights fall off quadratically: there the patches that
/// measured the flow were clipped by the border and the pooled cells partly out of view, a
/// bias the confidences do not see. The taper only lowers BA weights; the confident fraction
/// (tracking loss, overlap, loop checks) is counted before it.
fn write_measurement(res: &FlowResult, cfg: &TrackerConfig, target: &mut Image<f32, 2>, weight: &mut Image<f32, 2>) -> f32 {
    let pooled = &res.pooled;
    let (w, h) = (pooled.flow.width(), pooled.flow.height());
    let (margin, taper) = (cfg.border_margin_px, cfg.border_taper_px);
    let (xmax, ymax) = (w as f32 - 1.0 - margin, h as f32 - 1.0 - margin);
    let mut n_conf = 0usize;
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let (u, v) = (pooled.flow.dx.data[p], pooled.flow.dy.data[p]);
            let (tx, ty) = (x as f32 + u, y as f32 + v);
            let (mut wx, mut wy) = (pooled.weight_x.data[p], pooled.weight_y.data[p]);
            let finite = tx.is_finite() && ty.is_finite() && wx.is_finite() && wy.is_finite();
            let in_view = tx >= margin && ty >= margin && tx <= xmax && ty <= ymax;
            if !finite || !in_view {
                wx = 0.0;
                wy = 0.0;
            }
            if 0.5 * (wx + wy) > cfg.confident_weight {
                n_conf += 1;
            }
            if taper > 0.0 && wx + wy > 0.0 {
                let to_target = (tx - margin).min(ty - margin).min(xmax - tx).min(ymax - ty);
                let to_source = (x.min(y).min(w - 1 - x).min(h - 1 - y)) as f32;
                let f = ((to_target.min(to_source) + 0.5) / taper).clamp(0.0, 1.0);
                wx *= f * f;
                wy *= f * f;
            }
            target.data[2 * p] = if finite { tx } else { x as f32 };
            target.data[2 * p + 1] = if finite { ty } else { y as f32 };
            weight.data[2 * p] = wx.max(0.0) * cfg.weight_scale;
            weight.data[2 * p + 1] = wy.max(0.0) * cfg.weight_scale;
        }
    }
    n_conf as f32 / (w * h).max(1) as f32
}

/// Grey [0, 1] of a frame into a preallocated plane of the same size.
fn to_grey(image: &FrameImage, out: &mut PlaneF32) {
    match image {
        FrameImage::Rgb8(i) => rgb_to_grey(i, out),
        FrameImage::Gray8(i) => {
            for (o, &v) in out.data.iter_mut().zip(&i.data) {
                *o = v as f32 / 255.0;
            }
        }
    }
}

/// Grey [0, 1] of an RGB image into a preallocated plane of the same size.
fn rgb_to_grey(image: &duv_core::ImageRgb8, out: &mut PlaneF32) {
    for (o, p) in out.data.iter_mut().zip(image.data.chunks_exact(3)) {
        *o = (LUMA_WEIGHTS[0] * p[0] as f32 + LUMA_WEIGHTS[1] * p[1] as f32 + LUMA_WEIGHTS[2] * p[2] as f32) / 255.0;
    }
}

/// Block means of a full-resolution plane at the depth grid (`cell` input pixels per depth
/// pixel); a block with a non-finite value or the `f32::MAX` "unknown" marker gives `bad`.
fn plane_block_means(full: &PlaneF32, cell: usize, out: &mut PlaneF32, bad: f32) {
    let w = full.width;
    let inv = 1.0 / (cell * cell) as f64;
    for ly in 0..out.height {
        for lx in 0..out.width {
            let mut sum = 0.0f64;
            let mut ok = true;
            for y in ly * cell..(ly + 1) * cell {
                for &v in &full.data[y * w + lx * cell..y * w + (lx + 1) * cell] {
                    ok &= v.is_finite() && v < f32::MAX;
                    sum += v as f64;
                }
            }
            out.data[ly * out.width + lx] = if ok { (sum * inv) as f32 } else { bad };
        }
    }
}

/// `pose` with its translation multiplied by `s`.
fn scale_translation(pose: &Se3, s: f64) -> Se3 {
    Se3::from_parts(Translation3::from(pose.translation.vector * s), pose.rotation)
}

impl State {
    /// Slots of the keyframes with a variance that are up to `n` places before and after
    /// keyframe `id` in insertion order (ids grow with insertion), itself left out; `id` need
    /// not be live (the keyframe just evicted).
    fn consistency_neighbours(&self, id: u64, n: usize) -> impl Iterator<Item = usize> + '_ {
        let order = &self.kfs.order;
        let before = order.partition_point(|&s| self.kfs.slots[s].id < id);
        let after = order.partition_point(|&s| self.kfs.slots[s].id <= id);
        order[before.saturating_sub(n)..before].iter().chain(&order[after..(after + n).min(order.len())]).copied().filter(|&s| self.kfs.slots[s].has_variance)
    }

    fn new(camera: &PinholeCamera, config: &TrackerConfig, cap: TrackerCapacity) -> Result<Self, TrackError> {
        let mut cfg = config.clone();
        let factor = cfg.resolved_depth_factor(camera.width, camera.height);
        cfg.depth_factor = Some(factor);
        cfg.flow.output_factor = factor;
        let (w, h) = (camera.width, camera.height);
        let flow = FlowEstimator::new(cfg.flow.clone(), w, h)?;
        let low = depth_grid_camera(camera, factor);
        let (lw, lh) = (low.width, low.height);
        let kfs = KeyframeStore::new(cap.max_keyframes, || Keyframe::new(&flow, w, h, lw, lh));
        let links = 2 * cfg.edges_per_keyframe;
        // Edges: every keyframe's links back, plus room for loop edges.
        let max_edges = cap.max_keyframes * links + 4 * cap.max_keyframes.max(8);
        let window_edges = cap.ba_window * links + 8;
        // The initialisation links each of its keyframes to up to `edges_per_keyframe` before it.
        let init_edges = cfg.init_keyframes * links;
        let n_pix = lw * lh;
        let ba = BaWorkspace::new(BaCapacity { max_keyframes: cap.ba_window, max_pixels_per_keyframe: n_pix, max_edges: window_edges });
        let gba_edges = if cfg.loop_closure || cfg.global_ba_period > 0 { max_edges } else { 1 };
        let gba_kfs = if cfg.loop_closure || cfg.global_ba_period > 0 { cap.max_keyframes } else { 1 };
        let gba = BaWorkspace::new(BaCapacity { max_keyframes: gba_kfs, max_pixels_per_keyframe: n_pix, max_edges: gba_edges });
        let screen = flow.finest_level() + 1;
        let loop_screen_level = (cfg.loop_screen_min_fraction > 0.0
            && screen <= flow.coarsest_level_seeded()
            && factor % (1 << screen) == 0)
            .then_some(screen);
        Ok(State {
            camera: *camera,
            low,
            grey: PlaneF32::new(w, h),
            cur: flow.new_frame(),
            cur_thumb: vec![0.0; THUMB_N],
            res: flow.new_result(),
            res_reverse: flow.new_result(),
            seed: FlowField::zeros(lw, lh, factor),
            prev_flow: FlowField::zeros(lw, lh, factor),
            have_prev_flow: false,
            obs_target: Image::new(lw, lh),
            obs_weight: Image::new(lw, lh),
            scratch: Vec::with_capacity(n_pix),
            scratch_depth: PlaneF32::new(lw, lh),
            kfs,
            edges: EdgeStore::new(max_edges, lw, lh),
            ba,
            gba,
            pg: PoseGraph::new(cap.max_keyframes, 2 * cap.max_keyframes + 8),
            window: Vec::with_capacity(cap.max_keyframes),
            new_edges: Vec::with_capacity(max_edges),
            candidates: Vec::with_capacity(cap.max_keyframes),
            loop_candidates: Vec::with_capacity(cap.max_keyframes),
            phase: Phase::Empty,
            state: TrackingState::Initializing,
            ref_slot: 0,
            last_pose: Se3::identity(),
            velocity: Se3::identity(),
            last_seq: 0,
            inserted_since_loop: 0,
            loop_screen_level,
            inserted_since_global: 0,
            times: StageTimes::default(),
            counters: TrackerCounters::default(),
            evicted_slot: None,
            pending_eviction: None,
            pending: None,
            init_snapshot: WindowSnapshot::new(cap.ba_window, init_edges, lw, lh),
            consistency: std::sync::Mutex::new(ConsistencyScratch::new(lw, lh)),
            flow,
            factor,
            cfg,
            cap,
        })
    }

    fn ba_config(&self, iterations: usize, fixed: usize) -> BaConfig {
        BaConfig { max_iterations: iterations, fixed_poses: fixed, ..self.cfg.ba }
    }

    fn track(&mut self, frame: &Frame) -> Result<TrackOutput, TrackError> {
        let (w, h) = (self.camera.width, self.camera.height);
        if frame.image.width() != w || frame.image.height() != h {
            return Err(TrackError::FrameSize { seq: frame.seq, width: frame.image.width(), height: frame.image.height(), expected_width: w, expected_height: h });
        }
        self.times.frames += 1;
        self.evicted_slot = None;
        // One deferred stage of the last keyframe insertion (map work; the frame comes after).
        let mut loop_closed = false;
        // A window solve is the frame's only stage: it costs about two edge pairs.
        for k in 0..self.cfg.stages_per_frame {
            let solve = self.next_stage_is_solve();
            if k > 0 && solve {
                break;
            }
            loop_closed |= self.run_pending_stage()?;
            if solve {
                break;
            }
        }
        let frames_since = frame.seq.saturating_sub(self.last_seq).max(1);
        let mut out = TrackOutput {
            t_ns: frame.t_ns,
            seq: frame.seq,
            world_from_cam: self.predict(frames_since),
            state: self.state,
            anchor: None,
            new_keyframe: None,
            evicted: None,
            loop_closed,
            note: TrackNote::None,
        };
        to_grey(&frame.image, &mut self.grey);
        // Health check first: a bad image never reaches the flow or the map.
        let (mean, contrast) = image_health(&self.grey.data, w, h);
        let bad = if mean.is_nan() || mean < self.cfg.min_mean_intensity {
            Some(LostReason::Black)
        } else if mean > self.cfg.max_mean_intensity {
            Some(LostReason::Saturated)
        } else if contrast < self.cfg.min_contrast {
            Some(LostReason::LowContrast)
        } else {
            None
        };
        if let Some(reason) = bad {
            return Ok(self.lost(out, reason));
        }
        let t0 = Instant::now();
        self.flow.prepare_into(&self.grey, &mut self.cur)?;
        self.times.flow += t0.elapsed();
        let mut out = match self.phase {
            Phase::Empty => {
                let pose = Se3::identity();
                let s = self.insert_keyframe_slot(frame, &pose);
                self.kfs.slots[s].inv_depth.data.fill(self.cfg.initial_inv_depth);
                self.ref_slot = s;
                self.phase = Phase::Collecting;
                self.state = TrackingState::Initializing;
                self.last_pose = pose;
                self.last_seq = frame.seq;
                out.world_from_cam = pose;
                out.state = TrackingState::Initializing;
                out.new_keyframe = Some(self.kfs.slots[s].id);
                out.anchor = Some(FrameAnchor { keyframe: self.kfs.slots[s].id, kf_from_cam: Se3::identity(), kf_scale: 1.0 });
                out
            }
            Phase::Collecting => self.track_collecting(frame, out)?,
            Phase::Running => {
                if matches!(self.state, TrackingState::Lost(_)) {
                    self.relocalise(frame, out)?
                } else {
                    self.track_running(frame, out, frames_since)?
                }
            }
        };
        out.evicted = self.pending_eviction.take();
        Ok(out)
    }

    /// Constant-velocity prediction `frames` frames after the last pose.
    fn predict(&self, frames: u64) -> Se3 {
        if frames <= 1 {
            return self.last_pose * self.velocity;
        }
        let xi = se3_log(&self.velocity) * frames as f64;
        self.last_pose * se3_exp(&xi)
    }

    fn lost(&mut self, mut out: TrackOutput, reason: LostReason) -> TrackOutput {
        self.counters.lost_frames += 1;
        self.state = TrackingState::Lost(reason);
        out.state = self.state;
        out.anchor = None;
        out
    }

    /// Flow `ref -> current` with `seed` (or none), result in `self.res`.
    fn flow_ref_to_current(&mut self, slot: usize, seeded: bool, forward_backward: bool) -> Result<(), TrackError> {
        let t0 = Instant::now();
        let seed = if seeded { Some(&self.seed) } else { None };
        let fb = forward_backward && self.cfg.flow.forward_backward;
        self.flow.estimate_with(&self.kfs.slots[slot].frame, &self.cur, seed, &mut self.res, fb)?;
        self.times.flow += t0.elapsed();
        self.times.flow_estimates += 1;
        Ok(())
    }

    fn motion_only(&mut self, slot: usize, pose: &mut Se3) -> Result<(), BaError> {
        let t0 = Instant::now();
        let kf = &self.kfs.slots[slot];
        let variance = (self.cfg.motion_depth_variance && kf.has_variance && kf.variance_unit.is_finite()).then_some(&kf.variance);
        let obs = [MotionOnlyObservation {
            world_from_keyframe: kf.world_from_cam,
            inv_depth: &kf.inv_depth,
            target_xy: &self.obs_target,
            weight_xy: &self.obs_weight,
            inv_depth_variance: variance,
            variance_of_unit_weight: kf.variance_unit,
        }];
        let cfg = BaConfig { max_iterations: self.cfg.motion_iterations, ..self.cfg.ba };
        let r = solve_motion_only(&self.low, &obs, pose, &cfg);
        self.times.ba += t0.elapsed();
        r.map(|_| ())
    }

    fn track_collecting(&mut self, frame: &Frame, mut out: TrackOutput) -> Result<TrackOutput, TrackError> {
        out.state = TrackingState::Initializing;
        self.state = TrackingState::Initializing;
        let r = self.ref_slot;
        if self.have_prev_flow {
            self.seed.dx.data.copy_from_slice(&self.prev_flow.dx.data);
            self.seed.dy.data.copy_from_slice(&self.prev_flow.dy.data);
        }
        self.flow_ref_to_current(r, self.have_prev_flow, true)?;
        let conf = write_measurement(&self.res, &self.cfg, &mut self.obs_target, &mut self.obs_weight);
        if conf < self.cfg.min_confident_fraction {
            // Nothing to trust: wait for a better frame (the first keyframe stays).
            self.have_prev_flow = false;
            out.note = TrackNote::InitLowConfidence { confident: conf, needed: self.cfg.min_confident_fraction };
            return Ok(out);
        }
        self.prev_flow.dx.data.copy_from_slice(&self.res.pooled.flow.dx.data);
        self.prev_flow.dy.data.copy_from_slice(&self.res.pooled.flow.dy.data);
        self.have_prev_flow = true;
        let mean_flow = self.res.stats.mean_flow_input_px / self.factor as f32;
        if mean_flow <= self.cfg.keyframe_flow_px {
            out.note = TrackNote::InitSmallFlow { flow_px: mean_flow * self.factor as f32, needed_px: self.cfg.keyframe_flow_px * self.factor as f32 };
            return Ok(out);
        }
        // A new keyframe. The previous one's staged solve first (its stages usually ran on the
        // frames in between): the pose and the splat below use the solved reference.
        self.finish_pending()?;
        // A first pose against the reference's (constant or solved) depth.
        let mut pose = self.kfs.slots[r].world_from_cam;
        if self.motion_only(r, &mut pose).is_err() {
            self.counters.ba_failures += 1;
            out.note = TrackNote::InitPoseFailed;
            return Ok(out);
        }
        let prev = r;
        let s = self.insert_keyframe_slot(frame, &pose);
        self.splat_depth(prev, s);
        // Incremental initialisation: link the new keyframe and refine everything collected
        // so far, so that each new keyframe starts from a better map than constant depth.
        self.new_edges.clear();
        let n = self.kfs.len();
        for back in 1..=self.cfg.edges_per_keyframe.min(n - 1) {
            let c = self.kfs.order[n - 1 - back];
            for (f, t) in [(s, c), (c, s)] {
                if let Some(e) = self.edges.add(f, t, false) {
                    self.new_edges.push(e);
                }
            }
        }
        self.window.clear();
        self.window.extend_from_slice(&self.kfs.order);
        let initialising = self.kfs.len() >= self.cfg.init_keyframes;
        if self.cfg.defer_rounds && self.cfg.defer_insertion && !initialising {
            // Staged like an insertion: one edge per stage, then the solve over everything
            // collected, on the following frames. The initial BA itself is not staged.
            self.pending = Some(Pending { slot: s, fixed: 1, next_round: 0, next_edge: 0, fine: true, next_candidate: None, collecting: true });
        } else {
            self.estimate_new_edges()?;
            self.solve_window(self.cfg.init_iterations, 1);
        }
        self.ref_slot = s;
        self.have_prev_flow = false;
        self.last_pose = pose;
        self.last_seq = frame.seq;
        out.world_from_cam = pose;
        out.new_keyframe = Some(self.kfs.slots[s].id);
        out.anchor = Some(FrameAnchor { keyframe: self.kfs.slots[s].id, kf_from_cam: Se3::identity(), kf_scale: 1.0 });
        if initialising {
            self.initialise()?;
            out.state = TrackingState::Tracking;
        } else {
            out.note = TrackNote::InitKeyframe { keyframes: self.kfs.len(), needed: self.cfg.init_keyframes };
        }
        out.world_from_cam = self.kfs.slots[s].world_from_cam;
        self.last_pose = out.world_from_cam;
        Ok(out)
    }

    /// Takes a slot for the current frame (swapping its prepared pyramid in) and fills the
    /// keyframe's image data; the depth is the caller's.
    fn insert_keyframe_slot(&mut self, frame: &Frame, pose: &Se3) -> usize {
        if self.kfs.is_full() {
            self.evict();
        }
        let s = self.kfs.push().expect("a slot is free after eviction");
        self.fill_keyframe_slot(s, frame.t_ns, frame.seq, pose);
        self.counters.keyframes_inserted += 1;
        self.times.keyframes += 1;
        s
    }

    /// Fills slot `s` from the current frame (`cur`, `grey`).
    fn fill_keyframe_slot(&mut self, s: usize, t_ns: Timestamp, seq: u64, pose: &Se3) {
        let (w, h) = (self.camera.width, self.camera.height);
        let kf = &mut self.kfs.slots[s];
        std::mem::swap(&mut kf.frame, &mut self.cur);
        kf.t_ns = t_ns;
        kf.seq = seq;
        kf.world_from_cam = *pose;
        for (g, &v) in kf.guide.iter_mut().zip(&self.grey.data) {
            *g = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        }
        block_means(&self.grey.data, w, self.factor, &mut kf.guide_low);
        thumbnail(&self.grey.data, w, h, &mut kf.thumb);
    }

    /// See [`Tracker::seed`].
    fn seed(&mut self, seed: &TrackerSeed<'_>) -> Result<(), TrackError> {
        if self.phase != Phase::Empty || self.kfs.len() > 0 {
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
        if seeds.len() + seed.frames.len() > self.kfs.capacity() {
            return Err(TrackError::Capacity { field: "max_keyframes", value: self.kfs.capacity(), problem: "fewer than the keyframes to seed" });
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
            rgb_to_grey(&k.image, &mut self.grey);
            let t0 = Instant::now();
            self.flow.prepare_into(&self.grey, &mut self.cur)?;
            self.times.flow += t0.elapsed();
            let s = self.kfs.push_with_id(k.index).expect("ids increase and a slot is free");
            self.fill_keyframe_slot(s, k.t_ns, sk.seq, &k.world_from_cam);
            let kf = &mut self.kfs.slots[s];
            plane_block_means(&k.inv_depth, self.factor, &mut kf.inv_depth, MIN_INV_DEPTH);
            for d in kf.inv_depth.data.iter_mut() {
                *d = d.max(MIN_INV_DEPTH);
            }
            plane_block_means(&k.inv_depth_variance, self.factor, &mut kf.variance, f32::MAX);
            kf.has_variance = true;
            // The recorded variance is metric; the unit weight it was scaled by is not logged.
            kf.variance_unit = f32::NAN;
        }
        self.kfs.reserve_ids_below(seed.next_keyframe_id);
        for sf in seed.frames {
            to_grey(&sf.frame.image, &mut self.grey);
            let t0 = Instant::now();
            self.flow.prepare_into(&self.grey, &mut self.cur)?;
            self.times.flow += t0.elapsed();
            let s = self.kfs.push().expect("a slot is free");
            self.fill_keyframe_slot(s, sf.frame.t_ns, sf.frame.seq, &sf.world_from_cam);
            // Depth: the previous seed's splatted in, or constant (triangulated below).
            match self.kfs.len() {
                1 => self.kfs.slots[s].inv_depth.data.fill(self.cfg.initial_inv_depth),
                n => self.splat_depth(self.kfs.order[n - 2], s),
            }
        }
        // Links as an insertion makes them: each keyframe to up to `edges_per_keyframe` older
        // ones that see the same scene, both directions, measured from one pair estimate.
        self.phase = Phase::Running;
        self.new_edges.clear();
        let n = self.kfs.len();
        for pos in 1..n {
            let s = self.kfs.order[pos];
            let mut links = 0;
            for back in 1..=pos {
                if links >= self.cfg.edges_per_keyframe {
                    break;
                }
                let c = self.kfs.order[pos - back];
                let (ks, kc) = (&self.kfs.slots[s], &self.kfs.slots[c]);
                let (flow, overlap) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kc.world_from_cam, None);
                if back == 1 || (flow <= self.cfg.edge_max_flow_px && overlap >= self.cfg.edge_min_overlap) {
                    for (f, t) in [(s, c), (c, s)] {
                        if let Some(e) = self.edges.add(f, t, false) {
                            self.new_edges.push(e);
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
        self.window.clear();
        self.window.extend_from_slice(&self.kfs.order[n.saturating_sub(self.cap.ba_window)..]);
        let fixed = self.window.len();
        self.solve_window(self.cfg.init_iterations, fixed);
        for _ in 1..self.cfg.init_rounds {
            self.estimate_new_edges()?;
            self.solve_window(self.cfg.init_iterations, fixed);
        }
        self.window_covariance(fixed);
        self.new_edges.clear();
        let newest = self.kfs.newest().expect("seeded");
        self.ref_slot = newest;
        self.state = TrackingState::Tracking;
        self.have_prev_flow = false;
        self.inserted_since_loop = 0;
        self.inserted_since_global = 0;
        self.pending = None;
        match seed.resume {
            Some(r) => {
                self.last_pose = r.world_from_cam;
                self.last_seq = r.seq;
                self.velocity = r.velocity;
            }
            None => {
                let last = &self.kfs.slots[newest];
                self.last_pose = last.world_from_cam;
                self.last_seq = last.seq;
                self.velocity = Se3::identity();
                if n >= 2 {
                    let before = &self.kfs.slots[self.kfs.order[n - 2]];
                    let frames = last.seq.saturating_sub(before.seq).max(1) as f64;
                    self.velocity = se3_exp(&(se3_log(&before.world_from_cam.inv_mul(&last.world_from_cam)) / frames));
                }
            }
        }
        Ok(())
    }

    /// Evicts the most redundant keyframe outside the window (the one whose neighbours are
    /// closest by induced flow); it is re-expressed relative to its predecessor.
    fn evict(&mut self) {
        let n = self.kfs.len();
        let last_candidate = n.saturating_sub(self.cap.ba_window);
        let mut best: Option<(f32, usize)> = None;
        for pos in 1..last_candidate.min(n.saturating_sub(1)) {
            let (a, b) = (self.kfs.order[pos - 1], self.kfs.order[pos + 1]);
            let (ka, kb) = (&self.kfs.slots[a], &self.kfs.slots[b]);
            let (flow, overlap) = induced_flow(&self.low, &ka.world_from_cam, &ka.inv_depth, &kb.world_from_cam, None);
            let score = flow / overlap.max(0.05);
            if best.is_none_or(|(s, _)| score < s) {
                best = Some((score, pos));
            }
        }
        let pos = best.map(|(_, p)| p).unwrap_or(1.min(n - 1));
        let s = self.kfs.order[pos];
        let parent = self.kfs.order[pos - 1];
        let (kp, ks) = (&self.kfs.slots[parent], &self.kfs.slots[s]);
        let ev = EvictedKeyframe {
            id: ks.id,
            t_ns: ks.t_ns,
            seq: ks.seq,
            scale_correction: ks.scale_correction,
            anchor: FrameAnchor { keyframe: kp.id, kf_from_cam: kp.world_from_cam.inv_mul(&ks.world_from_cam), kf_scale: kp.scale_correction },
        };
        self.edges.remove_touching(s);
        self.kfs.remove_at(pos);
        if self.ref_slot == s {
            self.ref_slot = parent;
        }
        self.evicted_slot = Some(s);
        self.pending_eviction = Some(ev);
        self.counters.keyframes_evicted += 1;
    }
}

/// Loads `window` (keyframe slots, oldest first) and the live edges between them into `ba`.
fn load_window(ba: &mut BaWorkspace, low: &PinholeCamera, kfs: &mut KeyframeStore, edges: &EdgeStore, window: &[usize], include_loops: bool) -> Result<(), BaError> {
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
fn write_back(ba: &BaWorkspace, kfs: &mut KeyframeStore, window: &[usize]) -> Result<(), BaError> {
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
    /// Estimates the flow of every edge in `new_edges` (seeded by the current estimate) and
    /// stores the measurements. Consecutive edges `a -> b`, `b -> a` share one pair estimate.
    fn estimate_new_edges(&mut self) -> Result<(), TrackError> {
        let mut i = 0;
        while i < self.new_edges.len() {
            i += self.estimate_new_edge_at(i)?;
        }
        Ok(())
    }

    /// Estimates `new_edges[i]` (with `new_edges[i + 1]` when that is its reverse and
    /// `pair_edges` is on); returns how many edges it measured.
    fn estimate_new_edge_at(&mut self, i: usize) -> Result<usize, TrackError> {
        let e = self.new_edges[i];
        let reverse = self.new_edges.get(i + 1).copied().filter(|_| self.cfg.pair_edges && self.phase == Phase::Running).filter(|&r| {
            let (a, b) = (&self.edges.edges[e], &self.edges.edges[r]);
            a.from == b.to && a.to == b.from
        });
        match reverse {
            Some(r) => {
                // Seeded from the older keyframe's depth (refined by earlier rounds; the
                // newer one's may only be splatted).
                let (ie, ir) = (self.kfs.slots[self.edges.edges[e].from].id, self.kfs.slots[self.edges.edges[r].from].id);
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
    fn estimate_edge_pair(&mut self, e: usize, r: usize) -> Result<(), TrackError> {
        let (from, to) = (self.edges.edges[e].from, self.edges.edges[e].to);
        let (kf, kt) = (&self.kfs.slots[from], &self.kfs.slots[to]);
        induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &kt.world_from_cam, Some(&mut self.seed));
        let t0 = Instant::now();
        let seed = if self.cfg.seed_edges { Some(&self.seed) } else { None };
        self.flow.estimate_pair(&kf.frame, &kt.frame, seed, &mut self.res, &mut self.res_reverse)?;
        self.times.flow += t0.elapsed();
        self.times.flow_estimates += 2;
        let edge = &mut self.edges.edges[e];
        write_measurement(&self.res, &self.cfg, &mut edge.target, &mut edge.weight);
        let edge = &mut self.edges.edges[r];
        write_measurement(&self.res_reverse, &self.cfg, &mut edge.target, &mut edge.weight);
        Ok(())
    }

    /// Estimates the flow of edge `e` seeded by the flow the current estimate induces, and
    /// stores its measurement. Returns the confident fraction.
    fn estimate_edge(&mut self, e: usize) -> Result<f32, TrackError> {
        let (from, to) = (self.edges.edges[e].from, self.edges.edges[e].to);
        let (kf, kt) = (&self.kfs.slots[from], &self.kfs.slots[to]);
        induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &kt.world_from_cam, Some(&mut self.seed));
        let t0 = Instant::now();
        let seed = if self.cfg.seed_edges { Some(&self.seed) } else { None };
        self.flow.estimate(&kf.frame, &kt.frame, seed, &mut self.res)?;
        self.times.flow += t0.elapsed();
        self.times.flow_estimates += 1;
        let edge = &mut self.edges.edges[e];
        Ok(write_measurement(&self.res, &self.cfg, &mut edge.target, &mut edge.weight))
    }

    /// Loads the window, solves, writes back; returns the final cost. A failed solve leaves
    /// the state as it was.
    fn solve_window(&mut self, iterations: usize, fixed: usize) -> Option<f64> {
        let t0 = Instant::now();
        let cfg = self.ba_config(iterations, fixed);
        let r = load_window(&mut self.ba, &self.low, &mut self.kfs, &self.edges, &self.window, false)
            .and_then(|_| self.ba.solve(&cfg))
            .and_then(|report| write_back(&self.ba, &mut self.kfs, &self.window).map(|_| report.final_cost));
        self.times.ba += t0.elapsed();
        match r {
            Ok(cost) => Some(cost),
            Err(e) => {
                tracing::debug!(error = %e, "track: window BA failed");
                self.counters.ba_failures += 1;
                None
            }
        }
    }

    /// Depth variance (Eq. 4) of every window keyframe at the loaded window's estimate.
    fn window_covariance(&mut self, fixed: usize) {
        let t0 = Instant::now();
        let cfg = self.ba_config(1, fixed);
        let r = self.ba.compute_covariance(&cfg);
        if r.is_ok() {
            let unit = match (self.cfg.variance_from_residuals, self.ba.unit_variance()) {
                (true, Some(u)) if u.is_finite() && u > 0.0 => u as f32,
                _ => 1.0,
            };
            for (k, &s) in self.window.iter().enumerate() {
                let kf = &mut self.kfs.slots[s];
                if self.ba.write_inv_depth_variance(k, &mut kf.variance).is_ok() {
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
            self.counters.ba_failures += 1;
        }
        self.times.covariance += t0.elapsed();
    }

    fn window_fixed(&self) -> usize {
        let n = self.window.len();
        if n >= 4 {
            n.saturating_sub(self.cfg.window_free_poses).max(2)
        } else {
            1
        }
    }

    /// Monocular initialisation: link the collected keyframes, then alternate flow and BA with
    /// many iterations from constant inverse depth.
    fn initialise(&mut self) -> Result<(), TrackError> {
        let n = self.kfs.len();
        self.new_edges.clear();
        for pos in 1..n {
            for back in 1..=self.cfg.edges_per_keyframe.min(pos) {
                let (a, b) = (self.kfs.order[pos], self.kfs.order[pos - back]);
                for (f, t) in [(a, b), (b, a)] {
                    if let Some(e) = self.edges.add(f, t, false) {
                        self.new_edges.push(e);
                    }
                }
            }
        }
        self.window.clear();
        self.window.extend_from_slice(&self.kfs.order);
        let collected = self.initial_rounds()?;
        let rms = self.cfg.init_level_start_rms_px as f64;
        let try_level = self.cfg.init_level_start && collected.is_none_or(|c| c > 0.5 * rms * rms);
        if try_level && self.init_snapshot.save(&self.kfs, &self.edges, &self.window, &self.new_edges) {
            self.level_start();
            let level = self.initial_rounds()?;
            let keep_level = match (collected, level) {
                (Some(c), Some(l)) => l < c,
                (None, Some(_)) => true,
                _ => false,
            };
            tracing::debug!(collected, level, keep_level, "track: initial BA from the collected and the level start");
            if !keep_level {
                self.init_snapshot.restore(&mut self.kfs, &mut self.edges, &self.window, &self.new_edges);
                // The covariance below is taken on the loaded window.
                if let Err(e) = load_window(&mut self.ba, &self.low, &mut self.kfs, &self.edges, &self.window, false) {
                    tracing::debug!(error = %e, "track: reloading the initial window failed");
                }
            }
            self.counters.init_level_start = keep_level;
        }
        self.window_covariance(1);
        self.phase = Phase::Running;
        self.state = TrackingState::Tracking;
        let newest = self.kfs.newest().expect("initialised with keyframes");
        self.ref_slot = newest;
        let last = &self.kfs.slots[newest];
        let before = &self.kfs.slots[self.kfs.order[n - 2]];
        let frames = last.seq.saturating_sub(before.seq).max(1) as f64;
        self.velocity = se3_exp(&(se3_log(&before.world_from_cam.inv_mul(&last.world_from_cam)) / frames));
        self.last_pose = last.world_from_cam;
        self.last_seq = last.seq;
        self.inserted_since_loop = 0;
        self.inserted_since_global = 0;
        Ok(())
    }

    /// `init_rounds` flow/BA rounds over the window (first pose fixed); the final cost per
    /// unit of flow weight of the new edges (`None` if the last solve failed).
    fn initial_rounds(&mut self) -> Result<Option<f64>, TrackError> {
        let mut cost = None;
        for _ in 0..self.cfg.init_rounds {
            self.estimate_new_edges()?;
            cost = self.solve_window(self.cfg.init_iterations, 1);
        }
        let weight: f64 = self.new_edges.iter().map(|&e| self.edges.edges[e].weight.data.iter().map(|&w| w as f64).sum::<f64>()).sum();
        Ok(cost.filter(|_| weight > 0.0).map(|c| c / weight))
    }

    /// The second start of the initial BA (`init_level_start`): every window keyframe at the
    /// first one's attitude, positions kept, every inverse depth the window's median.
    fn level_start(&mut self) {
        let Some(&first) = self.window.first() else { return };
        let attitude = self.kfs.slots[first].world_from_cam.rotation;
        self.scratch.clear();
        for &s in &self.window {
            self.scratch.extend(self.kfs.slots[s].inv_depth.data.iter().copied().filter(|d| d.is_finite() && *d >= MIN_INV_DEPTH));
        }
        let median = if self.scratch.is_empty() {
            self.cfg.initial_inv_depth
        } else {
            let m = self.scratch.len() / 2;
            *self.scratch.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1
        };
        for &s in &self.window {
            let kf = &mut self.kfs.slots[s];
            kf.world_from_cam = Se3::from_parts(kf.world_from_cam.translation, attitude);
            kf.inv_depth.data.fill(median);
        }
    }

    fn anchor_to(&self, slot: usize, pose: &Se3) -> FrameAnchor {
        let kf = &self.kfs.slots[slot];
        FrameAnchor { keyframe: kf.id, kf_from_cam: kf.world_from_cam.inv_mul(pose), kf_scale: kf.scale_correction }
    }

    fn track_running(&mut self, frame: &Frame, mut out: TrackOutput, frames_since: u64) -> Result<TrackOutput, TrackError> {
        let r = self.ref_slot;
        let predicted = self.predict(frames_since);
        {
            let kf = &self.kfs.slots[r];
            induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &predicted, Some(&mut self.seed));
        }
        self.flow_ref_to_current(r, true, self.cfg.frame_forward_backward)?;
        let conf = write_measurement(&self.res, &self.cfg, &mut self.obs_target, &mut self.obs_weight);
        tracing::trace!(seq = frame.seq, keyframe = self.kfs.slots[r].id, conf, mean_flow_input_px = self.res.stats.mean_flow_input_px, "track: frame flow");
        if conf < self.cfg.min_confident_fraction {
            return Ok(self.lost(out, LostReason::LowConfidence));
        }
        let mut pose = predicted;
        if self.motion_only(r, &mut pose).is_err() {
            return Ok(self.lost(out, LostReason::NoPose));
        }
        self.accept_pose(&pose, frame.seq, frames_since);
        self.state = TrackingState::Tracking;
        out.state = TrackingState::Tracking;
        out.world_from_cam = pose;
        out.anchor = Some(self.anchor_to(r, &pose));
        let measured = self.res.stats.mean_flow_input_px / self.factor as f32;
        let (induced, in_view) = {
            let kf = &self.kfs.slots[r];
            induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &pose, None)
        };
        let overlap = in_view.min(conf);
        if measured.max(induced) > self.cfg.keyframe_flow_px || overlap < self.cfg.keyframe_min_overlap {
            self.add_keyframe(frame, &mut out)?;
        }
        Ok(out)
    }

    /// A measured pose: updates the velocity and the last pose.
    fn accept_pose(&mut self, pose: &Se3, seq: u64, frames_since: u64) {
        let xi = se3_log(&self.last_pose.inv_mul(pose)) / frames_since.max(1) as f64;
        self.velocity = se3_exp(&xi);
        self.last_pose = *pose;
        self.last_seq = seq;
    }

    /// Initial inverse depth of keyframe `s` from keyframe `prev`: `prev`'s points splatted
    /// into `s` (bilinear weights, weighted mean: "closest wins" would bias every new keyframe
    /// closer, and with it the scale), holes filled with the median.
    fn splat_depth(&mut self, prev: usize, s: usize) {
        let low = self.low;
        let (w, h) = (low.width, low.height);
        let (kp, ks) = (&self.kfs.slots[prev], &self.kfs.slots[s]);
        let rel = ks.world_from_cam.inv_mul(&kp.world_from_cam);
        let rot = rel.rotation.to_rotation_matrix().into_inner();
        let t = rel.translation.vector;
        // Weighted sums in `scratch_depth`, weights in `scratch` (both depth-grid sized).
        self.scratch_depth.data.fill(0.0);
        self.scratch.clear();
        self.scratch.resize(w * h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let d = kp.inv_depth.data[y * w + x] as f64;
                let q = Vector3::new((x as f64 - low.cx) / low.fx, (y as f64 - low.cy) / low.fy, 1.0);
                let p = rot * q + t * d;
                if p.z <= 1e-6 {
                    continue;
                }
                let (u, v) = (low.fx * p.x / p.z + low.cx, low.fy * p.y / p.z + low.cy);
                let inv = (d / p.z) as f32;
                if !(inv.is_finite() && u > -1.0 && v > -1.0 && u < w as f64 && v < h as f64) {
                    continue;
                }
                let (u0, v0) = (u.floor(), v.floor());
                let (au, av) = ((u - u0) as f32, (v - v0) as f32);
                for (dy, wy) in [(0, 1.0 - av), (1, av)] {
                    for (dx, wx) in [(0, 1.0 - au), (1, au)] {
                        let (uu, vv) = (u0 as i64 + dx, v0 as i64 + dy);
                        if uu < 0 || vv < 0 || uu >= w as i64 || vv >= h as i64 {
                            continue;
                        }
                        let i = vv as usize * w + uu as usize;
                        self.scratch_depth.data[i] += wx * wy * inv;
                        self.scratch[i] += wx * wy;
                    }
                }
            }
        }
        for (d, &wgt) in self.scratch_depth.data.iter_mut().zip(&self.scratch) {
            *d = if wgt > 0.05 { *d / wgt } else { 0.0 };
        }
        self.scratch.clear();
        self.scratch.extend(self.scratch_depth.data.iter().copied().filter(|v| *v > 0.0));
        let fill = if self.scratch.is_empty() {
            kp.inv_depth.data.iter().sum::<f32>() / kp.inv_depth.data.len().max(1) as f32
        } else {
            let m = self.scratch.len() / 2;
            *self.scratch.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1
        };
        let ks = &mut self.kfs.slots[s];
        for (dst, &src) in ks.inv_depth.data.iter_mut().zip(&self.scratch_depth.data) {
            *dst = if src > 0.0 { src } else { fill };
        }
    }

    /// Inserts the current frame as a keyframe: links, flow/BA rounds, covariance, pruning,
    /// loop closure.
    /// The frame's pose is `last_pose` (just accepted).
    fn add_keyframe(&mut self, frame: &Frame, out: &mut TrackOutput) -> Result<(), TrackError> {
        // The previous insertion's deferred stages use the window and its new edges. They move
        // the reference keyframe, and `last_pose` with it: the new keyframe starts from the
        // re-anchored pose, not the one measured against the reference before (with keyframes
        // every two or three frames that stale pose drifted the map by 8 % of the path).
        out.loop_closed |= self.finish_pending()?;
        let pose = self.last_pose;
        let prev = self.ref_slot;
        let s = self.insert_keyframe_slot(frame, &pose);
        self.splat_depth(prev, s);
        let n = self.kfs.len();
        self.window.clear();
        self.window.extend_from_slice(&self.kfs.order[n.saturating_sub(self.cap.ba_window)..]);
        self.new_edges.clear();
        let mut links = 0;
        for i in (0..self.window.len().saturating_sub(1)).rev() {
            if links >= self.cfg.edges_per_keyframe {
                break;
            }
            let c = self.window[i];
            let (ks, kc) = (&self.kfs.slots[s], &self.kfs.slots[c]);
            let (flow, overlap) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kc.world_from_cam, None);
            if c == prev || (flow <= self.cfg.edge_max_flow_px && overlap >= self.cfg.edge_min_overlap) {
                for (f, t) in [(s, c), (c, s)] {
                    if let Some(e) = self.edges.add(f, t, false) {
                        self.new_edges.push(e);
                    }
                }
                links += 1;
            }
        }
        let fixed = self.window_fixed();
        if self.cfg.defer_rounds && self.cfg.defer_insertion {
            // Every round deferred, one edge or one solve per stage: the keyframe's frame pays
            // only for the insertion. Pruning judges the motion-only pose and splatted depth.
            let (kp, ks) = (&self.kfs.slots[prev], &self.kfs.slots[s]);
            let (flow, _) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kp.world_from_cam, None);
            tracing::debug!(kf = ks.id, links, induced_flow_px = flow, "track: keyframe inserted (rounds deferred)");
            if flow < self.cfg.prune_flow_px {
                let refined = ks.world_from_cam;
                self.prune_new_keyframe(s, prev, &refined, out);
                return Ok(());
            }
            self.accept_new_keyframe(s, out, Pending { slot: s, fixed, next_round: 0, next_edge: 0, fine: true, next_candidate: None, collecting: false });
            return Ok(());
        }
        self.keyframe_round(fixed)?;
        if self.cfg.local_rounds == 1 {
            self.window_covariance(fixed);
        }
        let (kp, ks) = (&self.kfs.slots[prev], &self.kfs.slots[s]);
        let (flow, _) = induced_flow(&self.low, &ks.world_from_cam, &ks.inv_depth, &kp.world_from_cam, None);
        let refined = ks.world_from_cam;
        tracing::debug!(kf = ks.id, links, induced_flow_px = flow, "track: keyframe inserted");
        if flow < self.cfg.prune_flow_px {
            self.prune_new_keyframe(s, prev, &refined, out);
            return Ok(());
        }
        // The remaining rounds, then loop closure or the periodic global BA: one stage per
        // following frame when deferred (latency), all now otherwise.
        self.accept_new_keyframe(s, out, Pending { slot: s, fixed, next_round: 1, next_edge: 0, fine: false, next_candidate: None, collecting: false });
        if !self.cfg.defer_rounds {
            while self.pending.is_some() {
                out.loop_closed |= self.run_pending_stage()?;
            }
            let kf = &self.kfs.slots[s];
            out.world_from_cam = kf.world_from_cam;
            self.last_pose = kf.world_from_cam;
        }
        Ok(())
    }

    /// Too close to the previous keyframe: the frame stays a plain frame.
    fn prune_new_keyframe(&mut self, s: usize, prev: usize, refined: &Se3, out: &mut TrackOutput) {
        self.edges.remove_touching(s);
        if let Some(pos) = self.kfs.position(s) {
            self.kfs.remove_at(pos);
        }
        self.counters.keyframes_pruned += 1;
        self.last_pose = *refined;
        out.world_from_cam = *refined;
        out.anchor = Some(self.anchor_to(prev, refined));
    }

    /// Keyframe `s` becomes the reference; `pending` holds its remaining stages.
    fn accept_new_keyframe(&mut self, s: usize, out: &mut TrackOutput, pending: Pending) {
        self.ref_slot = s;
        self.inserted_since_loop += 1;
        self.inserted_since_global += 1;
        self.pending = Some(pending);
        let kf = &self.kfs.slots[s];
        out.world_from_cam = kf.world_from_cam;
        out.new_keyframe = Some(kf.id);
        out.anchor = Some(FrameAnchor { keyframe: kf.id, kf_from_cam: Se3::identity(), kf_scale: kf.scale_correction });
        self.last_pose = kf.world_from_cam;
    }

    /// One flow/BA round of a keyframe insertion: re-estimate the new edges seeded by the
    /// current estimate, then solve the window.
    fn keyframe_round(&mut self, fixed: usize) -> Result<(), TrackError> {
        self.estimate_new_edges()?;
        self.round_solve(fixed);
        Ok(())
    }

    /// The window BA of a round; the last pose follows the reference keyframe.
    fn round_solve(&mut self, fixed: usize) {
        let r = self.ref_slot;
        let before = self.kfs.slots[r].world_from_cam;
        self.solve_window(self.cfg.local_iterations, fixed);
        self.last_pose = self.kfs.slots[r].world_from_cam * before.inv_mul(&self.last_pose);
    }

    /// Runs the next deferred stage of the last insertion; true when it closed a loop.
    fn run_pending_stage(&mut self) -> Result<bool, TrackError> {
        let Some(mut p) = self.pending else { return Ok(false) };
        if p.collecting {
            // The edges, then one solve of `init_iterations` (cut into solves of
            // `local_iterations` iterations each, it lost the turbid survey's scale at
            // 320x240: 13.8 % ATE).
            if p.next_edge < self.new_edges.len() {
                p.next_edge += self.estimate_new_edge_at(p.next_edge)?;
                self.pending = Some(p);
            } else {
                self.solve_window(self.cfg.init_iterations, p.fixed);
                self.pending = None;
            }
            return Ok(false);
        }
        if p.fine && p.next_round < self.cfg.local_rounds {
            if p.next_edge < self.new_edges.len() {
                p.next_edge += self.estimate_new_edge_at(p.next_edge)?;
                let last_round = p.next_round + 1 == self.cfg.local_rounds;
                if self.cfg.loop_closure && last_round && p.next_edge >= self.new_edges.len() && p.next_candidate.is_none() {
                    // The loop search goes before the last solve, into the stage the last
                    // edge pair leaves free (the solve takes a frame of its own). After the
                    // solve it took a fourth frame, and with keyframes every three or four
                    // frames it ran inside the next keyframe's frame (about 100 ms at
                    // 640x480 against 60 ms without loop closure). Ranking is a thumbnail
                    // comparison and verification is seeded by the keyframe's motion-only
                    // pose: neither needs the solve.
                    self.rank_loop_candidates(p.slot);
                    p.next_candidate = Some(0);
                }
            } else if let Some(k) = self.unverified_candidate(&p) {
                let closed = self.try_loop_candidate(p.slot, k)?;
                // After a closure the window solve still runs (the global BA moved it).
                p.next_candidate = Some(if closed { self.loop_candidates.len() } else { k + 1 });
                self.pending = Some(p);
                return Ok(closed);
            } else {
                self.round_solve(p.fixed);
                p.next_round += 1;
                p.next_edge = 0;
                if p.next_round == self.cfg.local_rounds {
                    self.window_covariance(p.fixed);
                    self.rounds_done(p);
                    return Ok(false);
                }
            }
            self.pending = Some(p);
            return Ok(false);
        }
        if p.next_round < self.cfg.local_rounds {
            self.keyframe_round(p.fixed)?;
            p.next_round += 1;
            if p.next_round == self.cfg.local_rounds {
                self.window_covariance(p.fixed);
                self.rounds_done(p);
                return Ok(false);
            }
            self.pending = Some(p);
            return Ok(false);
        }
        // Then the loop search, one candidate verified (a flow) per stage.
        if self.cfg.loop_closure {
            let next = match p.next_candidate {
                Some(k) => k,
                None => {
                    self.rank_loop_candidates(p.slot);
                    0
                }
            };
            if next < self.loop_candidates.len() {
                let closed = self.try_loop_candidate(p.slot, next)?;
                if closed {
                    self.pending = None;
                    return Ok(true);
                }
                if next + 1 < self.loop_candidates.len() {
                    self.pending = Some(Pending { next_candidate: Some(next + 1), ..p });
                    return Ok(false);
                }
            }
        }
        self.finish_insertion();
        Ok(false)
    }

    /// After the last flow/BA round of an insertion: ends it when the fine stages searched
    /// for loops before the solve; otherwise ranks the loop candidates right away (a
    /// thumbnail comparison, cheap) and ends the insertion when there is none to verify. A
    /// loop search with nothing to verify used to take a stage of its own, and after a window
    /// solve (a frame's only stage) a frame of its own; with keyframes every three frames
    /// (the end of the generated survey) that pushed the rest of the next insertion into the
    /// next keyframe's frame.
    fn rounds_done(&mut self, mut p: Pending) {
        if self.cfg.loop_closure && p.next_candidate.is_none() {
            self.rank_loop_candidates(p.slot);
            p.next_candidate = Some(0);
            if !self.loop_candidates.is_empty() {
                self.pending = Some(p);
                return;
            }
        }
        self.finish_insertion();
    }

    /// The insertion's deferred work is done; a periodic global BA when due.
    fn finish_insertion(&mut self) {
        self.pending = None;
        if self.cfg.global_ba_period > 0 && self.inserted_since_global >= self.cfg.global_ba_period {
            self.global_ba();
        }
    }

    /// The loop candidate of `p` to verify next, if its search has ranked candidates and not
    /// verified them all.
    fn unverified_candidate(&self, p: &Pending) -> Option<usize> {
        p.next_candidate.filter(|&k| k < self.loop_candidates.len())
    }

    /// Whether the next deferred stage is a window solve (or a whole round).
    fn next_stage_is_solve(&self) -> bool {
        match self.pending {
            Some(p) if p.collecting || (p.fine && p.next_round < self.cfg.local_rounds) => {
                p.next_edge >= self.new_edges.len() && self.unverified_candidate(&p).is_none()
            }
            Some(p) => p.next_round < self.cfg.local_rounds,
            None => false,
        }
    }

    /// Runs every deferred stage.
    fn finish_pending(&mut self) -> Result<bool, TrackError> {
        let mut closed = false;
        while self.pending.is_some() {
            closed |= self.run_pending_stage()?;
        }
        Ok(closed)
    }

    /// Dense BA over every live keyframe with every stored edge (loops included).
    fn global_ba(&mut self) -> bool {
        let n = self.kfs.len();
        if n < 3 || self.gba.capacity().max_keyframes < n {
            return false;
        }
        let t0 = Instant::now();
        let ref_before = self.kfs.slots[self.ref_slot].world_from_cam;
        self.window.clear();
        self.window.extend_from_slice(&self.kfs.order);
        let cfg = self.ba_config(self.cfg.global_iterations, 1);
        let r = load_window(&mut self.gba, &self.low, &mut self.kfs, &self.edges, &self.window, true)
            .and_then(|_| self.gba.solve(&cfg))
            .and_then(|_| write_back(&self.gba, &mut self.kfs, &self.window));
        self.times.global_ba += t0.elapsed();
        self.inserted_since_global = 0;
        match r {
            Ok(()) => {
                let ref_after = self.kfs.slots[self.ref_slot].world_from_cam;
                self.last_pose = ref_after * ref_before.inv_mul(&self.last_pose);
                self.counters.global_bas += 1;
                true
            }
            Err(e) => {
                tracing::debug!(error = %e, "track: global BA failed");
                self.counters.ba_failures += 1;
                false
            }
        }
    }

    /// Median of `z_in_s (from c) * d_s(own)`: the scale of `s`'s own depth relative to `c`'s,
    /// with `world_from_s` expressed in `c`'s scale. Uses confident pixels of `obs_weight`.
    fn relative_scale(&mut self, c: usize, world_from_s: &Se3, s: usize) -> Option<f64> {
        let low = self.low;
        let (w, h) = (low.width, low.height);
        let (kc, ks) = (&self.kfs.slots[c], &self.kfs.slots[s]);
        let rel = world_from_s.inv_mul(&kc.world_from_cam);
        self.scratch.clear();
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                if 0.5 * (self.obs_weight.data[2 * p] + self.obs_weight.data[2 * p + 1]) <= self.cfg.confident_weight {
                    continue;
                }
                let d = kc.inv_depth.data[p] as f64;
                let xc = nalgebra::Point3::new((x as f64 - low.cx) / low.fx / d, (y as f64 - low.cy) / low.fy / d, 1.0 / d);
                let xs = rel * xc;
                if xs.z <= 1e-6 {
                    continue;
                }
                let (u, v) = ((low.fx * xs.x / xs.z + low.cx).round(), (low.fy * xs.y / xs.z + low.cy).round());
                if u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
                    continue;
                }
                let own = ks.inv_depth.data[v as usize * w + u as usize] as f64;
                let r = (xs.z * own) as f32;
                if r.is_finite() && r > 0.0 {
                    self.scratch.push(r);
                }
            }
        }
        if self.scratch.len() < 20 {
            return None;
        }
        let m = self.scratch.len() / 2;
        Some(*self.scratch.select_nth_unstable_by(m, |a, b| a.total_cmp(b)).1 as f64)
    }

    /// Ranks live keyframes among the first `upto` by thumbnail NCC with `thumb` into
    /// `self.candidates` (best first, at least `min_ncc`).
    fn rank_candidates(&mut self, thumb_slot: Option<usize>, upto: usize, min_ncc: f32) {
        self.candidates.clear();
        for pos in 0..upto.min(self.kfs.len()) {
            let c = self.kfs.order[pos];
            let t = match thumb_slot {
                Some(s) => &self.kfs.slots[s].thumb,
                None => &self.cur_thumb,
            };
            let score = ncc(t, &self.kfs.slots[c].thumb);
            if score >= min_ncc {
                self.candidates.push((score, c));
            }
        }
        self.candidates.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        self.candidates.truncate(self.cfg.search_candidates);
    }

    /// Ranks the loop candidates of new keyframe `s` into `loop_candidates` (none while a loop
    /// was closed too recently or the graph is too short).
    fn rank_loop_candidates(&mut self, s: usize) {
        let n = self.kfs.len();
        if self.inserted_since_loop < self.cfg.loop_min_interval || n < self.cfg.loop_exclude_recent + 3 {
            self.loop_candidates.clear();
            return;
        }
        let t0 = Instant::now();
        self.rank_candidates(Some(s), n - 1 - self.cfg.loop_exclude_recent, self.cfg.loop_min_ncc);
        self.loop_candidates.clear();
        let k = self.candidates.len().min(self.cfg.loop_candidates);
        self.loop_candidates.extend_from_slice(&self.candidates[..k]);
        self.times.loop_closure += t0.elapsed();
    }

    /// Verifies loop candidate `k` of new keyframe `s` (flow, motion-only pose, relative
    /// scale); on success corrects the graph (Sim(3) pose graph, then dense global BA).
    fn try_loop_candidate(&mut self, s: usize, k: usize) -> Result<bool, TrackError> {
        let t0 = Instant::now();
        let (flow0, ba0, gba0) = (self.times.flow, self.times.ba, self.times.global_ba);
        let result = self.loop_candidate_inner(s, k);
        // Exclusive of the flow and BA it ran (counted in those stages).
        let inner = (self.times.flow - flow0) + (self.times.ba - ba0) + (self.times.global_ba - gba0);
        self.times.loop_closure += t0.elapsed().saturating_sub(inner);
        result
    }

    fn loop_candidate_inner(&mut self, s: usize, k: usize) -> Result<bool, TrackError> {
        let c = self.loop_candidates[k].1;
        // Seeded by the flow the current (drifted) estimate induces: drift is small next
        // to what the pyramid recovers, and the seed only offers each patch a candidate.
        {
            let (kc, ks) = (&self.kfs.slots[c], &self.kfs.slots[s]);
            induced_flow(&self.low, &kc.world_from_cam, &kc.inv_depth, &ks.world_from_cam, Some(&mut self.seed));
        }
        let t0 = Instant::now();
        let (kc, ks) = (&self.kfs.slots[c].frame, &self.kfs.slots[s].frame);
        if let Some(level) = self.loop_screen_level {
            let screen = self.flow.screen(kc, ks, Some(&self.seed), level, self.cfg.loop_screen_weight)?;
            self.times.flow += t0.elapsed();
            self.times.loop_screens += 1;
            if screen.confident_fraction < self.cfg.loop_screen_min_fraction {
                return Ok(false);
            }
        }
        let t0 = Instant::now();
        self.flow.estimate(kc, ks, Some(&self.seed), &mut self.res)?;
        self.times.flow += t0.elapsed();
        self.times.flow_estimates += 1;
        let conf = write_measurement(&self.res, &self.cfg, &mut self.obs_target, &mut self.obs_weight);
        let mean_flow = self.res.stats.mean_flow_input_px / self.factor as f32;
        if conf < self.cfg.loop_min_confident_fraction || mean_flow > self.cfg.loop_max_flow_px {
            return Ok(false);
        }
        // Start from the current estimate (close: drift is a few percent of the loop).
        let mut world_from_s = self.kfs.slots[s].world_from_cam;
        if self.motion_only(c, &mut world_from_s).is_err() {
            return Ok(false);
        }
        let Some(scale) = self.relative_scale(c, &world_from_s, s) else { return Ok(false) };
        if !(0.2..5.0).contains(&scale) {
            return Ok(false);
        }
        // The loop edge c -> s keeps this flow for the global BA.
        if let Some(e) = self.edges.add(c, s, true) {
            let ed = &mut self.edges.edges[e];
            ed.target.data.copy_from_slice(&self.obs_target.data);
            ed.weight.data.copy_from_slice(&self.obs_weight.data);
        }
        let z = sim3_relative(&self.kfs.slots[c].world_from_cam.inv_mul(&world_from_s), scale);
        self.pose_graph(c, s, z);
        if self.cfg.loop_global_ba {
            self.global_ba();
        }
        self.inserted_since_loop = 0;
        self.counters.loops_closed += 1;
        self.times.loops += 1;
        let rel = self.kfs.slots[c].world_from_cam.inv_mul(&world_from_s);
        tracing::debug!(
            from = self.kfs.slots[c].id,
            to = self.kfs.slots[s].id,
            from_seq = self.kfs.slots[c].seq,
            to_seq = self.kfs.slots[s].seq,
            ncc = self.loop_candidates[k].0,
            conf,
            mean_flow,
            scale,
            rel_t = rel.translation.vector.norm(),
            rel_deg = rel.rotation.angle().to_degrees(),
            "track: loop closed"
        );
        Ok(true)
    }

    /// Sim(3) pose graph over every live keyframe: consecutive relative poses as they are, plus
    /// the loop constraint `z` between slots `c` and `s`; applies the correction (poses,
    /// depth scale) to every keyframe.
    fn pose_graph(&mut self, c: usize, s: usize, z: duv_core::Sim3) {
        let ref_before = self.kfs.slots[self.ref_slot].world_from_cam;
        self.pg.clear();
        for &k in &self.kfs.order {
            self.pg.add_node(&self.kfs.slots[k].world_from_cam);
        }
        for i in 1..self.pg.nodes.len() {
            let z = self.pg.nodes[i - 1].inverse() * self.pg.nodes[i];
            self.pg.add_constraint(PoseConstraint { a: i - 1, b: i, z, weight: 1.0 });
        }
        let (Some(a), Some(b)) = (self.kfs.position(c), self.kfs.position(s)) else { return };
        self.pg.add_constraint(PoseConstraint { a, b, z, weight: 1.0 });
        self.pg.optimize(self.cfg.pose_graph_iterations);
        for (i, &k) in self.kfs.order.iter().enumerate() {
            let (pose, scale) = sim3_split(&self.pg.nodes[i]);
            let kf = &mut self.kfs.slots[k];
            kf.world_from_cam = pose;
            let inv = (1.0 / scale) as f32;
            for d in kf.inv_depth.data.iter_mut() {
                *d *= inv;
            }
            for v in kf.variance.data.iter_mut() {
                if *v < f32::MAX {
                    *v *= inv * inv;
                }
            }
            kf.scale_correction *= scale;
        }
        let kr = &self.kfs.slots[self.ref_slot];
        let rel = ref_before.inv_mul(&self.last_pose);
        let scale = self.pg.nodes[self.kfs.position(self.ref_slot).unwrap_or(0)].scaling();
        self.last_pose = kr.world_from_cam * scale_translation(&rel, scale);
        self.velocity = scale_translation(&self.velocity, scale);
    }

    /// Lost: try the reference keyframe with the predicted pose, then appearance candidates.
    fn relocalise(&mut self, frame: &Frame, mut out: TrackOutput) -> Result<TrackOutput, TrackError> {
        let w = self.camera.width;
        thumbnail(&self.grey.data, w, self.camera.height, &mut self.cur_thumb);
        // The reference keyframe first, seeded by the prediction (a short outage).
        let r = self.ref_slot;
        let predicted = out.world_from_cam;
        {
            let kf = &self.kfs.slots[r];
            induced_flow(&self.low, &kf.world_from_cam, &kf.inv_depth, &predicted, Some(&mut self.seed));
        }
        if let Some(pose) = self.try_relocalise_against(r, Some(predicted))? {
            return Ok(self.relocalised(out, r, pose, frame.seq));
        }
        self.rank_candidates(None, self.kfs.len(), self.cfg.reloc_min_ncc);
        for k in 0..self.candidates.len() {
            let c = self.candidates[k].1;
            if c == r {
                continue;
            }
            if let Some(pose) = self.try_relocalise_against(c, None)? {
                return Ok(self.relocalised(out, c, pose, frame.seq));
            }
        }
        out.world_from_cam = predicted;
        Ok(self.lost(out, LostReason::NotRelocalised))
    }

    /// Flow from keyframe `c` (seeded by `self.seed` when `predicted` is given) and
    /// motion-only BA; the pose when the match is verified.
    fn try_relocalise_against(&mut self, c: usize, predicted: Option<Se3>) -> Result<Option<Se3>, TrackError> {
        self.flow_ref_to_current(c, predicted.is_some(), true)?;
        let conf = write_measurement(&self.res, &self.cfg, &mut self.obs_target, &mut self.obs_weight);
        let mean_flow = self.res.stats.mean_flow_input_px / self.factor as f32;
        if conf < self.cfg.min_confident_fraction.max(self.cfg.loop_min_confident_fraction) || mean_flow > self.cfg.reloc_max_flow_px {
            return Ok(None);
        }
        let mut pose = predicted.unwrap_or(self.kfs.slots[c].world_from_cam);
        if self.motion_only(c, &mut pose).is_err() {
            return Ok(None);
        }
        Ok(Some(pose))
    }

    fn relocalised(&mut self, mut out: TrackOutput, c: usize, pose: Se3, seq: u64) -> TrackOutput {
        self.ref_slot = c;
        self.velocity = Se3::identity();
        self.last_pose = pose;
        self.last_seq = seq;
        self.state = TrackingState::Relocalised;
        self.counters.relocalisations += 1;
        out.state = TrackingState::Relocalised;
        out.world_from_cam = pose;
        out.anchor = Some(self.anchor_to(c, &pose));
        out
    }
}
