//! Tracker parameters ([`TrackerConfig`], algorithm data: defaults here and nowhere else) and
//! capacities ([`TrackerCapacity`], from the board: every buffer is sized from them once).

use super::ba::BaConfig;
use super::flow::FlowConfig;
use serde::{Deserialize, Serialize};

/// Fixed sizes of a [`Tracker`](super::Tracker), taken from the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackerCapacity {
    /// Keyframes kept in the graph (`budgets.max_keyframes`); older redundant ones are evicted.
    pub max_keyframes: usize,
    /// Keyframes in the sliding local BA window (`budgets.ba_window`).
    pub ba_window: usize,
    /// Worker threads of the tracker's rayon pool (`threads.tracking`).
    pub threads: usize,
}

impl TrackerCapacity {
    /// The capacities a board gives.
    pub fn from_board(board: &duv_core::config::board::Board) -> Self {
        TrackerCapacity {
            max_keyframes: board.budgets.max_keyframes as usize,
            ba_window: board.budgets.ba_window as usize,
            threads: board.threads.tracking as usize,
        }
    }
}

/// Most neighbours on each side that `consistency_neighbours` may ask for.
pub const MAX_CONSISTENCY_NEIGHBOURS: usize = 8;

/// Every parameter of the tracker. Pixel quantities named `_px` are in low-resolution (depth
/// grid) pixels, as DROID-SLAM measures flow, unless named otherwise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackerConfig {
    /// Input pixels per inverse-depth pixel, also the flow's pooled output cell; absent: the
    /// largest of 4, 8, 16, 32 that leaves at least `depth_min_pixels` depth pixels (8 at
    /// 320x240, 16 at 640x480: a grid of about 40x30, which the pixel thresholds below are
    /// tuned for and which keeps the BA cost independent of the input size).
    pub depth_factor: Option<usize>,
    /// Depth pixels the automatic `depth_factor` keeps at least.
    pub depth_min_pixels: usize,
    /// Dense flow front end (its `output_factor` is replaced by `depth_factor`).
    pub flow: FlowConfig,
    /// Seed the keyframe-edge flows with the flow the current BA estimate induces.
    pub seed_edges: bool,
    /// Measure both directions of a keyframe link with one pair estimate (the forward-backward
    /// passes of one edge are the two edges' flows): half the edge-flow cost, the two
    /// directions no longer independent measurements. After initialisation only (with pairs
    /// the initial map from constant depth came out worse).
    pub pair_edges: bool,
    /// Run the forward-backward check on the flow that tracks each frame against its keyframe
    /// (keyframe edges always have it). Off, the frame's flow costs half and its confidences
    /// rest on texture and the photometric residual alone; a wrong pose from a bad match then
    /// reaches the map through the next keyframe's start: the 320x240 survey with seed 3
    /// drifted to 8.7 % of the path (0.21 % with the check), so it is on by default.
    pub frame_forward_backward: bool,
    /// Local window BA (its `max_iterations` and `fixed_poses` are set per use).
    pub ba: BaConfig,
    /// A frame becomes a keyframe when the mean flow from the last keyframe exceeds this: the
    /// larger of the measured flow (confidence-weighted) and the flow its estimated pose
    /// induces on the keyframe's depth grid.
    pub keyframe_flow_px: f32,
    /// A frame also becomes a keyframe when fewer than this fraction of the last keyframe's
    /// pixels are confidently matched in it, or land in its view (the overlap runs out).
    pub keyframe_min_overlap: f32,
    /// A new keyframe whose BA-induced mean flow to the previous one is below this is dropped.
    pub prune_flow_px: f32,
    /// Keyframes collected before the initial BA (monocular initialisation).
    pub init_keyframes: usize,
    /// When a frame cannot be matched to the reference keyframe while at least this many
    /// keyframes are collected, the initial BA runs on them at once (the view was matched
    /// often enough to start from) and the frame is tracked as the first after a loss (turned
    /// predictions, relocalisation, a new segment) instead of the collection being dropped by
    /// `init_restart_after`: a turn at a low frame rate during the collection. 0: always wait
    /// for `init_keyframes`.
    pub init_min_keyframes: usize,
    /// Flow/BA rounds of the initial BA.
    pub init_rounds: usize,
    /// Gauss-Newton iterations per round of the initial BA.
    pub init_iterations: usize,
    /// Give the initial BA a second start and keep whichever ends at the lower cost per unit
    /// of flow weight: every collected keyframe at the first one's attitude (positions as
    /// collected) with one constant inverse depth (the median of the collected depths), then
    /// the same `init_rounds` flow/BA rounds. The collected estimate grows keyframe by
    /// keyframe from constant depth, and over a near-planar seabed two-view geometry has two
    /// solutions: the wrong one is a camera pitching steadily over a seabed bent to match,
    /// consistent enough from view to view that the BA stays there, and every later keyframe
    /// continues it. On the turbid survey at 320x240 (generator seeds 2 and 4) the track
    /// bent by about 2.5 degrees per keyframe from the first ones on, 12.5 % ATE; from the
    /// level start the same rounds end at a sixth of the cost. Costs one more set of rounds, once.
    pub init_level_start: bool,
    /// The level start is tried only when the collected start's solve ends above this RMS
    /// residual, in depth-grid pixels of whitened flow error (its Huber cost per unit of flow
    /// weight over `rms^2 / 2`); 0 always tries it. On the generated surveys (clear, coastal,
    /// turbid; generator seeds 1-4; 320x240 and 640x480) the collected start ended at
    /// 0.030-0.047 px where it was right and at 0.066-0.22 px where it had bent.
    pub init_level_start_rms_px: f32,
    /// Initialisation starts again from the current frame after this many frames in a row
    /// could not be matched to the reference keyframe (flow confident on too few pixels, or no
    /// pose against it): the vehicle has moved on from the view it started on (a dark or
    /// snowy start, a turbidity burst, a low frame rate), and waiting would hang for ever. The
    /// keyframes collected so far are dropped with their provisional poses. 0 never restarts.
    pub init_restart_after: usize,
    /// Recovery in new territory (multi-map): after this many good frames in a row (image
    /// health passed) that could not be relocalised against any stored keyframe, a new map
    /// segment starts from the current frame, as a new initialisation whose first pose is the
    /// prediction and whose depth is the last reference keyframe's median. The stored keyframes
    /// stay: when a later keyframe matches one of another segment (loop detection, or
    /// relocalisation after a loss), the two are merged with the Sim(3) the match measures.
    /// 0 never starts one (stays lost until relocalised).
    pub new_segment_after: usize,
    /// Marine snow removal ([`crate::despeckle`]): bright specks up to `2 r + 1` pixels across
    /// and brighter than their surroundings by more than `despeckle_min_contrast` are replaced
    /// by the seabed around them before the flow sees the frame. `r` is
    /// `despeckle_radius_px`, or with 0 one pixel per 160 of image width from 320 pixels wide
    /// (2 at 320x240, 4 at 640x480) and none below: at 160x120 a 3-pixel speck cannot be told
    /// from the texture's finest detail (the survey's ATE rose from 0.136 to 0.168 m there).
    /// Fast turns: when the flow from the reference keyframe at the predicted pose is not
    /// confident (or relocalisation after a loss), the prediction is tried again turned about
    /// the camera's vertical axis by +-1 and +-2 times this many degrees, and the first turn
    /// whose flow is confident on at least `loop_min_confident_fraction` of the pixels and
    /// whose motion-only BA converges is taken (a survey's lane turn at a low frame rate turns
    /// the camera 9-10 degrees a frame while the motion model predicts the straight lane's).
    /// 0 turns it off.
    pub turn_search_deg: f32,
    pub despeckle: bool,
    pub despeckle_radius_px: usize,
    /// Grey level (in [0, 1]) by which a speck must stand out of the grey-scale opening.
    pub despeckle_min_contrast: f32,
    /// Flow/BA rounds per keyframe insertion (the recurrent updates of the paper). One by
    /// default: the seed from the BA estimate already carries the previous keyframes' solve
    /// into the edges; a second round cost a quarter more CPU per frame (58 against 47 ms
    /// at 640x480) for 0.09 % against 0.11 % ATE on the survey, 0.34 % against 0.37 % on
    /// the 1 m/s test loop.
    pub local_rounds: usize,
    /// Gauss-Newton iterations per round of the local BA.
    pub local_iterations: usize,
    /// Run the insertion's later rounds, then its loop search or global BA, one stage per
    /// following frame (spreads the keyframe cost: lower worst-case frame latency).
    pub defer_rounds: bool,
    /// With `defer_rounds`, defer the first round too, in stages of one edge (pair) or one
    /// window solve: the keyframe's own frame pays only for the insertion, and pruning judges
    /// the motion-only pose (the frames after it track against the splatted depth until the
    /// round's BA has run). On by default: it is what keeps the worst steady-state frame near
    /// one frame plus two stages. When keyframes come faster than their stages (every two
    /// or three frames), a new keyframe first finishes the previous one's stages and starts
    /// from the frame's pose re-anchored to the solved reference.
    pub defer_insertion: bool,
    /// Deferred stages run at the start of each frame (a new keyframe first finishes what is
    /// left of the previous one). Two: an insertion (up to three edge pairs, the window solve
    /// with Eq. 4, which is a frame's only stage, one loop candidate) is done within four
    /// frames, before the next keyframe on all but the fastest motion.
    pub stages_per_frame: usize,
    /// Newest window keyframes whose poses the local BA moves; the older ones are held fixed
    /// (at least two are always fixed: gauge and scale). Fewer free poses tie new keyframes
    /// to the established map and slow monocular scale drift.
    pub window_free_poses: usize,
    /// Older keyframes a new keyframe is linked to (each link is two directed edges).
    pub edges_per_keyframe: usize,
    /// Largest BA-induced mean flow between two keyframes that still gives an edge.
    pub edge_max_flow_px: f32,
    /// Smallest fraction of a keyframe's pixels that must land inside the other for an edge.
    pub edge_min_overlap: f32,
    /// Inverse depth the first keyframe starts from, 1/m (sets the arbitrary monocular scale).
    pub initial_inv_depth: f32,
    /// Gauss-Newton iterations of the motion-only BA of a frame.
    pub motion_iterations: usize,
    /// The motion-only BA of a frame weighs each keyframe pixel by its depth's uncertainty
    /// too: the keyframe's inverse-depth variance (Eq. 4), propagated through the projection,
    /// is added to the flow's (see `MotionOnlyObservation::inv_depth_variance`). Pixels whose
    /// depth the window BA never measured (the prior alone holds them, relative standard
    /// deviations of 2-5 against 0.01-0.03 measured) then stop pulling the pose. Without it
    /// the 640x480 coastal survey with generator seed 3 traded translation for pitch from
    /// frame 113 on (4.3 % ATE; 0.07 % with it).
    pub motion_depth_variance: bool,
    /// Flow targets closer than this to the image border get no weight (the pooled flow of a
    /// cell partly out of view is biased).
    pub border_margin_px: f32,
    /// Distance from either image's border (past the margin) over which a measurement's BA
    /// weights fall off quadratically to zero: flow there comes from border-clipped patches
    /// and partly out-of-view cells. 0 (the default) disables it: on the 320x240 survey 3 px
    /// took the ATE from 0.11 % to 0.06 % of the path, but on the turbid survey at 320x240,
    /// where the hazy far field already carries little weight, it took it from 0.21 % to
    /// 0.66 % (2 px) and 14 % (3 px).
    pub border_taper_px: f32,
    /// Scale of the flow confidences into BA weights (inverse variance per weight unit).
    pub weight_scale: f32,
    /// A pooled pixel is confident when both of its axis weights exceed this.
    pub confident_weight: f32,
    /// Tracking fails when fewer than this fraction of the keyframe's pixels are confident.
    pub min_confident_fraction: f32,
    /// A frame whose mean intensity (in [0, 1]) is below this is black.
    pub min_mean_intensity: f32,
    /// A frame whose mean intensity is above this is saturated.
    pub max_mean_intensity: f32,
    /// A frame whose contrast (standard deviation of 4x4 block means, intensity units) is
    /// below this is a contrast collapse (turbidity burst).
    pub min_contrast: f32,
    /// Thumbnails (appearance) a relocalisation or loop search verifies with flow, best first.
    pub search_candidates: usize,
    /// Smallest thumbnail NCC of a relocalisation candidate.
    pub reloc_min_ncc: f32,
    /// Largest mean flow to a relocalisation candidate.
    pub reloc_max_flow_px: f32,
    /// Detect loops and correct the graph (pose graph in Sim(3), then dense global BA).
    pub loop_closure: bool,
    /// Keyframes before the newest that are not loop candidates (the recent trajectory).
    pub loop_exclude_recent: usize,
    /// Loop candidates verified with flow per new keyframe, best thumbnail NCC first (one
    /// flow each, one per deferred stage). Each costs a keyframe edge; a loop missed at one
    /// keyframe is offered again at the next, as the vehicle keeps overlapping the old track.
    pub loop_candidates: usize,
    /// Smallest thumbnail NCC of a loop candidate.
    pub loop_min_ncc: f32,
    /// Largest mean flow magnitude between a loop candidate and the new keyframe.
    pub loop_max_flow_px: f32,
    /// Smallest confident fraction of the flow between a loop candidate and the new keyframe.
    pub loop_min_confident_fraction: f32,
    /// Loop candidates are screened before the full flow check: both flow passes run down to
    /// one level above the finest only (about a fifth of the check's cost) and a candidate
    /// goes on to the full check only when at least `loop_screen_min_fraction` of the
    /// output-grid cells have a mean weight (photometric x forward-backward) over
    /// `loop_screen_weight`. 0 turns the screen off. Measured on generated survey, loop and
    /// turbid sequences (3 seeds, 320x240 and 640x480): every candidate that passed the full
    /// check screened at 0.27 or more, 90 % of those that failed it under 0.11.
    pub loop_screen_min_fraction: f32,
    /// Cell weight of the loop screen's confident fraction (lower than `confident_weight`:
    /// the screen's coarser flow weighs less).
    pub loop_screen_weight: f32,
    /// Keyframes inserted between two accepted loop closures at least.
    pub loop_min_interval: usize,
    /// Gauss-Newton iterations of the Sim(3) pose graph.
    pub pose_graph_iterations: usize,
    /// Run a dense global BA over every keyframe after each accepted loop (after the pose graph).
    pub loop_global_ba: bool,
    /// Run a dense global BA over every keyframe after this many insertions (0: only after
    /// loops). Each run costs one frame of tens of milliseconds (about 70 ms for 56 keyframes
    /// at 320x240 with 2 iterations), which is why it is off by default.
    pub global_ba_period: usize,
    /// Gauss-Newton iterations of the dense global BA.
    pub global_iterations: usize,
    /// Frames the dense global BA runs in the background before it is applied (0: on the
    /// tracking thread, in the frame that asks for it). Counted in frames, not time, so a
    /// replay gives the same trajectory; the apply waits for the worker when it is not done
    /// (`global_ba_waits`). See the tracker's `background` module.
    pub global_ba_lag_frames: usize,
    /// Spatial sigma of the joint bilateral upsampling, low-res pixels.
    pub upsample_sigma_px: f32,
    /// Range sigma of the joint bilateral upsampling, intensity units.
    pub upsample_sigma_intensity: f32,
    /// Weight of the interpolation uncertainty (the weighted spread of the neighbours' inverse
    /// depths) added to the upsampled variance.
    pub upsample_spread_gain: f32,
    /// Surface gap of the joint bilateral upsampling of the inverse depth: where the sorted
    /// inverse depths of a pixel's neighbours step by more than this fraction of their
    /// weighted median, they straddle an occlusion boundary, and only the surface around the
    /// weighted median is averaged instead of blending a depth between the two (see
    /// `Neighbourhood::surface_value` in `track/upsample.rs`). 0 (the default) averages every
    /// neighbour. 0.1 sharpened the clear-water maps of tracked keyframes (+0.1 to +0.8 dB) but
    /// lost 1.7 dB on the turbid one and the coastal medium estimate (README, mapping figures).
    pub upsample_surface_gap: f32,
    /// Border term of the full-resolution variance, in depth-grid pixels: the variance is
    /// multiplied by `1 + (border_variance_px / d)^2`, `d` the distance to the image border
    /// in depth-grid pixels (see `border_variance` in `track/upsample.rs`: flow near the
    /// border is biased, which Eq. 4 cannot see). 0 disables it.
    pub border_variance_px: f32,
    /// Texture term of the full-resolution variance: each depth-grid cell's variance is
    /// multiplied by the keyframe's geometric-mean grey-level variance over the cell's own
    /// (see `texture_variance` in `track/upsample.rs`: a flat cell's depth is interpolated,
    /// not measured, which the pooled flow weights of Eq. 4 cannot see).
    pub texture_variance: bool,
    /// Multi-view consistency term of the full-resolution variance: the keyframes up to this
    /// many before and after a keyframe (in insertion order, each with a variance) give second
    /// estimates of its depth wherever they see it; the mean squared disagreement, over those
    /// neighbours and `consistency_radius_cells` around each depth-grid cell, is blended in
    /// (see `track/consistency.rs`: a bias the flow shares over a region, such as haze on the
    /// far seabed, is invisible to Eq. 4 but not to another keyframe's depth). 0 disables it;
    /// at most 8.
    pub consistency_neighbours: usize,
    /// Half-width, in depth-grid cells, of the window the disagreement is averaged over.
    /// At most 8.
    pub consistency_radius_cells: usize,
    /// Share of the disagreement in the blended variance, `var^(1 - a) * d2^a`, in [0, 1]
    /// (0: the term is off).
    pub consistency_exponent: f32,
    /// Scale Eq. 4 by the window BA's a posteriori variance of unit weight
    /// ([`BaWorkspace::unit_variance`](super::ba::BaWorkspace::unit_variance)): the flow
    /// weights are relative confidences, not inverse pixel variances, so the Hessian alone
    /// gives variances in arbitrary units (on the clear survey a median relative standard
    /// deviation of 0.70 against a median relative error of 0.013). Scaled, they are in 1/m^2
    /// and the mapper's absolute limits (seeding, the medium estimate) mean what they say.
    /// The ordering within a keyframe (and so the AUSE) does not change.
    pub variance_from_residuals: bool,
}

impl TrackerConfig {
    /// The despeckle radius for images `width` pixels wide (`None`: off).
    pub fn despeckle_radius(&self, width: usize) -> Option<usize> {
        if !self.despeckle {
            return None;
        }
        match self.despeckle_radius_px {
            0 if width >= 320 => Some(width / 160),
            0 => None,
            r => Some(r),
        }
    }
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            depth_factor: None,
            depth_min_pixels: 1200,
            flow: FlowConfig::default(),
            seed_edges: true,
            pair_edges: true,
            frame_forward_backward: true,
            ba: BaConfig::default(),
            keyframe_flow_px: 2.5,
            keyframe_min_overlap: 0.5,
            prune_flow_px: 1.0,
            init_keyframes: 8,
            init_min_keyframes: 4,
            init_rounds: 3,
            init_iterations: 15,
            init_level_start: true,
            init_level_start_rms_px: 0.05,
            init_restart_after: 3,
            new_segment_after: 3,
            turn_search_deg: 8.0,
            despeckle: true,
            despeckle_radius_px: 0,
            despeckle_min_contrast: 0.1,
            local_rounds: 1,
            local_iterations: 4,
            defer_rounds: true,
            defer_insertion: true,
            stages_per_frame: 2,
            window_free_poses: 4,
            edges_per_keyframe: 3,
            edge_max_flow_px: 20.0,
            edge_min_overlap: 0.4,
            initial_inv_depth: 0.5,
            motion_iterations: 6,
            motion_depth_variance: true,
            border_margin_px: 1.0,
            border_taper_px: 0.0,
            weight_scale: 1.0,
            confident_weight: 0.2,
            min_confident_fraction: 0.15,
            min_mean_intensity: 0.03,
            max_mean_intensity: 0.97,
            min_contrast: 0.004,
            search_candidates: 3,
            reloc_min_ncc: 0.3,
            reloc_max_flow_px: 8.0,
            loop_closure: true,
            loop_exclude_recent: 10,
            loop_candidates: 1,
            loop_min_ncc: 0.5,
            loop_max_flow_px: 6.0,
            loop_min_confident_fraction: 0.35,
            loop_screen_min_fraction: 0.1,
            loop_screen_weight: 0.05,
            loop_min_interval: 5,
            pose_graph_iterations: 20,
            loop_global_ba: true,
            global_ba_period: 0,
            global_iterations: 6,
            global_ba_lag_frames: 10,
            upsample_sigma_px: 0.8,
            upsample_sigma_intensity: 0.08,
            upsample_spread_gain: 1.0,
            upsample_surface_gap: 0.0,
            border_variance_px: 4.0,
            texture_variance: true,
            consistency_neighbours: 3,
            consistency_radius_cells: 1,
            consistency_exponent: 0.85,
            variance_from_residuals: true,
        }
    }
}

/// A tracker parameter that is out of range.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("tracker config: {field}: {problem}")]
pub struct ConfigError {
    pub field: &'static str,
    /// What the value must be (the allowed range).
    pub problem: String,
}

impl TrackerConfig {
    /// The depth factor for `width x height` input: the configured one, or the automatic choice.
    pub fn resolved_depth_factor(&self, width: usize, height: usize) -> usize {
        self.depth_factor.unwrap_or_else(|| {
            [32usize, 16, 8, 4].into_iter().find(|&f| (width / f) * (height / f) >= self.depth_min_pixels).unwrap_or(4)
        })
    }

    /// Checks the fields the tracker relies on (flow and BA are checked by their owners,
    /// [`FlowConfig::validate`] and [`BaConfig::validate`]; `Tracker::new` runs all three).
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field, problem: &str| Err(ConfigError { field, problem: problem.to_string() });
        if self.depth_factor.is_some_and(|f| !(1..=32).contains(&f)) {
            return bad("depth_factor", "must be in 1..=32");
        }
        if self.depth_min_pixels == 0 {
            return bad("depth_min_pixels", "must be at least 1");
        }
        if !(self.turn_search_deg.is_finite() && (0.0..=45.0).contains(&self.turn_search_deg)) {
            return bad("turn_search_deg", "must be in [0, 45] degrees (0: off)");
        }
        if self.despeckle_radius_px > 32 {
            return bad("despeckle_radius_px", "must be at most 32 (0: one pixel per 160 of image width)");
        }
        if self.init_min_keyframes != 0 && !(3..=self.init_keyframes).contains(&self.init_min_keyframes) {
            return bad("init_min_keyframes", "must be 0 (off) or from 3 to init_keyframes");
        }
        if self.init_keyframes < 2 {
            return bad("init_keyframes", "must be at least 2");
        }
        if self.window_free_poses == 0 {
            return bad("window_free_poses", "must be at least 1");
        }
        if self.edges_per_keyframe == 0 {
            return bad("edges_per_keyframe", "must be at least 1");
        }
        for (field, v) in [("init_rounds", self.init_rounds), ("local_rounds", self.local_rounds)] {
            if v == 0 {
                return bad(field, "must be at least 1");
            }
        }
        for (field, v) in [
            ("init_iterations", self.init_iterations),
            ("local_iterations", self.local_iterations),
            ("stages_per_frame", self.stages_per_frame),
            ("motion_iterations", self.motion_iterations),
            ("pose_graph_iterations", self.pose_graph_iterations),
            ("global_iterations", self.global_iterations),
        ] {
            if v == 0 {
                return bad(field, "must be at least 1");
            }
        }
        let positive = [
            ("keyframe_flow_px", self.keyframe_flow_px),
            ("edge_max_flow_px", self.edge_max_flow_px),
            ("initial_inv_depth", self.initial_inv_depth),
            ("weight_scale", self.weight_scale),
            ("reloc_max_flow_px", self.reloc_max_flow_px),
            ("loop_max_flow_px", self.loop_max_flow_px),
            ("upsample_sigma_px", self.upsample_sigma_px),
            ("upsample_sigma_intensity", self.upsample_sigma_intensity),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, "must be finite and positive");
            }
        }
        let unit = [
            ("prune_flow_px", self.prune_flow_px, f32::MAX),
            ("edge_min_overlap", self.edge_min_overlap, 1.0),
            ("border_margin_px", self.border_margin_px, 8.0),
            ("border_taper_px", self.border_taper_px, 16.0),
            ("keyframe_min_overlap", self.keyframe_min_overlap, 1.0),
            ("confident_weight", self.confident_weight, 1.0),
            ("min_confident_fraction", self.min_confident_fraction, 1.0),
            ("min_mean_intensity", self.min_mean_intensity, 1.0),
            ("max_mean_intensity", self.max_mean_intensity, 1.0),
            ("min_contrast", self.min_contrast, 1.0),
            ("despeckle_min_contrast", self.despeckle_min_contrast, 1.0),
            ("upsample_spread_gain", self.upsample_spread_gain, 1e6),
            ("init_level_start_rms_px", self.init_level_start_rms_px, 1e3),
            ("upsample_surface_gap", self.upsample_surface_gap, 1e3),
            ("border_variance_px", self.border_variance_px, 1e3),
            ("consistency_exponent", self.consistency_exponent, 1.0),
            ("reloc_min_ncc", self.reloc_min_ncc, 1.0),
            ("loop_min_ncc", self.loop_min_ncc, 1.0),
            ("loop_min_confident_fraction", self.loop_min_confident_fraction, 1.0),
            ("loop_screen_min_fraction", self.loop_screen_min_fraction, 1.0),
            ("loop_screen_weight", self.loop_screen_weight, 1.0),
        ];
        for (field, v, hi) in unit {
            if !(v.is_finite() && v >= 0.0 && v <= hi) {
                let range = if hi == f32::MAX { "must be finite and >= 0".to_string() } else { format!("must be in [0, {hi}], got {v}") };
                return Err(ConfigError { field, problem: range });
            }
        }
        if self.consistency_neighbours > MAX_CONSISTENCY_NEIGHBOURS {
            return bad("consistency_neighbours", "at most 8");
        }
        if self.consistency_radius_cells > 8 {
            return bad("consistency_radius_cells", "at most 8");
        }
        if self.prune_flow_px >= self.keyframe_flow_px {
            return bad("prune_flow_px", "must be below keyframe_flow_px");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn consistency_settings_out_of_range_are_refused_by_name() {
        assert!(TrackerConfig::default().validate().is_ok());
        let off = TrackerConfig { consistency_neighbours: 0, consistency_exponent: 0.0, ..TrackerConfig::default() };
        assert!(off.validate().is_ok());
        let cases = [
            (TrackerConfig { consistency_neighbours: MAX_CONSISTENCY_NEIGHBOURS + 1, ..TrackerConfig::default() }, "consistency_neighbours"),
            (TrackerConfig { consistency_radius_cells: 9, ..TrackerConfig::default() }, "consistency_radius_cells"),
            (TrackerConfig { consistency_exponent: 1.5, ..TrackerConfig::default() }, "consistency_exponent"),
            (TrackerConfig { consistency_exponent: f32::NAN, ..TrackerConfig::default() }, "consistency_exponent"),
            (TrackerConfig { consistency_exponent: -0.1, ..TrackerConfig::default() }, "consistency_exponent"),
        ];
        for (cfg, field) in cases {
            assert_eq!(cfg.validate().unwrap_err().field, field);
        }
    }

    #[test]
    fn early_initialisation_needs_3_to_init_keyframes() {
        for (n, ok) in [(0, true), (2, false), (3, true), (8, true), (9, false)] {
            let cfg = TrackerConfig { init_min_keyframes: n, ..TrackerConfig::default() };
            match cfg.validate() {
                Ok(()) => assert!(ok, "{n} accepted"),
                Err(e) => assert!(!ok && e.field == "init_min_keyframes", "{n}: {e:?}"),
            }
        }
    }
}
