//! The mapper's stages on the Vulkan device (`gpu/`), each the kernel twin of a CPU
//! reference in [`super::render`] / [`super::adam`] with the same name and buffer order:
//!
//! | stage | kernel | CPU reference |
//! |---|---|---|
//! | projection | `project_forward.project_forward` | `project_gaussians` |
//! | tile counts prefix sum | `prefix_sum.*` (via `vulkan::ops`) | `exclusive_scan` |
//! | tile binning | `map_gaussian_to_intersects` | `emit_intersections` |
//! | depth/tile key sort | `radix_sort.*` (via `vulkan::ops`) | `radix_sort_pairs` |
//! | tile ranges, index maps | `tile_ranges.{tile_ranges, gather_sorted, invert_permutation}` | `tile_ranges`, `gather_sorted_gaussians`, `invert_permutation` |
//! | rasterise forward with the medium | `rasterize.rasterize` | `rasterize_forward` |
//! | rasterise backward, per-Gaussian sums | `rasterize_backward.{rasterize_backward, rasterize_backward_atomic, reduce_isect_grads}` | `rasterize_backward`, `reduce_isect_grads` |
//! | projection backward | `project_backward.project_backward` | `project_backward` |
//! | Adam | `adam.adam_step` | `AdamGroup::step` |
//! | losses and their gradients ([`loss`]) | `loss.*` | `total_loss` |
//! | Adam over the whole map ([`optimiser`]) | `adam_map.{check_grads, map_step}` | `AdamGroup::step` per group |
//! | medium MLP forward and backward ([`medium`]) | `medium.*` | `MediumWorkspace::{forward, backward}` |
//! | pruning: keep flags, compaction ([`compact`]) | `compact.{keep_flags, scatter}` | the prune rule of `densify_and_prune`, `retain_strided` |
//!
//! [`GpuProjection`], [`GpuBinning`], [`GpuRasterForward`], [`GpuRasterBackward`] and
//! [`GpuProjectBackward`] own their buffers, allocated once from the arena for a fixed
//! capacity; [`GpuForwardRenderer`] runs the forward stages as `RasterWorkspace::forward`
//! does, [`GpuRenderer`] the forward and the backward as `RasterWorkspace::{forward,
//! backward}` do (one submission for the backward). The backward writes one gradient per
//! intersection and sums them per Gaussian. Within a tile, a subgroup's sums are added to the
//! intersection's gradient with float atomics (`rasterize_backward_atomic`) by default; in
//! deterministic mode ([`duv_gpu::GpuOptions::deterministic`], and on devices without
//! float atomics) through workgroup memory in subgroup order (`rasterize_backward`), so
//! results are bit-identical from run to run on one device. No other kernel adds floats with
//! atomics.
//! [`RenderBackend`] is what the mapper renders with: these stages, or the CPU reference
//! ([`MapperDevice`] chooses; no Vulkan device at all falls back with one warning).
//!
//! A mapper step on Vulkan ([`RenderBackend::forward_for_loss`],
//! [`RenderBackend::loss_and_backward`], [`RenderBackend::adam_step`]): the map is resident
//! on the device between densification steps ([`GpuRenderer::make_resident`]), the forward
//! leaves its images on the device, the loss kernels write the backward's upstream gradients
//! in place, Adam updates the device map, and only the loss sums, the medium gradients and
//! the updated parameters come back to the host. The medium network and densification
//! (clone, split) still run on the host: the medium planes go up and their gradients come
//! back every step, and at each densify/prune step the map, its statistics and moments come
//! back ([`GpuRenderer::release`]) and go up again at the next step.

pub mod compact;
pub mod kernels;
pub mod loss;
pub mod medium;
pub mod ops;
pub mod optimiser;

use ops::{record_exclusive_scan, record_radix_sort_indirect, ScanScratch, SortScratch, COUNT_ON_DEVICE, SORT_BLOCK};
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
pub use kernels::{Kernel, KERNELS};
use crate::adam::{AdamGroup, StepConstants};
use crate::medium::{C_MED, MEDIUM_CHANNELS};
use crate::gaussians::{GaussianGrads, Gaussians, ParamGroup, PARAMS_PER_GAUSSIAN};
use duv_core::{PinholeCamera, Se3};
use crate::render::{
    check_backward_inputs, check_output, check_rgb, check_size, validate_gaussians, DepthMode, MediumPlanes, ProjectedSplat, ProjectionSetup,
    RasterCapacity, RenderConfig, RenderError, RenderOutput, RenderStats, RenderUpstream, SplatGrad, TileGrid, TileRect,
};

/// Floats per projected splat on the GPU: three vec4s, `mean2d, conic[0..2] | conic[2], z,
/// opacity, q_max | colour, 0` (what the rasterisers load as vectors; [`splat_floats`]).
pub const SPLAT_FLOATS: usize = 12;

/// A [`ProjectedSplat`] in the GPU layout ([`SPLAT_FLOATS`]).
pub fn splat_floats(s: &ProjectedSplat<f32>) -> [f32; SPLAT_FLOATS] {
    [s.mean2d[0], s.mean2d[1], s.conic[0], s.conic[1], s.conic[2], s.z, s.opacity, s.q_max, s.colour[0], s.colour[1], s.colour[2], 0.0]
}
/// Words of the `Setup` struct of `project_forward.wgsl`.
pub const SETUP_WORDS: usize = 32;

/// The `Setup` struct of `project_forward.wgsl` as words: the [`ProjectionSetup`] floats, then
/// `n, width, height, tile_size, tiles_x, tiles_y` as u32.
pub fn projection_setup_words(s: &ProjectionSetup<f32>, grid: &TileGrid, n: usize) -> [u32; SETUP_WORDS] {
    let r = &s.cam_from_world_rot;
    let floats = [
        r[0][0],
        r[0][1],
        r[0][2],
        r[1][0],
        r[1][1],
        r[1][2],
        r[2][0],
        r[2][1],
        r[2][2],
        s.cam_from_world_trans[0],
        s.cam_from_world_trans[1],
        s.cam_from_world_trans[2],
        s.cam_centre_in_world[0],
        s.cam_centre_in_world[1],
        s.cam_centre_in_world[2],
        s.fx,
        s.fy,
        s.cx,
        s.cy,
        s.lim_x[0],
        s.lim_x[1],
        s.lim_y[0],
        s.lim_y[1],
        s.near_z,
        s.blur,
    ];
    let mut w = [0u32; SETUP_WORDS];
    for (o, f) in w.iter_mut().zip(floats) {
        *o = f.to_bits();
    }
    let ints = [n, grid.width, grid.height, grid.tile_size, grid.tiles_x, grid.tiles_y, 0];
    for (o, v) in w[floats.len()..].iter_mut().zip(ints) {
        *o = v as u32;
    }
    w
}

/// Projection and tile-count scan buffers for up to `capacity` Gaussians.
pub struct GpuProjection {
    pub capacity: usize,
    pub setup: GpuBuffer<u32>,
    /// [`PARAMS_PER_GAUSSIAN`] floats per Gaussian, [`crate::gaussians::GaussianParam::to_array`] order.
    pub params: GpuBuffer<f32>,
    pub splats: GpuBuffer<f32>,
    pub rects: GpuBuffer<[u32; 4]>,
    pub tiles_touched: GpuBuffer<u32>,
    /// `capacity + 1` exclusive offsets of the tile counts.
    pub isect_offsets: GpuBuffer<u32>,
    pub scan: ScanScratch,
    /// Host staging of the parameters and the offsets (allocated once).
    staging: Vec<f32>,
    staging_offsets: Vec<u32>,
}

impl GpuProjection {
    pub fn new(ctx: &mut GpuContext, capacity: usize) -> Result<Self, GpuError> {
        Ok(GpuProjection {
            capacity,
            setup: ctx.alloc("projection setup", SETUP_WORDS)?,
            params: ctx.alloc("Gaussian parameters", capacity * PARAMS_PER_GAUSSIAN)?,
            splats: ctx.alloc("projected splats", capacity * SPLAT_FLOATS)?,
            rects: ctx.alloc("tile rectangles", capacity)?,
            tiles_touched: ctx.alloc("tiles touched", capacity)?,
            isect_offsets: ctx.alloc("intersection offsets", capacity + 1)?,
            scan: ScanScratch::new(ctx, capacity)?,
            staging: vec![0.0; capacity * PARAMS_PER_GAUSSIAN],
            staging_offsets: vec![0; capacity + 1],
        })
    }

    /// Uploads the map (SoA on the host, AoS on the GPU).
    pub fn upload(&mut self, ctx: &mut GpuContext, gaussians: &Gaussians) -> Result<(), GpuError> {
        let n = gaussians.len();
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "Gaussian parameters", requested: n, len: self.capacity });
        }
        for i in 0..n {
            self.staging[i * PARAMS_PER_GAUSSIAN..(i + 1) * PARAMS_PER_GAUSSIAN].copy_from_slice(&gaussians.get(i).to_array());
        }
        ctx.write(&self.params, &self.staging[..n * PARAMS_PER_GAUSSIAN])
    }

    /// Reads the device map into `gaussians` (its `len()` Gaussians; AoS on the GPU, SoA on
    /// the host).
    pub fn read_params(&mut self, ctx: &GpuContext, gaussians: &mut Gaussians) -> Result<(), GpuError> {
        let n = gaussians.len();
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "Gaussian parameters", requested: n, len: self.capacity });
        }
        ctx.read(&self.params, &mut self.staging[..n * PARAMS_PER_GAUSSIAN])?;
        gaussians
            .copy_from_aos(&self.staging[..n * PARAMS_PER_GAUSSIAN])
            .map_err(|_| GpuError::OutOfRange { what: "Gaussian parameters", requested: n, len: self.capacity })
    }

    /// Records `project_forward` over `n` Gaussians (setup written by
    /// [`GpuProjection::write_setup`]), then the exclusive scan of the tile counts with
    /// `max_intersections` as the limit.
    pub fn record(&self, ctx: &mut GpuContext, n: usize, max_intersections: usize) -> Result<(), GpuError> {
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "projected splats", requested: n, len: self.capacity });
        }
        if n == 0 {
            return Ok(());
        }
        let bufs = [self.setup.range(), self.params.range(), self.splats.range(), self.rects.range(), self.tiles_touched.range()];
        ctx.dispatch(Kernel::ProjectForwardProjectForward, &bufs, &[], [n.div_ceil(256) as u32, 1, 1])?;
        record_exclusive_scan(ctx, &self.tiles_touched, n, &self.isect_offsets, &self.scan, max_intersections.min(u32::MAX as usize) as u32)
    }

    /// Writes the camera/pose setup for `n` Gaussians (before `begin()`).
    pub fn write_setup(&self, ctx: &mut GpuContext, setup: &ProjectionSetup<f32>, grid: &TileGrid, n: usize) -> Result<(), GpuError> {
        ctx.write(&self.setup, &projection_setup_words(setup, grid, n))
    }

    /// Reads the splats, rectangles and counts of `n` Gaussians back (tests, debugging).
    pub fn read(
        &self,
        ctx: &GpuContext,
        n: usize,
        splats: &mut [ProjectedSplat<f32>],
        rects: &mut [TileRect],
        tiles_touched: &mut [u32],
    ) -> Result<(), GpuError> {
        let mut raw = vec![0.0f32; n * SPLAT_FLOATS];
        ctx.read(&self.splats, &mut raw)?;
        for (s, r) in splats[..n].iter_mut().zip(raw.chunks_exact(SPLAT_FLOATS)) {
            *s = ProjectedSplat {
                mean2d: [r[0], r[1]],
                conic: [r[2], r[3], r[4]],
                z: r[5],
                opacity: r[6],
                colour: [r[8], r[9], r[10]],
                q_max: r[7],
            };
        }
        let mut raw_rects = vec![[0u32; 4]; n];
        ctx.read(&self.rects, &mut raw_rects)?;
        for (r, w) in rects[..n].iter_mut().zip(&raw_rects) {
            *r = TileRect { x0: w[0], y0: w[1], x1: w[2], y1: w[3] };
        }
        ctx.read(&self.tiles_touched, &mut tiles_touched[..n])
    }
}

/// Tile binning, sort and ranges for up to `max_intersections` intersections on a grid of
/// up to `max_tiles` tiles.
pub struct GpuBinning {
    pub max_intersections: usize,
    pub max_tiles: usize,
    pub keys: GpuBuffer<u64>,
    pub values: GpuBuffer<u32>,
    pub isect_gaussian: GpuBuffer<u32>,
    pub sort: SortScratch,
    /// `num_tiles + 1` CSR offsets into the sorted intersections.
    pub tile_offsets: GpuBuffer<u32>,
    pub sorted_gaussian: GpuBuffer<u32>,
    pub slot_to_sorted: GpuBuffer<u32>,
    /// `[count, sort blocks, 1, 1, 256-intersection groups, 1, 1, 0]`, written on the device
    /// (`intersection_count`).
    pub isect_args: GpuBuffer<u32>,
}

impl GpuBinning {
    pub fn new(ctx: &mut GpuContext, max_intersections: usize, max_tiles: usize) -> Result<Self, GpuError> {
        Ok(GpuBinning {
            max_intersections,
            max_tiles,
            keys: ctx.alloc("intersection keys", max_intersections)?,
            values: ctx.alloc("intersection slots", max_intersections)?,
            isect_gaussian: ctx.alloc("intersection Gaussians", max_intersections)?,
            sort: SortScratch::new(ctx, max_intersections)?,
            tile_offsets: ctx.alloc("tile offsets", max_tiles + 1)?,
            sorted_gaussian: ctx.alloc("sorted Gaussians", max_intersections)?,
            slot_to_sorted: ctx.alloc("slot to sorted", max_intersections)?,
            isect_args: ctx.alloc("intersection count and dispatch arguments", 8)?,
        })
    }

    /// Records, for `n` projected Gaussians, in the projection's submission: emit the keys,
    /// count them on the device (`intersection_count`: the scan's total, 0 after an overflow,
    /// which emits nothing), sort them, tile ranges, gather and invert, the per-intersection
    /// kernels dispatched indirectly from that count, so the host reads nothing between the
    /// projection and the rasteriser. CPU references: `emit_intersections`,
    /// `radix_sort_pairs`, `tile_ranges`, `gather_sorted_gaussians`, `invert_permutation`.
    pub fn record(&self, ctx: &mut GpuContext, proj: &GpuProjection, grid: &TileGrid, n: usize) -> Result<(), GpuError> {
        let num_tiles = grid.num_tiles();
        if num_tiles > self.max_tiles {
            return Err(GpuError::OutOfRange { what: "tile offsets", requested: num_tiles + 1, len: self.max_tiles + 1 });
        }
        let count = self.isect_args.slice_range(0, 1)?;
        if n > 0 {
            let params = [n as u32, grid.tiles_x as u32, 0, 0];
            let bufs = [
                proj.splats.range(),
                proj.rects.range(),
                proj.isect_offsets.range(),
                proj.scan.status.range(),
                self.keys.range(),
                self.values.range(),
                self.isect_gaussian.range(),
            ];
            ctx.dispatch(Kernel::MapGaussianToIntersectsMapGaussianToIntersects, &bufs, bytemuck::bytes_of(&params), [
                n.div_ceil(256) as u32,
                1,
                1,
            ])?;
            let params = [SORT_BLOCK as u32, 0, 0, 0];
            ctx.dispatch(
                Kernel::MapGaussianToIntersectsIntersectionCount,
                &[proj.scan.status.range(), self.isect_args.range()],
                bytemuck::bytes_of(&params),
                [1, 1, 1],
            )?;
        } else {
            // No Gaussian, no scan: no intersection (and no dispatch from the arguments).
            ctx.fill(self.isect_args.range(), 0)?;
        }
        let key_bits = crate::render::isect_key_bits(num_tiles);
        record_radix_sort_indirect(ctx, &self.keys, &self.values, count, self.isect_args.slice_range(1, 3)?, key_bits, &self.sort)?;
        let params = [COUNT_ON_DEVICE, num_tiles as u32, 0, 0];
        let imm = bytemuck::bytes_of(&params);
        ctx.dispatch(Kernel::TileRangesTileRanges, &[self.keys.range(), self.tile_offsets.range(), count], imm, [
            (num_tiles + 1).div_ceil(256) as u32,
            1,
            1,
        ])?;
        let per_isect = self.isect_args.slice_range(4, 3)?;
        let gather = [self.values.range(), self.isect_gaussian.range(), self.sorted_gaussian.range(), count];
        ctx.dispatch_indirect(Kernel::TileRangesGatherSorted, &gather, imm, per_isect)?;
        ctx.dispatch_indirect(Kernel::TileRangesInvertPermutation, &[self.values.range(), self.slot_to_sorted.range(), count], imm, per_isect)?;
        Ok(())
    }
}

/// Whether the rasterisers take two pixels per thread by default (`*_pairs` entry points:
/// each splat a subgroup shares serves two pixels, so half the shuffles, subgroup sums and
/// atomics per pixel): on devices whose subgroups have fewer lanes than this (CPU devices
/// such as lavapipe, 8 lanes: the backward in 0.58-0.73x the time of one pixel per thread,
/// the forward in 0.79x), not on wider ones (an H100, 32 lanes: the backward 0.750 ms against
/// 0.711 ms, the forward 0.28 against 0.27 ms at 640x480 with 100k Gaussians; half the
/// threads per tile hide less latency there). The mapper's rasteriser policy, not the
/// device layer's ([`GpuRasterForward::pixel_pairs`], [`GpuRenderer::set_pixel_pairs`]).
pub const PIXEL_PAIRS_BELOW_SUBGROUP: u32 = 32;

/// [`PIXEL_PAIRS_BELOW_SUBGROUP`] applied to `ctx`'s device.
pub fn default_pixel_pairs(ctx: &GpuContext) -> bool {
    ctx.info().subgroup_size < PIXEL_PAIRS_BELOW_SUBGROUP
}

/// Rasterisation forward buffers for images up to `max_pixels` pixels: the medium planes
/// (inputs) and every output of [`crate::render::RenderOutput`].
pub struct GpuRasterForward {
    pub max_pixels: usize,
    pub c_med: GpuBuffer<f32>,
    pub sigma_att: GpuBuffer<f32>,
    pub sigma_bs: GpuBuffer<f32>,
    pub colour: GpuBuffer<f32>,
    pub restored: GpuBuffer<f32>,
    /// Per pixel `[depth, depth_var, alpha, final_t]`.
    pub scalars: GpuBuffer<[f32; 4]>,
    pub isect_end: GpuBuffer<u32>,
    /// Two pixels per thread ([`PIXEL_PAIRS_BELOW_SUBGROUP`]); the device's default at `new`.
    pub pixel_pairs: bool,
    /// Host staging of the scalars (allocated once).
    staging: Vec<[f32; 4]>,
}

impl GpuRasterForward {
    pub fn new(ctx: &mut GpuContext, max_pixels: usize) -> Result<Self, GpuError> {
        Ok(GpuRasterForward {
            max_pixels,
            c_med: ctx.alloc("medium c_med", max_pixels * 3)?,
            sigma_att: ctx.alloc("medium sigma_att", max_pixels * 3)?,
            sigma_bs: ctx.alloc("medium sigma_bs", max_pixels * 3)?,
            colour: ctx.alloc("rendered colour", max_pixels * 3)?,
            restored: ctx.alloc("restored colour", max_pixels * 3)?,
            scalars: ctx.alloc("depth, variance, alpha, final T", max_pixels)?,
            isect_end: ctx.alloc("isect end", max_pixels)?,
            pixel_pairs: default_pixel_pairs(ctx),
            staging: vec![[0.0; 4]; max_pixels],
        })
    }

    /// Uploads the per-pixel medium planes.
    pub fn upload_medium(&self, ctx: &mut GpuContext, medium: &MediumPlanes) -> Result<(), GpuError> {
        ctx.write(&self.c_med, &medium.c_med.data)?;
        ctx.write(&self.sigma_att, &medium.sigma_att.data)?;
        ctx.write(&self.sigma_bs, &medium.sigma_bs.data)
    }

    /// Records `rasterize` over the grid. CPU reference: `rasterize_forward`.
    pub fn record(
        &self,
        ctx: &mut GpuContext,
        splats: &GpuBuffer<f32>,
        bin: &GpuBinning,
        grid: &TileGrid,
        intrinsics: [f32; 4],
        depth_mode: DepthMode,
    ) -> Result<(), GpuError> {
        if grid.width * grid.height > self.max_pixels {
            return Err(GpuError::OutOfRange { what: "rendered colour", requested: grid.width * grid.height, len: self.max_pixels });
        }
        let [fx, fy, cx, cy] = intrinsics;
        let mode = match depth_mode {
            DepthMode::InverseDepth => 0u32,
            DepthMode::Depth => 1,
        };
        let params = [fx.to_bits(), fy.to_bits(), cx.to_bits(), cy.to_bits(), grid.width as u32, grid.height as u32, grid.tiles_x as u32, mode];
        let bufs = [
            splats.range(),
            bin.sorted_gaussian.range(),
            bin.tile_offsets.range(),
            self.c_med.range(),
            self.sigma_att.range(),
            self.sigma_bs.range(),
            self.colour.range(),
            self.restored.range(),
            self.scalars.range(),
            self.isect_end.range(),
        ];
        let kernel = if self.pixel_pairs { Kernel::RasterizeRasterizePairs } else { Kernel::RasterizeRasterize };
        ctx.dispatch(kernel, &bufs, bytemuck::bytes_of(&params), [grid.tiles_x as u32, grid.tiles_y as u32, 1])
    }

    /// Reads the outputs of a `width x height` render into `out`.
    pub fn read(&mut self, ctx: &GpuContext, out: &mut RenderOutput) -> Result<(), GpuError> {
        let n = out.width() * out.height();
        ctx.read(&self.colour, &mut out.colour.data)?;
        ctx.read(&self.restored, &mut out.restored.data)?;
        let scalars = &mut self.staging[..n];
        ctx.read(&self.scalars, scalars)?;
        for (i, s) in scalars.iter().enumerate() {
            out.depth.data[i] = s[0];
            out.depth_var.data[i] = s[1];
            out.alpha.data[i] = s[2];
            out.final_t.data[i] = s[3];
        }
        ctx.read(&self.isect_end, &mut out.isect_end)
    }

    /// Writes what the backward pass reads of a forward render (depth, variance, alpha,
    /// final T, isect end) from `out`: the backward of a forward computed elsewhere (tests).
    pub fn upload_output(&mut self, ctx: &mut GpuContext, out: &RenderOutput) -> Result<(), GpuError> {
        let n = out.width() * out.height();
        if n > self.max_pixels {
            return Err(GpuError::OutOfRange { what: "depth, variance, alpha, final T", requested: n, len: self.max_pixels });
        }
        for (i, s) in self.staging[..n].iter_mut().enumerate() {
            *s = [out.depth.data[i], out.depth_var.data[i], out.alpha.data[i], out.final_t.data[i]];
        }
        ctx.write(&self.scalars, &self.staging[..n])?;
        ctx.write(&self.isect_end, &out.isect_end)
    }
}

/// Floats of one splat gradient on the GPU: the fields of [`SplatGrad`] in order (mean2d,
/// conic, opacity, colour, z, mean2d_densify) without the pixel count, which is a u32 buffer
/// of its own.
pub const GRAD_FLOATS: usize = 12;

fn splat_grad_from(v: &[f32], pixels: u32) -> SplatGrad<f32> {
    SplatGrad {
        mean2d: [v[0], v[1]],
        conic: [v[2], v[3], v[4]],
        opacity: v[5],
        colour: [v[6], v[7], v[8]],
        z: v[9],
        mean2d_densify: [v[10], v[11]],
        pixels,
    }
}

/// Rasterisation backward buffers for images up to `max_pixels` pixels, `max_intersections`
/// intersections and `max_gaussians` Gaussians: the upstream gradients (inputs), one splat
/// gradient per sorted intersection, one per Gaussian, and the per-pixel medium gradients.
pub struct GpuRasterBackward {
    pub max_pixels: usize,
    pub max_intersections: usize,
    pub max_gaussians: usize,
    pub up_colour: GpuBuffer<f32>,
    pub up_restored: GpuBuffer<f32>,
    /// Per pixel `[dL/ddepth, dL/ddepth_var, dL/dalpha, 0]`.
    pub up_scalars: GpuBuffer<[f32; 4]>,
    /// [`GRAD_FLOATS`] per sorted intersection, and its pixel count.
    pub partials: GpuBuffer<f32>,
    pub partial_pixels: GpuBuffer<u32>,
    pub grad_c_med: GpuBuffer<f32>,
    pub grad_sigma_att: GpuBuffer<f32>,
    pub grad_sigma_bs: GpuBuffer<f32>,
    /// [`GRAD_FLOATS`] per Gaussian, and its pixel count.
    pub splat_grads: GpuBuffer<f32>,
    pub splat_pixels: GpuBuffer<u32>,
    /// The atomic backward sums a subgroup's 13 values per intersection by a reduce-scatter
    /// (`rasterize_backward_atomic_scatter`) on subgroups of 32 lanes and more (faster there:
    /// 0.98 -> 0.78 ms at 640x480/100k on an H100) and by 13 `subgroupAdd`s
    /// (`rasterize_backward_atomic`) below (1.5x faster on lavapipe's 8 lanes); `true` takes
    /// the reduce-scatter on any subgroup size (tests, so that lavapipe runs it too).
    pub force_reduce_scatter: bool,
    /// Where the atomic backward adds its sums: `Some(true)` straight into each Gaussian's
    /// splat gradient (`splat_grads`, zeroed first; no per-intersection partials and no
    /// `reduce_isect_grads`), `Some(false)` into the intersections' partials, reduced per
    /// Gaussian after. `None` (the default): per Gaussian on a CPU device (lavapipe, where
    /// zeroing and reducing the partials took 23 of 273 ms at 320x240/100k), per intersection
    /// on a GPU (what the H100 figures were measured with). The deterministic backward always
    /// writes per intersection.
    pub atomics_per_gaussian: Option<bool>,
    /// Two pixels per thread in the atomic backward ([`PIXEL_PAIRS_BELOW_SUBGROUP`]); the
    /// device's default at `new`.
    pub pixel_pairs: bool,
    /// Host staging (allocated once).
    staging_up: Vec<[f32; 4]>,
    staging_grads: Vec<f32>,
    staging_pixels: Vec<u32>,
}

impl GpuRasterBackward {
    pub fn new(ctx: &mut GpuContext, max_pixels: usize, max_intersections: usize, max_gaussians: usize) -> Result<Self, GpuError> {
        let most = max_intersections.max(max_gaussians);
        Ok(GpuRasterBackward {
            max_pixels,
            max_intersections,
            max_gaussians,
            up_colour: ctx.alloc("dL/dcolour", max_pixels * 3)?,
            up_restored: ctx.alloc("dL/drestored", max_pixels * 3)?,
            up_scalars: ctx.alloc("dL/d depth, variance, alpha", max_pixels)?,
            partials: ctx.alloc("intersection splat gradients", max_intersections * GRAD_FLOATS)?,
            partial_pixels: ctx.alloc("intersection pixel counts", max_intersections)?,
            grad_c_med: ctx.alloc("dL/dc_med", max_pixels * 3)?,
            grad_sigma_att: ctx.alloc("dL/dsigma_att", max_pixels * 3)?,
            grad_sigma_bs: ctx.alloc("dL/dsigma_bs", max_pixels * 3)?,
            splat_grads: ctx.alloc("splat gradients", max_gaussians * GRAD_FLOATS)?,
            splat_pixels: ctx.alloc("splat pixel counts", max_gaussians)?,
            force_reduce_scatter: false,
            atomics_per_gaussian: None,
            pixel_pairs: default_pixel_pairs(ctx),
            staging_up: vec![[0.0; 4]; max_pixels],
            staging_grads: vec![0.0; most * GRAD_FLOATS],
            staging_pixels: vec![0; most],
        })
    }

    /// Uploads the upstream gradients of a `width x height` render.
    pub fn upload_upstream(&mut self, ctx: &mut GpuContext, up: &RenderUpstream) -> Result<(), GpuError> {
        let n = up.width() * up.height();
        if n > self.max_pixels {
            return Err(GpuError::OutOfRange { what: "dL/d depth, variance, alpha", requested: n, len: self.max_pixels });
        }
        ctx.write(&self.up_colour, &up.colour.data)?;
        ctx.write(&self.up_restored, &up.restored.data)?;
        for (i, s) in self.staging_up[..n].iter_mut().enumerate() {
            *s = [up.depth.data[i], up.depth_var.data[i], up.alpha.data[i], 0.0];
        }
        ctx.write(&self.up_scalars, &self.staging_up[..n])
    }

    /// Records `rasterize_backward` over the grid (one [`SplatGrad`] per sorted intersection
    /// in `partials`, the medium gradients per pixel; `rasterize_backward_atomic` with float
    /// atomics unless the context is deterministic), then `reduce_isect_grads` over `n`
    /// Gaussians (their intersection offsets `isect_offsets`); or, where the atomic kernel adds
    /// per Gaussian ([`Self::atomics_per_gaussian`]), zeroes the `n` splat gradients and runs
    /// it alone. The forward outputs are read
    /// from `fwd`, the medium planes too. CPU reference: `rasterize_backward` +
    /// `reduce_isect_grads`.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &mut GpuContext,
        splats: &GpuBuffer<f32>,
        isect_offsets: &GpuBuffer<u32>,
        bin: &GpuBinning,
        fwd: &GpuRasterForward,
        grid: &TileGrid,
        intrinsics: [f32; 4],
        depth_mode: DepthMode,
        n: usize,
    ) -> Result<(), GpuError> {
        if grid.width * grid.height > self.max_pixels.min(fwd.max_pixels) {
            return Err(GpuError::OutOfRange { what: "dL/dc_med", requested: grid.width * grid.height, len: self.max_pixels });
        }
        if bin.max_intersections > self.max_intersections {
            return Err(GpuError::OutOfRange { what: "intersection splat gradients", requested: bin.max_intersections, len: self.max_intersections });
        }
        if n > self.max_gaussians {
            return Err(GpuError::OutOfRange { what: "splat gradients", requested: n, len: self.max_gaussians });
        }
        let [fx, fy, cx, cy] = intrinsics;
        let mode = match depth_mode {
            DepthMode::InverseDepth => 0u32,
            DepthMode::Depth => 1,
        };
        let per_gaussian = !ctx.deterministic() && self.atomics_per_gaussian.unwrap_or(ctx.info().is_cpu());
        let params =
            [fx.to_bits(), fy.to_bits(), cx.to_bits(), cy.to_bits(), grid.width as u32, grid.height as u32, grid.tiles_x as u32, mode, per_gaussian as u32];
        let kernel = if ctx.deterministic() {
            Kernel::RasterizeBackwardRasterizeBackward
        } else {
            if per_gaussian {
                // The atomic kernel adds into the Gaussians' zeroed splat gradients.
                if n > 0 {
                    ctx.fill(self.splat_grads.slice_range(0, n * GRAD_FLOATS)?, 0)?;
                    ctx.fill(self.splat_pixels.slice_range(0, n)?, 0)?;
                }
            } else {
                // The atomic kernel adds into zeroed partials: the render's intersections',
                // counted on the device.
                let zero = [self.partials.range(), self.partial_pixels.range(), bin.isect_args.slice_range(0, 1)?];
                ctx.dispatch_indirect(Kernel::RasterizeBackwardZeroPartials, &zero, &[], bin.isect_args.slice_range(4, 3)?)?;
            }
            match (self.force_reduce_scatter || ctx.info().subgroup_size >= 32, self.pixel_pairs) {
                (true, false) => Kernel::RasterizeBackwardRasterizeBackwardAtomicScatter,
                (false, false) => Kernel::RasterizeBackwardRasterizeBackwardAtomic,
                (true, true) => Kernel::RasterizeBackwardRasterizeBackwardAtomicPairsScatter,
                (false, true) => Kernel::RasterizeBackwardRasterizeBackwardAtomicPairs,
            }
        };
        let lookup = |name: &str| {
            Some(match name {
                "splats" => splats.range(),
                "sorted_gaussian" => bin.sorted_gaussian.range(),
                "tile_offsets" => bin.tile_offsets.range(),
                "c_med" => fwd.c_med.range(),
                "sigma_att" => fwd.sigma_att.range(),
                "sigma_bs" => fwd.sigma_bs.range(),
                "fwd_scalars" => fwd.scalars.range(),
                "fwd_isect_end" => fwd.isect_end.range(),
                "up_colour" => self.up_colour.range(),
                "up_restored" => self.up_restored.range(),
                "up_scalars" => self.up_scalars.range(),
                "partials" => self.partials.range(),
                "partial_pixels" => self.partial_pixels.range(),
                "partials_sum" if per_gaussian => self.splat_grads.range(),
                "partial_pixels_sum" if per_gaussian => self.splat_pixels.range(),
                "partials_sum" => self.partials.range(),
                "partial_pixels_sum" => self.partial_pixels.range(),
                "grad_c_med" => self.grad_c_med.range(),
                "grad_sigma_att" => self.grad_sigma_att.range(),
                "grad_sigma_bs" => self.grad_sigma_bs.range(),
                _ => return None,
            })
        };
        ctx.dispatch_named(kernel, lookup, bytemuck::bytes_of(&params), [grid.tiles_x as u32, grid.tiles_y as u32, 1])?;
        if n == 0 || per_gaussian {
            return Ok(());
        }
        let params = [n as u32, 0, 0, 0];
        let groups = n.div_ceil(256);
        let gx = groups.min(65535);
        let bufs = [
            isect_offsets.range(),
            bin.slot_to_sorted.range(),
            self.partials.range(),
            self.partial_pixels.range(),
            self.splat_grads.range(),
            self.splat_pixels.range(),
            bin.isect_args.slice_range(0, 1)?,
        ];
        ctx.dispatch(Kernel::RasterizeBackwardReduceIsectGrads, &bufs, bytemuck::bytes_of(&params), [
            gx as u32,
            groups.div_ceil(gx) as u32,
            1,
        ])
    }

    fn read_grads(
        ctx: &GpuContext,
        grads: &GpuBuffer<f32>,
        pixels: &GpuBuffer<u32>,
        staging_grads: &mut [f32],
        staging_pixels: &mut [u32],
        out: &mut [SplatGrad<f32>],
    ) -> Result<(), GpuError> {
        let n = out.len();
        ctx.read(grads, &mut staging_grads[..n * GRAD_FLOATS])?;
        ctx.read(pixels, &mut staging_pixels[..n])?;
        for (i, o) in out.iter_mut().enumerate() {
            *o = splat_grad_from(&staging_grads[i * GRAD_FLOATS..(i + 1) * GRAD_FLOATS], staging_pixels[i]);
        }
        Ok(())
    }

    /// Reads the per-Gaussian splat gradients (`out.len()` Gaussians) and the medium gradients
    /// of a `width x height` render (overwritten, as the CPU reference does).
    pub fn read(&mut self, ctx: &GpuContext, out: &mut [SplatGrad<f32>], medium_grads: &mut MediumPlanes) -> Result<(), GpuError> {
        Self::read_grads(ctx, &self.splat_grads, &self.splat_pixels, &mut self.staging_grads, &mut self.staging_pixels, out)?;
        ctx.read(&self.grad_c_med, &mut medium_grads.c_med.data)?;
        ctx.read(&self.grad_sigma_att, &mut medium_grads.sigma_att.data)?;
        ctx.read(&self.grad_sigma_bs, &mut medium_grads.sigma_bs.data)
    }

    /// Reads the per-intersection partials (`out.len()` sorted intersections; tests, debugging).
    pub fn read_partials(&mut self, ctx: &GpuContext, out: &mut [SplatGrad<f32>]) -> Result<(), GpuError> {
        Self::read_grads(ctx, &self.partials, &self.partial_pixels, &mut self.staging_grads, &mut self.staging_pixels, out)
    }
}

/// Parameter gradients and densification statistics of up to `capacity` Gaussians on the
/// GPU: [`PARAMS_PER_GAUSSIAN`] floats per Gaussian in the layout of the parameters, plus the
/// three statistics of [`GaussianGrads`].
pub struct GpuProjectBackward {
    pub capacity: usize,
    pub grads: GpuBuffer<f32>,
    pub densify_grad_norm: GpuBuffer<f32>,
    pub pixels_touched: GpuBuffer<u32>,
    pub views: GpuBuffer<u32>,
    /// Host staging (allocated once).
    staging: Vec<f32>,
    staging_norm: Vec<f32>,
    staging_counts: Vec<u32>,
}

impl GpuProjectBackward {
    pub fn new(ctx: &mut GpuContext, capacity: usize) -> Result<Self, GpuError> {
        Ok(GpuProjectBackward {
            capacity,
            grads: ctx.alloc("Gaussian gradients", capacity * PARAMS_PER_GAUSSIAN)?,
            densify_grad_norm: ctx.alloc("densify gradient norms", capacity)?,
            pixels_touched: ctx.alloc("pixels touched", capacity)?,
            views: ctx.alloc("views", capacity)?,
            staging: vec![0.0; capacity * PARAMS_PER_GAUSSIAN],
            staging_norm: vec![0.0; capacity],
            staging_counts: vec![0; 2 * capacity],
        })
    }

    fn check_len(&self, n: usize) -> Result<(), GpuError> {
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "Gaussian gradients", requested: n, len: self.capacity });
        }
        Ok(())
    }

    /// Uploads `grads` (what the backward pass adds into).
    pub fn upload(&mut self, ctx: &mut GpuContext, grads: &GaussianGrads) -> Result<(), GpuError> {
        let n = grads.len();
        self.check_len(n)?;
        for g in ParamGroup::ALL {
            let (w, off) = (g.width(), g.offset());
            for (i, src) in grads.group(g).chunks_exact(w).enumerate() {
                self.staging[i * PARAMS_PER_GAUSSIAN + off..i * PARAMS_PER_GAUSSIAN + off + w].copy_from_slice(src);
            }
        }
        ctx.write(&self.grads, &self.staging[..n * PARAMS_PER_GAUSSIAN])?;
        ctx.write(&self.densify_grad_norm, grads.densify_grad_norm())?;
        ctx.write(&self.pixels_touched, grads.pixels_touched())?;
        ctx.write(&self.views, grads.views())
    }

    /// Records zeroing the parameter gradients of `n` Gaussians (the densification statistics
    /// keep accumulating, as `GaussianGrads::zero_params` leaves them).
    pub fn record_zero_params(&self, ctx: &mut GpuContext, n: usize) -> Result<(), GpuError> {
        self.check_len(n)?;
        if n == 0 {
            return Ok(());
        }
        ctx.fill(self.grads.slice_range(0, n * PARAMS_PER_GAUSSIAN)?, 0)
    }

    /// Records zeroing the gradients and statistics of `n` Gaussians.
    pub fn record_zero(&self, ctx: &mut GpuContext, n: usize) -> Result<(), GpuError> {
        self.check_len(n)?;
        if n == 0 {
            return Ok(());
        }
        ctx.fill(self.grads.slice_range(0, n * PARAMS_PER_GAUSSIAN)?, 0)?;
        ctx.fill(self.densify_grad_norm.slice_range(0, n)?, 0)?;
        ctx.fill(self.pixels_touched.slice_range(0, n)?, 0)?;
        ctx.fill(self.views.slice_range(0, n)?, 0)
    }

    /// Records `project_backward` over `n` Gaussians: the splat gradients of `raster` back to
    /// the parameters in `proj` (with the setup of the forward pass), ADDED into these
    /// buffers. CPU reference: `project_backward`.
    pub fn record(&self, ctx: &mut GpuContext, proj: &GpuProjection, raster: &GpuRasterBackward, n: usize) -> Result<(), GpuError> {
        self.check_len(n)?;
        if n > proj.capacity || n > raster.max_gaussians {
            return Err(GpuError::OutOfRange { what: "splat gradients", requested: n, len: proj.capacity.min(raster.max_gaussians) });
        }
        if n == 0 {
            return Ok(());
        }
        let groups = n.div_ceil(256);
        let gx = groups.min(65535);
        let bufs = [
            proj.params.range(),
            proj.setup.range(),
            raster.splat_grads.range(),
            raster.splat_pixels.range(),
            self.grads.range(),
            self.densify_grad_norm.range(),
            self.pixels_touched.range(),
            self.views.range(),
        ];
        ctx.dispatch(Kernel::ProjectBackwardProjectBackward, &bufs, &[], [gx as u32, groups.div_ceil(gx) as u32, 1])
    }

    /// Reads the gradients and statistics of `grads.len()` Gaussians into `grads`
    /// (overwritten).
    pub fn read(&mut self, ctx: &GpuContext, grads: &mut GaussianGrads) -> Result<(), GpuError> {
        let n = grads.len();
        self.check_len(n)?;
        ctx.read(&self.grads, &mut self.staging[..n * PARAMS_PER_GAUSSIAN])?;
        for g in ParamGroup::ALL {
            let (w, off) = (g.width(), g.offset());
            for (i, dst) in grads.group_mut(g).chunks_exact_mut(w).enumerate() {
                dst.copy_from_slice(&self.staging[i * PARAMS_PER_GAUSSIAN + off..i * PARAMS_PER_GAUSSIAN + off + w]);
            }
        }
        ctx.read(&self.densify_grad_norm, &mut self.staging_norm[..n])?;
        let (touched, views) = self.staging_counts.split_at_mut(self.capacity);
        ctx.read(&self.pixels_touched, &mut touched[..n])?;
        ctx.read(&self.views, &mut views[..n])?;
        grads
            .set_densify_stats(&self.staging_norm[..n], &touched[..n], &views[..n])
            .expect("lengths equal grads.len() by construction");
        Ok(())
    }
}

/// Records one Adam step over `n` values (`values`, `grads`, first and second moments `m`,
/// `v`, same layout). CPU reference: `AdamGroup::step` (the per-value update), constants from
/// [`StepConstants::new`].
pub fn record_adam_step(
    ctx: &mut GpuContext,
    values: &GpuBuffer<f32>,
    grads: &GpuBuffer<f32>,
    m: &GpuBuffer<f32>,
    v: &GpuBuffer<f32>,
    n: usize,
    k: &StepConstants,
) -> Result<(), GpuError> {
    for b in [values, grads, m, v] {
        if b.len() < n {
            return Err(GpuError::OutOfRange { what: b.what(), requested: n, len: b.len() });
        }
    }
    if n == 0 {
        return Ok(());
    }
    let params = [
        k.beta1.to_bits(),
        k.one_minus_beta1.to_bits(),
        k.beta2.to_bits(),
        k.one_minus_beta2.to_bits(),
        k.step_size.to_bits(),
        k.inv_sqrt_bias2.to_bits(),
        k.eps.to_bits(),
        n as u32,
    ];
    let groups = n.div_ceil(256);
    let gx = groups.min(65535);
    let bufs = [values.range(), grads.range(), m.range(), v.range()];
    ctx.dispatch(Kernel::AdamAdamStep, &bufs, bytemuck::bytes_of(&params), [gx as u32, groups.div_ceil(gx) as u32, 1])
}

/// Why a GPU render failed: bad input or a full buffer (the same [`RenderError`] the CPU
/// reference reports), or the device.
#[derive(Debug, thiserror::Error)]
pub enum VulkanRenderError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Loss(#[from] crate::loss::LossError),
    #[error(transparent)]
    Medium(#[from] medium::GpuMediumError),
}

/// The medium of a mapper step evaluated on the device: the network, the view's pose (the
/// node directions), the single-coefficient tie.
#[derive(Clone, Copy)]
pub struct DeviceMediumStep<'a> {
    pub net: &'a crate::medium::MediumNet,
    pub world_from_cam: &'a Se3,
    pub single_coefficient: bool,
}

/// The medium's backward of a mapper step on the device: the prior and the tie applied to the
/// plane gradients (`medium_prior.medium_upstream`), then the network's backward; its
/// parameter gradient is written into `param_grads` (overwritten).
pub struct DeviceMediumBackward<'a> {
    pub prior: Option<&'a crate::medium_estimate::MediumPrior>,
    pub single_coefficient: bool,
    pub param_grads: &'a mut [f32],
}

/// Where a forward render takes the medium planes from.
#[derive(Clone, Copy)]
pub enum MediumSource<'a> {
    /// Planes computed on the host, uploaded.
    Host(&'a MediumPlanes),
    /// The medium network on the device ([`medium::GpuMedium`], its parameters and view
    /// written), evaluated into the rasteriser's planes before the projection; with
    /// `single_coefficient`, `sigma_bs` is a copy of `sigma_att`.
    Device { medium: &'a medium::GpuMedium, single_coefficient: bool },
}

/// The forward render on the GPU, every buffer allocated once for a [`RasterCapacity`]:
/// projection + tile-count scan (one submission; the total is read back, as the CPU reference
/// checks it before emitting), then binning, sort, ranges and rasterisation (a second one).
pub struct GpuForwardRenderer {
    pub capacity: RasterCapacity,
    pub projection: GpuProjection,
    pub binning: GpuBinning,
    pub raster: GpuRasterForward,
    /// The view whose geometry (projection, binning, sort, tile ranges) of the device map
    /// [`Self::submit_geometry_ahead`] submitted; the next deferred forward of the device map
    /// for the same view skips it. Any other forward, or a change to the device map
    /// ([`GpuRenderer`] clears it), forgets it.
    ahead: Option<AheadView>,
    /// Geometries submitted ahead, and forwards that used one (a benchmark's and a test's
    /// check that the overlap happens).
    pub ahead_submitted: u64,
    pub ahead_used: u64,
}

/// The view a geometry pass was submitted ahead for ([`GpuForwardRenderer::submit_geometry_ahead`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct AheadView {
    camera: PinholeCamera,
    cam_from_world: Se3,
    config: RenderConfig,
    n: usize,
}

impl GpuForwardRenderer {
    pub fn new(ctx: &mut GpuContext, capacity: RasterCapacity) -> Result<Self, GpuError> {
        let grid = TileGrid::new(capacity.width, capacity.height);
        Ok(GpuForwardRenderer {
            capacity,
            projection: GpuProjection::new(ctx, capacity.max_gaussians)?,
            binning: GpuBinning::new(ctx, capacity.max_intersections, grid.num_tiles())?,
            raster: GpuRasterForward::new(ctx, capacity.width * capacity.height)?,
            ahead: None,
            ahead_submitted: 0,
            ahead_used: 0,
        })
    }

    /// Records and submits, left running ([`GpuContext::submit`]), the geometry of the next
    /// forward of the device map (in [`GpuProjection::params`], `n` Gaussians) from
    /// `cam_from_world`: projection, tile counts and their scan, binning, sort and tile
    /// ranges, so that the device runs it while the host finishes a step. The next
    /// [`Self::forward_on_device`] of the device map with `defer` and the same view records
    /// only the medium and the rasterisation after it (the same commands as in one
    /// submission, so the same results). A tile overflow shows with that forward's count.
    pub fn submit_geometry_ahead(&mut self, ctx: &mut GpuContext, n: usize, camera: &PinholeCamera, cam_from_world: &Se3, config: &RenderConfig) -> Result<(), VulkanRenderError> {
        self.ahead = None;
        if camera.width == 0 || camera.height == 0 || camera.width > self.capacity.width || camera.height > self.capacity.height {
            return Err(RenderError::CapacityExceeded { what: "image pixels", requested: camera.width * camera.height, capacity: self.capacity.width * self.capacity.height }.into());
        }
        if n > self.capacity.max_gaussians {
            return Err(RenderError::CapacityExceeded { what: "Gaussians", requested: n, capacity: self.capacity.max_gaussians }.into());
        }
        let setup = ProjectionSetup::<f32>::new(camera, cam_from_world, config)?;
        let grid = TileGrid::new(camera.width, camera.height);
        self.projection.write_setup(ctx, &setup, &grid, n)?;
        ctx.begin()?;
        self.projection.record(ctx, n, self.capacity.max_intersections)?;
        self.binning.record(ctx, &self.projection, &grid, n)?;
        ctx.submit()?;
        self.ahead = Some(AheadView { camera: *camera, cam_from_world: *cam_from_world, config: *config, n });
        self.ahead_submitted += 1;
        Ok(())
    }

    /// Forgets a geometry submitted ahead (the device map or its buffers changed).
    pub fn forget_geometry_ahead(&mut self) {
        self.ahead = None;
    }

    /// Renders `gaussians` seen from `cam_from_world` through `medium` into `out`, as
    /// [`crate::render::RasterWorkspace::forward`] does on the CPU (same validation,
    /// same errors; [`RenderError::TileOverflow`] reports the size needed).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.forward_impl(ctx, gaussians, camera, cam_from_world, MediumSource::Host(medium), config, Some(out), false, false)
    }

    /// [`Self::forward`] that leaves the rendered images on the device (in [`Self::raster`]),
    /// for the loss kernels; nothing but the intersection count is read back (so
    /// [`RenderStats::visible`] is 0: not counted).
    /// With `params_on_device` the map already in [`GpuProjection::params`] is rendered
    /// (`gaussians`, the host's copy, only gives the count: the device map is the optimiser's).
    /// With `defer` the submission is left running ([`GpuContext::submit`]) and the stats are
    /// zeros: the intersection count, and a tile overflow, are the next submission's to read
    /// ([`GpuRenderer::loss_and_backward`]).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_on_device(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: MediumSource,
        config: &RenderConfig,
        params_on_device: bool,
        defer: bool,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.forward_impl(ctx, gaussians, camera, cam_from_world, medium, config, None, params_on_device, defer)
    }

    #[allow(clippy::too_many_arguments)]
    fn forward_impl(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: MediumSource,
        config: &RenderConfig,
        mut out: Option<&mut RenderOutput>,
        params_on_device: bool,
        defer: bool,
    ) -> Result<RenderStats, VulkanRenderError> {
        let _span = tracing::debug_span!("map.gpu_forward", gaussians = gaussians.len()).entered();
        if camera.width == 0 || camera.height == 0 {
            return Err(RenderError::EmptyImage { width: camera.width, height: camera.height }.into());
        }
        let setup = ProjectionSetup::<f32>::new(camera, cam_from_world, config)?;
        let grid = TileGrid::new(camera.width, camera.height);
        if camera.width > self.capacity.width || camera.height > self.capacity.height {
            return Err(RenderError::CapacityExceeded {
                what: "image pixels",
                requested: camera.width * camera.height,
                capacity: self.capacity.width * self.capacity.height,
            }
            .into());
        }
        let n = gaussians.len();
        if n > self.capacity.max_gaussians {
            return Err(RenderError::CapacityExceeded { what: "Gaussians", requested: n, capacity: self.capacity.max_gaussians }.into());
        }
        if let MediumSource::Host(medium) = medium {
            check_size("medium planes", medium.width(), medium.height(), &grid)?;
            for (_, plane) in medium.planes() {
                check_size("medium planes", plane.width, plane.height, &grid)?;
            }
        }
        if let Some(out) = out.as_deref() {
            check_output(out, &grid)?;
        }
        // The device's own map was checked when it went there; Adam there refuses a
        // non-finite gradient, so it stays finite (the host copy may be behind it).
        if !params_on_device {
            validate_gaussians(gaussians)?;
        }
        if let MediumSource::Host(medium) = medium {
            for (what, plane) in medium.planes() {
                check_rgb(what, plane, what != "c_med")?;
            }
        }

        // The geometry submitted ahead for this view, if it is the one wanted.
        let view = AheadView { camera: *camera, cam_from_world: *cam_from_world, config: *config, n };
        let ahead = self.ahead.take();
        let geometry_done = params_on_device && defer && out.is_none() && ahead == Some(view);
        self.ahead_used += geometry_done as u64;
        if !params_on_device {
            self.projection.upload(ctx, gaussians)?;
        }
        if !geometry_done {
            self.projection.write_setup(ctx, &setup, &grid, n)?;
        }
        if let MediumSource::Host(medium) = medium {
            self.raster.upload_medium(ctx, medium)?;
        }
        ctx.begin()?;
        if let MediumSource::Device { medium, single_coefficient } = medium {
            match medium.grid() {
                Some(g) if (g.width, g.height) == (camera.width, camera.height) => {}
                _ => return Err(RenderError::NoForward { why: "the device medium's view is not this camera's (GpuMedium::write_view)" }.into()),
            }
            let r = &self.raster;
            medium.record_forward(ctx, &r.c_med, &r.sigma_att, &r.sigma_bs)?;
            if single_coefficient {
                let px = camera.width * camera.height;
                ctx.copy(r.sigma_att.slice_range(0, 3 * px)?, r.sigma_bs.slice_range(0, 3 * px)?)?;
            }
        }
        // One submission: the intersection count stays on the device (the binning's kernels
        // are dispatched from it); the host reads it afterwards. An overflow renders no
        // intersection and is an error here.
        if !geometry_done {
            self.projection.record(ctx, n, self.capacity.max_intersections)?;
            self.binning.record(ctx, &self.projection, &grid, n)?;
        }
        let intrinsics = [camera.fx as f32, camera.fy as f32, camera.cx as f32, camera.cy as f32];
        self.raster.record(ctx, &self.projection.splats, &self.binning, &grid, intrinsics, config.depth_mode)?;
        self.projection.scan.prefetch_result(ctx)?;
        if defer && out.is_none() {
            ctx.submit()?;
            return Ok(RenderStats { visible: 0, intersections: 0 });
        }
        ctx.submit_and_wait()?;
        let n_isects = if n == 0 {
            0
        } else {
            match self.projection.scan.result(ctx)? {
                Ok(total) => total as usize,
                Err(needed) => return Err(RenderError::TileOverflow { needed, capacity: self.capacity.max_intersections }.into()),
            }
        };
        if let Some(out) = out.as_deref_mut() {
            self.raster.read(ctx, out)?;
        }
        let mut visible = 0;
        // Counted only with the images (an optimisation step's forward would read every
        // Gaussian's offset back for a statistic nothing uses).
        if n > 0 && out.is_some() {
            // Visible Gaussians: those with a non-empty tile range in the offsets.
            let mut offsets = std::mem::take(&mut self.projection.staging_offsets);
            ctx.read(&self.projection.isect_offsets, &mut offsets[..n + 1])?;
            visible = offsets[..n + 1].windows(2).filter(|p| p[1] > p[0]).count();
            self.projection.staging_offsets = offsets;
        }
        Ok(RenderStats { visible, intersections: n_isects })
    }
}

/// What [`GpuRenderer::backward`] needs of the last forward pass.
#[derive(Clone, Copy, Debug)]
struct GpuForwardState {
    grid: TileGrid,
    intrinsics: [f32; 4],
    depth_mode: DepthMode,
    n_gaussians: usize,
    n_isects: usize,
}

/// Forward and backward render on the GPU, every buffer allocated once for a
/// [`RasterCapacity`]: the twin of [`crate::render::RasterWorkspace`]. The backward
/// differentiates the last forward with what that forward left on the device (the map, the
/// medium, the projected splats, the sorted intersections, depth, variance, alpha, final T and
/// isect end), so the caller passes the same map and medium again, as it must to the CPU
/// reference.
pub struct GpuRenderer {
    pub fwd: GpuForwardRenderer,
    pub raster_backward: GpuRasterBackward,
    pub project_backward: GpuProjectBackward,
    /// The loss kernels, for [`Self::loss_and_backward`].
    pub loss: loss::GpuLoss,
    /// Adam over the map, for [`Self::adam_step`].
    pub adam: optimiser::GpuMapAdam,
    /// The medium network on the device ([`Self::enable_medium`]); `None`: planes from the host.
    pub medium: Option<medium::GpuMedium>,
    /// `Some(n)` while the device holds the optimiser's map of `n` Gaussians (parameters,
    /// gradients and densification statistics, Adam moments): see [`Self::make_resident`].
    resident: Option<usize>,
    /// The device map's parameters changed since the host last had them ([`Self::adam_step`]
    /// reads nothing back; [`Self::sync`] does).
    params_stale: bool,
    /// [`Self::arm_adam_step`] was called: the next [`Self::loss_and_backward`] ends with the
    /// Adam step, whose outcome (`Some(taken)`) waits in `fused_adam` for [`Self::adam_step`].
    adam_armed: bool,
    fused_adam: Option<bool>,
    /// The view of the next step ([`Self::plan_next_view`]): the next
    /// [`Self::loss_and_backward`] submits its geometry after the step's Adam.
    next_view: Option<AheadView>,
    last: Option<GpuForwardState>,
    /// The last forward was deferred: its intersection count is read after the loss's
    /// submission.
    count_pending: bool,
    /// Host staging of the loss's dL/dc_med (allocated once).
    staging_c_med: Vec<f32>,
}

impl GpuRenderer {
    /// Intersections of the last forward, if one ran since the geometry last changed.
    pub fn last_intersections(&self) -> Option<usize> {
        self.last.map(|l| l.n_isects)
    }

    /// Whether the rasterisers take two pixels per thread ([`PIXEL_PAIRS_BELOW_SUBGROUP`]).
    pub fn pixel_pairs(&self) -> bool {
        self.fwd.raster.pixel_pairs
    }

    /// Switches [`Self::pixel_pairs`] in the forward and the backward; returns the previous setting.
    pub fn set_pixel_pairs(&mut self, on: bool) -> bool {
        self.raster_backward.pixel_pairs = on;
        std::mem::replace(&mut self.fwd.raster.pixel_pairs, on)
    }

    pub fn new(ctx: &mut GpuContext, capacity: RasterCapacity) -> Result<Self, GpuError> {
        Ok(GpuRenderer {
            fwd: GpuForwardRenderer::new(ctx, capacity)?,
            raster_backward: GpuRasterBackward::new(
                ctx,
                capacity.width * capacity.height,
                capacity.max_intersections,
                capacity.max_gaussians,
            )?,
            project_backward: GpuProjectBackward::new(ctx, capacity.max_gaussians)?,
            loss: loss::GpuLoss::new(ctx, capacity.width, capacity.height)?,
            adam: optimiser::GpuMapAdam::new(ctx, capacity.max_gaussians)?,
            medium: None,
            resident: None,
            params_stale: false,
            adam_armed: false,
            fused_adam: None,
            next_view: None,
            last: None,
            count_pending: false,
            staging_c_med: vec![0.0; 3 * capacity.width * capacity.height],
        })
    }

    /// [`GpuForwardRenderer::forward_on_device`], remembered for [`Self::loss_and_backward`].
    /// With `defer` its submission is left running while the host records the loss and
    /// backward ([`GpuContext::submit`]); the stats are then zeros and the intersection count,
    /// or a [`RenderError::TileOverflow`], comes with [`Self::loss_and_backward`] (whose Adam
    /// step is not taken after an overflow).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_on_device(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        device_medium: Option<&DeviceMediumStep>,
        config: &RenderConfig,
        defer: bool,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.last = None;
        self.count_pending = false;
        // A plan made before a step that failed is not this step's.
        self.next_view = None;
        let on_device = self.check_resident(gaussians.len())?;
        let source = match (device_medium, self.medium.as_mut()) {
            (Some(step), Some(gm)) => {
                gm.upload_params(ctx, step.net)?;
                gm.write_view(ctx, camera, step.world_from_cam)?;
                MediumSource::Device { medium: gm, single_coefficient: step.single_coefficient }
            }
            (Some(_), None) => return Err(RenderError::NoForward { why: "no device medium (GpuRenderer::enable_medium)" }.into()),
            (None, _) => MediumSource::Host(medium),
        };
        let stats = self.fwd.forward_on_device(ctx, gaussians, camera, cam_from_world, source, config, on_device, defer)?;
        self.remember(camera, config, gaussians.len(), stats.intersections);
        self.count_pending = defer;
        Ok(stats)
    }

    /// Allocates the medium network's buffers ([`medium::GpuMedium`]) for this renderer's
    /// largest view, nodes every `step` pixels and networks of `layout`, once; a second call
    /// with the same arguments does nothing, with others it is an error (the arena never
    /// frees).
    pub fn enable_medium(&mut self, ctx: &mut GpuContext, step: usize, layout: crate::medium::MediumLayout) -> Result<(), VulkanRenderError> {
        if let Some(m) = &self.medium {
            if m.step() == step && m.layout() == layout {
                return Ok(());
            }
            return Err(RenderError::NoForward { why: "the device medium was sized for another grid step or network" }.into());
        }
        let cap = self.fwd.capacity;
        self.medium = Some(medium::GpuMedium::new(ctx, cap.width, cap.height, step, layout)?);
        Ok(())
    }

    /// Whether the device holds the map; an error when it holds another size than the host's.
    fn check_resident(&self, n: usize) -> Result<bool, RenderError> {
        match self.resident {
            Some(r) if r != n => Err(RenderError::NoForward { why: "the device map and the host map differ in size (release the device map before changing the host's)" }),
            Some(_) => Ok(true),
            None => Ok(false),
        }
    }

    /// Hands the map to the device optimiser: uploads the parameters, the gradients with the
    /// densification statistics (which then accumulate on the device) and the Adam moments
    /// of `adam` (one group per [`ParamGroup`]). From here until [`Self::release`] the device
    /// copy is the map: [`Self::forward_on_device`] and [`Self::forward`] render it without an
    /// upload, [`Self::loss_and_backward`] zeroes the parameter gradients on the device and
    /// reads none back, and [`Self::adam_step`] updates it and reads nothing back (the host's
    /// parameters are behind until [`Self::sync`]).
    pub fn make_resident(&mut self, ctx: &mut GpuContext, gaussians: &Gaussians, grads: &GaussianGrads, adam: &[AdamGroup]) -> Result<(), VulkanRenderError> {
        let n = gaussians.len();
        if grads.len() != n {
            return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: n }.into());
        }
        validate_gaussians(gaussians)?;
        self.resident = None;
        self.fwd.forget_geometry_ahead();
        self.fwd.projection.upload(ctx, gaussians)?;
        self.project_backward.upload(ctx, grads)?;
        self.adam.upload_moments(ctx, adam, n)?;
        self.resident = Some(n);
        self.params_stale = false;
        self.disarm_adam();
        Ok(())
    }

    /// Whether the device holds the optimiser's map ([`Self::make_resident`]).
    pub fn is_resident(&self) -> bool {
        self.resident.is_some()
    }

    /// Whether the host's parameters are behind the resident device map's (steps since the
    /// last [`Self::sync`]).
    pub fn host_params_stale(&self) -> bool {
        self.resident.is_some() && self.params_stale
    }

    /// Reads the device map's parameters into `gaussians` (when they changed since the host
    /// last had them), its gradients, densification statistics and Adam moments into `grads`
    /// and `adam`; the map stays resident. Nothing to do when it is not.
    pub fn sync(&mut self, ctx: &GpuContext, gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<(), VulkanRenderError> {
        let Some(n) = self.resident else { return Ok(()) };
        if grads.len() != n || gaussians.len() != n {
            return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: n }.into());
        }
        if self.params_stale {
            self.fwd.projection.read_params(ctx, gaussians)?;
            self.params_stale = false;
        }
        self.project_backward.read(ctx, grads)?;
        self.adam.read_moments(ctx, adam, n)?;
        Ok(())
    }

    /// [`Self::sync`], then the host copy is the map again (before the host changes it:
    /// densification, pruning, new keyframes).
    pub fn release(&mut self, ctx: &GpuContext, gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<(), VulkanRenderError> {
        self.sync(ctx, gaussians, grads, adam)?;
        self.resident = None;
        self.fwd.forget_geometry_ahead();
        self.disarm_adam();
        Ok(())
    }

    /// Forgets the device map without reading it (the host replaced the whole map).
    pub fn drop_resident(&mut self) {
        self.resident = None;
        self.params_stale = false;
        self.fwd.forget_geometry_ahead();
        self.disarm_adam();
    }

    fn disarm_adam(&mut self) {
        self.adam_armed = false;
        self.fused_adam = None;
    }

    /// The view the step after the next [`Self::loss_and_backward`] renders, if known
    /// (`Mapper::iterate` draws its keyframe ahead): that call then submits the view's geometry
    /// after the step's Adam ([`GpuForwardRenderer::submit_geometry_ahead`]; with the Adam step
    /// armed and the device medium only), and the device runs it while the host finishes the
    /// step. The next deferred forward of that view skips it; any other is rendered as always.
    pub fn plan_next_view(&mut self, camera: &PinholeCamera, cam_from_world: &Se3, config: &RenderConfig, n: usize) {
        self.next_view = Some(AheadView { camera: *camera, cam_from_world: *cam_from_world, config: *config, n });
    }

    /// The constants of each group's next step (one group per [`ParamGroup`]).
    fn write_next_step_constants(&self, ctx: &mut GpuContext, adam: &[AdamGroup]) -> Result<(), GpuError> {
        let consts: [StepConstants; 6] = std::array::from_fn(|k| adam[k].next_step_constants());
        self.adam.write_constants(ctx, &consts)
    }

    /// Makes the next [`Self::loss_and_backward`] end with the Adam step of the resident map
    /// (its constants from `adam` written now), in the same submission, so that
    /// [`Self::adam_step`] then only counts it (or reports it refused) instead of submitting
    /// it. A loss that is not finite is still an error after that step was taken (or refused
    /// for a non-finite gradient).
    pub fn arm_adam_step(&mut self, ctx: &mut GpuContext, adam: &[AdamGroup]) -> Result<(), VulkanRenderError> {
        if self.resident.is_none() || adam.len() != ParamGroup::ALL.len() {
            return Err(RenderError::NoForward { why: "the map is not on the device (make_resident)" }.into());
        }
        self.write_next_step_constants(ctx, adam)?;
        self.adam_armed = true;
        self.fused_adam = None;
        Ok(())
    }

    /// One Adam step of every parameter group on the device map with the gradients of the
    /// last [`Self::loss_and_backward`]; each group's step is counted, nothing is read back
    /// (the host's copy of the map, `gaussians`, only sized, is behind until [`Self::sync`]).
    /// Returns `false`, changing nothing, when a gradient is not finite (as `AdamGroup::step`
    /// refuses it).
    pub fn adam_step(&mut self, ctx: &mut GpuContext, gaussians: &Gaussians, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        let Some(n) = self.resident else {
            return Err(RenderError::NoForward { why: "the map is not on the device (make_resident)" }.into());
        };
        if gaussians.len() != n || adam.len() != ParamGroup::ALL.len() {
            return Err(RenderError::NoForward { why: "the device map and the host map differ in size" }.into());
        }
        if let Some(taken) = self.fused_adam.take() {
            // Already run, at the end of the loss's submission (`arm_adam_step`).
            if taken {
                adam.iter_mut().for_each(AdamGroup::count_step);
                self.params_stale = true;
            }
            return Ok(taken);
        }
        // A step of its own changes the map a geometry submitted ahead projected.
        self.fwd.forget_geometry_ahead();
        self.write_next_step_constants(ctx, adam)?;
        ctx.begin()?;
        self.adam.record_step(ctx, &self.fwd.projection.params, &self.project_backward.grads, self.fwd.projection.scan.status.range(), n)?;
        ctx.submit_and_wait()?;
        if self.adam.step_refused(ctx)? {
            return Ok(false);
        }
        adam.iter_mut().for_each(AdamGroup::count_step);
        self.params_stale = true;
        Ok(true)
    }

    /// Reads the gradients of the last backward into `grads` (e.g. to name a non-finite one).
    pub fn read_grads(&mut self, ctx: &GpuContext, grads: &mut GaussianGrads) -> Result<(), VulkanRenderError> {
        Ok(self.project_backward.read(ctx, grads)?)
    }

    fn remember(&mut self, camera: &PinholeCamera, config: &RenderConfig, n_gaussians: usize, n_isects: usize) {
        self.last = Some(GpuForwardState {
            grid: TileGrid::new(camera.width, camera.height),
            intrinsics: [camera.fx as f32, camera.fy as f32, camera.cx as f32, camera.cy as f32],
            depth_mode: config.depth_mode,
            n_gaussians,
            n_isects,
        });
    }

    /// The loss of the last forward against `target` and its backward, on the device with no
    /// image crossing to the host: `loss.wgsl` writes the upstream gradients where
    /// `rasterize_backward` reads them, one submission from the loss to `project_backward`.
    /// **Adds** the parameter gradients and densification statistics into `grads`,
    /// **overwrites** `medium_grads` (the renderer's) and `d_medium_loss` (the loss's own
    /// dL/dmedium, the medium prior on `c_med`). Returns the loss terms and the PSNR (dB).
    /// CPU twin: `total_loss` then `RasterWorkspace::backward` ([`RenderBackend::loss_and_backward`]).
    #[allow(clippy::too_many_arguments)]
    pub fn loss_and_backward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        target: &crate::loss::TargetView,
        target_key: Option<loss::TargetKey>,
        loss_config: &crate::loss::LossConfig,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
        d_medium_loss: &mut crate::medium::MediumPlanes,
        device_medium: Option<&mut DeviceMediumBackward>,
    ) -> Result<(crate::loss::LossTerms, f64), VulkanRenderError> {
        let last = self.last.ok_or(RenderError::NoForward { why: "no successful forward pass in this renderer" })?;
        let grid = last.grid;
        if gaussians.len() != last.n_gaussians {
            return Err(RenderError::NoForward { why: "the map changed size since the forward pass" }.into());
        }
        if grads.len() != gaussians.len() {
            return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: gaussians.len() }.into());
        }
        for (_, plane) in medium_grads.planes() {
            check_size("medium planes", plane.width, plane.height, &grid)?;
        }
        check_size("loss dL/dmedium", d_medium_loss.width, d_medium_loss.height, &grid)?;
        let _span = tracing::debug_span!("map.gpu_loss_backward", intersections = last.n_isects).entered();
        let (w, h) = (grid.width, grid.height);
        self.loss.upload_target(ctx, target, target_key)?;
        let n = last.n_gaussians;
        let resident = self.check_resident(n)?;
        let fuse_adam = std::mem::take(&mut self.adam_armed) && resident;
        self.fused_adam = None;
        if !resident {
            self.project_backward.upload(ctx, grads)?;
        }
        ctx.begin()?;
        if resident {
            self.project_backward.record_zero_params(ctx, n)?;
        }
        let fwd = &self.fwd;
        let bufs = loss::LossBuffers {
            colour: &fwd.raster.colour,
            scalars: &fwd.raster.scalars,
            c_med: Some(&fwd.raster.c_med),
            up_colour: &self.raster_backward.up_colour,
            up_scalars: &self.raster_backward.up_scalars,
        };
        self.loss.record(ctx, &bufs, w, h, loss_config)?;
        ctx.fill(self.raster_backward.up_restored.range(), 0)?;
        self.raster_backward.record(
            ctx,
            &fwd.projection.splats,
            &fwd.projection.isect_offsets,
            &fwd.binning,
            &fwd.raster,
            &grid,
            last.intrinsics,
            last.depth_mode,
            n,
        )?;
        self.project_backward.record(ctx, &fwd.projection, &self.raster_backward, n)?;
        let device_medium = match (device_medium, self.medium.as_ref()) {
            (Some(step), Some(gm)) => {
                let (r, rb) = (&fwd.raster, &self.raster_backward);
                let planes = medium::MediumPlaneBuffers {
                    c_med: &r.c_med,
                    sigma_att: &r.sigma_att,
                    sigma_bs: &r.sigma_bs,
                    grad_c_med: &rb.grad_c_med,
                    grad_sigma_att: &rb.grad_sigma_att,
                    grad_sigma_bs: &rb.grad_sigma_bs,
                    loss_d_c_med: &self.loss.d_c_med,
                };
                medium::record_medium_upstream(ctx, &planes, w * h, step.prior, step.single_coefficient)?;
                gm.record_zero_grads(ctx)?;
                gm.record_backward(ctx, &rb.grad_c_med, &rb.grad_sigma_att, &rb.grad_sigma_bs)?;
                Some((step, gm))
            }
            (Some(_), None) => return Err(RenderError::NoForward { why: "no device medium (GpuRenderer::enable_medium)" }.into()),
            (None, _) => None,
        };
        if fuse_adam {
            self.adam.record_step(ctx, &fwd.projection.params, &self.project_backward.grads, fwd.projection.scan.status.range(), n)?;
            self.adam.prefetch_refused(ctx)?;
        }
        self.loss.prefetch_terms(ctx)?;
        if let Some((_, gm)) = device_medium.as_ref() {
            gm.prefetch_grads(ctx)?;
        }
        match self.next_view.take() {
            // The next step's geometry runs on the device while the host reads this step's
            // results (copied for it in this submission) and finishes the step.
            Some(v) if fuse_adam && device_medium.is_some() && v.n == n => {
                ctx.submit()?;
                self.fwd.submit_geometry_ahead(ctx, n, &v.camera, &v.cam_from_world, &v.config)?;
            }
            _ => ctx.submit_and_wait()?,
        }
        if std::mem::take(&mut self.count_pending) {
            // The deferred forward's count: after an overflow nothing of this step counts
            // (its render had no intersection, Adam did not step).
            let total = match n {
                0 => 0,
                _ => match self.fwd.projection.scan.result(ctx)? {
                    Ok(total) => total as usize,
                    Err(needed) => {
                        self.last = None;
                        return Err(RenderError::TileOverflow { needed, capacity: self.fwd.capacity.max_intersections }.into());
                    }
                },
            };
            if let Some(l) = self.last.as_mut() {
                l.n_isects = total;
            }
        }
        if fuse_adam {
            self.fused_adam = Some(!self.adam.step_refused(ctx)?);
        }
        let terms = self.loss.read_terms(ctx)?;
        if !resident {
            self.project_backward.read(ctx, grads)?;
        }
        if let Some((step, gm)) = device_medium {
            // The medium's parameter gradient is all that comes back of it.
            gm.read_grads(ctx, step.param_grads)?;
            return Ok((terms, self.loss.last_psnr_db()));
        }
        ctx.read(&self.raster_backward.grad_c_med, &mut medium_grads.c_med.data)?;
        ctx.read(&self.raster_backward.grad_sigma_att, &mut medium_grads.sigma_att.data)?;
        ctx.read(&self.raster_backward.grad_sigma_bs, &mut medium_grads.sigma_bs.data)?;
        // The loss's dL/dmedium has only the c_med channels (the medium prior).
        let staging = &mut self.staging_c_med[..3 * w * h];
        ctx.read(&self.loss.d_c_med, staging)?;
        for (px, d) in d_medium_loss.data.chunks_exact_mut(MEDIUM_CHANNELS).zip(staging.chunks_exact(3)) {
            px.fill(0.0);
            px[C_MED..C_MED + 3].copy_from_slice(d);
        }
        Ok((terms, self.loss.last_psnr_db()))
    }

    /// [`GpuForwardRenderer::forward`], remembered for [`Self::backward`].
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.last = None;
        // A resident map is rendered as the device holds it (the host's may be behind).
        let on_device = self.check_resident(gaussians.len())?;
        let stats = self.fwd.forward_impl(ctx, gaussians, camera, cam_from_world, MediumSource::Host(medium), config, Some(out), on_device, false)?;
        self.remember(camera, config, gaussians.len(), stats.intersections);
        Ok(stats)
    }

    /// Differentiates the last [`Self::forward`] for the upstream gradients, as
    /// [`crate::render::RasterWorkspace::backward`] does on the CPU (same checks, same
    /// errors): **adds** the parameter gradients and densification statistics into `grads`
    /// and **overwrites** `medium_grads`. One submission: `rasterize_backward`,
    /// `reduce_isect_grads`, `project_backward`.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        medium: &MediumPlanes,
        out: &RenderOutput,
        upstream: &RenderUpstream,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
    ) -> Result<(), VulkanRenderError> {
        let last = self.last.ok_or(RenderError::NoForward { why: "no successful forward pass in this renderer" })?;
        if self.fwd.ahead.is_some() {
            return Err(RenderError::NoForward { why: "the next step's geometry, submitted ahead, replaced this forward's (plan_next_view)" }.into());
        }
        let grid = last.grid;
        check_backward_inputs(last.n_gaussians, &grid, gaussians, medium, out, upstream, grads, medium_grads)?;

        let _span = tracing::debug_span!("map.gpu_backward", intersections = last.n_isects).entered();
        let n = last.n_gaussians;
        self.raster_backward.upload_upstream(ctx, upstream)?;
        self.project_backward.upload(ctx, grads)?;
        ctx.begin()?;
        let fwd = &self.fwd;
        self.raster_backward.record(
            ctx,
            &fwd.projection.splats,
            &fwd.projection.isect_offsets,
            &fwd.binning,
            &fwd.raster,
            &grid,
            last.intrinsics,
            last.depth_mode,
            n,
        )?;
        self.project_backward.record(ctx, &fwd.projection, &self.raster_backward, n)?;
        ctx.submit_and_wait()?;
        self.project_backward.read(ctx, grads)?;
        ctx.read(&self.raster_backward.grad_c_med, &mut medium_grads.c_med.data)?;
        ctx.read(&self.raster_backward.grad_sigma_att, &mut medium_grads.sigma_att.data)?;
        ctx.read(&self.raster_backward.grad_sigma_bs, &mut medium_grads.sigma_bs.data)?;
        Ok(())
    }
}

