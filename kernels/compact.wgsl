// Pruning as stream compaction (CPU references: `Gaussians::retain`, `GaussianGrads::retain`,
// `AdamGroup::retain` / `retain_strided` in src/map/adam.rs; the prune rule of
// `densify_and_prune` in src/map/densify.rs). Two kernels around the prefix sum of
// `prefix_sum.wgsl` (host: `map::vulkan::compact::GpuCompaction`):
//   keep_flags  one thread per Gaussian: flags[i] = 1 when the Gaussian survives the prune
//               rule, else 0
//   (then `gpu::ops::record_exclusive_scan` of the flags: offsets[0..=n], offsets[n] = kept)
//   scatter     one workgroup per 256 items of a buffer of n items x `stride` 32-bit values,
//               its threads on consecutive values: item i's values go from i * stride to
//               offsets[i] * stride when it is kept, out of place (in place would race);
//               values from kept * stride on are copied unchanged, so the whole destination
//               [0, n * stride) is written and equals the CPU's in-place `retain_strided`,
//               stale tail included.
// Every buffer is bound as words (`array<u32>`): f32 and u32 buffers alike, moved bit for bit
// (NaN payloads, subnormals and -0 included), and the prune rule compares bit patterns, so
// nothing depends on the device's float rounding, NaN handling or denormal flushing.

// --- keep_flags ---------------------------------------------------------------------------
// The CPU rule, per Gaussian:
//   keep = sigmoid(opacity_logit) as f64 >= prune_min_opacity
//       && exp(fold(f32::MIN, max)(log_scale[0..3])) as f64 <= prune_max_scale_m
// Both sides are monotone in one f32 input, so the host (`PruneThresholds::new`) turns them
// into exact thresholds on the inputs by bisection over the CPU functions themselves, as
// order keys (below): opacity key >= min_opacity_key (a NaN opacity fails, as on the CPU) and
// the key of the largest log scale, NaNs skipped and f32::MIN as the start (Rust's f32::max
// returns the other argument when one is NaN), <= max_log_scale_key.

struct FlagParams {
    n: u32,
    // Opacity logit of Gaussian i at opacity_src[i * opacity_stride + opacity_offset].
    opacity_stride: u32,
    opacity_offset: u32,
    // Log scales of Gaussian i at scale_src[i * scale_stride + scale_offset + 0..3].
    scale_stride: u32,
    scale_offset: u32,
    min_opacity_key: u32,
    max_log_scale_key: u32,
    pad: u32,
}

// --- scatter ------------------------------------------------------------------------------

struct ScatterParams {
    n: u32,
    // Values per item; n * stride < 2^32 (checked by the host).
    stride: u32,
    pad0: u32,
    pad1: u32,
}

var<immediate> flag_params: FlagParams;
var<immediate> scatter_params: ScatterParams;

@group(0) @binding(0) var<storage, read> opacity_src: array<u32>;
@group(0) @binding(1) var<storage, read> scale_src: array<u32>;
@group(0) @binding(2) var<storage, read_write> flags: array<u32>;

// Exclusive offsets of the flags, n + 1 entries (offsets[n] = kept).
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read> src: array<u32>;
@group(0) @binding(5) var<storage, read_write> dst: array<u32>;

const WG: u32 = 256u;
// Order key of f32::MIN (bits 0xff7fffff).
const F32_MIN_KEY: u32 = 0x00800000u;

// Maps f32 bits to a u32 whose unsigned order is the float order (-0 just below +0); NaNs
// land outside [key(-inf), key(+inf)] and are tested separately.
fn order_key(bits: u32) -> u32 {
    if ((bits & 0x80000000u) != 0u) {
        return ~bits;
    }
    return bits | 0x80000000u;
}

fn is_nan(bits: u32) -> bool {
    return (bits & 0x7fffffffu) > 0x7f800000u;
}

// Linear thread index of a 2D grid (past 65535 workgroups: rows of groups.x).
fn linear_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.y * groups.x * WG + gid.x;
}

@compute @workgroup_size(256)
fn keep_flags(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    if (i >= flag_params.n) {
        return;
    }
    let o = opacity_src[i * flag_params.opacity_stride + flag_params.opacity_offset];
    let opaque = !is_nan(o) && order_key(o) >= flag_params.min_opacity_key;
    var largest = F32_MIN_KEY;
    let base = i * flag_params.scale_stride + flag_params.scale_offset;
    for (var k = 0u; k < 3u; k = k + 1u) {
        let s = scale_src[base + k];
        if (!is_nan(s) && order_key(s) > largest) {
            largest = order_key(s);
        }
    }
    let small = largest <= flag_params.max_log_scale_key;
    flags[i] = select(0u, 1u, opaque && small);
}

// Offsets of the workgroup's items and the next one (items first .. first + 256).
var<workgroup> tile_offsets: array<u32, 257>;

@compute @workgroup_size(256)
fn scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32, @builtin(num_workgroups) groups: vec3<u32>) {
    // One workgroup per 256 items (rows of groups.x workgroups past 65535); its threads walk
    // the items' values side by side, 256 consecutive values per step.
    let first = (wg.y * groups.x + wg.x) * WG;
    let n = scatter_params.n;
    if (first >= n) {
        return;
    }
    let items = min(WG, n - first);
    if (t <= items) {
        tile_offsets[t] = offsets[first + t];
    }
    if (t == 0u && items == WG) {
        tile_offsets[WG] = offsets[first + WG];
    }
    workgroupBarrier();
    let stride = scatter_params.stride;
    let tail = offsets[n] * stride;
    let base = first * stride;
    let values = items * stride;
    // Item and component of local value v = t + 256 s, advanced without a division per value.
    var item = t / stride;
    var component = t - item * stride;
    let step_items = WG / stride;
    let step_components = WG - step_items * stride;
    for (var v = t; v < values; v = v + WG) {
        let j = base + v;
        let x = src[j];
        let out = tile_offsets[item];
        if (tile_offsets[item + 1u] != out) {
            dst[out * stride + component] = x;
        }
        // The kept items fill [0, kept * stride); the rest keeps its values, as the CPU's
        // in-place compaction leaves them.
        if (j >= tail) {
            dst[j] = x;
        }
        item = item + step_items;
        component = component + step_components;
        if (component >= stride) {
            component = component - stride;
            item = item + 1u;
        }
    }
}
