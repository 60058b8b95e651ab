//! Forward and backward render on the Vulkan device (`map::vulkan::GpuRenderer`) against the
//! CPU reference (`RasterWorkspace::forward` + `backward`) in the same run: 320x240 and
//! 640x480 with 20k and 100k random Gaussians (the scenes of `benches/render.rs`) and random
//! upstream gradients. Medians of several runs, the GPU time including uploads and
//! read-backs, then the per-kernel GPU timestamps (forward and backward kernels), and the
//! backward again in deterministic mode (no float atomics) where the device has them.
//!
//! Then the whole mapper step (`Mapper::step_on`: medium network, forward, losses, backward,
//! Adam) on the Vulkan mapper (map, Adam and medium network on the device) against the CPU
//! mapper, same sizes and maps, one keyframe rendered from the map itself.
//!
//! Run: `cargo bench --bench gpu_render` (release; `DUV_VULKAN_DEVICE` picks the device);
//! `cargo bench --bench gpu_render -- --quick`: 320x240 with 20k Gaussians only, 3 runs (a CPU
//! Vulkan device such as lavapipe takes seconds per backward pass); `-- --gaussians N` runs
//! that count only; `-- --variants` also times the mapper step with each CPU-device kernel
//! variant switched against the device's default, one at a time; `-- --mapper-only` skips
//! the bare forward+backward; `-- --timeline` prints each Vulkan mapper's last timed step
//! dispatch by dispatch (start, end and the gap before it, from the timestamp queries).

#[path = "../tests/common/render_scene.rs"]
mod render_scene;

use std::path::Path;
use std::time::{Duration, Instant};

use duv_core::config::Board;
use duv_core::rng::Rng;
use duv_gpu::{GpuContext, GpuOptions};
use duv_map::vulkan::{Kernel, KERNELS};
use duv_map::gaussians::GaussianGrads;
use duv_map::render::{MediumPlanes, RasterCapacity, RasterWorkspace, RenderConfig, RenderError, RenderOutput};
use duv_core::{ImageRgb8, Keyframe, PlaneF32, Timestamp};
use duv_map::mapper::{Mapper, MapperCapacity, MapperConfig};
use duv_map::medium::{MediumConfig, MediumNet};
use duv_map::backend::MapperDevice;
use duv_map::vulkan::{GpuRenderer, VulkanRenderError};
use render_scene::{camera, random_gaussians, random_medium, random_upstream, world_from_cam};

const RUNS: usize = 7;
const QUICK_RUNS: usize = 3;

fn median_ms(samples: &mut [Duration]) -> f64 {
    samples.sort();
    samples[samples.len() / 2].as_secs_f64() * 1e3
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let runs = if quick { QUICK_RUNS } else { RUNS };
    let board = Board::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/sim.toml")).expect("boards/sim.toml");
    let mut ctx = match GpuContext::new(&GpuOptions::with_budget_mb(board.budgets.gpu_mb), &KERNELS) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("gpu_render: no Vulkan device, nothing to compare: {e}");
            return;
        }
    };
    println!("device: {}; CPU reference on {} rayon threads; median of {runs} runs", ctx.info(), rayon::current_num_threads());
    // Fixed GPU memory of the forward and backward buffers for a 640x480 run with a 300k
    // Gaussian cap and room for 10 tile intersections per Gaussian (allocated, not used).
    let mark = ctx.arena_used_bytes();
    let cap300k = RasterCapacity { width: 640, height: 480, max_gaussians: 300_000, max_intersections: 3_000_000 };
    let medium_layout = MediumNet::<f32>::new(&MediumConfig::default()).unwrap().layout();
    match GpuRenderer::new(&mut ctx, cap300k).map_err(VulkanRenderError::from).and_then(|mut r| r.enable_medium(&mut ctx, MediumConfig::default().grid_step_px, medium_layout)) {
        Ok(_) => {}
        Err(e) => println!("mapper buffers for 640x480, 300k Gaussians, 3M intersections do not fit: {e}"),
    }
    println!(
        "mapper buffers (render, losses, Adam moments, medium network) for 640x480, 300k Gaussians, 3M intersections: {:.1} MiB of the {} MiB arena",
        (ctx.arena_used_bytes() - mark) as f64 / (1 << 20) as f64,
        ctx.arena_capacity_bytes() >> 20
    );
    ctx.arena_reset_to(mark);
    let config = RenderConfig::default();
    let variants = std::env::args().any(|a| a == "--variants");
    let mapper_only = std::env::args().any(|a| a == "--mapper-only");
    let timeline = std::env::args().any(|a| a == "--timeline");
    let sizes: &[(usize, usize)] = if quick { &[(320, 240)] } else { &[(320, 240), (640, 480)] };
    // `--gaussians N`: that count only (with `--quick`: at 320x240).
    let args: Vec<String> = std::env::args().collect();
    let only: Option<usize> = args.iter().position(|a| a == "--gaussians").and_then(|i| args.get(i + 1)).map(|v| v.parse().expect("--gaussians N"));
    let only = only.map(|n| [n]);
    let counts: &[usize] = match &only {
        Some(n) => n,
        None if quick => &[20_000],
        None => &[20_000, 100_000],
    };
    for &(w, h) in sizes.iter().filter(|_| !mapper_only) {
        let cam = camera(w, h, 0.5 * w as f64 / 35f64.to_radians().tan());
        let cam_from_world = world_from_cam().inverse();
        for &n in counts {
            let mut rng = Rng::new(n as u64);
            let gaussians = random_gaussians(&mut rng, n, n, &cam, &world_from_cam(), (1.0, 10.0), (0.7, 4.0), (-2.0, 3.0));
            let medium = random_medium(&mut rng, w, h);
            let mut out = RenderOutput::new(w, h);
            let mut cap = RasterCapacity { width: w, height: h, max_gaussians: n, max_intersections: 4 * n };
            let mut ws = RasterWorkspace::new(cap).unwrap();
            let stats = match ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out) {
                Err(RenderError::TileOverflow { needed, .. }) => {
                    cap.max_intersections = needed as usize;
                    ws = RasterWorkspace::new(cap).unwrap();
                    ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out).unwrap()
                }
                other => other.unwrap(),
            };
            let up = random_upstream(&mut rng, w, h);
            let mut grads = GaussianGrads::with_capacity(n);
            grads.reset(n).unwrap();
            let mut medium_grads = MediumPlanes::new(w, h);
            ws.backward(&gaussians, &medium, &out, &up, &mut grads, &mut medium_grads).unwrap();
            let mark = ctx.arena_used_bytes();
            let mut gpu = GpuRenderer::new(&mut ctx, cap).unwrap();
            let used_mib = (ctx.arena_used_bytes() - mark) as f64 / (1 << 20) as f64;
            let mut gpu_out = RenderOutput::new(w, h);
            let mut gpu_grads = GaussianGrads::with_capacity(n);
            gpu_grads.reset(n).unwrap();
            let mut gpu_medium_grads = MediumPlanes::new(w, h);
            gpu.forward(&mut ctx, &gaussians, &cam, &cam_from_world, &medium, &config, &mut gpu_out).unwrap();
            gpu.backward(&mut ctx, &gaussians, &medium, &gpu_out, &up, &mut gpu_grads, &mut gpu_medium_grads).unwrap();
            ctx.reset_profile();
            let (mut cpu_f, mut cpu_b, mut gpu_f, mut gpu_b) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for _ in 0..runs {
                grads.reset(n).unwrap();
                gpu_grads.reset(n).unwrap();
                let t0 = Instant::now();
                ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out).unwrap();
                let t1 = Instant::now();
                ws.backward(&gaussians, &medium, &out, &up, &mut grads, &mut medium_grads).unwrap();
                let t2 = Instant::now();
                gpu.forward(&mut ctx, &gaussians, &cam, &cam_from_world, &medium, &config, &mut gpu_out).unwrap();
                let t3 = Instant::now();
                gpu.backward(&mut ctx, &gaussians, &medium, &gpu_out, &up, &mut gpu_grads, &mut gpu_medium_grads).unwrap();
                let t4 = Instant::now();
                cpu_f.push(t1 - t0);
                cpu_b.push(t2 - t1);
                gpu_f.push(t3 - t2);
                gpu_b.push(t4 - t3);
            }
            let err = out.colour.data.iter().zip(&gpu_out.colour.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            let (cf, cb, gf, gb) = (median_ms(&mut cpu_f), median_ms(&mut cpu_b), median_ms(&mut gpu_f), median_ms(&mut gpu_b));
            println!(
                "{w}x{h}, {n} Gaussians ({} visible, {} intersections): forward+backward CPU {:8.2} ms ({cf:.2} + {cb:.2}), \
                 Vulkan {:8.2} ms ({gf:.2} + {gb:.2}) (CPU/Vulkan {:.2}x); colour max abs diff {err:.1e}",
                stats.visible,
                stats.intersections,
                cf + cb,
                gf + gb,
                (cf + cb) / (gf + gb)
            );
            println!("    host side per forward+backward: {}", ctx.host_stats().describe_per(runs as u64));
            for (k, d, ms) in ctx.profile().rows() {
                println!("    {:<48} {:8.3} ms per iteration ({} dispatches)", k.name(), ms / runs as f64, d / runs as u64);
            }
            // The backward in deterministic mode (no float atomics), same inputs.
            if !ctx.deterministic() {
                ctx.set_deterministic(true);
                let before = ctx.profile().clone();
                let mut det_b = Vec::new();
                for _ in 0..runs {
                    gpu_grads.reset(n).unwrap();
                    let t = Instant::now();
                    gpu.backward(&mut ctx, &gaussians, &medium, &gpu_out, &up, &mut gpu_grads, &mut gpu_medium_grads).unwrap();
                    det_b.push(t.elapsed());
                }
                ctx.set_deterministic(false);
                let db = median_ms(&mut det_b);
                println!("    backward in deterministic mode (fixed-order reduction instead of float atomics): {db:.2} ms ({:.2}x the atomic backward)", db / gb);
                let k = Kernel::RasterizeBackwardRasterizeBackward as usize;
                let ms = (ctx.profile().total_ns[k] - before.total_ns[k]) * 1e-6 / runs as f64;
                println!("    {:<48} {ms:8.3} ms per iteration (deterministic)", Kernel::RasterizeBackwardRasterizeBackward.name());
            }
            // The atomic backward with the other `pixel_pairs` setting, same inputs.
            if !ctx.deterministic() {
                let was = gpu.set_pixel_pairs(!gpu.pixel_pairs());
                let before = ctx.profile().clone();
                let mut other_b = Vec::new();
                for _ in 0..runs {
                    gpu_grads.reset(n).unwrap();
                    let t = Instant::now();
                    gpu.backward(&mut ctx, &gaussians, &medium, &gpu_out, &up, &mut gpu_grads, &mut gpu_medium_grads).unwrap();
                    other_b.push(t.elapsed());
                }
                let ob = median_ms(&mut other_b);
                let which = if was { "one pixel per thread" } else { "pixel pairs" };
                println!("    backward with {which}: {ob:.2} ms ({:.2}x the backward above)", ob / gb);
                for (k, info) in KERNELS.iter().enumerate() {
                    let (d, ms) = (ctx.profile().dispatches[k], ctx.profile().total_ns[k] * 1e-6);
                    let (d0, ns0) = (before.dispatches[k], before.total_ns[k]);
                    if d > d0 && info.name().starts_with("rasterize_backward.rasterize") {
                        println!("    {:<48} {:8.3} ms per iteration ({which})", info.name(), (ms - ns0 * 1e-6) / runs as f64);
                    }
                }
                gpu.set_pixel_pairs(was);
            }
            println!("    GPU buffers of this renderer: {used_mib:.1} MiB of the {} MiB arena", ctx.arena_capacity_bytes() >> 20);
            ctx.arena_reset_to(mark);
        }
    }
    // The device is released for the mappers, which open their own.
    drop(ctx);
    for &(w, h) in sizes {
        for &n in counts {
            mapper_step(w, h, n, runs, board.budgets.gpu_mb, variants, timeline);
        }
    }
}

/// A kernel variant of the Vulkan mapper switched against the device's default: the
/// CPU-device variants on a GPU, the GPU kernels on a CPU device (`--variants`).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Switch {
    None,
    SortSerial,
    AtomicsPerGaussian,
    MediumSerial,
    SlidingSsim,
    AdamQuads,
    SpinWait,
    NoPlanAhead,
}

impl Switch {
    const ALL: [Switch; 7] = [Switch::SortSerial, Switch::AtomicsPerGaussian, Switch::MediumSerial, Switch::SlidingSsim, Switch::AdamQuads, Switch::SpinWait, Switch::NoPlanAhead];

    /// Sets the variant on `r` (and `ctx`) to the opposite of the device's default (`is_cpu`;
    /// the fence waits: on); returns its label. (`NoPlanAhead` is the mapper's: `label` only.)
    fn apply(self, r: &mut GpuRenderer, ctx: &mut GpuContext, is_cpu: bool) -> String {
        let on = !is_cpu;
        let name = match self {
            Switch::None => return String::new(),
            Switch::SortSerial => {
                r.fwd.binning.sort.serial = Some(on);
                "radix sort by one invocation per block"
            }
            Switch::AtomicsPerGaussian => {
                r.raster_backward.atomics_per_gaussian = Some(on);
                "backward atomics per Gaussian"
            }
            Switch::MediumSerial => {
                match r.medium.as_mut() {
                    Some(m) => m.serial = Some(on),
                    None => return "no medium network on the device".into(),
                }
                "medium network by one invocation per node"
            }
            Switch::SlidingSsim => {
                r.loss.sliding_ssim = Some(on);
                "sliding-window SSIM"
            }
            Switch::AdamQuads => {
                r.adam.quads = Some(on);
                "Adam by four Gaussians per invocation"
            }
            Switch::SpinWait => {
                ctx.set_spin_wait(true);
                return "fence waits polled (spin wait)".into();
            }
            Switch::NoPlanAhead => return "no geometry submitted ahead".into(),
        };
        format!("{name} {}", if on { "on" } else { "off" })
    }
}

/// Median ms of `Mapper::step_on` on the CPU mapper and on the Vulkan mapper with one and two
/// pixels per thread in the rasterisers (`GpuRenderer::set_pixel_pairs`), for `n` random Gaussians
/// at `w x h`, one keyframe (the CPU render of the map, no tracked depth), no densification.
/// With `variants`, also the Vulkan mapper with each CPU-device kernel variant switched
/// against the device's default ([`Switch`]), one at a time. Each step is
/// `step_on_then(0, Some(0))`, as `Mapper::iterate` steps with the keyframe it will draw next:
/// the Vulkan renderer submits the next step's geometry after each step's Adam.
fn mapper_step(w: usize, h: usize, n: usize, runs: usize, gpu_mb: u32, variants: bool, timeline: bool) {
    let cam = camera(w, h, 0.5 * w as f64 / 35f64.to_radians().tan());
    let mut rng = Rng::new(n as u64);
    let gaussians = random_gaussians(&mut rng, n, n, &cam, &world_from_cam(), (1.0, 10.0), (0.7, 4.0), (-2.0, 3.0));
    let config = MapperConfig { densify_every: 0, intersections_per_gaussian: 16, ..MapperConfig::default() };
    let capacity = MapperCapacity { max_gaussians: n, max_keyframes: 2, width: w, height: h };
    let mut plan = vec![(MapperDevice::Cpu, None, Switch::None), (MapperDevice::Vulkan, Some(false), Switch::None), (MapperDevice::Vulkan, Some(true), Switch::None)];
    if variants {
        plan.extend(Switch::ALL.iter().map(|&s| (MapperDevice::Vulkan, None, s)));
    }
    let mut mappers = Vec::new();
    for (device, pairs, switch) in plan {
        let mut m = Mapper::new(config.clone(), capacity).unwrap();
        let options = GpuOptions::with_budget_mb(gpu_mb);
        let what = m.use_device(device, &options).unwrap();
        if let (Some(p), Some((r, _))) = (pairs, m.gpu_renderer_mut()) {
            r.set_pixel_pairs(p);
        }
        if device == MapperDevice::Vulkan && !m.renders_on_vulkan() {
            println!("mapper step {w}x{h}, {n} Gaussians: no Vulkan mapper ({what})");
            return;
        }
        let is_cpu = m.gpu().is_some_and(|g| g.info().is_cpu());
        m.set_plan_ahead(switch != Switch::NoPlanAhead);
        let pairs_now = m.gpu_renderer_mut().map(|(r, _)| r.pixel_pairs());
        let label = match (pairs_now, m.gpu_renderer_mut()) {
            (Some(pairs), Some((r, ctx))) if switch != Switch::None => format!("{}, {}", if pairs { "pixel pairs" } else { "one pixel per thread" }, switch.apply(r, ctx, is_cpu)),
            (Some(true), _) => "pixel pairs".to_string(),
            (Some(false), _) => "one pixel per thread".to_string(),
            (None, _) => String::new(),
        };
        m.set_gaussians(&gaussians).unwrap();
        let render = m.render(&cam, &world_from_cam()).unwrap();
        let image = ImageRgb8 { width: w, height: h, data: render.colour.data.iter().map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect() };
        let kf = Keyframe {
            index: 0,
            t_ns: Timestamp(0),
            image,
            world_from_cam: world_from_cam(),
            camera: cam,
            inv_depth: PlaneF32 { width: w, height: h, data: vec![0.0; w * h] },
            inv_depth_variance: PlaneF32 { width: w, height: h, data: vec![f32::INFINITY; w * h] },
        };
        m.add_keyframe(&kf).unwrap();
        m.step_on_then(0, Some(0)).unwrap();
        m.set_gpu_timestamps(false);
        mappers.push((m, what, label, Vec::new()));
    }
    // The timed steps without timestamp queries, each mapper's back to back (on an H100,
    // alternating steps between the mappers, or between a mapper and the CPU mapper, made each
    // GPU step 0.15-0.35 ms slower: two devices' contexts switching, or a GPU left idle), in
    // two rounds for the Vulkan mappers, so both see the machine early and late.
    let host_before: Vec<_> = mappers.iter().map(|(m, _, _, _)| m.gpu().map(|g| g.host_stats())).collect();
    let vulkan = 1..mappers.len();
    let rounds = [0..1, vulkan.clone(), vulkan];
    for (round, group) in rounds.iter().enumerate() {
        for (m, _, _, samples) in &mut mappers[group.clone()] {
            let count = if round == 0 { runs } else { runs.div_ceil(2) };
            // The device's wait for the host counted between this block's steps only.
            if let Some(g) = m.gpu() {
                g.forget_idle();
            }
            for _ in 0..count {
                let t = Instant::now();
                m.step_on_then(0, Some(0)).unwrap();
                samples.push(t.elapsed());
            }
        }
    }
    // Then as many with timestamp queries, for the per-kernel tables (and their median, to
    // show what the queries cost).
    for ((m, _, which, samples), host_before) in mappers.iter_mut().zip(host_before) {
        let timed = samples.len() as u64;
        let host_after = m.gpu().map(|g| g.host_stats());
        // Steps left running (each step's submissions chain into the next) counted before.
        if let Some((_, ctx)) = m.gpu_renderer_mut() {
            ctx.finish().unwrap();
        }
        let timestamps = m.set_gpu_timestamps(true);
        let before = m.gpu().map(|g| g.profile().clone());
        let mut profiled = Vec::new();
        if timestamps {
            for _ in 0..runs {
                let t = Instant::now();
                m.step_on_then(0, Some(0)).unwrap();
                profiled.push(t.elapsed());
            }
            if let Some((_, ctx)) = m.gpu_renderer_mut() {
                ctx.finish().unwrap();
            }
        }
        if let (Some(before), Some(host_before), Some(host_after), Some(gpu)) = (before, host_before, host_after, m.gpu()) {
            println!("Vulkan mapper step {w}x{h}, {n} Gaussians ({which}), host side per step: {}", host_after.since(&host_before).describe_per(timed));
            if let Some((submitted, used)) = m.geometry_ahead_counts() {
                println!("Vulkan mapper step {w}x{h}, {n} Gaussians ({which}), the next step's geometry submitted ahead {submitted} times, used {used} times");
            }
            if timestamps {
                println!("Vulkan mapper step {w}x{h}, {n} Gaussians ({which}), with timestamp queries: {:.2} ms", median_ms(&mut profiled));
            }
            let profile = gpu.profile();
            let kernels_ms: f64 = (0..profile.kernels.len()).filter(|&k| profile.dispatches[k] > 0).map(|k| (profile.total_ns[k] - before.total_ns[k]) * 1e-6).sum::<f64>() / runs as f64;
            let spans = (profile.spans - before.spans).max(1);
            println!(
                "Vulkan mapper step {w}x{h}, {n} Gaussians ({which}), on the device: first kernel's start to last one's end {:.3} ms per step ({:.2} stretches), kernels {kernels_ms:.3} ms",
                (profile.span_ns - before.span_ns) * 1e-6 / runs as f64,
                spans as f64 / runs as f64
            );
            println!("Vulkan mapper step {w}x{h}, {n} Gaussians ({which}), per kernel:");
            for (k, info) in profile.kernels.iter().enumerate() {
                let (d, ms) = (profile.dispatches[k], profile.total_ns[k] * 1e-6);
                let (d0, ns0) = (before.dispatches[k], before.total_ns[k]);
                let ms = ms - ns0 * 1e-6;
                if d > d0 {
                    println!("    {:<48} {:8.3} ms per step ({} dispatches)", info.name(), ms / runs as f64, (d - d0) / runs as u64);
                }
            }
            if timeline && timestamps {
                println!("Vulkan mapper step {w}x{h}, {n} Gaussians ({which}), the last timed steps' dispatches, at most 120 (start, end, gap after the previous end, ms):");
                let mut end_before = 0.0f64;
                let count = gpu.last_timeline().count();
                for (k, start, end) in gpu.last_timeline().skip(count.saturating_sub(120)) {
                    println!("      {:<48} {start:7.3} {end:7.3} {:+7.3}", k.name(), start - end_before);
                    end_before = end_before.max(end);
                }
            }
        }
    }
    let times: Vec<(String, String, f64, usize)> =
        mappers.iter_mut().map(|(m, what, label, samples)| (what.clone(), label.clone(), median_ms(samples), m.gaussians().len())).collect();
    let (cpu, one, pairs) = (&times[0], &times[1], &times[2]);
    println!(
        "mapper step {w}x{h}, {n} Gaussians: CPU mapper {:8.2} ms, Vulkan mapper {:8.2} ms, with pixel pairs {:8.2} ms (CPU/Vulkan {:.2}x and {:.2}x, pairs/one {:.3}; {}; {}, {} and {} Gaussians after the steps)",
        cpu.2,
        one.2,
        pairs.2,
        cpu.2 / one.2,
        cpu.2 / pairs.2,
        pairs.2 / one.2,
        one.0,
        cpu.3,
        one.3,
        pairs.3
    );
    // The device's default pixel setting, against which the switched variants ran.
    if let Some(default) = times[1..3].iter().find(|t| times[3..].first().is_some_and(|v| v.1.starts_with(&t.1))) {
        for (_, label, ms, _) in &times[3..] {
            println!("mapper step {w}x{h}, {n} Gaussians, {label}: {ms:8.2} ms ({:.3}x the default, {}: {:.2} ms)", ms / default.2, default.1, default.2);
        }
    }
}
