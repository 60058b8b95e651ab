//! Stage 3, `map.sort`: least-significant-digit radix sort of `(key, value)` pairs on u64
//! keys, 8 bits per pass, only as many passes as the keys have significant bits (tile id
//! bits + 32 depth bits). Stable, so intersections of equal key keep slot (Gaussian) order.
//!
//! One pass has the GPU shape: per-block digit histograms (parallel over blocks), an
//! exclusive scan of the histograms in digit-major order, then each block scatters its
//! elements to their offsets. The scatter runs block after block here: its writes are
//! disjoint but interleaved, which safe Rust cannot hand to several threads. A pass where
//! every key has the same digit moves nothing and is skipped.

use rayon::prelude::*;

/// Elements per sort block (one workgroup's tile of keys).
pub const SORT_BLOCK: usize = 4096;
/// Digit width in bits and number of digit values.
pub const RADIX_BITS: u32 = 8;
pub const RADIX: usize = 1 << RADIX_BITS;

/// Length of the histogram scratch [`radix_sort_pairs`] needs for `n` elements.
pub const fn sort_histogram_len(n: usize) -> usize {
    n.div_ceil(SORT_BLOCK) * RADIX
}

/// Number of bits needed to hold values up to `max_value`.
pub fn bits_for(max_value: u64) -> u32 {
    64 - max_value.leading_zeros()
}

/// Sorts `keys` ascending, permuting `values` alongside, looking at the low `key_bits` bits
/// only (higher bits must be zero). `keys_tmp` / `values_tmp` have at least `keys.len()`
/// entries and `histograms` at least [`sort_histogram_len`]`(keys.len())`.
pub fn radix_sort_pairs(
    keys: &mut [u64],
    values: &mut [u32],
    keys_tmp: &mut [u64],
    values_tmp: &mut [u32],
    histograms: &mut [u32],
    key_bits: u32,
) {
    let n = keys.len();
    assert!(values.len() == n && keys_tmp.len() >= n && values_tmp.len() >= n, "sort buffers too small");
    assert!(histograms.len() >= sort_histogram_len(n), "sort histogram too small");
    if n < 2 {
        return;
    }
    let (keys_tmp, values_tmp) = (&mut keys_tmp[..n], &mut values_tmp[..n]);
    let hist = &mut histograms[..sort_histogram_len(n)];
    let passes = key_bits.min(64).div_ceil(RADIX_BITS);
    let mut in_tmp = false;
    for pass in 0..passes {
        let shift = pass * RADIX_BITS;
        let moved = if in_tmp {
            sort_pass(keys_tmp, values_tmp, keys, values, hist, shift)
        } else {
            sort_pass(keys, values, keys_tmp, values_tmp, hist, shift)
        };
        if moved {
            in_tmp = !in_tmp;
        }
    }
    if in_tmp {
        keys.copy_from_slice(keys_tmp);
        values.copy_from_slice(values_tmp);
    }
}

#[inline(always)]
fn digit(key: u64, shift: u32) -> usize {
    ((key >> shift) as usize) & (RADIX - 1)
}

/// One stable counting pass on the digit at `shift`; false (nothing written) when every key
/// has the same digit.
fn sort_pass(src_k: &[u64], src_v: &[u32], dst_k: &mut [u64], dst_v: &mut [u32], hist: &mut [u32], shift: u32) -> bool {
    let n = src_k.len();
    let blocks = n.div_ceil(SORT_BLOCK);
    // Kernel 1: per-block histograms.
    src_k.par_chunks(SORT_BLOCK).zip(hist.par_chunks_mut(RADIX)).for_each(|(chunk, h)| {
        h.fill(0);
        for &k in chunk {
            h[digit(k, shift)] += 1;
        }
    });
    // Kernel 2: exclusive scan, digit-major, so block b's digit-d elements follow those of
    // blocks < b and precede digit d + 1.
    let mut running = 0u32;
    for d in 0..RADIX {
        let start = running;
        for b in 0..blocks {
            let c = hist[b * RADIX + d];
            hist[b * RADIX + d] = running;
            running += c;
        }
        if running - start == n as u32 {
            return false;
        }
    }
    // Kernel 3: per-block stable scatter.
    for (b, (ks, vs)) in src_k.chunks(SORT_BLOCK).zip(src_v.chunks(SORT_BLOCK)).enumerate() {
        let h = &mut hist[b * RADIX..(b + 1) * RADIX];
        for (&k, &v) in ks.iter().zip(vs) {
            let slot = &mut h[digit(k, shift)];
            dst_k[*slot as usize] = k;
            dst_v[*slot as usize] = v;
            *slot += 1;
        }
    }
    true
}
