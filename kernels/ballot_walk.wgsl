// The set-bit walk of ballot.wgsl (`ballot_any`, `ballot_first`, `ballot_last`,
// `ballot_clear`) on given masks, one invocation per mask (CPU reference:
// `gpu::ops::ballot_walk`; the rasterisers walk their reach ballots this way, and on devices
// of up to 32 lanes only the first word is ever set, so this is where the others are tested).
//   walk_order  mask i -> order[i * 256 ..]: its set bits front to back (`ballot_first`), then
//               back to front (`ballot_last`), each walk ended by 0xffffffff where shorter
//               than 128.

const WALK_WORDS: u32 = 256u;
const END: u32 = 0xffffffffu;

struct WalkParams {
    n: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

var<immediate> params: WalkParams;

@group(0) @binding(0) var<storage, read> masks: array<vec4<u32>>;
@group(0) @binding(1) var<storage, read_write> order: array<u32>;

//!include ballot.wgsl

@compute @workgroup_size(64)
fn walk_order(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= params.n) {
        return;
    }
    let o = i * WALK_WORDS;
    var written = 0u;
    var left = masks[i];
    if (ballot_any(left)) {
        loop {
            let j = ballot_first(left);
            left = ballot_clear(left, j);
            order[o + written] = j;
            written += 1u;
            if (!ballot_any(left)) {
                break;
            }
        }
    }
    if (written < 128u) {
        order[o + written] = END;
    }
    written = 0u;
    left = masks[i];
    if (ballot_any(left)) {
        loop {
            let j = ballot_last(left);
            left = ballot_clear(left, j);
            order[o + 128u + written] = j;
            written += 1u;
            if (!ballot_any(left)) {
                break;
            }
        }
    }
    if (written < 128u) {
        order[o + 128u + written] = END;
    }
}
