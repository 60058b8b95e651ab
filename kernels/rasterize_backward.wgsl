// Rasterisation backward with the underwater medium (CPU reference: `rasterize_backward` /
// `backprop_pixel` and `reduce_isect_grads`, src/map/render/raster_bwd.rs, the same
// arithmetic in the same order).
//
// `rasterize_backward`: one workgroup per 16x16 tile, one thread per pixel. The tile's sorted
// splats are walked back to front (staged through workgroup memory 256 at a time); each
// thread back-propagates its pixel through the splats it blended in the forward pass
// (`start .. isect_end`), recovering the transmittance from the stored final T. For every
// intersection of the tile, the workgroup sums its pixels' contributions in workgroup memory
// (fixed order: 16 rows of 16 pixels each, then the 16 row sums) and writes one SplatGrad per
// sorted intersection, so no float atomics are used and the result is deterministic. Each
// pixel writes the gradient with respect to its medium parameters.
//
// `reduce_isect_grads`: one thread per Gaussian sums its intersections' partials, found
// through the inverse sort permutation.
//
// Per intersection, `partials` holds 12 floats in the order of `SplatGrad`: mean2d (2),
// conic (3), opacity, colour (3), z, mean2d_densify (2); `partial_pixels` the pixel count.

const TILE: u32 = 16u;
const BATCH: u32 = 256u;
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

struct Splat {
    mean2d: vec2<f32>,
    conic: vec3<f32>,
    z: f32,
    opacity: f32,
    colour: vec3<f32>,
    q_max: f32,
}

var<workgroup> batch: array<Splat, 256>;
// Contributions of the 256 pixels to one intersection, value-major: red[v * 256 + pixel].
var<workgroup> red: array<f32, 3328>;
// Row sums: row_sums[v * 16 + row].
var<workgroup> row_sums: array<f32, 208>;
var<workgroup> wg_start: u32;
var<workgroup> wg_stop: u32;

fn load_splat(g: u32) -> Splat {
    let o = g * SPLAT_FLOATS;
    var s: Splat;
    s.mean2d = vec2<f32>(splats[o], splats[o + 1u]);
    s.conic = vec3<f32>(splats[o + 2u], splats[o + 3u], splats[o + 4u]);
    s.z = splats[o + 5u];
    s.opacity = splats[o + 6u];
    s.colour = vec3<f32>(splats[o + 7u], splats[o + 8u], splats[o + 9u]);
    s.q_max = splats[o + 10u];
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

@compute @workgroup_size(16, 16)
fn rasterize_backward(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
                      @builtin(local_invocation_index) t_index: u32) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = wg.x * TILE + lid.x;
    let y = wg.y * TILE + lid.y;
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
    // Uniform across the workgroup, so the loops' barriers are in uniform control flow.
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
        let count = min(BATCH, batch_end - start);
        let base = batch_end - count;
        workgroupBarrier();
        if (t_index < count) {
            batch[t_index] = load_splat(sorted_gaussian[base + t_index]);
        }
        workgroupBarrier();
        for (var jj = 0u; jj < count; jj = jj + 1u) {
            let j = count - 1u - jj;
            let k = base + j;
            // This pixel's contribution to intersection k (zero unless blended there).
            var c_mean2d = vec2<f32>(0.0);
            var c_conic = vec3<f32>(0.0);
            var c_opacity = 0.0;
            var c_colour = vec3<f32>(0.0);
            var c_z = 0.0;
            var c_densify = vec2<f32>(0.0);
            var c_pixels = 0.0;
            if (inside && k < end) {
                let s = batch[j];
                let dx = fx - s.mean2d.x;
                let dy = fy - s.mean2d.y;
                let q = s.conic.x * dx * dx + 2.0 * s.conic.y * dx * dy + s.conic.z * dy * dy;
                var hit = q <= s.q_max * 1.0001 + 1e-3;
                var gauss = 0.0;
                var raw = 0.0;
                if (hit) {
                    gauss = exp(-0.5 * q);
                    raw = s.opacity * gauss;
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
                    let range_m = s.z * ray_norm;
                    c_pixels = 1.0;
                    var value = 0.0;
                    var g_range = 0.0;
                    for (var c = 0u; c < 3u; c = c + 1u) {
                        let e_att = exp(-m_att[c] * range_m);
                        let e_bs = exp(-m_bs[c] * range_m);
                        let col = s.colour[c];
                        value = value + (up_c[c] * (col * e_att - m_c[c] * e_bs) + up_r[c] * col);
                        c_colour[c] = w * (up_c[c] * e_att + up_r[c]);
                        g_range = g_range + w * up_c[c] * (m_bs[c] * m_c[c] * e_bs - m_att[c] * col * e_att);
                        g_c_med[c] = g_c_med[c] - up_c[c] * w * e_bs;
                        g_att[c] = g_att[c] - up_c[c] * w * col * range_m * e_att;
                        g_bs[c] = g_bs[c] + up_c[c] * w * m_c[c] * range_m * e_bs;
                    }
                    let d = depth_value(s.z);
                    let dd = d - state.x;
                    value = value + ((up_s.x * dd + up_s.y * (dd * dd - state.y)) * inv_w + up_s.z);
                    let g_d = w * (up_s.x + 2.0 * up_s.y * dd) * inv_w;
                    c_z = g_range * ray_norm + g_d * depth_value_dz(s.z);
                    let g_alpha = t * value - behind / one_minus;
                    behind = behind + w * value;
                    if (!clamped) {
                        c_opacity = g_alpha * gauss;
                        let g_q = -0.5 * alpha * g_alpha;
                        c_conic = vec3<f32>(g_q * dx * dx, g_q * 2.0 * dx * dy, g_q * dy * dy);
                        c_mean2d = vec2<f32>(-2.0 * g_q * (s.conic.x * dx + s.conic.y * dy),
                                             -2.0 * g_q * (s.conic.y * dx + s.conic.z * dy));
                        let scale = exp(min(sigma_med * range_m, MAX_DENSIFY_EXPONENT));
                        c_densify = c_mean2d * scale;
                    }
                }
            }
            red[t_index] = c_mean2d.x;
            red[256u + t_index] = c_mean2d.y;
            red[512u + t_index] = c_conic.x;
            red[768u + t_index] = c_conic.y;
            red[1024u + t_index] = c_conic.z;
            red[1280u + t_index] = c_opacity;
            red[1536u + t_index] = c_colour.x;
            red[1792u + t_index] = c_colour.y;
            red[2048u + t_index] = c_colour.z;
            red[2304u + t_index] = c_z;
            red[2560u + t_index] = c_densify.x;
            red[2816u + t_index] = c_densify.y;
            red[3072u + t_index] = c_pixels;
            workgroupBarrier();
            // Row sums: thread v * 16 + row sums the 16 pixels of one row for value v.
            if (t_index < RED_VALUES * TILE) {
                let v = t_index / TILE;
                let row = t_index % TILE;
                let o = v * 256u + row * TILE;
                var acc = 0.0;
                for (var p = 0u; p < TILE; p = p + 1u) {
                    acc = acc + red[o + p];
                }
                row_sums[t_index] = acc;
            }
            workgroupBarrier();
            // Thread v sums the 16 rows of value v and writes it (read before the next
            // intersection's row sums, which follow a barrier).
            if (t_index < RED_VALUES) {
                var acc = 0.0;
                for (var r = 0u; r < TILE; r = r + 1u) {
                    acc = acc + row_sums[t_index * TILE + r];
                }
                if (t_index < GRAD_FLOATS) {
                    partials[k * GRAD_FLOATS + t_index] = acc;
                } else {
                    partial_pixels[k] = u32(acc);
                }
            }
        }
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
