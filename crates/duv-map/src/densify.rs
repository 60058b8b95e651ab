//! Adaptive density control (3DGS §5.2, paper §3.3) on a map of fixed capacity.
//!
//! One call, every few iterations:
//! 1. **Prune** Gaussians that became transparent (`sigmoid(opacity) < prune_min_opacity`) or
//!    too large (largest axis above `prune_max_scale_m`).
//! 2. **Densify** the survivors whose mean attenuation-compensated screen-space gradient
//!    (`densify_grad_norm / views`, the paper's `detach(exp(sigma_med t))` scaling is in
//!    [`GaussianGrads::densify_grad_norm`]) is at least `grad_threshold`: a small Gaussian is
//!    **cloned**, a large one (largest axis above `split_scale_m`) is **split** into two at
//!    `mean +- R (s * n)` (`n` a standard normal sample) with scales divided by 1.6.
//! 3. **Hard cap:** new Gaussians are appended while there is room; once the map is full, each
//!    new one **replaces** the least useful Gaussian (lowest `opacity x pixels touched`, never a
//!    parent densified in the same step, nor a slot already replaced), at most `max_replace_fraction` of the map per call. No buffer grows.
//!
//! Seeding a new keyframe into a full map ([`Removal::LeastUseful`], called by
//! `Mapper::add_keyframe` up to `init_replace_fraction` of the cap) evicts by the same measure
//! with the footprint in place of the current window's pixel count: the window only holds the
//! views optimised since the last reset, mostly the newest keyframes, and by it the surface
//! that only old keyframes see would go first (measured: the first two of 13 keyframes fell
//! from 34-35 dB to 17-20 dB).
//!
//! Every compaction moves the Adam moments with the parameters ([`AdamGroup::retain`]); an
//! appended Gaussian starts with zero moments ([`AdamGroup::grow`]), a replaced slot has its
//! moments zeroed ([`AdamGroup::reset_items`]). The gradients and statistics are reset for the
//! new length. Scratch buffers are sized once for the capacity: no call allocates.

use super::adam::{retain_strided, AdamError, AdamGroup};
use super::gaussians::{GaussianGrads, Gaussians, ParamGroup};
use super::render::{quat_to_mat3, sigmoid};
use duv_core::rng::Rng;

/// Thresholds of one densify/prune step (copied from the mapper's config).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensifyParams {
    /// Mean screen-space gradient norm (pixel units) above which a Gaussian is densified.
    pub grad_threshold: f64,
    /// Gaussians whose largest axis (m) is above this are split, smaller ones cloned.
    pub split_scale_m: f64,
    /// Gaussians less opaque than this are pruned.
    pub prune_min_opacity: f64,
    /// Gaussians whose largest axis (m) is above this are pruned.
    pub prune_max_scale_m: f64,
    /// Share of the map that may be replaced per step once it is full, in [0, 1].
    pub max_replace_fraction: f64,
}

/// What one step did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct DensifyReport {
    pub pruned: usize,
    pub cloned: usize,
    pub split: usize,
    /// New Gaussians written over the least useful ones because the map was full.
    pub replaced: usize,
    /// Candidates dropped because the map was full and the replacement budget spent.
    pub dropped: usize,
    /// Map size after the step.
    pub len: usize,
}

/// Per-Gaussian scratch of [`densify_and_prune`], allocated once for the capacity.
#[derive(Clone, Debug)]
pub struct DensifyScratch {
    keep: Vec<bool>,
    candidate: Vec<bool>,
    usefulness: Vec<f32>,
    avg_grad: Vec<f32>,
    order: Vec<u32>,
    victims: Vec<u32>,
}

impl DensifyScratch {
    pub fn with_capacity(capacity: usize) -> Self {
        DensifyScratch {
            keep: vec![false; capacity],
            candidate: vec![false; capacity],
            usefulness: vec![0.0; capacity],
            avg_grad: vec![0.0; capacity],
            order: Vec::with_capacity(capacity),
            victims: Vec::with_capacity(capacity),
        }
    }
}

/// Which Gaussians [`remove_gaussians`] takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Removal {
    /// The tile-overflow policy (a render needed more tile intersections than its buffers
    /// hold): the largest axis first, the Gaussians that cover the most tiles.
    Largest,
    /// The seeding policy of a full map (a new keyframe shows surface no Gaussian covers yet):
    /// lowest `opacity x (footprint + 1)` first, with the footprint
    /// ([`GaussianGrads::fold_footprint`]) the most pixels per view a Gaussian covered in any
    /// keyframe so far, so the surface that only old keyframes see is kept.
    LeastUseful,
}

/// Removes `count` Gaussians chosen by `by`, with their Adam moments and footprints, and
/// resets the gradients for the new length; returns how many went. Allocates nothing (the
/// order lives in the scratch).
pub fn remove_gaussians(
    gaussians: &mut Gaussians,
    grads: &mut GaussianGrads,
    adam: &mut [AdamGroup],
    count: usize,
    by: Removal,
    s: &mut DensifyScratch,
) -> Result<usize, AdamError> {
    grads.fold_footprint();
    // The key, highest removed first, in the scratch's gradient slot.
    let keys = &mut s.avg_grad[..gaussians.len()];
    match by {
        Removal::Largest => {
            let log_scale = gaussians.group(ParamGroup::LogScale);
            for (i, key) in keys.iter_mut().enumerate() {
                *key = log_scale[i * 3..i * 3 + 3].iter().fold(f32::MIN, |a, &b| a.max(b));
            }
        }
        Removal::LeastUseful => {
            let (opacity, footprint) = (gaussians.group(ParamGroup::OpacityLogit), grads.footprint());
            for (i, key) in keys.iter_mut().enumerate() {
                *key = -(sigmoid(opacity[i]) * (footprint[i] + 1.0));
            }
        }
    }
    let n = gaussians.len();
    let count = count.min(n);
    if count == 0 {
        return Ok(0);
    }
    s.order.clear();
    for i in 0..n {
        s.order.push(i as u32);
        s.keep[i] = true;
    }
    let key = &s.avg_grad;
    // Ties by index, so the choice is deterministic.
    s.order.select_nth_unstable_by(count - 1, |&a, &b| key[b as usize].total_cmp(&key[a as usize]).then(a.cmp(&b)));
    for &i in &s.order[..count] {
        s.keep[i as usize] = false;
    }
    drop_unkept(gaussians, grads, adam, &s.keep[..n])
}

/// Removes the Gaussians whose mean `remove` picks, with their Adam moments and footprints,
/// and resets the gradients for the new length; returns how many went. Allocates nothing.
pub fn remove_where(
    gaussians: &mut Gaussians,
    grads: &mut GaussianGrads,
    adam: &mut [AdamGroup],
    s: &mut DensifyScratch,
    mut remove: impl FnMut([f32; 3]) -> bool,
) -> Result<usize, AdamError> {
    grads.fold_footprint();
    let n = gaussians.len();
    let mean = gaussians.group(ParamGroup::Mean);
    let mut any = false;
    for (i, keep) in s.keep[..n].iter_mut().enumerate() {
        *keep = !remove([mean[i * 3], mean[i * 3 + 1], mean[i * 3 + 2]]);
        any |= !*keep;
    }
    if !any {
        return Ok(0);
    }
    drop_unkept(gaussians, grads, adam, &s.keep[..n])
}

/// Compacts the map, its Adam moments and footprints to the Gaussians `keep` marks.
fn drop_unkept(gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup], keep: &[bool]) -> Result<usize, AdamError> {
    let n = gaussians.len();
    let mut kept = n;
    for (k, g) in ParamGroup::ALL.iter().enumerate() {
        kept = adam[k].retain(gaussians.group_mut(*g), keep)?;
    }
    gaussians.truncate(kept);
    grads.retain_footprint(keep);
    grads.reset(kept).map_err(|_| AdamError::CapacityExceeded { requested: kept, capacity: grads.capacity() })?;
    Ok(n - kept)
}

/// Prunes, then clones/splits, within the map's capacity; `adam` holds one group per
/// [`ParamGroup::ALL`] entry, in that order, aligned with the map. See the module doc.
pub fn densify_and_prune(
    gaussians: &mut Gaussians,
    grads: &mut GaussianGrads,
    adam: &mut [AdamGroup],
    params: &DensifyParams,
    rng: &mut Rng,
    s: &mut DensifyScratch,
) -> Result<DensifyReport, AdamError> {
    let n = gaussians.len();
    let capacity = gaussians.capacity();
    debug_assert_eq!(grads.len(), n);
    debug_assert_eq!(adam.len(), ParamGroup::ALL.len());
    let mut report = DensifyReport::default();
    grads.fold_footprint();
    {
        let (dgn, touched, views) = (grads.densify_grad_norm(), grads.pixels_touched(), grads.views());
        let opacity = gaussians.group(ParamGroup::OpacityLogit);
        let log_scale = gaussians.group(ParamGroup::LogScale);
        for i in 0..n {
            let avg = if views[i] > 0 { dgn[i] / views[i] as f32 } else { 0.0 };
            let op = sigmoid(opacity[i]);
            let max_scale = log_scale[i * 3..i * 3 + 3].iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
            let keep = op as f64 >= params.prune_min_opacity && max_scale as f64 <= params.prune_max_scale_m;
            s.keep[i] = keep;
            s.candidate[i] = keep && avg as f64 >= params.grad_threshold;
            s.usefulness[i] = op * touched[i] as f32;
            s.avg_grad[i] = avg;
        }
    }
    // 1. Prune: parameters and moments move together; the scratch follows the same mask.
    let mut kept = n;
    for (k, g) in ParamGroup::ALL.iter().enumerate() {
        kept = adam[k].retain(gaussians.group_mut(*g), &s.keep[..n])?;
    }
    gaussians.truncate(kept);
    grads.retain_footprint(&s.keep[..n]);
    retain_strided(&mut s.candidate[..n], 1, &s.keep[..n]);
    retain_strided(&mut s.usefulness[..n], 1, &s.keep[..n]);
    retain_strided(&mut s.avg_grad[..n], 1, &s.keep[..n]);
    report.pruned = n - kept;
    let n = kept;

    // 2. Densify, strongest gradients first; 3. replace the least useful once full.
    s.order.clear();
    s.victims.clear();
    for i in 0..n {
        if s.candidate[i] {
            s.order.push(i as u32);
        }
        s.victims.push(i as u32);
        // From here on `keep` marks Gaussians already used this step (a densified parent or a
        // replaced slot): neither is replaced, nor densified, again.
        s.keep[i] = false;
    }
    let avg = &s.avg_grad;
    s.order.sort_unstable_by(|&a, &b| avg[b as usize].total_cmp(&avg[a as usize]).then(a.cmp(&b)));
    let useful = &s.usefulness;
    s.victims.sort_unstable_by(|&a, &b| useful[a as usize].total_cmp(&useful[b as usize]).then(a.cmp(&b)));
    let replace_budget = (params.max_replace_fraction.clamp(0.0, 1.0) * n as f64) as usize;
    let mut next_victim = 0;
    let split_log = (params.split_scale_m.max(1e-30) as f32).ln();
    let shrink = 1.6f32.ln();
    for oi in 0..s.order.len() {
        let i = s.order[oi] as usize;
        if s.keep[i] {
            continue;
        }
        s.keep[i] = true;
        let mut parent = gaussians.get(i);
        let mut child = parent;
        let max_log = parent.log_scale.iter().fold(f32::MIN, |a, &b| a.max(b));
        let split = max_log > split_log;
        if split {
            let q = parent.rotation;
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            let r = quat_to_mat3(&q.map(|v| v / norm));
            let local = [0, 1, 2].map(|k| parent.log_scale[k].exp() * rng.normal() as f32);
            for row in 0..3 {
                let off = r[row][0] * local[0] + r[row][1] * local[1] + r[row][2] * local[2];
                child.mean[row] = parent.mean[row] + off;
                parent.mean[row] -= off;
            }
            for k in 0..3 {
                parent.log_scale[k] -= shrink;
                child.log_scale[k] -= shrink;
            }
        }
        let parent_footprint = grads.footprint_at(i);
        if gaussians.len() < capacity {
            grads.set_footprint(gaussians.len(), parent_footprint);
            gaussians.push(&child).map_err(|_| AdamError::CapacityExceeded { requested: capacity + 1, capacity })?;
            for group in adam.iter_mut() {
                group.grow(1)?;
            }
        } else if report.replaced < replace_budget && {
            while next_victim < s.victims.len() && s.keep[s.victims[next_victim] as usize] {
                next_victim += 1;
            }
            next_victim < s.victims.len()
        } {
            let v = s.victims[next_victim] as usize;
            s.keep[v] = true;
            next_victim += 1;
            gaussians.set(v, &child);
            grads.set_footprint(v, parent_footprint);
            for group in adam.iter_mut() {
                group.reset_items(v, 1)?;
            }
            report.replaced += 1;
        } else {
            report.dropped += s.order.len() - oi;
            break;
        }
        if split {
            gaussians.set(i, &parent);
            report.split += 1;
        } else {
            report.cloned += 1;
        }
    }
    grads.reset(gaussians.len()).map_err(|_| AdamError::CapacityExceeded { requested: gaussians.len(), capacity: grads.capacity() })?;
    report.len = gaussians.len();
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::adam::AdamGroupConfig;
    use crate::gaussians::GaussianParam;

    /// Six Gaussians, opacity logits and footprints chosen so the order of usefulness is known;
    /// Gaussian 1 was large in an earlier window but is not seen in the current one.
    #[test]
    fn eviction_removes_the_least_useful_and_keeps_what_old_views_saw() {
        let n = 6;
        let mut g = Gaussians::with_capacity(8);
        let mut grads = GaussianGrads::with_capacity(8);
        // (opacity logit, footprint of earlier windows, pixels touched / views now)
        let spec = [(0.0f32, 0.0f32, (4u32, 1u32)), (0.0, 300.0, (0, 0)), (-3.0, 0.0, (0, 0)), (2.0, 0.0, (50, 2)), (-1.0, 0.0, (0, 0)), (0.0, 0.0, (2, 1))];
        for (i, &(logit, _, _)) in spec.iter().enumerate() {
            let p = GaussianParam { mean: [i as f32, 0.0, 5.0], log_scale: [-3.0; 3], rotation: [1.0, 0.0, 0.0, 0.0], opacity_logit: logit, f_dc: [0.1; 3], f_rest: [0.0; 9] };
            g.push(&p).unwrap();
        }
        grads.reset(n).unwrap();
        for (i, &(_, fp, _)) in spec.iter().enumerate() {
            grads.set_footprint(i, fp);
        }
        let touched: Vec<u32> = spec.iter().map(|s| s.2 .0).collect();
        let views: Vec<u32> = spec.iter().map(|s| s.2 .1).collect();
        grads.set_densify_stats(&vec![0.0; n], &touched, &views).unwrap();
        let mut adam: Vec<AdamGroup> = ParamGroup::ALL.iter().map(|&pg| AdamGroup::new(AdamGroupConfig::default(), pg.width(), n, 8).unwrap()).collect();
        // Mark each Gaussian's first moment with its index, to check they move together.
        for (k, &pg) in ParamGroup::ALL.iter().enumerate() {
            let m: Vec<f32> = (0..n).flat_map(|i| std::iter::repeat(i as f32).take(pg.width())).collect();
            let v = vec![0.0; n * pg.width()];
            adam[k].set_state(1, &m, &v).unwrap();
        }
        let mut s = DensifyScratch::with_capacity(8);
        // Usefulness sigmoid(logit) * (footprint + 1): 0: 0.5*5 = 2.5, 1: 0.5*301, 2: 0.047*1,
        // 3: 0.88*26, 4: 0.27*1, 5: 0.5*3 = 1.5. The three least useful: 2, 4, 5.
        let removed = remove_gaussians(&mut g, &mut grads, &mut adam, 3, Removal::LeastUseful, &mut s).unwrap();
        assert_eq!(removed, 3);
        assert_eq!(g.len(), 3);
        let xs: Vec<f32> = (0..3).map(|i| g.get(i).mean[0]).collect();
        assert_eq!(xs, vec![0.0, 1.0, 3.0], "Gaussians 0, 1 and 3 stay, in order");
        assert_eq!(grads.len(), 3);
        assert_eq!(grads.footprint(), &[4.0, 300.0, 25.0], "footprints folded from the window and moved with the map");
        for (k, &pg) in ParamGroup::ALL.iter().enumerate() {
            let (m, _) = adam[k].moments();
            let firsts: Vec<f32> = (0..3).map(|i| m[i * pg.width()]).collect();
            assert_eq!(firsts, vec![0.0, 1.0, 3.0], "moments of {} move with their Gaussians", pg.name());
        }
        assert_eq!(grads.pixels_touched(), &[0, 0, 0], "the window's statistics are reset");
        // Asking for more than the map holds removes everything, nothing more.
        assert_eq!(remove_gaussians(&mut g, &mut grads, &mut adam, 10, Removal::LeastUseful, &mut s).unwrap(), 3);
        assert!(g.is_empty());
    }
}
