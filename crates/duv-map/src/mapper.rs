//! The mapper (paper §3.2-3.3): owns the Gaussian map, the medium network, their Adam states
//! and every workspace, takes keyframes from the tracker and optimises the map against them.
//!
//! * [`Mapper::add_keyframe`] removes the Gaussians the keyframe's confident depth sees
//!   through ([`MapperConfig::carve_in_front_factor`]), stores the keyframe and back-projects
//!   new Gaussians from its inverse depth where the tracker is confident (relative standard
//!   deviation at most [`MapperConfig::init_max_rel_std`]) and the current map does not already
//!   cover the pixel (rendered alpha below [`MapperConfig::init_covered_alpha`]), on a grid of
//!   [`MapperConfig::init_stride_px`] pixels, never past the capacity. The keyframe that leaves
//!   the window at that moment seeds what is still uncovered from its less certain depth (up to
//!   [`MapperConfig::late_init_max_rel_std`]) where that hides no stored keyframe's surface.
//! * [`Mapper::iterate`] runs one optimisation step on one keyframe picked by
//!   [`schedule::pick_keyframe`](super::schedule::pick_keyframe): medium forward, render
//!   forward, [`total_loss`], render backward, medium backward, one Adam step per group; every
//!   [`MapperConfig::densify_every`] iterations [`densify_and_prune`] runs and the medium's
//!   Adam moments are reset (§3.3).
//!
//! All buffers are sized in [`Mapper::new`] from a [`MapperCapacity`] (the board's
//! `max_gaussians` and `max_keyframes`, the camera size); every keyframe must have that size.
//! Once the keyframe store is full, a random keyframe older than the window is dropped (its
//! Gaussians stay in the map).

use serde::{Deserialize, Serialize};
use std::time::Instant;

use super::adam::{AdamError, AdamGroup, AdamGroupConfig};
use super::densify::{densify_and_prune, remove_gaussians, remove_where, DensifyParams, DensifyReport, DensifyScratch, Removal};
use super::gaussians::{GaussianGrads, GaussianParam, Gaussians, ParamGroup, SH_C0};
use super::loss::{LossConfig, LossError, LossTerms, LossWorkspace, TargetView};
use super::medium_estimate::{estimate_medium, set_coefficients, Coefficients, MediumEstimate, MediumEstimateConfig, MediumEstimateError, MediumPrior};
use super::medium::{MediumConfig, MediumError, MediumNet, MediumPlanes as MediumPlanes9, MediumWorkspace, C_MED, MEDIUM_CHANNELS, SIGMA_ATT, SIGMA_BS};
use super::render::{MediumPlanes, RasterCapacity, RenderConfig, RenderError, RenderOutput, RenderStats, RenderUpstream};
use super::schedule::pick_keyframe;
use super::backend::{MapperDevice, RenderBackend};
pub use crate::loss::psnr_db;
use super::vulkan::{loss::TargetKey, DeviceMediumBackward, DeviceMediumStep, VulkanRenderError};
use duv_core::rng::Rng;
use duv_core::alloc::prefault;
use duv_core::{ImageRgb8, ImageRgbF32, Keyframe, MediumParams, PinholeCamera, PlaneF32, Se3};

/// Why the mapper refused a call. Nothing is changed by a refused call unless stated.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MapperError {
    #[error("render: {0}")]
    Render(#[from] RenderError),
    #[error("medium: {0}")]
    Medium(#[from] MediumError),
    #[error("loss: {0}")]
    Loss(#[from] LossError),
    #[error("optimiser: {0}")]
    Adam(#[from] AdamError),
    #[error("mapper config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
    #[error("keyframe {index}: {why}")]
    BadKeyframe { index: u64, why: &'static str },
    #[error("keyframe {index} is {width}x{height}, the mapper was built for {expected_width}x{expected_height}")]
    KeyframeSize { index: u64, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("no keyframe to optimise")]
    NoKeyframes,
    /// The Vulkan device failed (the message names the kernel).
    #[error("Vulkan mapper: {0}")]
    Gpu(String),
    #[error("keyframe slot {slot} out of range ({count} keyframes)")]
    NoSuchKeyframe { slot: usize, count: usize },
    #[error("{0}")]
    MediumEstimate(#[from] MediumEstimateError),
    #[error("{0}")]
    PoseRefine(#[from] super::pose_refine::PoseRefineError),
}

impl From<VulkanRenderError> for MapperError {
    fn from(e: VulkanRenderError) -> Self {
        match e {
            VulkanRenderError::Render(r) => MapperError::Render(r),
            VulkanRenderError::Gpu(g) => MapperError::Gpu(g.to_string()),
            VulkanRenderError::Loss(l) => MapperError::Loss(l),
            VulkanRenderError::Medium(crate::vulkan::medium::GpuMediumError::Medium(m)) => MapperError::Medium(m),
            VulkanRenderError::Medium(m) => MapperError::Gpu(m.to_string()),
        }
    }
}

/// Adam learning rates, one per parameter group. A config file may give any subset; the rest
/// keep [`LearningRates::default`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LearningRates {
    /// Gaussian means, metres per step.
    pub mean: f64,
    /// Log scales per step.
    pub log_scale: f64,
    /// Quaternion components per step.
    pub rotation: f64,
    /// Opacity logits per step.
    pub opacity_logit: f64,
    /// SH degree-0 coefficients per step.
    pub f_dc: f64,
    /// SH degree-1 coefficients per step.
    pub f_rest: f64,
    /// Medium network parameters per step.
    pub medium: f64,
}

impl Default for LearningRates {
    fn default() -> Self {
        LearningRates { mean: 4e-4, log_scale: 1e-2, rotation: 1e-3, opacity_logit: 2.5e-2, f_dc: 1e-2, f_rest: 5e-4, medium: 1e-3 }
    }
}

impl LearningRates {
    /// The rate of a Gaussian parameter group.
    pub fn of(&self, g: ParamGroup) -> f64 {
        match g {
            ParamGroup::Mean => self.mean,
            ParamGroup::LogScale => self.log_scale,
            ParamGroup::Rotation => self.rotation,
            ParamGroup::OpacityLogit => self.opacity_logit,
            ParamGroup::FDc => self.f_dc,
            ParamGroup::FRest => self.f_rest,
        }
    }
}

/// Parameters of the mapper. Defaults live in [`MapperConfig::default`] and nowhere else.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapperConfig {
    /// Loss weights (Eq. 12-14).
    pub loss: LossConfig,
    /// Renderer settings (depth mode must stay inverse depth: the keyframes carry inverse depth).
    pub render: RenderConfig,
    /// Medium network shape and initial water.
    pub medium: MediumConfig,
    /// Adam learning rates per parameter group.
    pub lr: LearningRates,
    /// Seed of the keyframe schedule and of the split sampling.
    pub seed: u64,
    /// Back-projection grid step, pixels (>= 1).
    pub init_stride_px: usize,
    /// Only pixels whose inverse-depth standard deviation is at most this fraction of the
    /// inverse depth seed Gaussians (0.5; on the tracked generated surveys the median keyframe
    /// pixel is near 0.03, and 90 % of the pixels pass).
    pub init_max_rel_std: f64,
    /// When a keyframe leaves the window (`window` newer ones have arrived), its pixels that
    /// `init_max_rel_std` refused and the map still does not cover seed Gaussians if their
    /// relative standard deviation is within this looser limit and the point lies in front of
    /// no stored keyframe's measured surface: surface no newer keyframe seeded, where this
    /// keyframe's uncertain depth is the best there is (on a survey, the image border the
    /// vehicle moves away from). 0 disables the late seeding.
    pub late_init_max_rel_std: f64,
    /// A new keyframe removes the Gaussians whose centre it sees this many times nearer (in
    /// inverse depth) than the surface it measured there with depth `init_max_rel_std` accepts:
    /// water it saw through, where a Gaussian can only be a floater (> 1; 0 disables).
    pub carve_in_front_factor: f64,
    /// Pixels where the current map already renders at least this alpha seed no Gaussian.
    pub init_covered_alpha: f64,
    /// When a new keyframe has more pixels to seed than the map has room for, up to this share
    /// of the Gaussian cap is freed first by evicting the least useful Gaussians
    /// ([`super::densify::Removal::LeastUseful`]), so the surface it adds is not left to
    /// densification alone, in [0, 1]; 0 seeds only into free room.
    pub init_replace_fraction: f64,
    /// Opacity of a new Gaussian, in (0, 1).
    pub init_opacity: f64,
    /// Scale of a new Gaussian as a multiple of its grid cell footprint `z stride / fx`.
    pub init_scale_factor: f64,
    /// Seed colours with the image corrected by the current medium estimate (else the raw image).
    pub init_compensate_medium: bool,
    /// Newest keyframes forming the window the schedule favours (>= 1).
    pub window: usize,
    /// Probability that an iteration picks a window keyframe rather than an older one. 0.3
    /// (0.7 before) keeps the older keyframes of a long survey from being forgotten: on the
    /// 100-frame tracked clear survey (12 keyframes, 600 iterations) SSIM 0.874 at 0.7, 0.879
    /// at 0.5, 0.881 at 0.3 (README, mapping figures).
    pub window_probability: f64,
    /// Densify/prune every this many iterations; 0 disables it.
    pub densify_every: u64,
    /// No densify/prune before this iteration.
    pub densify_start: u64,
    /// Mean attenuation-compensated screen-space gradient (pixel units) that triggers densification.
    pub densify_grad_threshold: f64,
    /// Gaussians larger than this (largest axis, m) are split rather than cloned.
    pub split_scale_m: f64,
    /// Gaussians less opaque than this are pruned.
    pub prune_min_opacity: f64,
    /// Gaussians larger than this (largest axis, m) are pruned.
    pub prune_max_scale_m: f64,
    /// Share of a full map that one densify step may replace, in [0, 1].
    pub max_replace_fraction: f64,
    /// Update the Gaussians (false: fit only the medium).
    pub optimise_gaussians: bool,
    /// Update the medium network (false: medium fixed).
    pub optimise_medium: bool,
    /// Tile intersections the raster workspace holds per Gaussian of capacity.
    pub intersections_per_gaussian: usize,
    /// Ablation (paper Table 6): one coefficient for both medium terms, `sigma_bs = sigma_att`
    /// (the network's `sigma_bs` head is unused).
    pub single_medium_coefficient: bool,
    /// When the map first holds this many keyframes, the medium is set to the closed-form
    /// estimate from their images and depths ([`super::medium_estimate`]) before the joint
    /// optimisation goes on, per colour channel whose fit is well determined; while a channel
    /// is not, the estimate is made again at twice as many keyframes (up to
    /// `max_keyframes`). 0 keeps the configured initial water. The estimate allocates its
    /// working set (samples and view pairs) each time it runs: at most 5 times with 64
    /// keyframes, never per frame.
    pub estimate_medium_at_keyframes: usize,
    /// The estimate is also made again at twice as many keyframes while that is at most this
    /// many, even once every channel is set: more views see each surface over a wider spread
    /// of ranges. A channel a later estimate accepts replaces the earlier one when one of its
    /// three coefficients moved by more than `refine_medium_estimate_min_change` (relative);
    /// otherwise the medium is left alone, since each replacement restarts the medium network
    /// and recolours the map (on the tracked turbid survey the estimate from 4 keyframes had
    /// red's attenuation 16 % low, the one from 16 within 3 %). 0 (or at most
    /// `estimate_medium_at_keyframes`) stops at the first estimate that sets every channel.
    pub refine_medium_estimate_until_keyframes: usize,
    /// See `refine_medium_estimate_until_keyframes`; >= 0.
    pub refine_medium_estimate_min_change: f64,
    /// Settings of that estimate.
    pub medium_estimate: MediumEstimateConfig,
    /// Weight of the prior that keeps the medium near the accepted estimate
    /// ([`super::medium_estimate::MediumPrior`]); 0 lets the joint optimisation move it freely.
    pub medium_prior_weight: f64,
    /// The prior's standard deviation of `ln sigma_att` and `ln sigma_bs` (relative).
    pub medium_prior_rel_std: f64,
    /// The prior's standard deviation of `c_med` (fraction of full scale).
    pub medium_prior_b_inf_std: f64,
}

impl Default for MapperConfig {
    fn default() -> Self {
        MapperConfig {
            loss: LossConfig::default(),
            render: RenderConfig::default(),
            medium: MediumConfig::default(),
            lr: LearningRates::default(),
            seed: 1,
            init_stride_px: 2,
            init_max_rel_std: 0.5,
            late_init_max_rel_std: 16.0,
            carve_in_front_factor: 1.5,
            init_covered_alpha: 0.9,
            init_replace_fraction: 0.1,
            init_opacity: 0.8,
            init_scale_factor: 0.5,
            init_compensate_medium: true,
            window: 4,
            window_probability: 0.3,
            densify_every: 50,
            densify_start: 50,
            densify_grad_threshold: 2e-4,
            split_scale_m: 0.05,
            prune_min_opacity: 0.02,
            prune_max_scale_m: 1.0,
            max_replace_fraction: 0.05,
            optimise_gaussians: true,
            optimise_medium: true,
            intersections_per_gaussian: 8,
            single_medium_coefficient: false,
            estimate_medium_at_keyframes: 4,
            refine_medium_estimate_until_keyframes: 16,
            refine_medium_estimate_min_change: 0.05,
            medium_estimate: MediumEstimateConfig::default(),
            medium_prior_weight: 0.01,
            medium_prior_rel_std: 0.1,
            medium_prior_b_inf_std: 0.02,
        }
    }
}

impl MapperConfig {
    /// Checks every field (and the nested configs); the error names the first bad one.
    pub fn validate(&self) -> Result<(), MapperError> {
        self.loss.validate()?;
        self.render.validate()?;
        self.medium.validate()?;
        self.medium_estimate.validate()?;
        let bad = |field: &'static str, value: f64, why: &'static str| Err(MapperError::InvalidConfig { field, value, why });
        for g in ParamGroup::ALL {
            AdamGroupConfig { lr: self.lr.of(g), ..AdamGroupConfig::default() }.validate()?;
        }
        AdamGroupConfig { lr: self.lr.medium, ..AdamGroupConfig::default() }.validate()?;
        if !(self.refine_medium_estimate_min_change.is_finite() && self.refine_medium_estimate_min_change >= 0.0) {
            return bad("refine_medium_estimate_min_change", self.refine_medium_estimate_min_change, "must be finite and >= 0");
        }
        if !(self.medium_prior_weight.is_finite() && self.medium_prior_weight >= 0.0) {
            return bad("medium_prior_weight", self.medium_prior_weight, "must be finite and >= 0");
        }
        for (field, v) in [("medium_prior_rel_std", self.medium_prior_rel_std), ("medium_prior_b_inf_std", self.medium_prior_b_inf_std)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, v, "must be finite and > 0");
            }
        }
        if !(self.carve_in_front_factor == 0.0 || (self.carve_in_front_factor.is_finite() && self.carve_in_front_factor > 1.0)) {
            return bad("carve_in_front_factor", self.carve_in_front_factor, "must be 0 (off) or finite and > 1");
        }
        if !(self.late_init_max_rel_std.is_finite() && self.late_init_max_rel_std >= 0.0) {
            return bad("late_init_max_rel_std", self.late_init_max_rel_std, "must be finite and >= 0");
        }
        if self.init_stride_px == 0 {
            return bad("init_stride_px", 0.0, "must be >= 1");
        }
        if self.window == 0 {
            return bad("window", 0.0, "must be >= 1");
        }
        if self.intersections_per_gaussian == 0 {
            return bad("intersections_per_gaussian", 0.0, "must be >= 1");
        }
        if !(self.init_opacity.is_finite() && self.init_opacity >= 1e-6 && self.init_opacity <= 1.0 - 1e-6) {
            return bad("init_opacity", self.init_opacity, "must be in [1e-6, 1 - 1e-6]");
        }
        for (field, v) in [
            ("window_probability", self.window_probability),
            ("max_replace_fraction", self.max_replace_fraction),
            ("init_covered_alpha", self.init_covered_alpha),
            ("init_replace_fraction", self.init_replace_fraction),
            ("prune_min_opacity", self.prune_min_opacity),
        ] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return bad(field, v, "must be in [0, 1]");
            }
        }
        for (field, v) in [
            ("init_max_rel_std", self.init_max_rel_std),
            ("init_scale_factor", self.init_scale_factor),
            ("densify_grad_threshold", self.densify_grad_threshold),
            ("split_scale_m", self.split_scale_m),
            ("prune_max_scale_m", self.prune_max_scale_m),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, v, "must be finite and > 0");
            }
        }
        Ok(())
    }
}

/// Fixed sizes of a mapper: the board's budgets and the camera size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapperCapacity {
    /// Largest Gaussian map (board `max_gaussians`).
    pub max_gaussians: usize,
    /// Keyframes kept for optimisation (board `map_keyframes`).
    pub max_keyframes: usize,
    /// Image size of every keyframe, pixels.
    pub width: usize,
    pub height: usize,
}

/// What one [`Mapper::iterate`] did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct IterationReport {
    /// Iteration number (1 for the first).
    pub iteration: u64,
    /// Index of the keyframe optimised.
    pub keyframe: u64,
    /// Loss terms before the step.
    pub loss: LossTerms,
    /// PSNR (dB) of the render against the keyframe image, before the step.
    pub psnr_db: f64,
    /// Map size after the step.
    pub gaussians: usize,
    /// Set when densify/prune ran after the step.
    pub densify: Option<DensifyReport>,
}

/// A stored keyframe with its float image and its depth target (variance 0 marks pixels
/// without depth, which the loss skips).
#[derive(Clone, Debug)]
pub(crate) struct MapKeyframe {
    pub(crate) kf: Keyframe,
    pub(crate) image: ImageRgbF32,
    pub(crate) target_variance: PlaneF32,
    /// Names this slot's target (image, depth, variance) for the device's target cache; a
    /// new one at every refill.
    pub(crate) target_key: TargetKey,
}

impl MapKeyframe {
    /// An empty slot of `width x height` pixels, every page written (resident from start-up).
    fn blank(width: usize, height: usize) -> Self {
        let camera = PinholeCamera { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0, width, height, distortion: None };
        let mut kf = Keyframe {
            index: 0,
            t_ns: duv_core::Timestamp::from_ns(0),
            image: ImageRgb8::new(width, height),
            world_from_cam: duv_core::Se3::identity(),
            camera,
            inv_depth: PlaneF32::new(width, height),
            inv_depth_variance: PlaneF32::new(width, height),
        };
        let mut image = ImageRgbF32::new(width, height);
        let mut target_variance = PlaneF32::new(width, height);
        prefault(&mut kf.image.data);
        prefault(&mut kf.inv_depth.data);
        prefault(&mut kf.inv_depth_variance.data);
        prefault(&mut image.data);
        prefault(&mut target_variance.data);
        MapKeyframe { kf, image, target_variance, target_key: TargetKey::fresh() }
    }

    /// Copies `kf` into this slot (same size: [`Mapper::add_keyframe`] checks it) with its
    /// float image and depth target; allocates nothing.
    fn refill(&mut self, kf: &Keyframe) {
        self.target_key = TargetKey::fresh();
        let k = &mut self.kf;
        k.index = kf.index;
        k.t_ns = kf.t_ns;
        k.world_from_cam = kf.world_from_cam;
        k.camera = kf.camera;
        k.image.data.copy_from_slice(&kf.image.data);
        k.inv_depth.data.copy_from_slice(&kf.inv_depth.data);
        k.inv_depth_variance.data.copy_from_slice(&kf.inv_depth_variance.data);
        for (o, &v) in self.image.data.iter_mut().zip(&kf.image.data) {
            *o = v as f32 / 255.0;
        }
        for ((t, &v), &d) in self.target_variance.data.iter_mut().zip(&kf.inv_depth_variance.data).zip(&kf.inv_depth.data) {
            *t = if d > 0.0 && d.is_finite() && v.is_finite() { v } else { 0.0 };
        }
    }
}

/// Per-view buffers, sized once.
#[derive(Clone, Debug)]
struct ViewBuffers {
    out: RenderOutput,
    upstream: RenderUpstream,
    planes9: MediumPlanes9,
    planes: MediumPlanes,
    planes_grad: MediumPlanes,
    d_planes9: MediumPlanes9,
    /// The loss's own dL/dmedium (the medium prior).
    d_medium_loss: MediumPlanes9,
}

/// Copies the medium network's 9-channel planes into the renderer's three RGB planes.
pub fn planes_from_nine(nine: &MediumPlanes9, out: &mut MediumPlanes) {
    for (((px, c), a), b) in nine
        .data
        .chunks_exact(MEDIUM_CHANNELS)
        .zip(out.c_med.data.chunks_exact_mut(3))
        .zip(out.sigma_att.data.chunks_exact_mut(3))
        .zip(out.sigma_bs.data.chunks_exact_mut(3))
    {
        c.copy_from_slice(&px[C_MED..C_MED + 3]);
        a.copy_from_slice(&px[SIGMA_ATT..SIGMA_ATT + 3]);
        b.copy_from_slice(&px[SIGMA_BS..SIGMA_BS + 3]);
    }
}

/// Copies the renderer's three RGB planes into the medium network's 9-channel layout.
pub fn nine_from_planes(planes: &MediumPlanes, out: &mut MediumPlanes9) {
    for (((px, c), a), b) in out
        .data
        .chunks_exact_mut(MEDIUM_CHANNELS)
        .zip(planes.c_med.data.chunks_exact(3))
        .zip(planes.sigma_att.data.chunks_exact(3))
        .zip(planes.sigma_bs.data.chunks_exact(3))
    {
        px[C_MED..C_MED + 3].copy_from_slice(c);
        px[SIGMA_ATT..SIGMA_ATT + 3].copy_from_slice(a);
        px[SIGMA_BS..SIGMA_BS + 3].copy_from_slice(b);
    }
}

/// The mapping stage: map, medium, optimiser state and keyframes.
pub struct Mapper {
    pub(crate) config: MapperConfig,
    pub(crate) capacity: MapperCapacity,
    pub(crate) gaussians: Gaussians,
    pub(crate) grads: GaussianGrads,
    /// One group per [`ParamGroup::ALL`] entry.
    pub(crate) adam: Vec<AdamGroup>,
    pub(crate) medium: MediumNet,
    pub(crate) medium_adam: AdamGroup,
    medium_grads: Vec<f32>,
    medium_ws: MediumWorkspace,
    raster: RenderBackend,
    /// `step_on_then` tells the renderer the next step's keyframe ([`Mapper::set_plan_ahead`]).
    plan_ahead: bool,
    raster_capacity: RasterCapacity,
    loss_ws: LossWorkspace,
    view: ViewBuffers,
    densify_scratch: DensifyScratch,
    pub(crate) keyframes: Vec<MapKeyframe>,
    /// Free keyframe slots: with `keyframes`, `max_keyframes` slots allocated (and written)
    /// at start-up, so the resident set does not grow as the keyframe history fills.
    spare_keyframes: Vec<MapKeyframe>,
    pub(crate) iteration: u64,
    pub(crate) rng: Rng,
    overflow: OverflowStats,
    /// The last render used over 90% of the intersection buffer.
    intersections_tight: bool,
    /// The newest closed-form medium estimate (some of its channels set the medium).
    medium_estimate: Option<MediumEstimate>,
    /// The prior on the coefficients the estimates so far determined.
    pub(crate) medium_prior: Option<MediumPrior>,
    /// Keyframe count of the next medium estimate; 0 once every channel is set (or off).
    pub(crate) medium_estimate_at: usize,
    /// Where the wall time went ([`Mapper::times`]).
    times: MapperTimes,
}

/// Renders that needed more tile intersections than the buffers hold, and what the policy did
/// ([`Mapper::forward_within_capacity`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct OverflowStats {
    /// Renders that overflowed (each followed by a prune and a new render).
    pub events: u64,
    /// Gaussians pruned by the policy.
    pub pruned: u64,
    /// Densification steps skipped because the intersection buffer was over 90% full.
    pub densify_skipped: u64,
    /// The largest number of intersections a view asked for, and the buffer's size.
    pub largest_needed: u64,
    pub capacity: usize,
}

/// Where a mapper's wall time went since it was made (or restored): seconds and counts of each
/// part, measured on the thread that calls it. The parts nest as their docs say; `duv run`
/// reports them to show where mapping inside a run spends what an optimisation step alone
/// (the `gpu_render` bench) does not.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MapperTimes {
    /// Optimisation steps ([`Mapper::step_on_then`]), densification excluded, uploads included.
    pub steps: u64,
    pub step_s: f64,
    /// Whole-map uploads to the device before a step (after the host changed the map: a new
    /// keyframe, densification, a restore); inside `step_s`.
    pub uploads: u64,
    pub upload_s: f64,
    /// Densify/prune runs, the map's read-back included.
    pub densify: u64,
    pub densify_s: f64,
    /// [`Mapper::add_keyframe`] calls, whole (read-back, carving, seeding renders, medium
    /// estimate).
    pub keyframes: u64,
    pub keyframe_s: f64,
    /// Closed-form medium estimates; inside `keyframe_s`.
    pub medium_estimates: u64,
    pub medium_estimate_s: f64,
    /// Reads of the device map to the host (before the host changes it, a checkpoint, an
    /// export); inside the parts that asked for them. Nothing on the CPU reference.
    pub read_backs: u64,
    pub read_back_s: f64,
}

impl MapperTimes {
    /// Milliseconds per step, uploads excluded: the figure the step bench measures.
    pub fn step_ms_without_uploads(&self) -> f64 {
        (self.step_s - self.upload_s) * 1e3 / self.steps.max(1) as f64
    }

    /// One line: each part's seconds and count.
    pub fn summary(&self) -> String {
        format!(
            "steps {:.2} s ({}, {:.2} ms each without uploads; {} whole-map uploads {:.2} s), densify {:.2} s ({}), keyframes added {:.2} s ({}; medium estimates {:.2} s), map read back {:.2} s ({})",
            self.step_s,
            self.steps,
            self.step_ms_without_uploads(),
            self.uploads,
            self.upload_s,
            self.densify_s,
            self.densify,
            self.keyframe_s,
            self.keyframes,
            self.medium_estimate_s,
            self.read_back_s,
            self.read_backs
        )
    }
}

/// Renders of one view after an overflow before the mapper reports the overflow as an error.
pub const OVERFLOW_RETRIES: usize = 8;

impl Mapper {
    /// An empty map with every buffer allocated for `capacity`.
    pub fn new(config: MapperConfig, capacity: MapperCapacity) -> Result<Self, MapperError> {
        config.validate()?;
        let (w, h) = (capacity.width, capacity.height);
        if w == 0 || h == 0 || capacity.max_gaussians == 0 || capacity.max_keyframes == 0 {
            return Err(MapperError::InvalidConfig { field: "capacity", value: 0.0, why: "sizes must be > 0" });
        }
        let cap = capacity.max_gaussians;
        let adam = ParamGroup::ALL
            .iter()
            .map(|&g| AdamGroup::new(AdamGroupConfig { lr: config.lr.of(g), ..AdamGroupConfig::default() }, g.width(), 0, cap))
            .collect::<Result<Vec<_>, _>>()?;
        let medium = MediumNet::new(&config.medium)?;
        let medium_adam = AdamGroup::new(AdamGroupConfig { lr: config.lr.medium, ..AdamGroupConfig::default() }, 1, medium.param_count(), medium.param_count())?;
        let raster_capacity = RasterCapacity {
            width: w,
            height: h,
            max_gaussians: cap,
            max_intersections: cap.saturating_mul(config.intersections_per_gaussian).max(1024),
        };
        let raster = RenderBackend::cpu(raster_capacity, "the default until Mapper::use_device")?;
        Ok(Mapper {
            medium_grads: vec![0.0; medium.param_count()],
            medium_ws: MediumWorkspace::with_grid(&medium, w, h, config.medium.grid_step_px),
            loss_ws: LossWorkspace::new(w, h),
            view: ViewBuffers {
                out: RenderOutput::new(w, h),
                upstream: RenderUpstream::new(w, h),
                planes9: MediumPlanes9::new(w, h),
                planes: MediumPlanes::new(w, h),
                planes_grad: MediumPlanes::new(w, h),
                d_planes9: MediumPlanes9::new(w, h),
                d_medium_loss: MediumPlanes9::new(w, h),
            },
            densify_scratch: DensifyScratch::with_capacity(cap),
            gaussians: Gaussians::with_capacity(cap),
            grads: GaussianGrads::with_capacity(cap),
            keyframes: Vec::with_capacity(capacity.max_keyframes),
            spare_keyframes: (0..capacity.max_keyframes).map(|_| MapKeyframe::blank(w, h)).collect(),
            iteration: 0,
            rng: Rng::new(config.seed),
            overflow: OverflowStats::default(),
            intersections_tight: false,
            medium_estimate: None,
            medium_prior: None,
            medium_estimate_at: config.estimate_medium_at_keyframes,
            adam,
            medium,
            medium_adam,
            raster,
            plan_ahead: true,
            raster_capacity,
            config,
            capacity,
            times: MapperTimes::default(),
        })
    }

    /// Renders from now on with `device` (the map and every optimiser state stay as they are);
    /// `gpu` sizes the GPU arena (the board's `budgets.gpu_mb`) and names the device. Returns
    /// [`Self::render_device`]. On an error the mapper renders with the CPU reference (a
    /// Vulkan renderer in use is released before the new one is opened).
    pub fn use_device(&mut self, device: MapperDevice, gpu: &duv_gpu::GpuOptions) -> Result<String, MapperError> {
        self.release_device_map()?;
        if self.raster.is_vulkan() {
            // Its GPU memory goes before the new renderer's arena is allocated.
            self.raster = RenderBackend::cpu(self.raster_capacity, "a Vulkan renderer was released")?;
        }
        self.raster = RenderBackend::open(device, gpu, self.raster_capacity)?;
        // The medium network on the device too when it is evaluated on a direction grid (per
        // pixel, its node records would take hundreds of MB: the host evaluates it then).
        if let Some(grid) = self.medium_ws.grid() {
            self.raster.enable_device_medium(grid.step, self.medium.layout())?;
        }
        // Last of the fixed buffers: every held keyframe's target on the device, as many as
        // fit in half the arena left, so a step on a keyframe seen before uploads nothing.
        let slots = self.raster.reserve_target_slots(self.capacity.max_keyframes)?;
        let what = self.render_device();
        tracing::info!(target_slots = slots, "map.device_targets");
        tracing::info!(renderer = %what, "map.device");
        Ok(what)
    }

    /// The renderer in use, one line: `Vulkan on <device>` or `CPU reference (<why>)`.
    pub fn render_device(&self) -> String {
        self.raster.describe()
    }

    /// Whether the Vulkan kernels render this map.
    pub fn renders_on_vulkan(&self) -> bool {
        self.raster.is_vulkan()
    }

    /// The open Vulkan device of the renderer (kernel timings, GPU memory), if any.
    pub fn gpu(&self) -> Option<&duv_gpu::GpuContext> {
        self.raster.gpu()
    }

    /// The Vulkan renderer's kernels and device, to switch between kernel variants (the
    /// CPU-device ones on a GPU and back) and device settings: benchmarks, tests; `None` on the
    /// CPU reference.
    pub fn gpu_renderer_mut(&mut self) -> Option<(&mut crate::vulkan::GpuRenderer, &mut duv_gpu::GpuContext)> {
        self.raster.renderer_mut()
    }

    /// Per-kernel timestamp queries on the Vulkan renderer on (the default) or off, so that a
    /// timed loop does not pay for them ([`duv_gpu::GpuContext::set_timestamps`]); returns
    /// whether there are timestamps to take.
    pub fn set_gpu_timestamps(&mut self, on: bool) -> bool {
        self.raster.set_gpu_timestamps(on)
    }

    /// On the Vulkan renderer the optimiser's map lives on the device between densification
    /// steps and nothing of it is read back after a step: the parameters ([`Mapper::gaussians`]),
    /// the Adam moments and the densification statistics come to the host here (and at every
    /// densify/prune, new keyframe and checkpoint). Call it before reading
    /// [`Mapper::gaussians`]' values, [`Mapper::adam_group`] or the statistics; nothing to do
    /// on the CPU reference.
    pub fn sync_from_device(&mut self) -> Result<(), MapperError> {
        let t0 = Instant::now();
        let read = self.raster.sync(&mut self.gaussians, &mut self.grads, &mut self.adam)?;
        self.count_read_back(read, t0);
        Ok(())
    }

    fn count_read_back(&mut self, read: bool, t0: Instant) {
        if read {
            self.times.read_backs += 1;
            self.times.read_back_s += t0.elapsed().as_secs_f64();
        }
    }

    /// Where the mapper's wall time went so far ([`MapperTimes`]).
    pub fn times(&self) -> &MapperTimes {
        &self.times
    }

    /// Synced, and the host copy is the map again: before the host changes the map.
    fn release_device_map(&mut self) -> Result<(), MapperError> {
        let t0 = Instant::now();
        let read = self.raster.release(&mut self.gaussians, &mut self.grads, &mut self.adam)?;
        self.count_read_back(read, t0);
        Ok(())
    }

    /// Whether [`Mapper::gaussians`]' values are behind the device map's (optimisation steps on
    /// Vulkan since the last [`Mapper::sync_from_device`]); the count is always current.
    pub fn host_map_stale(&self) -> bool {
        self.raster.host_params_stale()
    }

    pub fn config(&self) -> &MapperConfig {
        &self.config
    }
    pub fn capacity(&self) -> MapperCapacity {
        self.capacity
    }
    /// The map as the host has it: on Vulkan, as of the last [`Mapper::sync_from_device`] (or
    /// host change of the map), see [`Mapper::host_map_stale`]; its `len()` is always current.
    pub fn gaussians(&self) -> &Gaussians {
        &self.gaussians
    }
    pub fn medium(&self) -> &MediumNet {
        &self.medium
    }
    /// Iterations run so far.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }
    /// Adam state of a Gaussian group (aligned with the map).
    /// The Adam state of group `g` (on Vulkan, as of the last [`Mapper::sync_from_device`]).
    pub fn adam_group(&self, g: ParamGroup) -> &AdamGroup {
        &self.adam[g as usize]
    }
    pub fn medium_adam(&self) -> &AdamGroup {
        &self.medium_adam
    }
    pub fn keyframe_count(&self) -> usize {
        self.keyframes.len()
    }
    /// The stored keyframe in slot `slot` (oldest first).
    pub fn keyframe(&self, slot: usize) -> Option<&Keyframe> {
        self.keyframes.get(slot).map(|k| &k.kf)
    }
    /// The medium along the optical axis of `world_from_cam` (`medium.json`).
    pub fn medium_summary(&self, world_from_cam: &Se3) -> MediumParams {
        let mut m = self.medium.summary_along_axis(world_from_cam);
        if self.config.single_medium_coefficient {
            m.beta_b = m.beta_d;
        }
        m
    }

    /// The medium network's planes for a view, with the single-coefficient tie applied.
    fn medium_forward(&mut self, camera: &PinholeCamera, world_from_cam: &Se3) -> Result<(), MapperError> {
        self.medium_ws.forward(&self.medium, camera, world_from_cam, &mut self.view.planes9)?;
        if self.config.single_medium_coefficient {
            for px in self.view.planes9.data.chunks_exact_mut(MEDIUM_CHANNELS) {
                for c in 0..3 {
                    px[SIGMA_BS + c] = px[SIGMA_ATT + c];
                }
            }
        }
        planes_from_nine(&self.view.planes9, &mut self.view.planes);
        Ok(())
    }

    /// Replaces the pose of the stored keyframe with index `index` (a correction from
    /// tracking); `Ok(false)` when no stored keyframe has that index.
    pub fn set_keyframe_pose(&mut self, index: u64, world_from_cam: Se3) -> Result<bool, MapperError> {
        if !world_from_cam.to_homogeneous().iter().all(|v| v.is_finite()) {
            return Err(MapperError::BadKeyframe { index, why: "pose is not finite" });
        }
        match self.keyframes.iter_mut().find(|k| k.kf.index == index) {
            Some(k) => {
                k.kf.world_from_cam = world_from_cam;
                Ok(true)
            }
            None => Ok(false),
        }
    }

    /// Photometric refinement of keyframe `slot`'s pose against the map rendered from it
    /// ([`super::pose_refine`]); the pose is replaced when the correction is accepted. A
    /// keyframe the map does not cover well enough is an error (`PoseRefine`), its pose kept.
    /// `input_pose` is the pose the refinement's prior holds it near (the tracker's).
    pub fn refine_keyframe_pose(&mut self, slot: usize, input_pose: &Se3, cfg: &super::pose_refine::PoseRefineConfig) -> Result<super::pose_refine::PoseCorrection, MapperError> {
        let _span = tracing::debug_span!("map.refine_pose", slot).entered();
        let (index, pose) = match self.keyframes.get(slot) {
            Some(k) => (k.kf.index, k.kf.world_from_cam),
            None => return Err(MapperError::NoSuchKeyframe { slot, count: self.keyframes.len() }),
        };
        self.render_keyframe(slot)?;
        let k = &self.keyframes[slot].kf;
        let out = &self.view.out;
        let c = super::pose_refine::align_to_render(&pose.inv_mul(input_pose), &k.image, &out.colour, &out.depth, &out.depth_var, &out.alpha, &k.camera, cfg)?;
        if c.accepted {
            self.set_keyframe_pose(index, c.apply(&pose))?;
        }
        Ok(c)
    }

    /// Replaces the map (e.g. a fixed test scene); Adam moments restart at zero.
    pub fn set_gaussians(&mut self, gaussians: &Gaussians) -> Result<(), MapperError> {
        if gaussians.len() > self.capacity.max_gaussians {
            return Err(RenderError::GaussianCapacity { capacity: self.capacity.max_gaussians }.into());
        }
        self.raster.drop_resident();
        self.gaussians.clear();
        for i in 0..gaussians.len() {
            self.gaussians.push(&gaussians.get(i))?;
        }
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            let cfg = *self.adam[k].config();
            self.adam[k] = AdamGroup::new(cfg, g.width(), self.gaussians.len(), self.capacity.max_gaussians)?;
        }
        self.grads.reset(self.gaussians.len())?;
        for i in 0..self.gaussians.len() {
            self.grads.set_footprint(i, 0.0);
        }
        Ok(())
    }

    /// Renders the map and medium from a pose; the result is valid until the next call.
    pub fn render(&mut self, camera: &PinholeCamera, world_from_cam: &Se3) -> Result<&RenderOutput, MapperError> {
        self.check_camera(u64::MAX, camera)?;
        self.medium_forward(camera, world_from_cam)?;
        self.forward_within_capacity(camera, world_from_cam, true, false, false)?;
        Ok(&self.view.out)
    }

    /// The output of the last [`Mapper::render`] (or keyframe render).
    pub fn last_render(&self) -> &RenderOutput {
        &self.view.out
    }

    /// The medium field's per-pixel parameters of the last [`Mapper::render`] (or keyframe
    /// render), for [`crate::restore::restore_captured`].
    pub fn view_medium(&self) -> &MediumPlanes {
        &self.view.planes
    }

    /// The water-free view of `captured`, seen from the pose of the last [`Mapper::render`]
    /// (or keyframe render), with that render's range and medium
    /// ([`crate::restore::restore_captured`]), into `dst`.
    pub fn restore_last(&self, captured: &ImageRgbF32, camera: &PinholeCamera, cfg: &crate::restore::RestoreConfig, dst: &mut ImageRgbF32) -> Result<crate::restore::RestoreStats, crate::restore::RestoreError> {
        crate::restore::restore_captured(captured, &self.view.out, &self.view.planes, camera, self.config.render.depth_mode, cfg, dst)
    }

    /// Renders keyframe `slot` (oldest first).
    pub fn render_keyframe(&mut self, slot: usize) -> Result<&RenderOutput, MapperError> {
        let (camera, pose) = match self.keyframes.get(slot) {
            Some(k) => (k.kf.camera, k.kf.world_from_cam),
            None => return Err(MapperError::NoSuchKeyframe { slot, count: self.keyframes.len() }),
        };
        self.render(&camera, &pose)
    }

    fn check_camera(&self, index: u64, camera: &PinholeCamera) -> Result<(), MapperError> {
        if camera.width != self.capacity.width || camera.height != self.capacity.height {
            return Err(MapperError::KeyframeSize {
                index,
                width: camera.width,
                height: camera.height,
                expected_width: self.capacity.width,
                expected_height: self.capacity.height,
            });
        }
        if camera.distortion.is_some() {
            return Err(MapperError::BadKeyframe { index, why: "the camera must be undistorted" });
        }
        Ok(())
    }

    /// Stores the keyframe and seeds Gaussians from its confident inverse depth where the map
    /// does not cover it yet; returns how many Gaussians were added.
    pub fn add_keyframe(&mut self, kf: impl std::borrow::Borrow<Keyframe>) -> Result<usize, MapperError> {
        let t0 = Instant::now();
        let added = self.add_keyframe_untimed(kf.borrow());
        self.times.keyframes += 1;
        self.times.keyframe_s += t0.elapsed().as_secs_f64();
        added
    }

    fn add_keyframe_untimed(&mut self, kf: &Keyframe) -> Result<usize, MapperError> {
        self.check_camera(kf.index, &kf.camera)?;
        if !kf.is_consistent() {
            return Err(MapperError::BadKeyframe { index: kf.index, why: "image, inverse depth and variance sizes differ from the camera's" });
        }
        if !kf.world_from_cam.to_homogeneous().iter().all(|v| v.is_finite()) {
            return Err(MapperError::BadKeyframe { index: kf.index, why: "pose is not finite" });
        }
        self.release_device_map()?;
        let carved = self.carve_in_front(kf)?;
        let (mut added, evicted) = self.seed_from(kf, SeedPass::Confident)?;
        let (w, h) = (kf.camera.width, kf.camera.height);
        let slot = if self.keyframes.len() == self.capacity.max_keyframes {
            let older = self.keyframes.len().saturating_sub(self.config.window);
            let slot = if older > 0 { self.rng.below(older as u64) as usize } else { 0 };
            self.keyframes.remove(slot)
        } else {
            self.spare_keyframes.pop().unwrap_or_else(|| MapKeyframe::blank(w, h))
        };
        self.store_keyframe(slot, kf);
        let estimate_at = self.medium_estimate_at.min(self.capacity.max_keyframes);
        if estimate_at > 0 && self.config.optimise_medium && self.keyframes.len() == estimate_at {
            let t_estimate = Instant::now();
            let estimated = self.estimate_medium();
            self.times.medium_estimates += 1;
            self.times.medium_estimate_s += t_estimate.elapsed().as_secs_f64();
            let all = match estimated {
                Ok(e) => {
                    tracing::info!(beta_d = ?e.medium.beta_d, beta_b = ?e.medium.beta_b, b_inf = ?e.medium.b_inf, determined = ?e.determined.map(|d| d.bits()), std_error = ?e.std_error, samples = e.samples, pairs = ?e.attenuation_pairs, "map.medium_estimate");
                    e.accepted.iter().all(|&a| a)
                }
                Err(e) => {
                    tracing::warn!(error = %e, "map.medium_estimate: the medium stays as it is");
                    false
                }
            };
            let next = estimate_at * 2;
            let again = !all || next <= self.config.refine_medium_estimate_until_keyframes;
            self.medium_estimate_at = if !again || estimate_at == self.capacity.max_keyframes { 0 } else { next };
        }
        // The keyframe that just left the window: what the map still does not cover there, no
        // newer keyframe has seeded, so its less certain depth is the best there is.
        let mut late = 0;
        let late_limit = self.config.late_init_max_rel_std;
        if late_limit > 0.0 && self.keyframes.len() > self.config.window {
            let i = self.keyframes.len() - 1 - self.config.window;
            let left = self.keyframes.remove(i);
            let seeded = self.seed_from(&left.kf, SeedPass::Late);
            self.keyframes.insert(i, left);
            late = seeded?.0;
            added += late;
        }
        tracing::debug!(added, late, evicted, carved, total = self.gaussians.len(), "map.add_keyframe");
        Ok(added)
    }

    /// Removes the Gaussians `kf` sees through ([`MapperConfig::carve_in_front_factor`]);
    /// returns how many went.
    fn carve_in_front(&mut self, kf: &Keyframe) -> Result<usize, MapperError> {
        let factor = self.config.carve_in_front_factor;
        if factor <= 0.0 || self.gaussians.is_empty() {
            return Ok(0);
        }
        let max_rel_std = self.config.init_max_rel_std;
        let carved = remove_where(&mut self.gaussians, &mut self.grads, &mut self.adam, &mut self.densify_scratch, |m| {
            let Some((i, p_inv_depth)) = pixel_of(kf, &nalgebra::Point3::new(m[0] as f64, m[1] as f64, m[2] as f64)) else {
                return false;
            };
            let (d, var) = (kf.inv_depth.data[i] as f64, kf.inv_depth_variance.data[i] as f64);
            d > 0.0 && d.is_finite() && var.is_finite() && var >= 0.0 && var.sqrt() <= max_rel_std * d && p_inv_depth > factor * d
        })?;
        Ok(carved)
    }

    /// Seeds Gaussians from `kf`'s inverse depth on the `init_stride_px` grid at the pixels
    /// `pass` takes ([`seed_point`]; the map's coverage is rendered from `kf`'s pose first);
    /// when more pixels qualify than the map has room for, first evicts up to
    /// `init_replace_fraction` of the cap. With [`SeedPass::Late`], `kf` must not be among the
    /// stored keyframes (those are the views whose measured surface its seeds must not hide).
    /// Returns (added, evicted).
    fn seed_from(&mut self, kf: &Keyframe, pass: SeedPass) -> Result<(usize, usize), MapperError> {
        // Current coverage and medium at this pose.
        self.render(&kf.camera, &kf.world_from_cam)?;
        let cfg = &self.config;
        let cam = kf.camera;
        let (w, h) = (cam.width, cam.height);
        let stride = cfg.init_stride_px;
        let opacity_logit = (cfg.init_opacity / (1.0 - cfg.init_opacity)).ln() as f32;
        let alpha = &self.view.out.alpha.data;
        let others = &self.keyframes;
        let wanted = (stride / 2..h).step_by(stride).map(|y| (stride / 2..w).step_by(stride).filter(|&x| seed_point(kf, alpha, cfg, pass, others, x, y).is_some()).count()).sum::<usize>();
        let room = self.gaussians.capacity() - self.gaussians.len();
        let mut evicted = 0;
        if wanted > room {
            let budget = (cfg.init_replace_fraction * self.gaussians.capacity() as f64) as usize;
            evicted = remove_gaussians(&mut self.gaussians, &mut self.grads, &mut self.adam, (wanted - room).min(budget), Removal::LeastUseful, &mut self.densify_scratch)?;
        }
        // Coverage stays the render's from before the eviction (not rendered again: the evicted
        // Gaussians are the least useful of the map, so the alpha changes little).
        let (cfg, alpha, others) = (&self.config, &self.view.out.alpha.data, &self.keyframes);
        let before = self.gaussians.len();
        'rows: for y in (stride / 2..h).step_by(stride) {
            for x in (stride / 2..w).step_by(stride) {
                let i = y * w + x;
                let Some((p_in_cam, p_in_world)) = seed_point(kf, alpha, cfg, pass, others, x, y) else {
                    continue;
                };
                if self.gaussians.len() == self.gaussians.capacity() {
                    break 'rows;
                }
                let z = p_in_cam.z;
                let range = p_in_cam.coords.norm() as f32;
                let log_scale = ((z * stride as f64 / cam.fx) * cfg.init_scale_factor).ln() as f32;
                let mut f_dc = [0.0f32; 3];
                for c in 0..3 {
                    let observed = kf.image.data[i * 3 + c] as f32 / 255.0;
                    let colour = if cfg.init_compensate_medium {
                        let px = &self.view.planes9.data[i * MEDIUM_CHANNELS..(i + 1) * MEDIUM_CHANNELS];
                        let backscatter = px[C_MED + c] * (1.0 - (-px[SIGMA_BS + c] * range).exp());
                        ((observed - backscatter) * (px[SIGMA_ATT + c] * range).exp()).clamp(0.0, 1.0)
                    } else {
                        observed
                    };
                    f_dc[c] = ((colour - 0.5) as f64 / SH_C0) as f32;
                }
                let p = GaussianParam {
                    mean: [p_in_world.x as f32, p_in_world.y as f32, p_in_world.z as f32],
                    log_scale: [log_scale; 3],
                    rotation: [1.0, 0.0, 0.0, 0.0],
                    opacity_logit,
                    f_dc,
                    f_rest: [0.0; 9],
                };
                // Until a view measures it, a seed counts as covering its own grid cell.
                self.grads.set_footprint(self.gaussians.len(), (stride * stride) as f32);
                self.gaussians.push(&p)?;
            }
        }
        let added = self.gaussians.len() - before;
        self.grads.fold_footprint();
        for group in self.adam.iter_mut() {
            group.grow(added)?;
        }
        self.grads.reset(self.gaussians.len())?;
        Ok((added, evicted))
    }

    /// The prior that holds the coefficients the estimates determined, once one did.
    pub fn medium_prior(&self) -> Option<&MediumPrior> {
        self.medium_prior.as_ref()
    }

    /// The newest closed-form medium estimate, if one was made; its `determined` coefficients set the medium.
    pub fn medium_estimate(&self) -> Option<&MediumEstimate> {
        self.medium_estimate.as_ref()
    }

    /// Estimates the water from the held keyframes ([`super::medium_estimate`]), sets the
    /// medium network to it (uniform in direction, as a fresh network; moments reset) and
    /// re-derives every Gaussian's base colour for the new water. Per channel, the
    /// coefficients the estimate determined are taken ([`MediumEstimate::determined`]) and
    /// held by the prior; the others keep the current medium along the first keyframe's axis.
    /// A channel an earlier estimate set changes only when this one determines at least the
    /// coefficients held so far and determines more or moved one of them by more than
    /// `refine_medium_estimate_min_change`. When nothing is taken, or on an error, the medium
    /// and map are unchanged (the estimate is still kept as [`Self::medium_estimate`]).
    pub fn estimate_medium(&mut self) -> Result<MediumEstimate, MapperError> {
        let _span = tracing::info_span!("map.medium_estimate", keyframes = self.keyframes.len()).entered();
        self.release_device_map()?;
        let keyframes: Vec<&Keyframe> = self.keyframes.iter().map(|k| &k.kf).collect();
        let first = keyframes.first().ok_or(MapperError::NoKeyframes)?.world_from_cam;
        let before = self.medium.summary_along_axis(&first);
        let estimate = estimate_medium(&keyframes, before.beta_d, &self.config.medium_estimate)?;
        self.medium_estimate = Some(estimate.clone());
        // A channel the medium already takes from an earlier estimate changes only when the
        // new one determines at least the coefficients held so far and either determines
        // more or moved one by more than the configured share.
        let min_change = self.config.refine_medium_estimate_min_change;
        let adopt: [Coefficients; 3] = std::array::from_fn(|c| {
            let new = estimate.determined[c];
            let held = self.medium_prior.as_ref().map_or(Coefficients::NONE, |p| p.held[c]);
            if !new.any() || !new.contains(held) {
                return Coefficients::NONE;
            }
            let Some(p) = self.medium_prior.as_ref().filter(|_| held.any() && new == held) else {
                return new;
            };
            let (a, b) = (&p.medium, &estimate.medium);
            let moved = |x: f64, y: f64| (y - x).abs() > min_change * x.abs();
            if (new.beta_d && moved(a.beta_d[c], b.beta_d[c])) || (new.beta_b && moved(a.beta_b[c], b.beta_b[c])) || (new.b_inf && moved(a.b_inf[c], b.b_inf[c])) {
                new
            } else {
                Coefficients::NONE
            }
        });
        if !adopt.iter().any(|a| a.any()) {
            return Ok(estimate);
        }
        let mut water = before;
        set_coefficients(&mut water, &estimate.medium, adopt);
        let mut medium = self.config.medium;
        for c in 0..3 {
            medium.init_c_med[c] = water.b_inf[c].clamp(1e-3, 0.999);
            medium.init_sigma_att[c] = water.beta_d[c].clamp(1e-3, 20.0);
            medium.init_sigma_bs[c] = water.beta_b[c].clamp(1e-3, 20.0);
        }
        let old = std::mem::replace(&mut self.medium, MediumNet::new(&medium)?);
        let mut prior = self.medium_prior.unwrap_or(MediumPrior {
            medium: water,
            held: [Coefficients::NONE; 3],
            weight: self.config.medium_prior_weight,
            rel_std: self.config.medium_prior_rel_std,
            b_inf_std: self.config.medium_prior_b_inf_std,
        });
        set_coefficients(&mut prior.medium, &water, adopt);
        for (c, a) in adopt.iter().enumerate().filter(|(_, a)| a.any()) {
            prior.held[c] = *a;
        }
        self.medium_prior = Some(prior);
        self.medium_adam.reset_moments();
        self.recolour_for_new_medium(&old);
        Ok(estimate)
    }

    /// Keeps what every Gaussian looked like from the keyframe that seeded it (the oldest held
    /// keyframe that sees it) when the medium changes from `old` to the current one:
    /// `J' = (J T + B - B') / T'`, `T = exp(-sigma_att r)`, `B = c_med (1 - exp(-sigma_bs r))`.
    fn recolour_for_new_medium(&mut self, old: &MediumNet) {
        let views: Vec<(Se3, PinholeCamera)> = self.keyframes.iter().map(|k| (k.kf.world_from_cam.inverse(), k.kf.camera)).collect();
        for i in 0..self.gaussians.len() {
            let mut p = self.gaussians.get(i);
            let mean = nalgebra::Point3::new(p.mean[0] as f64, p.mean[1] as f64, p.mean[2] as f64);
            let seen = views.iter().find_map(|(cam_from_world, cam)| {
                let q = cam_from_world * mean;
                let (u, v) = (cam.fx * q.x / q.z + cam.cx, cam.fy * q.y / q.z + cam.cy);
                (q.z > 0.0 && u >= 0.0 && v >= 0.0 && u < cam.width as f64 && v < cam.height as f64).then_some((cam_from_world, q))
            });
            let Some((cam_from_world, q)) = seen else { continue };
            let range = q.coords.norm();
            let dir = cam_from_world.rotation.inverse() * (q.coords / range);
            let dir = [dir.x as f32, dir.y as f32, dir.z as f32];
            let (was, now) = (old.eval_direction(dir), self.medium.eval_direction(dir));
            let range = range as f32;
            for c in 0..3 {
                let seen_as = |m: &[f32; MEDIUM_CHANNELS], j: f32| j * (-m[SIGMA_ATT + c] * range).exp() + m[C_MED + c] * (1.0 - (-m[SIGMA_BS + c] * range).exp());
                let j = 0.5 + SH_C0 as f32 * p.f_dc[c];
                let observed = seen_as(&was, j);
                let backscatter = seen_as(&now, 0.0);
                let colour = ((observed - backscatter) * (now[SIGMA_ATT + c] * range).exp()).clamp(0.0, 1.0);
                p.f_dc[c] = ((colour - 0.5) as f64 / SH_C0) as f32;
            }
            self.gaussians.set(i, &p);
        }
    }

    /// Fills `slot` from `kf` and makes it the newest keyframe.
    fn store_keyframe(&mut self, mut slot: MapKeyframe, kf: &Keyframe) {
        slot.refill(kf);
        self.keyframes.push(slot);
    }

    /// Appends `kf` as the newest keyframe in a free slot (checkpoint restore: the history is
    /// rebuilt oldest first, never beyond `max_keyframes`).
    pub(crate) fn push_restored_keyframe(&mut self, kf: &Keyframe) {
        let (w, h) = (kf.camera.width, kf.camera.height);
        let slot = self.spare_keyframes.pop().unwrap_or_else(|| MapKeyframe::blank(w, h));
        self.store_keyframe(slot, kf);
    }

    /// One optimisation step on a scheduled keyframe, then densify/prune when due.
    pub fn iterate(&mut self) -> Result<IterationReport, MapperError> {
        if self.keyframes.is_empty() {
            return Err(MapperError::NoKeyframes);
        }
        let slot = pick_keyframe(&mut self.rng, self.keyframes.len(), self.config.window, self.config.window_probability);
        // The keyframe the next call draws if nothing changes meanwhile, so that the Vulkan
        // renderer can run its geometry while this step finishes (a wrong guess costs nothing
        // but the overlap).
        let next = pick_keyframe(&mut self.rng.clone(), self.keyframes.len(), self.config.window, self.config.window_probability);
        self.step_on_then(slot, Some(next))
    }

    /// `(submitted, used)`: next-step geometries the Vulkan renderer submitted ahead and the
    /// forwards that used one ([`Self::step_on_then`]); `None` on the CPU reference.
    pub fn geometry_ahead_counts(&self) -> Option<(u64, u64)> {
        self.raster.geometry_ahead_counts()
    }

    /// Whether [`Self::step_on_then`] (and so [`Self::iterate`]) tells the renderer which
    /// keyframe the next step is on (on by default); the maps are the same either way. Returns
    /// the previous setting.
    pub fn set_plan_ahead(&mut self, on: bool) -> bool {
        std::mem::replace(&mut self.plan_ahead, on)
    }

    /// One optimisation step on keyframe `slot` (oldest first), then densify/prune when due.
    pub fn step_on(&mut self, slot: usize) -> Result<IterationReport, MapperError> {
        self.step_on_then(slot, None)
    }

    /// [`Self::step_on`], told that the next step is on keyframe `next`: the Vulkan renderer
    /// then submits that view's geometry (projection, binning, sort) right after this step's
    /// Adam, and the device runs it while the host finishes this step
    /// (`GpuRenderer::plan_next_view`). The next step renders exactly as without the hint; a
    /// hint that turns out wrong (another keyframe, the map changed) is ignored.
    pub fn step_on_then(&mut self, slot: usize, next: Option<usize>) -> Result<IterationReport, MapperError> {
        let t0 = Instant::now();
        let densify_before = self.times.densify_s;
        let report = self.step_on_then_untimed(slot, next);
        self.times.steps += 1;
        self.times.step_s += t0.elapsed().as_secs_f64() - (self.times.densify_s - densify_before);
        report
    }

    fn step_on_then_untimed(&mut self, slot: usize, next: Option<usize>) -> Result<IterationReport, MapperError> {
        let next = next.filter(|_| self.plan_ahead);
        let _span = tracing::debug_span!("map.iterate", iteration = self.iteration + 1).entered();
        let count = self.keyframes.len();
        let kf = self.keyframes.get(slot).ok_or(MapperError::NoSuchKeyframe { slot, count })?;
        let (camera, pose) = (kf.kf.camera, kf.kf.world_from_cam);
        // On Vulkan the optimiser's map stays on the device (Adam there too), and the medium
        // network runs there when enabled (`use_device`).
        let device_map = self.config.optimise_gaussians && self.raster.is_vulkan();
        let device_medium = self.raster.has_device_medium();
        if !device_medium {
            self.medium_forward(&camera, &pose)?;
        }
        // On Vulkan the forward's submission runs while the loss and backward are recorded; a
        // tile overflow then shows with the loss (nothing of that step taken) and the step is
        // done again after the overflow policy, as when the forward reports it.
        let mut tries = 0;
        let (loss, psnr_db) = loop {
            self.forward_within_capacity(&camera, &pose, false, device_map, device_medium)?;
            if device_map && self.raster.is_resident() {
                // The Gaussians' Adam step in the same submission as the loss and backward.
                self.raster.arm_adam_step(&self.adam)?;
                if let Some(kf) = next.and_then(|k| self.keyframes.get(k)) {
                    self.raster.plan_next_view(&kf.kf.camera, &kf.kf.world_from_cam.inverse(), &self.config.render, self.gaussians.len());
                }
            }
            let kf = &self.keyframes[slot];
            let v = &mut self.view;
            let target = TargetView { image: &kf.image, depth: &kf.kf.inv_depth, depth_variance: &kf.target_variance };
            // A resident device map has its gradients zeroed on the device (the host's are
            // not read back unless a step is refused).
            if !(device_map && self.raster.is_resident()) {
                self.grads.zero_params();
            }
            let mut medium_back = DeviceMediumBackward {
                prior: self.medium_prior.as_ref(),
                single_coefficient: self.config.single_medium_coefficient,
                param_grads: &mut self.medium_grads,
            };
            let result = self.raster.loss_and_backward(
                &self.gaussians,
                &v.planes,
                &v.planes9,
                &v.out,
                &target,
                Some(kf.target_key),
                &self.config.loss,
                &mut self.loss_ws,
                &mut v.upstream,
                &mut self.grads,
                &mut v.planes_grad,
                &mut v.d_medium_loss,
                match device_medium {
                    true => Some(&mut medium_back),
                    false => None,
                },
            );
            match result {
                Err(VulkanRenderError::Render(RenderError::TileOverflow { needed, capacity })) if tries < OVERFLOW_RETRIES && !self.gaussians.is_empty() => {
                    tries += 1;
                    self.prune_for_overflow(needed, capacity)?;
                }
                other => break other?,
            }
        };
        if let Some(n) = self.raster.last_intersections() {
            self.intersections_tight = n * 10 > self.raster_capacity.max_intersections * 9;
        }
        if device_medium {
            // The medium's backward ran on the device; `medium_grads` holds its gradient.
            if self.config.optimise_medium {
                self.medium_adam.step(self.medium.params_mut(), &self.medium_grads)?;
            }
        } else {
            self.medium_backward_on_host(&camera, &pose)?;
        }
        self.step_gaussians()?;
        self.finish_step(slot, loss, psnr_db)
    }

    /// The medium's backward on the host: the planes' gradient from the renderer and the
    /// loss, the prior, the single-coefficient tie, the network's backward, its Adam step.
    fn medium_backward_on_host(&mut self, camera: &PinholeCamera, pose: &Se3) -> Result<(), MapperError> {
        let v = &mut self.view;
        nine_from_planes(&v.planes_grad, &mut v.d_planes9);
        for (d, &l) in v.d_planes9.data.iter_mut().zip(&v.d_medium_loss.data) {
            *d += l;
        }
        if let Some(prior) = &self.medium_prior {
            prior.loss_and_grad(&v.planes9.data, &mut v.d_planes9.data);
        }
        if self.config.single_medium_coefficient {
            fold_single_coefficient(&mut v.d_planes9.data);
        }
        if self.config.optimise_medium {
            self.medium_grads.fill(0.0);
            self.medium_ws.backward(&self.medium, camera, pose, &v.d_planes9, &mut self.medium_grads)?;
            self.medium_adam.step(self.medium.params_mut(), &self.medium_grads)?;
        }
        Ok(())
    }

    /// The Gaussians' Adam step: on the device map when it is resident, else on the host.
    fn step_gaussians(&mut self) -> Result<(), MapperError> {
        if self.config.optimise_gaussians && self.raster.is_resident() {
            if !self.raster.adam_step(&self.gaussians, &mut self.grads, &mut self.adam)? {
                // Refused on the device, nothing changed; name the value as the host step would.
                let bad = ParamGroup::ALL.iter().find_map(|&g| {
                    let values = self.grads.group(g);
                    values.iter().position(|v| !v.is_finite()).map(|index| AdamError::NonFiniteGradient { index, value: values[index] })
                });
                return Err(bad.map_or_else(|| MapperError::Gpu("Adam on the device refused a step but every gradient read back is finite".into()), MapperError::from));
            }
        } else if self.config.optimise_gaussians {
            for (k, g) in ParamGroup::ALL.iter().enumerate() {
                self.adam[k].step(self.gaussians.group_mut(*g), self.grads.group(*g))?;
            }
        }
        Ok(())
    }

    /// Counts the step and densifies/prunes when due.
    fn finish_step(&mut self, slot: usize, loss: LossTerms, psnr_db: f64) -> Result<IterationReport, MapperError> {
        self.iteration += 1;
        let cfg = &self.config;
        let due = cfg.optimise_gaussians && cfg.densify_every > 0 && self.iteration >= cfg.densify_start && self.iteration % cfg.densify_every == 0;
        // Overflow policy: no densification while the last render left under 10% of the
        // intersection buffer free (pruning still happens through the overflow path).
        let densify = if due && self.intersections_tight {
            self.overflow.densify_skipped += 1;
            None
        } else if due {
            let t0 = Instant::now();
            let report = self.densify_and_prune();
            self.times.densify += 1;
            self.times.densify_s += t0.elapsed().as_secs_f64();
            Some(report?)
        } else {
            None
        };
        Ok(IterationReport { iteration: self.iteration, keyframe: self.keyframes[slot].kf.index, loss, psnr_db, gaussians: self.gaussians.len(), densify })
    }

    /// The forward render of the current map into the view buffers, with the tile-overflow
    /// policy: when the view needs more tile intersections than the renderer's buffers hold
    /// (sized once from the Gaussian cap x `intersections_per_gaussian`), the Gaussians with
    /// the largest axis are pruned (half the excess share of the map plus 2%) and the view is
    /// rendered again (up to [`OVERFLOW_RETRIES`] times); densification waits while the buffer
    /// stays over 90% full. No buffer is ever reallocated. Counted in [`Self::overflow_stats`].
    fn forward_within_capacity(&mut self, camera: &PinholeCamera, world_from_cam: &Se3, images_on_host: bool, device_map: bool, device_medium: bool) -> Result<RenderStats, MapperError> {
        let cam_from_world = &world_from_cam.inverse();
        let mut tries = 0;
        loop {
            if device_map && !self.raster.is_resident() {
                let t0 = Instant::now();
                self.raster.ensure_resident(&self.gaussians, &self.grads, &self.adam)?;
                self.times.uploads += 1;
                self.times.upload_s += t0.elapsed().as_secs_f64();
            }
            let v = &mut self.view;
            let rendered = if images_on_host {
                self.raster.forward(&self.gaussians, camera, cam_from_world, &v.planes, &self.config.render, &mut v.out)
            } else {
                let step = DeviceMediumStep { net: &self.medium, world_from_cam, single_coefficient: self.config.single_medium_coefficient };
                self.raster.forward_for_loss(&self.gaussians, camera, cam_from_world, &v.planes, device_medium.then_some(&step), &self.config.render, &mut v.out)
            };
            match rendered {
                Ok(stats) => {
                    self.intersections_tight = stats.intersections * 10 > self.raster_capacity.max_intersections * 9;
                    return Ok(stats);
                }
                Err(VulkanRenderError::Render(RenderError::TileOverflow { needed, capacity })) if tries < OVERFLOW_RETRIES && !self.gaussians.is_empty() => {
                    tries += 1;
                    self.prune_for_overflow(needed, capacity)?;
                }
                Err(e) => return Err(e.into()),
            }
        }
    }

    /// The tile-overflow policy's pruning: the Gaussians with the largest axis, half the excess
    /// share of the map plus 2% (the largest go first and cover more tiles than the average,
    /// so this converges from below in a few renders); densification pauses.
    fn prune_for_overflow(&mut self, needed: u64, capacity: usize) -> Result<(), MapperError> {
        let n = self.gaussians.len();
        self.release_device_map()?;
        let share = (0.5 * (1.0 - capacity as f64 / needed.max(1) as f64) + 0.02).clamp(0.01, 1.0);
        let count = ((n as f64 * share).ceil() as usize).clamp(1, n);
        let pruned = remove_gaussians(&mut self.gaussians, &mut self.grads, &mut self.adam, count, Removal::Largest, &mut self.densify_scratch)?;
        self.intersections_tight = true;
        let o = &mut self.overflow;
        o.events += 1;
        o.pruned += pruned as u64;
        o.largest_needed = o.largest_needed.max(needed);
        o.capacity = capacity;
        tracing::warn!(needed, capacity, pruned, "map: tile intersections overflow; pruned the largest Gaussians, densification paused");
        Ok(())
    }

    /// What the tile-overflow policy has done so far.
    pub fn overflow_stats(&self) -> OverflowStats {
        self.overflow
    }

    /// Prunes and densifies now (see [`densify_and_prune`]) and resets the medium's Adam
    /// moments (§3.3). The split offsets are drawn from a stream derived from the seed and the
    /// iteration, not from the mapper's own generator, so the keyframe schedule does not
    /// depend on how many Gaussians were split: two runs whose density control differs by a
    /// few splits (the CPU reference and the Vulkan kernels round differently) still visit
    /// the same keyframes in the same order.
    pub fn densify_and_prune(&mut self) -> Result<DensifyReport, MapperError> {
        self.release_device_map()?;
        let c = &self.config;
        let params = DensifyParams {
            grad_threshold: c.densify_grad_threshold,
            split_scale_m: c.split_scale_m,
            prune_min_opacity: c.prune_min_opacity,
            prune_max_scale_m: c.prune_max_scale_m,
            max_replace_fraction: c.max_replace_fraction,
        };
        let mut split_rng = Rng::derive(c.seed, self.iteration);
        let report = densify_and_prune(&mut self.gaussians, &mut self.grads, &mut self.adam, &params, &mut split_rng, &mut self.densify_scratch)?;
        self.medium_adam.reset_moments();
        tracing::debug!(?report, "map.densify");
        Ok(report)
    }
}

/// Which keyframe pixels a seeding pass takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SeedPass {
    /// A new keyframe: depth within `init_max_rel_std`.
    Confident,
    /// A keyframe leaving the window: depth that `init_max_rel_std` refused but
    /// `late_init_max_rel_std` accepts, back-projected to a point that floats in front of no
    /// stored keyframe's measured surface (so that depth, less certain, cannot hide what
    /// another view saw).
    Late,
}

/// A late seed more than this fraction nearer (in inverse depth) than the surface another
/// keyframe measured along the same ray would float in that keyframe's view.
const LATE_SEED_IN_FRONT: f64 = 0.1;

/// Whether `p_in_world` lies in keyframe `o`'s view in front of the surface `o` measured
/// there (inverse depth over `1 + LATE_SEED_IN_FRONT` times `o`'s); pixels where `o` has no
/// depth say nothing.
fn in_front_of_surface(o: &MapKeyframe, p_in_world: &nalgebra::Point3<f64>) -> bool {
    let Some((i, p_inv_depth)) = pixel_of(&o.kf, p_in_world) else {
        return false;
    };
    let measured = o.kf.inv_depth.data[i] as f64;
    measured > 0.0 && measured.is_finite() && p_inv_depth > measured * (1.0 + LATE_SEED_IN_FRONT)
}

/// The pixel (index, nearest) of keyframe `kf`'s image that `p_in_world` projects to, and
/// the point's inverse depth in that camera; `None` behind the camera or outside the image.
fn pixel_of(kf: &Keyframe, p_in_world: &nalgebra::Point3<f64>) -> Option<(usize, f64)> {
    let c = &kf.camera;
    let p = kf.world_from_cam.inverse_transform_point(p_in_world);
    if p.z <= 0.0 {
        return None;
    }
    let (u, v) = ((c.fx * p.x / p.z + c.cx).round(), (c.fy * p.y / p.z + c.cy).round());
    if !(u >= 0.0 && v >= 0.0 && u < c.width as f64 && v < c.height as f64) {
        return None;
    }
    Some((v as usize * c.width + u as usize, 1.0 / p.z))
}

/// The point keyframe pixel (`x`, `y`) seeds, in the camera and world frames, or `None`: it
/// needs valid inverse depth whose relative standard deviation is in the band `pass` takes,
/// a map rendering less than `init_covered_alpha` there (`alpha`, the map's alpha from the
/// keyframe's pose) and, for [`SeedPass::Late`], a point in front of no surface that a
/// keyframe of `others` measured ([`in_front_of_surface`]).
fn seed_point(kf: &Keyframe, alpha: &[f32], cfg: &MapperConfig, pass: SeedPass, others: &[MapKeyframe], x: usize, y: usize) -> Option<(nalgebra::Point3<f64>, nalgebra::Point3<f64>)> {
    let cam = &kf.camera;
    let i = y * cam.width + x;
    let d = kf.inv_depth.data[i];
    let var = kf.inv_depth_variance.data[i];
    if !(d > 0.0 && d.is_finite() && var.is_finite() && var >= 0.0 && (alpha[i] as f64) < cfg.init_covered_alpha) {
        return None;
    }
    let rel_std = (var as f64).sqrt() / d as f64;
    let in_band = match pass {
        SeedPass::Confident => rel_std <= cfg.init_max_rel_std,
        SeedPass::Late => rel_std > cfg.init_max_rel_std && rel_std <= cfg.late_init_max_rel_std,
    };
    if !in_band {
        return None;
    }
    let z = 1.0 / d as f64;
    let p_in_cam = nalgebra::Point3::new((x as f64 - cam.cx) / cam.fx * z, (y as f64 - cam.cy) / cam.fy * z, z);
    let p_in_world = kf.world_from_cam * p_in_cam;
    if pass == SeedPass::Late && others.iter().any(|o| in_front_of_surface(o, &p_in_world)) {
        return None;
    }
    Some((p_in_cam, p_in_world))
}

/// With one coefficient for both medium terms (`sigma_bs` tied to `sigma_att`), the
/// gradient of `sigma_bs` belongs to `sigma_att`: adds it there and zeroes it, per pixel of
/// 9-channel medium-plane gradients. Kernel twin: `medium_prior.medium_upstream`.
pub fn fold_single_coefficient(d_planes9: &mut [f32]) {
    for px in d_planes9.chunks_exact_mut(MEDIUM_CHANNELS) {
        for c in 0..3 {
            px[SIGMA_ATT + c] += px[SIGMA_BS + c];
            px[SIGMA_BS + c] = 0.0;
        }
    }
}

