//! Rasterisation backward on the device (`rasterize_backward.wgsl`), twin of
//! `render::raster_bwd`: [`GpuRasterBackward`].

use super::*;
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::render::{
    DepthMode, MediumPlanes, RenderUpstream, SplatGrad, TileGrid,
};

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
