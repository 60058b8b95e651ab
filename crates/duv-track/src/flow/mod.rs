//! Dense correspondence front end: a classical coarse-to-fine optical flow in the place of
//! RAFT, seeded by the flow the current bundle-adjustment estimate induces, so that flow and
//! BA can alternate as the paper's recurrent updates do (§3.1, Eq. 1).
//!
//! # Method (DIS-like)
//! Dense Inverse Search (Kroeger et al., ECCV 2016) with a variational refinement, run on a
//! pyramid (`[1 3 3 1] / 8` filter, halving) from a start level down to the finest level.
//! The finest level is by default the coarsest with at least 160 x 120 pixels (level 1 of
//! 320 x 240, level 2 of 640 x 480), so an edge costs about the same at any input size and its
//! accuracy is fixed relative to the BA's 1/8 grid. At every level:
//! 1. *Initial field*: at the start level the seed (zero without one), below it the coarser
//!    level's field upsampled by two.
//! 2. *Inverse search*: square patches on a regular grid (`patch_size`, `patch_stride`) are
//!    moved by inverse-compositional Gauss-Newton on the mean-removed patch residual. Hessian
//!    and mean gradient belong to the source frame and are precomputed by `prepare`, and a
//!    translation has the same bilinear weights at every patch pixel, so one iteration is one
//!    cheap warp of the patch. Each patch starts from whichever of the propagated flow and the
//!    seed has the lower patch SSD (a seed from BA rescues patches the pyramid got wrong),
//!    and ends on the best iterate it evaluated (stopping if it runs a patch size away).
//! 3. *Densification*: a pixel's flow is the mean of the flows of the patches covering it,
//!    each weighted by `1 / max(|residual|, densify_eps)` at that pixel.
//! 4. *Variational refinement* (the finest `refine_levels` levels only: coarser ones just seed
//!    the next level's patches, and refining them did not change the final accuracy in the
//!    tests): feature constancy (Charbonnier) plus Charbonnier smoothness, linearised around
//!    the current field and solved by red-black block SOR. This fixes what translating
//!    patches cannot represent (rotation, scale, perspective inside a patch): in the tests
//!    it takes the median error of a 3 degree rotation with 4 % zoom from 0.2 to 0.06 px.
//!
//! The backward flow (dst to src) runs the same with the frames swapped; its seed is the
//! inverted forward seed. The forward-backward error is `|F(x) + B(x + F(x))|`.
//!
//! # Features: why locally normalised intensity
//! Underwater images differ from frame to frame by a colour cast, a contrast loss and a
//! backscatter veil that grows with range: locally, an affine change `a I + b` whose `a`, `b`
//! vary smoothly over the image. The default feature, [`FeatureKind::LocalNormalized`],
//! `(I - mean_w(I)) / sqrt(var_w(I) + eps^2)` over a small box window, cancels any such
//! change exactly where `a` and `b` are constant over the window, and lifts weak, hazy texture
//! to unit contrast, so the patch search and the refinement see the same signal near and far.
//! `eps` keeps sensor noise in flat regions from being amplified to full contrast; those
//! regions get low confidence anyway from the texture term (below). Being one channel, it
//! keeps the search as cheap as raw intensity. [`FeatureKind::SoftCensus`] adds robustness
//! to outliers (marine snow, specular glints) for four times the search cost: four channels
//! `d / sqrt(d^2 + census_eps^2)`, `d` a difference of normalised intensity to a neighbour
//! two pixels away. [`FeatureKind::Intensity`] is the raw baseline (patch means are still
//! removed, so a constant offset is tolerated). Grey input only: the colour cast is handled
//! by normalisation, and luma keeps the green and blue channels that carry texture underwater.
//!
//! # Confidence: the diagonal of Sigma^-1
//! Two weights per pixel in `[0, 1]`, one per image axis, products of
//! - *texture*: the marginal information of the flow along that axis, from the structure
//!   tensor `J` of the intensity (not the feature: information is signal over sensor noise)
//!   summed over a `(2 texture_radius + 1)^2` window and divided by the noise variance at
//!   that level: `lambda_x = (Jxx - Jxy^2 / Jyy) / sigma^2`, the inverse of the x variance of
//!   a patch-flow estimate, so an edge gives high weight across it and none along it, a
//!   diagonal edge low weight on both axes. Minus the floor pure noise would give, mapped to
//!   `lambda / (lambda + 1 / texture_sigma^2)`; the lower of the source's (at the pixel) and
//!   the destination's (at the target), as both ends of a match need texture;
//! - *photometric*: `1 / (1 + (r / residual_sigma)^2)`, `r` the RMS feature residual at the
//!   flow's target;
//! - *forward-backward*: `1 / (1 + (e / fb_sigma)^2)`, zero beyond `fb_max`, with `e` the
//!   error's component along that axis (the ambiguous axis of an edge may disagree while the
//!   determined one is right);
//! - *in view*: zero where the target leaves the destination image.
//!
//! Scale them by the BA's nominal flow precision to get Sigma^-1 in 1/px^2.
//!
//! `fb_sigma_px` and `fb_max_px` are written in pixels of an image [`REFERENCE_WIDTH_PX`] (320)
//! wide and scaled up with a wider input: the same angle of disagreement at every size above
//! it. The finest level is about 160 x 120 at every size (`finest_min_pixels`), so a mismatch
//! of one finest-level pixel is two input pixels at 320x240 and four at 640x480; thresholds
//! fixed in input pixels rejected twice the angle at 640x480 and failed its initialisation on
//! weak texture (the `sandturn` and `lowfps` rows of `duv bench track`). Narrower inputs keep
//! them in input pixels: there the finest level is the input itself, and halved thresholds
//! (a quarter of a finest-level pixel at 160x120) lost the generated survey (4.1 % of path).
//! `texture_sigma_px` stays in input pixels: it is weighed against the sensor noise at the
//! finest level, which falls faster than the cell grows. `pool_spread_px` stays too: scaled as
//! well, the `lowfps` row at 640x480 kept fewer frames (131 of 150 against 144).
//!
//! # Grids and units
//! A grid with cell `c` input pixels (level `l` has `c = 2^l`; the pooled output
//! `c = output_factor`) has pixel `(i, j)` covering input pixels `[c i, c i + c)` with its
//! centre at input coordinate `c i + (c - 1) / 2`; pixel centres are at integer coordinates,
//! as in `core::camera`. Flow values are in the grid's own pixels: the target of `(i, j)` is
//! `(i + dx, j + dy)` in the same grid. [`FlowField::cell_px`] records the grid; the full
//! output is at `finest_level`, the pooled output at `output_factor`, and a seed may be given
//! on any grid (typically the BA's).
//!
//! # Allocation and threads
//! [`FlowEstimator::new`] allocates every pyramid level, patch table, flow field and scratch
//! plane; [`FlowEstimator::new_frame`] and [`FlowEstimator::new_result`] allocate the per-frame
//! and per-edge outputs. After that, [`FlowEstimator::prepare_into`] and
//! [`FlowEstimator::estimate`] never allocate (see `tests/flow_alloc.rs`), on one condition:
//! row-parallel loops use rayon, and a rayon call made from outside a pool goes through its
//! injector queue, which allocates a small block every 63 calls (about one per frame). Run
//! the tracker inside its pool (`ThreadPool::install`) and nothing is allocated per frame.
//!
//! # Tracing
//! One `track.flow` span (DEBUG) per edge with a TRACE event of [`FlowStats`];
//! `track.flow.prepare` (TRACE) per prepared frame.

mod confidence;
mod pyramid;
mod refine;
mod search;
pub mod synth;
#[cfg(test)]
mod tests;

use duv_core::PlaneF32;
use rayon::prelude::*;

/// Errors of the `track::flow` module.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FlowError {
    #[error("{what}: size {found_w}x{found_h} does not match the estimator's {expected_w}x{expected_h}")]
    SizeMismatch { what: &'static str, expected_w: usize, expected_h: usize, found_w: usize, found_h: usize },
    #[error("seed flow: grid {found_w}x{found_h} with {cell_px}-px cells does not cover a {width}x{height} image (expected {expected_w}x{expected_h})")]
    SeedGrid {
        cell_px: usize,
        width: usize,
        height: usize,
        expected_w: usize,
        expected_h: usize,
        found_w: usize,
        found_h: usize,
    },
    #[error("{what}: non-finite value {value} at pixel ({x}, {y})")]
    NonFinite { what: &'static str, x: usize, y: usize, value: f32 },
    #[error("flow config: {field}: {problem}")]
    Config { field: &'static str, problem: &'static str },
    #[error("image {width}x{height} is too small: level {level} would be {level_w}x{level_h}, under the {min_px}-px minimum")]
    TooSmall { width: usize, height: usize, level: usize, level_w: usize, level_h: usize, min_px: usize },
    #[error("result: flow grid of {found_px}-px cells where the estimator writes {expected_px}-px cells")]
    ResultCell { expected_px: usize, found_px: usize },
    #[error("{what}: prepared by an estimator with another size or feature configuration")]
    ForeignFrame { what: &'static str },
}

/// What the flow matches on. See the module documentation for the trade-offs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureKind {
    /// Raw grey intensity (patch means removed). Baseline; not robust to haze or contrast loss.
    Intensity,
    /// Locally normalised intensity, one channel (the default).
    LocalNormalized,
    /// Soft census of the locally normalised intensity, four channels.
    SoftCensus,
}

impl FeatureKind {
    /// Feature channels per pixel.
    pub fn channels(self) -> usize {
        match self {
            FeatureKind::Intensity | FeatureKind::LocalNormalized => 1,
            FeatureKind::SoftCensus => 4,
        }
    }
}

/// Parameters of the flow front end. Pixel quantities are in input pixels unless named
/// otherwise; feature quantities in feature units (unit contrast for normalised features).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlowConfig {
    /// Feature the patches and the refinement match on.
    pub feature: FeatureKind,
    /// Radius of the box window of the local normalisation (window `2 r + 1`).
    pub normalize_radius: usize,
    /// Regulariser of the local normalisation, in intensity units (input in [0, 1]).
    pub normalize_eps: f32,
    /// Softness of the soft census, in normalised-intensity units.
    pub census_eps: f32,
    /// Finest pyramid level computed (0 = input resolution, 1 = half, 2 = quarter); `None`
    /// picks the coarsest level with at least `finest_min_pixels` pixels whose cell divides
    /// `output_factor`, so that the cost per edge does not grow with the input size.
    pub finest_level: Option<usize>,
    /// Pixels the automatic finest level must have at least (160 x 120 by default: level 1 of
    /// 320 x 240, level 2 of 640 x 480).
    pub finest_min_pixels: usize,
    /// Coarsest level without a seed; `None` picks the coarsest whose shorter side holds two patches.
    pub coarsest_level: Option<usize>,
    /// Level to start from when a seed is given; `None` starts from the unseeded coarsest level.
    pub coarsest_level_seeded: Option<usize>,
    /// Side of the square patches of the inverse search, in level pixels.
    pub patch_size: usize,
    /// Spacing of the patch grid, in level pixels (`<= patch_size`).
    pub patch_stride: usize,
    /// Gauss-Newton iterations per patch at most.
    pub patch_iterations: usize,
    /// A patch stops when its update is shorter than this, in level pixels.
    pub patch_min_step_px: f32,
    /// Residual floor of the densification weights, in feature units.
    pub densify_eps: f32,
    /// Levels refined variationally, counted from the finest (coarser levels only seed the
    /// next one's patches, which the refinement barely improves).
    pub refine_levels: usize,
    /// Linearisations (warps) of the variational refinement per level; 0 disables it.
    pub refine_outer: usize,
    /// SOR sweeps per linearisation.
    pub refine_iterations: usize,
    /// Weight of the smoothness term against the per-channel data term.
    pub refine_smoothness: f32,
    /// Charbonnier epsilon of the data term, in feature units.
    pub refine_data_eps: f32,
    /// Charbonnier epsilon of the smoothness term, in level pixels per pixel.
    pub refine_smooth_eps: f32,
    /// Compute the backward flow and the forward-backward check (doubles the cost).
    pub forward_backward: bool,
    /// Standard deviation of the input intensity noise, in intensity units ([0, 1] input).
    pub noise_sigma: f32,
    /// Flow standard deviation at which the texture weight is 0.5, in input pixels.
    pub texture_sigma_px: f32,
    /// Radius of the structure-tensor window, in finest-level pixels.
    pub texture_radius: usize,
    /// RMS feature residual at which the photometric weight is 0.5.
    pub residual_sigma: f32,
    /// Forward-backward error at which its weight is 0.5, in pixels of a
    /// [`REFERENCE_WIDTH_PX`]-wide image (scaled up with a wider input).
    pub fb_sigma_px: f32,
    /// Forward-backward error beyond which the weight is zero, in pixels of a
    /// [`REFERENCE_WIDTH_PX`]-wide image (scaled up with a wider input).
    pub fb_max_px: f32,
    /// Cell of the pooled output in input pixels (the BA's depth resolution, 4 to 8 typically);
    /// a multiple of the finest level's cell `2^finest_level`.
    pub output_factor: usize,
    /// Spread (weighted standard deviation) of the flow inside a pooled cell at which its
    /// weight halves, in input pixels: motion boundaries and bad matches pool badly.
    pub pool_spread_px: f32,
}

impl Default for FlowConfig {
    fn default() -> Self {
        FlowConfig {
            feature: FeatureKind::LocalNormalized,
            normalize_radius: 3,
            normalize_eps: 0.01,
            census_eps: 0.3,
            finest_level: None,
            finest_min_pixels: 160 * 120,
            coarsest_level: None,
            coarsest_level_seeded: None,
            patch_size: 8,
            patch_stride: 4,
            patch_iterations: 8,
            patch_min_step_px: 0.01,
            densify_eps: 0.05,
            refine_levels: 1,
            refine_outer: 1,
            refine_iterations: 5,
            refine_smoothness: 2.0,
            refine_data_eps: 0.1,
            refine_smooth_eps: 0.1,
            forward_backward: true,
            noise_sigma: 0.006,
            texture_sigma_px: 0.5,
            texture_radius: 3,
            residual_sigma: 0.5,
            fb_sigma_px: 0.5,
            fb_max_px: 2.0,
            output_factor: 8,
            pool_spread_px: 1.0,
        }
    }
}

/// A flow field on a grid of `cell_px`-pixel cells (see the module doc for the convention).
#[derive(Clone, Debug, PartialEq)]
pub struct FlowField {
    /// Input pixels per grid pixel.
    pub cell_px: usize,
    /// Horizontal flow, in grid pixels.
    pub dx: PlaneF32,
    /// Vertical flow, in grid pixels.
    pub dy: PlaneF32,
}

impl FlowField {
    /// A zero field of `width x height` grid pixels.
    pub fn zeros(width: usize, height: usize, cell_px: usize) -> Self {
        FlowField { cell_px, dx: PlaneF32::new(width, height), dy: PlaneF32::new(width, height) }
    }
    /// The grid of cell `cell_px` (> 0) over an `input_w x input_h` image, filled with a
    /// constant flow given in input pixels.
    pub fn constant(input_w: usize, input_h: usize, cell_px: usize, dx_input_px: f32, dy_input_px: f32) -> Self {
        let (w, h) = (input_w / cell_px, input_h / cell_px);
        let c = cell_px as f32;
        FlowField {
            cell_px,
            dx: PlaneF32::filled(w, h, [dx_input_px / c]),
            dy: PlaneF32::filled(w, h, [dy_input_px / c]),
        }
    }
    /// The grid of cell `cell_px` (> 0) over an `input_w x input_h` image, filled from a
    /// function of the input coordinates of each cell centre returning a flow in input pixels
    /// (how a seed is made from the BA's current poses and depths).
    pub fn from_fn(
        input_w: usize,
        input_h: usize,
        cell_px: usize,
        mut flow_input_px: impl FnMut(f32, f32) -> (f32, f32),
    ) -> Self {
        let mut f = FlowField::zeros(input_w / cell_px, input_h / cell_px, cell_px);
        let c = cell_px as f32;
        for y in 0..f.height() {
            for x in 0..f.width() {
                let (u, v) = flow_input_px(cell_centre(cell_px, x as f32), cell_centre(cell_px, y as f32));
                let i = y * f.width() + x;
                f.dx.data[i] = u / c;
                f.dy.data[i] = v / c;
            }
        }
        f
    }
    pub fn width(&self) -> usize {
        self.dx.width
    }
    pub fn height(&self) -> usize {
        self.dx.height
    }
    /// Flow at grid pixel `(x, y)`, in grid pixels.
    pub fn get(&self, x: usize, y: usize) -> (f32, f32) {
        let i = y * self.width() + x;
        (self.dx.data[i], self.dy.data[i])
    }
    /// Bilinear flow at grid coordinates, clamped to the grid, in grid pixels (zero for an
    /// empty grid).
    pub fn sample(&self, x: f32, y: f32) -> (f32, f32) {
        if self.width() == 0 || self.height() == 0 {
            return (0.0, 0.0);
        }
        let (x0, y0, ax, ay) = bilinear_cell(self.width(), self.height(), x, y);
        let w = self.width();
        (bilinear_at(&self.dx.data, w, x0, y0, ax, ay), bilinear_at(&self.dy.data, w, x0, y0, ax, ay))
    }
    /// Flow at coordinates `(x, y)` of another grid with cell `cell_px`, in that grid's pixels.
    pub fn sample_in_grid(&self, cell_px: usize, x: f32, y: f32) -> (f32, f32) {
        let (gx, gy) = (convert_coord(cell_px, self.cell_px, x), convert_coord(cell_px, self.cell_px, y));
        let (u, v) = self.sample(gx, gy);
        let k = self.cell_px as f32 / cell_px as f32;
        (u * k, v * k)
    }
    /// Flow magnitude at grid pixel `(x, y)`, in input pixels.
    pub fn magnitude_input_px(&self, x: usize, y: usize) -> f32 {
        let (u, v) = self.get(x, y);
        (u * u + v * v).sqrt() * self.cell_px as f32
    }
}

/// Input coordinate of the centre of grid pixel `i` for cells of `cell_px` input pixels.
#[inline]
pub fn cell_centre(cell_px: usize, i: f32) -> f32 {
    let c = cell_px as f32;
    c * i + 0.5 * (c - 1.0)
}

/// Converts a coordinate on a grid of cell `from_cell` to one on a grid of cell `to_cell`.
#[inline]
pub fn convert_coord(from_cell: usize, to_cell: usize, x: f32) -> f32 {
    let t = to_cell as f32;
    (cell_centre(from_cell, x) - 0.5 * (t - 1.0)) / t
}

/// The BA's view of an edge: flow and per-axis weights pooled to `output_factor` cells.
#[derive(Clone, Debug, PartialEq)]
pub struct PooledFlow {
    /// Confidence-weighted mean of the finest flow over each cell, in pooled-grid pixels.
    pub flow: FlowField,
    /// Mean x weight over the cell, lowered by the flow's spread inside it.
    pub weight_x: PlaneF32,
    /// Mean y weight over the cell, lowered by the flow's spread inside it.
    pub weight_y: PlaneF32,
}

impl PooledFlow {
    /// Target (the flow-corrected correspondence p_ij of Eq. 1) of pooled pixel `(x, y)`, in
    /// pooled-grid coordinates.
    pub fn target(&self, x: usize, y: usize) -> (f32, f32) {
        let (u, v) = self.flow.get(x, y);
        (x as f32 + u, y as f32 + v)
    }
}

/// Summary of one estimate, also traced.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FlowStats {
    /// Pyramid level the estimate started from (depends on whether a seed was given).
    pub start_level: usize,
    /// Mean of `(weight_x + weight_y) / 2` over the finest grid.
    pub mean_weight: f32,
    /// Fraction of finest pixels whose forward target lies inside the destination image.
    pub in_view_fraction: f32,
    /// Weighted mean forward flow magnitude, in input pixels (for keyframe selection).
    pub mean_flow_input_px: f32,
}

/// Output of [`FlowEstimator::estimate`]; allocate once with [`FlowEstimator::new_result`].
#[derive(Clone, Debug, PartialEq)]
pub struct FlowResult {
    /// Forward flow src -> dst at the finest level.
    pub flow: FlowField,
    /// Backward flow dst -> src at the finest level (zero when `forward_backward` is off).
    pub backward: FlowField,
    /// Per-pixel x weight in [0, 1] (diagonal of Sigma^-1 up to a global scale).
    pub weight_x: PlaneF32,
    /// Per-pixel y weight in [0, 1].
    pub weight_y: PlaneF32,
    /// Forward-backward error in finest-level pixels; +inf where the target is out of view,
    /// 0 when `forward_backward` is off.
    pub fb_error: PlaneF32,
    /// RMS feature residual at the target; +inf where the target is out of view.
    pub residual: PlaneF32,
    /// Flow and weights pooled to the BA's grid.
    pub pooled: PooledFlow,
    pub stats: FlowStats,
}

/// What [`FlowEstimator::screen`] measured of an edge at a coarse level.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FlowScreen {
    pub level: usize,
    /// Fraction of output-grid cells whose mean weight (photometric x forward-backward, the
    /// estimate's terms but texture) exceeds the `confident_weight` asked for.
    pub confident_fraction: f32,
    /// Weighted mean flow magnitude in input pixels.
    pub mean_flow_input_px: f32,
}

/// Everything `prepare` builds from one image: pyramid, features, gradients, patch tables and
/// texture weights. Built once per keyframe and reused for all its edges.
#[derive(Clone, Debug)]
pub struct PreparedFrame {
    layout: Layout,
    levels: Vec<PreparedLevel>,
    /// Texture weights at the finest level, x and y.
    texture_x: Vec<f32>,
    texture_y: Vec<f32>,
}

impl PreparedFrame {
    pub fn width(&self) -> usize {
        self.layout.width
    }
    pub fn height(&self) -> usize {
        self.layout.height
    }
    /// Texture (aperture) weights of this frame at the finest level, as x and y planes.
    pub fn texture_weights(&self) -> (&[f32], &[f32]) {
        (&self.texture_x, &self.texture_y)
    }
}

/// What makes prepared frames interchangeable between estimators.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Layout {
    width: usize,
    height: usize,
    feature: FeatureKind,
    normalize_radius: usize,
    normalize_eps: f32,
    census_eps: f32,
    finest_level: usize,
    coarsest_level: usize,
    patch_size: usize,
    patch_stride: usize,
    noise_sigma: f32,
    texture_sigma_px: f32,
    texture_radius: usize,
}

#[derive(Clone, Debug, Default)]
pub(crate) struct PreparedLevel {
    w: usize,
    h: usize,
    /// Smoothed intensity at this level.
    image: Vec<f32>,
    /// `C` feature channels per pixel, interleaved (empty below the finest level).
    feat: Vec<f32>,
    /// Feature gradients along x, `C` channels interleaved like `feat`.
    grad_x: Vec<f32>,
    /// Feature gradients along y, `C` channels interleaved like `feat`.
    grad_y: Vec<f32>,
    /// Per patch of the level's grid: inverse Hessian and mean gradients.
    patches: Vec<PatchData>,
}

/// Precomputed inverse-search data of one source patch.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PatchData {
    /// Inverse of the mean-removed Gauss-Newton Hessian: `[a, b, c]` of `[[a, b], [b, c]]`.
    hinv: [f32; 3],
    /// Mean gradient per channel, `[gx_0, gy_0, ...]` (up to four channels).
    mean_grad: [f32; 8],
}

/// Patch grid of one level.
#[derive(Clone, Debug, Default)]
pub(crate) struct LevelGeom {
    w: usize,
    h: usize,
    /// Side of the patches.
    patch: usize,
    patch_x: Vec<usize>,
    patch_y: Vec<usize>,
    /// Per row: first and last patch row covering it.
    cover_y: Vec<(u32, u32)>,
}

impl LevelGeom {
    fn new(w: usize, h: usize, patch: usize, stride: usize) -> Self {
        let px = grid_positions(w, patch, stride);
        let py = grid_positions(h, patch, stride);
        LevelGeom { w, h, patch, cover_y: cover(&py, h, patch), patch_x: px, patch_y: py }
    }
    fn patch_count(&self) -> usize {
        self.patch_x.len() * self.patch_y.len()
    }
}

fn grid_positions(n: usize, patch: usize, stride: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (0..).map(|k| k * stride).take_while(|&p| p + patch <= n).collect();
    if let Some(&last) = v.last() {
        if last + patch < n {
            v.push(n - patch);
        }
    }
    v
}

fn cover(pos: &[usize], n: usize, patch: usize) -> Vec<(u32, u32)> {
    (0..n)
        .map(|x| {
            let first = pos.iter().position(|&p| p + patch > x).unwrap_or(0);
            let last = pos.iter().rposition(|&p| p <= x).unwrap_or(first);
            (first as u32, last as u32)
        })
        .collect()
}

/// Dense flow of one level, level pixels.
#[derive(Clone, Debug, Default)]
pub(crate) struct LevelFlow {
    dx: Vec<f32>,
    dy: Vec<f32>,
}

/// Scratch planes of `prepare`.
#[derive(Clone, Debug, Default)]
pub(crate) struct PrepScratch {
    a: Vec<f32>,
    b: Vec<f32>,
    c: Vec<f32>,
    d: Vec<f32>,
    e: Vec<f32>,
    f: Vec<f32>,
}

/// Scratch of the densification and the variational refinement, sized for the finest level.
#[derive(Clone, Debug, Default)]
pub(crate) struct RefineScratch {
    /// Densification weight sums, one per pixel.
    weight_sum: Vec<f32>,
    /// Per pixel `[a11, a12, a22, c1, c2, smooth, 0, 0]`.
    coeff: Vec<[f32; 8]>,
    /// Red-black cells (red: `x + y` even), `ceil(w / 2)` per row and colour: neighbour weights,
    /// inverse of the 2x2 block, right-hand constants, active flag (see `refine`).
    cells: [Vec<[f32; 10]>; 2],
    /// Flow of the cells of each colour.
    u: [Vec<f32>; 2],
    v: [Vec<f32>; 2],
}

/// A seed as seen from a pyramid level.
#[derive(Clone, Copy)]
pub(crate) enum SeedView<'a> {
    None,
    /// The caller's src -> dst flow.
    Forward(&'a FlowField),
    /// Its inverse, for the dst -> src pass: `-S(y - S(y))`.
    Backward(&'a FlowField),
}

impl SeedView<'_> {
    /// Seed at level coordinates `(x, y)`, in level pixels.
    #[inline]
    fn at(&self, level: usize, x: f32, y: f32) -> Option<(f32, f32)> {
        let cell = 1usize << level;
        match *self {
            SeedView::None => None,
            SeedView::Forward(f) => Some(f.sample_in_grid(cell, x, y)),
            SeedView::Backward(f) => {
                let (u, v) = f.sample_in_grid(cell, x, y);
                let (u2, v2) = f.sample_in_grid(cell, x - u, y - v);
                Some((-u2, -v2))
            }
        }
    }
}

/// The flow front end: owns the buffers of one image size and configuration.
#[derive(Debug)]
pub struct FlowEstimator {
    cfg: FlowConfig,
    layout: Layout,
    /// Index = level; empty below the finest level.
    geoms: Vec<LevelGeom>,
    start_unseeded: usize,
    start_seeded: usize,
    fwd: Vec<LevelFlow>,
    bwd: Vec<LevelFlow>,
    patch_flow: Vec<[f32; 2]>,
    refine: RefineScratch,
    prep: PrepScratch,
}

/// Input width up to which the thresholds in reference pixels (`fb_sigma_px`, `fb_max_px`) are
/// input pixels; [`FlowEstimator::new`] scales them by `width / REFERENCE_WIDTH_PX` above it.
pub const REFERENCE_WIDTH_PX: usize = 320;

impl FlowConfig {
    /// The configuration with its reference-pixel thresholds in input pixels of a `width`-wide
    /// image (unchanged up to [`REFERENCE_WIDTH_PX`]).
    pub fn at_input_width(&self, width: usize) -> FlowConfig {
        let scale = (width as f32 / REFERENCE_WIDTH_PX as f32).max(1.0);
        FlowConfig {
            fb_sigma_px: self.fb_sigma_px * scale,
            fb_max_px: self.fb_max_px * scale,
            ..self.clone()
        }
    }
}

/// Finest level accepted (1/16 of the input).
const MAX_FINEST_LEVEL: usize = 4;

/// Smallest side, in level pixels, of a level the estimator works on, as a multiple of the patch.
const MIN_LEVEL_PATCHES: usize = 2;

impl FlowEstimator {
    /// Validates `cfg` for `width x height` input and allocates all buffers. The thresholds
    /// in reference pixels are scaled to this width ([`FlowConfig::at_input_width`]);
    /// [`FlowEstimator::config`] returns them scaled.
    pub fn new(cfg: FlowConfig, width: usize, height: usize) -> Result<Self, FlowError> {
        validate(&cfg)?;
        let cfg = cfg.at_input_width(width);
        let finest = match cfg.finest_level {
            Some(l) => l,
            None => (0..=MAX_FINEST_LEVEL)
                .take_while(|&l| {
                    (width >> l) * (height >> l) >= cfg.finest_min_pixels && cfg.output_factor % (1 << l) == 0
                })
                .last()
                .unwrap_or(0),
        };
        let finest_cell = 1usize << finest;
        if cfg.output_factor < finest_cell || cfg.output_factor % finest_cell != 0 {
            return Err(FlowError::Config { field: "output_factor", problem: "must be a multiple of 2^finest_level" });
        }
        let p = cfg.patch_size;
        let fits = |l: usize| (width >> l).min(height >> l) >= MIN_LEVEL_PATCHES * p;
        let too_small = |l: usize| FlowError::TooSmall {
            width,
            height,
            level: l,
            level_w: width >> l,
            level_h: height >> l,
            min_px: MIN_LEVEL_PATCHES * p,
        };
        if !fits(finest) {
            return Err(too_small(finest));
        }
        let coarsest = match cfg.coarsest_level {
            Some(l) if l < finest => {
                return Err(FlowError::Config { field: "coarsest_level", problem: "below finest_level" })
            }
            Some(l) if !fits(l) => return Err(too_small(l)),
            Some(l) => l,
            None => (finest..32).take_while(|&l| fits(l)).last().unwrap_or(finest),
        };
        let start_seeded = match cfg.coarsest_level_seeded {
            Some(l) if l < finest || l > coarsest => {
                return Err(FlowError::Config {
                    field: "coarsest_level_seeded",
                    problem: "outside finest_level..=coarsest level",
                })
            }
            Some(l) => l,
            None => coarsest,
        };
        if (width / cfg.output_factor).min(height / cfg.output_factor) == 0 {
            return Err(too_small(finest));
        }
        let layout = Layout {
            width,
            height,
            feature: cfg.feature,
            normalize_radius: cfg.normalize_radius,
            normalize_eps: cfg.normalize_eps,
            census_eps: cfg.census_eps,
            finest_level: finest,
            coarsest_level: coarsest,
            patch_size: p,
            patch_stride: cfg.patch_stride,
            noise_sigma: cfg.noise_sigma,
            texture_sigma_px: cfg.texture_sigma_px,
            texture_radius: cfg.texture_radius,
        };
        let geoms: Vec<LevelGeom> = (0..=coarsest)
            .map(|l| {
                if l < finest {
                    LevelGeom::default()
                } else {
                    LevelGeom::new(width >> l, height >> l, p, cfg.patch_stride)
                }
            })
            .collect();
        let flows = || -> Vec<LevelFlow> {
            (0..=coarsest)
                .map(|l| {
                    let n = if l < finest { 0 } else { (width >> l) * (height >> l) };
                    LevelFlow { dx: vec![0.0; n], dy: vec![0.0; n] }
                })
                .collect()
        };
        let max_patches = geoms.iter().map(LevelGeom::patch_count).max().unwrap_or(0);
        let (fw, fh) = (width >> finest, height >> finest);
        let cells = fh * fw.div_ceil(2);
        let n0 = width * height;
        Ok(FlowEstimator {
            fwd: flows(),
            bwd: flows(),
            patch_flow: vec![[0.0; 2]; max_patches],
            refine: RefineScratch {
                weight_sum: vec![0.0; fw * fh],
                coeff: vec![[0.0; 8]; fw * fh],
                cells: [vec![[0.0; 10]; cells], vec![[0.0; 10]; cells]],
                u: [vec![0.0; cells], vec![0.0; cells]],
                v: [vec![0.0; cells], vec![0.0; cells]],
            },
            prep: PrepScratch {
                a: vec![0.0; n0],
                b: vec![0.0; n0],
                c: vec![0.0; n0],
                d: vec![0.0; n0],
                e: vec![0.0; n0],
                f: vec![0.0; n0],
            },
            cfg,
            layout,
            geoms,
            start_unseeded: coarsest,
            start_seeded,
        })
    }

    /// The configuration in use, its reference-pixel thresholds in this input's pixels.
    pub fn config(&self) -> &FlowConfig {
        &self.cfg
    }
    /// Input size this estimator was built for.
    pub fn size(&self) -> (usize, usize) {
        (self.layout.width, self.layout.height)
    }
    /// Finest level computed (the full output's grid has cells of `2^finest_level` pixels).
    pub fn finest_level(&self) -> usize {
        self.layout.finest_level
    }
    /// Coarsest level used without a seed.
    pub fn coarsest_level(&self) -> usize {
        self.start_unseeded
    }
    /// Level an estimate starts from with a seed.
    pub fn coarsest_level_seeded(&self) -> usize {
        self.start_seeded
    }
    /// Size of the finest-level grid (the full output).
    pub fn finest_size(&self) -> (usize, usize) {
        let l = self.layout.finest_level;
        (self.layout.width >> l, self.layout.height >> l)
    }
    /// Size of the pooled grid.
    pub fn pooled_size(&self) -> (usize, usize) {
        (self.layout.width / self.cfg.output_factor, self.layout.height / self.cfg.output_factor)
    }

    /// Allocates a frame for [`FlowEstimator::prepare_into`].
    pub fn new_frame(&self) -> PreparedFrame {
        let (w, h) = (self.layout.width, self.layout.height);
        let c = self.cfg.feature.channels();
        let levels = (0..=self.start_unseeded)
            .map(|l| {
                let (lw, lh) = (w >> l, h >> l);
                let featured = l >= self.layout.finest_level;
                let n = if featured { lw * lh } else { 0 };
                PreparedLevel {
                    w: lw,
                    h: lh,
                    image: vec![0.0; lw * lh],
                    feat: vec![0.0; n * c],
                    grad_x: vec![0.0; n * c],
                    grad_y: vec![0.0; n * c],
                    patches: vec![PatchData::default(); self.geoms[l].patch_count()],
                }
            })
            .collect();
        let (fw, fh) = self.finest_size();
        PreparedFrame { layout: self.layout, levels, texture_x: vec![0.0; fw * fh], texture_y: vec![0.0; fw * fh] }
    }

    /// Allocates a result for [`FlowEstimator::estimate`].
    pub fn new_result(&self) -> FlowResult {
        let (fw, fh) = self.finest_size();
        let (pw, ph) = self.pooled_size();
        let cell = 1 << self.layout.finest_level;
        FlowResult {
            flow: FlowField::zeros(fw, fh, cell),
            backward: FlowField::zeros(fw, fh, cell),
            weight_x: PlaneF32::new(fw, fh),
            weight_y: PlaneF32::new(fw, fh),
            fb_error: PlaneF32::new(fw, fh),
            residual: PlaneF32::new(fw, fh),
            pooled: PooledFlow {
                flow: FlowField::zeros(pw, ph, self.cfg.output_factor),
                weight_x: PlaneF32::new(pw, ph),
                weight_y: PlaneF32::new(pw, ph),
            },
            stats: FlowStats::default(),
        }
    }

    /// Builds a prepared frame (allocating); see [`FlowEstimator::prepare_into`].
    pub fn prepare(&mut self, image: &PlaneF32) -> Result<PreparedFrame, FlowError> {
        let mut frame = self.new_frame();
        self.prepare_into(image, &mut frame)?;
        Ok(frame)
    }

    /// Builds pyramid, features, gradients, patch tables and texture weights of a grey image
    /// (intensity in [0, 1]) into `frame`, without allocating.
    pub fn prepare_into(&mut self, image: &PlaneF32, frame: &mut PreparedFrame) -> Result<(), FlowError> {
        let (w, h) = (self.layout.width, self.layout.height);
        if image.width != w || image.height != h {
            return Err(FlowError::SizeMismatch {
                what: "image",
                expected_w: w,
                expected_h: h,
                found_w: image.width,
                found_h: image.height,
            });
        }
        if frame.layout != self.layout {
            return Err(FlowError::ForeignFrame { what: "frame to prepare" });
        }
        if let Some(i) = image.data.iter().position(|v| !v.is_finite()) {
            return Err(FlowError::NonFinite { what: "image", x: i % w, y: i / w, value: image.data[i] });
        }
        let _span = tracing::trace_span!("track.flow.prepare", width = w, height = h).entered();
        match self.cfg.feature.channels() {
            1 => pyramid::prepare::<1>(&self.cfg, &self.layout, &self.geoms, image, frame, &mut self.prep),
            _ => pyramid::prepare::<4>(&self.cfg, &self.layout, &self.geoms, image, frame, &mut self.prep),
        }
        Ok(())
    }

    /// Estimates the flow `src -> dst` (and back), starting from `seed` (src -> dst, any grid
    /// over the input; `None` for zero), into `out`. Never allocates.
    pub fn estimate(
        &mut self,
        src: &PreparedFrame,
        dst: &PreparedFrame,
        seed: Option<&FlowField>,
        out: &mut FlowResult,
    ) -> Result<(), FlowError> {
        self.estimate_with(src, dst, seed, out, self.cfg.forward_backward)
    }

    /// [`estimate`](Self::estimate) with the forward-backward check on or off for this call
    /// only, whatever the configuration says (off: the backward pass is not run, half the
    /// cost, and the confidences have no forward-backward term). Never allocates.
    pub fn estimate_with(
        &mut self,
        src: &PreparedFrame,
        dst: &PreparedFrame,
        seed: Option<&FlowField>,
        out: &mut FlowResult,
        forward_backward: bool,
    ) -> Result<(), FlowError> {
        let (w, h) = (self.layout.width, self.layout.height);
        let _span = tracing::debug_span!("track.flow", width = w, height = h, seeded = seed.is_some()).entered();
        self.check_inputs(src, dst, seed, out)?;
        let start = self.run_passes(src, dst, seed, forward_backward);
        let finest = self.layout.finest_level;
        if forward_backward {
            out.backward.dx.data.copy_from_slice(&self.bwd[finest].dx);
            out.backward.dy.data.copy_from_slice(&self.bwd[finest].dy);
        } else {
            out.backward.dx.data.fill(0.0);
            out.backward.dy.data.fill(0.0);
        }
        out.flow.dx.data.copy_from_slice(&self.fwd[finest].dx);
        out.flow.dy.data.copy_from_slice(&self.fwd[finest].dy);
        finish(&self.cfg, forward_backward, finest, start, src, dst, out);
        Ok(())
    }

    /// Estimates both directions of an edge from the same two passes: `src -> dst` into `out`
    /// and `dst -> src` into `out_reverse` (the backward pass of the forward-backward check is
    /// the reverse edge's forward flow, and the forward pass its check), each with its own
    /// confidences. Half the cost of two [`estimate`](Self::estimate) calls; the reverse
    /// direction's seed is the inverted `seed`. Without `forward_backward` both passes still
    /// run (each direction then has no forward-backward term). Never allocates.
    pub fn estimate_pair(
        &mut self,
        src: &PreparedFrame,
        dst: &PreparedFrame,
        seed: Option<&FlowField>,
        out: &mut FlowResult,
        out_reverse: &mut FlowResult,
    ) -> Result<(), FlowError> {
        let (w, h) = (self.layout.width, self.layout.height);
        let _span = tracing::debug_span!("track.flow.pair", width = w, height = h, seeded = seed.is_some()).entered();
        self.check_inputs(src, dst, seed, out)?;
        self.check_result(out_reverse)?;
        let start = self.run_passes(src, dst, seed, true);
        let finest = self.layout.finest_level;
        out.flow.dx.data.copy_from_slice(&self.fwd[finest].dx);
        out.flow.dy.data.copy_from_slice(&self.fwd[finest].dy);
        out.backward.dx.data.copy_from_slice(&self.bwd[finest].dx);
        out.backward.dy.data.copy_from_slice(&self.bwd[finest].dy);
        out_reverse.flow.dx.data.copy_from_slice(&self.bwd[finest].dx);
        out_reverse.flow.dy.data.copy_from_slice(&self.bwd[finest].dy);
        out_reverse.backward.dx.data.copy_from_slice(&self.fwd[finest].dx);
        out_reverse.backward.dy.data.copy_from_slice(&self.fwd[finest].dy);
        let fb = self.cfg.forward_backward;
        finish(&self.cfg, fb, finest, start, src, dst, out);
        finish(&self.cfg, fb, finest, start, dst, src, out_reverse);
        Ok(())
    }

    /// A cheap look at an edge before paying for [`estimate`](Self::estimate): both passes run
    /// from the start level down to `level` only (the loop search asks for one above the
    /// finest: no variational refinement, a quarter of the finest level's pixels), then
    /// [`FlowScreen`] summarises the flow there with the estimate's photometric and
    /// forward-backward weights, averaged over the output grid's cells. The loop search rejects most
    /// candidates with it. Never allocates.
    pub fn screen(
        &mut self,
        src: &PreparedFrame,
        dst: &PreparedFrame,
        seed: Option<&FlowField>,
        level: usize,
        confident_weight: f32,
    ) -> Result<FlowScreen, FlowError> {
        let start = if seed.is_some() { self.start_seeded } else { self.start_unseeded };
        if level < self.layout.finest_level || level > start || self.cfg.output_factor % (1 << level) != 0 {
            return Err(FlowError::Config {
                field: "screen level",
                problem: "must lie between the finest and the start level, with 2^level dividing output_factor",
            });
        }
        let (w, h) = (self.layout.width, self.layout.height);
        let _span = tracing::debug_span!("track.flow.screen", width = w, height = h, level).entered();
        for (frame, what) in [(src, "src"), (dst, "dst")] {
            if frame.layout != self.layout {
                return Err(FlowError::ForeignFrame { what });
            }
        }
        if let Some(s) = seed {
            check_seed(s, w, h)?;
        }
        self.run_passes_to(src, dst, seed, true, level);
        let (fwd, bwd) = (&self.fwd[level], &self.bwd[level]);
        let c = self.cfg.feature.channels();
        let (s, d) = (&src.levels[level], &dst.levels[level]);
        let (flow, back) = ((&fwd.dx[..], &fwd.dy[..]), (&bwd.dx[..], &bwd.dy[..]));
        Ok(match c {
            1 => confidence::screen::<1>(&self.cfg, level, s, d, flow, back, confident_weight),
            _ => confidence::screen::<4>(&self.cfg, level, s, d, flow, back, confident_weight),
        })
    }

    fn check_inputs(&self, src: &PreparedFrame, dst: &PreparedFrame, seed: Option<&FlowField>, out: &FlowResult) -> Result<(), FlowError> {
        let (w, h) = (self.layout.width, self.layout.height);
        for (frame, what) in [(src, "src"), (dst, "dst")] {
            if frame.layout.width != w || frame.layout.height != h {
                return Err(FlowError::SizeMismatch {
                    what,
                    expected_w: w,
                    expected_h: h,
                    found_w: frame.layout.width,
                    found_h: frame.layout.height,
                });
            }
            if frame.layout != self.layout {
                return Err(FlowError::ForeignFrame { what });
            }
        }
        self.check_result(out)?;
        if let Some(s) = seed {
            check_seed(s, w, h)?;
        }
        Ok(())
    }

    /// The forward pass (and the backward one with `backward`) into `fwd` / `bwd`; returns the
    /// start level.
    fn run_passes(&mut self, src: &PreparedFrame, dst: &PreparedFrame, seed: Option<&FlowField>, backward: bool) -> usize {
        self.run_passes_to(src, dst, seed, backward, self.layout.finest_level)
    }

    /// [`run_passes`](Self::run_passes) stopping at level `stop` (>= the finest level).
    fn run_passes_to(&mut self, src: &PreparedFrame, dst: &PreparedFrame, seed: Option<&FlowField>, backward: bool, stop: usize) -> usize {
        let start = if seed.is_some() { self.start_seeded } else { self.start_unseeded };
        let (fwd_seed, bwd_seed) = match seed {
            Some(s) => (SeedView::Forward(s), SeedView::Backward(s)),
            None => (SeedView::None, SeedView::None),
        };
        let finest = self.layout.finest_level;
        let FlowEstimator { cfg, geoms, fwd, bwd, patch_flow, refine, .. } = self;
        let cfg = &*cfg;
        let run = |a: &PreparedFrame,
                   b: &PreparedFrame,
                   s,
                   flows: &mut [LevelFlow],
                   pf: &mut [[f32; 2]],
                   rs: &mut RefineScratch| {
            match cfg.feature.channels() {
                1 => run_direction::<1>(cfg, geoms, a, b, s, finest, stop, start, flows, pf, rs),
                _ => run_direction::<4>(cfg, geoms, a, b, s, finest, stop, start, flows, pf, rs),
            }
        };
        run(src, dst, fwd_seed, fwd, patch_flow, refine);
        if backward {
            run(dst, src, bwd_seed, bwd, patch_flow, refine);
        }
        start
    }

    fn check_result(&self, out: &FlowResult) -> Result<(), FlowError> {
        let (fw, fh) = self.finest_size();
        let (pw, ph) = self.pooled_size();
        let planes = [
            (&out.flow.dx, fw, fh),
            (&out.flow.dy, fw, fh),
            (&out.backward.dx, fw, fh),
            (&out.backward.dy, fw, fh),
            (&out.weight_x, fw, fh),
            (&out.weight_y, fw, fh),
            (&out.fb_error, fw, fh),
            (&out.residual, fw, fh),
            (&out.pooled.flow.dx, pw, ph),
            (&out.pooled.flow.dy, pw, ph),
            (&out.pooled.weight_x, pw, ph),
            (&out.pooled.weight_y, pw, ph),
        ];
        for (p, ew, eh) in planes {
            if p.width != ew || p.height != eh || p.data.len() != ew * eh {
                return Err(FlowError::SizeMismatch {
                    what: "result",
                    expected_w: ew,
                    expected_h: eh,
                    found_w: p.width,
                    found_h: p.height,
                });
            }
        }
        let cells =
            [(out.flow.cell_px, 1 << self.layout.finest_level), (out.pooled.flow.cell_px, self.cfg.output_factor)];
        for (found, expected) in cells {
            if found != expected {
                return Err(FlowError::ResultCell { expected_px: expected, found_px: found });
            }
        }
        Ok(())
    }
}

/// Confidences, pooling and stats of `out` (its `flow` and `backward` filled) for `src -> dst`.
fn finish(cfg: &FlowConfig, forward_backward: bool, finest: usize, start: usize, src: &PreparedFrame, dst: &PreparedFrame, out: &mut FlowResult) {
    match cfg.feature.channels() {
        1 => confidence::weights::<1>(cfg, forward_backward, finest, &src.levels[finest], &dst.levels[finest], src, dst, out),
        _ => confidence::weights::<4>(cfg, forward_backward, finest, &src.levels[finest], &dst.levels[finest], src, dst, out),
    }
    confidence::pool(cfg, finest, out);
    out.stats = confidence::stats(out, start);
    tracing::trace!(
        start_level = out.stats.start_level,
        mean_weight = out.stats.mean_weight,
        in_view = out.stats.in_view_fraction,
        mean_flow_px = out.stats.mean_flow_input_px,
        "flow estimated"
    );
}

impl FlowConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), FlowError> {
        validate(self)
    }
}

fn validate(cfg: &FlowConfig) -> Result<(), FlowError> {
    let bad = |field, problem| Err(FlowError::Config { field, problem });
    if !(4..=32).contains(&cfg.patch_size) {
        return bad("patch_size", "must be in 4..=32");
    }
    if cfg.patch_stride == 0 || cfg.patch_stride > cfg.patch_size {
        return bad("patch_stride", "must be in 1..=patch_size");
    }
    if cfg.finest_level.is_some_and(|l| l > MAX_FINEST_LEVEL) {
        return bad("finest_level", "must be at most 4");
    }
    if cfg.output_factor == 0 {
        return bad("output_factor", "must be positive");
    }
    let positive = [
        ("normalize_eps", cfg.normalize_eps),
        ("census_eps", cfg.census_eps),
        ("densify_eps", cfg.densify_eps),
        ("refine_data_eps", cfg.refine_data_eps),
        ("refine_smooth_eps", cfg.refine_smooth_eps),
        ("noise_sigma", cfg.noise_sigma),
        ("texture_sigma_px", cfg.texture_sigma_px),
        ("residual_sigma", cfg.residual_sigma),
        ("fb_sigma_px", cfg.fb_sigma_px),
        ("fb_max_px", cfg.fb_max_px),
        ("pool_spread_px", cfg.pool_spread_px),
    ];
    for (field, v) in positive {
        if !(v.is_finite() && v > 0.0) {
            return bad(field, "must be finite and positive");
        }
    }
    if !(cfg.refine_smoothness.is_finite() && cfg.refine_smoothness >= 0.0) {
        return bad("refine_smoothness", "must be finite and non-negative");
    }
    if !(cfg.patch_min_step_px.is_finite() && cfg.patch_min_step_px >= 0.0) {
        return bad("patch_min_step_px", "must be finite and non-negative");
    }
    Ok(())
}

fn check_seed(seed: &FlowField, width: usize, height: usize) -> Result<(), FlowError> {
    let c = seed.cell_px.max(1);
    let (ew, eh) = (width / c, height / c);
    if seed.cell_px == 0 || seed.width() != ew || seed.height() != eh || ew == 0 || eh == 0 {
        return Err(FlowError::SeedGrid {
            cell_px: seed.cell_px,
            width,
            height,
            expected_w: ew,
            expected_h: eh,
            found_w: seed.width(),
            found_h: seed.height(),
        });
    }
    for (plane, what) in [(&seed.dx, "seed dx"), (&seed.dy, "seed dy")] {
        if plane.data.len() != ew * eh {
            return Err(FlowError::SeedGrid {
                cell_px: seed.cell_px,
                width,
                height,
                expected_w: ew,
                expected_h: eh,
                found_w: plane.width,
                found_h: plane.height,
            });
        }
        if let Some(i) = plane.data.iter().position(|v| !v.is_finite()) {
            return Err(FlowError::NonFinite { what, x: i % ew, y: i / ew, value: plane.data[i] });
        }
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn run_direction<const C: usize>(
    cfg: &FlowConfig,
    geoms: &[LevelGeom],
    src: &PreparedFrame,
    dst: &PreparedFrame,
    seed: SeedView<'_>,
    finest: usize,
    stop: usize,
    start: usize,
    flows: &mut [LevelFlow],
    patch_flow: &mut [[f32; 2]],
    refine: &mut RefineScratch,
) {
    for level in (stop..=start).rev() {
        let geom = &geoms[level];
        let (lower, upper) = flows.split_at_mut(level + 1);
        let flow = &mut lower[level];
        if level == start {
            fill_from_seed(geom, seed, level, flow);
        } else {
            upsample(&upper[0], &geoms[level + 1], flow, geom);
        }
        let (s, d) = (&src.levels[level], &dst.levels[level]);
        let pf = &mut patch_flow[..geom.patch_count()];
        // At the start level the initial field is the seed itself: no second candidate.
        let candidate = if level == start { SeedView::None } else { seed };
        search::search_patches::<C>(cfg, geom, s, d, flow, candidate, level, pf);
        search::densify::<C>(cfg, geom, s, d, pf, flow, &mut refine.weight_sum);
        if level < finest + cfg.refine_levels {
            refine::refine::<C>(cfg, geom, s, d, flow, refine);
        }
    }
}

fn fill_from_seed(geom: &LevelGeom, seed: SeedView<'_>, level: usize, flow: &mut LevelFlow) {
    let w = geom.w;
    flow.dx.par_chunks_mut(w).zip(flow.dy.par_chunks_mut(w)).enumerate().for_each(|(y, (rx, ry))| {
        for x in 0..w {
            let (u, v) = seed.at(level, x as f32, y as f32).unwrap_or((0.0, 0.0));
            rx[x] = u;
            ry[x] = v;
        }
    });
}

/// Coarse field (level l + 1) to fine (level l): bilinear at the matching coordinate, times two.
fn upsample(coarse: &LevelFlow, cg: &LevelGeom, fine: &mut LevelFlow, fg: &LevelGeom) {
    let w = fg.w;
    fine.dx.par_chunks_mut(w).zip(fine.dy.par_chunks_mut(w)).enumerate().for_each(|(y, (rx, ry))| {
        let cy = (y as f32 - 0.5) * 0.5;
        for x in 0..w {
            let cx = (x as f32 - 0.5) * 0.5;
            let (x0, y0, ax, ay) = bilinear_cell(cg.w, cg.h, cx, cy);
            rx[x] = 2.0 * bilinear_at(&coarse.dx, cg.w, x0, y0, ax, ay);
            ry[x] = 2.0 * bilinear_at(&coarse.dy, cg.w, x0, y0, ax, ay);
        }
    });
}

/// Top-left cell and fractions of a bilinear lookup at `(x, y)`, clamped to the grid
/// (`w`, `h` >= 1; a one-pixel side degenerates to nearest).
#[inline(always)]
pub(crate) fn bilinear_cell(w: usize, h: usize, x: f32, y: f32) -> (usize, usize, f32, f32) {
    let xc = x.clamp(0.0, (w - 1) as f32);
    let yc = y.clamp(0.0, (h - 1) as f32);
    let x0 = (xc as usize).min(w.saturating_sub(2));
    let y0 = (yc as usize).min(h.saturating_sub(2));
    (x0, y0, (xc - x0 as f32).min(1.0), (yc - y0 as f32).min(1.0))
}

/// Bilinear value of a single-channel plane at a cell from [`bilinear_cell`].
#[inline(always)]
pub(crate) fn bilinear_at(data: &[f32], w: usize, x0: usize, y0: usize, ax: f32, ay: f32) -> f32 {
    let i = y0 * w + x0;
    let x1 = if ax > 0.0 { 1 } else { 0 };
    let y1 = if ay > 0.0 { w } else { 0 };
    let top = data[i] + ax * (data[i + x1] - data[i]);
    let bottom = data[i + y1] + ax * (data[i + y1 + x1] - data[i + y1]);
    top + ay * (bottom - top)
}

/// Bilinear value of `N` interleaved channels at a cell from [`bilinear_cell`].
#[inline(always)]
pub(crate) fn bilinear_n<const N: usize>(data: &[f32], w: usize, x0: usize, y0: usize, ax: f32, ay: f32) -> [f32; N] {
    let i = (y0 * w + x0) * N;
    let dx = if ax > 0.0 { N } else { 0 };
    let dy = if ay > 0.0 { w * N } else { 0 };
    let (w00, w10, w01, w11) = ((1.0 - ax) * (1.0 - ay), ax * (1.0 - ay), (1.0 - ax) * ay, ax * ay);
    let mut out = [0.0; N];
    for (c, o) in out.iter_mut().enumerate() {
        *o = w00 * data[i + c] + w10 * data[i + dx + c] + w01 * data[i + dy + c] + w11 * data[i + dy + dx + c];
    }
    out
}
