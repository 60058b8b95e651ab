//! Adam over the map on the device (`kernels/adam_map.wgsl`): the twin of one
//! [`AdamGroup::step`] per parameter group, with the map, its gradients and both moments
//! resident on the device in the renderer's interleaved layout
//! ([`PARAMS_PER_GAUSSIAN`] floats per Gaussian, `GaussianParam::to_array` order).
//!
//! The host keeps the step counts and the configuration ([`AdamGroup`]); the moments live on
//! the device between [`GpuMapAdam::upload_moments`] and [`GpuMapAdam::read_moments`], which
//! convert between the host's one-buffer-per-group layout and the device's interleaved one.
//! A step whose gradients hold a non-finite value is refused as the CPU refuses it: the
//! `check_grads` pass raises a flag, `map_step` then changes nothing, and
//! [`GpuMapAdam::step_refused`] reports it after the submission.

use duv_gpu::{GpuBuffer, GpuContext, GpuError, GpuRange};
use super::kernels::Kernel;
use crate::adam::{AdamGroup, StepConstants};
use crate::gaussians::{ParamGroup, PARAMS_PER_GAUSSIAN};

/// Parameter groups ([`ParamGroup::ALL`]).
const GROUPS: usize = ParamGroup::ALL.len();
/// Floats per group in the constants buffer (`GroupConsts` of `adam_map.wgsl`).
const CONST_FLOATS: usize = 8;
/// Gaussians per invocation of the CPU-device kernels (`map_step_quads`).
const QUAD: usize = 4;

/// The device half of the map's optimiser for up to `capacity` Gaussians.
pub struct GpuMapAdam {
    capacity: usize,
    /// First and second moments, interleaved like the parameters.
    pub m: GpuBuffer<f32>,
    pub v: GpuBuffer<f32>,
    consts: GpuBuffer<[f32; CONST_FLOATS]>,
    group_of: GpuBuffer<u32>,
    flag: GpuBuffer<u32>,
    /// Host staging of one interleaved moment buffer (allocated once).
    staging: Vec<f32>,
    /// Four Gaussians per invocation (`check_grads_quads`, `map_step_quads`) instead of one
    /// value; the same bits. `None`: on a CPU device (lavapipe loads buffer values lane by
    /// lane; this reads the flag, the groups and their constants once per invocation instead
    /// of once per value).
    pub quads: Option<bool>,
}

impl GpuMapAdam {
    pub fn new(ctx: &mut GpuContext, capacity: usize) -> Result<Self, GpuError> {
        let group_of = ctx.alloc("Adam group of each offset", PARAMS_PER_GAUSSIAN)?;
        let mut table = [0u32; PARAMS_PER_GAUSSIAN];
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            table[g.offset()..g.offset() + g.width()].fill(k as u32);
        }
        ctx.write(&group_of, &table)?;
        Ok(GpuMapAdam {
            capacity,
            m: ctx.alloc("Adam first moments of the map", capacity * PARAMS_PER_GAUSSIAN)?,
            v: ctx.alloc("Adam second moments of the map", capacity * PARAMS_PER_GAUSSIAN)?,
            consts: ctx.alloc("Adam step constants per group", GROUPS)?,
            group_of,
            flag: ctx.alloc("Adam non-finite gradient flag", 1)?,
            staging: vec![0.0; capacity * PARAMS_PER_GAUSSIAN],
            quads: None,
        })
    }

    fn check(&self, n: usize) -> Result<(), GpuError> {
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: "Adam moments of the map", requested: n, len: self.capacity });
        }
        Ok(())
    }

    /// Uploads the moments of the `n` live Gaussians of `groups` (one per [`ParamGroup`]).
    pub fn upload_moments(&mut self, ctx: &mut GpuContext, groups: &[AdamGroup], n: usize) -> Result<(), GpuError> {
        self.check(n)?;
        check_groups(groups.len())?;
        for which in 0..2 {
            for (k, g) in ParamGroup::ALL.iter().enumerate() {
                let (w, off) = (g.width(), g.offset());
                let (m, v) = groups[k].moments();
                let src = if which == 0 { m } else { v };
                if src.len() < n * w {
                    return Err(GpuError::OutOfRange { what: "host Adam moments", requested: n * w, len: src.len() });
                }
                for (i, chunk) in src[..n * w].chunks_exact(w).enumerate() {
                    self.staging[i * PARAMS_PER_GAUSSIAN + off..i * PARAMS_PER_GAUSSIAN + off + w].copy_from_slice(chunk);
                }
            }
            let dst = if which == 0 { &self.m } else { &self.v };
            ctx.write(dst, &self.staging[..n * PARAMS_PER_GAUSSIAN])?;
        }
        Ok(())
    }

    /// Reads the moments of the `n` live Gaussians back into `groups`.
    pub fn read_moments(&mut self, ctx: &GpuContext, groups: &mut [AdamGroup], n: usize) -> Result<(), GpuError> {
        self.check(n)?;
        check_groups(groups.len())?;
        for which in 0..2 {
            let src = if which == 0 { &self.m } else { &self.v };
            ctx.read(src, &mut self.staging[..n * PARAMS_PER_GAUSSIAN])?;
            for (k, g) in ParamGroup::ALL.iter().enumerate() {
                let (w, off) = (g.width(), g.offset());
                let (m, v) = groups[k].moments_mut();
                let dst = if which == 0 { m } else { v };
                if dst.len() < n * w {
                    return Err(GpuError::OutOfRange { what: "host Adam moments", requested: n * w, len: dst.len() });
                }
                for (i, chunk) in dst[..n * w].chunks_exact_mut(w).enumerate() {
                    chunk.copy_from_slice(&self.staging[i * PARAMS_PER_GAUSSIAN + off..i * PARAMS_PER_GAUSSIAN + off + w]);
                }
            }
        }
        Ok(())
    }

    /// Writes the step constants of every group (before `begin()`).
    pub fn write_constants(&self, ctx: &mut GpuContext, k: &[StepConstants; GROUPS]) -> Result<(), GpuError> {
        let words = k.map(|c| [c.beta1, c.one_minus_beta1, c.beta2, c.one_minus_beta2, c.step_size, c.inv_sqrt_bias2, c.eps, 0.0]);
        ctx.write(&self.consts, &words)
    }

    /// Records one step over `n` Gaussians of `params` with `grads` (same layout): the
    /// gradient check, then the update unless it raised the flag.
    /// `render_status`: the status of the render's tile-count scan (`[overflow, ...]`); after
    /// an overflow the step is not taken ([`Self::step_refused`]).
    pub fn record_step(&self, ctx: &mut GpuContext, params: &GpuBuffer<f32>, grads: &GpuBuffer<f32>, render_status: GpuRange, n: usize) -> Result<(), GpuError> {
        self.check(n)?;
        let values = n * PARAMS_PER_GAUSSIAN;
        for b in [params, grads] {
            if b.len() < values {
                return Err(GpuError::OutOfRange { what: b.what(), requested: values, len: b.len() });
            }
        }
        ctx.fill(self.flag.range(), 0)?;
        if n == 0 {
            return Ok(());
        }
        let imm = [values as u32, PARAMS_PER_GAUSSIAN as u32, 0, 0];
        let quads = self.quads.unwrap_or(ctx.info().is_cpu());
        let (items, size) = if quads { (n.div_ceil(QUAD), 64) } else { (values, 256) };
        let groups = items.div_ceil(size);
        let gx = groups.min(65535);
        let grid = [gx as u32, groups.div_ceil(gx) as u32, 1];
        let lookup = |name: &str| -> Option<GpuRange> {
            Some(match name {
                "values" => params.range(),
                "grads" => grads.range(),
                "m1" => self.m.range(),
                "m2" => self.v.range(),
                "flag" => self.flag.range(),
                "consts" => self.consts.range(),
                "group_of" => self.group_of.range(),
                "render_status" => render_status,
                _ => return None,
            })
        };
        let (check, step) = if quads { (Kernel::AdamMapCheckGradsQuads, Kernel::AdamMapMapStepQuads) } else { (Kernel::AdamMapCheckGrads, Kernel::AdamMapMapStep) };
        ctx.dispatch_named(check, lookup, bytemuck::cast_slice(&imm), grid)?;
        ctx.dispatch_named(step, lookup, bytemuck::cast_slice(&imm), grid)
    }

    /// After the submission of [`Self::record_step`]: whether the step was refused for a
    /// non-finite gradient (nothing changed then).
    /// Records the refusal flag for the host in the step's submission ([`GpuContext::prefetch`]).
    pub fn prefetch_refused(&self, ctx: &mut GpuContext) -> Result<(), GpuError> {
        ctx.prefetch(self.flag.range())
    }

    pub fn step_refused(&self, ctx: &GpuContext) -> Result<bool, GpuError> {
        let mut flag = [0u32];
        ctx.read_prefetched(&self.flag, &mut flag)?;
        Ok(flag[0] != 0)
    }
}

fn check_groups(len: usize) -> Result<(), GpuError> {
    if len != GROUPS {
        return Err(GpuError::OutOfRange { what: "Adam parameter groups", requested: GROUPS, len });
    }
    Ok(())
}
