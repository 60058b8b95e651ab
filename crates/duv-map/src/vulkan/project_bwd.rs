//! Projection backward on the device (`project_backward.wgsl`), twin of `render::project_bwd`:
//! [`GpuProjectBackward`].

use super::*;
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::gaussians::{GaussianGrads, ParamGroup, PARAMS_PER_GAUSSIAN};

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
