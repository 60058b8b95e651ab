//! Forward render on the Vulkan device (`map::vulkan::GpuForwardRenderer`) against the CPU
//! reference (`RasterWorkspace::forward`) in the same run: 320x240 and 640x480 with 20k and
//! 100k random Gaussians (the scenes of `benches/render.rs`). Medians of several runs, the
//! GPU time including uploads and read-backs, then the per-kernel GPU timestamps.
//! The backward pass has no kernels yet, so this measures the forward only.
//!
//! Run: `cargo bench --bench gpu_render` (release; `DUV_VULKAN_DEVICE` picks the device).

#[path = "../tests/common/render_scene.rs"]
mod render_scene;

use std::path::Path;
use std::time::{Duration, Instant};

use duv::config::Board;
use duv::core::rng::Rng;
use duv::gpu::{GpuContext, GpuOptions};
use duv::map::render::{RasterCapacity, RasterWorkspace, RenderConfig, RenderError, RenderOutput};
use duv::map::vulkan::GpuForwardRenderer;
use render_scene::{camera, random_gaussians, random_medium, world_from_cam};

const RUNS: usize = 7;

fn median_ms(samples: &mut [Duration]) -> f64 {
    samples.sort();
    samples[samples.len() / 2].as_secs_f64() * 1e3
}

fn main() {
    let board = Board::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/sim.toml")).expect("boards/sim.toml");
    let mut ctx = match GpuContext::new(&GpuOptions::with_budget_mb(board.budgets.gpu_mb)) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("gpu_render: no Vulkan device, nothing to compare: {e}");
            return;
        }
    };
    println!("device: {}; CPU reference on {} rayon threads; median of {RUNS} runs", ctx.info(), rayon::current_num_threads());
    // Fixed GPU memory of the forward buffers for a 640x480 run with a 300k Gaussian cap and
    // room for 10 tile intersections per Gaussian (allocated, not used).
    let mark = ctx.arena_used_bytes();
    let cap300k = RasterCapacity { width: 640, height: 480, max_gaussians: 300_000, max_intersections: 3_000_000 };
    GpuForwardRenderer::new(&mut ctx, cap300k).unwrap();
    println!(
        "forward buffers for 640x480, 300k Gaussians, 3M intersections: {:.1} MiB of the {} MiB arena (Adam moments and gradients not included)",
        (ctx.arena_used_bytes() - mark) as f64 / (1 << 20) as f64,
        ctx.arena_capacity_bytes() >> 20
    );
    ctx.arena_reset_to(mark);
    let config = RenderConfig::default();
    for (w, h) in [(320usize, 240usize), (640, 480)] {
        let cam = camera(w, h, 0.5 * w as f64 / 35f64.to_radians().tan());
        let cam_from_world = world_from_cam().inverse();
        for n in [20_000usize, 100_000] {
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
            let mark = ctx.arena_used_bytes();
            let mut gpu = GpuForwardRenderer::new(&mut ctx, cap).unwrap();
            let used_mib = (ctx.arena_used_bytes() - mark) as f64 / (1 << 20) as f64;
            let mut gpu_out = RenderOutput::new(w, h);
            gpu.forward(&mut ctx, &gaussians, &cam, &cam_from_world, &medium, &config, &mut gpu_out).unwrap();
            ctx.reset_profile();
            let (mut cpu_t, mut gpu_t) = (Vec::new(), Vec::new());
            for _ in 0..RUNS {
                let t0 = Instant::now();
                ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out).unwrap();
                let t1 = Instant::now();
                gpu.forward(&mut ctx, &gaussians, &cam, &cam_from_world, &medium, &config, &mut gpu_out).unwrap();
                let t2 = Instant::now();
                cpu_t.push(t1 - t0);
                gpu_t.push(t2 - t1);
            }
            let err = out.colour.data.iter().zip(&gpu_out.colour.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            let (cpu_ms, gpu_ms) = (median_ms(&mut cpu_t), median_ms(&mut gpu_t));
            println!(
                "{w}x{h}, {n} Gaussians ({} visible, {} intersections): forward CPU {cpu_ms:8.2} ms, Vulkan {gpu_ms:8.2} ms \
                 (CPU/Vulkan {:.2}x); colour max abs diff {err:.1e}",
                stats.visible,
                stats.intersections,
                cpu_ms / gpu_ms
            );
            for (k, d, ms) in ctx.profile().rows() {
                println!("    {:<48} {:8.3} ms per forward ({} dispatches)", k.name(), ms / RUNS as f64, d / RUNS as u64);
            }
            println!("    GPU buffers of this renderer: {used_mib:.1} MiB of the {} MiB arena", ctx.arena_capacity_bytes() >> 20);
            ctx.arena_reset_to(mark);
        }
    }
}
