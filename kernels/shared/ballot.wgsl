// Subgroup ballots as vec4<u32> (128 lanes): a bit, and walking the set bits. Shared by
// rasterize.wgsl, rasterize_backward.wgsl and ballot_walk.wgsl (its parity kernel; `//!include
// ballot.wgsl`, pasted in by build.rs). No dependencies.

// Bit `j` of a subgroup ballot.
fn ballot_bit(m: vec4<u32>, j: u32) -> bool {
    var w = m.x;
    if (j >= 96u) {
        w = m.w;
    } else if (j >= 64u) {
        w = m.z;
    } else if (j >= 32u) {
        w = m.y;
    }
    return ((w >> (j & 31u)) & 1u) != 0u;
}

// Walking a ballot's set bits (the pair kernels walk the splats a subgroup reaches this way):
//     var left = reach;
//     if (ballot_any(left)) {
//         loop {
//             let j = ballot_first(left);   // or ballot_last, back to front
//             left = ballot_clear(left, j);
//             ...
//             if (!ballot_any(left)) { break; }
//         }
//     }
// On a CPU device (lavapipe, Mesa 22.3) a branch does not skip anything: an `if` runs its body
// under a lane mask even when no lane takes it, and only a loop's exit branches for real (once
// every lane has left). Counting j over the whole step and `continue`-ing past the splats no
// pixel reaches ran every skipped splat's arithmetic masked; walking the set bits runs only
// the reached ones. The loop tests its exit at the bottom, so it does not run once more, masked,
// after the last bit (a `while` would). The rasterisers took 0.5-0.6x the time.
fn ballot_any(m: vec4<u32>) -> bool {
    return any(m != vec4<u32>(0u));
}

// The lowest set bit of a non-zero ballot.
fn ballot_first(m: vec4<u32>) -> u32 {
    if (m.x != 0u) {
        return firstTrailingBit(m.x);
    }
    if (m.y != 0u) {
        return 32u + firstTrailingBit(m.y);
    }
    if (m.z != 0u) {
        return 64u + firstTrailingBit(m.z);
    }
    return 96u + firstTrailingBit(m.w);
}

// The highest set bit of a non-zero ballot.
fn ballot_last(m: vec4<u32>) -> u32 {
    if (m.w != 0u) {
        return 96u + firstLeadingBit(m.w);
    }
    if (m.z != 0u) {
        return 64u + firstLeadingBit(m.z);
    }
    if (m.y != 0u) {
        return 32u + firstLeadingBit(m.y);
    }
    return firstLeadingBit(m.x);
}

// `m` without bit `j`.
fn ballot_clear(m: vec4<u32>, j: u32) -> vec4<u32> {
    let w = j / 32u;
    let bit = 1u << (j % 32u);
    return m & ~vec4<u32>(select(0u, bit, w == 0u), select(0u, bit, w == 1u), select(0u, bit, w == 2u), select(0u, bit, w == 3u));
}
