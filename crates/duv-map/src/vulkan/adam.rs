//! One Adam step of the resident map on the device (`adam.wgsl`), twin of `crate::adam`:
//! [`record_adam_step`].

use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::adam::StepConstants;

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
