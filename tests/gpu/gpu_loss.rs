//! The loss kernels (`kernels/loss.wgsl`, `map::vulkan::loss::GpuLoss`) on the Vulkan device
//! (lavapipe in CI) against the CPU reference `map::loss::total_loss`: every term's value,
//! the upstream gradients dL/dC, dL/dD, dL/dV, dL/dA and dL/dc_med, on images whose pixel
//! count is not a multiple of the 256-wide workgroups, with invalid tracked pixels of every
//! kind; a second run is bit-identical; bad input is an error.

use crate::gpu_common;

use duv_core::rng::Rng;
use duv_core::Image;
use duv_gpu::{GpuBuffer, GpuContext};
use duv_map::loss::{total_loss, LossConfig, LossError, LossTerms, LossWorkspace, RenderedView, TargetView};
use duv_map::mapper::psnr_db;
use duv_map::medium::{MediumPlanes, C_MED, MEDIUM_CHANNELS};
use duv_map::vulkan::loss::{GpuLoss, LossBuffers};
use duv_map::vulkan::VulkanRenderError;

/// Loss values: `|gpu - cpu| <= tol * max(|cpu|, 1e-6)` (f32 workgroup sums against f64 row
/// sums; the GPU's exp/log are not correctly rounded).
const VALUE_REL_TOL: f64 = 1e-4;
/// Gradients: `|gpu - cpu| <= GRAD_REL_TOL * max(|cpu|, GRAD_FLOOR_FRACTION * max |cpu|)` per
/// value, the floor taken over every value of the same image (see `tests/gpu/gpu_map.rs`).
const GRAD_REL_TOL: f64 = 1e-3;
const GRAD_FLOOR_FRACTION: f64 = 1e-2;

/// A rendered view and its keyframe: the render near the target as during optimisation,
/// tracked pixels invalid by NaN depth, infinite, zero, negative and too large variance.
struct Scene {
    colour: Image<f32, 3>,
    depth: Image<f32, 1>,
    depth_var: Image<f32, 1>,
    alpha: Image<f32, 1>,
    medium: MediumPlanes,
    target: Image<f32, 3>,
    track_depth: Image<f32, 1>,
    track_var: Image<f32, 1>,
}

fn image<const C: usize>(w: usize, h: usize, mut f: impl FnMut(usize) -> f32) -> Image<f32, C> {
    Image { width: w, height: h, data: (0..w * h * C).map(&mut f).collect() }
}

fn scene(w: usize, h: usize, seed: u64) -> Scene {
    let mut rng = Rng::new(seed);
    let target = image::<3>(w, h, |_| rng.range(0.0, 1.0) as f32);
    let colour = image::<3>(w, h, |i| (target.data[i] as f64 + rng.range(-0.2, 0.2)) as f32);
    let depth = image::<1>(w, h, |_| rng.range(0.1, 1.0) as f32);
    let depth_var = image::<1>(w, h, |i| if i % 97 == 0 { -1e-4 } else { rng.range(0.0, 0.05) as f32 });
    let alpha = image::<1>(w, h, |i| if i % 13 == 0 { 1.0 } else { rng.range(0.0, 1.0) as f32 });
    let medium = image::<MEDIUM_CHANNELS>(w, h, |_| rng.range(0.05, 0.9) as f32);
    let track_depth = image::<1>(w, h, |i| if i % 31 == 0 { f32::NAN } else { (depth.data[i] as f64 + rng.range(-0.1, 0.1)) as f32 });
    let track_var = image::<1>(w, h, |i| match i % 41 {
        0 => f32::INFINITY,
        1 => 0.0,
        2 => -0.5,
        3 => 2e4,
        _ => rng.range(1e-3, 0.2) as f32,
    });
    Scene { colour, depth, depth_var, alpha, medium, target, track_depth, track_var }
}

fn cpu_loss(s: &Scene, config: &LossConfig, with_medium: bool) -> (LossTerms, LossWorkspace) {
    cpu_loss_against(s, s, config, with_medium)
}

/// The CPU loss of `render`'s rendered view against `keyframe`'s target.
fn cpu_loss_against(render: &Scene, keyframe: &Scene, config: &LossConfig, with_medium: bool) -> (LossTerms, LossWorkspace) {
    let s = render;
    let mut ws = LossWorkspace::new(s.colour.width, s.colour.height);
    let rendered = RenderedView { color: &s.colour, depth: &s.depth, depth_variance: &s.depth_var, alpha: &s.alpha, medium: with_medium.then_some(&s.medium) };
    let target = TargetView { image: &keyframe.target, depth: &keyframe.track_depth, depth_variance: &keyframe.track_var };
    let terms = total_loss(&mut ws, config, &rendered, &target).unwrap();
    (terms, ws)
}

/// The render's buffers on the device, as the rasteriser leaves them.
struct DeviceView {
    colour: GpuBuffer<f32>,
    scalars: GpuBuffer<[f32; 4]>,
    c_med: GpuBuffer<f32>,
    up_colour: GpuBuffer<f32>,
    up_scalars: GpuBuffer<[f32; 4]>,
}

fn upload_view(ctx: &mut GpuContext, s: &Scene) -> DeviceView {
    let n = s.colour.width * s.colour.height;
    let v = DeviceView {
        colour: ctx.alloc("rendered colour", 3 * n).unwrap(),
        scalars: ctx.alloc("rendered scalars", n).unwrap(),
        c_med: ctx.alloc("c_med", 3 * n).unwrap(),
        up_colour: ctx.alloc("dL/dC", 3 * n).unwrap(),
        up_scalars: ctx.alloc("dL/d scalars", n).unwrap(),
    };
    ctx.write(&v.colour, &s.colour.data).unwrap();
    let scalars: Vec<[f32; 4]> = (0..n).map(|i| [s.depth.data[i], s.depth_var.data[i], s.alpha.data[i], 1.0 - s.alpha.data[i]]).collect();
    ctx.write(&v.scalars, &scalars).unwrap();
    let c_med: Vec<f32> = s.medium.data.chunks_exact(MEDIUM_CHANNELS).flat_map(|px| px[C_MED..C_MED + 3].to_vec()).collect();
    ctx.write(&v.c_med, &c_med).unwrap();
    // Garbage in the outputs: the loss must overwrite them.
    ctx.write(&v.up_colour, &vec![7.0; 3 * n]).unwrap();
    ctx.write(&v.up_scalars, &vec![[7.0; 4]; n]).unwrap();
    v
}

/// Runs the GPU loss once; returns the terms and (dC, [dD, dV, dA], dc_med).
fn gpu_loss(ctx: &mut GpuContext, gpu: &mut GpuLoss, v: &DeviceView, s: &Scene, config: &LossConfig, with_medium: bool) -> (LossTerms, Vec<f32>, Vec<[f32; 4]>, Vec<f32>) {
    let (w, h) = (s.colour.width, s.colour.height);
    let n = w * h;
    gpu.upload_target(ctx, &TargetView { image: &s.target, depth: &s.track_depth, depth_variance: &s.track_var }, None).unwrap();
    let bufs = LossBuffers { colour: &v.colour, scalars: &v.scalars, c_med: with_medium.then_some(&v.c_med), up_colour: &v.up_colour, up_scalars: &v.up_scalars };
    ctx.begin().unwrap();
    gpu.record(ctx, &bufs, w, h, config).unwrap();
    ctx.submit_and_wait().unwrap();
    let terms = gpu.read_terms(ctx).unwrap();
    let mut d_colour = vec![0.0f32; 3 * n];
    let mut d_scalars = vec![[0.0f32; 4]; n];
    let mut d_c_med = vec![0.0f32; 3 * n];
    ctx.read(&v.up_colour, &mut d_colour).unwrap();
    ctx.read(&v.up_scalars, &mut d_scalars).unwrap();
    ctx.read(&gpu.d_c_med, &mut d_c_med).unwrap();
    (terms, d_colour, d_scalars, d_c_med)
}

fn check_values(what: &str, gpu: &LossTerms, cpu: &LossTerms) {
    assert_eq!(gpu.valid_depth_pixels, cpu.valid_depth_pixels, "{what}: valid depth pixels");
    for (name, g, c) in [
        ("l1", gpu.l1, cpu.l1),
        ("ssim", gpu.ssim, cpu.ssim),
        ("photometric", gpu.photometric, cpu.photometric),
        ("mahalanobis", gpu.mahalanobis, cpu.mahalanobis),
        ("kl", gpu.kl, cpu.kl),
        ("smoothness", gpu.smoothness, cpu.smoothness),
        ("accuracy", gpu.accuracy, cpu.accuracy),
        ("medium_variation", gpu.medium_variation, cpu.medium_variation),
        ("total", gpu.total, cpu.total),
    ] {
        let err = (g - c).abs() / c.abs().max(1e-6);
        eprintln!("{what}: {name} GPU {g:.7e} CPU {c:.7e} rel {err:.1e}");
        assert!(err <= VALUE_REL_TOL, "{what}: {name}: GPU {g} vs CPU {c} (relative error {err:.2e})");
    }
}

fn check_grads(what: &str, gpu: impl Iterator<Item = f32>, cpu: impl Iterator<Item = f32> + Clone) {
    let scale = cpu.clone().fold(0.0f64, |m, v| m.max(v.abs() as f64));
    let floor = GRAD_FLOOR_FRACTION * scale;
    let mut worst = (0usize, 0.0f64, 0.0f32, 0.0f32);
    let mut count = 0;
    for (i, (g, c)) in gpu.zip(cpu).enumerate() {
        count += 1;
        let err = (g - c).abs() as f64 / (c.abs() as f64).max(floor).max(f64::MIN_POSITIVE);
        if err > worst.1 {
            worst = (i, err, g, c);
        }
    }
    eprintln!("{what}: {count} values, largest |cpu| {scale:.3e}, worst scaled error {:.2e}", worst.1);
    assert!(count > 0, "{what}: nothing compared");
    assert!(worst.1 <= GRAD_REL_TOL, "{what}[{}]: GPU {} vs CPU {} (scaled error {:.2e})", worst.0, worst.2, worst.3, worst.1);
}

fn compare(ctx: &mut GpuContext, w: usize, h: usize, config: &LossConfig, with_medium: bool, label: &str) {
    let s = scene(w, h, 5 + w as u64);
    let (cpu_terms, ws) = cpu_loss(&s, config, with_medium);
    let mark = ctx.arena_used_bytes();
    let mut gpu = GpuLoss::new(ctx, w + 3, h + 2).unwrap();
    let v = upload_view(ctx, &s);
    // The SSIM filters by sliding windows (a CPU device's default) against one pixel per
    // invocation: the same bits on a CPU device (lavapipe). On a GPU the driver's compiler may
    // fuse the two kernels' multiply-adds differently (the H100's did: the last bits of dL/dC
    // differ), so there each meets the CPU reference's tolerances.
    gpu.sliding_ssim = Some(false);
    let per_pixel = gpu_loss(ctx, &mut gpu, &v, &s, config, with_medium);
    gpu.sliding_ssim = Some(true);
    let (terms, d_colour, d_scalars, d_c_med) = gpu_loss(ctx, &mut gpu, &v, &s, config, with_medium);
    if ctx.info().is_cpu() {
        assert_eq!(terms.total.to_bits(), per_pixel.0.total.to_bits(), "{label}: loss differs between the sliding and per-pixel SSIM filters");
        assert_eq!(terms.ssim.to_bits(), per_pixel.0.ssim.to_bits(), "{label}: SSIM term differs between the sliding and per-pixel SSIM filters");
        assert!(d_colour == per_pixel.1, "{label}: dL/dC differs between the sliding and per-pixel SSIM filters");
    } else {
        check_values(&format!("{label} (per-pixel SSIM)"), &per_pixel.0, &cpu_terms);
        check_grads(&format!("{label} (per-pixel SSIM): dL/dC"), per_pixel.1.iter().copied(), ws.grads().d_color.data.iter().copied());
    }
    check_values(label, &terms, &cpu_terms);
    let (psnr_gpu, psnr_cpu) = (gpu.last_psnr_db(), psnr_db(&s.colour, &s.target));
    eprintln!("{label}: PSNR GPU {psnr_gpu:.6} dB CPU {psnr_cpu:.6} dB");
    assert!((psnr_gpu - psnr_cpu).abs() <= 1e-4, "{label}: PSNR GPU {psnr_gpu} vs CPU {psnr_cpu}");
    let g = ws.grads();
    check_grads(&format!("{label}: dL/dC"), d_colour.iter().copied(), g.d_color.data.iter().copied());
    check_grads(&format!("{label}: dL/dD"), d_scalars.iter().map(|s| s[0]), g.d_depth.data.iter().copied());
    check_grads(&format!("{label}: dL/dV"), d_scalars.iter().map(|s| s[1]), g.d_depth_variance.data.iter().copied());
    check_grads(&format!("{label}: dL/dA"), d_scalars.iter().map(|s| s[2]), g.d_alpha.data.iter().copied());
    let cpu_c_med = g.d_medium.data.chunks_exact(MEDIUM_CHANNELS).flat_map(|px| px[C_MED..C_MED + 3].to_vec()).collect::<Vec<_>>();
    if with_medium && config.medium_variation_weight > 0.0 {
        check_grads(&format!("{label}: dL/dc_med"), d_c_med.iter().copied(), cpu_c_med.iter().copied());
    } else {
        assert!(d_c_med.iter().all(|&v| v == 0.0), "{label}: dL/dc_med must be zero without the medium prior");
    }
    // A second run on the same device: bit-identical (no float atomics).
    let (terms2, d_colour2, d_scalars2, d_c_med2) = gpu_loss(ctx, &mut gpu, &v, &s, config, with_medium);
    assert_eq!(terms.total.to_bits(), terms2.total.to_bits(), "{label}: loss differs between runs");
    assert!(d_colour == d_colour2 && d_scalars == d_scalars2 && d_c_med == d_c_med2, "{label}: gradients differ between runs");
    ctx.arena_reset_to(mark);
}

#[test]
fn loss_kernels_match_total_loss() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("loss_kernels_match_total_loss") else { return };
    // 203 x 117 = 23751 pixels: 93 workgroups, the last one partial; rows and columns not
    // multiples of anything.
    compare(&mut ctx, 203, 117, &LossConfig::default(), true, "defaults 203x117");
    // Every weight on and larger, so each term's gradient matters in the comparison.
    let strong = LossConfig { mahalanobis_weight: 0.5, kl_weight: 0.3, smoothness_weight: 0.7, accuracy_weight: 0.2, medium_variation_weight: 0.4, accuracy_beta: 0.6, ..LossConfig::default() };
    compare(&mut ctx, 61, 37, &strong, true, "strong weights 61x37");
    compare(&mut ctx, 61, 37, &LossConfig { kl_one_sided: true, ..strong }, true, "one-sided KL 61x37");
}

#[test]
fn loss_kernels_skip_what_the_config_turns_off() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("loss_kernels_skip_what_the_config_turns_off") else { return };
    // Depth terms only (no photometric, no medium planes given), then photometric only.
    let depth_only = LossConfig { photometric_weight: 0.0, accuracy_weight: 0.0, ..LossConfig::default() };
    compare(&mut ctx, 70, 40, &depth_only, false, "depth only 70x40");
    let photo_only = LossConfig { mahalanobis_weight: 0.0, kl_weight: 0.0, smoothness_weight: 0.0, accuracy_weight: 0.0, medium_variation_weight: 0.0, ..LossConfig::default() };
    compare(&mut ctx, 300, 3, &photo_only, true, "photometric only 300x3");
}

#[test]
fn loss_kernels_refuse_bad_input() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("loss_kernels_refuse_bad_input") else { return };
    let (w, h) = (40, 30);
    let mark = ctx.arena_used_bytes();
    let mut gpu = GpuLoss::new(&mut ctx, w, h).unwrap();
    let mut s = scene(w, h, 3);
    let v = upload_view(&mut ctx, &s);
    let bufs = LossBuffers { colour: &v.colour, scalars: &v.scalars, c_med: Some(&v.c_med), up_colour: &v.up_colour, up_scalars: &v.up_scalars };
    let config = LossConfig::default();
    // Nothing uploaded yet.
    ctx.begin().unwrap();
    let e = gpu.record(&mut ctx, &bufs, w, h, &config).unwrap_err();
    ctx.submit_and_wait().unwrap();
    assert!(e.to_string().contains("target image"), "{e}");
    assert!(gpu.read_terms(&ctx).is_err(), "read_terms before any record must fail");
    // A non-finite keyframe pixel is named.
    s.target.data[17] = f32::NAN;
    let e = gpu.upload_target(&mut ctx, &TargetView { image: &s.target, depth: &s.track_depth, depth_variance: &s.track_var }, None).unwrap_err();
    assert!(matches!(e, VulkanRenderError::Loss(LossError::NonFinite { what: "target image", index: 17, .. })), "{e}");
    s.target.data[17] = 0.5;
    // Larger than the buffers.
    let big = scene(w + 1, h, 4);
    let e = gpu.upload_target(&mut ctx, &TargetView { image: &big.target, depth: &big.track_depth, depth_variance: &big.track_var }, None).unwrap_err();
    assert!(matches!(e, VulkanRenderError::Loss(LossError::CapacityExceeded { .. })), "{e}");
    // Depth of another size than the image.
    let small = scene(w - 1, h, 4);
    let e = gpu.upload_target(&mut ctx, &TargetView { image: &s.target, depth: &small.track_depth, depth_variance: &s.track_var }, None).unwrap_err();
    assert!(matches!(e, VulkanRenderError::Loss(LossError::SizeMismatch { what: "tracked depth", .. })), "{e}");
    // A render of another size than the uploaded target.
    gpu.upload_target(&mut ctx, &TargetView { image: &s.target, depth: &s.track_depth, depth_variance: &s.track_var }, None).unwrap();
    ctx.begin().unwrap();
    let e = gpu.record(&mut ctx, &bufs, w, h - 1, &config).unwrap_err();
    assert!(matches!(e, VulkanRenderError::Loss(LossError::SizeMismatch { .. })), "{e}");
    // A bad config is named.
    let bad = LossConfig { ssim_lambda: 1.5, ..config };
    let e = gpu.record(&mut ctx, &bufs, w, h, &bad).unwrap_err();
    assert!(e.to_string().contains("ssim_lambda"), "{e}");
    ctx.submit_and_wait().unwrap();
    // A non-finite rendered value (not checked on the device) makes the loss an error.
    let mut colour = s.colour.data.clone();
    colour[5] = f32::INFINITY;
    ctx.write(&v.colour, &colour).unwrap();
    ctx.begin().unwrap();
    gpu.record(&mut ctx, &bufs, w, h, &config).unwrap();
    ctx.submit_and_wait().unwrap();
    let e = gpu.read_terms(&ctx).unwrap_err();
    assert!(matches!(e, VulkanRenderError::Loss(LossError::NonFinite { .. })), "{e}");
    ctx.arena_reset_to(mark);
}

/// Keyed targets stay on the device: a step on a keyframe whose target is still in a slot
/// uploads nothing and compares with exactly that target; with more keyframes than slots the
/// least recently used slot is refilled, and an unkeyed upload never leaves a reusable key.
#[test]
fn keyed_targets_are_kept_on_the_device() {
    use duv_map::vulkan::loss::TargetKey;
    let Some(mut ctx) = gpu_common::gpu_or_skip("keyed_targets_are_kept_on_the_device") else { return };
    let (w, h) = (45, 29);
    let mark = ctx.arena_used_bytes();
    let mut gpu = GpuLoss::new(&mut ctx, w, h).unwrap();
    assert_eq!(gpu.target_slots(), 1);
    assert_eq!(gpu.reserve_target_slots(&mut ctx, 2).unwrap(), 2, "two small slots fit");
    let scenes: Vec<Scene> = (0..3).map(|k| scene(w, h, 40 + k)).collect();
    let keys: Vec<TargetKey> = (0..3).map(|_| TargetKey::fresh()).collect();
    // Each keyframe's target against the same render.
    let v = upload_view(&mut ctx, &scenes[0]);
    let bufs = LossBuffers { colour: &v.colour, scalars: &v.scalars, c_med: Some(&v.c_med), up_colour: &v.up_colour, up_scalars: &v.up_scalars };
    let config = LossConfig::default();
    let total = |ctx: &mut GpuContext, gpu: &mut GpuLoss, s: &Scene, key: Option<TargetKey>, garble: bool| {
        let target = TargetView { image: &s.target, depth: &s.track_depth, depth_variance: &s.track_var };
        let garbled;
        let target = if garble {
            // What the host passes on a hit is not read: the slot is.
            garbled = Image { data: s.target.data.iter().map(|p| 1.0 - p).collect(), ..s.target.clone() };
            TargetView { image: &garbled, ..target }
        } else {
            target
        };
        gpu.upload_target(ctx, &target, key).unwrap();
        ctx.begin().unwrap();
        gpu.record(ctx, &bufs, w, h, &config).unwrap();
        ctx.submit_and_wait().unwrap();
        gpu.read_terms(ctx).unwrap().total
    };
    let expect: Vec<f64> = scenes.iter().map(|k| cpu_loss_against(&scenes[0], k, &config, true).0.total).collect();
    let near = |got: f64, want: f64| (got - want).abs() <= VALUE_REL_TOL * want.abs().max(1e-6);
    let a = total(&mut ctx, &mut gpu, &scenes[0], Some(keys[0]), false);
    let b = total(&mut ctx, &mut gpu, &scenes[1], Some(keys[1]), false);
    assert!(near(a, expect[0]) && near(b, expect[1]), "fresh uploads: {a} vs {}, {b} vs {}", expect[0], expect[1]);
    assert_eq!(gpu.target_hits, 0);
    // Both are on the device: neither is uploaded again (the garbled host image is ignored).
    assert_eq!(total(&mut ctx, &mut gpu, &scenes[0], Some(keys[0]), true).to_bits(), a.to_bits());
    assert_eq!(total(&mut ctx, &mut gpu, &scenes[1], Some(keys[1]), true).to_bits(), b.to_bits());
    assert_eq!(gpu.target_hits, 2);
    // A third keyframe takes the least recently used slot (keyframe 0's) ...
    let c = total(&mut ctx, &mut gpu, &scenes[2], Some(keys[2]), false);
    assert!(near(c, expect[2]), "{c} vs {}", expect[2]);
    assert_eq!(total(&mut ctx, &mut gpu, &scenes[1], Some(keys[1]), true).to_bits(), b.to_bits(), "keyframe 1 was kept");
    assert_eq!(gpu.target_hits, 3);
    // ... so keyframe 0 is uploaded again (a garbled image would now be compared).
    let garbled = total(&mut ctx, &mut gpu, &scenes[0], Some(keys[0]), true);
    assert_eq!(gpu.target_hits, 3, "keyframe 0 was evicted");
    assert!(!near(garbled, expect[0]), "the re-upload must read the host image");
    // An unkeyed upload refills slot 0 and forgets its key.
    let unkeyed = total(&mut ctx, &mut gpu, &scenes[1], None, false);
    assert!(near(unkeyed, expect[1]));
    let again = total(&mut ctx, &mut gpu, &scenes[2], Some(keys[2]), false);
    assert!(near(again, expect[2]));
    ctx.arena_reset_to(mark);
}
