// Exclusive prefix sum of u32 counts, three kernels (CPU reference: `exclusive_scan`,
// src/map/render/bin.rs, the same three-kernel shape):
//   reduce       one workgroup per 512-element block: the block's sum
//   scan_blocks  one workgroup: exclusive scan of the block sums, the total, overflow flag
//   scan_add     one workgroup per block: exclusive scan of the block from its offset
// `offsets` has n + 1 entries (offsets[n] = total). Block sums and the total are exact 64-bit
// values (u32 pairs). When the total exceeds `limit` (or 2^32),
// `status` = [1, needed_lo, needed_hi] and scan_add writes nothing (fixed capacity: the
// caller reacts by policy, nothing is reallocated).
// Workgroup memory is not zero-initialised (build.rs): every kernel writes what it reads.

const WG: u32 = 256u;
const BLOCK: u32 = 512u;

struct ScanParams {
    n: u32,
    limit: u32,
    blocks: u32,
    pad: u32,
}

var<immediate> params: ScanParams;

@group(0) @binding(0) var<storage, read> counts: array<u32>;
// Per block: (sum lo, sum hi) from reduce, exact as u64; scan_blocks replaces .x by the
// block's offset (valid when the total fits).
@group(0) @binding(1) var<storage, read_write> block_sums: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> offsets: array<u32>;
// [failed, needed_lo, needed_hi, total_lo]
@group(0) @binding(3) var<storage, read_write> status: array<u32>;

var<workgroup> sh: array<u32, 512>;
var<workgroup> sh_hi: array<u32, 256>;

fn count_at(i: u32) -> u32 {
    if (i < params.n) {
        return counts[i];
    }
    return 0u;
}

// Work-efficient (Blelloch) exclusive scan of sh[0..512] in place by 256 threads; returns the
// total. Must be called from uniform control flow.
fn scan_shared(t: u32) -> u32 {
    var offset = 1u;
    for (var d = BLOCK >> 1u; d > 0u; d = d >> 1u) {
        workgroupBarrier();
        if (t < d) {
            let ai = offset * (2u * t + 1u) - 1u;
            let bi = offset * (2u * t + 2u) - 1u;
            sh[bi] = sh[bi] + sh[ai];
        }
        offset = offset << 1u;
    }
    workgroupBarrier();
    let total = sh[BLOCK - 1u];
    workgroupBarrier();
    if (t == 0u) {
        sh[BLOCK - 1u] = 0u;
    }
    for (var d = 1u; d < BLOCK; d = d << 1u) {
        offset = offset >> 1u;
        workgroupBarrier();
        if (t < d) {
            let ai = offset * (2u * t + 1u) - 1u;
            let bi = offset * (2u * t + 2u) - 1u;
            let v = sh[ai];
            sh[ai] = sh[bi];
            sh[bi] = sh[bi] + v;
        }
    }
    workgroupBarrier();
    return total;
}

@compute @workgroup_size(256)
fn reduce(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let base = wg.x * BLOCK;
    let a = count_at(base + t);
    let lo0 = a + count_at(base + t + WG);
    sh[t] = lo0;
    sh_hi[t] = select(0u, 1u, lo0 < a);
    // Tree reduction in (lo, hi) pairs: exact, as the CPU reference's u64 block sums.
    for (var s = WG >> 1u; s > 0u; s = s >> 1u) {
        workgroupBarrier();
        if (t < s) {
            let lo = sh[t] + sh[t + s];
            sh_hi[t] = sh_hi[t] + sh_hi[t + s] + select(0u, 1u, lo < sh[t]);
            sh[t] = lo;
        }
    }
    if (t == 0u) {
        block_sums[wg.x] = vec2<u32>(sh[0], sh_hi[0]);
    }
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_index) t: u32) {
    // The exact total first (one thread, before the offsets overwrite .x).
    if (t == 0u) {
        var lo = 0u;
        var hi = 0u;
        for (var i = 0u; i < params.blocks; i = i + 1u) {
            let v = block_sums[i];
            let next = lo + v.x;
            hi = hi + v.y + select(0u, 1u, next < lo);
            lo = next;
        }
        let failed = hi > 0u || lo > params.limit;
        status[0] = select(0u, 1u, failed);
        status[1] = lo;
        status[2] = hi;
        status[3] = lo;
        if (!failed) {
            offsets[params.n] = lo;
        }
    }
    storageBarrier();
    workgroupBarrier();
    var carry = 0u;
    let chunks = (params.blocks + BLOCK - 1u) / BLOCK;
    for (var c = 0u; c < chunks; c = c + 1u) {
        let base = c * BLOCK;
        let i0 = base + 2u * t;
        let i1 = i0 + 1u;
        var v0 = 0u;
        var v1 = 0u;
        if (i0 < params.blocks) {
            v0 = block_sums[i0].x;
        }
        if (i1 < params.blocks) {
            v1 = block_sums[i1].x;
        }
        workgroupBarrier();
        sh[2u * t] = v0;
        sh[2u * t + 1u] = v1;
        let total = scan_shared(t);
        // Offsets wrap only when the total does not fit, and then scan_add writes nothing.
        if (i0 < params.blocks) {
            block_sums[i0].x = sh[2u * t] + carry;
        }
        if (i1 < params.blocks) {
            block_sums[i1].x = sh[2u * t + 1u] + carry;
        }
        carry = carry + total;
    }
}

@compute @workgroup_size(256)
fn scan_add(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let base = wg.x * BLOCK;
    sh[2u * t] = count_at(base + 2u * t);
    sh[2u * t + 1u] = count_at(base + 2u * t + 1u);
    scan_shared(t);
    let ok = status[0] == 0u;
    let block_offset = block_sums[wg.x].x;
    let i0 = base + 2u * t;
    if (ok && i0 < params.n) {
        offsets[i0] = block_offset + sh[2u * t];
    }
    if (ok && i0 + 1u < params.n) {
        offsets[i0 + 1u] = block_offset + sh[2u * t + 1u];
    }
}
