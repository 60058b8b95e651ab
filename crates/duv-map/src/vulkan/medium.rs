//! The medium network (Eq. 10) on the GPU: the twin of
//! [`MediumWorkspace::with_grid`](crate::medium::MediumWorkspace::with_grid) (the CPU
//! reference, [`crate::medium`]), kernels in `kernels/medium.wgsl`.
//!
//! # Loop shape
//! Forward ([`GpuMedium::record_forward`]): `medium.nodes`, one thread per grid node (the
//! encoding of the node's world direction, two softplus layers of 64, the heads), then
//! `medium.interpolate`, one thread per pixel, bilinear from the four nodes around it as
//! `MediumWorkspace::forward` does, written straight into the rasteriser's medium planes
//! (`c_med`, `sigma_att`, `sigma_bs`, RGB interleaved per pixel: the buffers of
//! [`super::GpuRasterForward`]), so the render reads them with no host round trip.
//!
//! Backward ([`GpuMedium::record_backward`]), from dL/d the planes in the same layout (the
//! buffers of [`super::GpuRasterBackward`]): the exact adjoint of the interpolation as the CPU
//! computes it (`medium.interpolate_adjoint_rows`: per image row and node column, a gather over
//! the row's pixels in x order; `medium.interpolate_adjoint_cols`: per node, a gather over the
//! rows in y order), then `medium.nodes_backward`, one thread per node: the forward pass again
//! and the backward of `backward_pixel`, storing the node's activations and deltas (a record of
//! `inputs + 266` floats); then the parameter gradient as a fixed-order reduction over the
//! nodes: `medium.param_grad_partials`, one thread per (parameter, chunk of [`NODE_CHUNK`]
//! nodes), and `medium.param_grad_sum`, one thread per parameter summing the chunks in order
//! and **adding** the result into [`GpuMedium::grads`] (as `MediumWorkspace::backward` adds
//! into its `grads`; [`GpuMedium::record_zero_grads`] starts a fresh gradient). No atomics:
//! two runs on one device are bit-identical.
//!
//! The node directions involve lens undistortion, so the host computes them per view with the
//! CPU reference's own code ([`GpuMedium::write_view`]) and uploads `3 x nodes` floats.
//! `step = 1` is the exact per-pixel network (nodes = pixels, interpolation weights 1 and 0).
//!
//! On a CPU device the node kernels run one invocation per node instead
//! ([`GpuMedium::serial`]: `medium.nodes_serial`, `nodes_backward_serial`, and
//! `param_grad_blocks` for the gradient, 8 rows of a tensor at one column per invocation;
//! `interpolate_cells`, the pixels of one row of a cell per invocation),
//! which gives the same bits there (on the H100 the last bits differ, each within the CPU
//! reference's tolerances): lavapipe loads buffer values lane by lane, so there one load per
//! lane feeds eight multiply-adds through `subgroupBroadcast` (at 640x480, step 8: nodes 46 ->
//! 4.1 ms, their backward 97 -> 6.8 ms, the parameter gradient 37 -> 9.9 ms).
//!
//! Every buffer is allocated once from the arena for a largest view and a grid step
//! ([`GpuMedium::new`]); a smaller view uses a prefix of each. The node records take
//! `4 (inputs + 266)` bytes per node: about 6 MB at 640x480 with the default step 8, but
//! 360 MB at step 1, which is for tests and debugging only.

use duv_core::{PinholeCamera, Se3};
use duv_gpu::{GpuBuffer, GpuContext, GpuError, GpuRange};
use super::kernels::Kernel;
use crate::medium_estimate::MediumPrior;
use crate::medium::{MediumError, MediumGrid, MediumLayout, MediumNet, View, HIDDEN, MAX_PE_FREQUENCIES, MEDIUM_CHANNELS};

/// Nodes per partial sum of the parameter gradient (`medium.param_grad_partials`).
pub const NODE_CHUNK: usize = 128;
/// Floats of `medium.wgsl`'s uniform view of the parameters (`wparams`: 2403 vec4, the
/// largest layout, 75 inputs); `params` is allocated at least this long.
pub const UNIFORM_PARAM_FLOATS: usize = 4 * 2403;
/// Words of the `MediumDims` immediate block of `medium.wgsl`.
const DIMS_WORDS: usize = 16;

/// Floats per node record: `[1, x (inputs), h1, h2, d_o, d_z2, d_z1]`.
pub fn record_floats(layout: &MediumLayout) -> usize {
    1 + layout.inputs + 2 * HIDDEN + MEDIUM_CHANNELS + 2 * HIDDEN
}

/// Why the GPU medium could not run: bad input (the CPU reference's [`MediumError`], or a view
/// past the capacity), or the device.
#[derive(Debug, thiserror::Error)]
pub enum GpuMediumError {
    #[error(transparent)]
    Medium(#[from] MediumError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("view is {width}x{height}, the GPU medium was sized for at most {max_width}x{max_height}")]
    ViewTooLarge { width: usize, height: usize, max_width: usize, max_height: usize },
    #[error("no view written: call GpuMedium::write_view before recording the medium")]
    NoView,
}

/// The medium network's buffers on the device, allocated once for views up to
/// `max_width x max_height`, one grid step and one [`MediumLayout`].
pub struct GpuMedium {
    layout: MediumLayout,
    pe_frequencies: usize,
    step: usize,
    max_width: usize,
    max_height: usize,
    max_nodes: usize,
    record: usize,
    /// The flat parameters, [`MediumLayout`] order ([`GpuMedium::upload_params`]).
    pub params: GpuBuffer<f32>,
    /// dL/d params, [`MediumLayout`] order; [`GpuMedium::record_backward`] adds into it.
    pub grads: GpuBuffer<f32>,
    /// Unit world direction per node, 3 floats.
    dirs: GpuBuffer<f32>,
    /// Network outputs per node, 9 floats in plane order.
    pub node_out: GpuBuffer<f32>,
    d_rows: GpuBuffer<f32>,
    d_nodes: GpuBuffer<f32>,
    records: GpuBuffer<f32>,
    partials: GpuBuffer<f32>,
    /// Host staging of the node directions (allocated once).
    staging: Vec<f32>,
    /// The grid of the view last written.
    view: Option<MediumGrid>,
    /// One invocation per node (`medium.nodes_serial`, `nodes_backward_serial`), the parameter
    /// gradient by blocks of 8 (`param_grad_blocks`) and the interpolation by a row of a cell
    /// (`interpolate_cells`) instead of a workgroup per node, a thread per parameter and one
    /// per pixel; the same bits on lavapipe (on the H100 the last bits differ, each within the
    /// CPU reference's tolerances). `None`: on a CPU device (lavapipe's buffer loads go lane by
    /// lane, and one loaded weight serves eight multiply-adds there; on the H100 the step took
    /// 1.19-1.41x with it). Needs subgroups of 8 to 64 lanes (ignored otherwise).
    pub serial: Option<bool>,
}

impl GpuMedium {
    /// Buffers for views up to `max_width x max_height`, nodes every `step` pixels (1..=64, as
    /// [`crate::medium::MediumConfig::grid_step_px`]) and networks of `layout`.
    pub fn new(ctx: &mut GpuContext, max_width: usize, max_height: usize, step: usize, layout: MediumLayout) -> Result<Self, GpuMediumError> {
        if !(1..=64).contains(&step) {
            return Err(MediumError::InvalidConfig { field: "grid_step_px", value: step as f64, why: "must be in 1..=64" }.into());
        }
        let pe_frequencies = layout.inputs.saturating_sub(3) / 6;
        if pe_frequencies > MAX_PE_FREQUENCIES || MediumLayout::new(pe_frequencies) != layout {
            return Err(MediumError::InvalidConfig { field: "medium layout inputs", value: layout.inputs as f64, why: "must be 3 + 6 L with L <= 12" }.into());
        }
        if max_width == 0 || max_height == 0 {
            return Err(MediumError::InvalidConfig { field: "GPU medium max_width x max_height", value: (max_width * max_height) as f64, why: "must be at least 1x1" }.into());
        }
        let grid = MediumGrid::new(max_width, max_height, step);
        let max_nodes = grid.nodes();
        let record = record_floats(&layout);
        let c = MEDIUM_CHANNELS;
        Ok(GpuMedium {
            layout,
            pe_frequencies,
            step,
            max_width,
            max_height,
            max_nodes,
            record,
            params: ctx.alloc("medium parameters", layout.len.max(UNIFORM_PARAM_FLOATS))?,
            grads: ctx.alloc("medium parameter gradient", layout.len)?,
            dirs: ctx.alloc("medium node directions", max_nodes * 3)?,
            node_out: ctx.alloc("medium node outputs", max_nodes * c)?,
            d_rows: ctx.alloc("medium adjoint row pass", max_height * grid.nodes_x * c)?,
            d_nodes: ctx.alloc("medium node gradients", max_nodes * c)?,
            records: ctx.alloc("medium node records", max_nodes * record)?,
            partials: ctx.alloc("medium gradient partial sums", max_nodes.div_ceil(NODE_CHUNK) * layout.len)?,
            staging: vec![0.0; max_nodes * 3],
            view: None,
            serial: None,
        })
    }

    pub fn layout(&self) -> MediumLayout {
        self.layout
    }
    pub fn step(&self) -> usize {
        self.step
    }
    /// The largest view, `(width, height)`.
    pub fn max_size(&self) -> (usize, usize) {
        (self.max_width, self.max_height)
    }
    /// Nodes of the largest view (the capacity of the node buffers).
    pub fn max_nodes(&self) -> usize {
        self.max_nodes
    }
    /// The grid of the view last written, if any.
    pub fn grid(&self) -> Option<MediumGrid> {
        self.view
    }

    /// Uploads the network's parameters (it must have this medium's layout).
    pub fn upload_params(&mut self, ctx: &mut GpuContext, net: &MediumNet) -> Result<(), GpuMediumError> {
        if net.layout() != self.layout {
            return Err(MediumError::LengthMismatch { what: "medium network (GPU medium built for another layout)", len: net.param_count(), expected: self.layout.len }.into());
        }
        ctx.write(&self.params, net.params())?;
        Ok(())
    }

    /// Computes and uploads the world direction of every grid node of the view (the CPU
    /// reference's `View::direction`, with lens undistortion). Errors as the CPU reference for
    /// a bad camera or a non-finite pose, and for a view past the capacity; on an error nothing
    /// changes (the previous view stays).
    pub fn write_view(&mut self, ctx: &mut GpuContext, camera: &PinholeCamera, world_from_cam: &Se3) -> Result<(), GpuMediumError> {
        let view = View::new(camera, world_from_cam)?;
        let (w, h) = (camera.width, camera.height);
        if w > self.max_width || h > self.max_height {
            return Err(GpuMediumError::ViewTooLarge { width: w, height: h, max_width: self.max_width, max_height: self.max_height });
        }
        let grid = MediumGrid::new(w, h, self.step);
        let n = grid.nodes();
        for j in 0..grid.nodes_y {
            for i in 0..grid.nodes_x {
                let d: [f32; 3] = view.direction(i * grid.step, j * grid.step);
                let k = 3 * (j * grid.nodes_x + i);
                self.staging[k..k + 3].copy_from_slice(&d);
            }
        }
        ctx.write(&self.dirs, &self.staging[..3 * n])?;
        self.view = Some(grid);
        Ok(())
    }

    /// The immediate block of `medium.wgsl` for the current view.
    fn dims_words(&self, grid: &MediumGrid) -> [u32; DIMS_WORDS] {
        let l = &self.layout;
        [
            grid.width,
            grid.height,
            grid.step,
            grid.nodes_x,
            grid.nodes_y,
            self.pe_frequencies,
            l.inputs,
            self.record,
            l.w1,
            l.b1,
            l.w2,
            l.b2,
            l.w_heads,
            l.b_heads,
            l.len,
            NODE_CHUNK,
        ]
        .map(|v| v as u32)
    }

    /// The buffer of each WGSL binding of `medium.wgsl` (for [`GpuContext::dispatch_named`]):
    /// this medium's own, the planes of the forward (`planes`) and their gradients (`upstream`).
    fn binding(&self, name: &str, planes: Option<[&GpuBuffer<f32>; 3]>, upstream: Option<[&GpuBuffer<f32>; 3]>) -> Option<GpuRange> {
        let own = match name {
            "params" | "wparams" => &self.params,
            "dirs" => &self.dirs,
            "node_out" => &self.node_out,
            "d_rows" => &self.d_rows,
            "d_nodes" => &self.d_nodes,
            "records" => &self.records,
            "partials" => &self.partials,
            "grads" => &self.grads,
            "c_med" => planes?[0],
            "sigma_att" => planes?[1],
            "sigma_bs" => planes?[2],
            "grad_c_med" => upstream?[0],
            "grad_sigma_att" => upstream?[1],
            "grad_sigma_bs" => upstream?[2],
            _ => return None,
        };
        Some(own.range())
    }

    /// Whether the node kernels run one invocation per node (`nodes_serial`,
    /// `nodes_backward_serial`, `param_grad_blocks`): [`GpuMedium::serial`], by default on a
    /// CPU device with subgroups of 8 to 64 lanes.
    fn serial(&self, ctx: &GpuContext) -> bool {
        let lanes = ctx.info().subgroup_size;
        self.serial.unwrap_or(ctx.info().is_cpu()) && (8..=64).contains(&lanes)
    }

    fn current_view(&self) -> Result<MediumGrid, GpuMediumError> {
        self.view.ok_or(GpuMediumError::NoView)
    }

    /// Records the forward pass for the view last written: the network on the nodes, then the
    /// bilinear interpolation into the three planes (3 floats per pixel each, the layout of
    /// [`super::GpuRasterForward`]'s `c_med`, `sigma_att`, `sigma_bs`), overwriting the view's
    /// `width x height` pixels. CPU reference: `MediumWorkspace::forward` with a grid (then
    /// `planes_from_nine`).
    pub fn record_forward(&self, ctx: &mut GpuContext, c_med: &GpuBuffer<f32>, sigma_att: &GpuBuffer<f32>, sigma_bs: &GpuBuffer<f32>) -> Result<(), GpuMediumError> {
        let grid = self.current_view()?;
        let planes = [c_med, sigma_att, sigma_bs];
        check_planes(&grid, planes)?;
        let dims = self.dims_words(&grid);
        let imm = bytemuck::bytes_of(&dims);
        let bind = |name: &str| self.binding(name, Some(planes), None);
        let serial = self.serial(ctx);
        let nodes = if serial { (Kernel::MediumNodesSerial, grid.nodes()) } else { (Kernel::MediumNodes, grid.nodes() * NODE_THREADS) };
        let pixels = if serial { (Kernel::MediumInterpolateCells, grid.height * grid.width.div_ceil(grid.step)) } else { (Kernel::MediumInterpolate, grid.width * grid.height) };
        for (kernel, items) in [nodes, pixels] {
            ctx.dispatch_named(kernel, bind, imm, groups_1d(kernel, items))?;
        }
        Ok(())
    }

    /// Records the backward pass for the view last written and the parameters uploaded (it
    /// recomputes the network on the nodes and does not read the forward's outputs) from dL/d
    /// the three planes (same layout as [`GpuMedium::record_forward`]'s
    /// outputs, e.g. [`super::GpuRasterBackward`]'s `grad_c_med`, `grad_sigma_att`,
    /// `grad_sigma_bs`), and **adds** dL/d params into [`GpuMedium::grads`]. CPU reference:
    /// `MediumWorkspace::backward` with a grid (after `nine_from_planes`). Unlike the CPU
    /// reference it does not check the upstream gradient for non-finite values (that would
    /// need a read back); they propagate into the gradient.
    pub fn record_backward(&self, ctx: &mut GpuContext, grad_c_med: &GpuBuffer<f32>, grad_sigma_att: &GpuBuffer<f32>, grad_sigma_bs: &GpuBuffer<f32>) -> Result<(), GpuMediumError> {
        let grid = self.current_view()?;
        let upstream = [grad_c_med, grad_sigma_att, grad_sigma_bs];
        check_planes(&grid, upstream)?;
        let dims = self.dims_words(&grid);
        let imm = bytemuck::bytes_of(&dims);
        let bind = |name: &str| self.binding(name, None, Some(upstream));
        let serial = self.serial(ctx);
        for (kernel, items) in [
            (Kernel::MediumInterpolateAdjointRows, grid.height * grid.nodes_x),
            (Kernel::MediumInterpolateAdjointCols, grid.nodes()),
            if serial { (Kernel::MediumNodesBackwardSerial, grid.nodes()) } else { (Kernel::MediumNodesBackward, grid.nodes() * NODE_THREADS) },
        ] {
            ctx.dispatch_named(kernel, bind, imm, groups_1d(kernel, items))?;
        }
        // One thread per (parameter, chunk of nodes), or per (8 rows of a tensor, column) and
        // chunk, then one per parameter.
        let len = self.layout.len;
        let chunks = grid.nodes().div_ceil(NODE_CHUNK).min(u32::MAX as usize) as u32;
        let (partials, threads) = if serial {
            let l = &self.layout;
            (Kernel::MediumParamGradBlocks, (l.inputs.div_ceil(8) + 1 + HIDDEN / 8 + 1 + HIDDEN / 8 + 1) * 64)
        } else {
            (Kernel::MediumParamGradPartials, len)
        };
        ctx.dispatch_named(partials, bind, imm, [threads.div_ceil(partials.info().workgroup_size[0] as usize) as u32, chunks, 1])?;
        let sum = Kernel::MediumParamGradSum;
        ctx.dispatch_named(sum, bind, imm, [len.div_ceil(sum.info().workgroup_size[0] as usize) as u32, 1, 1])?;
        Ok(())
    }

    /// Records zeroing [`GpuMedium::grads`] (a fresh gradient).
    pub fn record_zero_grads(&self, ctx: &mut GpuContext) -> Result<(), GpuMediumError> {
        ctx.fill(self.grads.range(), 0)?;
        Ok(())
    }

    /// Reads dL/d params ([`MediumLayout`] order) into `out` (exactly the layout's length).
    /// Records the parameter gradient for the host in the backward's submission
    /// ([`GpuContext::prefetch`]), for [`Self::read_grads`].
    pub fn prefetch_grads(&self, ctx: &mut GpuContext) -> Result<(), GpuError> {
        ctx.prefetch(self.grads.range())
    }

    pub fn read_grads(&self, ctx: &GpuContext, out: &mut [f32]) -> Result<(), GpuMediumError> {
        if out.len() != self.layout.len {
            return Err(MediumError::LengthMismatch { what: "medium parameter gradient", len: out.len(), expected: self.layout.len }.into());
        }
        ctx.read_prefetched(&self.grads, out)?;
        Ok(())
    }
}

/// Each plane must hold the view's `3 x width x height` floats.
fn check_planes(grid: &MediumGrid, planes: [&GpuBuffer<f32>; 3]) -> Result<(), GpuError> {
    let need = 3 * grid.width * grid.height;
    for b in planes {
        if b.len() < need {
            return Err(GpuError::OutOfRange { what: b.what(), requested: need, len: b.len() });
        }
    }
    Ok(())
}

/// Threads per node of `nodes` and `nodes_backward`: one workgroup per node, a thread per
/// hidden unit.
const NODE_THREADS: usize = HIDDEN;

/// Workgroups for one thread per item of `n`, as a 2D grid past 65535 workgroups (the kernels
/// flatten `gid.y * groups.x * size + gid.x`).
fn groups_1d(kernel: Kernel, n: usize) -> [u32; 3] {
    let groups = n.div_ceil(kernel.info().workgroup_size[0] as usize);
    if groups == 0 {
        return [0, 1, 1];
    }
    let gx = groups.min(65535);
    [gx as u32, groups.div_ceil(gx).min(u32::MAX as usize) as u32, 1]
}

/// Words of the `PriorParams` immediate block of `medium_prior.wgsl`.
const PRIOR_WORDS: usize = 20;

/// The medium planes and their gradients of one view on the device: the rasteriser's
/// forward planes and backward gradients, and the loss's dL/dc_med.
#[derive(Clone, Copy, Debug)]
pub struct MediumPlaneBuffers<'a> {
    pub c_med: &'a GpuBuffer<f32>,
    pub sigma_att: &'a GpuBuffer<f32>,
    pub sigma_bs: &'a GpuBuffer<f32>,
    pub grad_c_med: &'a GpuBuffer<f32>,
    pub grad_sigma_att: &'a GpuBuffer<f32>,
    pub grad_sigma_bs: &'a GpuBuffer<f32>,
    pub loss_d_c_med: &'a GpuBuffer<f32>,
}

/// Records `medium_prior.medium_upstream` over `pixels` pixels: adds the loss's dL/dc_med and
/// the gradient of `prior` (if any) into the plane gradients and folds `sigma_bs`'s into
/// `sigma_att` when `single_coefficient`. CPU reference: in `Mapper::step_on`, the loss's
/// `d_medium`, [`MediumPrior::loss_and_grad`], [`crate::mapper::fold_single_coefficient`].
pub fn record_medium_upstream(ctx: &mut GpuContext, bufs: &MediumPlaneBuffers, pixels: usize, prior: Option<&MediumPrior>, single_coefficient: bool) -> Result<(), GpuError> {
    for b in [bufs.c_med, bufs.sigma_att, bufs.sigma_bs, bufs.grad_c_med, bufs.grad_sigma_att, bufs.grad_sigma_bs, bufs.loss_d_c_med] {
        if b.len() < 3 * pixels {
            return Err(GpuError::OutOfRange { what: b.what(), requested: 3 * pixels, len: b.len() });
        }
    }
    if pixels == 0 {
        return Ok(());
    }
    let mut w = [0u32; PRIOR_WORDS];
    w[0] = pixels as u32;
    w[2] = single_coefficient as u32;
    if let Some(p) = prior.filter(|p| p.weight != 0.0) {
        w[1] = (0..3).fold(0, |m, c| {
            let h = p.held[c];
            m | (h.beta_d as u32) << c | (h.beta_b as u32) << (3 + c) | (h.b_inf as u32) << (6 + c)
        });
        let f = |v: f64| (v as f32).to_bits();
        w[4] = f(p.weight / pixels as f64);
        w[5] = f(1.0 / (p.rel_std * p.rel_std));
        w[6] = f(1.0 / (p.b_inf_std * p.b_inf_std));
        for c in 0..3 {
            w[8 + c] = f(p.medium.beta_d[c].ln());
            w[12 + c] = f(p.medium.beta_b[c].ln());
            w[16 + c] = f(p.medium.b_inf[c]);
        }
    }
    let lookup = |name: &str| -> Option<GpuRange> {
        Some(match name {
            "c_med" => bufs.c_med.range(),
            "sigma_att" => bufs.sigma_att.range(),
            "sigma_bs" => bufs.sigma_bs.range(),
            "grad_c_med" => bufs.grad_c_med.range(),
            "grad_sigma_att" => bufs.grad_sigma_att.range(),
            "grad_sigma_bs" => bufs.grad_sigma_bs.range(),
            "d_c_med" => bufs.loss_d_c_med.range(),
            _ => return None,
        })
    };
    ctx.dispatch_named(Kernel::MediumPriorMediumUpstream, lookup, bytemuck::cast_slice(&w), [pixels.div_ceil(256) as u32, 1, 1])
}

