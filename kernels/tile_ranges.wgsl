// Per-tile ranges of the sorted intersections and the two index maps of the rasterisers
// (CPU references: `tile_ranges`, `gather_sorted_gaussians`, `invert_permutation`,
// src/map/render/tiles.rs):
//   tile_ranges       one thread per tile t in 0..=num_tiles: tile_offsets[t] = number of
//                     sorted keys with a tile id below t (binary search, as partition_point)
//   gather_sorted     one thread per intersection: sorted_gaussian[k] = isect_gaussian[slot_k]
//   invert_permutation one thread per intersection: slot_to_sorted[slot_k] = k

struct RangeParams {
    n_keys: u32,
    num_tiles: u32,
    pad0: u32,
    pad1: u32,
}

var<immediate> params: RangeParams;

@group(0) @binding(0) var<storage, read> sorted_keys: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read_write> tile_offsets: array<u32>;
@group(0) @binding(2) var<storage, read> sorted_slots: array<u32>;
@group(0) @binding(3) var<storage, read> isect_gaussian: array<u32>;
@group(0) @binding(4) var<storage, read_write> sorted_gaussian: array<u32>;
@group(0) @binding(5) var<storage, read_write> slot_to_sorted: array<u32>;
// The key count when `params.n_keys` is `COUNT_ON_DEVICE` (the intersection count).
@group(0) @binding(6) var<storage, read> count: array<u32>;

//!include device_count.wgsl

fn key_count() -> u32 {
    return host_or_device_count(params.n_keys);
}

// `key_tile` of src/map/render/bin.rs: the bits above the 21 of the depth.
fn key_tile(key: vec2<u32>) -> u32 {
    return (key.y << 11u) | (key.x >> 21u);
}

@compute @workgroup_size(256)
fn tile_ranges(@builtin(global_invocation_id) gid: vec3<u32>) {
    let t = gid.x;
    if (t > params.num_tiles) {
        return;
    }
    var lo = 0u;
    var hi = key_count();
    while (lo < hi) {
        let mid = lo + (hi - lo) / 2u;
        if (key_tile(sorted_keys[mid]) < t) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    tile_offsets[t] = lo;
}

@compute @workgroup_size(256)
fn gather_sorted(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if (k >= key_count()) {
        return;
    }
    sorted_gaussian[k] = isect_gaussian[sorted_slots[k]];
}

@compute @workgroup_size(256)
fn invert_permutation(@builtin(global_invocation_id) gid: vec3<u32>) {
    let k = gid.x;
    if (k >= key_count()) {
        return;
    }
    slot_to_sorted[sorted_slots[k]] = k;
}
