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
// `rasterize_pairs` (`GpuContext::pixel_pairs`, the default on subgroups under 32 lanes) takes
// two pixels per thread, 128 threads a tile, so each shuffled splat serves two pixels, and
// walks only the splats the subgroup reaches (the ballot's set bits, ballot.wgsl: on
// lavapipe 0.6x the time of stepping through all of them).
//
// Per pixel and channel: C = c_med + sum_n w_n (c_n exp(-sigma_att t_n) - c_med exp(-sigma_bs t_n)),
// restored = sum_n w_n c_n, depth D and variance V by West's weighted update, alpha = sum w_n,
// final_t (object transmittance behind the last blended splat) and isect_end for the backward.

const TILE: u32 = 16u;
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

// Three vec4s per splat (`SplatVecs`, as project_forward writes them): a vector load takes
// one pass over a CPU device's lanes where a float takes one each (lavapipe).
@group(0) @binding(0) var<storage, read> splats: array<vec4<f32>>;
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
    return SplatVecs(splats[3u * g], splats[3u * g + 1u], splats[3u * g + 2u]);
}

//!include ballot.wgsl

//!include splat_reach.wgsl

//!include pixel_medium.wgsl

// What a pixel carries from splat to splat (front to back).
struct PixelBlend {
    t: f32,
    colour: vec3<f32>,
    restored: vec3<f32>,
    w_sum: f32,
    mean: f32,
    m2: f32,
    end: u32,
    done: bool,
}

fn pixel_blend(inside: bool, start: u32) -> PixelBlend {
    var b: PixelBlend;
    b.t = 1.0;
    b.colour = vec3<f32>(0.0);
    b.restored = vec3<f32>(0.0);
    b.w_sum = 0.0;
    b.mean = 0.0;
    b.m2 = 0.0;
    b.end = start;
    b.done = !inside;
    return b;
}

// Blends splat `s` (intersection `k`) into the pixel, unless it is finished or the splat
// misses it.
fn blend_splat(p: PixelMedium, b: ptr<function, PixelBlend>, s: SplatVecs, k: u32) {
    if ((*b).done) {
        return;
    }
    let dx = p.fx - s.a.x;
    let dy = p.fy - s.a.y;
    let q = s.a.z * dx * dx + 2.0 * s.a.w * dx * dy + s.b.x * dy * dy;
    if (q > s.b.w * 1.0001 + 1e-3) {
        return;
    }
    let gauss = exp(-0.5 * q);
    let raw = s.b.z * gauss;
    if (raw < ALPHA_MIN) {
        return;
    }
    let alpha = min(raw, ALPHA_MAX);
    let next_t = (*b).t * (1.0 - alpha);
    if (next_t < T_MIN) {
        (*b).done = true;
        return;
    }
    let w = alpha * (*b).t;
    let z = s.b.y;
    let range_m = z * p.ray_norm;
    let direct = s.c.xyz * exp(-p.m_att * range_m);
    let veiled = p.m_c * exp(-p.m_bs * range_m);
    (*b).colour = (*b).colour + w * (direct - veiled);
    (*b).restored = (*b).restored + w * s.c.xyz;
    var d = z;
    if (params.depth_mode == 0u) {
        d = 1.0 / z;
    }
    let w_new = (*b).w_sum + w;
    let delta = d - (*b).mean;
    (*b).mean = (*b).mean + delta * w / w_new;
    (*b).m2 = (*b).m2 + w * delta * (d - (*b).mean);
    (*b).w_sum = w_new;
    (*b).t = next_t;
    (*b).end = k + 1u;
}

fn write_pixel(x: u32, y: u32, p: PixelMedium, b: PixelBlend) {
    let i = y * params.width + x;
    let colour = b.colour + p.m_c;
    out_colour[i * 3u] = colour.x;
    out_colour[i * 3u + 1u] = colour.y;
    out_colour[i * 3u + 2u] = colour.z;
    out_restored[i * 3u] = b.restored.x;
    out_restored[i * 3u + 1u] = b.restored.y;
    out_restored[i * 3u + 2u] = b.restored.z;
    var depth = 0.0;
    var depth_var = 0.0;
    if (b.w_sum > 0.0) {
        depth = b.mean;
        depth_var = b.m2 / b.w_sum;
    }
    out_scalars[i] = vec4<f32>(depth, depth_var, b.w_sum, b.t);
    out_isect_end[i] = b.end;
}

// Lane l's splat of the step from `b` (zero beyond the tile's list).
fn load_step(b: u32, stop: u32, lane: u32) -> SplatVecs {
    var own: SplatVecs;
    if (b + lane < stop) {
        own = load_splat_vecs(sorted_gaussian[b + lane]);
    }
    return own;
}

// Splat j of the step, shared by lane j (every lane shuffles, finished ones too).
fn shared_splat(own: SplatVecs, j: u32) -> SplatVecs {
    var s: SplatVecs;
    s.a = subgroupShuffle(own.a, j);
    s.b = subgroupShuffle(own.b, j);
    s.c = subgroupShuffle(own.c, j);
    return s;
}

@compute @workgroup_size(256)
fn rasterize(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
             @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = wg.x * TILE + t_index % TILE;
    let y = wg.y * TILE + t_index / TILE;
    let inside = x < params.width && y < params.height;
    let p = pixel_medium(x, y);
    let start = tile_offsets[tile];
    let stop = tile_offsets[tile + 1u];
    var px = pixel_blend(inside, start);
    for (var b = start; b < stop; b = b + sg) {
        if (subgroupAll(px.done)) {
            break;
        }
        let own = load_step(b, stop, lane);
        let count = min(sg, stop - b);
        // Against the box of the subgroup's pixels still blending.
        let at = vec2<f32>(p.fx, p.fy);
        let reach = batch_reach(own, count, lane, at, at, px.done);
        for (var j = 0u; j < count; j = j + 1u) {
            if (!ballot_bit(reach, j)) {
                continue;
            }
            blend_splat(p, &px, shared_splat(own, j), b + j);
        }
    }
    if (inside) {
        write_pixel(x, y, p, px);
    }
}

// `rasterize` with two pixels per thread (`GpuContext::pixel_pairs`): thread t of 128 takes the
// pixel pair `pair_x`, `pair_y` (and the row below), so each splat the subgroup shares serves
// two pixels (half the shuffles per pixel). The same arithmetic per pixel.
@compute @workgroup_size(128)
fn rasterize_pairs(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t_index: u32,
                   @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_size) sg: u32) {
    let tile = wg.y * params.tiles_x + wg.x;
    let x = pair_x(wg, t_index);
    let y0 = pair_y(wg, t_index);
    let y1 = y0 + 1u;
    let in0 = x < params.width && y0 < params.height;
    let in1 = x < params.width && y1 < params.height;
    let p0 = pixel_medium(x, y0);
    let p1 = pixel_medium(x, y1);
    let start = tile_offsets[tile];
    let stop = tile_offsets[tile + 1u];
    var px0 = pixel_blend(in0, start);
    var px1 = pixel_blend(in1, start);
    for (var b = start; b < stop; b = b + sg) {
        let done = px0.done && px1.done;
        if (subgroupAll(done)) {
            break;
        }
        let own = load_step(b, stop, lane);
        let count = min(sg, stop - b);
        // Against the box of the subgroup's pixels still blending.
        let lo = vec2<f32>(p0.fx, select(p0.fy, p1.fy, px0.done));
        let hi = vec2<f32>(p0.fx, select(p1.fy, p0.fy, px1.done));
        // The reached splats only, front to back (`ballot_first`: a CPU device would run the
        // others masked).
        var left = batch_reach(own, count, lane, lo, hi, done);
        if (ballot_any(left)) {
            loop {
                let j = ballot_first(left);
                left = ballot_clear(left, j);
                let s = shared_splat(own, j);
                blend_splat(p0, &px0, s, b + j);
                blend_splat(p1, &px1, s, b + j);
                if (!ballot_any(left)) {
                    break;
                }
            }
        }
    }
    if (in0) {
        write_pixel(x, y0, p0, px0);
    }
    if (in1) {
        write_pixel(x, y1, p1, px1);
    }
}
