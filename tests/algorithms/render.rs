//! The splatting renderer with the underwater medium (`duv_map::render`): hand-computed
//! projections and blends, the closed-form image formation model, the tiled f32 pipeline
//! against the untiled f64 reference, the GPU-shaped building blocks (prefix sum, radix sort,
//! tile ranges, overflow) against plain algorithms, input validation, and gradient checks of
//! every backward stage against central differences in f64.
//!
//! Sizes cross tile boundaries: 37x29 images are 3x2 tiles of 16 with partial tiles.

use crate::render_scene;

use duv_core::rng::Rng;
use duv_core::{PinholeCamera, RadTan, Se3};
use duv_map::gaussians::{GaussianGrads, GaussianParam, Gaussians, ParamGroup, PARAMS_PER_GAUSSIAN};
use duv_map::render::reference::{medium_f64, render_reference, ReferenceView};
use duv_map::render::{
    backprop_pixel, bits_for, blend_pixel, isect_key, isect_key_bits, key_tile, DEPTH_KEY_BITS, exclusive_scan, project_splat, project_splat_backward, radix_sort_pairs, scan_blocks, sigmoid,
    sort_histogram_len, tile_ranges, DepthMode, MediumPlanes, PixelForward, PixelMedium, PixelRay, PixelState, PixelUpstream,
    ProjectedSplat, ProjectionSetup, RasterCapacity, RasterWorkspace, RenderConfig, RenderError, RenderOutput, RenderUpstream, SplatGrad, TileGrid,
    ALPHA_MIN,
};
use render_scene::{camera, f_dc_for, random_gaussians, random_medium, random_upstream, world_from_cam};

/// f32 tiled pipeline against the f64 untiled reference, any output value.
const FORWARD_PARITY_TOL: f64 = 2e-5;
/// Hand-computed projections and blends (f32 arithmetic on O(1) values).
const HAND_TOL: f64 = 1e-5;
/// Opaque layer against `J exp(-beta_D r) + B (1 - exp(-beta_B r))`: blending stops with up
/// to 2e-4 transmittance left (3DGS early termination at 1e-4, alphas <= 0.5), plus f32.
const PLANE_TOL: f64 = 3e-4;
/// f32 pipeline gradients against f64 central differences.
const GRAD_REL_TOL: f64 = 1e-3;
/// Generic backward stages run in f64 against f64 central differences.
const F64_GRAD_REL_TOL: f64 = 1e-6;
/// A gradient smaller than this fraction of the largest in its group is compared with that
/// floor instead of its own size (negligible gradients are checked absolutely).
const GRAD_FLOOR_FRACTION: f64 = 1e-2;
/// Central-difference step (f64; the loss is smooth between alpha-threshold kinks).
const FD_STEP: f64 = 1e-6;
/// Share of parameters allowed to sit on a kink (alpha crossing 1/255 within the step).
const MAX_KINK_SHARE: f64 = 0.02;

fn capacity(width: usize, height: usize, max_gaussians: usize) -> RasterCapacity {
    RasterCapacity { width, height, max_gaussians, max_intersections: 65_536 }
}

fn zero_medium(width: usize, height: usize) -> MediumPlanes {
    MediumPlanes::new(width, height)
}

fn render(
    gaussians: &Gaussians,
    cam: &PinholeCamera,
    cam_from_world: &Se3,
    medium: &MediumPlanes,
    config: &RenderConfig,
) -> (RasterWorkspace, RenderOutput) {
    let mut ws = RasterWorkspace::new(capacity(cam.width, cam.height, gaussians.capacity())).unwrap();
    let mut out = RenderOutput::new(cam.width, cam.height);
    ws.forward(gaussians, cam, cam_from_world, medium, config, &mut out).unwrap();
    (ws, out)
}

fn plain(mean: [f32; 3], sigma_m: f32, logit: f32, colour: [f64; 3]) -> GaussianParam<f32> {
    GaussianParam {
        mean,
        log_scale: [sigma_m.ln(); 3],
        rotation: [1.0, 0.0, 0.0, 0.0],
        opacity_logit: logit,
        f_dc: colour.map(f_dc_for),
        f_rest: [0.0; 9],
    }
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

// ---------------------------------------------------------------------------------------
// Hand-computed cases.

#[test]
fn isotropic_gaussian_on_the_optical_axis() {
    let cam = PinholeCamera::new(40.0, 40.0, 18.0, 14.0, 37, 29).unwrap();
    let (s, z, logit) = (0.05f32, 2.0f32, 0.5f32);
    let mut g = Gaussians::with_capacity(1);
    g.push(&plain([0.0, 0.0, z], s, logit, [0.8, 0.4, 0.2])).unwrap();
    let o = 1.0 / (1.0 + (-logit as f64).exp());
    for blur in [0.0f32, 0.3] {
        let config = RenderConfig { cov2d_blur_px2: blur, ..RenderConfig::default() };
        let (ws, out) = render(&g, &cam, &Se3::identity(), &zero_medium(37, 29), &config);
        let sp = ws.splats()[0];
        // 2D covariance f^2 s^2 / z^2 = 1600 * 0.0025 / 4 = 1 px^2 (+ blur); mean at the
        // principal point.
        let var = (40.0 * 40.0 * (s * s) as f64 / (z * z) as f64) + blur as f64;
        assert!(close(sp.mean2d[0] as f64, 18.0, HAND_TOL) && close(sp.mean2d[1] as f64, 14.0, HAND_TOL), "{sp:?}");
        assert!(close(sp.conic[0] as f64, 1.0 / var, HAND_TOL) && close(sp.conic[2] as f64, 1.0 / var, HAND_TOL), "{sp:?}");
        assert!(close(sp.conic[1] as f64, 0.0, HAND_TOL));
        assert!(close(sp.z as f64, 2.0, HAND_TOL) && close(sp.opacity as f64, o, 1e-6));
        // Alpha at the centre is the opacity; one pixel to the right exp(-1/(2 var)).
        let i = 14 * 37 + 18;
        assert!(close(out.alpha.data[i] as f64, o, 1e-6), "{}", out.alpha.data[i]);
        assert!(close(out.alpha.data[i + 1] as f64, o * (-0.5 / var).exp(), 1e-6));
        for (c, col) in [0.8, 0.4, 0.2].into_iter().enumerate() {
            assert!(close(out.colour.data[i * 3 + c] as f64, o * col, HAND_TOL));
            assert!(close(out.restored.data[i * 3 + c] as f64, o * col, HAND_TOL));
        }
        assert!(close(out.depth.data[i] as f64, 0.5, 1e-6) && out.depth_var.data[i].abs() < 1e-9);
        assert!(close(out.final_t.data[i] as f64, 1.0 - o, 1e-6));
    }
}

#[test]
fn two_gaussians_blend_in_depth_order_regardless_of_input_order() {
    let cam = PinholeCamera::new(40.0, 40.0, 18.0, 14.0, 37, 29).unwrap();
    let near = plain([0.0, 0.0, 2.0], 0.05, 1.0, [0.9, 0.1, 0.1]);
    let far = plain([0.0, 0.0, 4.0], 0.2, 0.0, [0.1, 0.1, 0.9]);
    let config = RenderConfig::default();
    let mut outs = Vec::new();
    for order in [[near, far], [far, near]] {
        let mut g = Gaussians::with_capacity(2);
        for p in &order {
            g.push(p).unwrap();
        }
        outs.push(render(&g, &cam, &Se3::identity(), &zero_medium(37, 29), &config).1);
    }
    assert_eq!(outs[0], outs[1], "blending must not depend on the input order");
    let out = &outs[0];
    let i = 14 * 37 + 18;
    let (a1, a2) = (sigmoid(1.0f64), 0.5);
    let (w1, w2) = (a1, (1.0 - a1) * a2);
    let expected = [0.9 * w1 + 0.1 * w2, 0.1 * w1 + 0.1 * w2, 0.1 * w1 + 0.9 * w2];
    for (c, e) in expected.into_iter().enumerate() {
        assert!(close(out.colour.data[i * 3 + c] as f64, e, HAND_TOL), "{c}: {}", out.colour.data[i * 3 + c]);
    }
    let depth = (w1 * 0.5 + w2 * 0.25) / (w1 + w2);
    let var = (w1 * (0.5 - depth).powi(2) + w2 * (0.25 - depth).powi(2)) / (w1 + w2);
    assert!(close(out.depth.data[i] as f64, depth, HAND_TOL) && close(out.depth_var.data[i] as f64, var, HAND_TOL));
    assert!(close(out.alpha.data[i] as f64, w1 + w2, HAND_TOL));
}

// ---------------------------------------------------------------------------------------
// The medium.

#[test]
fn opaque_layer_matches_the_image_formation_model() {
    let (w, h) = (37, 29);
    let cam = camera(w, h, 40.0);
    let z0 = 3.0f64;
    let (spacing, sigma) = (0.06f64, 0.15f32);
    let half_x = (0.5 * w as f64 / 40.0) * z0 + 0.6;
    let half_y = (0.5 * h as f64 / 40.0) * z0 + 0.6;
    let (nx, ny) = ((2.0 * half_x / spacing) as usize, (2.0 * half_y / spacing) as usize);
    let mut g = Gaussians::with_capacity(nx * ny);
    let j = [0.7, 0.5, 0.3];
    for iy in 0..ny {
        for ix in 0..nx {
            let mut p = plain([(-half_x + ix as f64 * spacing) as f32, (-half_y + iy as f64 * spacing) as f32, z0 as f32], sigma, 0.0, j);
            p.log_scale[2] = 1e-3f32.ln();
            g.push(&p).unwrap();
        }
    }
    let (b, beta_d, beta_b) = ([0.1f32, 0.3, 0.4], [0.4f32, 0.15, 0.1], [0.3f32, 0.2, 0.25]);
    let medium = MediumPlanes::uniform(w, h, b, beta_d, beta_b);
    let (_, out) = render(&g, &cam, &Se3::identity(), &medium, &RenderConfig::default());
    let mut max_err = 0.0f64;
    for y in 0..h {
        for x in 0..w {
            let ray = PixelRay::new(x, y, cam.fx, cam.fy, cam.cx, cam.cy);
            let r = z0 * ray.ray_norm;
            for c in 0..3 {
                let expected = j[c] * (-beta_d[c] as f64 * r).exp() + b[c] as f64 * (1.0 - (-beta_b[c] as f64 * r).exp());
                max_err = max_err.max((out.colour.pixel(x, y)[c] as f64 - expected).abs());
            }
            assert!(out.final_t.pixel(x, y)[0] < 2e-4 + 1e-6, "layer not opaque at ({x}, {y})");
            assert!(close(out.depth.pixel(x, y)[0] as f64, 1.0 / z0, 1e-5));
        }
    }
    eprintln!("opaque layer vs closed form: max abs error {max_err:.2e} (tolerance {PLANE_TOL:.0e})");
    assert!(max_err <= PLANE_TOL, "max error {max_err}");
}

#[test]
fn empty_scene_renders_the_medium_colour_exactly() {
    let (w, h) = (37, 29);
    let cam = camera(w, h, 30.0);
    let medium = random_medium(&mut Rng::new(5), w, h);
    // An empty map, and a map whose only Gaussian is behind the camera.
    let mut behind = Gaussians::with_capacity(1);
    behind.push(&plain([0.0, 0.0, -2.0], 0.1, 2.0, [0.5; 3])).unwrap();
    for g in [Gaussians::with_capacity(1), behind] {
        let (_, out) = render(&g, &cam, &Se3::identity(), &medium, &RenderConfig::default());
        assert_eq!(out.colour.data, medium.c_med.data);
        assert!(out.alpha.data.iter().chain(&out.depth.data).chain(&out.restored.data).all(|&v| v == 0.0));
        assert!(out.final_t.data.iter().all(|&v| v == 1.0));
    }
}

// ---------------------------------------------------------------------------------------
// The tiled pipeline against the untiled reference.

fn max_forward_difference(out: &RenderOutput, reference: &[PixelForward<f64>]) -> f64 {
    let mut d = 0.0f64;
    for (i, r) in reference.iter().enumerate() {
        for c in 0..3 {
            d = d.max((out.colour.data[i * 3 + c] as f64 - r.colour[c]).abs());
            d = d.max((out.restored.data[i * 3 + c] as f64 - r.restored[c]).abs());
        }
        d = d.max((out.depth.data[i] as f64 - r.depth).abs());
        d = d.max((out.depth_var.data[i] as f64 - r.depth_var).abs());
        d = d.max((out.alpha.data[i] as f64 - r.alpha).abs());
        d = d.max((out.final_t.data[i] as f64 - r.final_t).abs());
    }
    d
}

#[test]
fn tiled_forward_matches_the_untiled_f64_reference() {
    let (w, h) = (37, 29);
    let cam = camera(w, h, 32.0);
    let cam_from_world = world_from_cam().inverse();
    let mut rng = Rng::new(11);
    // Sparse, medium and dense (alphas clamped at 0.99, early termination) scenes.
    for (n, mode, sigma_px, logits) in [
        (30, DepthMode::InverseDepth, (1.0, 5.0), (-2.0, 4.0)),
        (120, DepthMode::Depth, (0.5, 8.0), (-2.0, 4.0)),
        (400, DepthMode::InverseDepth, (2.0, 10.0), (0.0, 7.0)),
    ] {
        let g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam(), (1.0, 6.0), sigma_px, logits);
        let medium = random_medium(&mut rng, w, h);
        let config = RenderConfig { depth_mode: mode, ..RenderConfig::default() };
        let (ws, out) = render(&g, &cam, &cam_from_world, &medium, &config);
        let params: Vec<GaussianParam<f64>> = (0..n).map(|i| g.get(i).map(f64::from)).collect();
        let reference = render_reference(&params, &cam, &cam_from_world, &medium, &config).unwrap();
        let d = max_forward_difference(&out, &reference);
        let isects: u32 = ws.tiles_touched().iter().sum();
        let terminated = out.final_t.data.iter().filter(|&&t| t < 1e-3).count();
        eprintln!(
            "{n} Gaussians ({mode:?}, {isects} intersections, {terminated} pixels near termination): \
             max |f32 tiled - f64 reference| = {d:.2e}"
        );
        assert!(d <= FORWARD_PARITY_TOL, "max difference {d}");
    }
}

// ---------------------------------------------------------------------------------------
// Building blocks against plain algorithms.

#[test]
fn prefix_sum_matches_a_sequential_scan() {
    let mut rng = Rng::new(3);
    for n in [0, 1, 511, 512, 513, 512 * 16 + 123] {
        let counts: Vec<u32> = (0..n).map(|_| rng.below(40) as u32).collect();
        let mut offsets = vec![u32::MAX; n + 1];
        let mut blocks = vec![0u64; scan_blocks(n)];
        let total = exclusive_scan(&counts, &mut offsets, &mut blocks, u32::MAX as u64).unwrap();
        let mut expected = Vec::with_capacity(n + 1);
        let mut acc = 0u32;
        for &c in &counts {
            expected.push(acc);
            acc += c;
        }
        expected.push(acc);
        assert_eq!(offsets, expected, "n = {n}");
        assert_eq!(total, acc as u64);
        // Over the limit: the exact total is reported and nothing is written.
        if acc > 0 {
            let mut untouched = vec![7u32; n + 1];
            assert_eq!(exclusive_scan(&counts, &mut untouched, &mut blocks, acc as u64 - 1), Err(acc as u64));
            assert!(untouched.iter().all(|&v| v == 7));
        }
    }
}

#[test]
fn radix_sort_matches_sort_unstable() {
    let mut rng = Rng::new(4);
    for n in [0, 1, 2, 4095, 4096, 4097, 512 * 16 + 123, 3 * 4096 + 7] {
        for key_bits in [64u32, 41, 13] {
            let mask = if key_bits == 64 { u64::MAX } else { (1u64 << key_bits) - 1 };
            // Few distinct values in the low bits so equal keys are common (stability).
            let mut keys: Vec<u64> = (0..n).map(|_| if rng.below(2) == 0 { rng.next_u64() & mask } else { rng.below(17) & mask }).collect();
            let mut values: Vec<u32> = (0..n as u32).collect();
            let mut expected: Vec<(u64, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
            expected.sort_unstable();
            let (mut kt, mut vt, mut hist) = (vec![0u64; n], vec![0u32; n], vec![0u32; sort_histogram_len(n)]);
            radix_sort_pairs(&mut keys, &mut values, &mut kt, &mut vt, &mut hist, key_bits);
            let got: Vec<(u64, u32)> = keys.into_iter().zip(values).collect();
            assert_eq!(got, expected, "n = {n}, key_bits = {key_bits}");
        }
    }
    assert_eq!((bits_for(0), bits_for(1), bits_for(255), bits_for(256)), (0, 1, 8, 9));
}

#[test]
fn tile_ranges_partition_the_sorted_keys() {
    let mut rng = Rng::new(8);
    let tiles = 23usize;
    let n = 512 * 16 + 123;
    let mut keys: Vec<u64> = (0..n).map(|_| isect_key(rng.below(tiles as u64 - 3) as u32 + 1, rng.range(0.1, 40.0) as f32)).collect();
    keys.sort_unstable();
    let mut offsets = vec![0u32; tiles + 1];
    tile_ranges(&keys, &mut offsets);
    assert_eq!((offsets[0], offsets[1], offsets[tiles]), (0, 0, n as u32));
    for t in 0..tiles {
        let range = offsets[t] as usize..offsets[t + 1] as usize;
        assert!(keys[range.clone()].iter().all(|&k| key_tile(k) as usize == t));
        assert_eq!(range.len(), keys.iter().filter(|&&k| key_tile(k) as usize == t).count());
    }
}

/// Intersection keys order by tile, then by depth to a relative 2^-13; closer depths tie (the
/// stable sort keeps the Gaussians' order); 640x480's tiles fit 32 bits (four radix passes).
#[test]
fn intersection_keys_order_by_tile_then_depth() {
    let mut rng = Rng::new(9);
    for _ in 0..10_000 {
        let (t1, t2) = (rng.below(5000) as u32, rng.below(5000) as u32);
        let (z1, z2) = (rng.range(0.01, 100.0) as f32, rng.range(0.01, 100.0) as f32);
        let (k1, k2) = (isect_key(t1, z1), isect_key(t2, z2));
        assert_eq!((key_tile(k1), key_tile(k2)), (t1, t2));
        if t1 != t2 {
            assert_eq!(k1 < k2, t1 < t2);
            continue;
        }
        // Never out of order; strictly ordered beyond twice the resolution.
        assert_eq!(k1 <= k2, z1 <= z2 || k1 == k2, "depths {z1} and {z2}");
        if (z1 - z2).abs() > 2.5e-4 * z1.max(z2) {
            assert_eq!(k1 < k2, z1 < z2, "depths {z1} and {z2}");
        }
        let z3 = z1 * 1.00001;
        assert!(isect_key(t1, z3) - k1 <= 1, "depths {z1} and {z3}: one step at most");
    }
    assert_eq!(isect_key(7, 3.0), isect_key(7, 3.0 * (1.0 + 1e-5)), "within the resolution: a tie");
    assert!(isect_key(7, 3.0) < isect_key(7, 3.0 * (1.0 + 2.5e-4)));
    assert_eq!(isect_key_bits(TileGrid::new(640, 480).num_tiles()), 32);
    assert_eq!(DEPTH_KEY_BITS + bits_for(TileGrid::new(1280, 720).num_tiles() as u64 - 1), isect_key_bits(3600));
}

#[test]
fn intersection_overflow_reports_the_size_needed() {
    let (w, h) = (37, 29);
    let cam = camera(w, h, 32.0);
    let pose = world_from_cam().inverse();
    let g = random_gaussians(&mut Rng::new(2), 200, 200, &cam, &world_from_cam(), (1.0, 5.0), (2.0, 10.0), (0.0, 2.0));
    let medium = random_medium(&mut Rng::new(1), w, h);
    let (_, _) = render(&g, &cam, &pose, &medium, &RenderConfig::default());
    let mut big = RasterWorkspace::new(capacity(w, h, 200)).unwrap();
    let mut out = RenderOutput::new(w, h);
    let needed = big.forward(&g, &cam, &pose, &medium, &RenderConfig::default(), &mut out).unwrap().intersections;
    assert!(needed > 200);
    let mut small = RasterWorkspace::new(RasterCapacity { max_intersections: needed - 1, ..capacity(w, h, 200) }).unwrap();
    let err = small.forward(&g, &cam, &pose, &medium, &RenderConfig::default(), &mut out).unwrap_err();
    assert_eq!(err, RenderError::TileOverflow { needed: needed as u64, capacity: needed - 1 });
    // No backward after a failed forward; an exact fit works.
    let mut grads = GaussianGrads::with_capacity(200);
    grads.reset(200).unwrap();
    let mut mg = MediumPlanes::new(w, h);
    let up = RenderUpstream::new(w, h);
    assert!(matches!(small.backward(&g, &medium, &out, &up, &mut grads, &mut mg), Err(RenderError::NoForward { .. })));
    let mut exact = RasterWorkspace::new(RasterCapacity { max_intersections: needed, ..capacity(w, h, 200) }).unwrap();
    assert_eq!(exact.forward(&g, &cam, &pose, &medium, &RenderConfig::default(), &mut out).unwrap().intersections, needed);
}

// ---------------------------------------------------------------------------------------
// Bad input.

#[test]
fn bad_input_is_reported_not_panicked() {
    let (w, h) = (37, 29);
    let cam = camera(w, h, 32.0);
    let pose = Se3::identity();
    let config = RenderConfig::default();
    let medium = MediumPlanes::uniform(w, h, [0.2; 3], [0.1; 3], [0.1; 3]);
    let mut ws = RasterWorkspace::new(capacity(w, h, 8)).unwrap();
    let mut out = RenderOutput::new(w, h);
    let mut g = Gaussians::with_capacity(8);
    for k in 0..4 {
        g.push(&plain([0.1 * k as f32, 0.0, 2.0], 0.05, 0.0, [0.5; 3])).unwrap();
    }
    let fwd = |ws: &mut RasterWorkspace, g: &Gaussians, cam: &PinholeCamera, medium: &MediumPlanes, out: &mut RenderOutput| {
        ws.forward(g, cam, &pose, medium, &config, out)
    };
    assert!(fwd(&mut ws, &g, &cam, &medium, &mut out).is_ok());

    let mut bad = g.clone();
    bad.group_mut(ParamGroup::Mean)[2 * 3 + 1] = f32::NAN;
    assert_eq!(fwd(&mut ws, &bad, &cam, &medium, &mut out), Err(RenderError::NonFiniteGaussian { index: 2, field: "mean" }));
    let mut bad = g.clone();
    bad.group_mut(ParamGroup::FRest)[3 * 9 + 8] = f32::INFINITY;
    assert_eq!(fwd(&mut ws, &bad, &cam, &medium, &mut out), Err(RenderError::NonFiniteGaussian { index: 3, field: "f_rest" }));
    let mut bad = g.clone();
    bad.group_mut(ParamGroup::Rotation)[4..8].fill(0.0);
    assert_eq!(fwd(&mut ws, &bad, &cam, &medium, &mut out), Err(RenderError::ZeroRotation { index: 1 }));

    let mut bad_medium = medium.clone();
    bad_medium.sigma_bs.set_pixel(5, 7, [0.1, f32::NAN, 0.1]);
    assert!(matches!(
        fwd(&mut ws, &g, &cam, &bad_medium, &mut out),
        Err(RenderError::BadPixel { what: "sigma_bs", x: 5, y: 7, channel: 1, .. })
    ));
    let mut bad_medium = medium.clone();
    bad_medium.sigma_att.set_pixel(36, 28, [0.1, 0.1, -0.5]);
    assert!(matches!(
        fwd(&mut ws, &g, &cam, &bad_medium, &mut out),
        Err(RenderError::BadPixel { what: "sigma_att", x: 36, y: 28, channel: 2, why: "is negative", .. })
    ));
    assert!(matches!(fwd(&mut ws, &g, &cam, &MediumPlanes::new(0, 0), &mut out), Err(RenderError::SizeMismatch { .. })));

    // Zero-size images, oversize images, distorted cameras, bad configs.
    assert!(matches!(RasterWorkspace::new(capacity(0, 29, 8)), Err(RenderError::EmptyImage { .. })));
    let zero_cam = PinholeCamera { width: 0, height: 0, ..cam };
    assert!(matches!(fwd(&mut ws, &g, &zero_cam, &medium, &mut out), Err(RenderError::EmptyImage { .. })));
    let big_cam = camera(64, 29, 32.0);
    assert!(matches!(
        fwd(&mut ws, &g, &big_cam, &MediumPlanes::new(64, 29), &mut RenderOutput::new(64, 29)),
        Err(RenderError::CapacityExceeded { .. })
    ));
    let distorted = cam.with_distortion(RadTan { k1: 0.1, k2: 0.0, p1: 0.0, p2: 0.0, k3: 0.0 }).unwrap();
    assert_eq!(fwd(&mut ws, &g, &distorted, &medium, &mut out), Err(RenderError::DistortedCamera));
    let bad_config = RenderConfig { near_z_m: 0.0, ..config };
    assert!(matches!(ws.forward(&g, &cam, &pose, &medium, &bad_config, &mut out), Err(RenderError::InvalidConfig { .. })));

    // Backward: NaN upstream, wrong gradient length, changed map.
    assert!(fwd(&mut ws, &g, &cam, &medium, &mut out).is_ok());
    let mut grads = GaussianGrads::with_capacity(8);
    let mut mg = MediumPlanes::new(w, h);
    let mut up = RenderUpstream::new(w, h);
    assert_eq!(ws.backward(&g, &medium, &out, &up, &mut grads, &mut mg), Err(RenderError::GradLenMismatch { grads: 0, gaussians: 4 }));
    grads.reset(4).unwrap();
    up.depth.data[3 * w + 2] = f32::NAN;
    assert!(matches!(
        ws.backward(&g, &medium, &out, &up, &mut grads, &mut mg),
        Err(RenderError::BadPixel { what: "dL/ddepth", x: 2, y: 3, .. })
    ));
    up.depth.data[3 * w + 2] = 0.0;
    assert!(ws.backward(&g, &medium, &out, &up, &mut grads, &mut mg).is_ok());
    let mut more = g.clone();
    more.push(&plain([0.0; 3], 0.1, 0.0, [0.5; 3])).unwrap();
    assert!(matches!(ws.backward(&more, &medium, &out, &up, &mut grads, &mut mg), Err(RenderError::NoForward { .. })));
    // Extreme but finite parameters are culled, not a panic.
    let mut extreme = g.clone();
    extreme.group_mut(ParamGroup::LogScale)[0..3].fill(200.0);
    extreme.group_mut(ParamGroup::Mean)[3..6].copy_from_slice(&[1e30, -1e30, 1e30]);
    assert!(fwd(&mut ws, &extreme, &cam, &medium, &mut out).is_ok());
    assert!(out.colour.data.iter().all(|v| v.is_finite()));
}

// ---------------------------------------------------------------------------------------
// Gradient checks.

/// Central difference of `f` at `x` along coordinate `k` with step `h`, and with step `h/2`
/// (the two disagree on a kink).
fn central(f: &mut impl FnMut(f64) -> f64, x: f64, h: f64) -> (f64, f64) {
    let d1 = (f(x + h) - f(x - h)) / (2.0 * h);
    let d2 = (f(x + 0.5 * h) - f(x - 0.5 * h)) / h;
    (d1, d2)
}

/// Compares analytic and numeric gradients of one group; returns (max relative error, kinks).
struct GroupCheck {
    name: String,
    pairs: Vec<(f64, f64, bool)>,
}

impl GroupCheck {
    fn new(name: impl Into<String>) -> Self {
        GroupCheck { name: name.into(), pairs: Vec::new() }
    }
    fn push(&mut self, analytic: f64, numeric: (f64, f64)) {
        let kink = (numeric.0 - numeric.1).abs() > 1e-6 + 1e-4 * numeric.0.abs();
        self.pairs.push((analytic, numeric.0, kink));
    }
    /// Maximum relative error over non-kink entries, and the kink count.
    fn evaluate(&self) -> (f64, usize) {
        let scale = self.pairs.iter().filter(|p| !p.2).map(|p| p.1.abs()).fold(0.0, f64::max);
        let floor = (GRAD_FLOOR_FRACTION * scale).max(1e-12);
        let err = self.pairs.iter().filter(|p| !p.2).map(|&(a, n, _)| (a - n).abs() / n.abs().max(floor)).fold(0.0, f64::max);
        (err, self.pairs.iter().filter(|p| p.2).count())
    }
}

fn assert_groups(groups: &[GroupCheck], tol: f64) {
    let mut total = 0;
    let mut kinks = 0;
    for g in groups {
        let (err, k) = g.evaluate();
        let scale = g.pairs.iter().map(|p| p.1.abs()).fold(0.0, f64::max);
        eprintln!("  {:<14} {:>5} values, max |grad| {:>9.3e}, max rel err {:>9.2e}, kinks {}", g.name, g.pairs.len(), scale, err, k);
        assert!(err <= tol, "{}: relative error {err} > {tol}", g.name);
        total += g.pairs.len();
        kinks += k;
    }
    assert!((kinks as f64) <= MAX_KINK_SHARE * total as f64, "{kinks} of {total} values on kinks");
}

fn splat_dot(s: &ProjectedSplat<f64>, g: &SplatGrad<f64>) -> f64 {
    let mut v = g.opacity * s.opacity + g.z * s.z;
    for i in 0..2 {
        v += g.mean2d[i] * s.mean2d[i];
    }
    for i in 0..3 {
        v += g.conic[i] * s.conic[i] + g.colour[i] * s.colour[i];
    }
    v
}

fn random_splat_grad(rng: &mut Rng) -> SplatGrad<f64> {
    let mut r = || rng.range(-1.0, 1.0);
    SplatGrad {
        mean2d: [r(), r()],
        conic: [r() * 10.0, r() * 10.0, r() * 10.0],
        opacity: r(),
        colour: [r(), r(), r()],
        z: r(),
        mean2d_densify: [0.0; 2],
        pixels: 1,
    }
}

#[test]
fn projection_backward_matches_central_differences_in_f64() {
    let cam = camera(37, 29, 32.0);
    let cam_from_world = world_from_cam().inverse();
    let setup = ProjectionSetup::<f64>::new(&cam, &cam_from_world, &RenderConfig::default()).unwrap();
    let mut rng = Rng::new(21);
    let g = random_gaussians(&mut rng, 40, 40, &cam, &world_from_cam(), (0.5, 6.0), (0.5, 12.0), (-3.0, 3.0));
    let mut groups: Vec<GroupCheck> = ParamGroup::ALL.iter().map(|g| GroupCheck::new(g.name())).collect();
    for i in 0..g.len() {
        let mut p = g.get(i).map(f64::from);
        // Some means outside the Jacobian's clamp range, some colours clamped at zero.
        if i % 5 == 1 {
            let p_in_cam = cam_from_world * nalgebra::Point3::new(p.mean[0], p.mean[1], p.mean[2]);
            let z = p_in_cam.z;
            let p_in_cam = nalgebra::Point3::new(1.2 * z * if i % 2 == 0 { 1.0 } else { -1.0 }, p_in_cam.y, z);
            let m = world_from_cam() * p_in_cam;
            p.mean = [m.x, m.y, m.z];
        }
        if i % 7 == 3 {
            p.f_dc[1] = -3.0;
        }
        let sg = random_splat_grad(&mut rng);
        let Some(analytic) = project_splat_backward(&p, &setup, &sg) else { continue };
        let analytic = analytic.to_array();
        let x0 = p.to_array();
        for k in 0..PARAMS_PER_GAUSSIAN {
            let mut f = |v: f64| {
                let mut x = x0;
                x[k] = v;
                project_splat(&GaussianParam::from_array(&x), &setup).map_or(0.0, |(s, _)| splat_dot(&s, &sg))
            };
            let num = central(&mut f, x0[k], FD_STEP);
            let group = ParamGroup::ALL.iter().position(|g| k >= g.offset() && k < g.offset() + g.width()).unwrap();
            groups[group].push(analytic[k], num);
        }
    }
    eprintln!("projection backward (f64) vs central differences:");
    assert_groups(&groups, F64_GRAD_REL_TOL);
}

/// (group, index) of every differentiable splat field: mean2d, conic, opacity, colour, z.
const SPLAT_FIELDS: [(usize, usize); 10] = [(0, 0), (0, 1), (1, 0), (1, 1), (1, 2), (2, 0), (3, 0), (3, 1), (3, 2), (4, 0)];

fn splat_field(s: &mut ProjectedSplat<f64>, group: usize, idx: usize) -> &mut f64 {
    match group {
        0 => &mut s.mean2d[idx],
        1 => &mut s.conic[idx],
        2 => &mut s.opacity,
        3 => &mut s.colour[idx],
        _ => &mut s.z,
    }
}

/// A splat gradient laid out as a splat, so [`splat_field`] reads both.
fn splat_grad_as_splat(g: &SplatGrad<f64>) -> ProjectedSplat<f64> {
    ProjectedSplat { mean2d: g.mean2d, conic: g.conic, z: g.z, opacity: g.opacity, colour: g.colour, q_max: 0.0 }
}

fn pixel_loss(px: &PixelForward<f64>, up: &PixelUpstream<f64>) -> f64 {
    let mut l = up.depth * px.depth + up.depth_var * px.depth_var + up.alpha * px.alpha;
    for c in 0..3 {
        l += up.colour[c] * px.colour[c] + up.restored[c] * px.restored[c];
    }
    l
}

#[test]
fn pixel_backward_matches_central_differences_in_f64() {
    let mut rng = Rng::new(31);
    let mut groups: Vec<GroupCheck> =
        ["mean2d", "conic", "opacity", "colour", "z", "c_med", "sigma_att", "sigma_bs"].into_iter().map(GroupCheck::new).collect();
    for trial in 0..40 {
        let mode = if trial % 2 == 0 { DepthMode::InverseDepth } else { DepthMode::Depth };
        let ray = PixelRay::new(10, 7, 30.0, 30.0, 18.0, 14.0);
        let n = 2 + trial % 7;
        let mut splats: Vec<ProjectedSplat<f64>> = (0..n)
            .map(|_| {
                let (a, c) = (rng.range(0.05, 0.5), rng.range(0.05, 0.5));
                let b = rng.range(-0.5, 0.5) * (a * c).sqrt();
                ProjectedSplat {
                    mean2d: [10.0 + rng.range(-3.0, 3.0), 7.0 + rng.range(-3.0, 3.0)],
                    conic: [a, b, c],
                    z: rng.range(1.0, 6.0),
                    opacity: rng.range(0.1, 0.9),
                    colour: [rng.range(0.0, 1.0), rng.range(0.0, 1.0), rng.range(0.0, 1.0)],
                    q_max: f64::INFINITY,
                }
            })
            .collect();
        splats.sort_by(|a, b| a.z.total_cmp(&b.z));
        let medium = PixelMedium {
            c_med: [rng.range(0.05, 0.6), rng.range(0.05, 0.6), rng.range(0.05, 0.6)],
            sigma_att: [rng.range(0.02, 0.5), rng.range(0.02, 0.5), rng.range(0.02, 0.5)],
            sigma_bs: [rng.range(0.02, 0.5), rng.range(0.02, 0.5), rng.range(0.02, 0.5)],
        };
        let mut r = || rng.range(-1.0, 1.0);
        let up = PixelUpstream { colour: [r(), r(), r()], restored: [r(), r(), r()], depth: r(), depth_var: r(), alpha: r() };
        let fwd = blend_pixel(0..n, |k| splats[k], &ray, &medium, mode);
        let state = PixelState { depth: fwd.depth, depth_var: fwd.depth_var, alpha: fwd.alpha, final_t: fwd.final_t };
        let mut analytic = vec![SplatGrad::<f64>::default(); n];
        let medium_grad = backprop_pixel(0..fwd.end, |k| splats[k], &ray, &medium, mode, &state, &up, |k, g| analytic[k].add(g));
        let loss = |splats: &[ProjectedSplat<f64>], medium: &PixelMedium<f64>| {
            pixel_loss(&blend_pixel(0..n, |k| splats[k], &ray, medium, mode), &up)
        };
        for k in 0..n {
            for (group, idx) in SPLAT_FIELDS {
                let mut f = |v: f64| {
                    let mut s = splats.clone();
                    *splat_field(&mut s[k], group, idx) = v;
                    loss(&s, &medium)
                };
                let x0 = *splat_field(&mut splats[k].clone(), group, idx);
                let num = central(&mut f, x0, FD_STEP);
                groups[group].push(*splat_field(&mut splat_grad_as_splat(&analytic[k]), group, idx), num);
            }
        }
        for (slot, grads) in [(5, medium_grad.c_med), (6, medium_grad.sigma_att), (7, medium_grad.sigma_bs)] {
            for c in 0..3 {
                let mut f = |v: f64| {
                    let mut m = medium;
                    match slot {
                        5 => m.c_med[c] = v,
                        6 => m.sigma_att[c] = v,
                        _ => m.sigma_bs[c] = v,
                    }
                    loss(&splats, &m)
                };
                let x0 = [medium.c_med, medium.sigma_att, medium.sigma_bs][slot - 5][c];
                groups[slot].push(grads[c], central(&mut f, x0, FD_STEP));
            }
        }
    }
    eprintln!("pixel backward (f64) vs central differences:");
    assert_groups(&groups, F64_GRAD_REL_TOL);
}

/// The random linear loss `sum(g * outputs)` of the f64 reference.
fn reference_loss(view: &ReferenceView, medium: &MediumPlanes, up: &RenderUpstream, width: usize, height: usize) -> f64 {
    let mut l = 0.0;
    for y in 0..height {
        for x in 0..width {
            let px = view.pixel(x, y, &medium_f64(medium, x, y));
            l += pixel_loss(&px, &upstream_f64(up, y * width + x));
        }
    }
    l
}

fn upstream_f64(up: &RenderUpstream, i: usize) -> PixelUpstream<f64> {
    let p = up.pixel(i);
    PixelUpstream {
        colour: p.colour.map(f64::from),
        restored: p.restored.map(f64::from),
        depth: p.depth as f64,
        depth_var: p.depth_var as f64,
        alpha: p.alpha as f64,
    }
}

/// Image and scene of an end-to-end gradient check.
struct CheckScene {
    width: usize,
    height: usize,
    focal_px: f64,
    sigma_px: (f64, f64),
    logits: (f64, f64),
}

const SPARSE: CheckScene = CheckScene { width: 37, height: 29, focal_px: 32.0, sigma_px: (1.5, 5.0), logits: (-1.5, 1.5) };

fn end_to_end_check(seed: u64, n: usize, mode: DepthMode, scene: CheckScene) {
    let (w, h) = (scene.width, scene.height);
    let cam = camera(w, h, scene.focal_px);
    let cam_from_world = world_from_cam().inverse();
    let config = RenderConfig { depth_mode: mode, ..RenderConfig::default() };
    let mut rng = Rng::new(seed);
    let mut g = random_gaussians(&mut rng, n, n, &cam, &world_from_cam(), (1.5, 5.0), scene.sigma_px, scene.logits);
    // One colour channel clamped at zero.
    let mut p = g.get(1);
    p.f_dc[2] = -3.0;
    g.set(1, &p);
    let medium = random_medium(&mut rng, w, h);
    let up = random_upstream(&mut rng, w, h);

    let (mut ws, out) = render(&g, &cam, &cam_from_world, &medium, &config);
    let terminated = out.final_t.data.iter().filter(|&&t| t < 1e-3).count();
    let clamped = (0..w * h)
        .filter(|&i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            ws.splats().iter().any(|s| {
                let (dx, dy) = (x - s.mean2d[0], y - s.mean2d[1]);
                s.opacity * (-0.5 * (s.conic[0] * dx * dx + 2.0 * s.conic[1] * dx * dy + s.conic[2] * dy * dy)).exp() > 0.99
            })
        })
        .count();
    let mut grads = GaussianGrads::with_capacity(n);
    grads.reset(n).unwrap();
    let mut medium_grads = MediumPlanes::new(w, h);
    ws.backward(&g, &medium, &out, &up, &mut grads, &mut medium_grads).unwrap();

    let params: Vec<GaussianParam<f64>> = (0..n).map(|i| g.get(i).map(f64::from)).collect();
    let mut groups: Vec<GroupCheck> = ParamGroup::ALL.iter().map(|g| GroupCheck::new(g.name())).collect();
    for i in 0..n {
        let analytic = grads.get(i).to_array();
        let x0 = params[i].to_array();
        for k in 0..PARAMS_PER_GAUSSIAN {
            let mut f = |v: f64| {
                let mut ps = params.clone();
                let mut x = x0;
                x[k] = v;
                ps[i] = GaussianParam::from_array(&x);
                let view = ReferenceView::new(&ps, &cam, &cam_from_world, &config).unwrap();
                reference_loss(&view, &medium, &up, w, h)
            };
            let num = central(&mut f, x0[k], FD_STEP);
            let group = ParamGroup::ALL.iter().position(|g| k >= g.offset() && k < g.offset() + g.width()).unwrap();
            groups[group].push(analytic[k] as f64, num);
        }
    }
    let view = ReferenceView::new(&params, &cam, &cam_from_world, &config).unwrap();
    let mut medium_groups = ["c_med", "sigma_att", "sigma_bs"].map(GroupCheck::new);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let m0 = medium_f64(&medium, x, y);
            let upx = upstream_f64(&up, i);
            for (slot, plane) in [&medium_grads.c_med, &medium_grads.sigma_att, &medium_grads.sigma_bs].into_iter().enumerate() {
                for c in 0..3 {
                    let mut f = |v: f64| {
                        let mut m = m0;
                        [&mut m.c_med, &mut m.sigma_att, &mut m.sigma_bs][slot][c] = v;
                        pixel_loss(&view.pixel(x, y, &m), &upx)
                    };
                    let x0 = [m0.c_med, m0.sigma_att, m0.sigma_bs][slot][c];
                    medium_groups[slot].push(plane.data[i * 3 + c] as f64, central(&mut f, x0, FD_STEP));
                }
            }
        }
    }
    eprintln!(
        "f32 pipeline vs f64 central differences ({n} Gaussians, {w}x{h}, {mode:?}, {terminated} pixels near \
         termination, {clamped} with a clamped alpha):"
    );
    groups.extend(medium_groups);
    assert_groups(&groups, GRAD_REL_TOL);
    // The clamped channel has no gradient.
    assert_eq!(grads.get(1).f_dc[2], 0.0);
}

#[test]
fn pipeline_gradients_match_central_differences_inverse_depth() {
    end_to_end_check(41, 14, DepthMode::InverseDepth, SPARSE);
}

#[test]
fn pipeline_gradients_match_central_differences_depth() {
    end_to_end_check(42, 8, DepthMode::Depth, SPARSE);
}

/// Heavy overlap: alphas clamped at 0.99 and blending stopped early at many pixels.
#[test]
fn pipeline_gradients_match_central_differences_dense() {
    let dense = CheckScene { width: 21, height: 19, focal_px: 24.0, sigma_px: (3.0, 8.0), logits: (0.5, 5.5) };
    end_to_end_check(43, 24, DepthMode::InverseDepth, dense);
}

#[test]
fn densification_statistics() {
    let (w, h) = (37, 29);
    let cam = PinholeCamera::new(40.0, 40.0, 18.0, 14.0, w, h).unwrap();
    let mut g = Gaussians::with_capacity(1);
    let z = 3.0f32;
    g.push(&plain([0.0, 0.0, z], 0.2, 0.5, [0.6, 0.5, 0.4])).unwrap();
    // A loss whose per-pixel mean gradients all point the same way in x: L = sum alpha (x - cx).
    let mut up = RenderUpstream::new(w, h);
    for y in 0..h {
        for x in 0..w {
            up.alpha.data[y * w + x] = x as f32 - 18.0;
        }
    }
    let mut norms = Vec::new();
    for sigma in [0.0f32, 0.3] {
        let medium = MediumPlanes::uniform(w, h, [0.2; 3], [sigma; 3], [0.1; 3]);
        let (mut ws, out) = render(&g, &cam, &Se3::identity(), &medium, &RenderConfig::default());
        let mut grads = GaussianGrads::with_capacity(1);
        grads.reset(1).unwrap();
        let mut mg = MediumPlanes::new(w, h);
        ws.backward(&g, &medium, &out, &up, &mut grads, &mut mg).unwrap();
        // Pixels touched: every pixel where the lone Gaussian's alpha reaches 1/255.
        let touched = out.alpha.data.iter().filter(|&&a| a as f64 >= ALPHA_MIN).count();
        assert_eq!(grads.pixels_touched()[0] as usize, touched);
        assert_eq!(grads.views()[0], 1);
        norms.push(grads.densify_grad_norm()[0] as f64);
        // A second view accumulates.
        ws.backward(&g, &medium, &out, &up, &mut grads, &mut mg).unwrap();
        assert_eq!(grads.views()[0], 2);
        assert!(close(grads.densify_grad_norm()[0] as f64, 2.0 * norms.last().unwrap(), 1e-4 * norms.last().unwrap()));
    }
    // With attenuation the screen-space gradient is scaled by exp(sigma t), t = z |ray| over
    // the footprint (|ray| in [1, 1.02] within 7 px of the axis at f = 40).
    let ratio = norms[1] / norms[0];
    let (lo, hi) = ((0.3 * z as f64).exp(), (0.3 * z as f64 * 1.02).exp());
    assert!(norms[0] > 0.0 && ratio >= lo * (1.0 - 1e-5) && ratio <= hi, "ratio {ratio} outside [{lo}, {hi}]");
}
