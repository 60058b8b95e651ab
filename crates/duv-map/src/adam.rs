//! Adam (Kingma & Ba 2015) per parameter group, with moments kept aligned to the parameters
//! when the map is densified, pruned or compacted.
//!
//! A group is one parameter tensor: the medium network's flat vector (stride 1, one item), or
//! one per-Gaussian attribute in the map's structure-of-arrays buffers (positions stride 3,
//! scales 3, rotations 4, opacity 1, colour coefficients ...). Items are the units that are
//! added and removed (one Gaussian's values); the group stores `stride` values per item and
//! its two moments in buffers allocated once for a capacity, never reallocated.
//!
//! Update (PyTorch's form, as 3DGS uses it), per value, at step `t` of the group:
//! ```text
//! m <- beta1 m + (1 - beta1) g
//! v <- beta2 v + (1 - beta2) g^2
//! p <- p - lr / (1 - beta1^t) * m / (sqrt(v) / sqrt(1 - beta2^t) + eps)
//! ```
//! Items added later start with zero moments and share the group's step count (as when 3DGS
//! concatenates new Gaussians). [`AdamGroup::reset_moments`] zeroes both moments and the step
//! count: a fresh start, which the paper applies to the medium network at every
//! densify/prune step (§3.3).
//!
//! Compaction: [`AdamGroup::retain`] and [`AdamGroup::swap_remove`] move a group's
//! parameters and moments together; [`retain_strided`] and [`swap_remove_strided`] apply the
//! same moves to any other per-item buffer (gradient accumulators, other groups), so one
//! keep-mask keeps everything aligned.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Values per parallel job of a step; smaller groups are updated on the calling thread.
const CHUNK: usize = 16 * 1024;

/// Why an optimiser call was refused. Bad input is reported here, never by a panic, and a
/// refused call changes nothing.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AdamError {
    #[error("adam config: {field} = {value} {why}")]
    InvalidConfig { field: &'static str, value: f64, why: &'static str },
    #[error("adam group stride must be at least 1")]
    ZeroStride,
    #[error("{what} has {len} values, expected {expected} ({items} items x stride {stride})")]
    LengthMismatch { what: &'static str, len: usize, expected: usize, items: usize, stride: usize },
    #[error("keep mask has {len} entries, the group has {items} items")]
    MaskLengthMismatch { len: usize, items: usize },
    #[error("adam group holds at most {capacity} items, {requested} requested")]
    CapacityExceeded { requested: usize, capacity: usize },
    #[error("gradient value {index} is {value}, not a finite number")]
    NonFiniteGradient { index: usize, value: f32 },
    #[error("item {index} is out of range ({items} items)")]
    IndexOutOfRange { index: usize, items: usize },
}

/// Step size, decay rates and epsilon of one group. Defaults live in
/// [`AdamGroupConfig::default`] and nowhere else.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdamGroupConfig {
    /// Learning rate (step size), in parameter units per step, > 0.
    pub lr: f64,
    /// Decay of the first moment, in [0, 1).
    pub beta1: f64,
    /// Decay of the second moment, in [0, 1).
    pub beta2: f64,
    /// Added to the denominator, > 0 (3DGS uses 1e-15 so tiny gradients still move).
    pub eps: f64,
}

impl Default for AdamGroupConfig {
    fn default() -> Self {
        AdamGroupConfig { lr: 1e-3, beta1: 0.9, beta2: 0.999, eps: 1e-15 }
    }
}

impl AdamGroupConfig {
    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), AdamError> {
        let bad = |field: &'static str, value: f64, why: &'static str| Err(AdamError::InvalidConfig { field, value, why });
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return bad("lr", self.lr, "must be finite and > 0");
        }
        for (field, v) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return bad(field, v, "must be in [0, 1)");
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return bad("eps", self.eps, "must be finite and > 0");
        }
        Ok(())
    }
}

/// Adam state of one parameter group: moments for up to `capacity` items of `stride` values.
#[derive(Clone, Debug)]
pub struct AdamGroup {
    config: AdamGroupConfig,
    stride: usize,
    capacity: usize,
    len: usize,
    steps: u64,
    m: Vec<f32>,
    v: Vec<f32>,
}

impl AdamGroup {
    /// A group of `len` items (zero moments), room for `capacity`.
    pub fn new(config: AdamGroupConfig, stride: usize, len: usize, capacity: usize) -> Result<Self, AdamError> {
        config.validate()?;
        if stride == 0 {
            return Err(AdamError::ZeroStride);
        }
        if len > capacity {
            return Err(AdamError::CapacityExceeded { requested: len, capacity });
        }
        Ok(AdamGroup { config, stride, capacity, len, steps: 0, m: vec![0.0; capacity * stride], v: vec![0.0; capacity * stride] })
    }

    pub fn config(&self) -> &AdamGroupConfig {
        &self.config
    }
    /// Changes the learning rate (schedules); the moments are kept.
    pub fn set_lr(&mut self, lr: f64) -> Result<(), AdamError> {
        AdamGroupConfig { lr, ..self.config }.validate()?;
        self.config.lr = lr;
        Ok(())
    }
    pub fn stride(&self) -> usize {
        self.stride
    }
    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    pub fn capacity(&self) -> usize {
        self.capacity
    }
    /// Steps taken since creation or the last [`AdamGroup::reset_moments`].
    pub fn steps(&self) -> u64 {
        self.steps
    }
    /// First and second moments of the live items.
    pub fn moments(&self) -> (&[f32], &[f32]) {
        let n = self.len * self.stride;
        (&self.m[..n], &self.v[..n])
    }

    /// Both moments of the live items, to be written (the device optimiser hands its
    /// moments back here, `map::vulkan::optimiser`).
    pub fn moments_mut(&mut self) -> (&mut [f32], &mut [f32]) {
        let n = self.len * self.stride;
        (&mut self.m[..n], &mut self.v[..n])
    }

    /// The constants of the group's next step, for a step taken on the device; count it with
    /// [`AdamGroup::count_step`] once it was taken.
    pub fn next_step_constants(&self) -> StepConstants {
        StepConstants::new(&self.config, self.steps + 1)
    }

    /// Counts one step taken on the device with [`AdamGroup::next_step_constants`].
    pub fn count_step(&mut self) {
        self.steps += 1;
    }

    /// Appends `items` items with zero moments (densification); their parameters are the
    /// caller's to write.
    pub fn grow(&mut self, items: usize) -> Result<(), AdamError> {
        let new_len = self.len + items;
        if new_len > self.capacity {
            return Err(AdamError::CapacityExceeded { requested: new_len, capacity: self.capacity });
        }
        self.m[self.len * self.stride..new_len * self.stride].fill(0.0);
        self.v[self.len * self.stride..new_len * self.stride].fill(0.0);
        self.len = new_len;
        Ok(())
    }

    /// One Adam step over the live items: `params` and `grads` hold `len * stride` values.
    /// A non-finite gradient refuses the whole step.
    pub fn step(&mut self, params: &mut [f32], grads: &[f32]) -> Result<(), AdamError> {
        let n = self.len * self.stride;
        self.check_len("parameters", params.len())?;
        self.check_len("gradients", grads.len())?;
        if let Some(index) = grads.iter().position(|g| !g.is_finite()) {
            return Err(AdamError::NonFiniteGradient { index, value: grads[index] });
        }
        self.steps += 1;
        let k = StepConstants::new(&self.config, self.steps);
        let (m, v) = (&mut self.m[..n], &mut self.v[..n]);
        if n <= CHUNK {
            adam_update(&k, params, grads, m, v);
        } else {
            params.par_chunks_mut(CHUNK).zip(grads.par_chunks(CHUNK)).zip(m.par_chunks_mut(CHUNK)).zip(v.par_chunks_mut(CHUNK)).for_each(|(((p, g), m), v)| adam_update(&k, p, g, m, v));
        }
        Ok(())
    }

    /// Restores a saved state (checkpoints): the step count and the moments of
    /// `m.len() / stride` items, which become the live items.
    pub fn set_state(&mut self, steps: u64, m: &[f32], v: &[f32]) -> Result<(), AdamError> {
        let items = m.len() / self.stride;
        if items > self.capacity {
            return Err(AdamError::CapacityExceeded { requested: items, capacity: self.capacity });
        }
        let n = items * self.stride;
        if m.len() != n || v.len() != n {
            return Err(AdamError::LengthMismatch { what: "saved moments", len: v.len().max(m.len()), expected: n, items, stride: self.stride });
        }
        self.m[..n].copy_from_slice(m);
        self.v[..n].copy_from_slice(v);
        self.len = items;
        self.steps = steps;
        Ok(())
    }

    /// Zeroes both moments of every item and the step count (paper §3.3: the medium's Adam
    /// state is reset at every densify/prune step).
    pub fn reset_moments(&mut self) {
        self.m.fill(0.0);
        self.v.fill(0.0);
        self.steps = 0;
    }

    /// Zeroes the moments of items `first..first + count` (slots reused for new Gaussians).
    pub fn reset_items(&mut self, first: usize, count: usize) -> Result<(), AdamError> {
        if first + count > self.len {
            return Err(AdamError::IndexOutOfRange { index: first + count - 1, items: self.len });
        }
        let r = first * self.stride..(first + count) * self.stride;
        self.m[r.clone()].fill(0.0);
        self.v[r].fill(0.0);
        Ok(())
    }

    /// Keeps the items whose `keep` entry is true, in order, moving parameters and moments
    /// together; `params` holds the `len * stride` live values. Returns the new item count;
    /// the values past it in `params` are stale.
    pub fn retain(&mut self, params: &mut [f32], keep: &[bool]) -> Result<usize, AdamError> {
        self.check_len("parameters", params.len())?;
        if keep.len() != self.len {
            return Err(AdamError::MaskLengthMismatch { len: keep.len(), items: self.len });
        }
        let n = self.len * self.stride;
        let kept = retain_strided(params, self.stride, keep);
        retain_strided(&mut self.m[..n], self.stride, keep);
        retain_strided(&mut self.v[..n], self.stride, keep);
        self.len = kept;
        Ok(kept)
    }

    /// Removes item `index` by moving the last item into its place (parameters and moments).
    pub fn swap_remove(&mut self, params: &mut [f32], index: usize) -> Result<(), AdamError> {
        self.check_len("parameters", params.len())?;
        if index >= self.len {
            return Err(AdamError::IndexOutOfRange { index, items: self.len });
        }
        let n = self.len * self.stride;
        swap_remove_strided(params, self.stride, index);
        swap_remove_strided(&mut self.m[..n], self.stride, index);
        swap_remove_strided(&mut self.v[..n], self.stride, index);
        self.len -= 1;
        Ok(())
    }

    fn check_len(&self, what: &'static str, len: usize) -> Result<(), AdamError> {
        let expected = self.len * self.stride;
        if len != expected {
            return Err(AdamError::LengthMismatch { what, len, expected, items: self.len, stride: self.stride });
        }
        Ok(())
    }
}

/// The f32 constants of step `steps` (1-based) of a group: what the per-value update and the
/// `adam.adam_step` kernel (its immediate block, in this field order) use.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepConstants {
    pub beta1: f32,
    pub one_minus_beta1: f32,
    pub beta2: f32,
    pub one_minus_beta2: f32,
    pub step_size: f32,
    pub inv_sqrt_bias2: f32,
    pub eps: f32,
}

impl StepConstants {
    pub fn new(c: &AdamGroupConfig, steps: u64) -> Self {
        let t = steps as i32;
        let bias1 = 1.0 - c.beta1.powi(t);
        let bias2 = 1.0 - c.beta2.powi(t);
        StepConstants {
            beta1: c.beta1 as f32,
            one_minus_beta1: (1.0 - c.beta1) as f32,
            beta2: c.beta2 as f32,
            one_minus_beta2: (1.0 - c.beta2) as f32,
            step_size: (c.lr / bias1) as f32,
            inv_sqrt_bias2: (1.0 / bias2.sqrt()) as f32,
            eps: c.eps as f32,
        }
    }
}

/// The per-value update; the kernel's body.
#[inline]
fn adam_update(k: &StepConstants, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
    for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
        *m = k.beta1 * *m + k.one_minus_beta1 * g;
        *v = k.beta2 * *v + k.one_minus_beta2 * g * g;
        *p -= k.step_size * *m / (v.sqrt() * k.inv_sqrt_bias2 + k.eps);
    }
}

/// Compacts `data` (items of `stride` values, `keep.len()` items) in place, keeping the items
/// whose `keep` entry is true in their order; returns the kept count. Values past
/// `kept * stride` are left as they were.
pub fn retain_strided<T: Copy>(data: &mut [T], stride: usize, keep: &[bool]) -> usize {
    let mut out = 0;
    for (item, &k) in keep.iter().enumerate() {
        if k {
            if out != item {
                data.copy_within(item * stride..(item + 1) * stride, out * stride);
            }
            out += 1;
        }
    }
    out
}

/// Moves the last item of `data` (items of `stride` values) over item `index`.
pub fn swap_remove_strided<T: Copy>(data: &mut [T], stride: usize, index: usize) {
    let last = data.len() / stride - 1;
    if index != last {
        data.copy_within(last * stride..(last + 1) * stride, index * stride);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Adam in f64 by the textbook formulas (bias-corrected moments).
    fn reference(p0: f64, grads: &[f64], c: &AdamGroupConfig) -> Vec<f64> {
        let (mut p, mut m, mut v) = (p0, 0.0, 0.0);
        let mut out = Vec::new();
        for (t, &g) in grads.iter().enumerate() {
            let t = t as i32 + 1;
            m = c.beta1 * m + (1.0 - c.beta1) * g;
            v = c.beta2 * v + (1.0 - c.beta2) * g * g;
            let m_hat = m / (1.0 - c.beta1.powi(t));
            let v_hat = v / (1.0 - c.beta2.powi(t));
            p -= c.lr * m_hat / (v_hat.sqrt() + c.eps);
            out.push(p);
        }
        out
    }

    #[test]
    fn three_steps_match_hand_computation() {
        let c = AdamGroupConfig { lr: 0.1, beta1: 0.9, beta2: 0.999, eps: 1e-8 };
        // Step 1 by hand: m = 0.05, v = 0.00025, m_hat = 0.5, v_hat = 0.25, p = 1 - 0.1 * 0.5 / 0.5 = 0.9.
        // Step 2 (g = -0.25): m = 0.045 - 0.025 = 0.02, v = 0.00024975 + 0.0000625 = 0.00031225,
        //   m_hat = 0.02 / 0.19 = 0.105263, v_hat = 0.00031225 / 0.001999 = 0.156203,
        //   p = 0.9 - 0.1 * 0.105263 / 0.395225 = 0.873366.
        // Step 3 (g = 1): m = 0.018 + 0.1 = 0.118, v = 0.000311938 + 0.001 = 0.001311938,
        //   m_hat = 0.118 / 0.271 = 0.435424, v_hat = 0.001311938 / 0.002997001 = 0.437750,
        //   p = 0.873366 - 0.1 * 0.435424 / 0.661627 = 0.807555.
        let hand = [0.9, 0.873366, 0.807555];
        let grads = [0.5, -0.25, 1.0];
        let expected = reference(1.0, &grads, &c);
        let mut group = AdamGroup::new(c, 2, 1, 4).unwrap();
        let mut params = [1.0f32, -2.0];
        for (k, &g) in grads.iter().enumerate() {
            // The second value sees the negated gradient: it moves by the same amount upwards.
            group.step(&mut params, &[g as f32, -g as f32]).unwrap();
            assert!((params[0] as f64 - expected[k]).abs() < 1e-6, "step {k}: {} vs {}", params[0], expected[k]);
            assert!((expected[k] - hand[k]).abs() < 1e-6, "step {k}: reference {} vs hand {}", expected[k], hand[k]);
            assert!(((params[1] + 2.0) as f64 + (expected[k] - 1.0)).abs() < 1e-6);
        }
        assert_eq!(group.steps(), 3);
    }

    #[test]
    fn reset_and_compaction_keep_alignment() {
        let c = AdamGroupConfig { lr: 0.01, ..AdamGroupConfig::default() };
        let stride = 3;
        let mut group = AdamGroup::new(c, stride, 5, 8).unwrap();
        // Parameter value encodes (item, component); gradient per item distinct so moments differ.
        let mut params: Vec<f32> = (0..5 * stride).map(|i| (i / stride) as f32 * 10.0 + (i % stride) as f32).collect();
        let grads: Vec<f32> = (0..5 * stride).map(|i| 0.1 * (1 + i / stride) as f32).collect();
        group.step(&mut params, &grads).unwrap();
        let item_of_param = |p: f32| ((p + 0.5) / 10.0).floor() as usize;
        let m_of_item = |item: usize| 0.1 * 0.1 * (1 + item) as f32; // (1 - beta1) g
        // Drop items 1 and 3.
        let kept = group.retain(&mut params, &[true, false, true, false, true]).unwrap();
        assert_eq!(kept, 3);
        assert_eq!(group.len(), 3);
        let (m, _) = group.moments();
        for i in 0..3 {
            let item = item_of_param(params[i * stride]);
            assert_eq!(item, [0, 2, 4][i]);
            for j in 0..stride {
                assert!((m[i * stride + j] - m_of_item(item)).abs() < 1e-7, "{i} {j}: {m:?}");
            }
        }
        // Swap-remove the first: the last (item 4) moves into slot 0 with its moments.
        group.swap_remove(&mut params[..3 * stride], 0).unwrap();
        assert_eq!(item_of_param(params[0]), 4);
        assert!((group.moments().0[0] - m_of_item(4)).abs() < 1e-7);
        // Grow: new items have zero moments; a step still works over the new length.
        group.grow(2).unwrap();
        assert!(group.moments().0[2 * stride..].iter().all(|&v| v == 0.0));
        let mut p4 = vec![0.0f32; 4 * stride];
        group.step(&mut p4, &vec![1.0; 4 * stride]).unwrap();
        assert!(matches!(group.grow(5), Err(AdamError::CapacityExceeded { requested: 9, capacity: 8 })));
        // Reset zeroes everything, including the bias-correction clock.
        group.reset_moments();
        assert_eq!(group.steps(), 0);
        assert!(group.moments().0.iter().chain(group.moments().1).all(|&v| v == 0.0));
    }

    #[test]
    fn bad_calls_change_nothing() {
        let mut group = AdamGroup::new(AdamGroupConfig::default(), 2, 3, 3).unwrap();
        let mut params = [1.0f32; 6];
        assert!(matches!(group.step(&mut params[..5], &[0.0; 6]), Err(AdamError::LengthMismatch { len: 5, expected: 6, .. })));
        let mut grads = [0.5f32; 6];
        grads[4] = f32::NAN;
        assert!(matches!(group.step(&mut params, &grads), Err(AdamError::NonFiniteGradient { index: 4, .. })));
        assert_eq!(params, [1.0; 6]);
        assert_eq!(group.steps(), 0);
        assert!(matches!(group.retain(&mut params, &[true]), Err(AdamError::MaskLengthMismatch { len: 1, items: 3 })));
        assert!(matches!(group.swap_remove(&mut params, 3), Err(AdamError::IndexOutOfRange { index: 3, .. })));
        assert!(matches!(AdamGroup::new(AdamGroupConfig { beta2: 1.0, ..AdamGroupConfig::default() }, 1, 1, 1), Err(AdamError::InvalidConfig { field: "beta2", .. })));
        assert!(matches!(AdamGroup::new(AdamGroupConfig::default(), 0, 1, 1), Err(AdamError::ZeroStride)));
    }
}
