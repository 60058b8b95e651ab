// The neural medium on a direction grid (CPU reference: `MediumWorkspace::with_grid` and its
// `forward` / `backward`, with `forward_pixel` / `backward_pixel`, src/map/medium.rs; the same
// order of operations). Node (i, j) of the grid sits at pixel (i step, j step); its world
// direction is computed on the host (`View::direction`: lens undistortion) and uploaded.
//
//   nodes                     one workgroup per node, a thread per hidden unit: encoding, two
//                             softplus layers of 64, the heads (sigmoid c_med, softplus
//                             sigma_att and sigma_bs) -> node_out
//   interpolate               one thread per pixel: bilinear from the 4 nodes (`MediumGrid::cell`)
//                             into the rasteriser's three RGB-interleaved planes
//   interpolate_adjoint_rows  one thread per (image row y, node column i): gather over the
//                             pixels of the row in x order (the CPU's row pass) -> d_rows
//   interpolate_adjoint_cols  one thread per node: gather over the rows in y order (the CPU's
//                             column pass) -> d_nodes
//   nodes_backward            one workgroup per node, a thread per hidden unit: recomputes the
//                             forward pass, back-propagates d_nodes and stores the node's
//                             record (below)
//   param_grad_partials       one thread per (parameter, chunk of chunk_nodes nodes): the sum of
//                             activation * delta over the chunk's nodes in node order
//   param_grad_sum            one thread per parameter: the chunks' sums in chunk order, ADDED
//                             into grads (as the CPU backward adds)
//
//   nodes_serial, nodes_backward_serial, param_grad_blocks, interpolate_cells
//                             CPU-device variants (`GpuMedium::serial`), at the end of the file
//
// No atomics: every sum has a fixed order, so two runs on one device are bit-identical.
// Step 1 is the per-pixel network: the interpolation weights are exactly 1 and 0.
//
// Node record (`record` floats per node): [1, x (inputs), h1 (64), h2 (64), d_o (9),
// d_z2 (64), d_z1 (64)]. The gradient of W[i][o] is the sum over nodes of
// act[i] * delta[o]; a bias is the same with the leading 1 as its activation.

const HIDDEN: u32 = 64u;
const CHANNELS: u32 = 9u;
// 3 + 6 MAX_PE_FREQUENCIES.
const MAX_INPUTS: u32 = 75u;

// `GpuMedium`'s immediate words (src/map/vulkan/medium.rs, `dims_words`), in this order.
struct MediumDims {
    width: u32,
    height: u32,
    step: u32,
    nodes_x: u32,
    nodes_y: u32,
    pe_frequencies: u32,
    inputs: u32,
    record: u32,
    // `MediumLayout` offsets into params / grads.
    w1: u32,
    b1: u32,
    w2: u32,
    b2: u32,
    w_heads: u32,
    b_heads: u32,
    len: u32,
    chunk_nodes: u32,
}

var<immediate> dims: MediumDims;

// The flat parameters, `MediumLayout` order (input-major weights: W[o][i] at w[i n_out + o]).
@group(0) @binding(0) var<storage, read> params: array<f32>;
// Unit world direction per node, 3 floats, node n = j nodes_x + i.
@group(0) @binding(1) var<storage, read> dirs: array<f32>;
// Network outputs per node, 9 floats in plane order (c_med, sigma_att, sigma_bs; R G B each).
@group(0) @binding(2) var<storage, read_write> node_out: array<f32>;
// The rasteriser's medium planes, 3 floats per pixel each.
@group(0) @binding(3) var<storage, read_write> c_med: array<f32>;
@group(0) @binding(4) var<storage, read_write> sigma_att: array<f32>;
@group(0) @binding(5) var<storage, read_write> sigma_bs: array<f32>;
// dL/d the planes, same layout.
@group(0) @binding(6) var<storage, read> grad_c_med: array<f32>;
@group(0) @binding(7) var<storage, read> grad_sigma_att: array<f32>;
@group(0) @binding(8) var<storage, read> grad_sigma_bs: array<f32>;
// Row pass of the adjoint: per image row, per node column, 9 floats.
@group(0) @binding(9) var<storage, read_write> d_rows: array<f32>;
// dL/d node outputs, 9 floats per node.
@group(0) @binding(10) var<storage, read_write> d_nodes: array<f32>;
@group(0) @binding(11) var<storage, read_write> records: array<f32>;
// Per chunk of nodes, one sum per parameter: partials[chunk len + p].
@group(0) @binding(12) var<storage, read_write> partials: array<f32>;
@group(0) @binding(13) var<storage, read_write> grads: array<f32>;

// The network with one workgroup per node and one thread per hidden unit: each unit's sum
// over its inputs in input order, as `forward` (and the CPU) adds them, so the values are the
// same as one thread per node would give; the layers meet in workgroup memory.
var<workgroup> wx: array<f32, MAX_INPUTS>;
var<workgroup> wh1: array<f32, HIDDEN>;
var<workgroup> ws1: array<f32, HIDDEN>;
var<workgroup> wh2: array<f32, HIDDEN>;
var<workgroup> ws2: array<f32, HIDDEN>;
var<workgroup> wd_o: array<f32, CHANNELS>;
var<workgroup> wd_z2: array<f32, HIDDEN>;
// W2 in `nodes_backward`, row r at r * W2_ROW: each thread takes a row there, where in
// `params` the rows of 64 threads (64 floats apart) would make each load touch 32 cache
// lines; a stride of 65 puts a row's consecutive values in different banks for the threads.
const W2_ROW: u32 = 65u;
var<workgroup> w2_rows: array<f32, 4160>;

// ln(1 + v), accurate for small v (no log1p in WGSL): log(u) v / (u - 1) with u = 1 + v
// cancels the rounding of u.
fn ln_1p(v: f32) -> f32 {
    let u = 1.0 + v;
    if (u == 1.0) {
        return v;
    }
    return log(u) * (v / (u - 1.0));
}

// `real::sigmoid`.
fn sigmoid(v: f32) -> f32 {
    if (v >= 0.0) {
        return 1.0 / (1.0 + exp(-v));
    }
    let e = exp(v);
    return e / (1.0 + e);
}

// `real::softplus`.
fn softplus(v: f32) -> f32 {
    if (v > 20.0) {
        return v + exp(-v);
    }
    return ln_1p(exp(v));
}

// `(softplus(z), sigmoid(z))` with one exponential (`softplus_sigmoid`).
fn softplus_sigmoid(z: f32) -> vec2<f32> {
    if (z > 20.0) {
        let e = exp(-z);
        return vec2<f32>(z + e, 1.0 / (1.0 + e));
    }
    let e = exp(z);
    return vec2<f32>(ln_1p(e), e / (1.0 + e));
}

// `real::dot` (eight partial sums, then the tail) of head row `row` with wd_o (9 values).
fn dot_head_row(row: u32) -> f32 {
    var acc: array<f32, 8>;
    for (var l = 0u; l < 8u; l++) {
        acc[l] = 0.0 + params[row + l] * wd_o[l];
    }
    let tail = 0.0 + params[row + 8u] * wd_o[8];
    return ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail;
}

// `real::dot` of hidden row `t` of W2 (from `w2_rows`) with wd_z2 (64 values: eight chunks of
// eight, no tail).
fn dot_hidden_row(t: u32) -> f32 {
    var acc: array<f32, 8>;
    for (var l = 0u; l < 8u; l++) {
        acc[l] = 0.0;
    }
    let row = t * W2_ROW;
    for (var c = 0u; c < 8u; c++) {
        for (var l = 0u; l < 8u; l++) {
            acc[l] += w2_rows[row + c * 8u + l] * wd_z2[c * 8u + l];
        }
    }
    return ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + 0.0;
}

// Offsets of a node record's parts from `base` (the record's first float, its leading 1).
struct RecordOffsets {
    x: u32,
    h1: u32,
    h2: u32,
    d_o: u32,
    dz2: u32,
    dz1: u32,
}

fn record_offsets(base: u32) -> RecordOffsets {
    let x = base + 1u;
    let h1 = x + dims.inputs;
    let h2 = h1 + HIDDEN;
    let d_o = h2 + HIDDEN;
    let dz2 = d_o + CHANNELS;
    return RecordOffsets(x, h1, h2, d_o, dz2, dz2 + HIDDEN);
}

fn node_count() -> u32 {
    return dims.nodes_x * dims.nodes_y;
}

fn node_dir(n: u32) -> vec3<f32> {
    return vec3<f32>(dirs[3u * n], dirs[3u * n + 1u], dirs[3u * n + 2u]);
}

// The lower node of pixel coordinate p, the upper one and the upper one's weight.
struct Cell {
    lo: u32,
    hi: u32,
    frac: f32,
}

fn cell(p: u32, nodes: u32) -> Cell {
    let i0 = p / dims.step;
    return Cell(i0, min(i0 + 1u, nodes - 1u), f32(p % dims.step) / f32(dims.step));
}

// Node index of a workgroup (2D grid past 65535 workgroups).
fn node_of(wg: vec3<u32>, groups: vec3<u32>) -> u32 {
    return wg.y * groups.x + wg.x;
}

// Input `i` of the encoding of `dir` (`forward`'s order: direction, then per frequency sin and
// cos of each axis); `freq` doubles from 1 exactly as there.
fn encoding(dir: vec3<f32>, i: u32) -> f32 {
    if (i < 3u) {
        return dir[i];
    }
    let k = (i - 3u) / 6u;
    let r = (i - 3u) % 6u;
    var freq = 1.0;
    for (var f = 0u; f < k; f++) {
        freq += freq;
    }
    let arg = reduce_angle(freq * dir[r % 3u]);
    if (r < 3u) {
        return sin(arg);
    }
    return cos(arg);
}

// 2 pi in two parts: TWO_PI_HI has 8 significant bits, so n * TWO_PI_HI is exact for the
// |n| <= 326 of 12 frequencies (|arg| <= 2048).
const TWO_PI_HI: f32 = 6.28125;
const TWO_PI_LO: f32 = 0.0019353071795864769;

// `arg` less the nearest multiple of 2 pi (Cody-Waite: the first subtraction exact, the
// second within a rounding), where sin and cos are accurate: a GPU's lose precision far
// from zero (the H100's were 1.9e-4 off at 12 frequencies, |arg| up to 2048; the encoding's
// inputs hold the direction exactly, so the CPU reference's libm is the truth).
fn reduce_angle(arg: f32) -> f32 {
    let n = round(arg * 0.15915494309189535);
    return (arg - n * TWO_PI_HI) - n * TWO_PI_LO;
}

// The forward pass of node `n` by the workgroup (thread t: hidden unit t; threads below
// CHANNELS: head t, returned). Leaves x, h1, s1, h2, s2 in workgroup memory.
fn forward_shared(n: u32, t: u32) -> vec2<f32> {
    let dir = node_dir(n);
    for (var i = t; i < dims.inputs; i += HIDDEN) {
        wx[i] = encoding(dir, i);
    }
    workgroupBarrier();
    var z1 = params[dims.b1 + t];
    for (var i = 0u; i < dims.inputs; i++) {
        z1 += wx[i] * params[dims.w1 + i * HIDDEN + t];
    }
    let a1 = softplus_sigmoid(z1);
    wh1[t] = a1.x;
    ws1[t] = a1.y;
    workgroupBarrier();
    var z2 = params[dims.b2 + t];
    for (var i = 0u; i < HIDDEN; i++) {
        z2 += wh1[i] * params[dims.w2 + i * HIDDEN + t];
    }
    let a2 = softplus_sigmoid(z2);
    wh2[t] = a2.x;
    ws2[t] = a2.y;
    workgroupBarrier();
    // Head t: (pre-activation, output).
    var head = vec2<f32>(0.0);
    if (t < CHANNELS) {
        var z = params[dims.b_heads + t];
        for (var i = 0u; i < HIDDEN; i++) {
            z += wh2[i] * params[dims.w_heads + i * CHANNELS + t];
        }
        head.x = z;
        if (t < 3u) {
            head.y = sigmoid(z);
        } else {
            head.y = softplus(z);
        }
    }
    return head;
}

@compute @workgroup_size(64)
fn nodes(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let n = node_of(wg, groups);
    // Uniform per workgroup: the barriers below are reached by all or none.
    if (n >= node_count()) {
        return;
    }
    let head = forward_shared(n, t);
    if (t < CHANNELS) {
        node_out[n * CHANNELS + t] = head.y;
    }
}

@compute @workgroup_size(256)
fn interpolate(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let p = gid.y * groups.x * 256u + gid.x;
    if (p >= dims.width * dims.height) {
        return;
    }
    let cx = cell(p % dims.width, dims.nodes_x);
    let cy = cell(p / dims.width, dims.nodes_y);
    let fx = cx.frac;
    let fy = cy.frac;
    let wa = (1.0 - fx) * (1.0 - fy);
    let wb = fx * (1.0 - fy);
    let wc = (1.0 - fx) * fy;
    let wd = fx * fy;
    let a = (cy.lo * dims.nodes_x + cx.lo) * CHANNELS;
    let b = (cy.lo * dims.nodes_x + cx.hi) * CHANNELS;
    let c = (cy.hi * dims.nodes_x + cx.lo) * CHANNELS;
    let d = (cy.hi * dims.nodes_x + cx.hi) * CHANNELS;
    for (var k = 0u; k < 3u; k++) {
        var v = wa * node_out[a + k] + wb * node_out[b + k] + wc * node_out[c + k] + wd * node_out[d + k];
        c_med[3u * p + k] = v;
        let k1 = k + 3u;
        v = wa * node_out[a + k1] + wb * node_out[b + k1] + wc * node_out[c + k1] + wd * node_out[d + k1];
        sigma_att[3u * p + k] = v;
        let k2 = k + 6u;
        v = wa * node_out[a + k2] + wb * node_out[b + k2] + wc * node_out[c + k2] + wd * node_out[d + k2];
        sigma_bs[3u * p + k] = v;
    }
}

@compute @workgroup_size(256)
fn interpolate_adjoint_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let t = gid.y * groups.x * 256u + gid.x;
    if (t >= dims.height * dims.nodes_x) {
        return;
    }
    let i = t % dims.nodes_x;
    let y = t / dims.nodes_x;
    let s = dims.step;
    var acc: array<f32, CHANNELS>;
    for (var k = 0u; k < CHANNELS; k++) {
        acc[k] = 0.0;
    }
    // Pixels of cell i - 1 see node i as their upper node (weight frac), pixels of cell i as
    // their lower one (weight 1 - frac); the CPU scatters them in x order, so gather in x order.
    var lo = 0u;
    if (i > 0u) {
        lo = (i - 1u) * s;
    }
    let hi = min((i + 1u) * s, dims.width);
    for (var px = lo; px < hi; px++) {
        let frac = f32(px % s) / f32(s);
        var w = 1.0 - frac;
        if (px < i * s) {
            w = frac;
        }
        let q = 3u * (y * dims.width + px);
        for (var k = 0u; k < 3u; k++) {
            acc[k] += w * grad_c_med[q + k];
            acc[k + 3u] += w * grad_sigma_att[q + k];
            acc[k + 6u] += w * grad_sigma_bs[q + k];
        }
    }
    for (var k = 0u; k < CHANNELS; k++) {
        d_rows[t * CHANNELS + k] = acc[k];
    }
}

@compute @workgroup_size(256)
fn interpolate_adjoint_cols(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let n = gid.y * groups.x * 256u + gid.x;
    if (n >= node_count()) {
        return;
    }
    let i = n % dims.nodes_x;
    let j = n / dims.nodes_x;
    let s = dims.step;
    let centre = j * s;
    var acc: array<f32, CHANNELS>;
    for (var k = 0u; k < CHANNELS; k++) {
        acc[k] = 0.0;
    }
    var lo = 0u;
    if (centre >= s - 1u) {
        lo = centre - (s - 1u);
    }
    let hi = min(centre + s, dims.height);
    for (var y = lo; y < hi; y++) {
        // `MediumGrid::weight`: 1 - |y - j step| / step.
        let dist = f32(max(y, centre) - min(y, centre)) / f32(s);
        let wy = max(1.0 - dist, 0.0);
        if (wy == 0.0) {
            continue;
        }
        let r = (y * dims.nodes_x + i) * CHANNELS;
        for (var k = 0u; k < CHANNELS; k++) {
            acc[k] += wy * d_rows[r + k];
        }
    }
    for (var k = 0u; k < CHANNELS; k++) {
        d_nodes[n * CHANNELS + k] = acc[k];
    }
}

@compute @workgroup_size(64)
fn nodes_backward(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let n = node_of(wg, groups);
    if (n >= node_count()) {
        return;
    }
    let base = n * dims.record;
    let r = record_offsets(base);
    var nonzero = false;
    for (var k = 0u; k < CHANNELS; k++) {
        nonzero = nonzero || d_nodes[n * CHANNELS + k] != 0.0;
    }
    if (!nonzero) {
        // The CPU skips such a node; a record of zeros adds nothing (uniform: the same
        // d_nodes for every thread).
        for (var r = t; r < dims.record; r += HIDDEN) {
            records[base + r] = select(0.0, 1.0, r == 0u);
        }
        return;
    }
    // Coalesced: thread t loads column t of every row (ordered before the reads by the
    // barriers of the forward).
    for (var r = 0u; r < HIDDEN; r++) {
        w2_rows[r * W2_ROW + t] = params[dims.w2 + r * HIDDEN + t];
    }
    let head = forward_shared(n, t);
    if (t == 0u) {
        records[base] = 1.0;
    }
    for (var i = t; i < dims.inputs; i += HIDDEN) {
        records[r.x + i] = wx[i];
    }
    records[r.h1 + t] = wh1[t];
    records[r.h2 + t] = wh2[t];
    // Heads: sigmoid' = s (1 - s); softplus' = sigmoid(o).
    if (t < CHANNELS) {
        var slope = 0.0;
        if (t < 3u) {
            slope = head.y * (1.0 - head.y);
        } else {
            slope = sigmoid(head.x);
        }
        let d = d_nodes[n * CHANNELS + t] * slope;
        wd_o[t] = d;
        records[r.d_o + t] = d;
    }
    workgroupBarrier();
    let dz2 = dot_head_row(dims.w_heads + t * CHANNELS) * ws2[t];
    wd_z2[t] = dz2;
    records[r.dz2 + t] = dz2;
    workgroupBarrier();
    records[r.dz1 + t] = dot_hidden_row(t) * ws1[t];
}

@compute @workgroup_size(64)
fn param_grad_partials(@builtin(global_invocation_id) gid: vec3<u32>) {
    let p = gid.x;
    if (p >= dims.len) {
        return;
    }
    let chunk = gid.y;
    let r = record_offsets(0u);
    // Offsets in the node record of the parameter's activation and delta.
    var a = 0u;
    var d = 0u;
    if (p < dims.b1) {
        let q = p - dims.w1;
        a = r.x + q / HIDDEN;
        d = r.dz1 + q % HIDDEN;
    } else if (p < dims.w2) {
        d = r.dz1 + (p - dims.b1);
    } else if (p < dims.b2) {
        let q = p - dims.w2;
        a = r.h1 + q / HIDDEN;
        d = r.dz2 + q % HIDDEN;
    } else if (p < dims.w_heads) {
        d = r.dz2 + (p - dims.b2);
    } else if (p < dims.b_heads) {
        let q = p - dims.w_heads;
        a = r.h2 + q / CHANNELS;
        d = r.d_o + q % CHANNELS;
    } else {
        d = r.d_o + (p - dims.b_heads);
    }
    let n0 = chunk * dims.chunk_nodes;
    let n1 = min(n0 + dims.chunk_nodes, node_count());
    var sum = 0.0;
    for (var n = n0; n < n1; n++) {
        let q = n * dims.record;
        sum += records[q + a] * records[q + d];
    }
    partials[chunk * dims.len + p] = sum;
}

@compute @workgroup_size(256)
fn param_grad_sum(@builtin(global_invocation_id) gid: vec3<u32>) {
    let p = gid.x;
    if (p >= dims.len) {
        return;
    }
    let chunks = (node_count() + dims.chunk_nodes - 1u) / dims.chunk_nodes;
    var sum = 0.0;
    for (var c = 0u; c < chunks; c++) {
        sum += partials[c * dims.len + p];
    }
    grads[p] = grads[p] + sum;
}


// --- CPU-device variants (`GpuMedium::serial`) -------------------------------------------
// On a CPU device (lavapipe: 8 lanes, a workgroup's barriers switch coroutines, and every
// buffer load at an address that differs between lanes or comes from a loop counter is a
// loop over the lanes) the workgroup per node above spends its time in loads: two per
// multiply-add. These kernels give each invocation a node (`nodes_serial`,
// `nodes_backward_serial`) or a block of 8 parameters (`param_grad_blocks`): each lane loads
// one of 8 consecutive weights (or activations) and `subgroupBroadcast` hands them to the
// other lanes, so one load serves eight multiply-adds per lane. The weights come from a
// uniform buffer (the same `params` range: lavapipe's uniform loads gather without a branch
// per lane). Every sum keeps the order of the kernels above (zero terms pad a row to a
// multiple of 8, adding exactly nothing), so `nodes_serial` and `param_grad_blocks` give the
// same bits as `nodes` and `param_grad_partials` on lavapipe (the H100's compiler gives the
// last bits otherwise, within tolerance). They need all lanes of a subgroup of at
// least 8 and at most 64 lanes active: out-of-range invocations compute a clamped node and
// do not store.

// `params` as a uniform buffer: 4 * 2403 floats hold the largest layout (75 inputs); the
// host allocates `params` at least this long (`UNIFORM_PARAM_FLOATS`).
@group(0) @binding(14) var<uniform> wparams: array<vec4<f32>, 2403>;

// Private rows: the inputs (at most 75) padded to a multiple of 8, or a hidden layer.
const ROW: u32 = 80u;

fn wp(i: u32) -> f32 {
    return wparams[i >> 2u][i & 3u];
}

// Lanes 0..7's `v`, to every lane.
fn bcast8(v: f32) -> array<f32, 8> {
    return array<f32, 8>(subgroupBroadcast(v, 0u), subgroupBroadcast(v, 1u), subgroupBroadcast(v, 2u), subgroupBroadcast(v, 3u),
                         subgroupBroadcast(v, 4u), subgroupBroadcast(v, 5u), subgroupBroadcast(v, 6u), subgroupBroadcast(v, 7u));
}

// The sum of the eight partial sums of `real::dot`, in its order.
fn sum8(acc: array<f32, 8>) -> f32 {
    return ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]));
}

// z + a[c] w_0 + ... + a[c + 7] w_7, added in that order, w_l being lane l's `wv`.
fn add8(z0: f32, wv: f32, a: ptr<private, array<f32, ROW>>, c: u32) -> f32 {
    let w = bcast8(wv);
    var z = z0;
    for (var l = 0u; l < 8u; l++) {
        z += (*a)[c + l] * w[l];
    }
    return z;
}

// The forward pass of node n by one invocation (lane `lane` of its subgroup), as
// `forward_shared`, into the private rows: x, then h1 / s1 and h2 / s2 (softplus and its
// slope, the sigmoid) and the nine heads' pre-activations.
var<private> px: array<f32, ROW>;
var<private> ph1: array<f32, ROW>;
var<private> ps1: array<f32, ROW>;
var<private> ph2: array<f32, ROW>;
var<private> ps2: array<f32, ROW>;
var<private> pz: array<f32, CHANNELS>;

// A hidden layer: unit o's sum over the `rows` inputs of `a` in order from its bias, then
// its softplus into h and the slope (sigmoid) into s.
fn softplus_layer(w: u32, b: u32, rows: u32, lane: u32, a: ptr<private, array<f32, ROW>>, h: ptr<private, array<f32, ROW>>, s: ptr<private, array<f32, ROW>>) {
    for (var o = 0u; o < HIDDEN; o++) {
        var z = wp(b + o);
        for (var c = 0u; c < rows; c += 8u) {
            let row = c + (lane & 7u);
            z = add8(z, select(0.0, wp(w + row * HIDDEN + o), row < rows), a, c);
        }
        let v = softplus_sigmoid(z);
        (*h)[o] = v.x;
        (*s)[o] = v.y;
    }
}

fn forward_serial(n: u32, lane: u32) {
    let dir = node_dir(n);
    for (var i = 0u; i < dims.inputs; i++) {
        px[i] = encoding(dir, i);
    }
    for (var i = dims.inputs; i < ROW; i++) {
        px[i] = 0.0;
    }
    softplus_layer(dims.w1, dims.b1, dims.inputs, lane, &px, &ph1, &ps1);
    softplus_layer(dims.w2, dims.b2, HIDDEN, lane, &ph1, &ph2, &ps2);
    for (var k = 0u; k < CHANNELS; k++) {
        var z = wp(dims.b_heads + k);
        for (var c = 0u; c < HIDDEN; c += 8u) {
            z = add8(z, wp(dims.w_heads + (c + (lane & 7u)) * CHANNELS + k), &ph2, c);
        }
        pz[k] = z;
    }
}

// Head k's output from its pre-activation (sigmoid c_med, softplus sigma_att and sigma_bs).
fn head_out(k: u32, z: f32) -> f32 {
    if (k < 3u) {
        return sigmoid(z);
    }
    return softplus(z);
}

// One invocation per node: `nodes`.
@compute @workgroup_size(64)
fn nodes_serial(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(subgroup_invocation_id) lane: u32) {
    let raw = gid.y * groups.x * 64u + gid.x;
    let n = min(raw, node_count() - 1u);
    forward_serial(n, lane);
    if (raw < node_count()) {
        for (var k = 0u; k < CHANNELS; k++) {
            node_out[n * CHANNELS + k] = head_out(k, pz[k]);
        }
    }
}

// One invocation per node: `nodes_backward` (the same record; a node whose d_nodes are all
// zero gets its activations and zero deltas, which add exactly nothing to the gradient).
@compute @workgroup_size(64)
fn nodes_backward_serial(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>, @builtin(subgroup_invocation_id) lane: u32) {
    let raw = gid.y * groups.x * 64u + gid.x;
    let n = min(raw, node_count() - 1u);
    let store = raw < node_count();
    forward_serial(n, lane);
    let base = n * dims.record;
    let r = record_offsets(base);
    // d_o, padded to 16 for the broadcasts below.
    var d_o: array<f32, 16>;
    for (var k = 0u; k < CHANNELS; k++) {
        var slope = 0.0;
        if (k < 3u) {
            let y = sigmoid(pz[k]);
            slope = y * (1.0 - y);
        } else {
            slope = sigmoid(pz[k]);
        }
        d_o[k] = d_nodes[n * CHANNELS + k] * slope;
    }
    // dz2[t] = (W_heads row t . d_o) s2[t], `dot_head_row`'s order.
    var dz2: array<f32, ROW>;
    for (var t = 0u; t < HIDDEN; t++) {
        let w = bcast8(wp(dims.w_heads + t * CHANNELS + (lane & 7u)));
        var acc: array<f32, 8>;
        for (var l = 0u; l < 8u; l++) {
            acc[l] = 0.0 + w[l] * d_o[l];
        }
        let tail = 0.0 + wp(dims.w_heads + t * CHANNELS + 8u) * d_o[8];
        dz2[t] = (sum8(acc) + tail) * ps2[t];
    }
    if (store) {
        records[base] = 1.0;
        for (var i = 0u; i < dims.inputs; i++) {
            records[r.x + i] = px[i];
        }
        for (var t = 0u; t < HIDDEN; t++) {
            records[r.h1 + t] = ph1[t];
            records[r.h2 + t] = ph2[t];
            records[r.dz2 + t] = dz2[t];
        }
        for (var k = 0u; k < CHANNELS; k++) {
            records[r.d_o + k] = d_o[k];
        }
    }
    // dz1[t] = (W2 row t . dz2) s1[t], `dot_hidden_row`'s order.
    for (var t = 0u; t < HIDDEN; t++) {
        var acc: array<f32, 8>;
        for (var l = 0u; l < 8u; l++) {
            acc[l] = 0.0;
        }
        for (var c = 0u; c < HIDDEN; c += 8u) {
            let w = bcast8(wp(dims.w2 + t * HIDDEN + c + (lane & 7u)));
            for (var l = 0u; l < 8u; l++) {
                acc[l] += w[l] * dz2[c + l];
            }
        }
        let dz1 = (sum8(acc) + 0.0) * ps1[t];
        if (store) {
            records[r.dz1 + t] = dz1;
        }
    }
}

// (rows, activation offset, delta offset, first parameter) of tensor k.
fn tensor_rows(k: u32, r: RecordOffsets) -> vec4<u32> {
    switch k {
        case 0u: { return vec4<u32>(dims.inputs, r.x, r.dz1, dims.w1); }
        case 1u: { return vec4<u32>(1u, 0u, r.dz1, dims.b1); }
        case 2u: { return vec4<u32>(HIDDEN, r.h1, r.dz2, dims.w2); }
        case 3u: { return vec4<u32>(1u, 0u, r.dz2, dims.b2); }
        case 4u: { return vec4<u32>(HIDDEN, r.h2, r.d_o, dims.w_heads); }
        default: { return vec4<u32>(1u, 0u, r.d_o, dims.b_heads); }
    }
}

// `param_grad_partials` by blocks: one invocation per (8 rows of a tensor, column o) and chunk
// of nodes. The tensors in `MediumLayout` order, each with its rows' activation and its
// columns' delta in the node record (a bias is one row whose activation is the record's
// leading 1); every tensor is 64 columns wide here (the heads' 9 padded), so a subgroup's
// lanes share their rows. Lane l loads activation row + l of each node, broadcast to the
// lanes; each sum is over the chunk's nodes in node order from 0.0, as there.
@compute @workgroup_size(64)
fn param_grad_blocks(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(subgroup_invocation_id) lane: u32) {
    let chunk = gid.y;
    var id = gid.x;
    let r = record_offsets(0u);
    var tensor = 0u;
    var t = vec4<u32>(0u);
    for (; tensor < 6u; tensor++) {
        t = tensor_rows(tensor, r);
        let threads = (t.x + 7u) / 8u * 64u;
        if (id < threads) {
            break;
        }
        id -= threads;
    }
    if (tensor == 6u) {
        // Past the last tensor: a whole subgroup (64 threads a tensor block).
        return;
    }
    var cols = HIDDEN;
    if (tensor >= 4u) {
        cols = CHANNELS;
    }
    let row0 = id / 64u * 8u;
    let o = id % 64u;
    // Clamped for the padding lanes: they load in range and store nothing.
    let d = t.z + min(o, cols - 1u);
    let a = t.y + min(row0 + (lane & 7u), t.x - 1u);
    let n0 = chunk * dims.chunk_nodes;
    let n1 = min(n0 + dims.chunk_nodes, node_count());
    var acc: array<f32, 8>;
    for (var l = 0u; l < 8u; l++) {
        acc[l] = 0.0;
    }
    for (var n = n0; n < n1; n++) {
        let q = n * dims.record;
        let av = bcast8(records[q + a]);
        let dv = records[q + d];
        for (var l = 0u; l < 8u; l++) {
            acc[l] += av[l] * dv;
        }
    }
    if (o < cols) {
        for (var l = 0u; l < 8u; l++) {
            let row = row0 + l;
            if (row < t.x) {
                partials[chunk * dims.len + t.w + row * cols + o] = acc[l];
            }
        }
    }
}

// `interpolate` by cells: one invocation per (image row, node cell along x), the cell's
// pixels of that row in x order, its four nodes loaded once (lanes on consecutive rows). The
// same weights and sums per pixel as `interpolate`, so the same bits on lavapipe.
@compute @workgroup_size(64)
fn interpolate_cells(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let t = gid.y * groups.x * 64u + gid.x;
    let cells = (dims.width + dims.step - 1u) / dims.step;
    if (t >= dims.height * cells) {
        return;
    }
    let y = t % dims.height;
    let x0 = t / dims.height * dims.step;
    let x1 = min(x0 + dims.step, dims.width);
    let cx = cell(x0, dims.nodes_x);
    let cy = cell(y, dims.nodes_y);
    let fy = cy.frac;
    let a = (cy.lo * dims.nodes_x + cx.lo) * CHANNELS;
    let b = (cy.lo * dims.nodes_x + cx.hi) * CHANNELS;
    let c = (cy.hi * dims.nodes_x + cx.lo) * CHANNELS;
    let d = (cy.hi * dims.nodes_x + cx.hi) * CHANNELS;
    var na: array<f32, CHANNELS>;
    var nb: array<f32, CHANNELS>;
    var nc: array<f32, CHANNELS>;
    var nd: array<f32, CHANNELS>;
    for (var k = 0u; k < CHANNELS; k++) {
        na[k] = node_out[a + k];
        nb[k] = node_out[b + k];
        nc[k] = node_out[c + k];
        nd[k] = node_out[d + k];
    }
    for (var x = x0; x < x1; x++) {
        let fx = cell(x, dims.nodes_x).frac;
        let wa = (1.0 - fx) * (1.0 - fy);
        let wb = fx * (1.0 - fy);
        let wc = (1.0 - fx) * fy;
        let wd = fx * fy;
        let p = y * dims.width + x;
        for (var k = 0u; k < 3u; k++) {
            c_med[3u * p + k] = wa * na[k] + wb * nb[k] + wc * nc[k] + wd * nd[k];
            let k1 = k + 3u;
            sigma_att[3u * p + k] = wa * na[k1] + wb * nb[k1] + wc * nc[k1] + wd * nd[k1];
            let k2 = k + 6u;
            sigma_bs[3u * p + k] = wa * na[k2] + wb * nb[k2] + wc * nc[k2] + wd * nd[k2];
        }
    }
}
