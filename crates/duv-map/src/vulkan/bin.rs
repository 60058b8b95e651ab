//! Binning on the device (tile counts, prefix sum, intersections, radix sort, tile ranges),
//! twin of `render::bin` and `render::sort`: [`GpuBinning`].

use super::*;
use super::ops::{record_radix_sort_indirect, SortScratch, COUNT_ON_DEVICE, SORT_BLOCK};
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::render::TileGrid;

/// Tile binning, sort and ranges for up to `max_intersections` intersections on a grid of
/// up to `max_tiles` tiles.
pub struct GpuBinning {
    pub max_intersections: usize,
    pub max_tiles: usize,
    pub keys: GpuBuffer<u64>,
    pub values: GpuBuffer<u32>,
    pub isect_gaussian: GpuBuffer<u32>,
    pub sort: SortScratch,
    /// `num_tiles + 1` CSR offsets into the sorted intersections.
    pub tile_offsets: GpuBuffer<u32>,
    pub sorted_gaussian: GpuBuffer<u32>,
    pub slot_to_sorted: GpuBuffer<u32>,
    /// `[count, sort blocks, 1, 1, 256-intersection groups, 1, 1, 0]`, written on the device
    /// (`intersection_count`).
    pub isect_args: GpuBuffer<u32>,
}

impl GpuBinning {
    pub fn new(ctx: &mut GpuContext, max_intersections: usize, max_tiles: usize) -> Result<Self, GpuError> {
        Ok(GpuBinning {
            max_intersections,
            max_tiles,
            keys: ctx.alloc("intersection keys", max_intersections)?,
            values: ctx.alloc("intersection slots", max_intersections)?,
            isect_gaussian: ctx.alloc("intersection Gaussians", max_intersections)?,
            sort: SortScratch::new(ctx, max_intersections)?,
            tile_offsets: ctx.alloc("tile offsets", max_tiles + 1)?,
            sorted_gaussian: ctx.alloc("sorted Gaussians", max_intersections)?,
            slot_to_sorted: ctx.alloc("slot to sorted", max_intersections)?,
            isect_args: ctx.alloc("intersection count and dispatch arguments", 8)?,
        })
    }

    /// Records, for `n` projected Gaussians, in the projection's submission: emit the keys,
    /// count them on the device (`intersection_count`: the scan's total, 0 after an overflow,
    /// which emits nothing), sort them, tile ranges, gather and invert, the per-intersection
    /// kernels dispatched indirectly from that count, so the host reads nothing between the
    /// projection and the rasteriser. CPU references: `emit_intersections`,
    /// `radix_sort_pairs`, `tile_ranges`, `gather_sorted_gaussians`, `invert_permutation`.
    pub fn record(&self, ctx: &mut GpuContext, proj: &GpuProjection, grid: &TileGrid, n: usize) -> Result<(), GpuError> {
        let num_tiles = grid.num_tiles();
        if num_tiles > self.max_tiles {
            return Err(GpuError::OutOfRange { what: "tile offsets", requested: num_tiles + 1, len: self.max_tiles + 1 });
        }
        let count = self.isect_args.slice_range(0, 1)?;
        if n > 0 {
            let params = [n as u32, grid.tiles_x as u32, 0, 0];
            let bufs = [
                proj.splats.range(),
                proj.rects.range(),
                proj.isect_offsets.range(),
                proj.scan.status.range(),
                self.keys.range(),
                self.values.range(),
                self.isect_gaussian.range(),
            ];
            ctx.dispatch(Kernel::MapGaussianToIntersectsMapGaussianToIntersects, &bufs, bytemuck::bytes_of(&params), [
                n.div_ceil(256) as u32,
                1,
                1,
            ])?;
            let params = [SORT_BLOCK as u32, 0, 0, 0];
            ctx.dispatch(
                Kernel::MapGaussianToIntersectsIntersectionCount,
                &[proj.scan.status.range(), self.isect_args.range()],
                bytemuck::bytes_of(&params),
                [1, 1, 1],
            )?;
        } else {
            // No Gaussian, no scan: no intersection (and no dispatch from the arguments).
            ctx.fill(self.isect_args.range(), 0)?;
        }
        let key_bits = crate::render::isect_key_bits(num_tiles);
        record_radix_sort_indirect(ctx, &self.keys, &self.values, count, self.isect_args.slice_range(1, 3)?, key_bits, &self.sort)?;
        let params = [COUNT_ON_DEVICE, num_tiles as u32, 0, 0];
        let imm = bytemuck::bytes_of(&params);
        ctx.dispatch(Kernel::TileRangesTileRanges, &[self.keys.range(), self.tile_offsets.range(), count], imm, [
            (num_tiles + 1).div_ceil(256) as u32,
            1,
            1,
        ])?;
        let per_isect = self.isect_args.slice_range(4, 3)?;
        let gather = [self.values.range(), self.isect_gaussian.range(), self.sorted_gaussian.range(), count];
        ctx.dispatch_indirect(Kernel::TileRangesGatherSorted, &gather, imm, per_isect)?;
        ctx.dispatch_indirect(Kernel::TileRangesInvertPermutation, &[self.values.range(), self.slot_to_sorted.range(), count], imm, per_isect)?;
        Ok(())
    }
}
