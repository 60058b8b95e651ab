//! Pruning on the GPU: stream compaction of the map and its optimiser moments, the twin of
//! [`crate::gaussians::Gaussians::retain`], [`crate::gaussians::GaussianGrads::retain`]
//! and [`crate::adam::AdamGroup::retain`] (all three [`crate::adam::retain_strided`]
//! per buffer: kept items keep their order, the values past the kept ones stay as they were).
//!
//! One keep mask moves every per-Gaussian buffer (`kernels/compact.wgsl`):
//! 1. the mask: uploaded from the host ([`GpuCompaction::upload_mask`]), written by any kernel
//!    into [`GpuCompaction::flags`], or computed on the device by the prune rule of
//!    [`crate::densify::densify_and_prune`] (`compact.keep_flags`,
//!    [`GpuCompaction::record_keep_flags`], thresholds from [`PruneThresholds`]);
//! 2. its exclusive prefix sum ([`GpuCompaction::record_scan`], `vulkan::ops`): the new index of
//!    every kept item, and the kept count;
//! 3. per buffer (a parameter group or the whole AoS parameter block, an Adam moment, a
//!    gradient or densification statistic; f32 or u32, any number of 32-bit values per item)
//!    `compact.scatter` into a scratch buffer, copied back ([`GpuCompaction::record_compact`]):
//!    in place from the caller's point of view.
//!
//! Values move as 32-bit words, bit for bit. Scratch comes from the arena once
//! ([`GpuCompaction::new`]); no call allocates. Sizes past the scratch or the buffers are
//! [`GpuError::OutOfRange`], never a panic.

use bytemuck::Pod;

use super::ops::{record_exclusive_scan, ScanScratch};
use duv_gpu::{GpuBuffer, GpuContext, GpuError};
use super::kernels::Kernel;
use crate::densify::DensifyParams;
use crate::gaussians::{ParamGroup, PARAMS_PER_GAUSSIAN};
use crate::render::sigmoid;

/// Items per workgroup of both kernels (`keep_flags`: one thread each; `scatter`: the
/// workgroup's 256 threads walk their values).
const WG: usize = 256;
/// Workgroups per grid row: the device minimum of `maxComputeWorkGroupCount[0]`.
pub const MAX_GROUPS_X: usize = 65535;

/// Workgroups for `n` items: one row, or rows of `max_x` (a 2D grid).
fn grid(n: usize, max_x: usize) -> [u32; 3] {
    let groups = n.div_ceil(WG);
    let gx = groups.min(max_x.max(1));
    [gx as u32, groups.div_ceil(gx.max(1)) as u32, 1]
}

/// The float order as unsigned order of a `u32` (`-0` just below `+0`; NaNs fall outside
/// `[order_key(-inf), order_key(inf)]`). `compact.wgsl` has the same function.
pub fn order_key(x: f32) -> u32 {
    let b = x.to_bits();
    if b & 0x8000_0000 != 0 {
        !b
    } else {
        b | 0x8000_0000
    }
}

/// Inverse of [`order_key`].
pub fn from_order_key(k: u32) -> f32 {
    f32::from_bits(if k & 0x8000_0000 != 0 { k & 0x7fff_ffff } else { !k })
}

/// The prune rule of [`crate::densify::densify_and_prune`] as two exact thresholds on its
/// f32 inputs, what `compact.keep_flags` compares (as [`order_key`]s):
///
/// `keep = sigmoid(opacity_logit) as f64 >= prune_min_opacity
///      && exp(max log_scale) as f64 <= prune_max_scale_m`
///
/// Each side is a monotone function of one f32, so the set of inputs it accepts is a
/// half-line of f32 values, found here by bisection over the same CPU expressions: the GPU
/// needs no `exp` (whose rounding differs from the host's) and agrees with the CPU bit for
/// bit. The maximum follows `fold(f32::MIN, f32::max)`: NaN scales are skipped and a Gaussian
/// whose three scales are NaN (or below `f32::MIN`) counts as `f32::MIN`; a NaN opacity is
/// pruned (a NaN compares false).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PruneThresholds {
    /// Smallest order key of an opacity logit that passes; above every finite key when none.
    pub min_opacity_key: u32,
    /// Largest order key of the largest log scale that passes; 0 (below every key the
    /// maximum can take) when none.
    pub max_log_scale_key: u32,
}

const NEG_INF_KEY: u32 = 0x007f_ffff;
const POS_INF_KEY: u32 = 0xff80_0000;
const F32_MIN_KEY: u32 = 0x0080_0000;

impl PruneThresholds {
    pub fn new(prune_min_opacity: f64, prune_max_scale_m: f64) -> Self {
        // The two expressions of densify.rs, verbatim on one value each.
        let opaque = |k: u32| sigmoid(from_order_key(k)) as f64 >= prune_min_opacity;
        let small = |k: u32| from_order_key(k).exp() as f64 <= prune_max_scale_m;
        // Smallest key in [-inf, inf] where `opaque` holds (it is non-decreasing).
        let min_opacity_key = if !opaque(POS_INF_KEY) {
            POS_INF_KEY + 1
        } else if opaque(NEG_INF_KEY) {
            NEG_INF_KEY
        } else {
            let (mut lo, mut hi) = (NEG_INF_KEY, POS_INF_KEY); // !opaque(lo), opaque(hi)
            while hi - lo > 1 {
                let mid = lo + (hi - lo) / 2;
                if opaque(mid) {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            hi
        };
        // Largest key in [f32::MIN, inf] where `small` holds (it is non-increasing).
        let max_log_scale_key = if !small(F32_MIN_KEY) {
            0
        } else if small(POS_INF_KEY) {
            POS_INF_KEY
        } else {
            let (mut lo, mut hi) = (F32_MIN_KEY, POS_INF_KEY); // small(lo), !small(hi)
            while hi - lo > 1 {
                let mid = lo + (hi - lo) / 2;
                if small(mid) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            lo
        };
        PruneThresholds { min_opacity_key, max_log_scale_key }
    }

    /// The thresholds of one densify/prune step.
    pub fn from_params(p: &DensifyParams) -> Self {
        Self::new(p.prune_min_opacity, p.prune_max_scale_m)
    }

    /// The test `compact.keep_flags` runs, on the host (equal to the CPU rule for every input).
    pub fn keeps(&self, opacity_logit: f32, log_scale: &[f32; 3]) -> bool {
        let opaque = !opacity_logit.is_nan() && order_key(opacity_logit) >= self.min_opacity_key;
        let mut largest = F32_MIN_KEY;
        for &s in log_scale {
            if !s.is_nan() && order_key(s) > largest {
                largest = order_key(s);
            }
        }
        opaque && largest <= self.max_log_scale_key
    }
}

/// Where `compact.keep_flags` reads the opacity logit and the three log scales of Gaussian
/// `i`: `opacity[i * opacity_stride + opacity_offset]` and `log_scale[i * scale_stride +
/// scale_offset + 0..3]`.
#[derive(Clone, Copy, Debug)]
pub struct PruneInputs {
    pub opacity: GpuBuffer<f32>,
    pub opacity_stride: usize,
    pub opacity_offset: usize,
    pub log_scale: GpuBuffer<f32>,
    pub scale_stride: usize,
    pub scale_offset: usize,
}

impl PruneInputs {
    /// The map as structure-of-arrays groups (the host layout): `opacity_logit` (1 per
    /// Gaussian) and `log_scale` (3 per Gaussian).
    pub fn groups(opacity_logit: &GpuBuffer<f32>, log_scale: &GpuBuffer<f32>) -> Self {
        PruneInputs {
            opacity: *opacity_logit,
            opacity_stride: ParamGroup::OpacityLogit.width(),
            opacity_offset: 0,
            log_scale: *log_scale,
            scale_stride: ParamGroup::LogScale.width(),
            scale_offset: 0,
        }
    }

    /// The map as [`PARAMS_PER_GAUSSIAN`] floats per Gaussian in
    /// [`crate::gaussians::GaussianParam::to_array`] order (`GpuProjection::params`).
    pub fn interleaved(params: &GpuBuffer<f32>) -> Self {
        PruneInputs {
            opacity: *params,
            opacity_stride: PARAMS_PER_GAUSSIAN,
            opacity_offset: ParamGroup::OpacityLogit.offset(),
            log_scale: *params,
            scale_stride: PARAMS_PER_GAUSSIAN,
            scale_offset: ParamGroup::LogScale.offset(),
        }
    }
}

/// Checks that `n` items of `width` values at `i * stride + offset` fit in `buf` (and in u32
/// indices); returns the values read.
fn check_strided(buf: &GpuBuffer<f32>, n: usize, stride: usize, offset: usize, width: usize) -> Result<usize, GpuError> {
    if n == 0 {
        return Ok(0);
    }
    let end = (n - 1).checked_mul(stride).and_then(|v| v.checked_add(offset + width));
    match end {
        Some(end) if end <= buf.len() && end <= u32::MAX as usize => Ok(end),
        _ => Err(GpuError::OutOfRange { what: buf.what(), requested: end.unwrap_or(usize::MAX), len: buf.len() }),
    }
}

/// Scratch and state of the compaction of up to `capacity` items of up to `max_item_words`
/// 32-bit values each. Use: the mask ([`Self::upload_mask`] before recording, then
/// [`Self::record_scan`]; or [`Self::record_keep_flags`]), then [`Self::record_compact`] per
/// buffer in the same or a later submission, then [`Self::kept`] after it.
pub struct GpuCompaction {
    pub capacity: usize,
    pub max_item_words: usize,
    /// The keep mask, one 0/1 word per item.
    pub flags: GpuBuffer<u32>,
    /// Exclusive prefix sum of the flags, `capacity + 1` entries; `offsets[n]` is the kept
    /// count of the last scan over `n` items (for kernels that follow).
    pub offsets: GpuBuffer<u32>,
    pub scan: ScanScratch,
    /// Where `compact.scatter` writes before the copy back, `capacity * max_item_words` words.
    pub scratch: GpuBuffer<u32>,
    /// Workgroups per row of the dispatch grid, [`MAX_GROUPS_X`]; more workgroups than this
    /// (more than 256 of them items) take further rows. Lower only to test the 2D grid.
    pub max_groups_x: usize,
    /// Items of the last recorded scan: what [`Self::record_compact`] moves.
    items: usize,
    /// Host staging of an uploaded mask (allocated once).
    staging: Vec<u32>,
}

impl GpuCompaction {
    /// Allocates the scratch from the arena (start-up only): flags and offsets for
    /// `capacity` items, the scatter target for `capacity * max_item_words` words (e.g.
    /// [`PARAMS_PER_GAUSSIAN`] to compact the interleaved parameters, 9 for the widest group).
    pub fn new(ctx: &mut GpuContext, capacity: usize, max_item_words: usize) -> Result<Self, GpuError> {
        let words = capacity.saturating_mul(max_item_words);
        if words > u32::MAX as usize {
            return Err(GpuError::OutOfRange { what: "compaction scratch (32-bit values)", requested: words, len: u32::MAX as usize });
        }
        Ok(GpuCompaction {
            capacity,
            max_item_words,
            flags: ctx.alloc("compaction keep flags", capacity)?,
            offsets: ctx.alloc("compaction offsets", capacity + 1)?,
            scan: ScanScratch::new(ctx, capacity)?,
            scratch: ctx.alloc("compaction scatter target", words)?,
            max_groups_x: MAX_GROUPS_X,
            items: 0,
            staging: vec![0; capacity],
        })
    }

    /// Items the next [`Self::record_compact`] moves (those of the last recorded scan).
    pub fn items(&self) -> usize {
        self.items
    }

    /// Writes the keep mask of `keep.len()` items into [`Self::flags`] (outside a
    /// recording); [`Self::record_scan`] over `keep.len()` items follows.
    pub fn upload_mask(&mut self, ctx: &mut GpuContext, keep: &[bool]) -> Result<(), GpuError> {
        let n = keep.len();
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: self.flags.what(), requested: n, len: self.capacity });
        }
        for (s, &k) in self.staging.iter_mut().zip(keep) {
            *s = k as u32;
        }
        ctx.write(&self.flags, &self.staging[..n])
    }

    /// Records the exclusive prefix sum of `flags[..n]` (each 0 or 1): the new index of every
    /// kept item and the kept count. The following compactions move `n` items.
    pub fn record_scan(&mut self, ctx: &mut GpuContext, n: usize) -> Result<(), GpuError> {
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: self.flags.what(), requested: n, len: self.capacity });
        }
        // The total is at most n < 2^32: the limit never trips.
        record_exclusive_scan(ctx, &self.flags, n, &self.offsets, &self.scan, u32::MAX)?;
        self.items = n;
        Ok(())
    }

    /// Records `compact.keep_flags` over `n` Gaussians (the prune rule, see
    /// [`PruneThresholds`]) and the scan of the flags.
    pub fn record_keep_flags(&mut self, ctx: &mut GpuContext, inputs: &PruneInputs, n: usize, thresholds: &PruneThresholds) -> Result<(), GpuError> {
        if n > self.capacity {
            return Err(GpuError::OutOfRange { what: self.flags.what(), requested: n, len: self.capacity });
        }
        check_strided(&inputs.opacity, n, inputs.opacity_stride, inputs.opacity_offset, 1)?;
        check_strided(&inputs.log_scale, n, inputs.scale_stride, inputs.scale_offset, 3)?;
        if n > 0 {
            let params = [
                n as u32,
                inputs.opacity_stride as u32,
                inputs.opacity_offset as u32,
                inputs.scale_stride as u32,
                inputs.scale_offset as u32,
                thresholds.min_opacity_key,
                thresholds.max_log_scale_key,
                0,
            ];
            let bufs = [inputs.opacity.range(), inputs.log_scale.range(), self.flags.slice_range(0, n)?];
            ctx.dispatch(Kernel::CompactKeepFlags, &bufs, bytemuck::bytes_of(&params), grid(n, self.max_groups_x))?;
        }
        self.record_scan(ctx, n)
    }

    /// Records the compaction of `buf`, items of `stride` elements of `T` (`T` 32-bit words:
    /// `f32`, `u32`, `[f32; 3]` ...), over the items of the last scan: kept items move down in
    /// order, the values past the kept ones stay as they were (`retain_strided`). In place
    /// from the caller's point of view (a scatter into [`Self::scratch`], copied back).
    pub fn record_compact<T: Pod>(&self, ctx: &mut GpuContext, buf: &GpuBuffer<T>, stride: usize) -> Result<(), GpuError> {
        const { assert!(std::mem::size_of::<T>().is_multiple_of(4) && std::mem::size_of::<T>() > 0, "compaction moves 32-bit words") };
        let words_per = std::mem::size_of::<T>() / 4;
        let item_words = stride.saturating_mul(words_per);
        if stride == 0 || item_words > self.max_item_words {
            return Err(GpuError::OutOfRange { what: self.scratch.what(), requested: item_words, len: self.max_item_words });
        }
        let n = self.items;
        if n * stride > buf.len() {
            return Err(GpuError::OutOfRange { what: buf.what(), requested: n * stride, len: buf.len() });
        }
        let words = n * item_words;
        if words == 0 {
            return Ok(());
        }
        let data = buf.slice_range(0, n * stride)?;
        let target = self.scratch.slice_range(0, words)?;
        let params = [n as u32, item_words as u32, 0, 0];
        let bufs = [self.offsets.slice_range(0, n + 1)?, data, target];
        ctx.dispatch(Kernel::CompactScatter, &bufs, bytemuck::bytes_of(&params), grid(n, self.max_groups_x))?;
        ctx.copy(target, data)
    }

    /// The kept count of the last scan (after its submission).
    pub fn kept(&self, ctx: &GpuContext) -> Result<usize, GpuError> {
        match self.scan.result(ctx)? {
            Ok(total) => Ok(total as usize),
            // Not reachable: the limit is u32::MAX and the total at most n.
            Err(needed) => Err(GpuError::OutOfRange { what: self.offsets.what(), requested: needed as usize, len: u32::MAX as usize }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::rng::Rng;

    /// The rule as `densify_and_prune` writes it.
    fn cpu_keeps(t: (f64, f64), opacity_logit: f32, log_scale: &[f32; 3]) -> bool {
        let op = sigmoid(opacity_logit);
        let max_scale = log_scale.iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
        op as f64 >= t.0 && max_scale as f64 <= t.1
    }

    #[test]
    fn order_key_is_the_float_order_and_round_trips() {
        let xs = [f32::NEG_INFINITY, f32::MIN, -1.5, -f32::MIN_POSITIVE, -1e-45, -0.0, 0.0, 1e-45, f32::MIN_POSITIVE, 2.0, f32::MAX, f32::INFINITY];
        for w in xs.windows(2) {
            assert!(order_key(w[0]) < order_key(w[1]), "{} {}", w[0], w[1]);
        }
        for x in xs {
            assert_eq!(from_order_key(order_key(x)).to_bits(), x.to_bits());
        }
        assert_eq!((order_key(f32::NEG_INFINITY), order_key(f32::INFINITY), order_key(f32::MIN)), (NEG_INF_KEY, POS_INF_KEY, F32_MIN_KEY));
    }

    #[test]
    fn thresholds_reproduce_the_cpu_prune_rule() {
        let mut rng = Rng::new(5);
        let specials = [f32::NAN, -f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.0, 1e-45, -1e-45, f32::MIN, f32::MAX];
        let rules = [(0.005, 3.0), (0.3, 0.5), (0.5, 1.0), (0.0, f64::INFINITY), (1.0, 0.0), (-1.0, -1.0), (f64::NAN, f64::NAN), (1.5, 1e-30)];
        for rule in rules {
            let t = PruneThresholds::new(rule.0, rule.1);
            // Around both thresholds, ulp by ulp, then random and special values.
            let mut opacities: Vec<f32> = Vec::new();
            let mut scales: Vec<f32> = Vec::new();
            for d in -300i64..=300 {
                opacities.push(from_order_key((t.min_opacity_key as i64 + d).clamp(NEG_INF_KEY as i64, POS_INF_KEY as i64) as u32));
                scales.push(from_order_key((t.max_log_scale_key as i64 + d).clamp(NEG_INF_KEY as i64, POS_INF_KEY as i64) as u32));
            }
            for _ in 0..20_000 {
                opacities.push(rng.range(-12.0, 12.0) as f32);
                scales.push(rng.range(-12.0, 4.0) as f32);
                opacities.push(f32::from_bits(rng.next_u64() as u32));
                scales.push(f32::from_bits(rng.next_u64() as u32));
            }
            opacities.extend(specials);
            scales.extend(specials);
            for (k, &o) in opacities.iter().enumerate() {
                let s = [scales[k], scales[(k * 7 + 3) % scales.len()], scales[(k * 13 + 5) % scales.len()]];
                for ls in [s, [s[0], f32::NAN, f32::NAN], [f32::NAN; 3], [1.0, 1.0, 1.0], [-100.0; 3]] {
                    assert_eq!(t.keeps(o, &ls), cpu_keeps(rule, o, &ls), "rule {rule:?}: opacity {o:e} ({:#x}), log scales {ls:?}", o.to_bits());
                }
            }
        }
    }
}
