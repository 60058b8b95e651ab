// Rasterisation backward with the underwater medium (CPU reference: `rasterize_backward` /
// `backprop_pixel` and `reduce_isect_grads`, src/map/render/raster_bwd.rs, the same
// per-pixel arithmetic in the same order).
//
// `rasterize_backward` (deterministic mode): one workgroup per 16x16 tile, one thread per
// pixel (row-major in the tile). The tile's sorted splats are walked back to front, `sg` (the
// subgroup size) at a time: lane l loads splat `base + l` and the subgroup shares them by
// `subgroupShuffle`, as the forward does, walking only the splats a pixel of the subgroup can
// reach (the ballot's set bits; a skipped splat's sums are zeros, which lane j writes for
// splat j, so each slot is written once). Each thread back-propagates its pixel through the
// splats it blended in the forward pass (`start .. isect_end`), recovering the transmittance
// from the stored final T (`backprop_splat`). Per intersection, the 13 contributions (12
// gradient floats and the pixel count) are summed within the subgroup (`subgroup_sum4`) and each
// subgroup's sums go to workgroup memory; after each step of `sg` intersections one barrier,
// then the subgroups' sums are added in subgroup order and one SplatGrad per sorted
// intersection is written (zero behind the last splat a pixel of the tile blended, where the
// walk starts). No float atomics, a fixed order on a given device: repeated runs are
// bit-identical. Each pixel writes the gradient with respect to its medium parameters.
//
// `rasterize_backward_atomic` and `rasterize_backward_atomic_scatter` (the default where the
// device has VK_EXT_shader_atomic_float; the host takes the second on subgroups of 32 lanes
// and more): the same per-pixel arithmetic; the subgroup's 13 sums per intersection by three
// vector butterflies and two ballots for the pixel count (`add_subgroup_sums_by_adds`) or by a
// reduce-scatter (`add_subgroup_sums`), each sum added once with a float atomic to the
// intersection's partials or, with `RasterParams::per_gaussian` (the host's choice on a CPU
// device), straight to its Gaussian's splat gradient, so that neither the intersections'
// partials need zeroing nor `reduce_isect_grads` runs (zeroed before the dispatch either way).
// No workgroup memory, no barriers, no workgroup-wide
// reduction, which took 60% of the backward on lavapipe; each subgroup starts at the last splat one of its pixels blended instead of the
// tile's last. The order of the additions, and so the last bits, may vary between runs.
//
// `rasterize_backward_atomic_pairs` and `rasterize_backward_atomic_pairs_scatter`
// (`GpuContext::pixel_pairs`, the default on subgroups under 32 lanes): the two atomic kernels
// with two pixels per thread, 128 threads a tile (`backward_atomic_pairs`): each splat a
// subgroup shares serves two pixels and the pair's contributions are added in the lane before
// the subgroup sums. On lavapipe the backward took 0.58-0.73x the time of one pixel per
// thread; on an H100 1.05x (fewer threads per tile hide less latency there). They walk only
// the splats the subgroup reaches (the ballot's set bits, ballot.wgsl), which on
// lavapipe took 0.54x the time of stepping through all of them.
//
// `reduce_isect_grads`: one thread per Gaussian sums its intersections' partials, found
// through the inverse sort permutation.
//
// Per intersection, `partials` holds 12 floats in the order of `SplatGrad`: mean2d (2),
// conic (3), opacity, colour (3), z, mean2d_densify (2); `partial_pixels` the pixel count.

const TILE: u32 = 16u;
const GRAD_FLOATS: u32 = 12u;
// Reduced values per intersection: the 12 floats and the pixel count.
const RED_VALUES: u32 = 13u;
const ALPHA_MIN: f32 = 0.003921568627450980; // 1/255
const ALPHA_MAX: f32 = 0.99;
const MAX_DENSIFY_EXPONENT: f32 = 60.0;

struct RasterParams {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    width: u32,
    height: u32,
    tiles_x: u32,
    // 0: inverse depth, 1: depth (`DepthMode`)
    depth_mode: u32,
    // The atomic kernels: 0 adds into the intersection's partials, 1 into the Gaussian's
    // (`partials_sum` and `partial_pixels_sum` are then the per-Gaussian buffers).
    per_gaussian: u32,
}

var<immediate> params: RasterParams;

// Three vec4s per splat (`SplatVecs`, as project_forward writes them): a vector load takes
// one pass over a CPU device's lanes where a float takes one each (lavapipe).
@group(0) @binding(0) var<storage, read> splats: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> sorted_gaussian: array<u32>;
@group(0) @binding(2) var<storage, read> tile_offsets: array<u32>;
@group(0) @binding(3) var<storage, read> c_med: array<f32>;
@group(0) @binding(4) var<storage, read> sigma_att: array<f32>;
@group(0) @binding(5) var<storage, read> sigma_bs: array<f32>;
// Forward outputs per pixel: depth, depth_var, alpha, final_t; and isect_end.
@group(0) @binding(6) var<storage, read> fwd_scalars: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> fwd_isect_end: array<u32>;
// Upstream gradients: colour (RGB), restored (RGB), and per pixel (depth, depth_var, alpha, 0).
@group(0) @binding(8) var<storage, read> up_colour: array<f32>;
@group(0) @binding(9) var<storage, read> up_restored: array<f32>;
@group(0) @binding(10) var<storage, read> up_scalars: array<vec4<f32>>;
@group(0) @binding(11) var<storage, read_write> partials: array<f32>;
@group(0) @binding(12) var<storage, read_write> partial_pixels: array<u32>;
@group(0) @binding(13) var<storage, read_write> grad_c_med: array<f32>;
@group(0) @binding(14) var<storage, read_write> grad_sigma_att: array<f32>;
@group(0) @binding(15) var<storage, read_write> grad_sigma_bs: array<f32>;

// A projected splat as three vectors (what one shuffle moves):
// a = (mean2d.x, mean2d.y, conic.x, conic.y), b = (conic.z, z, opacity, q_max), c = (colour, 0).
struct SplatVecs {
    a: vec4<f32>,
    b: vec4<f32>,
    c: vec4<f32>,
}

// Per subgroup and intersection of the current step, the 13 subgroup sums:
// red[(subgroup * sg + j) * RED_VALUES + v] (256 x 13 floats for any subgroup size).
var<workgroup> red: array<f32, 3328>;
var<workgroup> wg_start: u32;
var<workgroup> wg_stop: u32;
// The largest `end` of the tile's pixels (where the walk starts), gathered then broadcast.
var<workgroup> wg_end_max: atomic<u32>;
var<workgroup> wg_top: u32;

//!include ballot.wgsl

//!include splat_reach.wgsl

fn load_splat_vecs(g: u32) -> SplatVecs {
    return SplatVecs(splats[3u * g], splats[3u * g + 1u], splats[3u * g + 2u]);
}

fn depth_value(z: f32) -> f32 {
    if (params.depth_mode == 0u) {
        return 1.0 / z;
    }
    return z;
}

fn depth_value_dz(z: f32) -> f32 {
    if (params.depth_mode == 0u) {
        return -1.0 / (z * z);
    }
    return 1.0;
}

// The atomic variant's per-intersection sums (zeroed before the dispatch), the same buffers
// as `partials` and `partial_pixels`.
@group(0) @binding(22) var<storage, read_write> partials_sum: array<atomic<f32>>;
@group(0) @binding(23) var<storage, read_write> partial_pixels_sum: array<atomic<u32>>;

//!include pixel_medium.wgsl

// What a pixel reads once: its ray, medium, upstream gradients and forward state.
struct PixelInputs {
    // position, ray and medium (`pixel_medium`)
    m: PixelMedium,
    up_c: vec3<f32>,
    up_r: vec3<f32>,
    // dL/d (depth, depth_var, alpha), 0
    up_s: vec4<f32>,
    // depth, depth_var, alpha, final_t
    state: vec4<f32>,
    inv_w: f32,
    sigma_med: f32,
}

// What a pixel carries from splat to splat (back to front).
struct PixelState {
    t: f32,
    behind: f32,
    g_c_med: vec3<f32>,
    g_att: vec3<f32>,
    g_bs: vec3<f32>,
}

// One pixel's contribution to one intersection, packed as the subgroup sums are taken:
// a = (mean2d, conic.xy), b = (conic.z, opacity, colour.xy), c = (colour.z, z, densify), pixels.
struct Contribution {
    a: vec4<f32>,
    b: vec4<f32>,
    c: vec4<f32>,
    pixels: f32,
}

fn pixel_inputs(x: u32, y: u32) -> PixelInputs {
    var p: PixelInputs;
    p.m = pixel_medium(x, y);
    let pix = min(y, params.height - 1u) * params.width + min(x, params.width - 1u);
    p.up_c = vec3<f32>(up_colour[pix * 3u], up_colour[pix * 3u + 1u], up_colour[pix * 3u + 2u]);
    p.up_r = vec3<f32>(up_restored[pix * 3u], up_restored[pix * 3u + 1u], up_restored[pix * 3u + 2u]);
    p.up_s = up_scalars[pix];
    p.state = fwd_scalars[pix];
    p.inv_w = 0.0;
    if (p.state.z > 0.0) {
        p.inv_w = 1.0 / p.state.z;
    }
    p.sigma_med = (p.m.m_att.x + p.m.m_att.y + p.m.m_att.z) / 3.0;
    return p;
}

fn pixel_state(p: PixelInputs) -> PixelState {
    var st: PixelState;
    st.t = p.state.w;
    st.behind = 0.0;
    st.g_c_med = p.up_c;
    st.g_att = vec3<f32>(0.0);
    st.g_bs = vec3<f32>(0.0);
    return st;
}

// Back-propagates a pixel through one splat it blended (or not: zero contribution), updating
// its transmittance, the gradient of the splats behind and its medium gradients.
fn backprop_splat(p: PixelInputs, st: ptr<function, PixelState>, s: SplatVecs) -> Contribution {
    var out: Contribution;
    out.a = vec4<f32>(0.0);
    out.b = vec4<f32>(0.0);
    out.c = vec4<f32>(0.0);
    out.pixels = 0.0;
    let conic = vec3<f32>(s.a.z, s.a.w, s.b.x);
    let z = s.b.y;
    let opacity = s.b.z;
    let dx = p.m.fx - s.a.x;
    let dy = p.m.fy - s.a.y;
    let q = conic.x * dx * dx + 2.0 * conic.y * dx * dy + conic.z * dy * dy;
    var hit = q <= s.b.w * 1.0001 + 1e-3;
    var gauss = 0.0;
    var raw = 0.0;
    if (hit) {
        gauss = exp(-0.5 * q);
        raw = opacity * gauss;
        hit = raw >= ALPHA_MIN;
    }
    if (!hit) {
        return out;
    }
    let clamped = raw > ALPHA_MAX;
    var alpha = raw;
    if (clamped) {
        alpha = ALPHA_MAX;
    }
    let one_minus = 1.0 - alpha;
    (*st).t = (*st).t / one_minus;
    let w = (*st).t * alpha;
    let range_m = z * p.m.ray_norm;
    out.pixels = 1.0;
    var value = 0.0;
    var g_range = 0.0;
    // The three channels as vectors (no per-channel indexing, which a CPU device turns into
    // memory accesses); the sums over channels in channel order, as the CPU reference adds
    // them.
    let e_att = exp(-p.m.m_att * range_m);
    let e_bs = exp(-p.m.m_bs * range_m);
    let col = s.c.xyz;
    let v3 = p.up_c * (col * e_att - p.m.m_c * e_bs) + p.up_r * col;
    value = ((value + v3.x) + v3.y) + v3.z;
    let c_colour = w * (p.up_c * e_att + p.up_r);
    let r3 = w * p.up_c * (p.m.m_bs * p.m.m_c * e_bs - p.m.m_att * col * e_att);
    g_range = ((g_range + r3.x) + r3.y) + r3.z;
    (*st).g_c_med = (*st).g_c_med - p.up_c * w * e_bs;
    (*st).g_att = (*st).g_att - p.up_c * w * col * range_m * e_att;
    (*st).g_bs = (*st).g_bs + p.up_c * w * p.m.m_c * range_m * e_bs;
    let d = depth_value(z);
    let dd = d - p.state.x;
    value = value + ((p.up_s.x * dd + p.up_s.y * (dd * dd - p.state.y)) * p.inv_w + p.up_s.z);
    let g_d = w * (p.up_s.x + 2.0 * p.up_s.y * dd) * p.inv_w;
    let c_z = g_range * p.m.ray_norm + g_d * depth_value_dz(z);
    let g_alpha = (*st).t * value - (*st).behind / one_minus;
    (*st).behind = (*st).behind + w * value;
    var c_mean2d = vec2<f32>(0.0);
    var c_conic = vec3<f32>(0.0);
    var c_opacity = 0.0;
    var c_densify = vec2<f32>(0.0);
    if (!clamped) {
        c_opacity = g_alpha * gauss;
        let g_q = -0.5 * alpha * g_alpha;
        c_conic = vec3<f32>(g_q * dx * dx, g_q * 2.0 * dx * dy, g_q * dy * dy);
        c_mean2d = vec2<f32>(-2.0 * g_q * (conic.x * dx + conic.y * dy), -2.0 * g_q * (conic.y * dx + conic.z * dy));
        let scale = exp(min(p.sigma_med * range_m, MAX_DENSIFY_EXPONENT));
        c_densify = c_mean2d * scale;
    }
    out.a = vec4<f32>(c_mean2d, c_conic.xy);
    out.b = vec4<f32>(c_conic.z, c_opacity, c_colour.xy);
    out.c = vec4<f32>(c_colour.z, c_z, c_densify);
    return out;
}

// The end of the pixel's blended range, clamped to the tile's range as the CPU reference does
// (`start`, nothing, for a thread outside the image).
fn pixel_end(x: u32, y: u32, inside: bool, start: u32, stop: u32) -> u32 {
    if (!inside) {
        return start;
    }
    return clamp(fwd_isect_end[y * params.width + x], start, stop);
}

// Lane l's splat of the batch `base .. base + count`.
fn load_batch(base: u32, count: u32, lane: u32) -> SplatVecs {
    var own: SplatVecs;
    if (lane < count) {
        own = load_splat_vecs(sorted_gaussian[base + lane]);
    }
    return own;
}

// The pixel's contribution to the batch's splat j, shared by lane j (zero unless the pixel
// blended it: `blended`).
fn splat_contribution(p: PixelInputs, st: ptr<function, PixelState>, own: SplatVecs, j: u32, blended: bool) -> Contribution {
    var s: SplatVecs;
    s.a = subgroupShuffle(own.a, j);
    s.b = subgroupShuffle(own.b, j);
    s.c = subgroupShuffle(own.c, j);
    if (blended) {
        return backprop_splat(p, st, s);
    }
    var c: Contribution;
    c.a = vec4<f32>(0.0);
    c.b = vec4<f32>(0.0);
    c.c = vec4<f32>(0.0);
    c.pixels = 0.0;
    return c;
}

fn write_medium_grads(x: u32, y: u32, st: PixelState) {
    let i = y * params.width + x;
    grad_c_med[i * 3u] = st.g_c_med.x;
    grad_c_med[i * 3u + 1u] = st.g_c_med.y;
    grad_c_med[i * 3u + 2u] = st.g_c_med.z;
    grad_sigma_att[i * 3u] = st.g_att.x;
    grad_sigma_att[i * 3u + 1u] = st.g_att.y;
    grad_sigma_att[i * 3u + 2u] = st.g_att.z;
    grad_sigma_bs[i * 3u] = st.g_bs.x;
    grad_sigma_bs[i * 3u + 1u] = st.g_bs.y;
    grad_sigma_bs[i * 3u + 2u] = st.g_bs.z;
}

// One subgroup's 13 sums for one intersection of the step into `red`.
fn write_red(slot: u32, s0: vec4<f32>, s1: vec4<f32>, s2: vec4<f32>, s3: f32) {
    let o = slot * RED_VALUES;
    red[o] = s0.x;
    red[o + 1u] = s0.y;
    red[o + 2u] = s0.z;
    red[o + 3u] = s0.w;
    red[o + 4u] = s1.x;
    red[o + 5u] = s1.y;
    red[o + 6u] = s1.z;
    red[o + 7u] = s1.w;
    red[o + 8u] = s2.x;
    red[o + 9u] = s2.y;
    red[o + 10u] = s2.z;
    red[o + 11u] = s2.w;
    red[o + 12u] = s3;
}

@compute @workgroup_size(256)
fn rasterize_backward(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                      @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32,
                      @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = wg.x * TILE + t_index % TILE;
    let y = wg.y * TILE + t_index / TILE;
    let inside = x < params.width && y < params.height;
    let p = pixel_inputs(x, y);
    var st = pixel_state(p);
    if (t_index == 0u) {
        wg_start = tile_offsets[tile];
        wg_stop = tile_offsets[tile + 1u];
        atomicStore(&wg_end_max, 0u);
    }
    // Uniform across the workgroup, so the loop's barriers are in uniform control flow.
    let start = workgroupUniformLoad(&wg_start);
    let stop = workgroupUniformLoad(&wg_stop);
    let end = pixel_end(x, y, inside, start, stop);
    // The walk starts at the last splat a pixel of the tile blended (where blending stopped
    // early, most of the tile's list); the intersections behind it get zero gradients.
    let sub_end = subgroupMax(end);
    if (lane == 0u) {
        atomicMax(&wg_end_max, sub_end);
    }
    workgroupBarrier();
    if (t_index == 0u) {
        wg_top = max(atomicLoad(&wg_end_max), start);
    }
    let top = workgroupUniformLoad(&wg_top);
    for (var i = t_index; i < (stop - top) * RED_VALUES; i = i + 256u) {
        let k = top + i / RED_VALUES;
        let v = i % RED_VALUES;
        if (v < GRAD_FLOATS) {
            partials[k * GRAD_FLOATS + v] = 0.0;
        } else {
            partial_pixels[k] = 0u;
        }
    }

    var batch_end = top;
    while (batch_end > start) {
        let count = min(sg, batch_end - start);
        let base = batch_end - count;
        let own = load_batch(base, count, lane);
        // The splats a pixel of this subgroup can reach, back to front (the ballot's set bits,
        // as the pair kernels walk them: a CPU device would run the others masked); the others'
        // sums are zero, written below.
        let at = vec2<f32>(p.m.fx, p.m.fy);
        let reach = batch_reach(own, count, lane, at, at, end <= base);
        var left = reach;
        if (ballot_any(left)) {
            loop {
                let j = ballot_last(left);
                left = ballot_clear(left, j);
                let k = base + j;
                // This pixel's contribution to intersection k (zero unless blended there).
                let c = splat_contribution(p, &st, own, j, k < end);
                // Subgroup sums (every lane takes part), written by lane 0; zeros without an
                // add when no pixel of this subgroup blended the splat.
                var s0 = vec4<f32>(0.0);
                var s1 = vec4<f32>(0.0);
                var s2 = vec4<f32>(0.0);
                var s3 = 0.0;
                if (subgroupAny(c.pixels > 0.0)) {
                    s0 = subgroup_sum4(c.a, sg);
                    s1 = subgroup_sum4(c.b, sg);
                    s2 = subgroup_sum4(c.c, sg);
                    s3 = subgroup_count(c.pixels);
                }
                if (lane == 0u) {
                    write_red(sg_id * sg + j, s0, s1, s2, s3);
                }
                if (!ballot_any(left)) {
                    break;
                }
            }
        }
        // Each slot once: lane j writes the zeros of splat j when the subgroup skipped it.
        if (lane < count && !ballot_bit(reach, lane)) {
            write_red(sg_id * sg + lane, vec4<f32>(0.0), vec4<f32>(0.0), vec4<f32>(0.0), 0.0);
        }
        workgroupBarrier();
        // Thread j * 13 + v (and + 256, for subgroups of more than 19 lanes) adds value v of
        // intersection base + j over the subgroups, in subgroup order.
        for (var i = t_index; i < count * RED_VALUES; i = i + 256u) {
            let j = i / RED_VALUES;
            let v = i % RED_VALUES;
            var acc = 0.0;
            for (var g = 0u; g < sg_count; g = g + 1u) {
                acc = acc + red[(g * sg + j) * RED_VALUES + v];
            }
            let k = base + j;
            if (v < GRAD_FLOATS) {
                partials[k * GRAD_FLOATS + v] = acc;
            } else {
                partial_pixels[k] = u32(acc);
            }
        }
        // The sums are read before the next step writes them.
        workgroupBarrier();
        batch_end = base;
    }
    if (inside) {
        write_medium_grads(x, y, st);
    }
}

// One halving step of `add_subgroup_sums`: lanes with `mask` set keep the upper half of the
// `half * 2` values they hold, the others the lower half, each adding its partner's copy of the
// half it keeps (the partner sends the half it gives up). Returns the offset of the kept half.
fn halve(v: ptr<function, array<f32, 16>>, half: u32, mask: u32, lane: u32) -> u32 {
    let upper = (lane & mask) != 0u;
    for (var i = 0u; i < half; i++) {
        let lo = (*v)[i];
        let hi = (*v)[i + half];
        let send = select(hi, lo, upper);
        let keep = select(lo, hi, upper);
        (*v)[i] = keep + subgroupShuffleXor(send, mask);
    }
    return select(0u, half, upper);
}

// Adds one intersection's 13 subgroup sums (the 12 gradient floats and the pixel count) to
// its partials with atomics, by a reduce-scatter instead of 13 full reductions: each halving
// step trades half of what a lane holds with the lane `mask` away (mask = sg/2, sg/4, ...)
// until each lane holds 16/sg of the values (one, for 16 lanes and more, with full adds over
// the lanes left); lanes then add the values they own, once each. 15 shuffles for 32 lanes,
// where 13 full sums take 65 (and `subgroup_sum4`'s four butterflies 20 of four floats each).
// Called in uniform control flow (every lane of the subgroup).
fn add_subgroup_sums(c: Contribution, k: u32, lane: u32, sg: u32) {
    var v = array<f32, 16>(c.a.x, c.a.y, c.a.z, c.a.w, c.b.x, c.b.y, c.b.z, c.b.w,
                           c.c.x, c.c.y, c.c.z, c.c.w, c.pixels, 0.0, 0.0, 0.0);
    var first = 0u;
    var held = 16u;
    var mask = sg >> 1u;
    // Unrolled by hand so that every step indexes the array with constants.
    if (mask >= 1u) {
        first += halve(&v, 8u, mask, lane);
        held = 8u;
        mask = mask >> 1u;
    }
    if (mask >= 1u) {
        first += halve(&v, 4u, mask, lane);
        held = 4u;
        mask = mask >> 1u;
    }
    if (mask >= 1u) {
        first += halve(&v, 2u, mask, lane);
        held = 2u;
        mask = mask >> 1u;
    }
    if (mask >= 1u) {
        first += halve(&v, 1u, mask, lane);
        held = 1u;
        mask = mask >> 1u;
    }
    // More than 16 lanes: the lanes that differ only in the low bits hold the same value.
    let owner_bits = select(0u, 2u * mask - 1u, mask >= 1u);
    for (var m = mask; m >= 1u; m = m >> 1u) {
        v[0] = v[0] + subgroupShuffleXor(v[0], m);
    }
    if ((lane & owner_bits) != 0u) {
        return;
    }
    // Constant indices only (a dynamically indexed array lives in memory on a CPU device).
    let o = k * GRAD_FLOATS;
    add_sum(o, k, first, v[0]);
    if (held >= 2u) {
        add_sum(o, k, first + 1u, v[1]);
    }
    if (held >= 4u) {
        add_sum(o, k, first + 2u, v[2]);
        add_sum(o, k, first + 3u, v[3]);
    }
    if (held >= 8u) {
        for (var i = 4u; i < 8u; i++) {
            add_sum(o, k, first + i, v[i]);
        }
    }
    if (held >= 16u) {
        for (var i = 8u; i < 16u; i++) {
            add_sum(o, k, first + i, v[i]);
        }
    }
}

// The sum of `v` over the subgroup, in every lane, by a butterfly of `subgroupShuffleXor`s
// with constant masks (as `subgroupAdd` would be, without its cost on lavapipe: there the
// backward took 0.79-0.82x the time). Deterministic: every lane adds the same pairs in the
// same order, so all lanes hold the same bits, run after run. Uniform control flow only.
fn subgroup_sum4(v: vec4<f32>, sg: u32) -> vec4<f32> {
    var s = v;
    if (sg > 1u) { s = s + subgroupShuffleXor(s, 1u); }
    if (sg > 2u) { s = s + subgroupShuffleXor(s, 2u); }
    if (sg > 4u) { s = s + subgroupShuffleXor(s, 4u); }
    if (sg > 8u) { s = s + subgroupShuffleXor(s, 8u); }
    if (sg > 16u) { s = s + subgroupShuffleXor(s, 16u); }
    if (sg > 32u) { s = s + subgroupShuffleXor(s, 32u); }
    if (sg > 64u) { s = s + subgroupShuffleXor(s, 64u); }
    return s;
}

// The sum over the subgroup of `pixels` (0, 1 or 2 in each lane: a lane's pixel count) by
// two ballots, where a fourth vector sum would take as long as each of the other three.
fn subgroup_count(pixels: f32) -> f32 {
    let one = subgroupBallot(pixels >= 1.0);
    let two = subgroupBallot(pixels >= 2.0);
    let bits = countOneBits(one) + countOneBits(two);
    return f32(bits.x + bits.y + bits.z + bits.w);
}

// `add_subgroup_sums` by three vector sums over the subgroup (`subgroup_sum4`), each lane then
// adding one sum (faster with few lanes, as lavapipe's 8).
fn add_subgroup_sums_by_adds(c: Contribution, k: u32, lane: u32, sg: u32) {
    let s0 = subgroup_sum4(c.a, sg);
    let s1 = subgroup_sum4(c.b, sg);
    let s2 = subgroup_sum4(c.c, sg);
    let s3 = subgroup_count(c.pixels);
    let o = k * GRAD_FLOATS;
    for (var v = lane; v < RED_VALUES; v += sg) {
        var s = s0;
        if (v >= 8u) {
            s = s2;
        } else if (v >= 4u) {
            s = s1;
        }
        add_sum(o, k, v, select(s[v & 3u], s3, v == GRAD_FLOATS));
    }
}

// Adds value `value` (of the 13) of intersection `k`, whose floats start at `o`.
fn add_sum(o: u32, k: u32, value: u32, sum: f32) {
    if (value < GRAD_FLOATS) {
        atomicAdd(&partials_sum[o + value], sum);
    } else if (value == GRAD_FLOATS) {
        atomicAdd(&partial_pixels_sum[k], u32(sum));
    }
}

// Where the atomic kernels add intersection `k`'s sums: its own slot, or its Gaussian's
// (`RasterParams::per_gaussian`).
fn sum_slot(k: u32) -> u32 {
    if (params.per_gaussian != 0u) {
        return sorted_gaussian[k];
    }
    return k;
}

// The atomic backward of one tile (both atomic entry points): `scatter` (a constant at each
// call, so each entry point keeps one of the two paths) picks the subgroup sums.
fn backward_atomic(wg: vec3<u32>, t_index: u32, lane: u32, sg: u32, scatter: bool) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = wg.x * TILE + t_index % TILE;
    let y = wg.y * TILE + t_index / TILE;
    let inside = x < params.width && y < params.height;
    let p = pixel_inputs(x, y);
    var st = pixel_state(p);
    // The same for every invocation of the workgroup (read by each: no barrier needed).
    let start = tile_offsets[tile];
    let stop = tile_offsets[tile + 1u];
    let end = pixel_end(x, y, inside, start, stop);
    // Without barriers each subgroup walks only the splats one of its pixels blended: from the
    // largest `end` of its lanes (where blending stopped early, most of the tile's list).
    var batch_end = subgroupMax(end);
    while (batch_end > start) {
        let count = min(sg, batch_end - start);
        let base = batch_end - count;
        let own = load_batch(base, count, lane);
        // Against the box of the subgroup's pixels that blended a splat of this batch (end > base).
        let at = vec2<f32>(p.m.fx, p.m.fy);
        let reach = batch_reach(own, count, lane, at, at, end <= base);
        for (var jj = 0u; jj < count; jj = jj + 1u) {
            let j = count - 1u - jj;
            if (!ballot_bit(reach, j)) {
                continue;
            }
            let k = base + j;
            let c = splat_contribution(p, &st, own, j, k < end);
            if (subgroupAny(c.pixels > 0.0)) {
                if (scatter) {
                    add_subgroup_sums(c, sum_slot(k), lane, sg);
                } else {
                    add_subgroup_sums_by_adds(c, sum_slot(k), lane, sg);
                }
            }
        }
        batch_end = base;
    }
    if (inside) {
        write_medium_grads(x, y, st);
    }
}

@compute @workgroup_size(256)
fn rasterize_backward_atomic(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                             @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    backward_atomic(wg, t_index, lane, sg, false);
}

@compute @workgroup_size(256)
fn rasterize_backward_atomic_scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                                     @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    backward_atomic(wg, t_index, lane, sg, true);
}

// The two pixels' contributions to one intersection, added in the lane (each zero unless its
// pixel blended the splat).
fn add_contributions(u: Contribution, v: Contribution) -> Contribution {
    var c: Contribution;
    c.a = u.a + v.a;
    c.b = u.b + v.b;
    c.c = u.c + v.c;
    c.pixels = u.pixels + v.pixels;
    return c;
}

// The atomic backward with two pixels per thread (both pair entry points): the same per-pixel
// arithmetic as `backward_atomic`, but each splat the subgroup shares by shuffles serves two
// pixels, and the pair's contributions are added in the lane before the subgroup sums, so per
// pixel there are half the shuffles, subgroup sums and atomics. The two pixels carry separate
// states (two independent chains for the scheduler).
fn backward_atomic_pairs(wg: vec3<u32>, t_index: u32, lane: u32, sg: u32, scatter: bool) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = pair_x(wg, t_index);
    let y0 = pair_y(wg, t_index);
    let y1 = y0 + 1u;
    let in0 = x < params.width && y0 < params.height;
    let in1 = x < params.width && y1 < params.height;
    let p0 = pixel_inputs(x, y0);
    let p1 = pixel_inputs(x, y1);
    var st0 = pixel_state(p0);
    var st1 = pixel_state(p1);
    let start = tile_offsets[tile];
    let stop = tile_offsets[tile + 1u];
    let end0 = pixel_end(x, y0, in0, start, stop);
    let end1 = pixel_end(x, y1, in1, start, stop);
    var batch_end = subgroupMax(max(end0, end1));
    while (batch_end > start) {
        let count = min(sg, batch_end - start);
        let base = batch_end - count;
        let own = load_batch(base, count, lane);
        // Against the box of the subgroup's pixels that blended a splat of this batch (end > base).
        let out0 = end0 <= base;
        let out1 = end1 <= base;
        let lo = vec2<f32>(p0.m.fx, select(p0.m.fy, p1.m.fy, out0));
        let hi = vec2<f32>(p0.m.fx, select(p1.m.fy, p0.m.fy, out1));
        // The reached splats only, back to front (`ballot_last`: a CPU device would run the
        // others masked).
        var left = batch_reach(own, count, lane, lo, hi, out0 && out1);
        if (ballot_any(left)) {
            loop {
                let j = ballot_last(left);
                left = ballot_clear(left, j);
                let k = base + j;
                var s: SplatVecs;
                s.a = subgroupShuffle(own.a, j);
                s.b = subgroupShuffle(own.b, j);
                s.c = subgroupShuffle(own.c, j);
                var c: Contribution;
                c.a = vec4<f32>(0.0);
                c.b = vec4<f32>(0.0);
                c.c = vec4<f32>(0.0);
                c.pixels = 0.0;
                if (k < end0) {
                    c = backprop_splat(p0, &st0, s);
                }
                if (k < end1) {
                    c = add_contributions(c, backprop_splat(p1, &st1, s));
                }
                if (subgroupAny(c.pixels > 0.0)) {
                    if (scatter) {
                        add_subgroup_sums(c, sum_slot(k), lane, sg);
                    } else {
                        add_subgroup_sums_by_adds(c, sum_slot(k), lane, sg);
                    }
                }
                if (!ballot_any(left)) {
                    break;
                }
            }
        }
        batch_end = base;
    }
    if (in0) {
        write_medium_grads(x, y0, st0);
    }
    if (in1) {
        write_medium_grads(x, y1, st1);
    }
}

@compute @workgroup_size(128)
fn rasterize_backward_atomic_pairs(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                                   @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    backward_atomic_pairs(wg, t_index, lane, sg, false);
}

@compute @workgroup_size(128)
fn rasterize_backward_atomic_pairs_scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                                           @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    backward_atomic_pairs(wg, t_index, lane, sg, true);
}

struct ReduceParams {
    // Gaussians.
    n: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

var<immediate> reduce_params: ReduceParams;

@group(0) @binding(16) var<storage, read> isect_offsets: array<u32>;
@group(0) @binding(17) var<storage, read> slot_to_sorted: array<u32>;
@group(0) @binding(18) var<storage, read> in_partials: array<f32>;
@group(0) @binding(19) var<storage, read> in_partial_pixels: array<u32>;
@group(0) @binding(20) var<storage, read_write> splat_grads: array<f32>;
@group(0) @binding(21) var<storage, read_write> splat_pixels: array<u32>;
// The render's intersection count on the device (`intersection_count`: 0 after a tile
// overflow, when the offsets were not written).
@group(0) @binding(24) var<storage, read> isect_count: array<u32>;

// Zeroes the first `isect_count[0]` intersections' partials for the atomic backward, a
// workgroup per 256 intersections (dispatched indirectly from that count): their 12 x 256
// consecutive floats, thread t taking every 256th from t (so each store is coalesced).
@compute @workgroup_size(256)
fn zero_partials(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let count = isect_count[0];
    let first = wg.x * 256u;
    let end = count * GRAD_FLOATS;
    for (var v = 0u; v < GRAD_FLOATS; v = v + 1u) {
        let i = first * GRAD_FLOATS + v * 256u + t;
        if (i < end) {
            partials[i] = 0.0;
        }
    }
    if (first + t < count) {
        partial_pixels[first + t] = 0u;
    }
}

@compute @workgroup_size(256)
fn reduce_isect_grads(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let g = gid.y * groups.x * 256u + gid.x;
    if (g >= reduce_params.n) {
        return;
    }
    var acc: array<f32, 12>;
    for (var v = 0u; v < GRAD_FLOATS; v = v + 1u) {
        acc[v] = 0.0;
    }
    var pixels = 0u;
    // No intersection (or an overflow, whose offsets are stale): every gradient is zero.
    var first = isect_offsets[g];
    var last = isect_offsets[g + 1u];
    if (isect_count[0] == 0u) {
        last = first;
    }
    for (var s = first; s < last; s = s + 1u) {
        let k = slot_to_sorted[s];
        for (var v = 0u; v < GRAD_FLOATS; v = v + 1u) {
            acc[v] = acc[v] + in_partials[k * GRAD_FLOATS + v];
        }
        pixels = pixels + in_partial_pixels[k];
    }
    for (var v = 0u; v < GRAD_FLOATS; v = v + 1u) {
        splat_grads[g * GRAD_FLOATS + v] = acc[v];
    }
    splat_pixels[g] = pixels;
}
