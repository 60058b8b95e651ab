//! The neural medium (paper Eq. 10, §3.3): a small MLP from a pixel's viewing direction to the
//! medium seen along that ray, constant along the ray.
//!
//! # Network
//! ```text
//! s        unit viewing direction of the pixel's ray, world frame
//! x        = [s, sin(2^k s), cos(2^k s) for k < L]           3 + 6 L inputs (L = pe_frequencies)
//! h1       = softplus(W1 x + b1)                             64
//! h2       = softplus(W2 h1 + b2)                            64
//! c_med    = sigmoid (W_c h2 + b_c)                          3, per colour channel
//! sigma_att= softplus(W_a h2 + b_a)                          3, 1/m
//! sigma_bs = softplus(W_b h2 + b_b)                          3, 1/m
//! ```
//! The frequencies are `2^k` without a factor pi (the NeRF code's convention): at L = 4 the
//! highest one spans about one period across a 60-degree view, so the medium can vary
//! smoothly with direction but cannot paint image detail. The three heads are independent
//! dense layers; they are stored side by side as one 64x9 layer, which is the same function.
//!
//! # Output layout (the renderer's medium input)
//! A 9-channel image ([`MediumPlanes`]), channels in the order `c_med` R G B, `sigma_att`
//! R G B, `sigma_bs` R G B ([`C_MED`], [`SIGMA_ATT`], [`SIGMA_BS`]). The renderer returns its
//! gradient in the same layout, and [`MediumWorkspace::backward`] takes it from there to every
//! weight and bias.
//!
//! # Parameters
//! One flat vector ([`MediumNet::params`]) so that one Adam group covers it; the offsets are in
//! [`MediumLayout`]. A dense layer with `n_in` inputs and `n_out` outputs stores its weight
//! `W[o][i]` at `w[i * n_out + o]` (input-major), so that the forward pass and the weight
//! gradient are whole-row multiply-adds that vectorise. Initialisation is Glorot-uniform from
//! [`MediumConfig::seed`], hidden biases zero; the heads' weights are scaled down by
//! [`MediumConfig::head_init_scale`] and their biases set to the inverse activation of the
//! configured initial water, so the first render sees a plausible, nearly uniform medium.
//!
//! # Loop shape
//! The forward pass is one independent job per pixel (rows in parallel), as the kernel will
//! be. The backward pass recomputes each pixel's activations instead of storing 128 floats
//! per pixel (what a fused GPU kernel does too) and accumulates weight gradients per band of
//! [`BAND_ROWS`] rows into its own slot of the workspace; the bands are then added in a fixed
//! order, so the result does not depend on the thread count.
//!
//! # Coarse direction grid
//! The input depends on the direction only, and the directions of neighbouring pixels differ
//! by a fraction of a degree, so a workspace built with [`MediumWorkspace::with_grid`]
//! evaluates the MLP only on a [`MediumGrid`] of nodes every `step` pixels (node `(i, j)` at
//! pixel `(i step, j step)`, the last node at or past the image border) and interpolates the
//! nine outputs bilinearly in between ([`MediumWorkspace::forward`]). Its backward pass is the
//! exact adjoint of that interpolation (a separable scatter, rows then columns, into the node
//! gradients) followed by the MLP backward on the nodes only. `step = 1` is the exact
//! per-pixel network ([`MediumNet::forward`], the oracle); the mapper's default is
//! [`MediumConfig::grid_step_px`] = 8, about 1/60 of the MLP evaluations.

use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::real::{axpy, dot, logit, softplus_inverse, Real};
use duv_core::rng::Rng;
use duv_core::{CameraModelError, Image, MediumParams, PinholeCamera, Se3};

/// Width of the two hidden layers (paper §3.3).
pub const HIDDEN: usize = 64;
/// Channels of the medium planes.
pub const MEDIUM_CHANNELS: usize = 9;
/// First channel of `c_med` (veiling light, R G B) in [`MediumPlanes`].
pub const C_MED: usize = 0;
/// First channel of `sigma_att` (direct-signal attenuation, 1/m, R G B).
pub const SIGMA_ATT: usize = 3;
/// First channel of `sigma_bs` (backscatter coefficient, 1/m, R G B).
pub const SIGMA_BS: usize = 6;
/// Largest accepted [`MediumConfig::pe_frequencies`].
pub const MAX_PE_FREQUENCIES: usize = 12;
/// Rows per band of the backward pass (one weight-gradient slot per band).
pub const BAND_ROWS: usize = 8;
/// Version of [`MediumCheckpoint`].
pub const MEDIUM_CHECKPOINT_VERSION: u32 = 1;

const MAX_INPUTS: usize = 3 + 6 * MAX_PE_FREQUENCIES;

/// Per-pixel medium planes: `c_med` RGB, `sigma_att` RGB, `sigma_bs` RGB.
pub type MediumPlanes<T = f32> = Image<T, MEDIUM_CHANNELS>;

/// Why the medium network could not be built, evaluated or differentiated. Bad input is
/// reported here, never by a panic.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MediumError {
    #[error("medium config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
    #[error("{what} is {width}x{height}, the camera is {expected_width}x{expected_height}")]
    SizeMismatch { what: &'static str, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("{what} has {len} samples, expected {expected}")]
    LengthMismatch { what: &'static str, len: usize, expected: usize },
    #[error("{what}: value {index} is {value}, not a finite number")]
    NonFinite { what: &'static str, index: usize, value: f64 },
    #[error("world_from_cam has a non-finite value")]
    NonFinitePose,
    #[error("medium camera is invalid: {0}")]
    BadCamera(#[from] CameraModelError),
    #[error("image has {height} rows, the medium workspace was sized for {max_height}")]
    CapacityExceeded { height: usize, max_height: usize },
    #[error("medium checkpoint has schema_version {found}, this build reads {expected}")]
    UnsupportedVersion { found: u32, expected: u32 },
}

/// Shape and initialisation of the medium network. Defaults live in
/// [`MediumConfig::default`] and nowhere else; a config file may give any subset of the fields.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MediumConfig {
    /// Positional-encoding frequencies L (the direction plus sin/cos at `2^k`, k < L); at most 12.
    pub pe_frequencies: usize,
    /// Seed of the deterministic weight initialisation.
    pub seed: u64,
    /// Initial veiling light `c_med` per channel R, G, B, in (0, 1).
    pub init_c_med: [f64; 3],
    /// Initial direct-signal attenuation `sigma_att` per channel, 1/m, > 0.
    pub init_sigma_att: [f64; 3],
    /// Initial backscatter coefficient `sigma_bs` per channel, 1/m, > 0.
    pub init_sigma_bs: [f64; 3],
    /// Factor on the Glorot range of the heads' initial weights (small: the first medium is
    /// the biases' water, nearly the same in every direction); in [0, 1].
    pub head_init_scale: f64,
    /// The mapper evaluates the network on a grid of directions every this many pixels and
    /// interpolates bilinearly (1 = every pixel, exact); 1..=64.
    #[serde(default = "default_grid_step_px")]
    pub grid_step_px: usize,
}

fn default_grid_step_px() -> usize {
    8
}

impl Default for MediumConfig {
    fn default() -> Self {
        MediumConfig {
            pe_frequencies: 4,
            seed: 0x5EA_0001,
            // Green-blue coastal water: red attenuates fastest, the veiling light is blue-green.
            init_c_med: [0.1, 0.3, 0.35],
            init_sigma_att: [0.3, 0.15, 0.1],
            init_sigma_bs: [0.25, 0.15, 0.1],
            head_init_scale: 0.01,
            grid_step_px: default_grid_step_px(),
        }
    }
}

impl MediumConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), MediumError> {
        let bad = |field: &'static str, value: f64, why: &'static str| Err(MediumError::InvalidConfig { field, value, why });
        if self.pe_frequencies > MAX_PE_FREQUENCIES {
            return bad("pe_frequencies", self.pe_frequencies as f64, "must be at most 12");
        }
        for &v in &self.init_c_med {
            if !(v > 0.0 && v < 1.0) {
                return bad("init_c_med", v, "must be in (0, 1)");
            }
        }
        for (field, values) in [("init_sigma_att", self.init_sigma_att), ("init_sigma_bs", self.init_sigma_bs)] {
            for v in values {
                if !(v.is_finite() && v > 0.0) {
                    return bad(field, v, "must be finite and > 0");
                }
            }
        }
        if !(0.0..=1.0).contains(&self.head_init_scale) {
            return bad("head_init_scale", self.head_init_scale, "must be in [0, 1]");
        }
        if !(1..=64).contains(&self.grid_step_px) {
            return bad("grid_step_px", self.grid_step_px as f64, "must be in 1..=64");
        }
        Ok(())
    }
}

/// Offsets of each tensor in the flat parameter vector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MediumLayout {
    /// Network inputs, `3 + 6 L`.
    pub inputs: usize,
    /// `W1`, `inputs x 64`, input-major.
    pub w1: usize,
    /// `b1`, 64.
    pub b1: usize,
    /// `W2`, `64 x 64`, input-major.
    pub w2: usize,
    /// `b2`, 64.
    pub b2: usize,
    /// The three heads side by side, `64 x 9`, input-major, outputs in plane order.
    pub w_heads: usize,
    /// Head biases, 9, in plane order.
    pub b_heads: usize,
    /// Total number of parameters.
    pub len: usize,
}

impl MediumLayout {
    pub fn new(pe_frequencies: usize) -> Self {
        let inputs = 3 + 6 * pe_frequencies;
        let w1 = 0;
        let b1 = w1 + inputs * HIDDEN;
        let w2 = b1 + HIDDEN;
        let b2 = w2 + HIDDEN * HIDDEN;
        let w_heads = b2 + HIDDEN;
        let b_heads = w_heads + HIDDEN * MEDIUM_CHANNELS;
        let len = b_heads + MEDIUM_CHANNELS;
        MediumLayout { inputs, w1, b1, w2, b2, w_heads, b_heads, len }
    }
}

/// The serialised form of a [`MediumNet`] (map checkpoints), read back with
/// [`MediumNet::from_checkpoint`], which checks it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MediumCheckpoint {
    /// Format version, [`MEDIUM_CHECKPOINT_VERSION`].
    pub schema_version: u32,
    /// Positional-encoding frequencies the parameters were trained with.
    pub pe_frequencies: usize,
    /// The flat parameter vector in [`MediumLayout`] order.
    pub params: Vec<f32>,
}

/// The medium MLP: its encoding size and its flat parameters, `f32` in the runtime, `f64` for
/// gradient checks ([`MediumNet::cast`]).
#[derive(Clone, Debug, PartialEq)]
pub struct MediumNet<T: Real = f32> {
    layout: MediumLayout,
    pe_frequencies: usize,
    params: Vec<T>,
}

impl<T: Real> MediumNet<T> {
    /// A network initialised deterministically from `config.seed`.
    pub fn new(config: &MediumConfig) -> Result<Self, MediumError> {
        config.validate()?;
        let layout = MediumLayout::new(config.pe_frequencies);
        let mut params = vec![T::ZERO; layout.len];
        let mut rng = Rng::new(config.seed);
        let mut glorot = |dst: &mut [T], fan_in: usize, fan_out: usize, scale: f64| {
            let a = (6.0 / (fan_in + fan_out) as f64).sqrt() * scale;
            for v in dst.iter_mut() {
                *v = T::from_f64(rng.range(-a, a));
            }
        };
        let l = layout;
        glorot(&mut params[l.w1..l.b1], l.inputs, HIDDEN, 1.0);
        glorot(&mut params[l.w2..l.b2], HIDDEN, HIDDEN, 1.0);
        glorot(&mut params[l.w_heads..l.b_heads], HIDDEN, 3, config.head_init_scale);
        for c in 0..3 {
            params[l.b_heads + C_MED + c] = T::from_f64(logit(config.init_c_med[c]));
            params[l.b_heads + SIGMA_ATT + c] = T::from_f64(softplus_inverse(config.init_sigma_att[c]));
            params[l.b_heads + SIGMA_BS + c] = T::from_f64(softplus_inverse(config.init_sigma_bs[c]));
        }
        Ok(MediumNet { layout, pe_frequencies: config.pe_frequencies, params })
    }

    pub fn layout(&self) -> MediumLayout {
        self.layout
    }
    pub fn pe_frequencies(&self) -> usize {
        self.pe_frequencies
    }
    pub fn param_count(&self) -> usize {
        self.layout.len
    }
    /// The flat parameters, [`MediumLayout`] order (the medium's Adam group).
    pub fn params(&self) -> &[T] {
        &self.params
    }
    pub fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }

    /// The same network in another precision.
    pub fn cast<U: Real>(&self) -> MediumNet<U> {
        MediumNet { layout: self.layout, pe_frequencies: self.pe_frequencies, params: self.params.iter().map(|v| U::from_f64(v.to_f64())).collect() }
    }

    /// The medium along one unit direction in the world frame, in plane order.
    pub fn eval_direction(&self, dir_in_world: [T; 3]) -> [T; MEDIUM_CHANNELS] {
        let mut act = Activations::new();
        forward_pixel(&self.params, &self.layout, self.pe_frequencies, dir_in_world, &mut act)
    }

    /// The medium along the camera's optical axis as the image-formation parameters written
    /// to `medium.json`: `beta_D = sigma_att`, `beta_B = sigma_bs`, `B_inf = c_med`.
    pub fn summary_along_axis(&self, world_from_cam: &Se3) -> MediumParams {
        let axis = world_from_cam.rotation * Vector3::z();
        let out = self.eval_direction([T::from_f64(axis.x), T::from_f64(axis.y), T::from_f64(axis.z)]);
        let pick = |first: usize| [0, 1, 2].map(|c| out[first + c].to_f64());
        MediumParams { beta_d: pick(SIGMA_ATT), beta_b: pick(SIGMA_BS), b_inf: pick(C_MED) }
    }

    /// Evaluates the medium for every pixel of the view into `out` (the camera's size).
    pub fn forward(&self, camera: &PinholeCamera, world_from_cam: &Se3, out: &mut MediumPlanes<T>) -> Result<(), MediumError> {
        let view = View::new(camera, world_from_cam)?;
        check_size("medium planes", out, camera)?;
        let (lay, l, params) = (&self.layout, self.pe_frequencies, &self.params[..]);
        out.data.par_chunks_mut(camera.width * MEDIUM_CHANNELS).enumerate().for_each(|(y, row)| {
            let mut act = Activations::new();
            for (x, px) in row.chunks_exact_mut(MEDIUM_CHANNELS).enumerate() {
                let o = forward_pixel(params, lay, l, view.direction(x, y), &mut act);
                px.copy_from_slice(&o);
            }
        });
        Ok(())
    }

    /// The parameters as a checkpoint (converted to `f32`).
    pub fn to_checkpoint(&self) -> MediumCheckpoint {
        MediumCheckpoint {
            schema_version: MEDIUM_CHECKPOINT_VERSION,
            pe_frequencies: self.pe_frequencies,
            params: self.params.iter().map(|v| v.to_f64() as f32).collect(),
        }
    }

    /// A network from a checkpoint, checked for version, size and finite values.
    pub fn from_checkpoint(checkpoint: &MediumCheckpoint) -> Result<Self, MediumError> {
        if checkpoint.schema_version != MEDIUM_CHECKPOINT_VERSION {
            return Err(MediumError::UnsupportedVersion { found: checkpoint.schema_version, expected: MEDIUM_CHECKPOINT_VERSION });
        }
        if checkpoint.pe_frequencies > MAX_PE_FREQUENCIES {
            return Err(MediumError::InvalidConfig { field: "pe_frequencies", value: checkpoint.pe_frequencies as f64, why: "must be at most 12" });
        }
        let layout = MediumLayout::new(checkpoint.pe_frequencies);
        if checkpoint.params.len() != layout.len {
            return Err(MediumError::LengthMismatch { what: "checkpoint parameters", len: checkpoint.params.len(), expected: layout.len });
        }
        check_finite("checkpoint parameters", &checkpoint.params)?;
        Ok(MediumNet { layout, pe_frequencies: checkpoint.pe_frequencies, params: checkpoint.params.iter().map(|&v| T::from_f64(v as f64)).collect() })
    }
}

/// Per-band weight-gradient slots of the backward pass, sized once for the tallest image.
#[derive(Clone, Debug)]
pub struct MediumWorkspace<T: Real = f32> {
    max_height: usize,
    param_count: usize,
    band_grads: Vec<T>,
    grid: Option<GridBuffers<T>>,
}

/// Where the network is evaluated for a `width x height` view: nodes every `step` pixels,
/// `nodes_x x nodes_y` of them, the last row and column at or past the image border.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MediumGrid {
    pub width: usize,
    pub height: usize,
    pub step: usize,
    pub nodes_x: usize,
    pub nodes_y: usize,
}

impl MediumGrid {
    /// The grid of a `width x height` view (`step` >= 1; sizes >= 1).
    pub fn new(width: usize, height: usize, step: usize) -> Self {
        let step = step.max(1);
        MediumGrid { width, height, step, nodes_x: (width.max(1) - 1).div_ceil(step) + 1, nodes_y: (height.max(1) - 1).div_ceil(step) + 1 }
    }

    /// MLP evaluations per view.
    pub fn nodes(&self) -> usize {
        self.nodes_x * self.nodes_y
    }

    /// The lower node of pixel coordinate `p` and the weight of the upper one.
    #[inline]
    fn cell<T: Real>(&self, p: usize, nodes: usize) -> (usize, usize, T) {
        let i0 = p / self.step;
        let frac = (p % self.step) as f64 / self.step as f64;
        (i0, (i0 + 1).min(nodes - 1), T::from_f64(frac))
    }

    /// Interpolation weight of node `i` at pixel coordinate `p` (0 outside its two cells).
    #[inline]
    fn weight<T: Real>(&self, p: usize, i: usize) -> T {
        let d = (p as f64 - (i * self.step) as f64).abs() / self.step as f64;
        T::from_f64((1.0 - d).max(0.0))
    }
}

/// The node buffers of a grid workspace.
#[derive(Clone, Debug)]
struct GridBuffers<T> {
    grid: MediumGrid,
    /// Network outputs per node, [`MediumPlanes`] layout at the grid size.
    nodes: Vec<T>,
    /// dL/d node outputs.
    d_nodes: Vec<T>,
    /// Row pass of the adjoint: per image row, per node column.
    d_rows: Vec<T>,
}

impl<T: Real> MediumWorkspace<T> {
    /// A workspace for `net` and images of up to `max_height` rows, exact per pixel.
    pub fn new(net: &MediumNet<T>, max_height: usize) -> Self {
        let bands = max_height.div_ceil(BAND_ROWS);
        MediumWorkspace { max_height, param_count: net.param_count(), band_grads: vec![T::ZERO; bands * net.param_count()], grid: None }
    }

    /// A workspace for `width x height` views that evaluates `net` every `step` pixels and
    /// interpolates bilinearly (`step` 1: the same as [`MediumWorkspace::new`]).
    pub fn with_grid(net: &MediumNet<T>, width: usize, height: usize, step: usize) -> Self {
        if step <= 1 {
            return Self::new(net, height);
        }
        let grid = MediumGrid::new(width, height, step);
        let n = grid.nodes() * MEDIUM_CHANNELS;
        let bands = grid.nodes_y.div_ceil(BAND_ROWS);
        MediumWorkspace {
            max_height: height,
            param_count: net.param_count(),
            band_grads: vec![T::ZERO; bands * net.param_count()],
            grid: Some(GridBuffers { grid, nodes: vec![T::ZERO; n], d_nodes: vec![T::ZERO; n], d_rows: vec![T::ZERO; height * grid.nodes_x * MEDIUM_CHANNELS] }),
        }
    }

    pub fn max_height(&self) -> usize {
        self.max_height
    }

    /// The direction grid, `None` when exact per pixel.
    pub fn grid(&self) -> Option<MediumGrid> {
        self.grid.as_ref().map(|g| g.grid)
    }

    /// The medium of every pixel of the view into `out`: exact per pixel, or interpolated from
    /// the grid nodes when the workspace has a grid (it must be the camera's size).
    pub fn forward(&mut self, net: &MediumNet<T>, camera: &PinholeCamera, world_from_cam: &Se3, out: &mut MediumPlanes<T>) -> Result<(), MediumError> {
        let Some(gb) = self.grid.as_mut() else {
            return net.forward(camera, world_from_cam, out);
        };
        let view = View::new(camera, world_from_cam)?;
        check_size("medium planes", out, camera)?;
        let g = gb.grid;
        check_grid(&g, camera)?;
        let (lay, l, params) = (&net.layout, net.pe_frequencies, &net.params[..]);
        gb.nodes.par_chunks_mut(g.nodes_x * MEDIUM_CHANNELS).enumerate().for_each(|(j, row)| {
            let mut act = Activations::new();
            for (i, px) in row.chunks_exact_mut(MEDIUM_CHANNELS).enumerate() {
                px.copy_from_slice(&forward_pixel(params, lay, l, view.direction(i * g.step, j * g.step), &mut act));
            }
        });
        let nodes = &gb.nodes[..];
        let node = |i: usize, j: usize| &nodes[(j * g.nodes_x + i) * MEDIUM_CHANNELS..(j * g.nodes_x + i + 1) * MEDIUM_CHANNELS];
        out.data.par_chunks_mut(camera.width * MEDIUM_CHANNELS).enumerate().for_each(|(y, row)| {
            let (j0, j1, fy) = g.cell::<T>(y, g.nodes_y);
            for (x, px) in row.chunks_exact_mut(MEDIUM_CHANNELS).enumerate() {
                let (i0, i1, fx) = g.cell::<T>(x, g.nodes_x);
                let (a, b, c, d) = (node(i0, j0), node(i1, j0), node(i0, j1), node(i1, j1));
                let (wa, wb, wc, wd) = ((T::ONE - fx) * (T::ONE - fy), fx * (T::ONE - fy), (T::ONE - fx) * fy, fx * fy);
                for k in 0..MEDIUM_CHANNELS {
                    px[k] = wa * a[k] + wb * b[k] + wc * c[k] + wd * d[k];
                }
            }
        });
        Ok(())
    }

    /// Back-propagates `d_planes` (dL/d medium planes, [`MediumPlanes`] layout) through the
    /// network for the view and **adds** dL/d params to `grads` ([`MediumLayout`] order), so
    /// several views can be accumulated; zero `grads` first for a fresh gradient.
    pub fn backward(
        &mut self,
        net: &MediumNet<T>,
        camera: &PinholeCamera,
        world_from_cam: &Se3,
        d_planes: &MediumPlanes<T>,
        grads: &mut [T],
    ) -> Result<(), MediumError> {
        let view = View::new(camera, world_from_cam)?;
        check_size("medium plane gradient", d_planes, camera)?;
        check_finite("medium plane gradient", &d_planes.data)?;
        if grads.len() != net.param_count() {
            return Err(MediumError::LengthMismatch { what: "parameter gradient", len: grads.len(), expected: net.param_count() });
        }
        if self.param_count != net.param_count() {
            return Err(MediumError::LengthMismatch { what: "medium workspace (built for another network)", len: self.param_count, expected: net.param_count() });
        }
        let (w, h) = (camera.width, camera.height);
        if h > self.max_height {
            return Err(MediumError::CapacityExceeded { height: h, max_height: self.max_height });
        }
        if self.grid.is_some() {
            return self.backward_grid(net, &view, camera, d_planes, grads);
        }
        let bands = h.div_ceil(BAND_ROWS);
        let p = self.param_count;
        let (lay, l, params) = (&net.layout, net.pe_frequencies, &net.params[..]);
        self.band_grads[..bands * p].par_chunks_mut(p).enumerate().for_each(|(band, g)| {
            g.fill(T::ZERO);
            let mut act = Activations::new();
            for y in band * BAND_ROWS..((band + 1) * BAND_ROWS).min(h) {
                let row = &d_planes.data[y * w * MEDIUM_CHANNELS..(y + 1) * w * MEDIUM_CHANNELS];
                for (x, d_out) in row.chunks_exact(MEDIUM_CHANNELS).enumerate() {
                    if d_out.iter().all(|&v| v == T::ZERO) {
                        continue;
                    }
                    let out = forward_pixel(params, lay, l, view.direction(x, y), &mut act);
                    backward_pixel(params, lay, &act, &out, d_out, g);
                }
            }
        });
        for band in self.band_grads[..bands * p].chunks_exact(p) {
            for (acc, &v) in grads.iter_mut().zip(band) {
                *acc += v;
            }
        }
        Ok(())
    }

    /// The grid backward: the adjoint of the bilinear interpolation (rows, then columns, each
    /// a gather in a fixed order), then the network backward on the nodes, banded by node rows.
    fn backward_grid(&mut self, net: &MediumNet<T>, view: &View<'_>, camera: &PinholeCamera, d_planes: &MediumPlanes<T>, grads: &mut [T]) -> Result<(), MediumError> {
        let Some(gb) = self.grid.as_mut() else {
            return Ok(());
        };
        let g = gb.grid;
        check_grid(&g, camera)?;
        let (w, h, nx) = (camera.width, camera.height, g.nodes_x);
        let c = MEDIUM_CHANNELS;
        // Row pass: d_rows[y][i] = sum_x weight(x, i) d_planes[y][x].
        gb.d_rows[..h * nx * c].par_chunks_mut(nx * c).enumerate().for_each(|(y, dst)| {
            dst.fill(T::ZERO);
            let row = &d_planes.data[y * w * c..(y + 1) * w * c];
            for (x, d) in row.chunks_exact(c).enumerate() {
                let (i0, i1, fx) = g.cell::<T>(x, nx);
                let w0 = T::ONE - fx;
                for k in 0..c {
                    dst[i0 * c + k] += w0 * d[k];
                }
                if i1 != i0 {
                    for k in 0..c {
                        dst[i1 * c + k] += fx * d[k];
                    }
                }
            }
        });
        // Column pass: d_nodes[j] = sum_y weight(y, j) d_rows[y].
        let d_rows = &gb.d_rows[..];
        gb.d_nodes.par_chunks_mut(nx * c).enumerate().for_each(|(j, dst)| {
            dst.fill(T::ZERO);
            let lo = (j * g.step).saturating_sub(g.step - 1);
            let hi = (j * g.step + g.step).min(h);
            for y in lo..hi {
                let wy = g.weight::<T>(y, j);
                if wy == T::ZERO {
                    continue;
                }
                for (a, &b) in dst.iter_mut().zip(&d_rows[y * nx * c..(y + 1) * nx * c]) {
                    *a += wy * b;
                }
            }
        });
        // Network backward on the nodes.
        let p = self.param_count;
        let bands = g.nodes_y.div_ceil(BAND_ROWS);
        let (lay, l, params) = (&net.layout, net.pe_frequencies, &net.params[..]);
        let d_nodes = &gb.d_nodes[..];
        self.band_grads[..bands * p].par_chunks_mut(p).enumerate().for_each(|(band, gr)| {
            gr.fill(T::ZERO);
            let mut act = Activations::new();
            for j in band * BAND_ROWS..((band + 1) * BAND_ROWS).min(g.nodes_y) {
                for i in 0..nx {
                    let d_out = &d_nodes[(j * nx + i) * c..(j * nx + i + 1) * c];
                    if d_out.iter().all(|&v| v == T::ZERO) {
                        continue;
                    }
                    let out = forward_pixel(params, lay, l, view.direction(i * g.step, j * g.step), &mut act);
                    backward_pixel(params, lay, &act, &out, d_out, gr);
                }
            }
        });
        for band in self.band_grads[..bands * p].chunks_exact(p) {
            for (acc, &v) in grads.iter_mut().zip(band) {
                *acc += v;
            }
        }
        Ok(())
    }
}

fn check_grid(grid: &MediumGrid, camera: &PinholeCamera) -> Result<(), MediumError> {
    if grid.width != camera.width || grid.height != camera.height {
        return Err(MediumError::SizeMismatch { what: "medium grid workspace", width: grid.width, height: grid.height, expected_width: camera.width, expected_height: camera.height });
    }
    Ok(())
}

/// The per-call view constants: intrinsics and the rotation taking camera rays to the world.
/// (Crate-visible: the GPU medium computes its node directions with it, `map::vulkan::medium`.)
pub(crate) struct View<'a> {
    camera: &'a PinholeCamera,
    world_from_cam_rot: Matrix3<f64>,
}

impl<'a> View<'a> {
    pub(crate) fn new(camera: &'a PinholeCamera, world_from_cam: &Se3) -> Result<Self, MediumError> {
        camera.validate()?;
        let h = world_from_cam.to_homogeneous();
        if !h.iter().all(|v| v.is_finite()) {
            return Err(MediumError::NonFinitePose);
        }
        Ok(View { camera, world_from_cam_rot: *world_from_cam.rotation.to_rotation_matrix().matrix() })
    }

    /// Unit ray direction of pixel (x, y) in the world frame. If undistortion fails (far outside
    /// the lens model's valid field), the distorted normalised coordinates stand in.
    #[inline]
    pub(crate) fn direction<T: Real>(&self, x: usize, y: usize) -> [T; 3] {
        let cam = self.camera;
        let uv = Vector2::new(x as f64, y as f64);
        let ray_in_cam = cam.ray(&uv).unwrap_or_else(|| Vector3::new((uv.x - cam.cx) / cam.fx, (uv.y - cam.cy) / cam.fy, 1.0).normalize());
        let d = self.world_from_cam_rot * ray_in_cam;
        [T::from_f64(d.x), T::from_f64(d.y), T::from_f64(d.z)]
    }
}

fn check_size<T>(what: &'static str, img: &Image<T, MEDIUM_CHANNELS>, camera: &PinholeCamera) -> Result<(), MediumError> {
    if img.width != camera.width || img.height != camera.height {
        return Err(MediumError::SizeMismatch { what, width: img.width, height: img.height, expected_width: camera.width, expected_height: camera.height });
    }
    let expected = camera.width * camera.height * MEDIUM_CHANNELS;
    if img.data.len() != expected {
        return Err(MediumError::LengthMismatch { what, len: img.data.len(), expected });
    }
    Ok(())
}

fn check_finite<T: Real>(what: &'static str, data: &[T]) -> Result<(), MediumError> {
    match data.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(MediumError::NonFinite { what, index, value: data[index].to_f64() }),
        None => Ok(()),
    }
}

/// One pixel's activations, kept for its backward pass (on the stack, no allocation).
struct Activations<T> {
    x: [T; MAX_INPUTS],
    /// softplus'(z1) = sigmoid(z1)
    s1: [T; HIDDEN],
    h1: [T; HIDDEN],
    s2: [T; HIDDEN],
    h2: [T; HIDDEN],
    /// The heads' pre-activations.
    o: [T; MEDIUM_CHANNELS],
}

impl<T: Real> Activations<T> {
    fn new() -> Self {
        Activations { x: [T::ZERO; MAX_INPUTS], s1: [T::ZERO; HIDDEN], h1: [T::ZERO; HIDDEN], s2: [T::ZERO; HIDDEN], h2: [T::ZERO; HIDDEN], o: [T::ZERO; MEDIUM_CHANNELS] }
    }
}

/// `(softplus(z), sigmoid(z))` with one exponential.
#[inline(always)]
fn softplus_sigmoid<T: Real>(z: T) -> (T, T) {
    if z > T::from_f64(20.0) {
        let e = (-z).exp();
        (z + e, T::ONE / (T::ONE + e))
    } else {
        let e = z.exp();
        (e.ln_1p(), e / (T::ONE + e))
    }
}

/// `out = act(b + sum_i x_i W[i, :])` for a hidden layer, keeping the activation's derivative.
#[inline(always)]
fn dense_softplus<T: Real>(w: &[T], b: &[T], x: &[T], h: &mut [T; HIDDEN], s: &mut [T; HIDDEN]) {
    let mut z = [T::ZERO; HIDDEN];
    z.copy_from_slice(b);
    for (i, &xi) in x.iter().enumerate() {
        axpy(xi, &w[i * HIDDEN..(i + 1) * HIDDEN], &mut z);
    }
    for k in 0..HIDDEN {
        (h[k], s[k]) = softplus_sigmoid(z[k]);
    }
}

/// The forward pass of one pixel: encoding, two hidden layers, the heads.
#[inline]
fn forward_pixel<T: Real>(p: &[T], lay: &MediumLayout, l: usize, dir: [T; 3], act: &mut Activations<T>) -> [T; MEDIUM_CHANNELS] {
    act.x[..3].copy_from_slice(&dir);
    let mut freq = T::ONE;
    for k in 0..l {
        for (a, &d) in dir.iter().enumerate() {
            let arg = freq * d;
            act.x[3 + 6 * k + a] = arg.sin();
            act.x[3 + 6 * k + 3 + a] = arg.cos();
        }
        freq += freq;
    }
    dense_softplus(&p[lay.w1..lay.b1], &p[lay.b1..lay.w2], &act.x[..lay.inputs], &mut act.h1, &mut act.s1);
    dense_softplus(&p[lay.w2..lay.b2], &p[lay.b2..lay.w_heads], &act.h1, &mut act.h2, &mut act.s2);
    let wh = &p[lay.w_heads..lay.b_heads];
    act.o.copy_from_slice(&p[lay.b_heads..lay.len]);
    for i in 0..HIDDEN {
        axpy(act.h2[i], &wh[i * MEDIUM_CHANNELS..(i + 1) * MEDIUM_CHANNELS], &mut act.o);
    }
    let mut out = [T::ZERO; MEDIUM_CHANNELS];
    for (k, (o, &pre)) in out.iter_mut().zip(&act.o).enumerate() {
        *o = if k < SIGMA_ATT { super::real::sigmoid(pre) } else { super::real::softplus(pre) };
    }
    out
}

/// Adds one pixel's contribution to the parameter gradient `g` given dL/d out.
#[inline]
fn backward_pixel<T: Real>(p: &[T], lay: &MediumLayout, act: &Activations<T>, out: &[T; MEDIUM_CHANNELS], d_out: &[T], g: &mut [T]) {
    // Heads: sigmoid' = s (1 - s); softplus' = sigmoid(o).
    let mut d_o = [T::ZERO; MEDIUM_CHANNELS];
    for k in 0..MEDIUM_CHANNELS {
        let slope = if k < SIGMA_ATT { out[k] * (T::ONE - out[k]) } else { super::real::sigmoid(act.o[k]) };
        d_o[k] = d_out[k] * slope;
    }
    let wh = &p[lay.w_heads..lay.b_heads];
    axpy(T::ONE, &d_o, &mut g[lay.b_heads..lay.len]);
    let mut d_z2 = [T::ZERO; HIDDEN];
    {
        let g_wh = &mut g[lay.w_heads..lay.b_heads];
        for (i, dz) in d_z2.iter_mut().enumerate() {
            let r = i * MEDIUM_CHANNELS..(i + 1) * MEDIUM_CHANNELS;
            axpy(act.h2[i], &d_o, &mut g_wh[r.clone()]);
            *dz = dot(&wh[r], &d_o) * act.s2[i];
        }
    }
    // Second hidden layer.
    axpy(T::ONE, &d_z2, &mut g[lay.b2..lay.w_heads]);
    let w2 = &p[lay.w2..lay.b2];
    let mut d_z1 = [T::ZERO; HIDDEN];
    {
        let g_w2 = &mut g[lay.w2..lay.b2];
        for (i, dz) in d_z1.iter_mut().enumerate() {
            let r = i * HIDDEN..(i + 1) * HIDDEN;
            axpy(act.h1[i], &d_z2, &mut g_w2[r.clone()]);
            *dz = dot(&w2[r], &d_z2) * act.s1[i];
        }
    }
    // First hidden layer.
    axpy(T::ONE, &d_z1, &mut g[lay.b1..lay.w2]);
    let g_w1 = &mut g[lay.w1..lay.b1];
    for i in 0..lay.inputs {
        axpy(act.x[i], &d_z1, &mut g_w1[i * HIDDEN..(i + 1) * HIDDEN]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn initial_medium_is_the_configured_water() {
        let config = MediumConfig::default();
        let net = MediumNet::<f64>::new(&config).unwrap();
        assert_eq!(net.param_count(), 27 * 64 + 64 + 64 * 64 + 64 + 64 * 9 + 9);
        let s = net.summary_along_axis(&Se3::identity());
        for c in 0..3 {
            assert!((s.b_inf[c] / config.init_c_med[c] - 1.0).abs() < 0.05, "{s:?}");
            assert!((s.beta_d[c] / config.init_sigma_att[c] - 1.0).abs() < 0.05, "{s:?}");
            assert!((s.beta_b[c] / config.init_sigma_bs[c] - 1.0).abs() < 0.05, "{s:?}");
        }
        // Deterministic from the seed.
        assert_eq!(net, MediumNet::<f64>::new(&config).unwrap());
        assert_ne!(net, MediumNet::<f64>::new(&MediumConfig { seed: 1, ..config }).unwrap());
    }

    #[test]
    fn checkpoint_round_trip_and_checks() {
        let net = MediumNet::<f32>::new(&MediumConfig::default()).unwrap();
        let json = serde_json::to_string(&net.to_checkpoint()).unwrap();
        let back: MediumCheckpoint = serde_json::from_str(&json).unwrap();
        assert_eq!(MediumNet::<f32>::from_checkpoint(&back).unwrap(), net);
        let mut short = back.clone();
        short.params.pop();
        assert!(matches!(MediumNet::<f32>::from_checkpoint(&short), Err(MediumError::LengthMismatch { .. })));
        let mut nan = back.clone();
        nan.params[5] = f32::NAN;
        assert!(matches!(MediumNet::<f32>::from_checkpoint(&nan), Err(MediumError::NonFinite { index: 5, .. })));
        assert!(serde_json::from_str::<MediumCheckpoint>(r#"{"schema_version":1,"pe_frequencies":4,"params":[],"x":1}"#).is_err());
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(matches!(
            MediumNet::<f32>::new(&MediumConfig { init_c_med: [0.1, 1.2, 0.3], ..MediumConfig::default() }),
            Err(MediumError::InvalidConfig { field: "init_c_med", .. })
        ));
        let net = MediumNet::<f32>::new(&MediumConfig::default()).unwrap();
        let cam = PinholeCamera::from_hfov(60.0, 23, 17).unwrap();
        let mut wrong = MediumPlanes::<f32>::new(22, 17);
        assert!(matches!(net.forward(&cam, &Se3::identity(), &mut wrong), Err(MediumError::SizeMismatch { width: 22, expected_width: 23, .. })));
        let mut ws = MediumWorkspace::new(&net, 10);
        let d = MediumPlanes::<f32>::new(23, 17);
        let mut g = vec![0.0; net.param_count()];
        assert!(matches!(ws.backward(&net, &cam, &Se3::identity(), &d, &mut g), Err(MediumError::CapacityExceeded { height: 17, max_height: 10 })));
        let mut ws = MediumWorkspace::new(&net, 17);
        let mut nan = d.clone();
        nan.data[40] = f32::NAN;
        assert!(matches!(ws.backward(&net, &cam, &Se3::identity(), &nan, &mut g), Err(MediumError::NonFinite { index: 40, .. })));
        assert!(matches!(ws.backward(&net, &cam, &Se3::identity(), &d, &mut g[1..]), Err(MediumError::LengthMismatch { .. })));
    }
}
