//! Stage 4, `map.tiles`: per-tile ranges of the sorted intersections, and the two index maps
//! the rasterisers use.
//!
//! `tile_offsets` is CSR-shaped: tile `t` owns sorted intersections
//! `tile_offsets[t] .. tile_offsets[t + 1]` (empty tiles get an empty range). Each entry is a
//! binary search over the sorted keys, one GPU thread per tile.

use rayon::prelude::*;

use super::bin::key_tile;

/// `tile_offsets[t]` = number of sorted keys with a tile id below `t`, for
/// `t in 0..=num_tiles` (`tile_offsets.len() == num_tiles + 1`).
pub fn tile_ranges(sorted_keys: &[u64], tile_offsets: &mut [u32]) {
    tile_offsets.par_iter_mut().enumerate().for_each(|(t, o)| {
        *o = sorted_keys.partition_point(|&k| (key_tile(k) as usize) < t) as u32;
    });
}

/// Gaussian id of every sorted intersection (one thread per intersection): the sort's values
/// are the intersections' slots before sorting.
pub fn gather_sorted_gaussians(sorted_slots: &[u32], isect_gaussian: &[u32], sorted_gaussian: &mut [u32]) {
    sorted_gaussian[..sorted_slots.len()].par_iter_mut().zip(sorted_slots.par_iter()).with_min_len(4096).for_each(|(g, &s)| {
        *g = isect_gaussian[s as usize];
    });
}

/// `slot_to_sorted[sorted_slots[k]] = k`: where each Gaussian's intersection slots ended up
/// after the sort, for the per-Gaussian gradient reduction. A scatter (one thread per
/// intersection on the GPU); sequential here.
pub fn invert_permutation(sorted_slots: &[u32], slot_to_sorted: &mut [u32]) {
    for (k, &s) in sorted_slots.iter().enumerate() {
        slot_to_sorted[s as usize] = k as u32;
    }
}
