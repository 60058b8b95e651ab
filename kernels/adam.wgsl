// One Adam step, one thread per value (CPU reference: `adam_update` in `AdamGroup::step`,
// src/map/adam.rs; constants from `StepConstants::new`, the immediate block in its field
// order):
//   m <- beta1 m + (1 - beta1) g;  v <- beta2 v + (1 - beta2) g^2
//   p <- p - step_size m / (sqrt(v) inv_sqrt_bias2 + eps)

struct AdamParams {
    beta1: f32,
    one_minus_beta1: f32,
    beta2: f32,
    one_minus_beta2: f32,
    step_size: f32,
    inv_sqrt_bias2: f32,
    eps: f32,
    n: u32,
}

var<immediate> params: AdamParams;

@group(0) @binding(0) var<storage, read_write> values: array<f32>;
@group(0) @binding(1) var<storage, read> grads: array<f32>;
@group(0) @binding(2) var<storage, read_write> m1: array<f32>;
@group(0) @binding(3) var<storage, read_write> m2: array<f32>;

@compute @workgroup_size(256)
fn adam_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    // 2D grid for more than 65535 workgroups.
    let i = gid.y * groups.x * 256u + gid.x;
    if (i >= params.n) {
        return;
    }
    let g = grads[i];
    let m = params.beta1 * m1[i] + params.one_minus_beta1 * g;
    let v = params.beta2 * m2[i] + params.one_minus_beta2 * g * g;
    m1[i] = m;
    m2[i] = v;
    values[i] = values[i] - params.step_size * m / (sqrt(v) * params.inv_sqrt_bias2 + params.eps);
}
