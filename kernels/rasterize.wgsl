// Rasterisation forward with the underwater medium: one workgroup per 16x16 tile, one thread
// per pixel (CPU reference: `rasterize_forward` / `blend_pixel` / `splat_alpha`,
// src/map/render/raster_fwd.rs, the same arithmetic in the same order). The tile's sorted
// splats are staged through workgroup memory 256 at a time; every thread takes part in every
// batch (barriers stay in uniform control flow) and stops blending on its own.
//
// Per pixel and channel: C = c_med + sum_n w_n (c_n exp(-sigma_att t_n) - c_med exp(-sigma_bs t_n)),
// restored = sum_n w_n c_n, depth D and variance V by West's weighted update, alpha = sum w_n,
// final_t (object transmittance behind the last blended splat) and isect_end for the backward.

const TILE: u32 = 16u;
const BATCH: u32 = 256u;
const SPLAT_FLOATS: u32 = 11u;
const ALPHA_MIN: f32 = 0.003921568627450980; // 1/255
const ALPHA_MAX: f32 = 0.99;
const T_MIN: f32 = 0.0001;

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
@group(0) @binding(6) var<storage, read_write> out_colour: array<f32>;
@group(0) @binding(7) var<storage, read_write> out_restored: array<f32>;
// Per pixel: depth, depth_var, alpha, final_t (4 floats).
@group(0) @binding(8) var<storage, read_write> out_scalars: array<vec4<f32>>;
@group(0) @binding(9) var<storage, read_write> out_isect_end: array<u32>;

struct Splat {
    mean2d: vec2<f32>,
    conic: vec3<f32>,
    z: f32,
    opacity: f32,
    colour: vec3<f32>,
    q_max: f32,
}

var<workgroup> batch: array<Splat, 256>;
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

@compute @workgroup_size(16, 16)
fn rasterize(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>,
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

    if (t_index == 0u) {
        wg_start = tile_offsets[tile];
        wg_stop = tile_offsets[tile + 1u];
    }
    // Uniform across the workgroup, so the batch loop's barriers are in uniform control flow.
    let start = workgroupUniformLoad(&wg_start);
    let stop = workgroupUniformLoad(&wg_stop);
    var t = 1.0;
    var colour = vec3<f32>(0.0);
    var restored = vec3<f32>(0.0);
    var w_sum = 0.0;
    var mean = 0.0;
    var m2 = 0.0;
    var end = start;
    var done = !inside;
    for (var b = start; b < stop; b = b + BATCH) {
        workgroupBarrier();
        if (b + t_index < stop) {
            batch[t_index] = load_splat(sorted_gaussian[b + t_index]);
        }
        workgroupBarrier();
        let count = min(BATCH, stop - b);
        for (var j = 0u; j < count; j = j + 1u) {
            if (done) {
                break;
            }
            let s = batch[j];
            let dx = fx - s.mean2d.x;
            let dy = fy - s.mean2d.y;
            let q = s.conic.x * dx * dx + 2.0 * s.conic.y * dx * dy + s.conic.z * dy * dy;
            if (q > s.q_max * 1.0001 + 1e-3) {
                continue;
            }
            let gauss = exp(-0.5 * q);
            let raw = s.opacity * gauss;
            if (raw < ALPHA_MIN) {
                continue;
            }
            let alpha = min(raw, ALPHA_MAX);
            let next_t = t * (1.0 - alpha);
            if (next_t < T_MIN) {
                done = true;
                break;
            }
            let w = alpha * t;
            let range_m = s.z * ray_norm;
            let direct = s.colour * exp(-m_att * range_m);
            let veiled = m_c * exp(-m_bs * range_m);
            colour = colour + w * (direct - veiled);
            restored = restored + w * s.colour;
            var d = s.z;
            if (params.depth_mode == 0u) {
                d = 1.0 / s.z;
            }
            let w_new = w_sum + w;
            let delta = d - mean;
            mean = mean + delta * w / w_new;
            m2 = m2 + w * delta * (d - mean);
            w_sum = w_new;
            t = next_t;
            end = b + j + 1u;
        }
    }
    if (inside) {
        let i = y * params.width + x;
        colour = colour + m_c;
        out_colour[i * 3u] = colour.x;
        out_colour[i * 3u + 1u] = colour.y;
        out_colour[i * 3u + 2u] = colour.z;
        out_restored[i * 3u] = restored.x;
        out_restored[i * 3u + 1u] = restored.y;
        out_restored[i * 3u + 2u] = restored.z;
        var depth = 0.0;
        var depth_var = 0.0;
        if (w_sum > 0.0) {
            depth = mean;
            depth_var = m2 / w_sum;
        }
        out_scalars[i] = vec4<f32>(depth, depth_var, w_sum, t);
        out_isect_end[i] = end;
    }
}
