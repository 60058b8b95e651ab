//! Keyframe nodes and their fixed-capacity store.
//!
//! A keyframe holds its pose, the prepared image pyramid of the flow front end, its inverse
//! depth and variance at the depth grid (1/`depth_factor` of the input), an 8-bit copy of the
//! image (the guide of the joint bilateral upsampling), the guide's block means at the depth
//! grid, and a normalised thumbnail for appearance search (loops, relocalisation). Slots are
//! allocated once; a keyframe entering the store takes a free slot, one leaving gives it back.

use super::flow::{FlowEstimator, PreparedFrame};
use duv_core::{PlaneF32, Se3, Timestamp};

/// Thumbnail size: the image box-averaged to 32 x 24 cells.
pub const THUMB_W: usize = 32;
pub const THUMB_H: usize = 24;
pub const THUMB_N: usize = THUMB_W * THUMB_H;

/// One keyframe slot.
pub(crate) struct Keyframe {
    /// Monotonic id (never reused).
    pub id: u64,
    pub t_ns: Timestamp,
    pub seq: u64,
    /// Map segment (a new one starts after a loss; merged segments share the older id).
    pub segment: u32,
    pub world_from_cam: Se3,
    /// Product of the scale corrections the pose graph applied to this keyframe (1 at birth).
    pub scale_correction: f64,
    /// Inverse depth at the depth grid, 1/m.
    pub inv_depth: PlaneF32,
    /// Inverse depth variance at the depth grid, (1/m)^2 (valid when `has_variance`).
    pub variance: PlaneF32,
    pub has_variance: bool,
    /// The a posteriori variance of unit weight `variance` was multiplied by (1 when it was
    /// not): `variance / variance_unit` is in the units of the flow weights (motion-only BA).
    /// NaN for a keyframe seeded from a log (the unit is not recorded): its variance then stays
    /// out of the motion-only BA until a window BA recomputes it.
    pub variance_unit: f32,
    pub frame: PreparedFrame,
    /// Full-resolution 8-bit grey image (upsampling guide).
    pub guide: Vec<u8>,
    /// Guide block means at the depth grid, [0, 1].
    pub guide_low: PlaneF32,
    /// Zero-mean, unit-norm thumbnail.
    pub thumb: Vec<f32>,
}

impl Keyframe {
    pub fn new(flow: &FlowEstimator, width: usize, height: usize, low_w: usize, low_h: usize) -> Self {
        Keyframe {
            id: 0,
            t_ns: Timestamp(0),
            seq: 0,
            segment: 0,
            world_from_cam: Se3::identity(),
            scale_correction: 1.0,
            inv_depth: PlaneF32::new(low_w, low_h),
            variance: PlaneF32::new(low_w, low_h),
            has_variance: false,
            variance_unit: 1.0,
            frame: flow.new_frame(),
            guide: vec![0; width * height],
            guide_low: PlaneF32::new(low_w, low_h),
            thumb: vec![0.0; THUMB_N],
        }
    }
}

/// Fixed-capacity keyframe storage: `slots` never grows; `order` lists the live slots oldest
/// first.
pub(crate) struct KeyframeStore {
    pub slots: Vec<Keyframe>,
    /// Live slot indices in insertion order.
    pub order: Vec<usize>,
    free: Vec<usize>,
    next_id: u64,
}

impl KeyframeStore {
    /// `capacity` live keyframes plus one staging slot (a keyframe just evicted, readable until
    /// the next frame).
    pub fn new(capacity: usize, make: impl Fn() -> Keyframe) -> Self {
        let slots: Vec<Keyframe> = (0..capacity + 1).map(|_| make()).collect();
        let free: Vec<usize> = (0..capacity + 1).rev().collect();
        KeyframeStore { slots, order: Vec::with_capacity(capacity + 1), free, next_id: 0 }
    }

    pub fn len(&self) -> usize {
        self.order.len()
    }

    /// Live keyframes the store may hold.
    pub fn capacity(&self) -> usize {
        self.slots.len() - 1
    }

    pub fn is_full(&self) -> bool {
        self.order.len() >= self.capacity()
    }

    /// Slot of the newest keyframe.
    pub fn newest(&self) -> Option<usize> {
        self.order.last().copied()
    }

    /// Takes a free slot, gives it a fresh id and appends it (newest). `None` when no slot is
    /// free (the caller evicts first).
    pub fn push(&mut self) -> Option<usize> {
        if self.is_full() {
            return None;
        }
        // First in, first out: a slot just freed by an eviction stays readable this frame.
        if self.free.is_empty() {
            return None;
        }
        let s = self.free.remove(0);
        self.slots[s].id = self.next_id;
        self.next_id += 1;
        self.slots[s].scale_correction = 1.0;
        self.slots[s].has_variance = false;
        self.slots[s].variance_unit = 1.0;
        self.order.push(s);
        Some(s)
    }

    /// Like [`push`](Self::push), with the id given (a keyframe recorded by an earlier run);
    /// later ids continue after it. `None` when no slot is free or `id` is below an id already
    /// given out.
    pub fn push_with_id(&mut self, id: u64) -> Option<usize> {
        if id < self.next_id {
            return None;
        }
        self.next_id = id;
        self.push()
    }

    /// Ids given out from now on are at least `next`.
    pub fn reserve_ids_below(&mut self, next: u64) {
        self.next_id = self.next_id.max(next);
    }

    /// Removes the keyframe at `order` position `pos`; its slot becomes free (its data stays
    /// readable until the slot is taken again).
    pub fn remove_at(&mut self, pos: usize) -> usize {
        let s = self.order.remove(pos);
        self.free.push(s);
        s
    }

    /// Position in `order` of slot `s`.
    pub fn position(&self, s: usize) -> Option<usize> {
        self.order.iter().position(|&o| o == s)
    }

    /// Slot of keyframe id `id`.
    pub fn slot_of(&self, id: u64) -> Option<usize> {
        self.order.iter().copied().find(|&s| self.slots[s].id == id)
    }
}

/// Writes the zero-mean, unit-norm box-averaged thumbnail of a grey image.
pub(crate) fn thumbnail(grey: &[f32], width: usize, height: usize, out: &mut [f32]) {
    for ty in 0..THUMB_H {
        let (y0, y1) = (ty * height / THUMB_H, ((ty + 1) * height / THUMB_H).max(ty * height / THUMB_H + 1).min(height));
        for tx in 0..THUMB_W {
            let (x0, x1) = (tx * width / THUMB_W, ((tx + 1) * width / THUMB_W).max(tx * width / THUMB_W + 1).min(width));
            let mut s = 0.0f32;
            for y in y0..y1 {
                s += grey[y * width + x0..y * width + x1].iter().sum::<f32>();
            }
            out[ty * THUMB_W + tx] = s / ((y1 - y0) * (x1 - x0)).max(1) as f32;
        }
    }
    normalise(out);
}

fn normalise(v: &mut [f32]) {
    let mean = v.iter().sum::<f32>() / v.len() as f32;
    let mut norm = 0.0f32;
    for x in v.iter_mut() {
        *x -= mean;
        norm += *x * *x;
    }
    let inv = if norm > 1e-12 { 1.0 / norm.sqrt() } else { 0.0 };
    for x in v.iter_mut() {
        *x *= inv;
    }
}

/// Normalised cross-correlation of two thumbnails (both zero-mean, unit-norm).
pub(crate) fn ncc(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Block means of a grey image at the depth grid (`cell` input pixels per low-res pixel).
pub(crate) fn block_means(grey: &[f32], width: usize, cell: usize, out: &mut PlaneF32) {
    let inv = 1.0 / (cell * cell) as f32;
    for ly in 0..out.height {
        for lx in 0..out.width {
            let mut s = 0.0;
            for y in ly * cell..(ly + 1) * cell {
                s += grey[y * width + lx * cell..y * width + (lx + 1) * cell].iter().sum::<f32>();
            }
            out.data[ly * out.width + lx] = s * inv;
        }
    }
}

/// Image statistics for the health check: mean intensity and contrast (standard deviation of
/// 4x4 block means, which averages sensor noise away).
pub(crate) fn image_health(grey: &[f32], width: usize, height: usize) -> (f32, f32) {
    let (bw, bh) = (width / 4, height / 4);
    if bw == 0 || bh == 0 {
        let mean = grey.iter().sum::<f32>() / grey.len().max(1) as f32;
        return (mean, 0.0);
    }
    let (mut s, mut s2) = (0.0f64, 0.0f64);
    for by in 0..bh {
        for bx in 0..bw {
            let mut b = 0.0f32;
            for y in by * 4..by * 4 + 4 {
                b += grey[y * width + bx * 4..y * width + bx * 4 + 4].iter().sum::<f32>();
            }
            let m = (b / 16.0) as f64;
            s += m;
            s2 += m * m;
        }
    }
    let n = (bw * bh) as f64;
    let mean = s / n;
    let var = (s2 / n - mean * mean).max(0.0);
    (mean as f32, var.sqrt() as f32)
}
