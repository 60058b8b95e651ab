//! The Gaussian map in structure-of-arrays buffers of fixed capacity, the layout of the GPU
//! storage buffers: one flat `f32` array per parameter group, `capacity * width` long,
//! allocated once. Gaussian `i` owns `group[i * width .. (i + 1) * width]`; only the first
//! `len` Gaussians are live. Adding past the capacity is an error, never a reallocation.
//!
//! # Parameters of one Gaussian (23 floats)
//! | group            | width | meaning                                                        |
//! |------------------|-------|----------------------------------------------------------------|
//! | `mean`           | 3     | centre in the world frame, metres                              |
//! | `log_scale`      | 3     | natural log of the standard deviations along the local axes    |
//! | `rotation`       | 4     | quaternion `(w, x, y, z)`, normalised where it is used          |
//! | `opacity_logit`  | 1     | opacity before the sigmoid                                     |
//! | `f_dc`           | 3     | SH degree 0 coefficient per channel (R, G, B)                  |
//! | `f_rest`         | 9     | SH degree 1, `f_rest[k * 3 + c]`: coefficient `k`, channel `c` |
//!
//! Colour (3DGS convention), with `(x, y, z)` the unit direction from the camera centre to the
//! mean in the world frame: `colour_c = max(0, 0.5 + SH_C0 f_dc[c] + SH_C1 (-y f_rest[c] +
//! z f_rest[3 + c] - x f_rest[6 + c]))`.

use super::real::Real;
use super::render::RenderError;

/// Real SH basis constant of degree 0, `1 / (2 sqrt(pi))`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// Real SH basis constant of degree 1, `sqrt(3) / (2 sqrt(pi))`.
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
/// Floats per Gaussian over all groups.
pub const PARAMS_PER_GAUSSIAN: usize = 23;

/// One Gaussian's parameters (or their gradients), generic so the f64 reference and the
/// gradient checks share the type with the f32 map.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GaussianParam<T> {
    pub mean: [T; 3],
    pub log_scale: [T; 3],
    pub rotation: [T; 4],
    pub opacity_logit: T,
    pub f_dc: [T; 3],
    pub f_rest: [T; 9],
}

impl<T: Copy + Default> GaussianParam<T> {
    /// The 23 values in group order (mean, log_scale, rotation, opacity_logit, f_dc, f_rest).
    pub fn to_array(&self) -> [T; PARAMS_PER_GAUSSIAN] {
        let mut out = [T::default(); PARAMS_PER_GAUSSIAN];
        out[0..3].copy_from_slice(&self.mean);
        out[3..6].copy_from_slice(&self.log_scale);
        out[6..10].copy_from_slice(&self.rotation);
        out[10] = self.opacity_logit;
        out[11..14].copy_from_slice(&self.f_dc);
        out[14..23].copy_from_slice(&self.f_rest);
        out
    }

    /// Inverse of [`Self::to_array`].
    pub fn from_array(v: &[T; PARAMS_PER_GAUSSIAN]) -> Self {
        let mut p = GaussianParam::<T>::default();
        p.mean.copy_from_slice(&v[0..3]);
        p.log_scale.copy_from_slice(&v[3..6]);
        p.rotation.copy_from_slice(&v[6..10]);
        p.opacity_logit = v[10];
        p.f_dc.copy_from_slice(&v[11..14]);
        p.f_rest.copy_from_slice(&v[14..23]);
        p
    }

    /// Applies `f` to every value.
    pub fn map<U: Copy + Default>(&self, f: impl Fn(T) -> U) -> GaussianParam<U> {
        let a = self.to_array();
        let mut b = [U::default(); PARAMS_PER_GAUSSIAN];
        for (o, &v) in b.iter_mut().zip(a.iter()) {
            *o = f(v);
        }
        GaussianParam::from_array(&b)
    }
}

/// The colour of a Gaussian seen along the unit direction `dir` (camera centre to mean,
/// world frame), before the clamp at zero: `0.5 + C0 f_dc + C1 (-y f1 + z f2 - x f3)`.
#[inline(always)]
pub fn sh_colour_raw<T: Real>(f_dc: &[T; 3], f_rest: &[T; 9], dir: &[T; 3]) -> [T; 3] {
    let (c0, c1, half) = (T::from_f64(SH_C0), T::from_f64(SH_C1), T::from_f64(0.5));
    let mut out = [T::ZERO; 3];
    for c in 0..3 {
        out[c] = half + c0 * f_dc[c] + c1 * (-dir[1] * f_rest[c] + dir[2] * f_rest[3 + c] - dir[0] * f_rest[6 + c]);
    }
    out
}

/// A parameter group of the SoA layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ParamGroup {
    Mean,
    LogScale,
    Rotation,
    OpacityLogit,
    FDc,
    FRest,
}

impl ParamGroup {
    pub const ALL: [ParamGroup; 6] =
        [ParamGroup::Mean, ParamGroup::LogScale, ParamGroup::Rotation, ParamGroup::OpacityLogit, ParamGroup::FDc, ParamGroup::FRest];

    /// Floats per Gaussian in this group.
    pub const fn width(self) -> usize {
        match self {
            ParamGroup::Mean | ParamGroup::LogScale | ParamGroup::FDc => 3,
            ParamGroup::Rotation => 4,
            ParamGroup::OpacityLogit => 1,
            ParamGroup::FRest => 9,
        }
    }

    pub const fn name(self) -> &'static str {
        match self {
            ParamGroup::Mean => "mean",
            ParamGroup::LogScale => "log_scale",
            ParamGroup::Rotation => "rotation",
            ParamGroup::OpacityLogit => "opacity_logit",
            ParamGroup::FDc => "f_dc",
            ParamGroup::FRest => "f_rest",
        }
    }

    /// Offset of the group's first value in [`GaussianParam::to_array`].
    pub const fn offset(self) -> usize {
        match self {
            ParamGroup::Mean => 0,
            ParamGroup::LogScale => 3,
            ParamGroup::Rotation => 6,
            ParamGroup::OpacityLogit => 10,
            ParamGroup::FDc => 11,
            ParamGroup::FRest => 14,
        }
    }
}

/// The six flat buffers, `capacity * width` each.
#[derive(Clone, Debug, PartialEq)]
struct ParamBuffers {
    groups: [Vec<f32>; 6],
}

impl ParamBuffers {
    fn zeroed(capacity: usize) -> Self {
        ParamBuffers { groups: ParamGroup::ALL.map(|g| vec![0.0; capacity * g.width()]) }
    }

    #[inline]
    fn get(&self, i: usize) -> GaussianParam<f32> {
        let mut a = [0.0f32; PARAMS_PER_GAUSSIAN];
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            let w = g.width();
            a[g.offset()..g.offset() + w].copy_from_slice(&self.groups[k][i * w..(i + 1) * w]);
        }
        GaussianParam::from_array(&a)
    }

    #[inline]
    fn set(&mut self, i: usize, p: &GaussianParam<f32>) {
        let a = p.to_array();
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            let w = g.width();
            self.groups[k][i * w..(i + 1) * w].copy_from_slice(&a[g.offset()..g.offset() + w]);
        }
    }

    fn copy_within(&mut self, from: usize, to: usize) {
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            let w = g.width();
            self.groups[k].copy_within(from * w..(from + 1) * w, to * w);
        }
    }

    fn fill_range(&mut self, start: usize, end: usize, value: f32) {
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            let w = g.width();
            self.groups[k][start * w..end * w].fill(value);
        }
    }
}

/// The Gaussian map: SoA parameter buffers of fixed capacity.
#[derive(Clone, Debug, PartialEq)]
pub struct Gaussians {
    capacity: usize,
    len: usize,
    buf: ParamBuffers,
}

impl Gaussians {
    /// An empty map holding up to `capacity` Gaussians; all memory is allocated here.
    pub fn with_capacity(capacity: usize) -> Self {
        Gaussians { capacity, len: 0, buf: ParamBuffers::zeroed(capacity) }
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

    /// Appends a Gaussian and returns its index; [`RenderError::GaussianCapacity`] when full.
    pub fn push(&mut self, p: &GaussianParam<f32>) -> Result<usize, RenderError> {
        if self.len == self.capacity {
            return Err(RenderError::GaussianCapacity { capacity: self.capacity });
        }
        self.buf.set(self.len, p);
        self.len += 1;
        Ok(self.len - 1)
    }

    /// Gaussian `i` (`i < len`; panics otherwise, like slice indexing).
    pub fn get(&self, i: usize) -> GaussianParam<f32> {
        assert!(i < self.len, "Gaussian {i} out of range (len {})", self.len);
        self.buf.get(i)
    }

    pub fn set(&mut self, i: usize, p: &GaussianParam<f32>) {
        assert!(i < self.len, "Gaussian {i} out of range (len {})", self.len);
        self.buf.set(i, p);
    }

    pub fn clear(&mut self) {
        self.len = 0;
    }

    pub fn truncate(&mut self, len: usize) {
        self.len = self.len.min(len);
    }

    /// Keeps the Gaussians for which `keep(index)` is true, in order, compacting in place
    /// (no allocation). Returns how many were removed.
    pub fn retain(&mut self, mut keep: impl FnMut(usize) -> bool) -> usize {
        let mut out = 0;
        for i in 0..self.len {
            if keep(i) {
                if out != i {
                    self.buf.copy_within(i, out);
                }
                out += 1;
            }
        }
        let removed = self.len - out;
        self.len = out;
        removed
    }

    /// The live values of one group, `len * width` floats.
    pub fn group(&self, g: ParamGroup) -> &[f32] {
        &self.buf.groups[g as usize][..self.len * g.width()]
    }

    pub fn group_mut(&mut self, g: ParamGroup) -> &mut [f32] {
        let n = self.len * g.width();
        &mut self.buf.groups[g as usize][..n]
    }

    /// Whether every value of the map is finite: large blocks without an early exit inside a
    /// block, so the loop vectorises (a per-Gaussian `position_first` took 12-15 ms for 100k
    /// Gaussians on 2 busy cores, in every render).
    pub fn all_finite(&self) -> bool {
        use rayon::prelude::*;
        ParamGroup::ALL.iter().all(|&g| self.group(g).par_chunks(1 << 15).all(|c| c.iter().fold(true, |ok, x| ok & x.is_finite())))
    }

    /// Overwrites the map's `len()` Gaussians from `aos`, [`PARAMS_PER_GAUSSIAN`] floats per
    /// Gaussian in [`GaussianParam::to_array`] order (a device map read back), in parallel
    /// blocks. `aos` shorter than that is an error and changes nothing.
    pub fn copy_from_aos(&mut self, aos: &[f32]) -> Result<(), RenderError> {
        use rayon::prelude::*;
        const BLOCK: usize = 4096;
        let n = self.len;
        if aos.len() < n * PARAMS_PER_GAUSSIAN {
            return Err(RenderError::CapacityExceeded { what: "parameters read back (floats)", requested: n * PARAMS_PER_GAUSSIAN, capacity: aos.len() });
        }
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            let (w, off) = (g.width(), g.offset());
            self.buf.groups[k][..n * w].par_chunks_mut(w * BLOCK).enumerate().for_each(|(b, dst)| {
                for (j, d) in dst.chunks_exact_mut(w).enumerate() {
                    let s = (b * BLOCK + j) * PARAMS_PER_GAUSSIAN + off;
                    d.copy_from_slice(&aos[s..s + w]);
                }
            });
        }
        Ok(())
    }

    /// The first Gaussian (lowest index) holding a non-finite value, with its group.
    pub fn find_non_finite(&self) -> Option<(usize, ParamGroup)> {
        use rayon::prelude::*;
        if self.all_finite() {
            return None;
        }
        let first = |g: ParamGroup| {
            let w = g.width();
            self.group(g).par_chunks(w).position_first(|v| !v.iter().all(|x| x.is_finite())).map(|i| (i, g))
        };
        ParamGroup::ALL.iter().filter_map(|&g| first(g)).min_by_key(|&(i, g)| (i, g.offset()))
    }
}

/// Gradients of a loss with respect to every Gaussian parameter (same SoA layout as
/// [`Gaussians`]), plus the densification statistics of paper §3.3.
///
/// [`RasterWorkspace::backward`](super::render::RasterWorkspace::backward) **adds** into these
/// buffers, so several views can be accumulated before an optimiser step; call
/// [`Self::zero_params`] (parameters only) or [`Self::reset`] (everything) in between.
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianGrads {
    capacity: usize,
    len: usize,
    buf: ParamBuffers,
    /// Per Gaussian, summed over backward passes: `| sum_pixels dL/dmean2d * exp(sigma_med t) |`
    /// (pixel units), the attenuation-compensated screen-space gradient norm of one view.
    densify_grad_norm: Vec<f32>,
    /// Per Gaussian, summed over backward passes: pixels the Gaussian contributed to.
    pixels_touched: Vec<u32>,
    /// Per Gaussian: backward passes (views) in which it contributed to at least one pixel.
    views: Vec<u32>,
    /// Per Gaussian, kept across statistics resets and moved with the map by its callers
    /// (densification, eviction, seeding): the largest mean pixels per view it contributed to
    /// over every statistics window so far ([`GaussianGrads::fold_footprint`]). A Gaussian
    /// that only old, rarely revisited keyframes see keeps the footprint it had when seen.
    footprint: Vec<f32>,
}

impl GaussianGrads {
    pub fn with_capacity(capacity: usize) -> Self {
        GaussianGrads {
            capacity,
            len: 0,
            buf: ParamBuffers::zeroed(capacity),
            densify_grad_norm: vec![0.0; capacity],
            pixels_touched: vec![0; capacity],
            views: vec![0; capacity],
            footprint: vec![0.0; capacity],
        }
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

    /// Folds the statistics of the current window into the footprints: each Gaussian seen in
    /// at least one view keeps the larger of its footprint and its mean pixels per view.
    pub fn fold_footprint(&mut self) {
        for i in 0..self.len {
            if self.views[i] > 0 {
                let mean = self.pixels_touched[i] as f32 / self.views[i] as f32;
                self.footprint[i] = self.footprint[i].max(mean);
            }
        }
    }

    /// Footprints of the current length ([`GaussianGrads::fold_footprint`]).
    pub fn footprint(&self) -> &[f32] {
        &self.footprint[..self.len]
    }

    /// Footprint of slot `i` (any slot below the capacity).
    pub fn footprint_at(&self, i: usize) -> f32 {
        self.footprint[i]
    }

    /// Sets the footprint of slot `i` (any slot below the capacity, also past the current
    /// length: a Gaussian appended before the next [`GaussianGrads::reset`]).
    pub fn set_footprint(&mut self, i: usize, pixels: f32) {
        self.footprint[i] = pixels;
    }

    /// Moves the footprints of the first `keep.len()` slots as a compaction by `keep` moves
    /// the map ([`super::adam::AdamGroup::retain`]); the statistics are not moved (reset them).
    pub fn retain_footprint(&mut self, keep: &[bool]) {
        super::adam::retain_strided(&mut self.footprint[..keep.len()], 1, keep);
    }

    /// Sets the length (to match the map) and zeroes every gradient and statistic; the
    /// footprints stay (slots appended since the last compaction keep what their caller set).
    pub fn reset(&mut self, len: usize) -> Result<(), RenderError> {
        if len > self.capacity {
            return Err(RenderError::GaussianCapacity { capacity: self.capacity });
        }
        self.len = len;
        self.buf.fill_range(0, len, 0.0);
        self.densify_grad_norm[..len].fill(0.0);
        self.pixels_touched[..len].fill(0);
        self.views[..len].fill(0);
        Ok(())
    }

    /// Zeroes the parameter gradients, keeping the densification statistics.
    pub fn zero_params(&mut self) {
        self.buf.fill_range(0, self.len, 0.0);
    }

    /// Zeroes the densification statistics, keeping the parameter gradients.
    pub fn reset_densify_stats(&mut self) {
        self.densify_grad_norm[..self.len].fill(0.0);
        self.pixels_touched[..self.len].fill(0);
        self.views[..self.len].fill(0);
    }

    pub fn get(&self, i: usize) -> GaussianParam<f32> {
        assert!(i < self.len, "Gaussian {i} out of range (len {})", self.len);
        self.buf.get(i)
    }

    pub fn group(&self, g: ParamGroup) -> &[f32] {
        &self.buf.groups[g as usize][..self.len * g.width()]
    }

    pub fn group_mut(&mut self, g: ParamGroup) -> &mut [f32] {
        let n = self.len * g.width();
        &mut self.buf.groups[g as usize][..n]
    }

    pub fn densify_grad_norm(&self) -> &[f32] {
        &self.densify_grad_norm[..self.len]
    }
    pub fn pixels_touched(&self) -> &[u32] {
        &self.pixels_touched[..self.len]
    }
    pub fn views(&self) -> &[u32] {
        &self.views[..self.len]
    }

    /// Restores saved densification statistics (checkpoints) for the first `dgn.len()`
    /// Gaussians, which must equal the current length.
    pub fn set_densify_stats(&mut self, dgn: &[f32], touched: &[u32], views: &[u32]) -> Result<(), RenderError> {
        if dgn.len() != self.len || touched.len() != self.len || views.len() != self.len {
            return Err(RenderError::GradLenMismatch { grads: dgn.len(), gaussians: self.len });
        }
        self.densify_grad_norm[..self.len].copy_from_slice(dgn);
        self.pixels_touched[..self.len].copy_from_slice(touched);
        self.views[..self.len].copy_from_slice(views);
        Ok(())
    }

    /// Same as [`Gaussians::retain`], for keeping gradients aligned with a pruned map.
    pub fn retain(&mut self, mut keep: impl FnMut(usize) -> bool) -> usize {
        let mut out = 0;
        for i in 0..self.len {
            if keep(i) {
                if out != i {
                    self.buf.copy_within(i, out);
                    self.densify_grad_norm[out] = self.densify_grad_norm[i];
                    self.pixels_touched[out] = self.pixels_touched[i];
                    self.views[out] = self.views[i];
                    self.footprint[out] = self.footprint[i];
                }
                out += 1;
            }
        }
        let removed = self.len - out;
        self.len = out;
        removed
    }

    /// Mutable views of every buffer, for the projection-backward stage.
    pub(crate) fn parts_mut(&mut self) -> GradParts<'_> {
        let n = self.len;
        let [mean, log_scale, rotation, opacity_logit, f_dc, f_rest] = &mut self.buf.groups;
        GradParts {
            mean: &mut mean[..n * 3],
            log_scale: &mut log_scale[..n * 3],
            rotation: &mut rotation[..n * 4],
            opacity_logit: &mut opacity_logit[..n],
            f_dc: &mut f_dc[..n * 3],
            f_rest: &mut f_rest[..n * 9],
            densify_grad_norm: &mut self.densify_grad_norm[..n],
            pixels_touched: &mut self.pixels_touched[..n],
            views: &mut self.views[..n],
        }
    }
}

pub(crate) struct GradParts<'a> {
    pub mean: &'a mut [f32],
    pub log_scale: &'a mut [f32],
    pub rotation: &'a mut [f32],
    pub opacity_logit: &'a mut [f32],
    pub f_dc: &'a mut [f32],
    pub f_rest: &'a mut [f32],
    pub densify_grad_norm: &'a mut [f32],
    pub pixels_touched: &'a mut [u32],
    pub views: &'a mut [u32],
}

#[cfg(test)]
mod tests {
    use super::*;

    fn param(k: f32) -> GaussianParam<f32> {
        let a: [f32; PARAMS_PER_GAUSSIAN] = std::array::from_fn(|i| k * 100.0 + i as f32);
        GaussianParam::from_array(&a)
    }

    #[test]
    fn push_get_retain_and_capacity() {
        let mut g = Gaussians::with_capacity(4);
        for k in 0..4 {
            assert_eq!(g.push(&param(k as f32)).unwrap(), k);
        }
        assert_eq!(g.push(&param(9.0)), Err(RenderError::GaussianCapacity { capacity: 4 }));
        assert_eq!(g.get(2), param(2.0));
        assert_eq!(g.group(ParamGroup::Rotation)[4..8], [106.0, 107.0, 108.0, 109.0]);
        assert_eq!(g.retain(|i| i != 1), 1);
        assert_eq!((g.len(), g.get(1)), (3, param(2.0)));
        assert_eq!(g.find_non_finite(), None);
        g.group_mut(ParamGroup::FRest)[2 * 9 + 4] = f32::NAN;
        g.group_mut(ParamGroup::OpacityLogit)[2] = f32::INFINITY;
        assert_eq!(g.find_non_finite(), Some((2, ParamGroup::OpacityLogit)));
    }

    /// `copy_from_aos` against `set` one Gaussian at a time, over several parallel blocks;
    /// `all_finite` and `find_non_finite` agree past a block boundary.
    #[test]
    fn copy_from_aos_matches_set_and_finite_checks_agree() {
        let n = 9000;
        let mut a = Gaussians::with_capacity(n);
        let mut b = Gaussians::with_capacity(n);
        let mut aos = Vec::with_capacity(n * PARAMS_PER_GAUSSIAN);
        for k in 0..n {
            a.push(&param(0.0)).unwrap();
            b.push(&param(0.0)).unwrap();
            aos.extend_from_slice(&param(k as f32 * 0.01).to_array());
        }
        assert!(a.copy_from_aos(&aos[..aos.len() - 1]).is_err());
        assert_eq!(a.get(n - 1), param(0.0), "a short buffer changes nothing");
        a.copy_from_aos(&aos).unwrap();
        for k in 0..n {
            b.set(k, &param(k as f32 * 0.01));
        }
        assert_eq!(a, b);
        assert!(a.all_finite());
        a.group_mut(ParamGroup::FDc)[3 * 8200 + 1] = f32::NEG_INFINITY;
        assert!(!a.all_finite());
        assert_eq!(a.find_non_finite(), Some((8200, ParamGroup::FDc)));
    }

    #[test]
    fn array_round_trip_and_sh_constants() {
        let p = param(3.0);
        assert_eq!(GaussianParam::from_array(&p.to_array()), p);
        assert!((SH_C0 - 0.5 / std::f64::consts::PI.sqrt()).abs() < 1e-16);
        assert!((SH_C1 - 3f64.sqrt() * 0.5 / std::f64::consts::PI.sqrt()).abs() < 1e-16);
    }
}
