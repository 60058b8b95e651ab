//! The mapper's stages on the Vulkan device (lavapipe in CI) against their CPU references in
//! `map`: projection (EWA) with the tile-count scan, tile binning + sort + ranges, the
//! rasteriser forward with the medium, the rasteriser backward with its per-Gaussian
//! reduction, the projection backward, Adam; the whole forward and backward. Sizes cross workgroup (256 threads) and tile
//! (16 px) boundaries.

use crate::gpu_common;
use crate::render_scene;

use duv_core::rng::Rng;
use duv_gpu::BindingKind;
use duv_map::backend::RenderBackend;
use duv_map::vulkan::Kernel;
use duv_map::gaussians::{GaussianGrads, GaussianParam, Gaussians, ParamGroup, PARAMS_PER_GAUSSIAN};
use duv_map::render::{
    emit_intersections, isect_key_bits, exclusive_scan, gather_sorted_gaussians, invert_permutation, project_gaussians, radix_sort_pairs, scan_blocks,
    sort_histogram_len, tile_ranges, DepthMode, ProjectedSplat, ProjectionSetup, RasterCapacity, RasterInputs, RasterWorkspace, RenderConfig, RenderError, RenderOutput, TileGrid, TileRect,
    project_backward, rasterize_backward, rasterize_forward, reduce_isect_grads, MediumPlanes, SplatGrad,
};
use duv_map::adam::{AdamGroup, AdamGroupConfig, StepConstants};
use duv_map::vulkan::{
    record_adam_step, GpuBinning, GpuForwardRenderer, GpuProjectBackward, GpuProjection, GpuRasterBackward, GpuRasterForward, GpuRenderer, VulkanRenderError, GRAD_FLOATS,
    splat_floats, SETUP_WORDS, SPLAT_FLOATS,
};
use render_scene::{camera, random_gaussians, random_medium, random_upstream, world_from_cam};

/// Forward values (pixels, conic entries, depth, opacity, colour): `|gpu - cpu| <= tol *
/// max(1, |cpu|)`. The GPU's exp/log/sqrt are not the host's correctly rounded ones.
const FORWARD_TOL: f64 = 1e-4;
/// Rendered images (colour, restored, depth, variance, alpha, final T): max abs error.
const RASTER_FORWARD_TOL: f64 = 1e-4;
/// Adam: parameters and moments, `|gpu - cpu| <= tol * max(1e-3, |cpu|)` (the GPU may fuse
/// multiply-adds and its sqrt is not correctly rounded).
const ADAM_REL_TOL: f64 = 1e-5;
/// Gradients (backward kernels): `|gpu - cpu| <= GRAD_REL_TOL * max(|cpu|, floor)` per value,
/// with `floor = GRAD_FLOOR_FRACTION * max |cpu|` over all values of the same field (e.g. every
/// Gaussian's dL/dconic.a, or every pixel's dL/dsigma_att). A gradient is a sum of per-pixel
/// terms of both signs (random upstream gradients); where they cancel, the sum is far smaller
/// than its terms and rounding of the terms (GPU exp, summation order: the GPU sums a tile's
/// pixels row by row, the CPU pixel by pixel) is a large relative error of a value that is
/// nearly zero on the field's scale. The floor makes such values count as absolute errors
/// against 1e-2 of the field's largest value; every other value is held to 1e-3 relative.
const GRAD_REL_TOL: f64 = 1e-3;
const GRAD_FLOOR_FRACTION: f64 = 1e-2;

fn grad_values(g: &SplatGrad<f32>) -> [f32; GRAD_FLOATS] {
    [
        g.mean2d[0],
        g.mean2d[1],
        g.conic[0],
        g.conic[1],
        g.conic[2],
        g.opacity,
        g.colour[0],
        g.colour[1],
        g.colour[2],
        g.z,
        g.mean2d_densify[0],
        g.mean2d_densify[1],
    ]
}

const GRAD_FIELDS: [&str; GRAD_FLOATS] =
    ["mean2d.x", "mean2d.y", "conic.a", "conic.b", "conic.c", "opacity", "colour.r", "colour.g", "colour.b", "z", "densify.x", "densify.y"];

/// Checks `got` against `want` (one field) with [`GRAD_REL_TOL`] and the floor of
/// [`GRAD_FLOOR_FRACTION`]; returns the worst `|gpu - cpu| / max(|cpu|, floor)`.
fn check_grads(what: &str, got: &[f32], want: &[f32]) -> f64 {
    let (i, err, floor) = gpu_common::worst_scaled_error(what, got, want, GRAD_FLOOR_FRACTION);
    assert!(err <= GRAD_REL_TOL, "{what}[{i}]: GPU {} vs CPU {} (scaled error {err:.3e}, floor {floor:.3e})", got[i], want[i]);
    err
}

fn close(a: f32, b: f32) -> bool {
    ((a - b).abs() as f64) <= FORWARD_TOL * (b.abs() as f64).max(1.0)
}

#[test]
fn kernel_table_matches_the_host_layouts() {
    // Pure table checks: no device needed.
    let project = Kernel::ProjectForwardProjectForward.info();
    assert_eq!(project.workgroup_size, [256, 1, 1]);
    let names: Vec<&str> = project.bindings.iter().map(|b| b.name).collect();
    assert_eq!(names, ["setup", "params", "splats", "rects", "tiles_touched"]);
    assert_eq!(project.bindings[0].bytes as usize, SETUP_WORDS * 4, "Setup struct vs projection_setup_words");
    assert_eq!(project.bindings[0].kind, BindingKind::StorageRead);
    assert_eq!(project.bindings[3].bytes, 16, "rects are vec4<u32> = [u32; 4]");
    assert_eq!(project.bindings[3].kind, BindingKind::StorageReadWrite);
    let sort = Kernel::RadixSortScatter.info();
    assert_eq!(sort.bindings[0].bytes, 8, "sort keys are vec2<u32> = u64");
    assert_eq!(sort.immediate_bytes, 16);
    assert_eq!(Kernel::PrefixSumScanAdd.info().immediate_bytes, 16);
    for k in [Kernel::RadixSortScatterSerial, Kernel::RadixSortHistogramSerial] {
        assert_eq!(k.info().workgroup_size, [duv_map::vulkan::ops::SERIAL_SCATTER_BLOCKS as u32, 1, 1], "{}: blocks per workgroup", k.name());
    }
    assert_eq!(PARAMS_PER_GAUSSIAN, 23, "params layout of project_forward.wgsl");
    for k in Kernel::all() {
        assert!(!k.info().spirv.is_empty() && k.info().spirv.len() % 4 == 0, "{}: SPIR-V", k.name());
    }
}

#[test]
fn projection_matches_project_gaussians() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("projection_matches_project_gaussians") else { return };
    let (w, h) = (150, 97); // 10 x 7 tiles, partial tiles on both axes
    let cam = camera(w, h, 120.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(5);
    let n_random = 256 * 12 + 37;
    let mut g = random_gaussians(&mut rng, n_random, n_random + 8, &cam, &world_from_cam, (0.5, 6.0), (0.5, 12.0), (-4.0, 5.0));
    // Culled cases: behind the camera, opacity below 1/255, zero rotation; plus one far off
    // to the side (projected, but no tile).
    let base = g.get(0);
    let behind = (world_from_cam * nalgebra::Point3::new(0.0, 0.0, -1.0)).coords;
    let side = (world_from_cam * nalgebra::Point3::new(40.0, 0.0, 2.0)).coords;
    for p in [
        GaussianParam { mean: [behind.x as f32, behind.y as f32, behind.z as f32], ..base },
        GaussianParam { opacity_logit: -8.0, ..base },
        GaussianParam { rotation: [0.0; 4], ..base },
        GaussianParam { mean: [side.x as f32, side.y as f32, side.z as f32], ..base },
    ] {
        g.push(&p).unwrap();
    }
    let n = g.len();
    let setup = ProjectionSetup::<f32>::new(&cam, &world_from_cam.inverse(), &RenderConfig::default()).unwrap();
    let grid = TileGrid::new(w, h);

    let mut cpu_splats = vec![ProjectedSplat::default(); n];
    let mut cpu_rects = vec![TileRect::default(); n];
    let mut cpu_counts = vec![0u32; n];
    project_gaussians(&g, &setup, &grid, &mut cpu_splats, &mut cpu_rects, &mut cpu_counts);

    let mut proj = GpuProjection::new(&mut ctx, n).unwrap();
    proj.upload(&mut ctx, &g).unwrap();
    proj.write_setup(&mut ctx, &setup, &grid, n).unwrap();
    ctx.begin().unwrap();
    proj.record(&mut ctx, n, 1 << 24).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut gpu_splats = vec![ProjectedSplat::default(); n];
    let mut gpu_rects = vec![TileRect::default(); n];
    let mut gpu_counts = vec![0u32; n];
    proj.read(&ctx, n, &mut gpu_splats, &mut gpu_rects, &mut gpu_counts).unwrap();

    let mut worst = 0.0f64;
    let mut visible = 0;
    for i in 0..n {
        let (a, b) = (splat_floats(&gpu_splats[i]), splat_floats(&cpu_splats[i]));
        for k in 0..SPLAT_FLOATS {
            assert!(close(a[k], b[k]), "Gaussian {i}, splat field {k}: GPU {} vs CPU {}", a[k], b[k]);
            worst = worst.max((a[k] - b[k]).abs() as f64 / (b[k].abs() as f64).max(1.0));
        }
        assert_eq!(gpu_rects[i], cpu_rects[i], "Gaussian {i}: tile rectangle");
        assert_eq!(gpu_counts[i], cpu_counts[i], "Gaussian {i}: tiles touched");
        visible += (cpu_counts[i] > 0) as usize;
    }
    // Behind the camera, opacity below 1/255, zero rotation, off to the side: no tile.
    assert_eq!(gpu_counts[n_random..], [0, 0, 0, 0], "the four culled Gaussians");
    assert!(visible > n_random / 2, "scene too sparse: {visible} of {n} visible");
    eprintln!("projection: {n} Gaussians, {visible} visible, worst scaled error {worst:.2e}");

    // The tile-count scan recorded after the projection.
    let mut cpu_offsets = vec![0u32; n + 1];
    let mut sums = vec![0u64; scan_blocks(n)];
    let total = exclusive_scan(&cpu_counts, &mut cpu_offsets, &mut sums, 1 << 24).unwrap();
    assert_eq!(proj.scan.result(&ctx).unwrap(), Ok(total));
    let mut gpu_offsets = vec![0u32; n + 1];
    ctx.read(&proj.isect_offsets, &mut gpu_offsets).unwrap();
    assert_eq!(gpu_offsets, cpu_offsets);
}

/// Every CPU stage up to the rasteriser's inputs.
struct CpuStages {
    splats: Vec<ProjectedSplat<f32>>,
    rects: Vec<TileRect>,
    offsets: Vec<u32>,
    total: usize,
    keys: Vec<u64>,
    slots: Vec<u32>,
    isect_gaussian: Vec<u32>,
    tile_offsets: Vec<u32>,
    sorted_gaussian: Vec<u32>,
    slot_to_sorted: Vec<u32>,
}

fn cpu_stages(g: &Gaussians, setup: &ProjectionSetup<f32>, grid: &TileGrid) -> CpuStages {
    let n = g.len();
    let mut splats = vec![ProjectedSplat::default(); n];
    let mut rects = vec![TileRect::default(); n];
    let mut counts = vec![0u32; n];
    project_gaussians(g, setup, grid, &mut splats, &mut rects, &mut counts);
    let mut offsets = vec![0u32; n + 1];
    let mut sums = vec![0u64; scan_blocks(n)];
    let total = exclusive_scan(&counts, &mut offsets, &mut sums, u32::MAX as u64).unwrap() as usize;
    let mut keys = vec![0u64; total];
    let mut slots = vec![0u32; total];
    let mut isect_gaussian = vec![0u32; total];
    emit_intersections(&splats, &rects, &offsets, grid, &mut keys, &mut slots, &mut isect_gaussian);
    let (mut kt, mut vt, mut hist) = (vec![0u64; total], vec![0u32; total], vec![0u32; sort_histogram_len(total)]);
    radix_sort_pairs(&mut keys, &mut slots, &mut kt, &mut vt, &mut hist, isect_key_bits(grid.num_tiles()));
    let mut tile_offsets = vec![0u32; grid.num_tiles() + 1];
    tile_ranges(&keys, &mut tile_offsets);
    let mut sorted_gaussian = vec![0u32; total];
    gather_sorted_gaussians(&slots, &isect_gaussian, &mut sorted_gaussian);
    let mut slot_to_sorted = vec![0u32; total];
    invert_permutation(&slots, &mut slot_to_sorted);
    CpuStages { splats, rects, offsets, total, keys, slots, isect_gaussian, tile_offsets, sorted_gaussian, slot_to_sorted }
}

#[test]
fn binning_sort_and_tile_ranges_match_the_cpu_stages() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("binning_sort_and_tile_ranges_match_the_cpu_stages") else { return };
    let (w, h) = (203, 141); // 13 x 9 tiles, partial tiles on both axes
    let cam = camera(w, h, 150.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(9);
    let n = 256 * 9 + 101;
    let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (0.5, 6.0), (0.5, 20.0), (-3.0, 5.0));
    let setup = ProjectionSetup::<f32>::new(&cam, &world_from_cam.inverse(), &RenderConfig::default()).unwrap();
    let grid = TileGrid::new(w, h);
    let cpu = cpu_stages(&g, &setup, &grid);
    let CpuStages { splats, rects, offsets, total, keys, slots, isect_gaussian, tile_offsets, sorted_gaussian, slot_to_sorted, .. } = cpu;
    assert!(total > 4096 * 2, "want several sort blocks, got {total} intersections");
    // GPU stages from the CPU projection (so that every kernel sees the same input).
    let proj = GpuProjection::new(&mut ctx, n).unwrap();
    let raw: Vec<f32> = splats.iter().flat_map(splat_floats).collect();
    ctx.write(&proj.splats, &raw).unwrap();
    let raw_rects: Vec<[u32; 4]> = rects.iter().map(|r| [r.x0, r.y0, r.x1, r.y1]).collect();
    ctx.write(&proj.rects, &raw_rects).unwrap();
    ctx.write(&proj.isect_offsets, &offsets).unwrap();
    // The scan's status as `record_exclusive_scan` leaves it: [overflow, total lo, hi, lo].
    ctx.write(&proj.scan.status, &[0, total as u32, 0, total as u32]).unwrap();
    let bin = GpuBinning::new(&mut ctx, total + 1000, grid.num_tiles()).unwrap();
    ctx.begin().unwrap();
    bin.record(&mut ctx, &proj, &grid, n).unwrap();
    ctx.submit_and_wait().unwrap();
    let read_u32 = |ctx: &duv_gpu::GpuContext, b: &duv_gpu::GpuBuffer<u32>, len: usize| {
        let mut v = vec![0u32; len];
        ctx.read(b, &mut v).unwrap();
        v
    };
    // The count and the indirect dispatch arguments the sort and the gathers were sized by.
    let t = total as u32;
    assert_eq!(read_u32(&ctx, &bin.isect_args, 8), [t, t.div_ceil(4096), 1, 1, t.div_ceil(256), 1, 1, 0], "intersection count");
    let mut gpu_keys = vec![0u64; total];
    ctx.read(&bin.keys, &mut gpu_keys).unwrap();
    assert_eq!(gpu_keys, keys, "sorted keys");
    assert_eq!(read_u32(&ctx, &bin.values, total), slots, "sorted slots");
    assert_eq!(read_u32(&ctx, &bin.isect_gaussian, total), isect_gaussian, "intersection Gaussians (unsorted slots)");
    assert_eq!(read_u32(&ctx, &bin.tile_offsets, grid.num_tiles() + 1), tile_offsets, "tile offsets");
    assert_eq!(read_u32(&ctx, &bin.sorted_gaussian, total), sorted_gaussian, "sorted Gaussians");
    assert_eq!(read_u32(&ctx, &bin.slot_to_sorted, total), slot_to_sorted, "slot to sorted");
    let rows: Vec<String> = ctx.profile().rows().map(|(k, d, ms)| format!("{} x{d}: {ms:.2} ms", k.name())).collect();
    eprintln!("{total} intersections; kernel times: {}", rows.join(", "));
}

#[test]
fn binning_writes_nothing_after_an_overflow() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("binning_writes_nothing_after_an_overflow") else { return };
    let (w, h) = (64, 48);
    let cam = camera(w, h, 60.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(3);
    let n = 300;
    let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (0.5, 4.0), (2.0, 10.0), (0.0, 3.0));
    let setup = ProjectionSetup::<f32>::new(&cam, &world_from_cam.inverse(), &RenderConfig::default()).unwrap();
    let grid = TileGrid::new(w, h);
    let mut proj = GpuProjection::new(&mut ctx, n).unwrap();
    let bin = GpuBinning::new(&mut ctx, 64, grid.num_tiles()).unwrap();
    proj.upload(&mut ctx, &g).unwrap();
    proj.write_setup(&mut ctx, &setup, &grid, n).unwrap();
    ctx.write(&bin.keys, &[u64::MAX; 64]).unwrap();
    ctx.begin().unwrap();
    proj.record(&mut ctx, n, bin.max_intersections).unwrap();
    ctx.submit_and_wait().unwrap();
    let needed = match proj.scan.result(&ctx).unwrap() {
        Err(needed) => needed,
        Ok(total) => panic!("{total} intersections fit in 64: the test needs an overflow"),
    };
    // The CPU projection gives the same size needed.
    let (mut s, mut r, mut c) = (vec![ProjectedSplat::default(); n], vec![TileRect::default(); n], vec![0u32; n]);
    project_gaussians(&g, &setup, &grid, &mut s, &mut r, &mut c);
    assert_eq!(needed, c.iter().map(|&v| v as u64).sum::<u64>());
    // Binning after the flagged scan writes no key, counts no intersection (so sorts and
    // gathers none) and leaves every tile empty.
    ctx.begin().unwrap();
    bin.record(&mut ctx, &proj, &grid, n).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut keys = vec![0u64; 64];
    ctx.read(&bin.keys, &mut keys).unwrap();
    assert!(keys.iter().all(|&k| k == u64::MAX), "keys written after an overflow");
    let mut args = [7u32; 8];
    ctx.read(&bin.isect_args, &mut args).unwrap();
    assert_eq!(args, [0, 0, 1, 1, 0, 1, 1, 0], "intersection count after an overflow");
    let mut offsets = vec![7u32; grid.num_tiles() + 1];
    ctx.read(&bin.tile_offsets, &mut offsets).unwrap();
    assert!(offsets.iter().all(|&o| o == 0), "tiles not empty after an overflow: {offsets:?}");
}

#[test]
fn rasterize_forward_matches_the_cpu_rasteriser() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("rasterize_forward_matches_the_cpu_rasteriser") else { return };
    for (mode, seed) in [(DepthMode::InverseDepth, 21), (DepthMode::Depth, 22)] {
        let (w, h) = (117, 83); // 8 x 6 tiles, partial tiles on both axes
        let cam = camera(w, h, 100.0);
        let world_from_cam = world_from_cam();
        let mut rng = Rng::new(seed);
        // Enough overlap that some tiles hold more than one 256-splat batch and blending
        // terminates early (T < 1e-4) in places.
        let n = 1500;
        let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (0.5, 6.0), (1.0, 14.0), (-1.0, 6.0));
        let medium = random_medium(&mut rng, w, h);
        let setup = ProjectionSetup::<f32>::new(&cam, &world_from_cam.inverse(), &RenderConfig::default()).unwrap();
        let grid = TileGrid::new(w, h);
        let cpu = cpu_stages(&g, &setup, &grid);
        let longest = cpu.tile_offsets.windows(2).map(|p| p[1] - p[0]).max().unwrap();
        assert!(longest > 256, "want a tile with more than one batch, longest has {longest}");
        let intrinsics = [cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32];
        let inputs = RasterInputs {
            splats: &cpu.splats,
            sorted_gaussian: &cpu.sorted_gaussian,
            tile_offsets: &cpu.tile_offsets,
            grid,
            intrinsics,
            depth_mode: mode,
        };
        let mut want = RenderOutput::new(w, h);
        rasterize_forward(&inputs, &medium, &mut want);

        let arena_mark = ctx.arena_used_bytes();
        let proj = GpuProjection::new(&mut ctx, n).unwrap();
        let bin = GpuBinning::new(&mut ctx, cpu.total, grid.num_tiles()).unwrap();
        let mut raster = GpuRasterForward::new(&mut ctx, w * h).unwrap();
        let raw: Vec<f32> = cpu.splats.iter().flat_map(splat_floats).collect();
        ctx.write(&proj.splats, &raw).unwrap();
        ctx.write(&bin.sorted_gaussian, &cpu.sorted_gaussian).unwrap();
        ctx.write(&bin.tile_offsets, &cpu.tile_offsets).unwrap();
        raster.upload_medium(&mut ctx, &medium).unwrap();
        // One pixel per thread and two (`rasterize_pairs`): the same arithmetic per pixel.
        for pairs in [false, true] {
            raster.pixel_pairs = pairs;
            ctx.begin().unwrap();
            raster.record(&mut ctx, &proj.splats, &bin, &grid, intrinsics, mode).unwrap();
            ctx.submit_and_wait().unwrap();
            let mut got = RenderOutput::new(w, h);
            raster.read(&ctx, &mut got).unwrap();
            let planes: [(&str, &[f32], &[f32]); 6] = [
                ("colour", &got.colour.data, &want.colour.data),
                ("restored", &got.restored.data, &want.restored.data),
                ("depth", &got.depth.data, &want.depth.data),
                ("depth_var", &got.depth_var.data, &want.depth_var.data),
                ("alpha", &got.alpha.data, &want.alpha.data),
                ("final_t", &got.final_t.data, &want.final_t.data),
            ];
            for (name, a, b) in planes {
                let (i, err) = a.iter().zip(b).map(|(x, y)| (x - y).abs() as f64).enumerate().fold((0, 0.0), |m, (i, e)| if e > m.1 { (i, e) } else { m });
                eprintln!("{mode:?} pairs {pairs} {name}: max abs error {err:.2e}");
                assert!(err <= RASTER_FORWARD_TOL, "{mode:?} pairs {pairs} {name}: max abs error {err:.3e} at element {i} (GPU {}, CPU {})", a[i], b[i]);
            }
            let ends_differ = got.isect_end.iter().zip(&want.isect_end).filter(|(a, b)| a != b).count();
            assert_eq!(ends_differ, 0, "{mode:?} pairs {pairs}: {ends_differ} pixels stop blending at a different splat");
        }
        ctx.arena_reset_to(arena_mark);
    }
}

#[test]
fn rasterize_backward_matches_the_cpu_reference() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("rasterize_backward_matches_the_cpu_reference") else { return };
    let table = Kernel::RasterizeBackwardRasterizeBackward.info();
    assert_eq!(table.workgroup_size, [256, 1, 1]);
    let names: Vec<&str> = table.bindings.iter().map(|b| b.name).collect();
    assert_eq!(names, [
        "splats",
        "sorted_gaussian",
        "tile_offsets",
        "c_med",
        "sigma_att",
        "sigma_bs",
        "fwd_scalars",
        "fwd_isect_end",
        "up_colour",
        "up_restored",
        "up_scalars",
        "partials",
        "partial_pixels",
        "grad_c_med",
        "grad_sigma_att",
        "grad_sigma_bs"
    ]);
    assert!(!table.float_atomics);
    // The atomic variants: the same buffers, their sums through atomic views of the partials.
    let mut want_names: Vec<&str> = names.iter().filter(|n| !n.starts_with("partial")).copied().collect();
    want_names.extend(["partials_sum", "partial_pixels_sum"]);
    for kernel in [Kernel::RasterizeBackwardRasterizeBackwardAtomic, Kernel::RasterizeBackwardRasterizeBackwardAtomicScatter] {
        let atomic = kernel.info();
        assert!(atomic.float_atomics, "{}", kernel.name());
        let atomic_names: Vec<&str> = atomic.bindings.iter().map(|b| b.name).collect();
        assert_eq!(atomic_names, want_names, "{}", kernel.name());
    }
    let reduce: Vec<&str> = Kernel::RasterizeBackwardReduceIsectGrads.info().bindings.iter().map(|b| b.name).collect();
    assert_eq!(reduce, ["isect_offsets", "slot_to_sorted", "in_partials", "in_partial_pixels", "splat_grads", "splat_pixels", "isect_count"]);
    let zero: Vec<&str> = Kernel::RasterizeBackwardZeroPartials.info().bindings.iter().map(|b| b.name).collect();
    assert_eq!((zero, Kernel::RasterizeBackwardZeroPartials.info().immediate_bytes), (vec!["partials", "partial_pixels", "isect_count"], 0));
    for (mode, seed) in [(DepthMode::InverseDepth, 23), (DepthMode::Depth, 24)] {
        let (w, h) = (117, 83); // 8 x 6 tiles, partial tiles on both axes
        let cam = camera(w, h, 100.0);
        let world_from_cam = world_from_cam();
        let mut rng = Rng::new(seed);
        // More than one 256-splat batch in some tiles, early termination in places, clamped
        // alphas (logits up to 6: opacity above 0.99), and more than one reduction workgroup.
        let n = 1500;
        let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (0.5, 6.0), (1.0, 14.0), (-1.0, 6.0));
        let medium = random_medium(&mut rng, w, h);
        let up = random_upstream(&mut rng, w, h);
        let setup = ProjectionSetup::<f32>::new(&cam, &world_from_cam.inverse(), &RenderConfig::default()).unwrap();
        let grid = TileGrid::new(w, h);
        let cpu = cpu_stages(&g, &setup, &grid);
        let longest = cpu.tile_offsets.windows(2).map(|p| p[1] - p[0]).max().unwrap();
        assert!(longest > 256, "want a tile with more than one batch, longest has {longest}");
        let intrinsics = [cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32];
        let inputs = RasterInputs {
            splats: &cpu.splats,
            sorted_gaussian: &cpu.sorted_gaussian,
            tile_offsets: &cpu.tile_offsets,
            grid,
            intrinsics,
            depth_mode: mode,
        };
        // The CPU forward is the input of both backward passes.
        let mut fwd = RenderOutput::new(w, h);
        rasterize_forward(&inputs, &medium, &mut fwd);
        assert!(fwd.final_t.data.iter().any(|&t| t < 2e-4), "{mode:?}: want pixels where blending terminates early");
        let mut want_partials = vec![SplatGrad::default(); cpu.total];
        let mut want_medium = MediumPlanes::new(w, h);
        rasterize_backward(&inputs, &medium, &fwd, &up, &mut want_partials, &mut want_medium);
        let mut want = vec![SplatGrad::default(); n];
        reduce_isect_grads(&cpu.offsets, &cpu.slot_to_sorted, &want_partials, &mut want);

        let arena_mark = ctx.arena_used_bytes();
        let proj = GpuProjection::new(&mut ctx, n).unwrap();
        let bin = GpuBinning::new(&mut ctx, cpu.total, grid.num_tiles()).unwrap();
        let mut raster = GpuRasterForward::new(&mut ctx, w * h).unwrap();
        let mut bwd = GpuRasterBackward::new(&mut ctx, w * h, cpu.total, n).unwrap();
        let raw: Vec<f32> = cpu.splats.iter().flat_map(splat_floats).collect();
        ctx.write(&proj.splats, &raw).unwrap();
        ctx.write(&proj.isect_offsets, &cpu.offsets).unwrap();
        ctx.write(&bin.sorted_gaussian, &cpu.sorted_gaussian).unwrap();
        ctx.write(&bin.tile_offsets, &cpu.tile_offsets).unwrap();
        ctx.write(&bin.slot_to_sorted, &cpu.slot_to_sorted).unwrap();
        // The intersection count and dispatch arguments `intersection_count` would write.
        let t = cpu.total as u32;
        ctx.write(&bin.isect_args, &[t, t.div_ceil(4096), 1, 1, t.div_ceil(256), 1, 1, 0]).unwrap();
        raster.upload_medium(&mut ctx, &medium).unwrap();
        raster.upload_output(&mut ctx, &fwd).unwrap();
        bwd.upload_upstream(&mut ctx, &up).unwrap();
        // Deterministic mode (reductions), then float atomics where the device has them, with
        // the subgroup sums the device's subgroup size picks and with the reduce-scatter
        // forced (lavapipe's 8 lanes would not take it otherwise).
        // Each atomic kernel with one pixel per thread and with two (`pixel_pairs`).
        // The atomic kernels adding per intersection (then reduced) and per Gaussian.
        let combos = [(true, false, false, false)]
            .into_iter()
            .chain([false, true].into_iter().flat_map(|per_gaussian| [(false, false, false, per_gaussian), (false, true, false, per_gaussian), (false, false, true, per_gaussian), (false, true, true, per_gaussian)]));
        for (deterministic, scatter, pairs, per_gaussian) in combos {
            bwd.force_reduce_scatter = scatter;
            bwd.atomics_per_gaussian = Some(per_gaussian);
            bwd.pixel_pairs = pairs;
            let kernel_name = match (ctx.set_deterministic(deterministic), scatter, pairs) {
                (true, _, _) => "deterministic",
                (false, false, false) => "atomic",
                (false, true, false) => "atomic, reduce-scatter",
                (false, false, true) => "atomic, pixel pairs",
                (false, true, true) => "atomic, pixel pairs, reduce-scatter",
            };
            let mode_name = format!("{kernel_name}{}", if per_gaussian { ", per Gaussian" } else { "" });
            let per_isect = !per_gaussian;
            if !deterministic && kernel_name == "deterministic" {
                eprintln!("{mode:?}: the device has no float atomics: rasterize_backward_atomic not run");
                continue;
            }
            // Garbage in every output, so a value the kernels fail to write is caught.
            ctx.begin().unwrap();
            for r in [bwd.partials.range(), bwd.splat_grads.range(), bwd.grad_c_med.range(), bwd.grad_sigma_att.range(), bwd.grad_sigma_bs.range()] {
                ctx.fill(r, 0x7fc0_0000).unwrap(); // NaN
            }
            ctx.fill(bwd.partial_pixels.range(), 0xdead).unwrap();
            ctx.fill(bwd.splat_pixels.range(), 0xdead).unwrap();
            bwd.record(&mut ctx, &proj.splats, &proj.isect_offsets, &bin, &raster, &grid, intrinsics, mode, n).unwrap();
            ctx.submit_and_wait().unwrap();
            let mut got = vec![SplatGrad::default(); n];
            let mut got_medium = MediumPlanes::new(w, h);
            bwd.read(&ctx, &mut got, &mut got_medium).unwrap();
            let mut got_partials = vec![SplatGrad::default(); cpu.total];
            bwd.read_partials(&ctx, &mut got_partials).unwrap();
            if deterministic {
                // No float atomics: a second run gives the same bits.
                ctx.begin().unwrap();
                bwd.record(&mut ctx, &proj.splats, &proj.isect_offsets, &bin, &raster, &grid, intrinsics, mode, n).unwrap();
                ctx.submit_and_wait().unwrap();
                let mut again = vec![SplatGrad::default(); n];
                let mut again_medium = MediumPlanes::new(w, h);
                bwd.read(&ctx, &mut again, &mut again_medium).unwrap();
                let bits = |v: &[SplatGrad<f32>]| v.iter().flat_map(|g| grad_values(g).map(f32::to_bits)).collect::<Vec<u32>>();
                assert_eq!(bits(&again), bits(&got), "{mode:?}: two GPU backward passes differ");
                assert_eq!(again_medium, got_medium, "{mode:?}: two GPU backward passes differ in the medium gradients");
            }

            // Pixel counts are integers: exact, per intersection and per Gaussian.
            let counts = |v: &[SplatGrad<f32>]| v.iter().map(|g| g.pixels).collect::<Vec<u32>>();
            if per_isect {
                assert_eq!(counts(&got_partials), counts(&want_partials), "{mode:?} {mode_name}: pixels per intersection");
            }
            assert_eq!(counts(&got), counts(&want), "{mode:?} {mode_name}: pixels per Gaussian");
            let touched = want.iter().filter(|g| g.pixels > 0).count();
            assert!(touched > n / 5, "{mode:?}: scene too sparse, {touched} of {n} Gaussians touch a pixel");
            let mut worst = [0.0f64; GRAD_FLOATS];
            for (f, name) in GRAD_FIELDS.iter().enumerate() {
                let field = |v: &[SplatGrad<f32>]| v.iter().map(|g| grad_values(g)[f]).collect::<Vec<f32>>();
                if per_isect {
                    check_grads(&format!("{mode:?} {mode_name} intersection {name}"), &field(&got_partials), &field(&want_partials));
                }
                worst[f] = check_grads(&format!("{mode:?} {mode_name} Gaussian {name}"), &field(&got), &field(&want));
            }
            let mut worst_medium = [0.0f64; 3];
            for (k, (name, a, b)) in [
                ("dL/dc_med", &got_medium.c_med.data, &want_medium.c_med.data),
                ("dL/dsigma_att", &got_medium.sigma_att.data, &want_medium.sigma_att.data),
                ("dL/dsigma_bs", &got_medium.sigma_bs.data, &want_medium.sigma_bs.data),
            ]
            .into_iter()
            .enumerate()
            {
                worst_medium[k] = check_grads(&format!("{mode:?} {mode_name} {name}"), a, b);
            }
            eprintln!(
                "{mode:?} {mode_name}: {} intersections, {touched} Gaussians touched; worst scaled error per field {:?}; medium c_med/att/bs {:?}",
                cpu.total,
                worst.map(|e| format!("{e:.1e}")),
                worst_medium.map(|e| format!("{e:.1e}")),
            );
        }
        ctx.set_deterministic(false);
        ctx.arena_reset_to(arena_mark);
    }
}

#[test]
fn project_backward_matches_the_cpu_reference() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("project_backward_matches_the_cpu_reference") else { return };
    let names: Vec<&str> = Kernel::ProjectBackwardProjectBackward.info().bindings.iter().map(|b| b.name).collect();
    assert_eq!(names, ["params", "setup", "splat_grads", "splat_pixels", "grads", "densify_grad_norm", "pixels_touched", "views"]);
    let (w, h) = (117, 83);
    let cam = camera(w, h, 100.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(27);
    let n_scene = 256 * 6 + 77;
    let mut g = random_gaussians(&mut rng, n_scene, n_scene + 64, &cam, &world_from_cam, (0.5, 6.0), (1.0, 14.0), (-1.0, 6.0));
    let medium = random_medium(&mut rng, w, h);
    let up = random_upstream(&mut rng, w, h);
    let setup = ProjectionSetup::<f32>::new(&cam, &world_from_cam.inverse(), &RenderConfig::default()).unwrap();
    let grid = TileGrid::new(w, h);
    // Splat gradients of a real backward pass (CPU), for the scene.
    let cpu = cpu_stages(&g, &setup, &grid);
    let inputs = RasterInputs {
        splats: &cpu.splats,
        sorted_gaussian: &cpu.sorted_gaussian,
        tile_offsets: &cpu.tile_offsets,
        grid,
        intrinsics: [cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32],
        depth_mode: DepthMode::InverseDepth,
    };
    let mut fwd = RenderOutput::new(w, h);
    rasterize_forward(&inputs, &medium, &mut fwd);
    let mut partials = vec![SplatGrad::default(); cpu.total];
    let mut medium_grads = MediumPlanes::new(w, h);
    rasterize_backward(&inputs, &medium, &fwd, &up, &mut partials, &mut medium_grads);
    let mut splat_grads = vec![SplatGrad::default(); n_scene];
    reduce_isect_grads(&cpu.offsets, &cpu.slot_to_sorted, &partials, &mut splat_grads);
    // Branches the scene rarely reaches, with made-up splat gradients: means beyond the
    // Jacobian's clamp on each side (x/z, y/z outside the field of view + 15%), a colour
    // channel clamped at 0, and a Gaussian with gradients but no pixel (must be left alone).
    let base = g.get(0);
    let at = |x: f64, y: f64, z: f64| {
        let p = world_from_cam * nalgebra::Point3::new(x * z, y * z, z);
        [p.x as f32, p.y as f32, p.z as f32]
    };
    let extra = [
        GaussianParam { mean: at(-1.2, 0.1, 3.0), ..base },
        GaussianParam { mean: at(1.3, -0.2, 2.0), ..base },
        GaussianParam { mean: at(0.2, -1.0, 4.0), ..base },
        GaussianParam { mean: at(-0.1, 1.1, 2.5), ..base },
        GaussianParam { f_dc: [-4.0, 0.5, 0.2], ..base },
        GaussianParam { f_dc: [0.3, -5.0, -6.0], ..base },
        base,
    ];
    for (k, p) in extra.iter().enumerate() {
        g.push(p).unwrap();
        let r = |rng: &mut Rng| rng.range(-1.0, 1.0) as f32;
        splat_grads.push(SplatGrad {
            mean2d: [r(&mut rng), r(&mut rng)],
            conic: [r(&mut rng) * 100.0, r(&mut rng) * 100.0, r(&mut rng) * 100.0],
            opacity: r(&mut rng),
            colour: [r(&mut rng), r(&mut rng), r(&mut rng)],
            z: r(&mut rng),
            mean2d_densify: [r(&mut rng), r(&mut rng)],
            pixels: if k + 1 == extra.len() { 0 } else { 1 + k as u32 },
        });
    }
    let n = g.len();
    let with_pixels = splat_grads.iter().filter(|s| s.pixels > 0).count();
    assert!(with_pixels > n / 5, "{with_pixels} of {n} Gaussians have a gradient");

    let mut want = GaussianGrads::with_capacity(n);
    want.reset(n).unwrap();
    project_backward(&g, &setup, &splat_grads, &mut want);

    let arena_mark = ctx.arena_used_bytes();
    let mut proj = GpuProjection::new(&mut ctx, n).unwrap();
    let raster = GpuRasterBackward::new(&mut ctx, 1, 1, n).unwrap();
    let mut pbwd = GpuProjectBackward::new(&mut ctx, n).unwrap();
    proj.upload(&mut ctx, &g).unwrap();
    proj.write_setup(&mut ctx, &setup, &grid, n).unwrap();
    let raw: Vec<f32> = splat_grads.iter().flat_map(grad_values).collect();
    ctx.write(&raster.splat_grads, &raw).unwrap();
    ctx.write(&raster.splat_pixels, &splat_grads.iter().map(|s| s.pixels).collect::<Vec<u32>>()).unwrap();
    let mut got = GaussianGrads::with_capacity(n);
    got.reset(n).unwrap();
    // NaN in the GPU buffers first, then the (zero) host gradients: the kernel adds to what
    // was uploaded.
    ctx.begin().unwrap();
    ctx.fill(pbwd.grads.range(), 0x7fc0_0000).unwrap();
    ctx.submit_and_wait().unwrap();
    pbwd.upload(&mut ctx, &got).unwrap();
    ctx.begin().unwrap();
    pbwd.record(&mut ctx, &proj, &raster, n).unwrap();
    ctx.submit_and_wait().unwrap();
    pbwd.read(&ctx, &mut got).unwrap();

    assert_eq!(got.pixels_touched(), want.pixels_touched(), "pixels touched");
    assert_eq!(got.views(), want.views(), "views");
    let untouched = n - 1;
    assert_eq!(got.get(untouched), GaussianParam::default(), "a Gaussian without pixels gets no gradient");
    assert_eq!(want.get(untouched), GaussianParam::default());
    let worst_norm = check_grads("densify_grad_norm", got.densify_grad_norm(), want.densify_grad_norm());
    let mut worst = Vec::new();
    for group in ParamGroup::ALL {
        let width = group.width();
        for c in 0..width {
            let field = |gr: &GaussianGrads| gr.group(group).chunks_exact(width).map(|v| v[c]).collect::<Vec<f32>>();
            let e = check_grads(&format!("{}[{c}]", group.name()), &field(&got), &field(&want));
            worst.push(format!("{}[{c}] {e:.1e}", group.name()));
        }
    }
    eprintln!("project_backward: {n} Gaussians, {with_pixels} with pixels; worst scaled errors: densify norm {worst_norm:.1e}, {}", worst.join(", "));

    // A second pass adds: every gradient doubles (x + x is exact), the counts too.
    ctx.begin().unwrap();
    pbwd.record(&mut ctx, &proj, &raster, n).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut twice = GaussianGrads::with_capacity(n);
    twice.reset(n).unwrap();
    pbwd.read(&ctx, &mut twice).unwrap();
    for group in ParamGroup::ALL {
        let doubled: Vec<f32> = got.group(group).iter().map(|v| 2.0 * v).collect();
        assert_eq!(twice.group(group), &doubled[..], "{}: a second pass must add", group.name());
    }
    let doubled: Vec<u32> = want.views().iter().map(|v| 2 * v).collect();
    assert_eq!(twice.views(), &doubled[..], "views after two passes");
    ctx.arena_reset_to(arena_mark);
}

#[test]
fn adam_step_matches_adam_group() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("adam_step_matches_adam_group") else { return };
    // 65535 * 256 + 3 * 256 + 5 values: more workgroups than one grid dimension holds.
    let items = (65535 * 256 + 3 * 256 + 5) / 3 + 1;
    let stride = 3;
    let n = items * stride;
    let config = AdamGroupConfig { lr: 0.01, ..AdamGroupConfig::default() };
    let mut group = AdamGroup::new(config, stride, items, items).unwrap();
    let mut rng = Rng::new(17);
    let mut cpu_params: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect();
    let arena_mark = ctx.arena_used_bytes();
    let values = ctx.alloc::<f32>("params", n).unwrap();
    let grads = ctx.alloc::<f32>("grads", n).unwrap();
    let m = ctx.alloc::<f32>("adam m", n).unwrap();
    let v = ctx.alloc::<f32>("adam v", n).unwrap();
    ctx.write(&values, &cpu_params).unwrap();
    ctx.begin().unwrap();
    ctx.fill(m.range(), 0).unwrap();
    ctx.fill(v.range(), 0).unwrap();
    ctx.submit_and_wait().unwrap();
    for step in 1..=3u64 {
        let g: Vec<f32> = (0..n).map(|i| if i % 7 == 0 { 0.0 } else { rng.range(-2.0, 2.0) as f32 }).collect();
        group.step(&mut cpu_params, &g).unwrap();
        ctx.write(&grads, &g).unwrap();
        ctx.begin().unwrap();
        record_adam_step(&mut ctx, &values, &grads, &m, &v, n, &StepConstants::new(&config, step)).unwrap();
        ctx.submit_and_wait().unwrap();
    }
    let (cpu_m, cpu_v) = group.moments();
    // The floor of the scale: m = beta1 m + (1 - beta1) g adds terms up to 0.2 that can
    // cancel, and a device that fuses it into an FMA (measured on an NVIDIA H100: m
    // -0.00045665205 against -0.00045663118, a few rounding steps of the terms) differs from
    // the CPU's two roundings by more than 1e-5 of the small result.
    for (name, buf, want, floor) in [("params", &values, &cpu_params[..], 1e-3), ("m", &m, &cpu_m[..n], 1e-2), ("v", &v, &cpu_v[..n], 1e-3)] {
        let mut got = vec![0.0f32; n];
        ctx.read(buf, &mut got).unwrap();
        let (i, err) = got
            .iter()
            .zip(want)
            .map(|(a, b)| (a - b).abs() as f64 / (b.abs() as f64).max(floor))
            .enumerate()
            .fold((0, 0.0), |acc, (i, e)| if e > acc.1 { (i, e) } else { acc });
        eprintln!("adam {name}: max scaled error {err:.2e}");
        assert!(err <= ADAM_REL_TOL, "adam {name}[{i}]: GPU {} vs CPU {} (scaled error {err:.2e})", got[i], want[i]);
    }
    ctx.arena_reset_to(arena_mark);
}

#[test]
fn gpu_forward_render_matches_raster_workspace() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("gpu_forward_render_matches_raster_workspace") else { return };
    let (w, h) = (160, 120);
    let cam = camera(w, h, 140.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(31);
    let n = 256 * 11 + 9;
    let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (1.0, 10.0), (0.7, 6.0), (-2.0, 3.0));
    let medium = random_medium(&mut rng, w, h);
    let config = RenderConfig::default();
    let cam_from_world = world_from_cam.inverse();
    let capacity = RasterCapacity { width: w, height: h, max_gaussians: n, max_intersections: 8 * n };
    let mut ws = RasterWorkspace::new(capacity).unwrap();
    let mut want = RenderOutput::new(w, h);
    let cpu_stats = ws.forward(&g, &cam, &cam_from_world, &medium, &config, &mut want).unwrap();
    let arena_mark = ctx.arena_used_bytes();
    let mut gpu = GpuForwardRenderer::new(&mut ctx, capacity).unwrap();
    let mut got = RenderOutput::new(w, h);
    let gpu_stats = gpu.forward(&mut ctx, &g, &cam, &cam_from_world, &medium, &config, &mut got).unwrap();
    assert_eq!((gpu_stats.visible, gpu_stats.intersections), (cpu_stats.visible, cpu_stats.intersections));
    for (name, a, b) in [
        ("colour", &got.colour.data, &want.colour.data),
        ("restored", &got.restored.data, &want.restored.data),
        ("depth", &got.depth.data, &want.depth.data),
        ("alpha", &got.alpha.data, &want.alpha.data),
    ] {
        let err = a.iter().zip(b.iter()).map(|(x, y)| (x - y).abs() as f64).fold(0.0, f64::max);
        eprintln!("whole forward {name}: max abs error {err:.2e}");
        assert!(err <= RASTER_FORWARD_TOL, "whole forward {name}: max abs error {err:.3e}");
    }
    // Too small an intersection buffer: the same overflow report as the CPU reference.
    let small = RasterCapacity { max_intersections: cpu_stats.intersections - 1, ..capacity };
    let mut gpu_small = GpuForwardRenderer::new(&mut ctx, small).unwrap();
    match gpu_small.forward(&mut ctx, &g, &cam, &cam_from_world, &medium, &config, &mut got) {
        Err(VulkanRenderError::Render(RenderError::TileOverflow { needed, capacity })) => {
            assert_eq!((needed as usize, capacity), (cpu_stats.intersections, cpu_stats.intersections - 1));
        }
        other => panic!("expected a tile overflow, got {other:?}"),
    }
    eprintln!("arena peak {} MiB of {} MiB", ctx.arena_peak_bytes() >> 20, ctx.arena_capacity_bytes() >> 20);
    ctx.arena_reset_to(arena_mark);
}

#[test]
fn gpu_forward_backward_matches_raster_workspace() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("gpu_forward_backward_matches_raster_workspace") else { return };
    let (w, h) = (160, 120);
    let cam = camera(w, h, 140.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(33);
    let n = 256 * 11 + 9;
    let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (1.0, 10.0), (0.7, 6.0), (-2.0, 3.0));
    let medium = random_medium(&mut rng, w, h);
    let up = random_upstream(&mut rng, w, h);
    let config = RenderConfig::default();
    let cam_from_world = world_from_cam.inverse();
    let capacity = RasterCapacity { width: w, height: h, max_gaussians: n, max_intersections: 8 * n };
    let mut ws = RasterWorkspace::new(capacity).unwrap();
    let mut want_out = RenderOutput::new(w, h);
    ws.forward(&g, &cam, &cam_from_world, &medium, &config, &mut want_out).unwrap();
    let mut want = GaussianGrads::with_capacity(n);
    want.reset(n).unwrap();
    let mut want_medium = MediumPlanes::new(w, h);
    ws.backward(&g, &medium, &want_out, &up, &mut want, &mut want_medium).unwrap();

    let arena_mark = ctx.arena_used_bytes();
    let mut gpu = GpuRenderer::new(&mut ctx, capacity).unwrap();
    let mut got_out = RenderOutput::new(w, h);
    let mut got = GaussianGrads::with_capacity(n);
    got.reset(n).unwrap();
    let mut got_medium = MediumPlanes::new(w, h);
    // Backward before any forward: the CPU reference's error.
    match gpu.backward(&mut ctx, &g, &medium, &got_out, &up, &mut got, &mut got_medium) {
        Err(VulkanRenderError::Render(RenderError::NoForward { .. })) => {}
        other => panic!("expected NoForward, got {other:?}"),
    }
    gpu.forward(&mut ctx, &g, &cam, &cam_from_world, &medium, &config, &mut got_out).unwrap();
    ctx.reset_profile();
    gpu.backward(&mut ctx, &g, &medium, &got_out, &up, &mut got, &mut got_medium).unwrap();
    let rows: Vec<String> = ctx.profile().rows().map(|(k, d, ms)| format!("{} x{d}: {ms:.2} ms", k.name())).collect();
    ctx.arena_reset_to(arena_mark);

    // The two forwards agree to RASTER_FORWARD_TOL, but where a splat's alpha is within
    // rounding of 1/255 at a pixel (or T within rounding of 1e-4), one side blends it and the
    // other does not: its pixel count differs by one. Such pixels must be rare.
    let ends_differ = got_out.isect_end.iter().zip(&want_out.isect_end).filter(|(a, b)| a != b).count();
    let count_diff: u64 = got.pixels_touched().iter().zip(want.pixels_touched()).map(|(a, b)| a.abs_diff(*b) as u64).sum();
    let count_total: u64 = want.pixels_touched().iter().map(|&v| v as u64).sum();
    assert!(count_total > (w * h) as u64, "the scene must cover the image");
    assert!(count_diff * 10_000 <= count_total, "pixel counts differ by {count_diff} of {count_total}");
    assert_eq!(got.views(), want.views(), "views");
    let mut worst = Vec::new();
    worst.push(format!("densify norm {:.1e}", check_grads("densify_grad_norm", got.densify_grad_norm(), want.densify_grad_norm())));
    for group in ParamGroup::ALL {
        let width = group.width();
        for c in 0..width {
            let field = |gr: &GaussianGrads| gr.group(group).chunks_exact(width).map(|v| v[c]).collect::<Vec<f32>>();
            let e = check_grads(&format!("whole backward {}[{c}]", group.name()), &field(&got), &field(&want));
            worst.push(format!("{}[{c}] {e:.1e}", group.name()));
        }
    }
    for (name, a, b) in [
        ("dL/dc_med", &got_medium.c_med.data, &want_medium.c_med.data),
        ("dL/dsigma_att", &got_medium.sigma_att.data, &want_medium.sigma_att.data),
        ("dL/dsigma_bs", &got_medium.sigma_bs.data, &want_medium.sigma_bs.data),
    ] {
        worst.push(format!("{name} {:.1e}", check_grads(&format!("whole backward {name}"), a, b)));
    }
    eprintln!(
        "whole backward: {ends_differ} pixels end elsewhere, pixel counts differ by {count_diff} of {count_total}; worst scaled errors: {}",
        worst.join(", ")
    );
    eprintln!("backward kernel times: {}", rows.join(", "));
}

/// No kernel uses float atomics (integer workgroup atomics only, in an order-independent
/// way), so two runs on one device give bit-identical images.
#[test]
fn forward_is_bit_identical_over_two_runs() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("forward_is_bit_identical_over_two_runs") else { return };
    let (w, h) = (96, 72);
    let cam = camera(w, h, 90.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(41);
    let n = 2000;
    let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam, (1.0, 8.0), (0.7, 8.0), (-2.0, 4.0));
    let medium = random_medium(&mut rng, w, h);
    let capacity = RasterCapacity { width: w, height: h, max_gaussians: n, max_intersections: 16 * n };
    let arena_mark = ctx.arena_used_bytes();
    let mut gpu = GpuForwardRenderer::new(&mut ctx, capacity).unwrap();
    let mut runs = [RenderOutput::new(w, h), RenderOutput::new(w, h)];
    for out in runs.iter_mut() {
        gpu.forward(&mut ctx, &g, &cam, &world_from_cam.inverse(), &medium, &RenderConfig::default(), out).unwrap();
    }
    let bits = |o: &RenderOutput| -> Vec<u32> {
        o.colour.data.iter().chain(&o.restored.data).chain(&o.depth.data).chain(&o.depth_var.data).chain(&o.alpha.data).map(|v| v.to_bits()).collect()
    };
    assert_eq!(bits(&runs[0]), bits(&runs[1]), "two GPU renders differ");
    assert_eq!(runs[0].isect_end, runs[1].isect_end);
    assert!(runs[0].alpha.data.iter().any(|&a| a > 0.5), "the scene must cover pixels");
    ctx.arena_reset_to(arena_mark);
}

#[test]
fn no_vulkan_device_falls_back_to_the_cpu_reference_and_other_errors_do_not() {
    // Pure policy: no device needed.
    let (w, h) = (48, 32);
    let capacity = RasterCapacity { width: w, height: h, max_gaussians: 100, max_intersections: 1000 };
    let unavailable = Err(duv_gpu::GpuError::NoDevice { seen: String::new() });
    let mut backend = RenderBackend::from_open_result(unavailable, capacity).unwrap();
    assert!(!backend.is_vulkan());
    let cam = camera(w, h, 40.0);
    let world_from_cam = world_from_cam();
    let mut rng = Rng::new(2);
    let g = random_gaussians(&mut rng, 50, 100, &cam, &world_from_cam, (1.0, 4.0), (1.0, 4.0), (0.0, 3.0));
    let medium = random_medium(&mut rng, w, h);
    let (mut a, mut b) = (RenderOutput::new(w, h), RenderOutput::new(w, h));
    backend.forward(&g, &cam, &world_from_cam.inverse(), &medium, &RenderConfig::default(), &mut a).unwrap();
    RasterWorkspace::new(capacity).unwrap().forward(&g, &cam, &world_from_cam.inverse(), &medium, &RenderConfig::default(), &mut b).unwrap();
    assert_eq!(a, b, "the fallback is the CPU reference");
    // A device that exists but was asked for wrongly is an error, not a silent fallback.
    let wrong = Err(duv_gpu::GpuError::NoMatchingDevice { env: duv_gpu::DEVICE_ENV, wanted: "nope".into(), seen: "0: llvmpipe".into() });
    match RenderBackend::from_open_result(wrong, capacity) {
        Err(VulkanRenderError::Gpu(duv_gpu::GpuError::NoMatchingDevice { wanted, .. })) => assert_eq!(wanted, "nope"),
        other => panic!("expected NoMatchingDevice, got {}", if other.is_ok() { "a backend".to_string() } else { "another error".into() }),
    }
}
