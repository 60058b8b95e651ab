// One least-significant-digit radix pass (8 bits) over (u64 key, u32 value) pairs, three
// kernels (CPU reference: `radix_sort_pairs` / `sort_pass`, src/map/render/sort.rs, the same
// shape and the same 4096-element blocks):
//   histogram  one workgroup per block: digit counts -> hist[block * 256 + digit]
//   scan       one workgroup: exclusive scan in digit-major order (block b's digit-d elements
//              follow those of blocks < b and precede digit d + 1), in place; the digit
//              totals' scan is a workgroup scan
//   scatter    one workgroup per block, 256-element chunks in order: stable scatter to dst,
//              the rank within a chunk from per-digit thread bitmasks (popcounts)
//   scatter_serial  the scatter of a block by one invocation, in element order (the CPU
//              reference's loop), eight blocks a workgroup (one a lane of lavapipe's 8; one
//              a workgroup took 2.4-2.8x as long): taken on CPU devices (lavapipe), where `scatter`'s barriers
//              and workgroup atomics took 2.6-5x its time (160-310 against 60 ms for four
//              passes over 392k pairs)
// Keys are u64 stored as vec2<u32> (lo, hi), the little-endian layout of a Rust u64.
// Integer atomics on workgroup memory only; no float atomics.

const WG: u32 = 256u;
const RADIX: u32 = 256u;
const SORT_BLOCK: u32 = 4096u;
// Blocks per workgroup of `scatter_serial` (`SERIAL_SCATTER_BLOCKS` of src/gpu/ops.rs).
const SERIAL_BLOCKS: u32 = 8u;

struct SortParams {
    // Pairs, or COUNT_ON_DEVICE: count[0].
    n: u32,
    shift: u32,
    pad0: u32,
    pad1: u32,
}

var<immediate> params: SortParams;

@group(0) @binding(0) var<storage, read> src_keys: array<vec2<u32>>;
@group(0) @binding(1) var<storage, read> src_values: array<u32>;
@group(0) @binding(2) var<storage, read_write> hist: array<u32>;
@group(0) @binding(3) var<storage, read_write> dst_keys: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read_write> dst_values: array<u32>;
// The pair count when `params.n` is `COUNT_ON_DEVICE`.
@group(0) @binding(5) var<storage, read> count: array<u32>;

//!include device_count.wgsl

fn pair_count() -> u32 {
    return host_or_device_count(params.n);
}

fn block_count() -> u32 {
    return (pair_count() + SORT_BLOCK - 1u) / SORT_BLOCK;
}

var<workgroup> counts: array<atomic<u32>, 256>;
var<workgroup> digit_offset: array<u32, 256>;
// Per digit, a 256-bit mask (8 words) of the chunk's threads holding that digit.
var<workgroup> masks: array<atomic<u32>, 2048>;

fn digit_of(key: vec2<u32>) -> u32 {
    if (params.shift < 32u) {
        return (key.x >> params.shift) & (RADIX - 1u);
    }
    return (key.y >> (params.shift - 32u)) & (RADIX - 1u);
}

@compute @workgroup_size(256)
fn histogram(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    atomicStore(&counts[t], 0u);
    workgroupBarrier();
    let base = wg.x * SORT_BLOCK;
    let n = pair_count();
    for (var k = 0u; k < SORT_BLOCK / WG; k = k + 1u) {
        let i = base + k * WG + t;
        if (i < n) {
            atomicAdd(&counts[digit_of(src_keys[i])], 1u);
        }
    }
    workgroupBarrier();
    hist[wg.x * RADIX + t] = atomicLoad(&counts[t]);
}

@compute @workgroup_size(256)
fn scan(@builtin(local_invocation_index) t: u32) {
    // Thread t owns digit t: its total over all blocks.
    let blocks = block_count();
    var total = 0u;
    // Four independent loads per iteration (a loop of one waits out each load in turn).
    var b = 0u;
    for (; b + 4u <= blocks; b = b + 4u) {
        let c0 = hist[b * RADIX + t];
        let c1 = hist[(b + 1u) * RADIX + t];
        let c2 = hist[(b + 2u) * RADIX + t];
        let c3 = hist[(b + 3u) * RADIX + t];
        total = total + ((c0 + c1) + (c2 + c3));
    }
    for (; b < blocks; b = b + 1u) {
        total = total + hist[b * RADIX + t];
    }
    // Exclusive scan of the digit totals over the workgroup (Hillis-Steele, 8 steps).
    digit_offset[t] = total;
    workgroupBarrier();
    var inclusive = total;
    for (var step = 1u; step < RADIX; step = step << 1u) {
        var add = 0u;
        if (t >= step) {
            add = digit_offset[t - step];
        }
        workgroupBarrier();
        inclusive = inclusive + add;
        digit_offset[t] = inclusive;
        workgroupBarrier();
    }
    var running = inclusive - total;
    b = 0u;
    for (; b + 4u <= blocks; b = b + 4u) {
        let c0 = hist[b * RADIX + t];
        let c1 = hist[(b + 1u) * RADIX + t];
        let c2 = hist[(b + 2u) * RADIX + t];
        let c3 = hist[(b + 3u) * RADIX + t];
        hist[b * RADIX + t] = running;
        hist[(b + 1u) * RADIX + t] = running + c0;
        hist[(b + 2u) * RADIX + t] = running + c0 + c1;
        hist[(b + 3u) * RADIX + t] = running + c0 + c1 + c2;
        running = running + ((c0 + c1) + (c2 + c3));
    }
    for (; b < blocks; b = b + 1u) {
        let c = hist[b * RADIX + t];
        hist[b * RADIX + t] = running;
        running = running + c;
    }
}

@compute @workgroup_size(256)
fn scatter(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    digit_offset[t] = hist[wg.x * RADIX + t];
    // Thread t clears digit t's 8 mask words once; afterwards each thread clears the word it set.
    for (var w = 0u; w < 8u; w = w + 1u) {
        atomicStore(&masks[t * 8u + w], 0u);
    }
    let base = wg.x * SORT_BLOCK;
    let n = pair_count();
    let word = t >> 5u;
    let bit = 1u << (t & 31u);
    for (var k = 0u; k < SORT_BLOCK / WG; k = k + 1u) {
        let i = base + k * WG + t;
        let valid = i < n;
        var d = 0u;
        var key = vec2<u32>(0u, 0u);
        workgroupBarrier();
        if (valid) {
            key = src_keys[i];
            d = digit_of(key);
            atomicOr(&masks[d * 8u + word], bit);
        }
        workgroupBarrier();
        var slot = 0u;
        var last = false;
        if (valid) {
            // Stable rank: same-digit elements earlier in this chunk (bits below t in d's
            // mask); the last of its digit (no bit above t) advances the digit's offset.
            var rank = 0u;
            var above = 0u;
            for (var w = 0u; w < 8u; w = w + 1u) {
                let m = atomicLoad(&masks[d * 8u + w]);
                if (w < word) {
                    rank = rank + countOneBits(m);
                } else if (w == word) {
                    rank = rank + countOneBits(m & (bit - 1u));
                    above = above | (m & ~(bit | (bit - 1u)));
                } else {
                    above = above | m;
                }
            }
            slot = digit_offset[d] + rank;
            last = above == 0u;
            dst_keys[slot] = key;
            dst_values[slot] = src_values[i];
        }
        workgroupBarrier();
        if (valid) {
            atomicStore(&masks[d * 8u + word], 0u);
            if (last) {
                digit_offset[d] = slot + 1u;
            }
        }
    }
}

// `scatter` with one invocation per block: each element to its digit's next slot, in element
// order (stable, the same destination as `scatter`). Invocation i of workgroup g takes block
// 8 g + i, so a CPU device's 8 lanes each walk a block (one lane a workgroup kept 7 of them
// idle); workgroups past the last block, where the dispatch is one per block (indirect, from
// the device's count), do nothing.
@compute @workgroup_size(SERIAL_BLOCKS)
fn scatter_serial(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) l: u32) {
    let block = wg.x * SERIAL_BLOCKS + l;
    if (block >= block_count()) {
        return;
    }
    var serial_counts: array<u32, 256>;
    for (var d = 0u; d < RADIX; d = d + 1u) {
        serial_counts[d] = hist[block * RADIX + d];
    }
    let base = block * SORT_BLOCK;
    let end = min(base + SORT_BLOCK, pair_count());
    for (var i = base; i < end; i = i + 1u) {
        let key = src_keys[i];
        let d = digit_of(key);
        let slot = serial_counts[d];
        serial_counts[d] = slot + 1u;
        dst_keys[slot] = key;
        dst_values[slot] = src_values[i];
    }
}

// `histogram` with one invocation per block, eight blocks a workgroup (as `scatter_serial`):
// the block's digit counts in a private array, no workgroup atomics. Taken with
// `scatter_serial`.
@compute @workgroup_size(SERIAL_BLOCKS)
fn histogram_serial(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) l: u32) {
    let block = wg.x * SERIAL_BLOCKS + l;
    if (block >= block_count()) {
        return;
    }
    var serial_counts: array<u32, 256>;
    for (var d = 0u; d < RADIX; d = d + 1u) {
        serial_counts[d] = 0u;
    }
    let base = block * SORT_BLOCK;
    let end = min(base + SORT_BLOCK, pair_count());
    for (var i = base; i < end; i = i + 1u) {
        let d = digit_of(src_keys[i]);
        serial_counts[d] = serial_counts[d] + 1u;
    }
    for (var d = 0u; d < RADIX; d = d + 1u) {
        hist[block * RADIX + d] = serial_counts[d];
    }
}
