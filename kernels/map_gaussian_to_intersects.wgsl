// Tile binning, one thread per Gaussian (CPU reference: `emit_intersections`,
// src/map/render/bin.rs): each Gaussian writes one (tile << 21 | 21 depth bits) key per tile of
// its rectangle into its slice offsets[g]..offsets[g + 1] of the intersection buffer, the slot
// itself as the sort value and its id per slot. When the tile-count scan flagged an overflow
// (status[0] != 0) nothing is written: the buffers have a fixed capacity.

const SPLAT_FLOATS: u32 = 12u;
// `DEPTH_KEY_BITS` of src/map/render/bin.rs: the depth's bits below the tile id.
const DEPTH_KEY_BITS: u32 = 21u;

struct BinParams {
    n: u32,
    tiles_x: u32,
    pad0: u32,
    pad1: u32,
}

var<immediate> params: BinParams;

@group(0) @binding(0) var<storage, read> splats: array<f32>;
@group(0) @binding(1) var<storage, read> rects: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read> status: array<u32>;
@group(0) @binding(4) var<storage, read_write> keys: array<vec2<u32>>;
@group(0) @binding(5) var<storage, read_write> values: array<u32>;
@group(0) @binding(6) var<storage, read_write> isect_gaussian: array<u32>;

@compute @workgroup_size(256)
fn map_gaussian_to_intersects(@builtin(global_invocation_id) gid: vec3<u32>) {
    let g = gid.x;
    if (g >= params.n || status[0] != 0u) {
        return;
    }
    let r = rects[g];
    let z_bits = bitcast<u32>(splats[g * SPLAT_FLOATS + 5u]);
    var slot = offsets[g];
    for (var ty = r.y; ty < r.w; ty = ty + 1u) {
        for (var tx = r.x; tx < r.z; tx = tx + 1u) {
            let tile = ty * params.tiles_x + tx;
            keys[slot] = vec2<u32>((tile << DEPTH_KEY_BITS) | (z_bits >> (31u - DEPTH_KEY_BITS)), tile >> (32u - DEPTH_KEY_BITS));
            values[slot] = slot;
            isect_gaussian[slot] = g;
            slot = slot + 1u;
        }
    }
}

// The intersection count of this render on the device, for the kernels after binning without
// a round trip to the host: `isect_args` = [count, sort blocks, 1, 1, 256-intersection
// groups, 1, 1, 0], the last two triples `vkCmdDispatchIndirect` arguments. An overflow
// (nothing emitted) counts 0. One thread.
struct CountParams {
    sort_block: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

var<immediate> count_params: CountParams;

@group(0) @binding(7) var<storage, read_write> isect_args: array<u32>;

@compute @workgroup_size(1)
fn intersection_count() {
    var n = status[1];
    if (status[0] != 0u) {
        n = 0u;
    }
    isect_args[0] = n;
    isect_args[1] = (n + count_params.sort_block - 1u) / count_params.sort_block;
    isect_args[2] = 1u;
    isect_args[3] = 1u;
    isect_args[4] = (n + 255u) / 256u;
    isect_args[5] = 1u;
    isect_args[6] = 1u;
    isect_args[7] = 0u;
}
