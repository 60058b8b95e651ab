//! The medium network on the Vulkan device (lavapipe in CI) against its CPU reference,
//! `MediumWorkspace::with_grid` (`map::medium`): the forward pass into the rasteriser's three
//! medium planes and the backward pass to the parameter gradient, on a direction grid (step 8,
//! a view that is no multiple of the step and crosses workgroup boundaries) and per pixel
//! (step 1). A second run is bit-identical; bad input is an error, not a panic.

use crate::gpu_common;

use std::time::Instant;

use duv_core::pose::so3_exp;
use duv_core::rng::Rng;
use duv_core::{PinholeCamera, RadTan, Se3};
use duv_gpu::{GpuContext, GpuError};
use duv_map::mapper::{nine_from_planes, planes_from_nine};
use duv_map::medium::{MediumConfig, MediumError, MediumLayout, MediumNet, MediumPlanes as MediumPlanes9, MediumWorkspace};
use duv_map::render::MediumPlanes;
use duv_map::vulkan::medium::{GpuMedium, GpuMediumError};
use duv_map::vulkan::GpuRasterForward;
use nalgebra::{Translation3, Vector3};

/// Forward planes: max `|gpu - cpu|` (the outputs are O(1); the GPU's sin, cos, exp and log
/// are not the host's correctly rounded ones).
const FORWARD_TOL: f64 = 1e-4;
/// Parameter gradient: `|gpu - cpu| <= GRAD_REL_TOL * max(|cpu|, floor)` per value, with
/// `floor = GRAD_FLOOR_FRACTION * max |cpu|` over the values of the same tensor (W1, b1, W2,
/// b2, the heads' W and b). Each value is a sum over nodes of terms of both signs (random
/// upstream gradients); where they cancel, rounding of the terms (GPU transcendentals,
/// summation order: chunks of nodes on the GPU, bands of node rows on the CPU) is a large
/// relative error of a value that is nearly zero on its tensor's scale.
const GRAD_REL_TOL: f64 = 1e-3;
const GRAD_FLOOR_FRACTION: f64 = 1e-3;

/// A network whose heads vary with the direction: the default initialisation with full-size
/// head weights, every parameter perturbed.
fn random_net(rng: &mut Rng, pe_frequencies: usize) -> MediumNet {
    let mut net = MediumNet::new(&MediumConfig { head_init_scale: 1.0, pe_frequencies, ..MediumConfig::default() }).unwrap();
    for p in net.params_mut() {
        *p += rng.range(-0.3, 0.3) as f32;
    }
    net
}

/// A turned camera off the origin with some lens distortion (the host undistorts per node).
fn view(rng: &mut Rng, width: usize, height: usize) -> (PinholeCamera, Se3) {
    let cam = PinholeCamera::from_hfov(70.0, width, height)
        .unwrap()
        .with_distortion(RadTan { k1: -0.08, k2: 0.01, p1: 0.001, p2: -0.0005, k3: 0.0 })
        .unwrap();
    let axis = Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
    let pose = Se3::from_parts(Translation3::new(0.4, -0.3, 1.2), so3_exp(&(axis.normalize() * rng.range(0.3, 2.5))));
    (cam, pose)
}

fn random_planes(rng: &mut Rng, width: usize, height: usize) -> MediumPlanes {
    let mut p = MediumPlanes::new(width, height);
    for plane in [&mut p.c_med, &mut p.sigma_att, &mut p.sigma_bs] {
        for v in plane.data.iter_mut() {
            *v = rng.range(-1.0, 1.0) as f32;
        }
    }
    p
}

/// Max abs difference of two planes.
fn max_abs(got: &[f32], want: &[f32]) -> f64 {
    assert_eq!(got.len(), want.len());
    got.iter().zip(want).map(|(a, b)| (a - b).abs() as f64).fold(0.0, |m, e| if e > m || e.is_nan() { e } else { m })
}

/// Checks the gradient tensor by tensor; returns the worst scaled error.
fn check_grads(layout: &MediumLayout, got: &[f32], want: &[f32]) -> f64 {
    let l = layout;
    let tensors = [("W1", l.w1, l.b1), ("b1", l.b1, l.w2), ("W2", l.w2, l.b2), ("b2", l.b2, l.w_heads), ("W_heads", l.w_heads, l.b_heads), ("b_heads", l.b_heads, l.len)];
    let mut worst = 0.0f64;
    for (what, a, b) in tensors {
        let (got, want) = (&got[a..b], &want[a..b]);
        let (i, err, floor) = gpu_common::worst_scaled_error(what, got, want, GRAD_FLOOR_FRACTION);
        eprintln!("  grad {what}: max scaled error {err:.2e} (floor {floor:.3e})");
        assert!(err <= GRAD_REL_TOL, "{what}[{i}]: GPU {} vs CPU {} (scaled error {err:.3e}, floor {floor:.3e})", got[i], want[i]);
        worst = worst.max(err);
    }
    worst
}

/// The GPU planes and gradient of one forward + backward (gradient from zero).
struct GpuRun {
    planes: MediumPlanes,
    grads: Vec<f32>,
}

#[allow(clippy::too_many_arguments)]
fn gpu_run(
    ctx: &mut GpuContext,
    medium: &mut GpuMedium,
    fwd: &GpuRasterForward,
    upstream: [&duv_gpu::GpuBuffer<f32>; 3],
    net: &MediumNet,
    cam: &PinholeCamera,
    pose: &Se3,
    d_planes: &MediumPlanes,
) -> GpuRun {
    let (w, h) = (cam.width, cam.height);
    medium.upload_params(ctx, net).unwrap();
    medium.write_view(ctx, cam, pose).unwrap();
    ctx.write(upstream[0], &d_planes.c_med.data).unwrap();
    ctx.write(upstream[1], &d_planes.sigma_att.data).unwrap();
    ctx.write(upstream[2], &d_planes.sigma_bs.data).unwrap();
    ctx.begin().unwrap();
    medium.record_zero_grads(ctx).unwrap();
    medium.record_forward(ctx, &fwd.c_med, &fwd.sigma_att, &fwd.sigma_bs).unwrap();
    medium.record_backward(ctx, upstream[0], upstream[1], upstream[2]).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut planes = MediumPlanes::new(w, h);
    ctx.read(&fwd.c_med, &mut planes.c_med.data).unwrap();
    ctx.read(&fwd.sigma_att, &mut planes.sigma_att.data).unwrap();
    ctx.read(&fwd.sigma_bs, &mut planes.sigma_bs.data).unwrap();
    let mut grads = vec![0.0; medium.layout().len];
    medium.read_grads(ctx, &mut grads).unwrap();
    GpuRun { planes, grads }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Forward and backward of a `w x h` view at `step` on a medium sized for `max_w x max_h`
/// against `MediumWorkspace::with_grid`, with the node kernels of both kinds (a workgroup per
/// node, and one invocation per node: `GpuMedium::serial`); a repeat run is bit-identical, a
/// second backward without zeroing adds, and the two kinds give the same bits.
fn check_parity(test: &str, (max_w, max_h): (usize, usize), (w, h): (usize, usize), step: usize, pe_frequencies: usize, seed: u64) {
    let Some(mut ctx) = gpu_common::gpu_or_skip(test) else { return };
    let mut rng = Rng::new(seed);
    let net = random_net(&mut rng, pe_frequencies);
    let (cam, pose) = view(&mut rng, w, h);
    let d_planes = random_planes(&mut rng, w, h);

    // CPU reference.
    let t = Instant::now();
    let mut ws = MediumWorkspace::with_grid(&net, w, h, step);
    let mut nine = MediumPlanes9::new(w, h);
    ws.forward(&net, &cam, &pose, &mut nine).unwrap();
    let mut want = MediumPlanes::new(w, h);
    planes_from_nine(&nine, &mut want);
    let mut d9 = MediumPlanes9::new(w, h);
    nine_from_planes(&d_planes, &mut d9);
    let mut want_grads = vec![0.0f32; net.param_count()];
    ws.backward(&net, &cam, &pose, &d9, &mut want_grads).unwrap();
    let cpu_ms = t.elapsed().as_secs_f64() * 1e3;

    let arena_mark = ctx.arena_used_bytes();
    let mut medium = GpuMedium::new(&mut ctx, max_w, max_h, step, net.layout()).unwrap();
    let fwd = GpuRasterForward::new(&mut ctx, max_w * max_h).unwrap();
    let upstream = [
        ctx.alloc::<f32>("dL/dc_med", max_w * max_h * 3).unwrap(),
        ctx.alloc::<f32>("dL/dsigma_att", max_w * max_h * 3).unwrap(),
        ctx.alloc::<f32>("dL/dsigma_bs", max_w * max_h * 3).unwrap(),
    ];
    let up = [&upstream[0], &upstream[1], &upstream[2]];
    let mut runs = Vec::new();
    for serial in [false, true] {
        medium.serial = Some(serial);
        runs.push(check_one(&mut ctx, &mut medium, &fwd, up, &net, (&cam, &pose), &d_planes, (&want, &want_grads)));
        eprintln!("[{test}] {w}x{h} step {step}, {} inputs, serial {serial}: CPU {cpu_ms:.1} ms", net.layout().inputs);
    }
    // On a CPU device (lavapipe) the two kinds give the same bits. On a GPU each kind met the
    // CPU reference's tolerances above, but the driver's compiler may fuse the multiply-adds
    // of the two differently (the H100's did: the last bits differ), so only those hold there.
    let same_bits = ctx.info().is_cpu();
    for (what, a, b) in [("c_med", &runs[0].planes.c_med, &runs[1].planes.c_med), ("sigma_att", &runs[0].planes.sigma_att, &runs[1].planes.sigma_att), ("sigma_bs", &runs[0].planes.sigma_bs, &runs[1].planes.sigma_bs)] {
        eprintln!("[{test}] forward {what}: serial against workgroup per node, max abs difference {:.2e}", max_abs(&a.data, &b.data));
        assert!(!same_bits || bits(&a.data) == bits(&b.data), "forward {what}: the serial node kernels differ from the workgroup per node");
    }
    assert!(!same_bits || bits(&runs[0].grads) == bits(&runs[1].grads), "gradient: the serial node kernels differ from the workgroup per node");
    ctx.arena_reset_to(arena_mark);
}

/// One kind of node kernels against the CPU reference (`want`), then twice more.
#[allow(clippy::too_many_arguments)]
fn check_one(
    ctx: &mut GpuContext,
    medium: &mut GpuMedium,
    fwd: &GpuRasterForward,
    up: [&duv_gpu::GpuBuffer<f32>; 3],
    net: &MediumNet,
    (cam, pose): (&PinholeCamera, &Se3),
    d_planes: &MediumPlanes,
    (want, want_grads): (&MediumPlanes, &[f32]),
) -> GpuRun {
    let (w, h) = (cam.width, cam.height);
    let t = Instant::now();
    let got = gpu_run(ctx, medium, fwd, up, net, cam, pose, d_planes);
    let gpu_ms = t.elapsed().as_secs_f64() * 1e3;
    let grid = medium.grid().unwrap();
    eprintln!("  {w}x{h}: {} nodes ({}x{}); GPU {gpu_ms:.1} ms", grid.nodes(), grid.nodes_x, grid.nodes_y);

    let mut worst_fwd = 0.0f64;
    for (what, g, c) in [("c_med", &got.planes.c_med, &want.c_med), ("sigma_att", &got.planes.sigma_att, &want.sigma_att), ("sigma_bs", &got.planes.sigma_bs, &want.sigma_bs)] {
        let err = max_abs(&g.data, &c.data);
        eprintln!("  forward {what}: max abs error {err:.2e}");
        assert!(err <= FORWARD_TOL, "forward {what}: max abs error {err:.3e} > {FORWARD_TOL:e}");
        worst_fwd = worst_fwd.max(err);
    }
    // The heads must not be constant, or the test would prove little.
    let spread = |v: &[f32]| v.iter().cloned().fold(f32::MIN, f32::max) - v.iter().cloned().fold(f32::MAX, f32::min);
    for (what, plane) in [("c_med", &want.c_med.data), ("sigma_att", &want.sigma_att.data), ("sigma_bs", &want.sigma_bs.data)] {
        assert!(spread(plane) > 0.05, "{what} is nearly constant over the view ({}); perturb the network more", spread(plane));
    }
    let worst_grad = check_grads(&net.layout(), &got.grads, want_grads);
    eprintln!("  forward max abs error {worst_fwd:.2e}, gradient max scaled error {worst_grad:.2e}");

    // A second run: bit-identical.
    let again = gpu_run(ctx, medium, fwd, up, net, cam, pose, d_planes);
    for (what, a, b) in [("c_med", &got.planes.c_med, &again.planes.c_med), ("sigma_att", &got.planes.sigma_att, &again.planes.sigma_att), ("sigma_bs", &got.planes.sigma_bs, &again.planes.sigma_bs)] {
        assert!(bits(&a.data) == bits(&b.data), "forward {what}: second run differs");
    }
    assert!(bits(&got.grads) == bits(&again.grads), "gradient: second run differs");

    // The backward adds: once more without zeroing gives exactly twice the gradient.
    ctx.begin().unwrap();
    medium.record_backward(ctx, up[0], up[1], up[2]).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut twice = vec![0.0f32; net.param_count()];
    medium.read_grads(ctx, &mut twice).unwrap();
    let doubled: Vec<f32> = got.grads.iter().map(|v| v + v).collect();
    assert!(bits(&twice) == bits(&doubled), "a second backward must add to the gradient");
    got
}

#[test]
fn grid_medium_matches_medium_workspace() {
    // 203x117 at step 8: 27x16 = 432 nodes (6.75 workgroups of 64, 3.4 chunks of 128), neither
    // size a multiple of the step, 23751 pixels (92.8 workgroups of 256); the medium is sized
    // for a larger view, so the view uses a prefix of every buffer.
    check_parity("grid_medium_matches_medium_workspace", (256, 128), (203, 117), 8, 4, 11);
}

#[test]
fn per_pixel_medium_matches_medium_net() {
    // Step 1: the nodes are the pixels (1073 of them: 17 workgroups of 64, 9 chunks of 128).
    check_parity("per_pixel_medium_matches_medium_net", (37, 29), (37, 29), 1, 4, 23);
}

#[test]
fn largest_encoding_matches_medium_workspace() {
    // 12 frequencies: 75 inputs, the largest layout (the whole of the serial kernels' uniform
    // view of the parameters); 9x7 nodes, one workgroup, 63 of its 64 invocations.
    check_parity("largest_encoding_matches_medium_workspace", (70, 50), (65, 49), 8, 12, 31);
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let Some(mut ctx) = gpu_common::gpu_or_skip("bad_input_is_an_error_not_a_panic") else { return };
    let mut rng = Rng::new(5);
    let net = random_net(&mut rng, 4);
    let arena_mark = ctx.arena_used_bytes();
    assert!(matches!(GpuMedium::new(&mut ctx, 64, 48, 0, net.layout()), Err(GpuMediumError::Medium(MediumError::InvalidConfig { .. }))));
    assert!(matches!(GpuMedium::new(&mut ctx, 64, 48, 65, net.layout()), Err(GpuMediumError::Medium(MediumError::InvalidConfig { .. }))));
    let mut odd = net.layout();
    odd.inputs += 1;
    assert!(matches!(GpuMedium::new(&mut ctx, 64, 48, 4, odd), Err(GpuMediumError::Medium(MediumError::InvalidConfig { .. }))));
    let mut medium = GpuMedium::new(&mut ctx, 64, 48, 4, net.layout()).unwrap();
    let planes = [ctx.alloc::<f32>("plane a", 64 * 48 * 3).unwrap(), ctx.alloc::<f32>("plane b", 64 * 48 * 3).unwrap(), ctx.alloc::<f32>("plane c", 64 * 48 * 3).unwrap()];
    let small = ctx.alloc::<f32>("small plane", 10).unwrap();

    // Nothing recorded before a view is written.
    ctx.begin().unwrap();
    assert!(matches!(medium.record_forward(&mut ctx, &planes[0], &planes[1], &planes[2]), Err(GpuMediumError::NoView)));
    assert!(matches!(medium.record_backward(&mut ctx, &planes[0], &planes[1], &planes[2]), Err(GpuMediumError::NoView)));
    ctx.submit_and_wait().unwrap();

    // A network of another layout; a gradient slice of the wrong length.
    let other = MediumNet::new(&MediumConfig { pe_frequencies: 2, ..MediumConfig::default() }).unwrap();
    assert!(matches!(medium.upload_params(&mut ctx, &other), Err(GpuMediumError::Medium(MediumError::LengthMismatch { .. }))));
    medium.upload_params(&mut ctx, &net).unwrap();
    let mut short = vec![0.0f32; net.param_count() - 1];
    assert!(matches!(medium.read_grads(&ctx, &mut short), Err(GpuMediumError::Medium(MediumError::LengthMismatch { .. }))));

    // A non-finite pose, a view past the capacity, a bad camera.
    let (cam, pose) = view(&mut rng, 64, 48);
    let mut nan_pose = pose;
    nan_pose.translation.vector.x = f64::NAN;
    assert!(matches!(medium.write_view(&mut ctx, &cam, &nan_pose), Err(GpuMediumError::Medium(MediumError::NonFinitePose))));
    let (big, _) = view(&mut rng, 65, 48);
    assert!(matches!(medium.write_view(&mut ctx, &big, &pose), Err(GpuMediumError::ViewTooLarge { width: 65, height: 48, max_width: 64, max_height: 48 })));
    let mut bad_cam = cam;
    bad_cam.fx = -1.0;
    assert!(matches!(medium.write_view(&mut ctx, &bad_cam, &pose), Err(GpuMediumError::Medium(MediumError::BadCamera(_)))));
    assert!(medium.grid().is_none(), "a failed write_view must not set a view");

    // Planes smaller than the view.
    medium.write_view(&mut ctx, &cam, &pose).unwrap();
    ctx.begin().unwrap();
    assert!(matches!(medium.record_forward(&mut ctx, &planes[0], &small, &planes[2]), Err(GpuMediumError::Gpu(GpuError::OutOfRange { what: "small plane", .. }))));
    assert!(matches!(medium.record_backward(&mut ctx, &small, &planes[1], &planes[2]), Err(GpuMediumError::Gpu(GpuError::OutOfRange { what: "small plane", .. }))));
    // Recording outside begin()/submit_and_wait() is the device layer's error.
    ctx.submit_and_wait().unwrap();
    assert!(matches!(medium.record_forward(&mut ctx, &planes[0], &planes[1], &planes[2]), Err(GpuMediumError::Gpu(GpuError::NotRecording { .. }))));

    // After all that, a valid run still works and gives finite planes.
    ctx.begin().unwrap();
    medium.record_forward(&mut ctx, &planes[0], &planes[1], &planes[2]).unwrap();
    ctx.submit_and_wait().unwrap();
    let mut out = vec![0.0f32; 64 * 48 * 3];
    ctx.read(&planes[1], &mut out).unwrap();
    assert!(out.iter().all(|v| v.is_finite() && *v > 0.0), "sigma_att must be finite and positive");
    ctx.arena_reset_to(arena_mark);
}

/// `medium_prior.medium_upstream` against the host's steps in `Mapper::step_on`: the loss's
/// dL/dc_med added to the renderer's plane gradients, `MediumPrior::loss_and_grad`, then
/// `fold_single_coefficient`; with and without the fold, with a prior on two channels.
#[test]
fn medium_upstream_matches_the_prior_and_the_fold() {
    use duv_core::MediumParams;
    use duv_map::mapper::fold_single_coefficient;
    use duv_map::medium::{C_MED, MEDIUM_CHANNELS};
    use duv_map::medium_estimate::{Coefficients, MediumPrior};
    use duv_map::vulkan::medium::{record_medium_upstream, MediumPlaneBuffers};
    let Some(mut ctx) = gpu_common::gpu_or_skip("medium_upstream_matches_the_prior_and_the_fold") else { return };
    let (w, h) = (203, 5);
    let n = w * h;
    let mut rng = Rng::new(41);
    let planes9 = MediumPlanes9 { width: w, height: h, data: (0..n * MEDIUM_CHANNELS).map(|_| rng.range(0.01, 1.5) as f32).collect() };
    let raster_grad9: Vec<f32> = (0..n * MEDIUM_CHANNELS).map(|_| rng.range(-1.0, 1.0) as f32).collect();
    let loss_c_med: Vec<f32> = (0..n * 3).map(|_| rng.range(-0.5, 0.5) as f32).collect();
    let prior = MediumPrior {
        medium: MediumParams { beta_d: [0.4, 0.2, 0.1], beta_b: [0.35, 0.25, 0.15], b_inf: [0.1, 0.3, 0.4] },
        // Whole, none, and a channel whose beta_D is free.
        held: [Coefficients::ALL, Coefficients::NONE, Coefficients { beta_d: false, beta_b: true, b_inf: true }],
        weight: 0.3,
        rel_std: 0.1,
        b_inf_std: 0.02,
    };
    let mark = ctx.arena_used_bytes();
    let alloc = |ctx: &mut GpuContext, what| ctx.alloc::<f32>(what, 3 * n).unwrap();
    let (c_med, att, bs, gc, ga, gb, ld) = (alloc(&mut ctx, "c_med"), alloc(&mut ctx, "att"), alloc(&mut ctx, "bs"), alloc(&mut ctx, "gc"), alloc(&mut ctx, "ga"), alloc(&mut ctx, "gb"), alloc(&mut ctx, "loss dc"));
    let channel = |data: &[f32], first: usize| -> Vec<f32> { data.chunks_exact(MEDIUM_CHANNELS).flat_map(|px| px[first..first + 3].to_vec()).collect() };
    for single in [false, true] {
        // Host: the step's order of additions.
        let mut want = raster_grad9.clone();
        for (px, d) in want.chunks_exact_mut(MEDIUM_CHANNELS).zip(loss_c_med.chunks_exact(3)) {
            for c in 0..3 {
                px[C_MED + c] += d[c];
            }
        }
        prior.loss_and_grad(&planes9.data, &mut want);
        if single {
            fold_single_coefficient(&mut want);
        }
        // Device.
        for (buf, first) in [(&c_med, 0), (&att, 3), (&bs, 6)] {
            ctx.write(buf, &channel(&planes9.data, first)).unwrap();
        }
        for (buf, first) in [(&gc, 0), (&ga, 3), (&gb, 6)] {
            ctx.write(buf, &channel(&raster_grad9, first)).unwrap();
        }
        ctx.write(&ld, &loss_c_med).unwrap();
        let bufs = MediumPlaneBuffers { c_med: &c_med, sigma_att: &att, sigma_bs: &bs, grad_c_med: &gc, grad_sigma_att: &ga, grad_sigma_bs: &gb, loss_d_c_med: &ld };
        ctx.begin().unwrap();
        record_medium_upstream(&mut ctx, &bufs, n, Some(&prior), single).unwrap();
        ctx.submit_and_wait().unwrap();
        for (buf, first, name) in [(&gc, 0, "c_med"), (&ga, 3, "sigma_att"), (&gb, 6, "sigma_bs")] {
            let mut got = vec![0.0f32; 3 * n];
            ctx.read(buf, &mut got).unwrap();
            let want_c = channel(&want, first);
            let scale = want_c.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let err = got.iter().zip(&want_c).map(|(a, b)| ((a - b).abs() / b.abs().max(1e-2 * scale).max(f32::MIN_POSITIVE)) as f64).fold(0.0, f64::max);
            eprintln!("single {single}: dL/d{name}: largest |cpu| {scale:.3e}, worst scaled error {err:.2e}");
            assert!(err <= GRAD_REL_TOL, "single {single}: dL/d{name}: scaled error {err:.2e}");
            if single && name == "sigma_bs" {
                assert!(got.iter().all(|&v| v == 0.0), "the fold leaves no sigma_bs gradient");
            }
        }
    }
    ctx.arena_reset_to(mark);
}
