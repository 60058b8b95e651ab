// Rasterisation backward with the underwater medium (CPU reference: `rasterize_backward` /
// `backprop_pixel` and `reduce_isect_grads`, src/map/render/raster_bwd.rs, the same
// per-pixel arithmetic in the same order).
//
// `rasterize_backward`: one workgroup per 16x16 tile, one thread per pixel (row-major in the
// tile). The tile's sorted splats are walked back to front, `sg` (the subgroup size) at a
// time: lane l loads splat `base + l` and the subgroup shares them by `subgroupShuffle`, as
// the forward does. Each thread back-propagates its pixel through the splats it blended in
// the forward pass (`start .. isect_end`), recovering the transmittance from the stored final
// T. Per intersection, the 13 contributions (12 gradient floats and the pixel count) are
// summed within the subgroup (`subgroupAdd`) and each subgroup's sums go to workgroup memory;
// after each step of `sg` intersections one barrier, then the subgroups' sums are added in
// subgroup order and one SplatGrad per sorted intersection is written. No float atomics, a
// fixed order on a given device: repeated runs are bit-identical. Two barriers per `sg`
// intersections (before: three per intersection, which dominated on lavapipe). Each pixel
// writes the gradient with respect to its medium parameters.
//
// `reduce_isect_grads`: one thread per Gaussian sums its intersections' partials, found
// through the inverse sort permutation.
//
// Per intersection, `partials` holds 12 floats in the order of `SplatGrad`: mean2d (2),
// conic (3), opacity, colour (3), z, mean2d_densify (2); `partial_pixels` the pixel count.

const TILE: u32 = 16u;
const SPLAT_FLOATS: u32 = 11u;
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
}

var<immediate> params: RasterParams;

@group(0) @binding(0) var<storage, read> splats: array<f32>;
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

fn load_splat_vecs(g: u32) -> SplatVecs {
    let o = g * SPLAT_FLOATS;
    var s: SplatVecs;
    s.a = vec4<f32>(splats[o], splats[o + 1u], splats[o + 2u], splats[o + 3u]);
    s.b = vec4<f32>(splats[o + 4u], splats[o + 5u], splats[o + 6u], splats[o + 10u]);
    s.c = vec4<f32>(splats[o + 7u], splats[o + 8u], splats[o + 9u], 0.0);
    return s;
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

@compute @workgroup_size(256)
fn rasterize_backward(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                      @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32,
                      @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = wg.x * TILE + t_index % TILE;
    let y = wg.y * TILE + t_index / TILE;
    let inside = x < params.width && y < params.height;
    let fx = f32(x);
    let fy = f32(y);
    let xn = (fx - params.cx) / params.fx;
    let yn = (fy - params.cy) / params.fy;
    let ray_norm = sqrt(xn * xn + yn * yn + 1.0);
    let pix = min(y, params.height - 1u) * params.width + min(x, params.width - 1u);
    let m_c = vec3<f32>(c_med[pix * 3u], c_med[pix * 3u + 1u], c_med[pix * 3u + 2u]);
    let m_att = vec3<f32>(sigma_att[pix * 3u], sigma_att[pix * 3u + 1u], sigma_att[pix * 3u + 2u]);
    let m_bs = vec3<f32>(sigma_bs[pix * 3u], sigma_bs[pix * 3u + 1u], sigma_bs[pix * 3u + 2u]);
    let up_c = vec3<f32>(up_colour[pix * 3u], up_colour[pix * 3u + 1u], up_colour[pix * 3u + 2u]);
    let up_r = vec3<f32>(up_restored[pix * 3u], up_restored[pix * 3u + 1u], up_restored[pix * 3u + 2u]);
    let up_s = up_scalars[pix];
    let state = fwd_scalars[pix];

    if (t_index == 0u) {
        wg_start = tile_offsets[tile];
        wg_stop = tile_offsets[tile + 1u];
    }
    // Uniform across the workgroup, so the loop's barriers are in uniform control flow.
    let start = workgroupUniformLoad(&wg_start);
    let stop = workgroupUniformLoad(&wg_stop);
    // Clamped to the tile's range, as the CPU reference does.
    let end = clamp(fwd_isect_end[pix], start, stop);

    var g_c_med = up_c;
    var g_att = vec3<f32>(0.0);
    var g_bs = vec3<f32>(0.0);
    var t = state.w;
    var behind = 0.0;
    var inv_w = 0.0;
    if (state.z > 0.0) {
        inv_w = 1.0 / state.z;
    }
    let sigma_med = (m_att.x + m_att.y + m_att.z) / 3.0;

    var batch_end = stop;
    while (batch_end > start) {
        let count = min(sg, batch_end - start);
        let base = batch_end - count;
        var own: SplatVecs;
        if (lane < count) {
            own = load_splat_vecs(sorted_gaussian[base + lane]);
        }
        for (var jj = 0u; jj < count; jj = jj + 1u) {
            let j = count - 1u - jj;
            let k = base + j;
            let va = subgroupShuffle(own.a, j);
            let vb = subgroupShuffle(own.b, j);
            let vc = subgroupShuffle(own.c, j);
            // This pixel's contribution to intersection k (zero unless blended there).
            var c_mean2d = vec2<f32>(0.0);
            var c_conic = vec3<f32>(0.0);
            var c_opacity = 0.0;
            var c_colour = vec3<f32>(0.0);
            var c_z = 0.0;
            var c_densify = vec2<f32>(0.0);
            var c_pixels = 0.0;
            if (inside && k < end) {
                let conic = vec3<f32>(va.z, va.w, vb.x);
                let z = vb.y;
                let opacity = vb.z;
                let dx = fx - va.x;
                let dy = fy - va.y;
                let q = conic.x * dx * dx + 2.0 * conic.y * dx * dy + conic.z * dy * dy;
                var hit = q <= vb.w * 1.0001 + 1e-3;
                var gauss = 0.0;
                var raw = 0.0;
                if (hit) {
                    gauss = exp(-0.5 * q);
                    raw = opacity * gauss;
                    hit = raw >= ALPHA_MIN;
                }
                if (hit) {
                    let clamped = raw > ALPHA_MAX;
                    var alpha = raw;
                    if (clamped) {
                        alpha = ALPHA_MAX;
                    }
                    let one_minus = 1.0 - alpha;
                    t = t / one_minus;
                    let w = t * alpha;
                    let range_m = z * ray_norm;
                    c_pixels = 1.0;
                    var value = 0.0;
                    var g_range = 0.0;
                    // The three channels as vectors (no per-channel indexing, which a CPU
                    // device turns into memory accesses); the sums over channels in channel
                    // order, as the CPU reference adds them.
                    let e_att = exp(-m_att * range_m);
                    let e_bs = exp(-m_bs * range_m);
                    let col = vc.xyz;
                    let v3 = up_c * (col * e_att - m_c * e_bs) + up_r * col;
                    value = ((value + v3.x) + v3.y) + v3.z;
                    c_colour = w * (up_c * e_att + up_r);
                    let r3 = w * up_c * (m_bs * m_c * e_bs - m_att * col * e_att);
                    g_range = ((g_range + r3.x) + r3.y) + r3.z;
                    g_c_med = g_c_med - up_c * w * e_bs;
                    g_att = g_att - up_c * w * col * range_m * e_att;
                    g_bs = g_bs + up_c * w * m_c * range_m * e_bs;
                    let d = depth_value(z);
                    let dd = d - state.x;
                    value = value + ((up_s.x * dd + up_s.y * (dd * dd - state.y)) * inv_w + up_s.z);
                    let g_d = w * (up_s.x + 2.0 * up_s.y * dd) * inv_w;
                    c_z = g_range * ray_norm + g_d * depth_value_dz(z);
                    let g_alpha = t * value - behind / one_minus;
                    behind = behind + w * value;
                    if (!clamped) {
                        c_opacity = g_alpha * gauss;
                        let g_q = -0.5 * alpha * g_alpha;
                        c_conic = vec3<f32>(g_q * dx * dx, g_q * 2.0 * dx * dy, g_q * dy * dy);
                        c_mean2d = vec2<f32>(-2.0 * g_q * (conic.x * dx + conic.y * dy),
                                             -2.0 * g_q * (conic.y * dx + conic.z * dy));
                        let scale = exp(min(sigma_med * range_m, MAX_DENSIFY_EXPONENT));
                        c_densify = c_mean2d * scale;
                    }
                }
            }
            // Subgroup sums of the 13 values packed in four vectors (every lane takes part),
            // written by lane 0; zeros without an add when no pixel of this subgroup blended
            // the splat (most of a tile's splats for most subgroups).
            var s0 = vec4<f32>(0.0);
            var s1 = vec4<f32>(0.0);
            var s2 = vec4<f32>(0.0);
            var s3 = 0.0;
            if (subgroupAny(c_pixels > 0.0)) {
                s0 = subgroupAdd(vec4<f32>(c_mean2d, c_conic.xy));
                s1 = subgroupAdd(vec4<f32>(c_conic.z, c_opacity, c_colour.xy));
                s2 = subgroupAdd(vec4<f32>(c_colour.z, c_z, c_densify));
                s3 = subgroupAdd(c_pixels);
            }
            if (lane == 0u) {
                let o = (sg_id * sg + j) * RED_VALUES;
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
        }
        workgroupBarrier();
        // Thread j * 13 + v adds value v of intersection base + j over the subgroups, in
        // subgroup order.
        if (t_index < count * RED_VALUES) {
            let j = t_index / RED_VALUES;
            let v = t_index % RED_VALUES;
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
        let i = y * params.width + x;
        grad_c_med[i * 3u] = g_c_med.x;
        grad_c_med[i * 3u + 1u] = g_c_med.y;
        grad_c_med[i * 3u + 2u] = g_c_med.z;
        grad_sigma_att[i * 3u] = g_att.x;
        grad_sigma_att[i * 3u + 1u] = g_att.y;
        grad_sigma_att[i * 3u + 2u] = g_att.z;
        grad_sigma_bs[i * 3u] = g_bs.x;
        grad_sigma_bs[i * 3u + 1u] = g_bs.y;
        grad_sigma_bs[i * 3u + 2u] = g_bs.z;
    }
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
    for (var s = isect_offsets[g]; s < isect_offsets[g + 1u]; s = s + 1u) {
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
