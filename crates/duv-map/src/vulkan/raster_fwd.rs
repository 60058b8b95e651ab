//! Rasterisation forward with the medium on the device (`rasterize.wgsl`), twin of
//! `render::raster_fwd`: [`GpuRasterForward`] and the pixel-pairs policy.

use super::*;
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::render::{
    DepthMode, MediumPlanes, RenderOutput, TileGrid,
};

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
