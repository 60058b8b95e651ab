//! GPU prefix sum and radix sort on the Vulkan device (lavapipe in CI) against plain CPU
//! algorithms and against the CPU references of the same name (`map::render`), with sizes that
//! cross workgroup boundaries. Integer kernels: results must be exactly equal.

use crate::gpu_common;

use duv_core::rng::Rng;
use duv_gpu::{GpuBuffer, GpuContext, GpuError, GpuOptions};
use duv_map::vulkan::KERNELS;
use duv_map::vulkan::ops::{
    ballot_walk, record_ballot_walk, record_exclusive_scan, record_radix_sort, ScanScratch, SortScratch, BALLOT_WALK_END, BALLOT_WALK_WORDS, SCAN_BLOCK, SORT_BLOCK,
};
use duv_map::render::{exclusive_scan, radix_sort_pairs, scan_blocks, sort_histogram_len};

/// Sizes crossing the 512-element scan block and (300 007 > 512 * 512) the one-workgroup
/// scan of the block sums, which then loops over more than one chunk.
const SCAN_SIZES: [usize; 4] = [1, SCAN_BLOCK * 16 + 123, SCAN_BLOCK * 3, 300_007];

fn plain_exclusive_scan(counts: &[u32]) -> Vec<u32> {
    let mut out = Vec::with_capacity(counts.len() + 1);
    let mut acc = 0u32;
    for &c in counts {
        out.push(acc);
        acc += c;
    }
    out.push(acc);
    out
}

#[test]
fn prefix_sum_matches_a_sequential_scan() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("prefix_sum_matches_a_sequential_scan") else { return };
    let max_n = *SCAN_SIZES.iter().max().unwrap();
    let counts_buf = ctx.alloc::<u32>("counts", max_n).unwrap();
    let offsets_buf = ctx.alloc::<u32>("offsets", max_n + 1).unwrap();
    let scratch = ScanScratch::new(&mut ctx, max_n).unwrap();
    let mut rng = Rng::new(7);
    for &n in &SCAN_SIZES {
        let counts: Vec<u32> = (0..n).map(|_| rng.below(40) as u32).collect();
        ctx.write(&counts_buf, &counts).unwrap();
        ctx.begin().unwrap();
        record_exclusive_scan(&mut ctx, &counts_buf, n, &offsets_buf, &scratch, u32::MAX).unwrap();
        ctx.submit_and_wait().unwrap();
        let mut got = vec![0u32; n + 1];
        ctx.read(&offsets_buf, &mut got).unwrap();
        let want = plain_exclusive_scan(&counts);
        assert_eq!(scratch.result(&ctx).unwrap(), Ok(want[n] as u64), "n = {n}: total");
        if let Some(i) = (0..=n).find(|&i| got[i] != want[i]) {
            panic!("n = {n}: offsets[{i}] = {} on the GPU, {} sequentially", got[i], want[i]);
        }
        // The CPU reference of the same name agrees too.
        let mut cpu = vec![0u32; n + 1];
        let mut sums = vec![0u64; scan_blocks(n)];
        assert_eq!(exclusive_scan(&counts, &mut cpu, &mut sums, u32::MAX as u64), Ok(want[n] as u64));
        assert_eq!(cpu, got, "n = {n}: GPU vs map::render::exclusive_scan");
    }
}

#[test]
fn ballot_walk_visits_every_set_bit_in_order() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("ballot_walk_visits_every_set_bit_in_order") else { return };
    // Empty, full, one bit at each word's ends, bits only in the upper words (lanes of a
    // 64-lane subgroup that devices of up to 32 lanes never set), and random masks.
    let mut masks: Vec<[u32; 4]> = vec![[0; 4], [u32::MAX; 4], [1, 0, 0, 0], [0, 0, 0, 1 << 31], [0, 1, 0, 0], [0, 0, 1 << 31, 0], [0, 0x8000_0001, 0, 0], [0, 0, 0x0f0f_0000, 3]];
    let mut rng = Rng::new(11);
    for _ in 0..200 {
        let sparse = rng.below(2) == 0;
        masks.push(std::array::from_fn(|_| {
            let w = rng.below(1 << 32) as u32;
            if sparse { w & rng.below(1 << 32) as u32 & rng.below(1 << 32) as u32 } else { w }
        }));
    }
    let n = masks.len();
    let masks_buf = ctx.alloc::<[u32; 4]>("ballot masks", n).unwrap();
    let order_buf = ctx.alloc::<u32>("ballot walk order", n * BALLOT_WALK_WORDS).unwrap();
    ctx.write(&masks_buf, &masks).unwrap();
    ctx.begin().unwrap();
    ctx.fill(order_buf.range(), 0xdead).unwrap();
    record_ballot_walk(&mut ctx, &masks_buf, n, &order_buf).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut got = vec![0u32; n * BALLOT_WALK_WORDS];
    ctx.read(&order_buf, &mut got).unwrap();
    for (i, m) in masks.iter().enumerate() {
        for (half, back) in [(0, false), (1, true)] {
            let want = ballot_walk(*m, back);
            let at = i * BALLOT_WALK_WORDS + half * 128;
            let walked = &got[at..at + want.len()];
            assert_eq!(walked, &want[..], "mask {m:08x?}, back to front {back}");
            if want.len() < 128 {
                assert_eq!(got[at + want.len()], BALLOT_WALK_END, "mask {m:08x?}, back to front {back}: walked past the last bit");
            }
        }
    }
    assert_eq!(ballot_walk([0b101, 0, 0, 1], true), [96, 2, 0]);
}

#[test]
fn prefix_sum_overflow_reports_the_size_needed_and_writes_nothing() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("prefix_sum_overflow_reports_the_size_needed_and_writes_nothing") else { return };
    let n = SCAN_BLOCK * 4 + 5;
    let counts_buf = ctx.alloc::<u32>("counts", n).unwrap();
    let offsets_buf = ctx.alloc::<u32>("offsets", n + 1).unwrap();
    let scratch = ScanScratch::new(&mut ctx, n).unwrap();
    let counts = vec![3u32; n];
    let needed = 3 * n as u64;
    ctx.write(&counts_buf, &counts).unwrap();
    ctx.write(&offsets_buf, &vec![0xdead_beef; n + 1]).unwrap();
    ctx.begin().unwrap();
    record_exclusive_scan(&mut ctx, &counts_buf, n, &offsets_buf, &scratch, (needed - 1) as u32).unwrap();
    ctx.submit_and_wait().unwrap();
    assert_eq!(scratch.result(&ctx).unwrap(), Err(needed));
    let mut got = vec![0u32; n + 1];
    ctx.read(&offsets_buf, &mut got).unwrap();
    assert!(got.iter().all(|&v| v == 0xdead_beef), "offsets written despite the overflow");
    // Totals past 2^32 are reported exactly (carry into the high word).
    let big = vec![u32::MAX / 2; 5];
    ctx.write(&counts_buf, &big).unwrap();
    ctx.begin().unwrap();
    record_exclusive_scan(&mut ctx, &counts_buf, 5, &offsets_buf, &scratch, u32::MAX).unwrap();
    ctx.submit_and_wait().unwrap();
    assert_eq!(scratch.result(&ctx).unwrap(), Err(5 * (u32::MAX / 2) as u64));
}

/// Keys shaped like the renderer's: a tile id in the high bits over a depth bit pattern, with
/// many exact duplicates so that stability is tested.
fn splat_like_keys(rng: &mut Rng, n: usize, tiles: u64) -> Vec<u64> {
    (0..n)
        .map(|_| {
            let tile = rng.below(tiles);
            let z = 0.5f32 + rng.below(64) as f32 * 0.25;
            (tile << 32) | z.to_bits() as u64
        })
        .collect()
}

/// Sorts `keys`/`values` on the device in place of their buffers (already written) and reads
/// them back; panics, naming `what`, at the first element that differs from a plain stable
/// sort of the pairs. Returns the sorted keys and values as read.
fn sort_on_device_like_a_stable_sort(
    ctx: &mut GpuContext,
    bufs: (&duv_gpu::GpuBuffer<u64>, &duv_gpu::GpuBuffer<u32>, &SortScratch),
    keys: &[u64],
    values: &[u32],
    key_bits: u32,
    what: &str,
) -> (Vec<u64>, Vec<u32>) {
    let (keys_buf, values_buf, scratch) = bufs;
    let n = keys.len();
    ctx.begin().unwrap();
    record_radix_sort(ctx, keys_buf, values_buf, n, key_bits, scratch).unwrap();
    ctx.submit_and_wait().unwrap();
    let (mut got_k, mut got_v) = (vec![0u64; n], vec![0u32; n]);
    ctx.read(keys_buf, &mut got_k).unwrap();
    ctx.read(values_buf, &mut got_v).unwrap();
    let mut want: Vec<(u64, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    want.sort_by_key(|p| p.0);
    let got: Vec<(u64, u32)> = got_k.iter().copied().zip(got_v.iter().copied()).collect();
    if let Some(i) = (0..n).find(|&i| got[i] != want[i]) {
        panic!("{what}: element {i} is {:?} on the GPU, {:?} by a stable sort", got[i], want[i]);
    }
    (got_k, got_v)
}

#[test]
fn radix_sort_matches_a_stable_sort() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("radix_sort_matches_a_stable_sort") else { return };
    // (n, tiles): 43-bit keys (6 passes, even) and 40-bit keys (5 passes: the final copy).
    let cases = [(SORT_BLOCK * 5 + 123, 1200u64), (SORT_BLOCK * 2 + 1, 200), (2, 3), (777, 256)];
    let max_n = cases.iter().map(|c| c.0).max().unwrap();
    let keys_buf = ctx.alloc::<u64>("keys", max_n).unwrap();
    let values_buf = ctx.alloc::<u32>("values", max_n).unwrap();
    let mut scratch = SortScratch::new(&mut ctx, max_n).unwrap();
    let mut rng = Rng::new(11);
    // The workgroup kernels and the serial ones (the default on a CPU device).
    for (&(n, tiles), serial) in cases.iter().flat_map(|c| [(c, false), (c, true)]) {
        scratch.serial = Some(serial);
        let keys = splat_like_keys(&mut rng, n, tiles);
        let values: Vec<u32> = (0..n as u32).collect();
        let key_bits = 32 + (64 - (tiles - 1).leading_zeros()).max(1);
        ctx.write(&keys_buf, &keys).unwrap();
        ctx.write(&values_buf, &values).unwrap();
        let what = format!("n = {n}, {key_bits}-bit keys, serial {serial}");
        let (got_k, got_v) = sort_on_device_like_a_stable_sort(&mut ctx, (&keys_buf, &values_buf, &scratch), &keys, &values, key_bits, &what);
        // The CPU reference of the same name agrees too.
        let (mut ck, mut cv) = (keys.clone(), values.clone());
        let (mut kt, mut vt, mut h) = (vec![0u64; n], vec![0u32; n], vec![0u32; sort_histogram_len(n)]);
        radix_sort_pairs(&mut ck, &mut cv, &mut kt, &mut vt, &mut h, key_bits);
        assert_eq!((ck, cv), (got_k, got_v), "{what}: GPU vs map::render::radix_sort_pairs");
    }
    let rows: Vec<String> = ctx.profile().rows().map(|(k, d, ms)| format!("{} x{d}: {ms:.2} ms", k.name())).collect();
    eprintln!("kernel times: {}", rows.join(", "));
}

/// Host transfers through a staging buffer (how a discrete GPU's device-local arena is read
/// and written): forced here with a 4 KiB staging buffer, so every transfer below crosses
/// chunks, at arena offsets that are not chunk-aligned. The sort on the staged context must
/// give exactly what the mapped one gives.
#[test]
fn staged_host_transfers_cross_chunks_and_sort_like_the_mapped_arena() {
    let Some(mapped) = gpu_common::gpu_or_skip("staged_host_transfers_cross_chunks_and_sort_like_the_mapped_arena") else { return };
    let staging = 4096u64;
    let options = GpuOptions { arena_bytes: 16 << 20, host_staging: Some(staging), ..GpuOptions::with_budget_mb(16) };
    let mut ctx = GpuContext::new(&options, &KERNELS).unwrap();
    assert_eq!(ctx.info().host_transfers, "staged");
    drop(mapped);
    // A 3-element buffer first puts the next ones off any 4 KiB boundary.
    let pad = ctx.alloc::<u32>("pad", 3).unwrap();
    let n = SORT_BLOCK * 3 + 77;
    let keys_buf = ctx.alloc::<u64>("keys", n).unwrap();
    let values_buf = ctx.alloc::<u32>("values", n).unwrap();
    let scratch = SortScratch::new(&mut ctx, n).unwrap();
    assert!(n * 8 > 4 * staging as usize, "the keys must cross several chunks");
    let mut rng = Rng::new(5);
    let keys = splat_like_keys(&mut rng, n, 700);
    let values: Vec<u32> = (0..n as u32).map(|v| v ^ 0x5a5a).collect();
    ctx.write(&pad, &[1, 2, 3]).unwrap();
    ctx.write(&keys_buf, &keys).unwrap();
    ctx.write(&values_buf, &values).unwrap();
    // Round trip before any kernel: exactly what was written, the pad untouched.
    let (mut k0, mut v0, mut p0) = (vec![0u64; n], vec![0u32; n], [0u32; 3]);
    ctx.read(&keys_buf, &mut k0).unwrap();
    ctx.read(&values_buf, &mut v0).unwrap();
    ctx.read(&pad, &mut p0).unwrap();
    assert!(k0 == keys && v0 == values, "staged round trip changed the data");
    assert_eq!(p0, [1, 2, 3]);
    let key_bits = 32 + 10;
    let (got_k, _) = sort_on_device_like_a_stable_sort(&mut ctx, (&keys_buf, &values_buf, &scratch), &keys, &values, key_bits, "staged");
    // A short read of a long buffer reads only what was asked.
    let mut head = vec![0u64; 5];
    ctx.read(&keys_buf, &mut head).unwrap();
    assert_eq!(head, got_k[..5]);

    // Small writes wait in the staging buffer's tail (512 bytes here) until the next
    // submission or transfer: 150 writes of 3 words overflow both its bytes and its 64
    // entries, later writes to a buffer replace earlier ones, and the result is as if each
    // had been written at once.
    let buffers: Vec<GpuBuffer<u32>> = (0..40).map(|_| ctx.alloc::<u32>("small writes", 3).unwrap()).collect();
    let mut model = vec![[0u32; 3]; buffers.len()];
    for k in 0..150u32 {
        let at = (k as usize * 7) % buffers.len();
        model[at] = [k, k + 1000, k + 2000];
        ctx.write(&buffers[at], &model[at]).unwrap();
    }
    for (b, want) in buffers.iter().zip(&model) {
        let mut got = [0u32; 3];
        ctx.read(b, &mut got).unwrap();
        assert_eq!(&got, want, "deferred small writes lost or reordered");
    }
    // A small write is on the device before the next submission's first command.
    let copy_to = ctx.alloc::<u32>("copy of a small write", 3).unwrap();
    ctx.write(&buffers[3], &[7, 8, 9]).unwrap();
    ctx.begin().unwrap();
    ctx.copy(buffers[3].range(), copy_to.range()).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut got = [0u32; 3];
    ctx.read(&copy_to, &mut got).unwrap();
    assert_eq!(got, [7, 8, 9], "a kernel after a small write must see it");

    // A prefetched range is read from the submission's own copy (no submission of its own)
    // until the next write or submission; a read outside it, or after those, is an ordinary
    // staged read of what the arena holds then.
    let prefetched = |ctx: &GpuContext| ctx.host_stats().prefetched_reads;
    ctx.begin().unwrap();
    ctx.copy(buffers[5].range(), copy_to.range()).unwrap();
    ctx.prefetch(copy_to.range()).unwrap();
    ctx.submit_and_wait().unwrap();
    let (before, submits) = (prefetched(&ctx), ctx.host_stats().submits);
    ctx.read(&copy_to, &mut got).unwrap();
    assert_eq!(got, model[5]);
    let mut first = [0u32; 1];
    ctx.read(&copy_to, &mut first).unwrap();
    assert_eq!(first[0], model[5][0]);
    assert_eq!((prefetched(&ctx) - before, ctx.host_stats().submits - submits), (2, 0), "both reads from the prefetched copy");
    ctx.read(&buffers[6], &mut got).unwrap();
    assert_eq!((got, prefetched(&ctx) - before), (model[6], 2), "not prefetched: an ordinary read");
    ctx.write(&copy_to, &[4, 5, 6]).unwrap();
    ctx.read(&copy_to, &mut got).unwrap();
    assert_eq!((got, prefetched(&ctx) - before), ([4, 5, 6], 2), "a write drops the prefetched copies");
}

/// A command waits (a barrier) only for what it depends on: two fills of separate buffers run
/// together, a copy from one of them waits, a copy from the other (ordered by that barrier)
/// does not, a copy of a copy's output waits again; the data are as if each ran in turn.
#[test]
fn barriers_only_where_a_command_depends_on_an_earlier_one() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("barriers_only_where_a_command_depends_on_an_earlier_one") else { return };
    let bufs: Vec<GpuBuffer<u32>> = (0..5).map(|_| ctx.alloc::<u32>("barrier test", 1000).unwrap()).collect();
    let barriers = |ctx: &GpuContext| ctx.host_stats().barriers;
    let before = barriers(&ctx);
    ctx.begin().unwrap();
    ctx.fill(bufs[0].range(), 11).unwrap();
    ctx.fill(bufs[1].range(), 22).unwrap();
    assert_eq!(barriers(&ctx) - before, 0, "two fills of separate buffers");
    ctx.copy(bufs[0].range(), bufs[2].range()).unwrap();
    assert_eq!(barriers(&ctx) - before, 1, "a copy of a filled buffer waits for the fill");
    ctx.copy(bufs[1].range(), bufs[3].range()).unwrap();
    assert_eq!(barriers(&ctx) - before, 1, "the other fill is already ordered");
    ctx.copy(bufs[2].range(), bufs[4].range()).unwrap();
    assert_eq!(barriers(&ctx) - before, 2, "a copy of a copy waits for it");
    ctx.fill(bufs[0].range(), 33).unwrap();
    assert_eq!(barriers(&ctx) - before, 2, "overwriting what an ordered copy read");
    ctx.fill(bufs[4].range(), 44).unwrap();
    assert_eq!(barriers(&ctx) - before, 3, "write after write");
    ctx.submit_and_wait().unwrap();
    let mut got = vec![0u32; 1000];
    for (b, want) in bufs.iter().zip([33, 22, 11, 22, 44]) {
        ctx.read(b, &mut got).unwrap();
        assert!(got.iter().all(|&v| v == want), "{want}: got {:?}", &got[..4]);
    }
}

/// A submission left running ([`GpuContext::submit`]) while the next is recorded: the next
/// sees what it wrote, a range it copied for the host is read after it ran, a small write made
/// meanwhile lands before the next submission's commands, and both are timed.
#[test]
fn a_submission_left_running_is_ordered_before_the_next() {
    let Some(mapped) = gpu_common::gpu_or_skip("a_submission_left_running_is_ordered_before_the_next") else { return };
    let staged = GpuContext::new(&GpuOptions { arena_bytes: 16 << 20, host_staging: Some(1 << 20), ..GpuOptions::with_budget_mb(16) }, &KERNELS).unwrap();
    assert_eq!(staged.info().host_transfers, "staged");
    for ctx in [mapped, staged] {
        submission_left_running(ctx);
    }
    let staged = GpuContext::new(&GpuOptions { arena_bytes: 16 << 20, host_staging: Some(1 << 20), ..GpuOptions::with_budget_mb(16) }, &KERNELS).unwrap();
    two_submissions_left_running(staged);
}

/// Two submissions left running: the first copies `a` into `x` and prefetches `x`, the second
/// (queued behind it without a wait) copies `b` into `x`, a third waits for the first. The
/// prefetched read gives the first's copy while a later one may still run; a plain read the
/// arena after all of them.
fn two_submissions_left_running(mut ctx: GpuContext) {
    let n = 4096;
    let (a, b, c, x) = (ctx.alloc::<u32>("a", n).unwrap(), ctx.alloc::<u32>("b", n).unwrap(), ctx.alloc::<u32>("c", n).unwrap(), ctx.alloc::<u32>("x", n).unwrap());
    let values = |k: u32| (0..n as u32).map(|i| i * 3 + k).collect::<Vec<u32>>();
    ctx.write(&a, &values(1)).unwrap();
    ctx.write(&b, &values(2)).unwrap();
    ctx.write(&c, &values(3)).unwrap();
    for round in 0..3 {
        ctx.begin().unwrap();
        ctx.copy(a.range(), x.range()).unwrap();
        ctx.prefetch(x.range()).unwrap();
        ctx.submit().unwrap();
        ctx.begin().unwrap();
        ctx.copy(b.range(), x.range()).unwrap();
        ctx.submit().unwrap();
        ctx.begin().unwrap();
        ctx.copy(c.range(), a.range()).unwrap();
        ctx.copy(x.range(), c.range()).unwrap();
        ctx.submit().unwrap();
        let mut got = vec![0u32; n];
        ctx.read_prefetched(&x, &mut got).unwrap();
        assert_eq!(got, values(1), "round {round}: the first submission's copy of x, not the second's");
        let mut arena = vec![0u32; n];
        ctx.read(&x, &mut arena).unwrap();
        assert_eq!(arena, values(2), "round {round}: x after every submission");
        let mut moved = vec![0u32; n];
        ctx.read(&a, &mut moved).unwrap();
        assert_eq!(moved, values(3), "round {round}: the third submission ran after the first");
        // Reset a and c for the next round (the prefetched copy of x is an older round's).
        ctx.write(&a, &values(1)).unwrap();
        ctx.write(&c, &values(3)).unwrap();
    }
}

fn submission_left_running(mut ctx: GpuContext) {
    let n = SORT_BLOCK * 2 + 5;
    let keys_buf = ctx.alloc::<u64>("keys", n).unwrap();
    let values_buf = ctx.alloc::<u32>("values", n).unwrap();
    let scratch = SortScratch::new(&mut ctx, n).unwrap();
    let copy = ctx.alloc::<u64>("copy of the sorted keys", n).unwrap();
    let small = ctx.alloc::<u32>("small write", 4).unwrap();
    let small_copy = ctx.alloc::<u32>("copy of the small write", 4).unwrap();
    let mut rng = Rng::new(12);
    let keys = splat_like_keys(&mut rng, n, 300);
    let values: Vec<u32> = (0..n as u32).collect();
    ctx.write(&keys_buf, &keys).unwrap();
    ctx.write(&values_buf, &values).unwrap();
    ctx.write(&small, &[1, 2, 3, 4]).unwrap();
    let (submits, profiled) = (ctx.host_stats().submits, ctx.profile().dispatches.iter().sum::<u64>());
    ctx.begin().unwrap();
    record_radix_sort(&mut ctx, &keys_buf, &values_buf, n, 32 + 9, &scratch).unwrap();
    ctx.prefetch(values_buf.range()).unwrap();
    ctx.submit().unwrap();
    // Meanwhile: a small write (deferred: it must not reach the arena before the sort ran, nor
    // be lost) and the next recording.
    ctx.write(&small, &[5, 6, 7, 8]).unwrap();
    ctx.begin().unwrap();
    ctx.copy(keys_buf.range(), copy.range()).unwrap();
    ctx.copy(small.range(), small_copy.range()).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut want: Vec<(u64, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    want.sort_by_key(|p| p.0);
    let mut got_keys = vec![0u64; n];
    ctx.read(&copy, &mut got_keys).unwrap();
    assert!(got_keys.iter().zip(&want).all(|(g, w)| *g == w.0), "the second submission copied the keys before the sort finished");
    let mut got_values = vec![0u32; n];
    let before = ctx.host_stats().prefetched_reads;
    ctx.read(&values_buf, &mut got_values).unwrap();
    let prefetched = if ctx.info().host_transfers == "staged" { 1 } else { 0 };
    assert_eq!(ctx.host_stats().prefetched_reads - before, prefetched, "the first submission's copy for the host");
    assert!(got_values.iter().zip(&want).all(|(g, w)| *g == w.1), "sorted values");
    let mut got_small = [0u32; 4];
    ctx.read(&small_copy, &mut got_small).unwrap();
    assert_eq!(got_small, [5, 6, 7, 8], "a small write made while a submission ran");
    assert_eq!(ctx.host_stats().submits - submits, 2);
    if ctx.info().timestamp_period_ns.is_some() {
        // Every pass of the sort (three kernels each) timed, from the first submission.
        let timed = ctx.profile().dispatches.iter().sum::<u64>() - profiled;
        assert_eq!(timed, 3 * (41u64).div_ceil(8), "dispatches timed over both submissions");
    }
}

#[test]
fn device_choice_and_pipeline_cache_on_disk() {
    let Some(ctx) = gpu_common::gpu_or_skip("device_choice_and_pipeline_cache_on_disk") else { return };
    let name = ctx.info().name.clone();
    drop(ctx);
    let dir = tempfile::tempdir().unwrap();
    let options = |device: Option<&str>| GpuOptions {
        arena_bytes: 1 << 20,
        device: device.map(str::to_owned),
        pipeline_cache_dir: Some(dir.path().to_path_buf()),
        deterministic: device.is_none(),
        host_staging: None,
    };
    // By index and by a case-insensitive substring of the name.
    let mut by_index = GpuContext::new(&options(Some("0")), &KERNELS).unwrap();
    // Float atomics unless asked for deterministic mode (or the device lacks them).
    assert_eq!(by_index.deterministic(), !by_index.info().float_atomics);
    assert!(by_index.set_deterministic(true));
    assert_eq!(by_index.set_deterministic(false), !by_index.info().float_atomics);
    let file = by_index.info().pipeline_cache_file.clone().expect("cache file");
    assert!(file.starts_with(dir.path()));
    let file_name = file.file_name().unwrap().to_string_lossy().into_owned();
    assert!(file_name.starts_with(&format!("pipelines-{:04x}-{:04x}-", by_index.info().vendor_id, by_index.info().device_id)), "{file_name}");
    assert!(std::fs::metadata(&file).unwrap().len() > 0, "pipeline cache written at start-up");
    drop(by_index);
    let substring = name.split_whitespace().next().unwrap().to_uppercase();
    let by_name = GpuContext::new(&options(Some(&substring)), &KERNELS).unwrap();
    assert_eq!(by_name.info().name, name);
    assert_eq!(by_name.info().pipeline_cache_file.as_ref(), Some(&file), "same device, same cache file (reused)");
    drop(by_name);
    match GpuContext::new(&options(Some("no-such-gpu")), &KERNELS) {
        Err(GpuError::NoMatchingDevice { wanted, seen, .. }) => {
            assert_eq!(wanted, "no-such-gpu");
            assert!(seen.contains(&name), "the error lists the devices seen: {seen}");
        }
        Err(e) => panic!("expected NoMatchingDevice, got {e}"),
        Ok(_) => panic!("a device matched 'no-such-gpu'"),
    }
    // The arena is the budget: more than it holds is refused, naming the buffer.
    let mut small = GpuContext::new(&options(None), &KERNELS).unwrap();
    assert!(small.deterministic(), "GpuOptions::deterministic was set");
    match small.alloc::<u32>("too big", (1 << 20) / 4 + 1) {
        Err(GpuError::ArenaFull { what, .. }) => assert_eq!(what, "too big"),
        other => panic!("expected ArenaFull, got {other:?}"),
    }
    // A dispatch with the wrong number of buffers names the kernel.
    let b = small.alloc::<u32>("b", 16).unwrap();
    small.begin().unwrap();
    let err = small.dispatch(duv_map::vulkan::Kernel::RadixSortScan, &[b.range(), b.range(), b.range()], &[0u8; 16], [1, 1, 1]).unwrap_err();
    assert!(err.to_string().contains("radix_sort.scan"), "{err}");
    small.submit_and_wait().unwrap();
}
