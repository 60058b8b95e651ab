// Rasterisation forward with the underwater medium: one workgroup per 16x16 tile, one thread
// per pixel (row-major in the tile; CPU reference: `rasterize_forward` / `blend_pixel` /
// `splat_alpha`, src/map/render/raster_fwd.rs, the same arithmetic in the same order).
//
// The tile's sorted splats are shared within each subgroup, not through workgroup memory:
// lane l loads splat `b + l` from the storage buffer, and the subgroup walks the `sg` splats
// of that step with `subgroupShuffle` (the index is the same in every lane). No barrier is
// needed, and a subgroup leaves the loop as soon as all its pixels are finished
// (`subgroupAll`). Measured on lavapipe (Mesa 22.3): loading staged splats from workgroup
// memory gathers lane by lane and made this kernel 5-10x slower than the shuffles.
//
// Per pixel and channel: C = c_med + sum_n w_n (c_n exp(-sigma_att t_n) - c_med exp(-sigma_bs t_n)),
// restored = sum_n w_n c_n, depth D and variance V by West's weighted update, alpha = sum w_n,
// final_t (object transmittance behind the last blended splat) and isect_end for the backward.

const TILE: u32 = 16u;
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

// A projected splat as three vectors (what one shuffle moves):
// a = (mean2d.x, mean2d.y, conic.x, conic.y), b = (conic.z, z, opacity, q_max), c = (colour, 0).
struct SplatVecs {
    a: vec4<f32>,
    b: vec4<f32>,
    c: vec4<f32>,
}

fn load_splat_vecs(g: u32) -> SplatVecs {
    let o = g * SPLAT_FLOATS;
    var s: SplatVecs;
    s.a = vec4<f32>(splats[o], splats[o + 1u], splats[o + 2u], splats[o + 3u]);
    s.b = vec4<f32>(splats[o + 4u], splats[o + 5u], splats[o + 6u], splats[o + 10u]);
    s.c = vec4<f32>(splats[o + 7u], splats[o + 8u], splats[o + 9u], 0.0);
    return s;
}

//!include splat_reach.wgsl

@compute @workgroup_size(256)
fn rasterize(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
             @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
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

    let start = tile_offsets[tile];
    let stop = tile_offsets[tile + 1u];
    var t = 1.0;
    var colour = vec3<f32>(0.0);
    var restored = vec3<f32>(0.0);
    var w_sum = 0.0;
    var mean = 0.0;
    var m2 = 0.0;
    var end = start;
    var done = !inside;
    for (var b = start; b < stop; b = b + sg) {
        if (subgroupAll(done)) {
            break;
        }
        // The box of the subgroup's pixels still blending.
        let lo = vec2<f32>(subgroupMin(select(fx, BIG, done)), subgroupMin(select(fy, BIG, done)));
        let hi = vec2<f32>(subgroupMax(select(fx, -BIG, done)), subgroupMax(select(fy, -BIG, done)));
        var own: SplatVecs;
        if (b + lane < stop) {
            own = load_splat_vecs(sorted_gaussian[b + lane]);
        }
        let count = min(sg, stop - b);
        let reach = subgroupBallot(lane < count && reaches(own, lo, hi));
        for (var j = 0u; j < count; j = j + 1u) {
            if (!ballot_bit(reach, j)) {
                continue;
            }
            // Every lane shuffles (finished ones too), then skips.
            let va = subgroupShuffle(own.a, j);
            let vb = subgroupShuffle(own.b, j);
            let vc = subgroupShuffle(own.c, j);
            if (done) {
                continue;
            }
            let dx = fx - va.x;
            let dy = fy - va.y;
            let q = va.z * dx * dx + 2.0 * va.w * dx * dy + vb.x * dy * dy;
            if (q > vb.w * 1.0001 + 1e-3) {
                continue;
            }
            let gauss = exp(-0.5 * q);
            let raw = vb.z * gauss;
            if (raw < ALPHA_MIN) {
                continue;
            }
            let alpha = min(raw, ALPHA_MAX);
            let next_t = t * (1.0 - alpha);
            if (next_t < T_MIN) {
                done = true;
                continue;
            }
            let w = alpha * t;
            let z = vb.y;
            let range_m = z * ray_norm;
            let direct = vc.xyz * exp(-m_att * range_m);
            let veiled = m_c * exp(-m_bs * range_m);
            colour = colour + w * (direct - veiled);
            restored = restored + w * vc.xyz;
            var d = z;
            if (params.depth_mode == 0u) {
                d = 1.0 / z;
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
