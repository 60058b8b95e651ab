//! Stage 2, `map.bin`: tile binning. An exclusive prefix sum over the per-Gaussian tile
//! counts gives every Gaussian its slice of the intersection buffer; then each Gaussian
//! writes one `(tile, depth)` key per tile it touches (one GPU thread per Gaussian).
//!
//! The prefix sum has the GPU's three-kernel shape: per-block reduction, a scan of the block
//! sums, per-block scan with the block's offset. The total is computed in u64 from the block
//! sums before anything is written, so an overflow of the intersection buffer is reported
//! with the size it would have needed and nothing is written past the capacity.

use rayon::prelude::*;

use super::project::{ProjectedSplat, TileRect};
use super::TileGrid;

/// Elements per prefix-sum block (a 256-thread workgroup scanning two elements each).
pub const SCAN_BLOCK: usize = 512;

/// Number of block sums [`exclusive_scan`] needs for `n` elements.
pub const fn scan_blocks(n: usize) -> usize {
    n.div_ceil(SCAN_BLOCK)
}

/// Exclusive prefix sum: `offsets[i] = counts[0] + .. + counts[i - 1]` for `i <= n`
/// (`offsets` has `n + 1` entries, `offsets[n]` the total), returned as u64. When the total
/// exceeds `limit`, returns `Err(total)` and leaves `offsets` unwritten.
/// `block_sums` needs [`scan_blocks`]`(n)` entries.
pub fn exclusive_scan(counts: &[u32], offsets: &mut [u32], block_sums: &mut [u64], limit: u64) -> Result<u64, u64> {
    let n = counts.len();
    let blocks = scan_blocks(n);
    assert!(offsets.len() > n && block_sums.len() >= blocks, "scan buffers too small");
    // Kernel 1: per-block reduction.
    counts.par_chunks(SCAN_BLOCK).zip(block_sums[..blocks].par_iter_mut()).for_each(|(chunk, sum)| {
        *sum = chunk.iter().map(|&c| c as u64).sum();
    });
    // Kernel 2: exclusive scan of the block sums (one workgroup).
    let mut total = 0u64;
    for s in block_sums[..blocks].iter_mut() {
        let v = *s;
        *s = total;
        total += v;
    }
    if total > limit {
        return Err(total);
    }
    // Kernel 3: per-block exclusive scan from the block's offset. total <= limit <= u32::MAX.
    offsets[..n].par_chunks_mut(SCAN_BLOCK).zip(counts.par_chunks(SCAN_BLOCK)).zip(block_sums[..blocks].par_iter()).for_each(
        |((out, chunk), &base)| {
            let mut acc = base as u32;
            for (o, &c) in out.iter_mut().zip(chunk) {
                *o = acc;
                acc += c;
            }
        },
    );
    offsets[n] = total as u32;
    Ok(total)
}

/// Bits of the depth in an intersection key: the f32 bit pattern of the (positive) depth
/// without its sign bit, always 0, and its 10 lowest mantissa bits, so a relative resolution
/// of 2^-13 (1.2 mm at 10 m). Depths closer than that keep the order of the Gaussians' index
/// (the sort is stable). 21 bits leave 11 for the tile id within 32, so that the sort takes
/// four 8-bit radix passes up to 2048 tiles (640x480 has 1200) instead of six.
pub const DEPTH_KEY_BITS: u32 = 21;

/// Sort key of one intersection: the tile id above the [`DEPTH_KEY_BITS`] highest bits of the
/// depth's f32 bit pattern (monotone for positive floats).
#[inline(always)]
pub fn isect_key(tile: u32, z: f32) -> u64 {
    ((tile as u64) << DEPTH_KEY_BITS) | (z.to_bits() >> (31 - DEPTH_KEY_BITS)) as u64
}

/// Tile id of a key.
#[inline(always)]
pub fn key_tile(key: u64) -> u32 {
    (key >> DEPTH_KEY_BITS) as u32
}

/// The key bits a sort of `num_tiles` tiles' keys must look at.
pub fn isect_key_bits(num_tiles: usize) -> u32 {
    DEPTH_KEY_BITS + super::sort::bits_for(num_tiles.saturating_sub(1) as u64)
}

/// Writes the intersections of every Gaussian into its slice `offsets[g]..offsets[g + 1]`:
/// the key, the slot index itself as the sort value (so the sort yields the permutation), and
/// the Gaussian id of the slot. Parallel over Gaussians by splitting the buffers at the
/// offsets, so every task owns its slices.
pub fn emit_intersections(
    splats: &[ProjectedSplat<f32>],
    rects: &[TileRect],
    offsets: &[u32],
    grid: &TileGrid,
    keys: &mut [u64],
    values: &mut [u32],
    isect_gaussian: &mut [u32],
) {
    let n = splats.len();
    let total = offsets[n] as usize;
    emit_range(0, n, splats, rects, offsets, grid, (&mut keys[..total], &mut values[..total], &mut isect_gaussian[..total]));
}

type EmitOut<'a> = (&'a mut [u64], &'a mut [u32], &'a mut [u32]);

const EMIT_LEAF: usize = 1024;

#[allow(clippy::too_many_arguments)]
fn emit_range(
    lo: usize,
    hi: usize,
    splats: &[ProjectedSplat<f32>],
    rects: &[TileRect],
    offsets: &[u32],
    grid: &TileGrid,
    out: EmitOut<'_>,
) {
    if hi - lo > EMIT_LEAF {
        let mid = lo + (hi - lo) / 2;
        let at = (offsets[mid] - offsets[lo]) as usize;
        let (k0, k1) = out.0.split_at_mut(at);
        let (v0, v1) = out.1.split_at_mut(at);
        let (g0, g1) = out.2.split_at_mut(at);
        rayon::join(
            || emit_range(lo, mid, splats, rects, offsets, grid, (k0, v0, g0)),
            || emit_range(mid, hi, splats, rects, offsets, grid, (k1, v1, g1)),
        );
        return;
    }
    let (keys, values, gids) = out;
    let base = offsets[lo];
    for g in lo..hi {
        let r = rects[g];
        let mut slot = (offsets[g] - base) as usize;
        for ty in r.y0..r.y1 {
            for tx in r.x0..r.x1 {
                let tile = ty * grid.tiles_x as u32 + tx;
                keys[slot] = isect_key(tile, splats[g].z);
                values[slot] = base + slot as u32;
                gids[slot] = g as u32;
                slot += 1;
            }
        }
    }
}
