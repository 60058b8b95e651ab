//! CPU reference of the 3D Gaussian splatting renderer with the underwater medium (paper
//! §3.2, Eq. 6-9 and 11), forward and backward: the oracle the GPU kernels are tested against.
//!
//! # Stages (one function each, the loop shape of its kernel)
//! 1. [`project_gaussians`] (`map.project`, per Gaussian): EWA projection, SH colour, reach.
//! 2. [`exclusive_scan`] + [`emit_intersections`] (`map.bin`, per Gaussian): tile binning into
//!    a fixed intersection buffer; overflow is reported with the size needed.
//! 3. [`radix_sort_pairs`] (`map.sort`): `(tile << 32 | depth bits)` keys.
//! 4. [`tile_ranges`], [`gather_sorted_gaussians`], [`invert_permutation`] (`map.tiles`).
//! 5. [`rasterize_forward`] (`map.raster_fwd`, per tile / pixel).
//! 6. [`rasterize_backward`] + [`reduce_isect_grads`] (`map.raster_bwd`, per tile / pixel,
//!    then per Gaussian).
//! 7. [`project_backward`] (`map.project_bwd`, per Gaussian).
//!
//! [`RasterWorkspace`] owns every buffer (allocated once from a [`RasterCapacity`]) and runs
//! the stages: [`RasterWorkspace::forward`] then [`RasterWorkspace::backward`]. The per-pixel
//! and per-Gaussian maths is generic over [`Real`]; [`mod@reference`] instantiates it in f64
//! without tiles, sorting or capacities, for the gradient checks.
//!
//! # Image formation (per pixel, per channel)
//! Over the Gaussians `n = 1..N` blended at the pixel, in depth order, with
//! `alpha_n = min(0.99, o_n exp(-d^T Sigma_2d^-1 d / 2))` (skipped below 1/255),
//! `T_n = prod_{m<n} (1 - alpha_m)`, `w_n = T_n alpha_n`, range `t_n = z_n |(xn, yn, 1)|`:
//!
//! ```text
//! C = sum_n T_n alpha_n c_n e^{-sigma_att t_n}
//!   + sum_n T_n c_med (e^{-sigma_bs t_{n-1}} - e^{-sigma_bs t_n})  + T_{N+1} c_med e^{-sigma_bs t_N}
//!   = c_med + sum_n w_n (c_n e^{-sigma_att t_n} - c_med e^{-sigma_bs t_n})          (t_0 = 0)
//! ```
//!
//! (the backscatter sum telescopes: every Gaussian hides the medium light from behind it).
//! One opaque layer at range `r` gives `J e^{-sigma_att r} + c_med (1 - e^{-sigma_bs r})`, the
//! image formation model with `beta_D = sigma_att`, `beta_B = sigma_bs`, `B_inf = c_med`; no
//! Gaussian gives `c_med`. Also rendered: the restored colour `sum_n w_n c_n`, the depth
//! `D = sum_n w_n d_n / sum_n w_n` (Eq. 11; `d_n = 1/z_n` by default, [`DepthMode`]), the depth
//! variance `V = sum_n w_n (d_n - D)^2 / sum_n w_n` and the alpha `sum_n w_n`. Blending stops
//! before a Gaussian that would bring the transmittance below 1e-4 (3DGS).
//!
//! Depth distribution losses (Eq. 12): a Gaussian KL between the blended depth distribution
//! and `N(D_track, sigma^2)` depends on the blend only through `D` and `V` (and the alpha
//! `W = sum_n w_n`), so an
//! upstream gradient on [`RenderOutput::depth`] and [`RenderOutput::depth_var`] (and
//! [`RenderOutput::alpha`]) is all it needs.
//!
//! # Conventions
//! Camera frame x right, y down, z forward; pixel centres at integer coordinates;
//! `cam_from_world` maps world points into the camera (`p_in_cam = cam_from_world * p_in_world`).
//! The camera must be undistorted. Tiles are [`TILE_SIZE`] pixels square.

mod bin;
mod math;
mod project;
mod project_bwd;
mod raster_bwd;
mod raster_fwd;
pub mod reference;
mod sort;
mod tiles;
mod workspace;

pub use bin::{emit_intersections, exclusive_scan, isect_key, isect_key_bits, key_tile, scan_blocks, DEPTH_KEY_BITS, SCAN_BLOCK};
pub use math::{quat_to_mat3, sigmoid};
pub use project::{project_gaussians, project_splat, tile_rect, ProjectedSplat, ProjectionSetup, TileRect};
pub use project_bwd::{project_backward, project_splat_backward};
pub use raster_bwd::{backprop_pixel, rasterize_backward, reduce_isect_grads, PixelState, PixelUpstream, SplatGrad, MAX_DENSIFY_EXPONENT};
pub use raster_fwd::{blend_pixel, depth_value, rasterize_forward, PixelForward, PixelMedium, PixelRay, RasterInputs};
pub use sort::{bits_for, radix_sort_pairs, sort_histogram_len, RADIX, RADIX_BITS, SORT_BLOCK};
pub use tiles::{gather_sorted_gaussians, invert_permutation, tile_ranges};
pub use workspace::{RasterWorkspace, RenderStats};
pub(crate) use workspace::{check_backward_inputs, check_output, check_rgb, check_size, validate_gaussians};

use duv_core::{CameraModelError, ImageRgbF32, PlaneF32};

/// Tile edge in pixels (the rasteriser workgroup is `TILE_SIZE^2` threads).
pub const TILE_SIZE: usize = 16;
/// Alphas below this are skipped (1/255).
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Alphas are clamped to this.
pub const ALPHA_MAX: f64 = 0.99;
/// Blending stops before the transmittance would fall below this.
pub const T_MIN: f64 = 1e-4;

/// Why a render could not run. Bad input is reported here (naming the Gaussian or pixel),
/// never by a panic.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RenderError {
    #[error("image is {width}x{height}: nothing to render")]
    EmptyImage { width: usize, height: usize },
    #[error("{what} is {width}x{height}, expected {expected_width}x{expected_height}")]
    SizeMismatch { what: &'static str, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("{what}: {requested} requested, the workspace holds {capacity}")]
    CapacityExceeded { what: &'static str, requested: usize, capacity: usize },
    #[error("tile intersections overflow: {needed} needed, the workspace holds {capacity}")]
    TileOverflow { needed: u64, capacity: usize },
    #[error("Gaussian map is full ({capacity} Gaussians)")]
    GaussianCapacity { capacity: usize },
    #[error("Gaussian {index}: {field} has a non-finite value")]
    NonFiniteGaussian { index: usize, field: &'static str },
    #[error("Gaussian {index}: rotation quaternion has zero norm")]
    ZeroRotation { index: usize },
    #[error("{what} at pixel ({x}, {y}) channel {channel}: {value} {why}")]
    BadPixel { what: &'static str, x: usize, y: usize, channel: usize, value: f32, why: &'static str },
    #[error("camera must be undistorted (use PinholeCamera::undistorted on rectified images)")]
    DistortedCamera,
    #[error("camera is invalid: {0}")]
    BadCamera(#[from] CameraModelError),
    #[error("cam_from_world has a non-finite value")]
    NonFinitePose,
    #[error("backward without a matching forward: {why}")]
    NoForward { why: &'static str },
    #[error("gradient buffers hold {grads} Gaussians, the map {gaussians} (call GaussianGrads::reset)")]
    GradLenMismatch { grads: usize, gaussians: usize },
    #[error("render config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
}

/// Which per-Gaussian depth `d_n` is blended into the rendered depth (Eq. 11).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthMode {
    /// `d_n = 1/z_n` (1/m), the paper's default.
    #[default]
    InverseDepth,
    /// `d_n = z_n` (m).
    Depth,
}

/// Rendering settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderConfig {
    /// Depth blended into [`RenderOutput::depth`]: inverse depth (default) or depth.
    pub depth_mode: DepthMode,
    /// Gaussians whose mean is nearer than this camera depth (m) are culled.
    pub near_z_m: f32,
    /// Added to the diagonal of every 2D covariance (px^2): the 3DGS low-pass filter.
    pub cov2d_blur_px2: f32,
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig { depth_mode: DepthMode::InverseDepth, near_z_m: 0.01, cov2d_blur_px2: 0.3 }
    }
}

impl RenderConfig {
    pub fn validate(&self) -> Result<(), RenderError> {
        if !(self.near_z_m.is_finite() && self.near_z_m > 0.0) {
            return Err(RenderError::InvalidConfig { field: "near_z_m", value: self.near_z_m as f64, why: "must be finite and > 0" });
        }
        if !(self.cov2d_blur_px2.is_finite() && self.cov2d_blur_px2 >= 0.0) {
            return Err(RenderError::InvalidConfig {
                field: "cov2d_blur_px2",
                value: self.cov2d_blur_px2 as f64,
                why: "must be finite and >= 0",
            });
        }
        Ok(())
    }
}

/// Image size and its tiling.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    pub width: usize,
    pub height: usize,
    pub tile_size: usize,
    pub tiles_x: usize,
    pub tiles_y: usize,
}

impl TileGrid {
    pub fn new(width: usize, height: usize) -> Self {
        TileGrid { width, height, tile_size: TILE_SIZE, tiles_x: width.div_ceil(TILE_SIZE), tiles_y: height.div_ceil(TILE_SIZE) }
    }
    pub fn num_tiles(&self) -> usize {
        self.tiles_x * self.tiles_y
    }
}

/// Per-pixel medium parameters, one RGB image each (row-major, channels interleaved), as the
/// medium field predicts them per ray (Eq. 10). Inputs of the forward pass, and the same
/// layout for their gradients from the backward pass.
#[derive(Clone, Debug, PartialEq)]
pub struct MediumPlanes {
    /// Veiling light / backscatter colour `c_med` (`B_inf`), nominally in [0, 1].
    pub c_med: ImageRgbF32,
    /// Attenuation of the direct signal, `sigma_att` (`beta_D`), 1/m, >= 0.
    pub sigma_att: ImageRgbF32,
    /// Attenuation governing the backscatter, `sigma_bs` (`beta_B`), 1/m, >= 0.
    pub sigma_bs: ImageRgbF32,
}

impl MediumPlanes {
    /// All zeros.
    pub fn new(width: usize, height: usize) -> Self {
        MediumPlanes {
            c_med: ImageRgbF32::new(width, height),
            sigma_att: ImageRgbF32::new(width, height),
            sigma_bs: ImageRgbF32::new(width, height),
        }
    }
    /// The same parameters at every pixel.
    pub fn uniform(width: usize, height: usize, c_med: [f32; 3], sigma_att: [f32; 3], sigma_bs: [f32; 3]) -> Self {
        MediumPlanes {
            c_med: ImageRgbF32::filled(width, height, c_med),
            sigma_att: ImageRgbF32::filled(width, height, sigma_att),
            sigma_bs: ImageRgbF32::filled(width, height, sigma_bs),
        }
    }
    pub fn width(&self) -> usize {
        self.c_med.width
    }
    pub fn height(&self) -> usize {
        self.c_med.height
    }
    pub fn pixel(&self, x: usize, y: usize) -> PixelMedium<f32> {
        PixelMedium { c_med: self.c_med.pixel(x, y), sigma_att: self.sigma_att.pixel(x, y), sigma_bs: self.sigma_bs.pixel(x, y) }
    }
    pub(crate) fn planes(&self) -> [(&'static str, &ImageRgbF32); 3] {
        [("c_med", &self.c_med), ("sigma_att", &self.sigma_att), ("sigma_bs", &self.sigma_bs)]
    }
}

/// What the forward pass renders (allocate once with [`RenderOutput::new`] and reuse).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOutput {
    /// The underwater image `C` (Eq. 6-9).
    pub colour: ImageRgbF32,
    /// The restored image `sum w_n c_n`: no attenuation, no backscatter.
    pub restored: ImageRgbF32,
    /// Blended depth `D` (Eq. 11), 1/m or m by [`DepthMode`]; 0 where nothing was blended.
    pub depth: PlaneF32,
    /// Blended depth variance `V` in the units of `depth` squared.
    pub depth_var: PlaneF32,
    /// Accumulated alpha `sum w_n`.
    pub alpha: PlaneF32,
    /// For the backward pass: object transmittance behind the last blended Gaussian.
    pub final_t: PlaneF32,
    /// For the backward pass: one past the last blended sorted intersection, per pixel.
    pub isect_end: Vec<u32>,
}

impl RenderOutput {
    pub fn new(width: usize, height: usize) -> Self {
        RenderOutput {
            colour: ImageRgbF32::new(width, height),
            restored: ImageRgbF32::new(width, height),
            depth: PlaneF32::new(width, height),
            depth_var: PlaneF32::new(width, height),
            alpha: PlaneF32::new(width, height),
            final_t: PlaneF32::new(width, height),
            isect_end: vec![0; width * height],
        }
    }
    pub fn width(&self) -> usize {
        self.colour.width
    }
    pub fn height(&self) -> usize {
        self.colour.height
    }
}

/// Upstream gradients of the loss with respect to each rendered output, same layouts as
/// [`RenderOutput`] (zero where a loss does not use an output).
#[derive(Clone, Debug, PartialEq)]
pub struct RenderUpstream {
    /// `dL/dC`, RGB.
    pub colour: ImageRgbF32,
    /// `dL/d restored`, RGB.
    pub restored: ImageRgbF32,
    /// `dL/dD`.
    pub depth: PlaneF32,
    /// `dL/dV`.
    pub depth_var: PlaneF32,
    /// `dL/d alpha`.
    pub alpha: PlaneF32,
}

impl RenderUpstream {
    /// All zeros.
    pub fn new(width: usize, height: usize) -> Self {
        RenderUpstream {
            colour: ImageRgbF32::new(width, height),
            restored: ImageRgbF32::new(width, height),
            depth: PlaneF32::new(width, height),
            depth_var: PlaneF32::new(width, height),
            alpha: PlaneF32::new(width, height),
        }
    }
    pub fn width(&self) -> usize {
        self.colour.width
    }
    pub fn height(&self) -> usize {
        self.colour.height
    }
    /// The upstream gradients at pixel index `i` (row-major).
    #[inline(always)]
    pub fn pixel(&self, i: usize) -> PixelUpstream<f32> {
        let rgb = |d: &[f32]| [d[i * 3], d[i * 3 + 1], d[i * 3 + 2]];
        PixelUpstream {
            colour: rgb(&self.colour.data),
            restored: rgb(&self.restored.data),
            depth: self.depth.data[i],
            depth_var: self.depth_var.data[i],
            alpha: self.alpha.data[i],
        }
    }
}

/// Fixed sizes of a [`RasterWorkspace`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RasterCapacity {
    /// Largest image width and height, pixels.
    pub width: usize,
    pub height: usize,
    /// Largest Gaussian map.
    pub max_gaussians: usize,
    /// Largest number of (tile, Gaussian) intersections per render.
    pub max_intersections: usize,
}
