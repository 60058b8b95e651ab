// Adam over the whole map on the device, every parameter group in one pass (CPU reference:
// `AdamGroup::step` per group, src/map/adam.rs, `adam_update`; the same per-value update as
// `adam.adam_step`). The map is interleaved, `stride` (23) floats per Gaussian in
// `GaussianParam::to_array` order, its gradients and both moments in the same layout;
// `group_of[o]` is the parameter group of offset o and `consts[group]` its step constants
// (`StepConstants::new` for the group's next step).
//
//   check_grads   one invocation per value: any non-finite gradient sets flag[0] bit 1 (u32
//                 atomic, exact; the CPU refuses such a step), a tile overflow of the render
//                 bit 2
//   map_step      one invocation per value; does nothing when flag[0] is set, so a refused
//                 step changes nothing

struct MapParams {
    n_values: u32,
    stride: u32,
    pad0: u32,
    pad1: u32,
}

// One group's constants, the field order of `StepConstants`.
struct GroupConsts {
    beta1: f32,
    one_minus_beta1: f32,
    beta2: f32,
    one_minus_beta2: f32,
    step_size: f32,
    inv_sqrt_bias2: f32,
    eps: f32,
    pad: f32,
}

var<immediate> params: MapParams;

@group(0) @binding(0) var<storage, read_write> values: array<f32>;
@group(0) @binding(1) var<storage, read> grads: array<f32>;
@group(0) @binding(2) var<storage, read_write> m1: array<f32>;
@group(0) @binding(3) var<storage, read_write> m2: array<f32>;
@group(0) @binding(4) var<storage, read_write> flag: array<atomic<u32>>;
@group(0) @binding(5) var<storage, read> consts: array<GroupConsts>;
@group(0) @binding(6) var<storage, read> group_of: array<u32>;
// The render's tile-count scan status ([overflow, ...]): after an overflow the step is not
// taken (flag bit 2), its gradients are those of a render that did not happen.
@group(0) @binding(7) var<storage, read> render_status: array<u32>;

fn value_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    // 2D grid for more than 65535 workgroups.
    return gid.y * groups.x * 256u + gid.x;
}

@compute @workgroup_size(256)
fn check_grads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = value_index(gid, groups);
    if (i >= params.n_values) {
        return;
    }
    if ((bitcast<u32>(grads[i]) & 0x7f800000u) == 0x7f800000u) {
        atomicOr(&flag[0], 1u);
    }
    if (i == 0u && render_status[0] != 0u) {
        atomicOr(&flag[0], 2u);
    }
}

@compute @workgroup_size(256)
fn map_step(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = value_index(gid, groups);
    if (i >= params.n_values || atomicLoad(&flag[0]) != 0u) {
        return;
    }
    update(i, consts[group_of[i % params.stride]]);
}

// Value i's Adam update with its group's constants k (`adam_update`).
fn update(i: u32, k: GroupConsts) {
    let g = grads[i];
    let m = k.beta1 * m1[i] + k.one_minus_beta1 * g;
    let v = k.beta2 * m2[i] + k.one_minus_beta2 * g * g;
    m1[i] = m;
    m2[i] = v;
    values[i] = values[i] - k.step_size * m / (sqrt(v) * k.inv_sqrt_bias2 + k.eps);
}


// --- CPU-device variants (`GpuMapAdam::quads`) ---------------------------------------------
// On a CPU device (lavapipe: every buffer access is a loop over the lanes) one invocation per
// value spends most of its time loading the flag, the value's group and the group's
// constants. These take four Gaussians per invocation: the flag is read once, the group of
// each offset and every group's constants once into private arrays. The same arithmetic per
// value as `check_grads` / `map_step`, so the same bits.

const QUAD: u32 = 4u;

@compute @workgroup_size(64)
fn check_grads_quads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let q = gid.y * groups.x * 64u + gid.x;
    let first = q * QUAD * params.stride;
    if (first >= params.n_values) {
        return;
    }
    let last = min(first + QUAD * params.stride, params.n_values);
    var bad = false;
    for (var i = first; i < last; i++) {
        bad = bad || (bitcast<u32>(grads[i]) & 0x7f800000u) == 0x7f800000u;
    }
    if (bad) {
        atomicOr(&flag[0], 1u);
    }
    if (q == 0u && render_status[0] != 0u) {
        atomicOr(&flag[0], 2u);
    }
}

@compute @workgroup_size(64)
fn map_step_quads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let q = gid.y * groups.x * 64u + gid.x;
    let first = q * QUAD * params.stride;
    if (first >= params.n_values || atomicLoad(&flag[0]) != 0u) {
        return;
    }
    var k: array<GroupConsts, 8>;
    for (var g = 0u; g < 8u; g++) {
        k[g] = consts[min(g, arrayLength(&consts) - 1u)];
    }
    var group: array<u32, 32>;
    for (var o = 0u; o < min(params.stride, 32u); o++) {
        group[o] = group_of[o];
    }
    let last = min(first + QUAD * params.stride, params.n_values);
    var o = 0u;
    for (var i = first; i < last; i++) {
        update(i, k[group[o]]);
        o += 1u;
        if (o == params.stride) {
            o = 0u;
        }
    }
}
