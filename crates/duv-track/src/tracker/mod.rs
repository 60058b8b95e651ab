//! The tracker: frames in, a pose for every frame and keyframes with inverse depth and
//! variance out (paper §3.1). See the [module docs](super) for the method.
//!
//! [`Tracker`] is the public face; its working state is split by concern, one file each:
//! [`output`] (what it reports), [`frame`] (per-frame tracking), [`init`] (initialisation),
//! [`window`] (edges and window BA), [`insert`] (keyframe insertion and eviction), [`loops`]
//! (loop closure), [`background`] (the dense global BA, on a worker thread of its own),
//! [`reloc`] (relocalisation), [`segments`] (map segments after a loss and their merging),
//! [`seed`] (resume seeding) and [`emit`] (keyframes handed on once their depth is final).

mod background;
mod emit;
mod frame;
mod init;
mod insert;
mod loops;
mod output;
mod reloc;
mod seed;
mod segments;
mod window;

pub use output::{EvictedKeyframe, FrameAnchor, KeyframeView, LostReason, StageTimes, TrackNote, TrackOutput, TrackerCounters, TrackingState};
pub use seed::{ResumePoint, SeedFrame, SeedKeyframe, TrackerSeed};
use frame::{FrameWork, Motion};
use init::Init;
use insert::{Insertion, Pending};
use background::{BackgroundBa, PendingGlobalBa};
use loops::Loops;
use output::Stats;
use reloc::Reloc;
use segments::Segments;
use window::WindowBa;
use window::load_window;

use super::ba::{solve_motion_only, BaCapacity, BaConfig, BaError, BaWorkspace, MotionOnlyObservation};
use super::config::{ConfigError, TrackerCapacity, TrackerConfig};
use super::flow::{FlowError, FlowEstimator, FlowField, FlowResult, PreparedFrame};
use super::graph::{sim3_relative, sim3_split, EdgeStore, PoseConstraint, PoseGraph};
use super::keyframes::{block_means, image_health, ncc, thumbnail, Keyframe, KeyframeStore, THUMB_N};
use super::snapshot::WindowSnapshot;
use super::consistency::{blend_consistency, consistency_grid, ConsistencyScratch};
use super::despeckle::Despeckle;
use super::upsample::{border_variance, joint_bilateral, texture_variance, UpsampleParams};
use duv_core::frame::LUMA_WEIGHTS;
use duv_core::pose::{se3_exp, se3_log};
use duv_core::{Frame, FrameImage, Image, PinholeCamera, PlaneF32, Se3, Timestamp};
use nalgebra::{Translation3, Vector3};
use std::time::{Duration, Instant};

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
    #[error("ignore mask has {len} pixels, the tracker's frames are {width}x{height}")]
    MaskSize { len: usize, width: usize, height: usize },
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
    /// Keyframes waiting for their depth to be final ([`Tracker::emit_keyframes_after`]).
    emit: emit::Emission,
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
    /// Per-frame flow work: the current frame and the buffers every frame reuses.
    work: FrameWork,
    /// The keyframes and the flow edges between them.
    graph: Graph,
    /// The window BA.
    win: WindowBa,
    /// Initialisation.
    init: Init,
    /// Loop closure and global BA.
    loops: Loops,
    /// Relocalisation.
    reloc: Reloc,
    /// Map segments (multi-map).
    segments: Segments,
    /// The tracking status and motion model.
    motion: Motion,
    /// Keyframe insertion and eviction.
    insert: Insertion,
    /// What the tracker reports about itself.
    stats: Stats,
    /// Workspace of the variance's consistency term (`upsample_keyframe` takes `&self`).
    consistency: std::sync::Mutex<ConsistencyScratch>,
    /// Depth-grid cells whose flow gets no weight ([`Tracker::set_ignore_mask`]).
    ignore: Option<Vec<bool>>,
}

/// The keyframes and the flow edges between them.
struct Graph {
    kfs: KeyframeStore,
    edges: EdgeStore,
    /// Edges added by the pending insertion.
    new_edges: Vec<usize>,
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
        Ok(Tracker { pool: std::sync::Arc::new(pool), emit: emit::Emission::new(cap.max_keyframes), st })
    }

    /// Tracks one frame. Frames of the wrong size are an error; black, saturated or
    /// featureless frames are reported as [`TrackingState::Lost`] and leave the map untouched.
    ///
    /// Called from outside the tracker's pool, each call enters it (`ThreadPool::install`),
    /// which goes through rayon's injector queue: that allocates a small block every 63 calls.
    /// The tracking thread of a pipeline runs its loop inside the pool with
    /// [`run_in_pool`](Self::run_in_pool) instead, and then nothing is allocated per frame.
    pub fn track(&mut self, frame: &Frame) -> Result<TrackOutput, TrackError> {
        let out = if self.pool.current_thread_index().is_some() {
            self.st.track(frame)?
        } else {
            let st = &mut self.st;
            self.pool.install(|| st.track(frame))?
        };
        if let TrackNote::InitRestarted { .. } = out.note {
            // The keyframes collected before the restart are gone: none is handed on.
            let kfs = &self.st.graph.kfs;
            self.emit.retain(|id| kfs.slot_of(id).is_some());
        }
        if let Some(id) = out.new_keyframe {
            self.emit.inserted(id);
        }
        Ok(out)
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
    /// Pixels to ignore (1) in every frame, row-major at the input size: a burned-in overlay,
    /// the vehicle's own frame in view. Their depth-grid cells, and the cells next to them,
    /// get no flow weight as a source or as a target, so a static overlay does not hold the
    /// motion at zero. Allocates once.
    pub fn set_ignore_mask(&mut self, mask: &[u8]) -> Result<(), TrackError> {
        let (w, h) = (self.st.camera.width, self.st.camera.height);
        if mask.len() != w * h {
            return Err(TrackError::MaskSize { len: mask.len(), width: w, height: h });
        }
        let (lw, lh, f) = (self.st.low.width, self.st.low.height, self.st.factor);
        let mut cells = vec![false; lw * lh];
        for y in 0..(lh * f).min(h) {
            for x in 0..(lw * f).min(w) {
                if mask[y * w + x] != 0 {
                    cells[(y / f) * lw + x / f] = true;
                }
            }
        }
        let mut grown = cells.clone();
        for y in 0..lh {
            for x in 0..lw {
                if cells[y * lw + x] {
                    for yy in y.saturating_sub(1)..=(y + 1).min(lh - 1) {
                        for xx in x.saturating_sub(1)..=(x + 1).min(lw - 1) {
                            grown[yy * lw + xx] = true;
                        }
                    }
                }
            }
        }
        self.st.ignore = grown.iter().any(|&c| c).then_some(grown);
        Ok(())
    }

    /// Whether an initial BA has run (before it, keyframe poses are provisional and the
    /// initialisation may start again without them). A new segment collecting its first
    /// keyframes does not undo it: see [`collecting_segment`](Self::collecting_segment).
    pub fn is_initialised(&self) -> bool {
        self.st.init.phase == Phase::Running || self.st.segments.initialised_once
    }
    /// The segment whose keyframes are still provisional (collecting for its initial BA), if any.
    pub fn collecting_segment(&self) -> Option<u32> {
        (self.st.init.phase != Phase::Running).then_some(self.st.segments.current)
    }
    /// New segments get ids from `next` on at least (a resume: the ids an earlier process of
    /// the dive gave out).
    pub fn reserve_segment_ids(&mut self, next: u32) {
        self.st.segments.next = self.st.segments.next.max(next);
    }
    /// The segment new keyframes join.
    pub fn current_segment(&self) -> u32 {
        self.st.segments.current
    }
    /// Distinct map segments among the live keyframes (1 once initialised and never lost for
    /// good, or when every segment merged).
    pub fn live_segments(&self) -> usize {
        self.st.live_segments()
    }
    pub fn state(&self) -> TrackingState {
        self.st.motion.state
    }
    pub fn times(&self) -> StageTimes {
        self.st.stats.times
    }
    pub fn counters(&self) -> TrackerCounters {
        self.st.stats.counters
    }
    /// Live keyframes, oldest first.
    pub fn keyframes(&self) -> impl Iterator<Item = KeyframeView<'_>> {
        self.st.graph.kfs.order.iter().map(|&s| view(&self.st.graph.kfs.slots[s]))
    }
    /// Number of live keyframes.
    pub fn num_keyframes(&self) -> usize {
        self.st.graph.kfs.len()
    }
    /// The keyframe evicted by the last [`track`](Self::track) call, readable until the next.
    pub fn evicted_keyframe(&self) -> Option<KeyframeView<'_>> {
        self.st.insert.evicted_slot.map(|s| view(&self.st.graph.kfs.slots[s]))
    }
    /// Live edges as `(from id, to id, is_loop)`.
    pub fn edges(&self) -> impl Iterator<Item = (u64, u64, bool)> + '_ {
        let st = &self.st;
        st.graph.edges.live.iter().map(move |&e| {
            let ed = &st.graph.edges.edges[e];
            (st.graph.kfs.slots[ed.from].id, st.graph.kfs.slots[ed.to].id, ed.is_loop)
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
        let slot = st.graph.kfs.slot_of(id).or(st.insert.evicted_slot.filter(|&s| st.graph.kfs.slots[s].id == id)).ok_or(TrackError::NoSuchKeyframe { id })?;
        let (w, h) = (st.camera.width, st.camera.height);
        for p in [&*inv_depth, &*variance] {
            if p.width != w || p.height != h || p.data.len() != w * h {
                return Err(TrackError::OutputSize { width: p.width, height: p.height, expected_width: w, expected_height: h });
            }
        }
        let kf = &st.graph.kfs.slots[slot];
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
                    let neighbours = st.consistency_neighbours(kf.id, kf.segment, cfg.consistency_neighbours).map(|s| (st.graph.kfs.slots[s].world_from_cam, &st.graph.kfs.slots[s].inv_depth));
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
        self.pool.install(|| {
            let started = st.global_ba();
            if st.loops.gba_running {
                st.finish_global_ba()
            } else {
                started
            }
        })
    }

    /// Applies a global BA still running in the background now, waiting for it (the end of a
    /// stream: [`Tracker::next_final_keyframe`] with `flush` does it). Returns whether one was
    /// pending and moved the map.
    pub fn finish_global_ba(&mut self) -> bool {
        self.st.finish_global_ba()
    }
}

fn view(kf: &Keyframe) -> KeyframeView<'_> {
    KeyframeView {
        id: kf.id,
        t_ns: kf.t_ns,
        seq: kf.seq,
        segment: kf.segment,
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
/// by `weight_scale`; none for cells `ignore` marks, as source or target) and returns the confident fraction (mean of the two weights above
/// `confident_weight`). Targets closer than `border_margin_px` to the border get no weight:
/// some of the cell's pixels may have left the view, and the pooled mean of those that stayed
/// is biased towards the smaller flows (with forward motion this stretched the map a few
/// percent per keyframe). Within `border_taper_px` of either image's border (source pixel or
/// target, past the margin) the weights fall off quadratically: there the patches that
/// measured the flow were clipped by the border and the pooled cells partly out of view, a
/// bias the confidences do not see. The taper only lowers BA weights; the confident fraction
/// (tracking loss, overlap, loop checks) is counted before it.
fn write_measurement(res: &mut FlowResult, cfg: &TrackerConfig, ignore: Option<&[bool]>, target: &mut Image<f32, 2>, weight: &mut Image<f32, 2>) -> f32 {
    if let Some(m) = ignore {
        // The flow's mean (keyframe and parallax decisions) without the ignored cells: a static
        // overlay's confident zero flow would hold it down.
        let (mut sum, mut sw) = (0.0f64, 0.0f64);
        for (p, _) in m.iter().enumerate().filter(|(_, &i)| !i) {
            let wgt = (res.pooled.weight_x.data[p] + res.pooled.weight_y.data[p]) as f64;
            let (u, v) = (res.pooled.flow.dx.data[p] as f64, res.pooled.flow.dy.data[p] as f64);
            if wgt > 0.0 && u.is_finite() && v.is_finite() {
                sum += wgt * (u * u + v * v).sqrt();
                sw += wgt;
            }
        }
        res.stats.mean_flow_input_px = if sw > 0.0 { (sum / sw * cfg.flow.output_factor as f64) as f32 } else { 0.0 };
    }
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
            // Ignored pixels (a static overlay), as the source cell or at the target.
            let ignored = ignore.is_some_and(|m| m[p] || (finite && in_view && m[(ty.round() as usize).min(h - 1) * w + (tx.round() as usize).min(w - 1)]));
            if !finite || !in_view || ignored {
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
    /// not be live (the keyframe just evicted). Only keyframes of `segment` (another segment's
    /// frame is not this one's).
    fn consistency_neighbours(&self, id: u64, segment: u32, n: usize) -> impl Iterator<Item = usize> + '_ {
        let order = &self.graph.kfs.order;
        let before = order.partition_point(|&s| self.graph.kfs.slots[s].id < id);
        let after = order.partition_point(|&s| self.graph.kfs.slots[s].id <= id);
        let slots = &self.graph.kfs.slots;
        order[before.saturating_sub(n)..before]
            .iter()
            .chain(&order[after..(after + n).min(order.len())])
            .copied()
            .filter(move |&s| slots[s].has_variance && slots[s].segment == segment)
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
            work: FrameWork {
                grey: PlaneF32::new(w, h),
                despeckle: cfg.despeckle_radius(w).map(|r| Despeckle::new(w, h, r, cfg.despeckle_min_contrast)),
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
                flow,
            },
            graph: Graph { kfs, edges: EdgeStore::new(max_edges, lw, lh), new_edges: Vec::with_capacity(max_edges) },
            win: WindowBa { ba, window: Vec::with_capacity(cap.max_keyframes) },
            init: Init { phase: Phase::Empty, init_snapshot: WindowSnapshot::new(cap.ba_window, init_edges, lw, lh), failed_in_a_row: 0 },
            loops: Loops {
                gba: BackgroundBa::new(gba, (cfg.loop_closure || cfg.global_ba_period > 0) && cfg.global_ba_lag_frames > 0)?,
                pending_gba: PendingGlobalBa { started_frame: 0, segment: 0, window: Vec::with_capacity(gba_kfs) },
                gba_running: false,
                pg: PoseGraph::new(cap.max_keyframes, 2 * cap.max_keyframes + 8),
                loop_candidates: Vec::with_capacity(cap.max_keyframes),
                inserted_since_loop: 0,
                loop_screen_level,
                inserted_since_global: 0,
            },
            reloc: Reloc { candidates: Vec::with_capacity(cap.max_keyframes) },
            segments: Segments { current: 0, next: 1, failed_relocs: 0, start_inv_depth: cfg.initial_inv_depth, initialised_once: false },
            motion: Motion { state: TrackingState::Initializing, ref_slot: 0, last_pose: Se3::identity(), velocity: Se3::identity(), last_seq: 0 },
            insert: Insertion { evicted_slot: None, pending_eviction: None, pending: None },
            stats: Stats { times: StageTimes::default(), counters: TrackerCounters::default() },
            consistency: std::sync::Mutex::new(ConsistencyScratch::new(lw, lh)),
            ignore: None,
            factor,
            cfg,
            cap,
        })
    }
}
