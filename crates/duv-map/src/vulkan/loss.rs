//! The mapping losses (Eq. 12-14) on the GPU: the twin of [`crate::loss::total_loss`],
//! kernels in `kernels/loss.wgsl`.
//!
//! [`GpuLoss`] holds the keyframes the views are compared with (image, tracked depth and
//! variance, uploaded by [`GpuLoss::upload_target`] unless the keyed target is still in one of
//! its slots) and the SSIM and reduction scratch, all allocated once for the largest image. [`GpuLoss::record`] reads the rendered
//! images where the rasteriser left them ([`LossBuffers`]) and writes the renderer's upstream
//! gradients where the rasteriser backward reads them, so a forward, the loss and the
//! backward run with no image crossing to the host. [`GpuLoss::read_terms`] reads back only
//! the per-workgroup sums of each term (8 floats per 256 pixels) and adds them in f64 in
//! workgroup order, as the CPU reference adds its row sums.
//!
//! Passes, one invocation per pixel (CPU reference in brackets, `src/map/loss.rs`):
//! `count_valid` (`count_valid`), `loss_pixels` (`l1_term`, `mahalanobis_term`, `kl_term`,
//! `smoothness_term`, `accuracy_term`: the same additions in the same order per pixel),
//! `ssim_rows` / `ssim_cols` / `ssim_back_rows` / `ssim_back_cols` (`ssim_term`: products and
//! the horizontal filter, the vertical filter and the SSIM map with its partials, the
//! transposed filters and the gradient), `medium_sums` / `medium_mean` / `medium_variation`
//! (`medium_variation_term`; the mean of `c_med` as a fixed-order reduction in f32 where the
//! CPU adds row sums in f64).
//!
//! The rendered images are not checked for non-finite values on the GPU (that would need
//! them on the host); a non-finite rendered value makes the loss non-finite, which
//! [`GpuLoss::read_terms`] reports as [`LossError::NonFinite`] naming the term.

use duv_core::Image;
use duv_gpu::{GpuBuffer, GpuContext, GpuError, GpuRange};
use super::kernels::Kernel;
use crate::loss::{ssim_kernel, LossConfig, LossError, LossTerms, TargetView, SSIM_WINDOW};

/// Pixels per workgroup of the per-pixel loss kernels.
const WG: usize = 256;
/// Pixels per invocation of the sliding SSIM filters (`SEG` of `loss.wgsl`).
const SSIM_SEGMENT: usize = 32;
/// Workgroup size of the sliding SSIM filters.
const SLIDING_WG: usize = 64;
/// Partial sums per workgroup (`partials[group * 8 + term]`).
pub const LOSS_PARTIALS: usize = 8;
/// RGB vectors (vec4 slots) per pixel of the SSIM moments: x, y, x^2, y^2, xy.
const MOMENTS: usize = 5;
/// RGB vectors per pixel of the SSIM map's partials: dS/dmu_x, dS/dE_xx, dS/dE_xy.
const SSIM_PARTIALS: usize = 3;

/// Words of the immediate block of `loss.wgsl` (`LossParams`).
const PARAM_WORDS: usize = 20;

/// The immediate block of `loss.wgsl` (`LossParams`, field for field), the constants cast as
/// the CPU reference casts them (`T::from_f64` of each config value).
fn loss_params(config: &LossConfig, width: usize, height: usize) -> [u32; PARAM_WORDS] {
    let f = |v: f64| (v as f32).to_bits();
    [
        width as u32,
        height as u32,
        config.kl_one_sided as u32,
        0,
        f(config.photometric_weight * (1.0 - config.ssim_lambda)),
        f(config.photometric_weight * config.ssim_lambda),
        f(config.mahalanobis_weight),
        f(config.kl_weight),
        f(config.kl_variance_floor),
        f(config.max_track_variance),
        f(config.smoothness_weight),
        f(config.smoothness_edge_gamma),
        f(config.smoothness_epsilon),
        f(config.accuracy_weight),
        f(config.accuracy_scale),
        (config.accuracy_beta as f32).ln().to_bits(),
        f(config.medium_variation_weight),
        0,
        0,
        0,
    ]
}

/// Where the loss reads the render and writes the renderer's upstream gradients (the buffers
/// of [`super::GpuRasterForward`] and [`super::GpuRasterBackward`]).
#[derive(Clone, Copy, Debug)]
pub struct LossBuffers<'a> {
    /// Rendered colour, RGB per pixel.
    pub colour: &'a GpuBuffer<f32>,
    /// Per pixel `[depth, depth variance, alpha, final T]`.
    pub scalars: &'a GpuBuffer<[f32; 4]>,
    /// The medium planes' `c_med`, RGB per pixel, for the medium-variation prior; `None`
    /// skips it (as `RenderedView::medium` = `None` does).
    pub c_med: Option<&'a GpuBuffer<f32>>,
    /// dL/dC, RGB per pixel (overwritten).
    pub up_colour: &'a GpuBuffer<f32>,
    /// Per pixel `[dL/dD, dL/dV, dL/dA, 0]` (overwritten).
    pub up_scalars: &'a GpuBuffer<[f32; 4]>,
}

/// One keyframe target on the device: its image (RGB per pixel) and the tracker's
/// `[depth, variance]` per pixel.
struct TargetSlot {
    image: GpuBuffer<f32>,
    track: GpuBuffer<[f32; 2]>,
    /// The [`TargetKey`] of what it holds (`None`: nothing reusable).
    key: Option<TargetKey>,
    /// Width and height of what it holds.
    size: (usize, usize),
    /// When it was last used ([`GpuLoss::upload_target`] calls), for least-recently-used reuse.
    last_used: u64,
}

/// Names a keyframe target's contents for [`GpuLoss::upload_target`]'s cache: the same key must
/// never name different pixels (the mapper draws a new one from [`TargetKey::fresh`] whenever a
/// keyframe slot is refilled).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TargetKey(u64);

impl TargetKey {
    /// A key no other call in this process returns.
    pub fn fresh() -> Self {
        static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        TargetKey(NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed))
    }
}

impl TargetSlot {
    fn new(ctx: &mut GpuContext, pixels: usize) -> Result<Self, GpuError> {
        Ok(TargetSlot {
            image: ctx.alloc("loss target image", pixels * 3)?,
            track: ctx.alloc("loss tracked depth and variance", pixels)?,
            key: None,
            size: (0, 0),
            last_used: 0,
        })
    }
}

/// The loss stage on the GPU for images up to `max_width x max_height`.
pub struct GpuLoss {
    max_width: usize,
    max_height: usize,
    /// Keyframe targets on the device: slot 0 from [`Self::new`], more from
    /// [`Self::reserve_target_slots`]; a keyed target found here is not uploaded again.
    slots: Vec<TargetSlot>,
    /// The slot the next [`Self::record`] compares with.
    current: usize,
    /// [`Self::upload_target`] calls so far (the slots' clock).
    uses: u64,
    /// Target uploads skipped because the keyed target was on the device.
    pub target_hits: u64,
    window: GpuBuffer<f32>,
    moments_a: GpuBuffer<[f32; 4]>,
    moments_b: GpuBuffer<[f32; 4]>,
    partials: GpuBuffer<f32>,
    valid_count: GpuBuffer<u32>,
    medium_sums: GpuBuffer<[f32; 4]>,
    /// dL/dc_med of the medium-variation prior, RGB per pixel (zero when it is off).
    pub d_c_med: GpuBuffer<f32>,
    staging_track: Vec<[f32; 2]>,
    staging_partials: Vec<f32>,
    /// Size of the uploaded target, and what the last [`Self::record`] evaluated.
    target_size: Option<(usize, usize)>,
    last: Option<(usize, usize, LossConfig, bool)>,
    last_mse: f64,
    /// The SSIM filters by segments of 32 pixels of a row or column per invocation, sliding
    /// the window (`loss.ssim_rows_sliding`, `ssim_cols_sliding` + `ssim_sum`,
    /// `ssim_back_rows_sliding`, `ssim_back_cols_sliding`) instead of one pixel per invocation
    /// loading its 11 taps; the same bits on lavapipe (on the H100 the last bits of dL/dC
    /// differ, each within the CPU reference's tolerances). `None`: on a CPU device (lavapipe
    /// loads buffer values lane by lane; on the H100 the step took 1.04-1.08x with it).
    pub sliding_ssim: Option<bool>,
}

impl GpuLoss {
    /// Every buffer, allocated once from the arena.
    pub fn new(ctx: &mut GpuContext, max_width: usize, max_height: usize) -> Result<Self, GpuError> {
        let n = (max_width * max_height).max(1);
        let groups = n.div_ceil(WG);
        let window = ctx.alloc("SSIM window", SSIM_WINDOW)?;
        ctx.write(&window, &ssim_kernel().map(|v| v as f32))?;
        Ok(GpuLoss {
            max_width,
            max_height,
            slots: vec![TargetSlot::new(ctx, n)?],
            current: 0,
            uses: 0,
            target_hits: 0,
            window,
            moments_a: ctx.alloc("SSIM moments", n * MOMENTS)?,
            moments_b: ctx.alloc("SSIM partials", n * SSIM_PARTIALS)?,
            partials: ctx.alloc("loss partial sums", groups * LOSS_PARTIALS)?,
            valid_count: ctx.alloc("loss valid depth count", 1)?,
            medium_sums: ctx.alloc("c_med sums", groups + 1)?,
            d_c_med: ctx.alloc("dL/dc_med of the medium prior", n * 3)?,
            staging_track: vec![[0.0; 2]; n],
            staging_partials: vec![0.0; groups * LOSS_PARTIALS],
            target_size: None,
            last: None,
            last_mse: f64::NAN,
            sliding_ssim: None,
        })
    }

    /// Adds target slots (each one keyframe at the largest image size) until there are
    /// `wanted` or the next would take more than half of the arena still free, whichever comes
    /// first; called once at start-up, after every fixed buffer. Returns the slot count.
    pub fn reserve_target_slots(&mut self, ctx: &mut GpuContext, wanted: usize) -> Result<usize, GpuError> {
        let n = (self.max_width * self.max_height).max(1);
        // Image and track, each rounded up to the arena's alignment.
        let slot_bytes = (4 * 5 * n as u64).next_multiple_of(256) + 512;
        while self.slots.len() < wanted {
            let free = ctx.arena_capacity_bytes().saturating_sub(ctx.arena_used_bytes());
            if slot_bytes > free / 2 {
                break;
            }
            self.slots.push(TargetSlot::new(ctx, n)?);
        }
        Ok(self.slots.len())
    }

    /// Number of keyframe targets the device holds at once.
    pub fn target_slots(&self) -> usize {
        self.slots.len()
    }

    /// Makes the view's keyframe image, tracked depth and variance the target of the next
    /// [`Self::record`], with the CPU reference's checks (sizes, a finite image; non-finite
    /// depth or variance marks a pixel invalid). With a `key` whose target is still in a slot
    /// nothing is checked or uploaded again; otherwise it goes into the least recently used
    /// slot (slot 0 when unkeyed).
    pub fn upload_target(&mut self, ctx: &mut GpuContext, target: &TargetView, key: Option<TargetKey>) -> Result<(), super::VulkanRenderError> {
        self.uses += 1;
        let (w, h) = (target.image.width, target.image.height);
        if let Some(slot) = key.and_then(|k| self.slots.iter().position(|s| s.key == Some(k) && s.size == (w, h))) {
            self.current = slot;
            self.slots[slot].last_used = self.uses;
            self.target_hits += 1;
            self.target_size = Some((w, h));
            return Ok(());
        }
        if w == 0 || h == 0 {
            return Err(LossError::Empty { what: "target image", width: w, height: h }.into());
        }
        if w > self.max_width || h > self.max_height {
            return Err(LossError::CapacityExceeded { width: w, height: h, max_width: self.max_width, max_height: self.max_height }.into());
        }
        check_len("target image", target.image)?;
        for (what, img) in [("tracked depth", target.depth), ("tracked depth variance", target.depth_variance)] {
            if img.width != w || img.height != h {
                return Err(LossError::SizeMismatch { what, width: img.width, height: img.height, reference: "target image", expected_width: w, expected_height: h }.into());
            }
            check_len(what, img)?;
        }
        if let Some(index) = target.image.data.iter().position(|v| !v.is_finite()) {
            return Err(LossError::NonFinite { what: "target image", index, value: target.image.data[index] as f64 }.into());
        }
        let n = w * h;
        for ((s, &d), &v) in self.staging_track[..n].iter_mut().zip(&target.depth.data).zip(&target.depth_variance.data) {
            *s = [d, v];
        }
        let slot = match key {
            None => 0,
            Some(_) => (0..self.slots.len()).min_by_key(|&i| self.slots[i].last_used).unwrap_or(0),
        };
        let s = &mut self.slots[slot];
        // Forgotten first: a failed write leaves no stale key behind.
        s.key = None;
        ctx.write(&s.image, &target.image.data)?;
        ctx.write(&s.track, &self.staging_track[..n])?;
        s.key = key;
        s.size = (w, h);
        s.last_used = self.uses;
        self.current = slot;
        self.target_size = Some((w, h));
        Ok(())
    }

    /// Records every term of `config` for a `width x height` render against the uploaded
    /// target: the upstream gradients into `bufs.up_colour` / `bufs.up_scalars` (overwritten)
    /// and [`Self::d_c_med`], the partial sums for [`Self::read_terms`].
    pub fn record(&mut self, ctx: &mut GpuContext, bufs: &LossBuffers, width: usize, height: usize, config: &LossConfig) -> Result<(), super::VulkanRenderError> {
        config.validate()?;
        self.last = None;
        match self.target_size {
            Some((w, h)) if (w, h) == (width, height) => {}
            Some((w, h)) => {
                return Err(LossError::SizeMismatch { what: "rendered colour", width, height, reference: "target image", expected_width: w, expected_height: h }.into())
            }
            None => return Err(LossError::Empty { what: "target image (none uploaded)", width: 0, height: 0 }.into()),
        }
        let n = width * height;
        for (what, len, need) in [
            ("rendered colour", bufs.colour.len(), 3 * n),
            ("rendered depth, variance, alpha", bufs.scalars.len(), n),
            ("dL/dcolour", bufs.up_colour.len(), 3 * n),
            ("dL/d depth, variance, alpha", bufs.up_scalars.len(), n),
        ] {
            if len < need {
                return Err(GpuError::OutOfRange { what, requested: need, len }.into());
            }
        }
        let medium = match bufs.c_med {
            Some(c) if config.medium_variation_weight > 0.0 => {
                if c.len() < 3 * n {
                    return Err(GpuError::OutOfRange { what: "medium c_med", requested: 3 * n, len: c.len() }.into());
                }
                Some(c)
            }
            _ => None,
        };
        let params = loss_params(config, width, height);
        let imm = bytemuck::cast_slice(&params);
        let groups = [n.div_ceil(WG) as u32, 1, 1];
        let c_med_range = medium.map(|c| c.range()).unwrap_or(self.d_c_med.range());
        let lookup = |name: &str| -> Option<GpuRange> {
            Some(match name {
                "colour" => bufs.colour.range(),
                "scalars" => bufs.scalars.range(),
                "target_image" => self.slots[self.current].image.range(),
                "track" => self.slots[self.current].track.range(),
                "up_colour" => bufs.up_colour.range(),
                "up_scalars" => bufs.up_scalars.range(),
                "partials" => self.partials.range(),
                "valid_count" => self.valid_count.range(),
                "window" => self.window.range(),
                "moments_a" => self.moments_a.range(),
                "moments_b" => self.moments_b.range(),
                "c_med" => c_med_range,
                "d_c_med" => self.d_c_med.range(),
                "c_med_sums" => self.medium_sums.range(),
                _ => return None,
            })
        };
        ctx.fill(self.valid_count.range(), 0)?;
        if config.mahalanobis_weight > 0.0 || config.kl_weight > 0.0 {
            ctx.dispatch_named(Kernel::LossCountValid, lookup, imm, groups)?;
        }
        ctx.dispatch_named(Kernel::LossLossPixels, lookup, imm, groups)?;
        if config.photometric_weight > 0.0 {
            if self.sliding_ssim.unwrap_or(ctx.info().is_cpu()) {
                // One invocation per segment of SSIM_SEGMENT pixels of a row, or of a column.
                let rows = [((width.div_ceil(SSIM_SEGMENT) * height).div_ceil(SLIDING_WG)) as u32, 1, 1];
                let cols = [((height.div_ceil(SSIM_SEGMENT) * width).div_ceil(SLIDING_WG)) as u32, 1, 1];
                for (k, g) in [
                    (Kernel::LossSsimRowsSliding, rows),
                    (Kernel::LossSsimColsSliding, cols),
                    (Kernel::LossSsimSum, groups),
                    (Kernel::LossSsimBackRowsSliding, rows),
                    (Kernel::LossSsimBackColsSliding, cols),
                ] {
                    ctx.dispatch_named(k, lookup, imm, g)?;
                }
            } else {
                for k in [Kernel::LossSsimRows, Kernel::LossSsimCols, Kernel::LossSsimBackRows, Kernel::LossSsimBackCols] {
                    ctx.dispatch_named(k, lookup, imm, groups)?;
                }
            }
        }
        if medium.is_some() {
            ctx.dispatch_named(Kernel::LossMediumSums, lookup, imm, groups)?;
            ctx.dispatch_named(Kernel::LossMediumMean, lookup, imm, [1, 1, 1])?;
            ctx.dispatch_named(Kernel::LossMediumVariation, lookup, imm, groups)?;
        } else {
            ctx.fill(self.d_c_med.range(), 0)?;
        }
        self.last = Some((width, height, *config, medium.is_some()));
        Ok(())
    }

    /// Records what [`Self::read_terms`] reads for the host in the loss's submission
    /// ([`GpuContext::prefetch`]): the valid depth count and the per-workgroup sums.
    pub fn prefetch_terms(&self, ctx: &mut GpuContext) -> Result<(), GpuError> {
        let Some((w, h, ..)) = self.last else { return Ok(()) };
        ctx.prefetch(self.valid_count.range())?;
        ctx.prefetch(self.partials.slice_range(0, (w * h).div_ceil(WG) * LOSS_PARTIALS)?)
    }

    /// Each term's value and the weighted total of the last recorded (and submitted) loss, as
    /// [`crate::loss::total_loss`] returns them.
    pub fn read_terms(&mut self, ctx: &GpuContext) -> Result<LossTerms, super::VulkanRenderError> {
        let (w, h, cfg, medium) = self.last.ok_or(LossError::Empty { what: "GPU loss (nothing recorded)", width: 0, height: 0 })?;
        let n = w * h;
        let groups = n.div_ceil(WG);
        let mut valid = [0u32; 1];
        ctx.read_prefetched(&self.valid_count, &mut valid)?;
        let valid = valid[0] as usize;
        let partials = &mut self.staging_partials[..groups * LOSS_PARTIALS];
        ctx.read_prefetched(&self.partials, partials)?;
        let mut sums = [0.0f64; LOSS_PARTIALS];
        for group in partials.chunks_exact(LOSS_PARTIALS) {
            for (s, &v) in sums.iter_mut().zip(group) {
                *s += v as f64;
            }
        }
        let (nf, validf) = (n as f64, valid.max(1) as f64);
        self.last_mse = sums[7] / (3.0 * nf);
        let mut t = LossTerms::default();
        if cfg.photometric_weight > 0.0 {
            t.l1 = sums[0] / (3.0 * nf);
            t.ssim = sums[5] / (3.0 * nf);
            t.photometric = (1.0 - cfg.ssim_lambda) * t.l1 + cfg.ssim_lambda * (1.0 - t.ssim);
        }
        if valid > 0 && cfg.mahalanobis_weight > 0.0 {
            t.mahalanobis = sums[1] / validf;
        }
        if valid > 0 && cfg.kl_weight > 0.0 {
            t.kl = sums[2] / validf;
        }
        if cfg.mahalanobis_weight > 0.0 || cfg.kl_weight > 0.0 {
            t.valid_depth_pixels = valid;
        }
        if cfg.smoothness_weight > 0.0 {
            t.smoothness = sums[3] / nf;
        }
        if cfg.accuracy_weight > 0.0 {
            t.accuracy = sums[4] / nf;
        }
        if medium {
            t.medium_variation = sums[6] / nf;
        }
        t.total = cfg.photometric_weight * t.photometric
            + cfg.mahalanobis_weight * t.mahalanobis
            + cfg.kl_weight * t.kl
            + cfg.smoothness_weight * t.smoothness
            + cfg.accuracy_weight * t.accuracy
            + cfg.medium_variation_weight * t.medium_variation;
        for (what, v) in [
            ("GPU loss: L1", t.l1),
            ("GPU loss: SSIM", t.ssim),
            ("GPU loss: Mahalanobis", t.mahalanobis),
            ("GPU loss: KL", t.kl),
            ("GPU loss: smoothness", t.smoothness),
            ("GPU loss: accuracy", t.accuracy),
            ("GPU loss: medium variation", t.medium_variation),
        ] {
            if !v.is_finite() {
                return Err(LossError::NonFinite { what, index: 0, value: v }.into());
            }
        }
        Ok(t)
    }

    /// PSNR in dB of the render read by the last [`Self::read_terms`] against the target
    /// (data range 1), as [`crate::loss::psnr_db`] computes it on the host.
    pub fn last_psnr_db(&self) -> f64 {
        if self.last_mse == 0.0 {
            f64::INFINITY
        } else {
            -10.0 * self.last_mse.log10()
        }
    }
}

fn check_len<const C: usize>(what: &'static str, img: &Image<f32, C>) -> Result<(), LossError> {
    let expected = img.width * img.height * C;
    if img.data.len() != expected {
        return Err(LossError::LengthMismatch { what, len: img.data.len(), expected });
    }
    Ok(())
}
