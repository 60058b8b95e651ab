//! Generic primitives recorded into the current submission: the exclusive prefix sum
//! (`kernels/prefix_sum.wgsl`) and the LSD radix sort of `(u64 key, u32 value)` pairs
//! (`kernels/radix_sort.wgsl`). Scratch buffers come from the arena once, sized for the
//! largest input ([`ScanScratch::new`], [`SortScratch::new`]).

use super::kernels::Kernel;
use duv_gpu::{GpuBuffer, GpuContext, GpuError, GpuRange};

/// Elements per prefix-sum workgroup (256 threads, two elements each).
pub const SCAN_BLOCK: usize = 512;
/// Elements per radix-sort workgroup.
pub const SORT_BLOCK: usize = 4096;
/// Digit values per radix pass (8 bits).
pub const RADIX: usize = 256;

fn groups(n: usize) -> [u32; 3] {
    [n as u32, 1, 1]
}

/// Scratch of [`record_exclusive_scan`] for up to `max_n` elements.
#[derive(Clone, Copy, Debug)]
pub struct ScanScratch {
    pub max_n: usize,
    /// Per block `(sum lo, sum hi)`, then `(offset, sum hi)`.
    pub block_sums: GpuBuffer<[u32; 2]>,
    /// `[failed, needed_lo, needed_hi, total_lo]`.
    pub status: GpuBuffer<u32>,
}

impl ScanScratch {
    pub fn new(ctx: &mut GpuContext, max_n: usize) -> Result<Self, GpuError> {
        Ok(ScanScratch {
            max_n,
            block_sums: ctx.alloc("scan block sums", max_n.div_ceil(SCAN_BLOCK).max(1))?,
            status: ctx.alloc("scan status", 4)?,
        })
    }

    /// Records the status for the host in the scan's submission ([`GpuContext::prefetch`]), so
    /// that [`Self::result`] needs no submission of its own.
    pub fn prefetch_result(&self, ctx: &mut GpuContext) -> Result<(), GpuError> {
        ctx.prefetch(self.status.range())
    }

    /// After the submission: `Ok(total)`, or `Err(needed)` when the total exceeded the limit
    /// (then the offsets were not written).
    pub fn result(&self, ctx: &GpuContext) -> Result<Result<u64, u64>, GpuError> {
        let mut s = [0u32; 4];
        ctx.read_prefetched(&self.status, &mut s)?;
        let total = s[1] as u64 | ((s[2] as u64) << 32);
        Ok(if s[0] == 0 { Ok(total) } else { Err(total) })
    }
}

/// Records the exclusive prefix sum of `counts[..n]` into `offsets[..=n]` (`offsets[n]` the
/// total) unless the total exceeds `limit`, in which case the status flags it and the offsets
/// stay unwritten. CPU reference: `map::render::exclusive_scan`.
pub fn record_exclusive_scan(
    ctx: &mut GpuContext,
    counts: &GpuBuffer<u32>,
    n: usize,
    offsets: &GpuBuffer<u32>,
    scratch: &ScanScratch,
    limit: u32,
) -> Result<(), GpuError> {
    if n > scratch.max_n || n > counts.len() {
        return Err(GpuError::OutOfRange { what: counts.what(), requested: n, len: scratch.max_n.min(counts.len()) });
    }
    if offsets.len() < n + 1 {
        return Err(GpuError::OutOfRange { what: offsets.what(), requested: n + 1, len: offsets.len() });
    }
    let blocks = n.div_ceil(SCAN_BLOCK);
    let params = [n as u32, limit, blocks as u32, 0];
    let imm = bytemuck::bytes_of(&params);
    let counts_r = counts.slice_range(0, n.max(1))?;
    let bufs = [counts_r, scratch.block_sums.range(), offsets.range(), scratch.status.range()];
    ctx.dispatch(Kernel::PrefixSumReduce, &[bufs[0], bufs[1]], imm, groups(blocks))?;
    ctx.dispatch(Kernel::PrefixSumScanBlocks, &[bufs[1], bufs[2], bufs[3]], imm, groups(1))?;
    ctx.dispatch(Kernel::PrefixSumScanAdd, &[bufs[0], bufs[1], bufs[2], bufs[3]], imm, groups(blocks))?;
    Ok(())
}

/// Scratch of [`record_radix_sort`] for up to `max_n` pairs.
#[derive(Clone, Copy, Debug)]
pub struct SortScratch {
    pub max_n: usize,
    pub keys_tmp: GpuBuffer<u64>,
    pub values_tmp: GpuBuffer<u32>,
    pub histograms: GpuBuffer<u32>,
    /// What the kernels' `count` binding takes when the host gives the count (unused then).
    pub unused_count: GpuBuffer<u32>,
    /// The scatter by one invocation per block (`scatter_serial`) or by a workgroup
    /// (`scatter`); `None` (the default) takes the serial one on a CPU device.
    pub serial: Option<bool>,
}

impl SortScratch {
    pub fn new(ctx: &mut GpuContext, max_n: usize) -> Result<Self, GpuError> {
        Ok(SortScratch {
            max_n,
            keys_tmp: ctx.alloc("sort keys (ping-pong)", max_n)?,
            values_tmp: ctx.alloc("sort values (ping-pong)", max_n)?,
            histograms: ctx.alloc("sort histograms", max_n.div_ceil(SORT_BLOCK).max(1) * RADIX)?,
            unused_count: ctx.alloc("sort count (host-given)", 4)?,
            serial: None,
        })
    }
}

/// Records a stable ascending sort of `keys[..n]` (only the low `key_bits` bits may be set)
/// with `values[..n]` alongside; the result is in `keys` / `values`. CPU reference:
/// `map::render::radix_sort_pairs`.
pub fn record_radix_sort(
    ctx: &mut GpuContext,
    keys: &GpuBuffer<u64>,
    values: &GpuBuffer<u32>,
    n: usize,
    key_bits: u32,
    scratch: &SortScratch,
) -> Result<(), GpuError> {
    if n > scratch.max_n || n > keys.len() || n > values.len() {
        return Err(GpuError::OutOfRange { what: keys.what(), requested: n, len: scratch.max_n.min(keys.len()).min(values.len()) });
    }
    if n < 2 {
        return Ok(());
    }
    let blocks = n.div_ceil(SORT_BLOCK);
    let a = (keys.slice_range(0, n)?, values.slice_range(0, n)?);
    let b = (scratch.keys_tmp.slice_range(0, n)?, scratch.values_tmp.slice_range(0, n)?);
    let hist = scratch.histograms.slice_range(0, blocks * RADIX)?;
    record_sort_passes(ctx, (a, b, hist, scratch.unused_count.range()), n as u32, key_bits, scratch.serial, |ctx, kernel, bufs, imm, blocks_per_group| {
        ctx.dispatch(kernel, bufs, imm, groups(blocks.div_ceil(blocks_per_group)))
    })
}

/// [`record_radix_sort`] of the first `count[0]` pairs, a count an earlier kernel of the
/// submission wrote (at most `scratch.max_n`, the caller's kernel's to ensure), with the blocks
/// dispatched indirectly from `block_args` (three u32: `ceil(count / SORT_BLOCK)`, 1, 1), so
/// the host never reads the count. The buffers are bound whole (up to `scratch.max_n`).
pub fn record_radix_sort_indirect(
    ctx: &mut GpuContext,
    keys: &GpuBuffer<u64>,
    values: &GpuBuffer<u32>,
    count: GpuRange,
    block_args: GpuRange,
    key_bits: u32,
    scratch: &SortScratch,
) -> Result<(), GpuError> {
    let n = scratch.max_n.min(keys.len()).min(values.len());
    if n == 0 {
        return Ok(());
    }
    let a = (keys.slice_range(0, n)?, values.slice_range(0, n)?);
    let b = (scratch.keys_tmp.slice_range(0, n)?, scratch.values_tmp.slice_range(0, n)?);
    let hist = scratch.histograms.range();
    // One workgroup per block from the device's count: those of the serial scatter past its
    // last block do nothing.
    record_sort_passes(ctx, (a, b, hist, count), COUNT_ON_DEVICE, key_bits, scratch.serial, |ctx, kernel, bufs, imm, _| ctx.dispatch_indirect(kernel, bufs, imm, block_args))
}

/// The count in a kernel's immediates that makes it read `count[0]`, a count an earlier kernel
/// of the submission wrote (`kernels/shared/device_count.wgsl`: the sort, the tile ranges).
pub const COUNT_ON_DEVICE: u32 = u32::MAX;

type SortBuffers = ((GpuRange, GpuRange), (GpuRange, GpuRange), GpuRange, GpuRange);

/// Blocks per workgroup of the serial histogram and scatter (`SERIAL_BLOCKS` of
/// `radix_sort.wgsl`: one invocation per block, a CPU device's 8 lanes each taking one).
pub const SERIAL_SCATTER_BLOCKS: usize = 8;

/// The passes of a radix sort of `n` pairs (or [`COUNT_ON_DEVICE`]) between `a` (keys,
/// values; the result) and `b`, with `hist` and `count` bound; `per_block` records a
/// per-block kernel taking the given number of blocks per workgroup.
fn record_sort_passes(
    ctx: &mut GpuContext,
    (a, b, hist, count): SortBuffers,
    n: u32,
    key_bits: u32,
    serial: Option<bool>,
    per_block: impl Fn(&mut GpuContext, Kernel, &[GpuRange], &[u8], usize) -> Result<(), GpuError>,
) -> Result<(), GpuError> {
    let passes = key_bits.min(64).div_ceil(8);
    // On a CPU device the histogram and scatter by one invocation per block, the scatter in
    // element order (what the CPU does); the workgroup kernels' barriers and workgroup atomics
    // cost lavapipe 2.6-5x.
    let (histogram, scatter, per_group) = match serial.unwrap_or(ctx.info().is_cpu()) {
        true => (Kernel::RadixSortHistogramSerial, Kernel::RadixSortScatterSerial, SERIAL_SCATTER_BLOCKS),
        false => (Kernel::RadixSortHistogram, Kernel::RadixSortScatter, 1),
    };
    for pass in 0..passes {
        let (src, dst) = if pass % 2 == 0 { (a, b) } else { (b, a) };
        let params = [n, pass * 8, 0, 0];
        let imm = bytemuck::bytes_of(&params);
        per_block(ctx, histogram, &[src.0, hist, count], imm, per_group)?;
        ctx.dispatch(Kernel::RadixSortScan, &[hist, count], imm, groups(1))?;
        per_block(ctx, scatter, &[src.0, src.1, hist, dst.0, dst.1, count], imm, per_group)?;
    }
    if passes % 2 == 1 {
        ctx.copy(b.0, a.0)?;
        ctx.copy(b.1, a.1)?;
    }
    Ok(())
}

/// Words of one mask's result in `ballot_walk.walk_order`: its set bits front to back, then
/// back to front, 128 words each, a shorter walk ended by [`BALLOT_WALK_END`].
pub const BALLOT_WALK_WORDS: usize = 256;
/// The end of a walk shorter than 128 in `ballot_walk.walk_order`'s result.
pub const BALLOT_WALK_END: u32 = u32::MAX;

/// The set bits of a 128-lane subgroup ballot (`mask[w]` holds lanes `32 w .. 32 w + 31`), in
/// ascending order or, `back_to_front`, descending: what the rasterisers' walk over their reach
/// ballots visits (CPU reference of `kernels/shared/ballot.wgsl`'s `ballot_first`,
/// `ballot_last` and `ballot_clear`; `ballot_walk.walk_order` runs them on the device).
pub fn ballot_walk(mask: [u32; 4], back_to_front: bool) -> Vec<u32> {
    let mut bits: Vec<u32> = (0..128u32).filter(|&j| mask[(j / 32) as usize] >> (j % 32) & 1 == 1).collect();
    if back_to_front {
        bits.reverse();
    }
    bits
}

/// Records `ballot_walk.walk_order` over `masks[..n]` into `order` ([`BALLOT_WALK_WORDS`] per
/// mask; the parity test of the ballot walk).
pub fn record_ballot_walk(ctx: &mut GpuContext, masks: &GpuBuffer<[u32; 4]>, n: usize, order: &GpuBuffer<u32>) -> Result<(), GpuError> {
    if n > masks.len() || n * BALLOT_WALK_WORDS > order.len() {
        return Err(GpuError::OutOfRange { what: order.what(), requested: n * BALLOT_WALK_WORDS, len: order.len() });
    }
    if n == 0 {
        return Ok(());
    }
    let params = [n as u32, 0, 0, 0];
    ctx.dispatch(Kernel::BallotWalkWalkOrder, &[masks.range(), order.range()], bytemuck::bytes_of(&params), [n.div_ceil(64) as u32, 1, 1])
}
