//! Pruning on the Vulkan device (lavapipe in CI): `compact.keep_flags` (the prune rule of
//! `densify_and_prune`), the scan of the flags and `compact.scatter` of every per-Gaussian
//! buffer (the six parameter groups, the interleaved parameters, both Adam moments of every
//! group, the parameter gradients and the densification statistics), against the CPU
//! compactions (`Gaussians::retain`, `GaussianGrads::retain`, `AdamGroup::retain`,
//! `retain_strided`). Compaction moves values, so the comparison is bit for bit, NaN payloads
//! and the untouched tail past the kept items included. Sizes cross workgroup (256 items)
//! and scan block (512) boundaries; narrow grid rows stand in for maps of more than 65535
//! workgroups.

use crate::gpu_common;

use duv_core::rng::Rng;
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use duv_map::adam::{retain_strided, AdamGroup, AdamGroupConfig};
use duv_map::densify::{densify_and_prune, DensifyParams, DensifyScratch};
use duv_map::gaussians::{GaussianGrads, GaussianParam, Gaussians, ParamGroup, PARAMS_PER_GAUSSIAN};
use duv_map::render::sigmoid;
use duv_map::vulkan::compact::{from_order_key, GpuCompaction, PruneInputs, PruneThresholds, MAX_GROUPS_X};

/// Gaussians of the main cases: 13 full workgroups and 7 more (6.5 scan blocks).
const N: usize = 256 * 13 + 7;

/// A value for a buffer: mostly ordinary, one in 16 an arbitrary bit pattern (NaNs with
/// payloads, infinities, subnormals, -0), which a compaction must move unchanged.
fn value(rng: &mut Rng, lo: f64, hi: f64) -> f32 {
    if rng.below(16) == 0 {
        f32::from_bits(rng.next_u64() as u32)
    } else {
        rng.range(lo, hi) as f32
    }
}

fn random_map(rng: &mut Rng, n: usize) -> Gaussians {
    let mut g = Gaussians::with_capacity(n);
    for _ in 0..n {
        let a: [f32; PARAMS_PER_GAUSSIAN] = std::array::from_fn(|_| value(rng, -3.0, 3.0));
        g.push(&GaussianParam::from_array(&a)).unwrap();
    }
    g
}

fn random_grads(rng: &mut Rng, n: usize) -> GaussianGrads {
    let mut grads = GaussianGrads::with_capacity(n);
    grads.reset(n).unwrap();
    for g in ParamGroup::ALL {
        for v in grads.group_mut(g) {
            *v = value(rng, -1.0, 1.0);
        }
    }
    let dgn: Vec<f32> = (0..n).map(|_| value(rng, 0.0, 5.0)).collect();
    let touched: Vec<u32> = (0..n).map(|_| rng.next_u64() as u32).collect();
    let views: Vec<u32> = (0..n).map(|_| rng.below(40) as u32).collect();
    grads.set_densify_stats(&dgn, &touched, &views).unwrap();
    grads
}

/// One Adam group per parameter group with random moments (set as a saved state).
fn random_adam(rng: &mut Rng, n: usize) -> Vec<AdamGroup> {
    ParamGroup::ALL
        .iter()
        .map(|g| {
            let mut a = AdamGroup::new(AdamGroupConfig::default(), g.width(), n, n).unwrap();
            let m: Vec<f32> = (0..n * g.width()).map(|_| value(rng, -0.1, 0.1)).collect();
            let v: Vec<f32> = (0..n * g.width()).map(|_| value(rng, 0.0, 0.01)).collect();
            a.set_state(7, &m, &v).unwrap();
            a
        })
        .collect()
}

fn interleaved(g: &Gaussians) -> Vec<f32> {
    (0..g.len()).flat_map(|i| g.get(i).to_array()).collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Asserts `got == want` bit for bit, naming the first difference.
fn assert_bits(what: &str, got: &[u32], want: &[u32]) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    if let Some(i) = got.iter().zip(want).position(|(a, b)| a != b) {
        panic!("{what}[{i}] (of {}): GPU {:#010x} vs CPU {:#010x}", got.len(), got[i], want[i]);
    }
}

/// A per-Gaussian buffer on the device, f32 or u32.
#[derive(Clone, Copy)]
enum Gpu {
    F32(GpuBuffer<f32>),
    U32(GpuBuffer<u32>),
}

/// A per-Gaussian buffer: its values (as bits) before the compaction, its stride.
struct Buffer {
    what: &'static str,
    before: Vec<u32>,
    stride: usize,
    gpu: Gpu,
}

impl Buffer {
    fn f32(ctx: &mut GpuContext, what: &'static str, before: &[f32], stride: usize) -> Self {
        let gpu = ctx.alloc(what, before.len()).unwrap();
        ctx.write(&gpu, before).unwrap();
        Buffer { what, before: bits(before), stride, gpu: Gpu::F32(gpu) }
    }

    fn u32(ctx: &mut GpuContext, what: &'static str, before: &[u32], stride: usize) -> Self {
        let gpu = ctx.alloc(what, before.len()).unwrap();
        ctx.write(&gpu, before).unwrap();
        Buffer { what, before: before.to_vec(), stride, gpu: Gpu::U32(gpu) }
    }

    fn floats(&self) -> GpuBuffer<f32> {
        match self.gpu {
            Gpu::F32(b) => b,
            Gpu::U32(_) => panic!("{} holds u32", self.what),
        }
    }

    fn record_compact(&self, ctx: &mut GpuContext, c: &GpuCompaction) -> Result<(), GpuError> {
        match &self.gpu {
            Gpu::F32(b) => c.record_compact(ctx, b, self.stride),
            Gpu::U32(b) => c.record_compact(ctx, b, self.stride),
        }
    }

    fn read(&self, ctx: &GpuContext) -> Vec<u32> {
        let n = self.before.len();
        match &self.gpu {
            Gpu::F32(b) => {
                let mut got = vec![0.0f32; n];
                ctx.read(b, &mut got).unwrap();
                bits(&got)
            }
            Gpu::U32(b) => {
                let mut got = vec![0u32; n];
                ctx.read(b, &mut got).unwrap();
                got
            }
        }
    }

    /// After the compaction: the whole buffer equals `retain_strided` on the host (the stale
    /// tail included), and its kept part equals `live` (what the CPU type's own retain left).
    fn check(&self, ctx: &GpuContext, keep: &[bool], kept: usize, live: &[u32]) {
        let got = self.read(ctx);
        let mut want = self.before.clone();
        assert_eq!(retain_strided(&mut want, self.stride, keep), kept, "{}: kept count", self.what);
        assert_bits(self.what, &got, &want);
        assert_bits(self.what, &got[..kept * self.stride], live);
    }
}

/// Every per-Gaussian buffer of a map with its gradients and Adam moments, on the device:
/// per group (values, Adam m, Adam v, gradient), then the interleaved parameters and the
/// three densification statistics.
struct DeviceMap {
    buffers: Vec<Buffer>,
}

const GROUP_BUFFERS: [[&str; 4]; 6] = [
    ["mean", "adam m mean", "adam v mean", "grad mean"],
    ["log_scale", "adam m log_scale", "adam v log_scale", "grad log_scale"],
    ["rotation", "adam m rotation", "adam v rotation", "grad rotation"],
    ["opacity_logit", "adam m opacity_logit", "adam v opacity_logit", "grad opacity_logit"],
    ["f_dc", "adam m f_dc", "adam v f_dc", "grad f_dc"],
    ["f_rest", "adam m f_rest", "adam v f_rest", "grad f_rest"],
];
const INTERLEAVED: usize = 24;

impl DeviceMap {
    fn upload(ctx: &mut GpuContext, g: &Gaussians, grads: &GaussianGrads, adam: &[AdamGroup]) -> Self {
        let mut buffers = Vec::new();
        for (k, grp) in ParamGroup::ALL.iter().enumerate() {
            let w = grp.width();
            let (m, v) = adam[k].moments();
            buffers.push(Buffer::f32(ctx, GROUP_BUFFERS[k][0], g.group(*grp), w));
            buffers.push(Buffer::f32(ctx, GROUP_BUFFERS[k][1], m, w));
            buffers.push(Buffer::f32(ctx, GROUP_BUFFERS[k][2], v, w));
            buffers.push(Buffer::f32(ctx, GROUP_BUFFERS[k][3], grads.group(*grp), w));
        }
        buffers.push(Buffer::f32(ctx, "interleaved parameters", &interleaved(g), PARAMS_PER_GAUSSIAN));
        buffers.push(Buffer::f32(ctx, "densify_grad_norm", grads.densify_grad_norm(), 1));
        buffers.push(Buffer::u32(ctx, "pixels_touched", grads.pixels_touched(), 1));
        buffers.push(Buffer::u32(ctx, "views", grads.views(), 1));
        DeviceMap { buffers }
    }

    fn group(&self, g: ParamGroup) -> GpuBuffer<f32> {
        self.buffers[4 * g as usize].floats()
    }

    fn record_compact_all(&self, ctx: &mut GpuContext, c: &GpuCompaction) {
        for b in &self.buffers {
            b.record_compact(ctx, c).unwrap();
        }
    }

    /// Checks every buffer against the CPU compactions: `g`, `grads`, `adam` after their
    /// retain with `keep`.
    fn check(&self, ctx: &GpuContext, keep: &[bool], kept: usize, g: &Gaussians, grads: &GaussianGrads, adam: &[AdamGroup]) {
        for (k, grp) in ParamGroup::ALL.iter().enumerate() {
            let (m, v) = adam[k].moments();
            self.buffers[4 * k].check(ctx, keep, kept, &bits(g.group(*grp)));
            self.buffers[4 * k + 1].check(ctx, keep, kept, &bits(m));
            self.buffers[4 * k + 2].check(ctx, keep, kept, &bits(v));
            self.buffers[4 * k + 3].check(ctx, keep, kept, &bits(grads.group(*grp)));
        }
        self.buffers[INTERLEAVED].check(ctx, keep, kept, &bits(&interleaved(g)));
        self.buffers[INTERLEAVED + 1].check(ctx, keep, kept, &bits(grads.densify_grad_norm()));
        self.buffers[INTERLEAVED + 2].check(ctx, keep, kept, grads.pixels_touched());
        self.buffers[INTERLEAVED + 3].check(ctx, keep, kept, grads.views());
    }
}

/// The CPU compaction of a map, its gradients and its Adam groups with one mask, as the
/// mapper prunes (`densify_and_prune`: `AdamGroup::retain` moves each group with its moments).
fn cpu_retain(g: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup], keep: &[bool]) -> usize {
    let n = g.len();
    let mut kept = n;
    for (k, grp) in ParamGroup::ALL.iter().enumerate() {
        // The moments; the group's values (a copy here) move through `Gaussians::retain`.
        kept = adam[k].retain(&mut g.group(*grp).to_vec(), keep).unwrap();
    }
    assert_eq!(g.len() - g.retain(|i| keep[i]), kept);
    assert_eq!(grads.len() - grads.retain(|i| keep[i]), kept);
    kept
}

/// Whether Gaussian `i` of `n` is kept.
type MaskRule = fn(&mut Rng, usize, usize) -> bool;

#[test]
fn compaction_matches_retain_on_every_buffer() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("compaction_matches_retain_on_every_buffer") else { return };
    let arena_mark = ctx.arena_used_bytes();
    let mut c = GpuCompaction::new(&mut ctx, N, PARAMS_PER_GAUSSIAN).unwrap();
    let mut rng = Rng::new(41);
    // (case, Gaussians, workgroups per grid row, mask). Rows narrower than the device's 65535
    // exercise the 2D grid (more than 65535 * 256 Gaussians) at a test's size.
    let masks: [(&str, usize, usize, MaskRule); 9] = [
        ("random half", N, MAX_GROUPS_X, |r, _, _| r.below(2) == 0),
        ("random 3%", N, MAX_GROUPS_X, |r, _, _| r.below(100) < 3),
        ("nothing", N, MAX_GROUPS_X, |_, _, _| false),
        ("everything", N, MAX_GROUPS_X, |_, _, _| true),
        ("only the last", N, MAX_GROUPS_X, |_, i, n| i + 1 == n),
        ("all but the first", N, MAX_GROUPS_X, |_, i, _| i > 0),
        ("one workgroup and one more, random", 257, MAX_GROUPS_X, |r, _, _| r.below(3) != 0),
        ("random half, 2D grid of 4-wide rows (4 x 4, 2 idle)", N, 4, |r, _, _| r.below(2) == 0),
        ("random half, 2D grid of 1-wide rows", N, 1, |r, _, _| r.below(2) == 0),
    ];
    for (case, n, row, rule) in masks {
        let g0 = random_map(&mut rng, n);
        let grads0 = random_grads(&mut rng, n);
        let adam0 = random_adam(&mut rng, n);
        let keep: Vec<bool> = (0..n).map(|i| rule(&mut rng, i, n)).collect();
        let mark = ctx.arena_used_bytes();
        let dev = DeviceMap::upload(&mut ctx, &g0, &grads0, &adam0);
        c.upload_mask(&mut ctx, &keep).unwrap();
        c.max_groups_x = row;
        ctx.begin().unwrap();
        c.record_scan(&mut ctx, n).unwrap();
        dev.record_compact_all(&mut ctx, &c);
        ctx.submit_and_wait().unwrap();
        let (mut g, mut grads, mut adam) = (g0.clone(), grads0.clone(), adam0.clone());
        let kept = cpu_retain(&mut g, &mut grads, &mut adam, &keep);
        assert_eq!(c.kept(&ctx).unwrap(), kept, "{case}: kept count");
        dev.check(&ctx, &keep, kept, &g, &grads, &adam);
        eprintln!("{case}: {n} Gaussians, {kept} kept: 28 buffers bit-identical to the CPU compaction");
        ctx.arena_reset_to(mark);
    }
    // No Gaussians at all: nothing recorded moves, the count is 0.
    c.max_groups_x = MAX_GROUPS_X;
    ctx.begin().unwrap();
    c.record_scan(&mut ctx, 0).unwrap();
    let empty = ctx.alloc::<f32>("empty", 1).unwrap();
    c.record_compact(&mut ctx, &empty, 3).unwrap();
    ctx.submit_and_wait().unwrap();
    assert_eq!(c.kept(&ctx).unwrap(), 0);
    ctx.arena_reset_to(arena_mark);
}

/// The CPU prune rule of `densify_and_prune`, written out (for the message of a mismatch;
/// the oracle of the test is `densify_and_prune` itself).
fn cpu_rule(p: &DensifyParams, opacity_logit: f32, log_scale: &[f32]) -> bool {
    let op = sigmoid(opacity_logit);
    let max_scale = log_scale.iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
    op as f64 >= p.prune_min_opacity && max_scale as f64 <= p.prune_max_scale_m
}

#[test]
fn keep_flags_and_pruning_match_densify_and_prune() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("keep_flags_and_pruning_match_densify_and_prune") else { return };
    let arena_mark = ctx.arena_used_bytes();
    let n = N;
    let mut c = GpuCompaction::new(&mut ctx, n, PARAMS_PER_GAUSSIAN).unwrap();
    let mut rng = Rng::new(43);
    // A grad threshold no Gaussian reaches: `densify_and_prune` only prunes.
    let params = DensifyParams {
        grad_threshold: f64::INFINITY,
        split_scale_m: 0.1,
        prune_min_opacity: 0.3,
        prune_max_scale_m: 0.5,
        max_replace_fraction: 0.0,
    };
    let t = PruneThresholds::from_params(&params);
    // Opacity logits and log scales around the thresholds (logit(0.3) = -0.85, ln 0.5 =
    // -0.69), a tenth exactly at a threshold or a few ulps off it, plus arbitrary bit patterns
    // (NaN, infinities, subnormals).
    let near = |rng: &mut Rng, key: u32, lo: f64, hi: f64| -> f32 {
        match rng.below(10) {
            0 => from_order_key((key as i64 + rng.below(7) as i64 - 3) as u32),
            1 => f32::from_bits(rng.next_u64() as u32),
            _ => rng.range(lo, hi) as f32,
        }
    };
    let mut g0 = random_map(&mut rng, n);
    for i in 0..n {
        let mut p = g0.get(i);
        p.opacity_logit = near(&mut rng, t.min_opacity_key, -2.0, 3.0);
        p.log_scale = std::array::from_fn(|_| near(&mut rng, t.max_log_scale_key, -2.5, -0.3));
        if i % 97 == 0 {
            p.log_scale = [f32::NAN; 3];
        }
        g0.set(i, &p);
    }
    let mut grads0 = random_grads(&mut rng, n);
    // Zero statistics: no Gaussian is a densification candidate.
    grads0.reset_densify_stats();
    let adam0 = random_adam(&mut rng, n);
    let dev = DeviceMap::upload(&mut ctx, &g0, &grads0, &adam0);

    // The CPU: the mapper's densify/prune step.
    let (mut g, mut grads, mut adam) = (g0.clone(), grads0.clone(), adam0.clone());
    let pruned_grads = grads.clone();
    let report = densify_and_prune(&mut g, &mut grads, &mut adam, &params, &mut Rng::new(1), &mut DensifyScratch::with_capacity(n)).unwrap();
    assert_eq!((report.cloned, report.split, report.replaced), (0, 0, 0));
    let kept = report.len;
    let keep: Vec<bool> = (0..n).map(|i| cpu_rule(&params, g0.get(i).opacity_logit, &g0.get(i).log_scale)).collect();
    assert_eq!(keep.iter().filter(|&&k| k).count(), kept, "the written-out rule is densify's");
    assert!(kept > n / 5 && kept < 4 * n / 5, "{kept} of {n} kept: both sides of the rule are exercised");

    // The GPU: flags from the interleaved parameters (on a 2D grid of 3-wide rows: 14
    // workgroups as 3 x 5), compared one by one; then flags from the groups, the scan and the
    // compaction of every buffer.
    let flag_buf = c.flags;
    let flags_of = |ctx: &GpuContext| {
        let mut f = vec![0u32; n];
        ctx.read(&flag_buf, &mut f).unwrap();
        f
    };
    c.max_groups_x = 3;
    ctx.begin().unwrap();
    c.record_keep_flags(&mut ctx, &PruneInputs::interleaved(&dev.buffers[INTERLEAVED].floats()), n, &t).unwrap();
    ctx.submit_and_wait().unwrap();
    c.max_groups_x = MAX_GROUPS_X;
    let flags = flags_of(&ctx);
    for i in 0..n {
        let p = g0.get(i);
        assert_eq!(flags[i] == 1, keep[i], "Gaussian {i}: opacity logit {:e}, log scales {:?}: GPU flag {}", p.opacity_logit, p.log_scale, flags[i]);
    }
    assert_eq!(c.kept(&ctx).unwrap(), kept);
    ctx.begin().unwrap();
    c.record_keep_flags(&mut ctx, &PruneInputs::groups(&dev.group(ParamGroup::OpacityLogit), &dev.group(ParamGroup::LogScale)), n, &t).unwrap();
    dev.record_compact_all(&mut ctx, &c);
    ctx.submit_and_wait().unwrap();
    assert_bits("flags from the groups", &flags_of(&ctx), &flags);
    assert_eq!(c.kept(&ctx).unwrap(), kept);
    // `densify_and_prune` resets the gradients; compare them with a plain retain instead.
    let mut retained_grads = pruned_grads;
    retained_grads.retain(|i| keep[i]);
    dev.check(&ctx, &keep, kept, &g, &retained_grads, &adam);
    eprintln!("prune rule: {kept} of {n} kept ({} pruned), flags and 28 buffers bit-identical to densify_and_prune", report.pruned);
    ctx.arena_reset_to(arena_mark);
}

#[test]
fn bad_sizes_are_errors() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("bad_sizes_are_errors") else { return };
    let arena_mark = ctx.arena_used_bytes();
    let oor = |r: Result<(), GpuError>| matches!(r, Err(GpuError::OutOfRange { .. }));
    assert!(matches!(GpuCompaction::new(&mut ctx, usize::MAX / 2, 9), Err(GpuError::OutOfRange { .. })));
    let mut c = GpuCompaction::new(&mut ctx, 100, 9).unwrap();
    let small = ctx.alloc::<f32>("small", 100 * 3).unwrap();
    let words = ctx.alloc::<u32>("words", 100 * 10).unwrap();
    assert!(oor(c.upload_mask(&mut ctx, &[true; 101])));
    c.upload_mask(&mut ctx, &[true; 100]).unwrap();
    ctx.begin().unwrap();
    assert!(oor(c.record_scan(&mut ctx, 101)));
    c.record_scan(&mut ctx, 100).unwrap();
    // Wider than the scatter target, a zero stride, a buffer shorter than the items.
    assert!(oor(c.record_compact(&mut ctx, &words, 10)));
    assert!(oor(c.record_compact(&mut ctx, &words, 0)));
    assert!(oor(c.record_compact(&mut ctx, &small, 4)));
    // The rule's inputs shorter than the Gaussians, more Gaussians than the capacity.
    assert!(oor(c.record_keep_flags(&mut ctx, &PruneInputs::interleaved(&small), 100, &PruneThresholds::new(0.1, 1.0))));
    assert!(oor(c.record_keep_flags(&mut ctx, &PruneInputs::groups(&small, &small), 101, &PruneThresholds::new(0.1, 1.0))));
    c.record_compact(&mut ctx, &small, 3).unwrap();
    ctx.submit_and_wait().unwrap();
    assert_eq!(c.kept(&ctx).unwrap(), 100);
    ctx.arena_reset_to(arena_mark);
}
