//! Shared helper of the GPU test binaries (`tests/gpu_*.rs`): opens the Vulkan device with
//! the `sim` board's GPU budget and logs device, driver and features. No device at all: a
//! loud skip locally, a failure when `CI` is set (CI runs on lavapipe, `.ci/run` installs it).
#![allow(dead_code)]

use std::path::Path;

use duv_core::config::Board;
use duv_gpu::{GpuContext, GpuOptions};

/// The device, or `None` (after a loud message) when no Vulkan device exists and `CI` is
/// unset. Any other failure (a kernel that does not build, the arena) fails the test.
pub fn gpu_or_skip(test: &str) -> Option<GpuContext> {
    let board = Board::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/sim.toml")).expect("boards/sim.toml");
    let mut options = GpuOptions::with_budget_mb(board.budgets.gpu_mb);
    options.pipeline_cache_dir = Some(std::env::temp_dir().join("duv-test-pipeline-cache"));
    match GpuContext::new(&options, &duv_map::vulkan::KERNELS) {
        Ok(ctx) => {
            eprintln!("[{test}] Vulkan device: {}; arena {} MiB", ctx.info(), ctx.arena_capacity_bytes() >> 20);
            Some(ctx)
        }
        Err(e) if e.is_unavailable() && std::env::var_os("CI").is_none() => {
            eprintln!("\n############################################################");
            eprintln!("## [{test}] SKIPPED: no Vulkan device ({e})");
            eprintln!("## install lavapipe (apt-get install mesa-vulkan-drivers) to run it");
            eprintln!("############################################################\n");
            None
        }
        Err(e) if e.is_unavailable() => panic!("[{test}] CI is set and no Vulkan device was found: {e}"),
        Err(e) => panic!("[{test}] opening the Vulkan device failed: {e}"),
    }
}

/// The worst scaled error of `got` against `want`: `(index, |got - want| / max(|want|,
/// floor), floor)` with `floor = floor_fraction * max |want|` (a NaN counts as the worst).
/// Panics when `want` is zero everywhere (nothing would be tested).
pub fn worst_scaled_error(what: &str, got: &[f32], want: &[f32], floor_fraction: f64) -> (usize, f64, f64) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let largest = want.iter().map(|v| v.abs() as f64).fold(0.0, f64::max);
    assert!(largest > 0.0, "{what}: the reference gradient is zero everywhere, nothing is tested");
    let floor = floor_fraction * largest;
    let (i, err) = got
        .iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs() as f64 / (w.abs() as f64).max(floor))
        .enumerate()
        .fold((0, 0.0), |m, (i, e)| if e > m.1 || e.is_nan() { (i, e) } else { m });
    (i, err, floor)
}
