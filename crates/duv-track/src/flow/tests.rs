//! Acceptance tests of the flow front end on procedural underwater images with known warps.

use super::synth::{self, Water};
use super::*;
use duv_core::{ImageRgbF32, PlaneF32};
use nalgebra::{Matrix3, Vector3};

/// Input size of the tests (the CI board's camera).
const W: usize = 320;
const H: usize = 240;
/// Canvas margin around the view, so that moving views see new content.
const MARGIN: usize = 48;
/// Input pixels at the border left out of accuracy statistics.
const BORDER_PX: f32 = 12.0;
/// Sensor noise of the synthetic camera (intensity units, before 8-bit quantisation).
const CAMERA_NOISE: f32 = 0.003;

/// Median end-point error bounds, input pixels.
const TRANSLATION_EPE_PX: f32 = 0.1;
const WARP_EPE_PX: f32 = 0.25;
const PHOTOMETRIC_EPE_PX: f32 = 0.3;
/// Median forward-backward error where the flow is right, finest-level pixels.
const FB_CONSISTENT_PX: f32 = 0.1;
/// Textured consistent regions must carry at least this many times the mean weight of
/// occluded, out-of-view or textureless ones.
const CONFIDENCE_RATIO: f32 = 4.0;

/// A known motion of the view: `fwd` maps a source pixel to its destination, `inv` back.
trait Warp {
    fn fwd(&self, x: f32, y: f32) -> (f32, f32);
    fn inv(&self, x: f32, y: f32) -> (f32, f32);
}

struct Translation(f32, f32);

impl Warp for Translation {
    fn fwd(&self, x: f32, y: f32) -> (f32, f32) {
        (x + self.0, y + self.1)
    }
    fn inv(&self, x: f32, y: f32) -> (f32, f32) {
        (x - self.0, y - self.1)
    }
}

/// `x' = centre + scale R(angle) (x - centre) + t`, as a homography.
fn similarity(angle_deg: f64, scale: f64, tx: f64, ty: f64) -> Homography {
    let (c, s) = (angle_deg.to_radians().cos() * scale, angle_deg.to_radians().sin() * scale);
    let (cx, cy) = (W as f64 / 2.0, H as f64 / 2.0);
    let to_centre = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let back = Matrix3::new(1.0, 0.0, cx + tx, 0.0, 1.0, cy + ty, 0.0, 0.0, 1.0);
    Homography::new(back * Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0) * to_centre)
}

struct Homography {
    m: Matrix3<f64>,
    m_inv: Matrix3<f64>,
}

impl Homography {
    fn new(m: Matrix3<f64>) -> Self {
        Homography { m, m_inv: m.try_inverse().expect("invertible warp") }
    }
    fn apply(m: &Matrix3<f64>, x: f32, y: f32) -> (f32, f32) {
        let p = m * Vector3::new(x as f64, y as f64, 1.0);
        ((p.x / p.z) as f32, (p.y / p.z) as f32)
    }
}

impl Warp for Homography {
    fn fwd(&self, x: f32, y: f32) -> (f32, f32) {
        Homography::apply(&self.m, x, y)
    }
    fn inv(&self, x: f32, y: f32) -> (f32, f32) {
        Homography::apply(&self.m_inv, x, y)
    }
}

/// Scene canvas for the test views.
fn canvas(seed: u64) -> ImageRgbF32 {
    synth::radiance(W + 2 * MARGIN, H + 2 * MARGIN, seed)
}

/// Source and destination colour views of `canvas` through water, before the camera.
fn views(canvas: &ImageRgbF32, warp: &dyn Warp) -> (ImageRgbF32, ImageRgbF32) {
    let mut src = synth::render(canvas, MARGIN, W, H, |x, y| (x, y));
    let mut dst = synth::render(canvas, MARGIN, W, H, |x, y| warp.inv(x, y));
    synth::through_water(&mut src, &Water::default());
    synth::through_water(&mut dst, &Water::default());
    (src, dst)
}

fn cameras(src: &ImageRgbF32, dst: &ImageRgbF32) -> (PlaneF32, PlaneF32) {
    (synth::camera_gray(src, CAMERA_NOISE, 101), synth::camera_gray(dst, CAMERA_NOISE, 202))
}

fn pair(warp: &dyn Warp, seed: u64) -> (PlaneF32, PlaneF32) {
    let (s, d) = views(&canvas(seed), warp);
    cameras(&s, &d)
}

fn run(cfg: FlowConfig, src: &PlaneF32, dst: &PlaneF32, seed: Option<&FlowField>) -> (FlowEstimator, FlowResult) {
    let mut est = FlowEstimator::new(cfg, src.width, src.height).unwrap();
    let a = est.prepare(src).unwrap();
    let b = est.prepare(dst).unwrap();
    let mut out = est.new_result();
    est.estimate(&a, &b, seed, &mut out).unwrap();
    (est, out)
}

fn median(mut v: Vec<f32>) -> f32 {
    assert!(!v.is_empty());
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// End-point errors (input pixels) of `flow` against `warp` at grid pixels whose centre and
/// true target are at least `BORDER_PX` inside the image and where `keep` holds.
fn epes(flow: &FlowField, warp: &dyn Warp, keep: impl Fn(f32, f32) -> bool) -> Vec<f32> {
    let c = flow.cell_px;
    let inside =
        |x: f32, y: f32| x >= BORDER_PX && y >= BORDER_PX && x <= W as f32 - BORDER_PX && y <= H as f32 - BORDER_PX;
    let mut out = Vec::new();
    for j in 0..flow.height() {
        for i in 0..flow.width() {
            let (x, y) = (cell_centre(c, i as f32), cell_centre(c, j as f32));
            let (tx, ty) = warp.fwd(x, y);
            if !(inside(x, y) && inside(tx, ty) && keep(x, y)) {
                continue;
            }
            let (u, v) = flow.get(i, j);
            let (eu, ev) = (u * c as f32 - (tx - x), v * c as f32 - (ty - y));
            out.push((eu * eu + ev * ev).sqrt());
        }
    }
    out
}

fn median_epe(flow: &FlowField, warp: &dyn Warp) -> f32 {
    median(epes(flow, warp, |_, _| true))
}

#[test]
fn translation_is_recovered_to_a_tenth_of_a_pixel() {
    let warp = Translation(3.4, -2.1);
    let (src, dst) = pair(&warp, 1);
    let (est, out) = run(FlowConfig::default(), &src, &dst, None);
    let e = median_epe(&out.flow, &warp);
    eprintln!("translation: median EPE {e:.4} px, stats {:?}", out.stats);
    assert!(e < TRANSLATION_EPE_PX, "median EPE {e} px");
    // The backward flow is the inverse translation.
    let back = median_epe(&out.backward, &Translation(-3.4, 2.1));
    assert!(back < TRANSLATION_EPE_PX, "backward median EPE {back} px");
    assert_eq!(out.stats.start_level, est.coarsest_level());
    assert!((out.stats.mean_flow_input_px - 4.0).abs() < 0.1, "{:?}", out.stats);
}

#[test]
fn similarity_and_perspective_warps_are_recovered() {
    let sim = similarity(3.0, 1.04, 2.5, -1.5);
    let (src, dst) = pair(&sim, 2);
    let (_, out) = run(FlowConfig::default(), &src, &dst, None);
    let e = median_epe(&out.flow, &sim);
    eprintln!("similarity: median EPE {e:.4} px");
    assert!(e < WARP_EPE_PX, "similarity median EPE {e} px");

    let persp = Homography::new(Matrix3::new(1.02, 0.015, 2.0, -0.01, 0.99, 1.0, 1.2e-4, -8e-5, 1.0));
    let (src, dst) = pair(&persp, 3);
    let (_, out) = run(FlowConfig::default(), &src, &dst, None);
    let e = median_epe(&out.flow, &persp);
    eprintln!("perspective: median EPE {e:.4} px");
    assert!(e < WARP_EPE_PX, "perspective median EPE {e} px");
}

#[test]
fn large_motion_is_recovered_through_the_pyramid() {
    let warp = Translation(20.0, -7.0);
    let (src, dst) = pair(&warp, 4);
    let (est, out) = run(FlowConfig::default(), &src, &dst, None);
    let e = median_epe(&out.flow, &warp);
    eprintln!("large motion: median EPE {e:.4} px from level {}", est.coarsest_level());
    assert!(e < WARP_EPE_PX, "median EPE {e} px");
}

#[test]
fn a_good_seed_needs_fewer_levels_and_iterations() {
    let warp = similarity(2.0, 1.02, 18.0, -9.0);
    let (src, dst) = pair(&warp, 5);
    // A BA-like seed: the true flow on the 1/8 grid, off by 0.4 px and slightly scaled.
    let seed = FlowField::from_fn(W, H, 8, |x, y| {
        let (tx, ty) = warp.fwd(x, y);
        (1.01 * (tx - x) + 0.4, 1.01 * (ty - y) - 0.3)
    });
    let cheap = FlowConfig { coarsest_level_seeded: Some(1), patch_iterations: 3, ..FlowConfig::default() };
    let (est, seeded) = run(cheap.clone(), &src, &dst, Some(&seed));
    assert_eq!(seeded.stats.start_level, 1);
    let e_seeded = median_epe(&seeded.flow, &warp);
    // The same budget without the seed: one level cannot bridge 20 px.
    let unseeded_cfg = FlowConfig { coarsest_level: Some(1), ..cheap };
    let (_, unseeded) = run(unseeded_cfg, &src, &dst, None);
    let e_unseeded = median_epe(&unseeded.flow, &warp);
    let (_, full) = run(FlowConfig::default(), &src, &dst, None);
    let e_full = median_epe(&full.flow, &warp);
    eprintln!(
        "seeded (1 level, 3 iterations): {e_seeded:.4} px; unseeded same budget: {e_unseeded:.3} px; \
         unseeded full pyramid ({} levels, 8 iterations): {e_full:.4} px",
        est.coarsest_level()
    );
    assert!(e_seeded < WARP_EPE_PX, "seeded median EPE {e_seeded} px");
    assert!(e_unseeded > 1.0, "one level should not bridge the motion without a seed: {e_unseeded} px");
    assert!(e_full < WARP_EPE_PX);
}

#[test]
fn contrast_loss_colour_cast_and_haze_still_match() {
    let warp = similarity(1.5, 1.01, 3.3, 2.2);
    let (src_rgb, mut dst_rgb) = views(&canvas(6), &warp);
    synth::photometric_change(&mut dst_rgb, 0.6, [0.9, 1.05, 1.12], [0.02, 0.05, 0.07], [0.0, 0.08, 0.1]);
    let (src, dst) = cameras(&src_rgb, &dst_rgb);
    for feature in [FeatureKind::LocalNormalized, FeatureKind::SoftCensus] {
        let (_, out) = run(FlowConfig { feature, ..FlowConfig::default() }, &src, &dst, None);
        let e = median_epe(&out.flow, &warp);
        eprintln!("photometric change, {feature:?}: median EPE {e:.4} px, mean weight {:.3}", out.stats.mean_weight);
        assert!(e < PHOTOMETRIC_EPE_PX, "{feature:?}: median EPE {e} px");
        assert!(out.stats.mean_weight > 0.3, "{feature:?}: {:?}", out.stats);
    }
    let (_, raw) = run(FlowConfig { feature: FeatureKind::Intensity, ..FlowConfig::default() }, &src, &dst, None);
    eprintln!("photometric change, Intensity (baseline): median EPE {:.4} px", median_epe(&raw.flow, &warp));
}

/// Mean of `plane` over finest-grid pixels whose input-pixel centre satisfies `keep`.
fn region_mean(plane: &PlaneF32, cell: usize, keep: impl Fn(f32, f32) -> bool) -> (f32, usize) {
    let mut s = 0.0f64;
    let mut n = 0;
    for j in 0..plane.height {
        for i in 0..plane.width {
            if keep(cell_centre(cell, i as f32), cell_centre(cell, j as f32)) {
                s += plane.data[j * plane.width + i] as f64;
                n += 1;
            }
        }
    }
    assert!(n > 20, "region too small: {n}");
    ((s / n as f64) as f32, n)
}

#[test]
fn confidence_is_low_where_matches_cannot_be_trusted() {
    let warp = Translation(7.0, 3.0);
    let mut scene = canvas(7);
    let inside = |x: f32, y: f32, r: [f32; 4]| x >= r[0] && x < r[2] && y >= r[1] && y < r[3];
    // Textureless sand, attached to the scene (view coordinates of the source).
    let flat = [30.0, 150.0, 110.0, 220.0];
    synth::flat_rect(&mut scene, 30 + MARGIN, 150 + MARGIN, 110 + MARGIN, 220 + MARGIN, [0.6, 0.52, 0.4]);
    // Vertical stripes of an aperiodic profile: texture along x only (aperture problem along y).
    let stripes = [200.0, 140.0, 290.0, 220.0];
    for y in 140..220 {
        for x in 200..290 {
            let t = x as f32;
            let v = 0.5 + 0.12 * (t / 2.3).sin() + 0.1 * (t / 3.7 + 1.0).sin() + 0.08 * (t / 6.1 + 2.0).sin();
            scene.set_pixel(x + MARGIN, y + MARGIN, [v, 0.9 * v, 0.8 * v]);
        }
    }
    let (src_rgb, mut dst_rgb) = views(&scene, &warp);
    // An occluder (a fish) appears in the destination: another texture over a rectangle.
    let occ_dst = [150usize, 30, 230, 100];
    let fish = synth::render(&canvas(77), MARGIN, W, H, |x, y| (x * 0.7, y * 0.7));
    for y in occ_dst[1]..occ_dst[3] {
        for x in occ_dst[0]..occ_dst[2] {
            dst_rgb.set_pixel(x, y, fish.pixel(x, y));
        }
    }
    let (src, dst) = cameras(&src_rgb, &dst_rgb);
    let (_, out) = run(FlowConfig::default(), &src, &dst, None);
    let cell = out.flow.cell_px;
    let shrink = |r: [f32; 4], m: f32| [r[0] + m, r[1] + m, r[2] - m, r[3] - m];
    // Source pixels whose true target lands inside the occluder.
    let occ = shrink(
        [occ_dst[0] as f32 - 7.0, occ_dst[1] as f32 - 3.0, occ_dst[2] as f32 - 7.0, occ_dst[3] as f32 - 3.0],
        10.0,
    );
    let out_of_view = |x: f32, _y: f32| x + 7.0 > W as f32 - 1.0 + 0.5;
    let special = |x: f32, y: f32| {
        inside(x, y, shrink(flat, -16.0)) || inside(x, y, shrink(stripes, -16.0)) || inside(x, y, shrink(occ, -26.0))
    };
    let textured = |x: f32, y: f32| {
        x > BORDER_PX && y > BORDER_PX && x < W as f32 - 20.0 && y < H as f32 - BORDER_PX && !special(x, y)
    };
    let mean_w = |keep: &dyn Fn(f32, f32) -> bool| {
        let (a, _) = region_mean(&out.weight_x, cell, keep);
        let (b, _) = region_mean(&out.weight_y, cell, keep);
        0.5 * (a + b)
    };
    let w_textured = mean_w(&textured);
    let w_flat = mean_w(&|x, y| inside(x, y, shrink(flat, 10.0)));
    let w_occ = mean_w(&|x, y| inside(x, y, occ));
    let w_oov = mean_w(&|x, y| out_of_view(x, y) && y > BORDER_PX && y < H as f32 - BORDER_PX);
    let (sx, _) = region_mean(&out.weight_x, cell, |x, y| inside(x, y, shrink(stripes, 10.0)));
    let (sy, _) = region_mean(&out.weight_y, cell, |x, y| inside(x, y, shrink(stripes, 10.0)));
    let fb_textured = median(
        (0..out.fb_error.data.len())
            .filter(|&i| {
                let (x, y) = (i % out.fb_error.width, i / out.fb_error.width);
                textured(cell_centre(cell, x as f32), cell_centre(cell, y as f32))
            })
            .map(|i| out.fb_error.data[i])
            .collect(),
    );
    let (fb_occ, _) = region_mean(&out.fb_error, cell, |x, y| inside(x, y, occ));
    eprintln!(
        "weights: textured {w_textured:.3}, flat {w_flat:.4}, occluded {w_occ:.4}, out of view {w_oov:.4}, \
         stripes x {sx:.3} y {sy:.4}; fb: textured median {fb_textured:.4}, occluded mean {fb_occ:.3}"
    );
    assert!(w_textured > 0.5, "textured weight {w_textured}");
    assert!(w_textured > CONFIDENCE_RATIO * w_flat, "flat {w_flat} vs textured {w_textured}");
    assert!(w_textured > CONFIDENCE_RATIO * w_occ, "occluded {w_occ} vs textured {w_textured}");
    assert_eq!(w_oov, 0.0, "out-of-view targets must have zero weight");
    assert!(sx > CONFIDENCE_RATIO * sy, "stripes: weight across {sx} vs along {sy}");
    assert!(fb_textured < FB_CONSISTENT_PX, "forward-backward error {fb_textured} px where the flow is right");
    assert!(fb_occ > 5.0 * fb_textured, "occluded fb {fb_occ} vs textured {fb_textured}");
    // The flow is right where the weights say so.
    let e = median(epes(&out.flow, &warp, textured));
    assert!(e < TRANSLATION_EPE_PX, "textured median EPE {e}");
}

#[test]
fn pooled_targets_average_the_full_flow() {
    let warp = Translation(3.4, -2.1);
    let (src, dst) = pair(&warp, 8);
    let (est, out) = run(FlowConfig::default(), &src, &dst, None);
    let (pw, ph) = est.pooled_size();
    assert_eq!((pw, ph), (W / 8, H / 8));
    assert_eq!(out.pooled.flow.cell_px, 8);
    let b = 8 / out.flow.cell_px;
    let fw = out.flow.width();
    let mut errs = Vec::new();
    for j in 0..ph {
        for i in 0..pw {
            // Recompute the confidence-weighted block mean in f64.
            let (mut sw, mut su) = (0.0f64, 0.0f64);
            for y in j * b..(j + 1) * b {
                for x in i * b..(i + 1) * b {
                    let k = y * fw + x;
                    sw += out.weight_x.data[k] as f64;
                    su += (out.weight_x.data[k] * out.flow.dx.data[k]) as f64;
                }
            }
            let (u, v) = out.pooled.flow.get(i, j);
            if sw > 1e-3 {
                assert!((u as f64 - su / sw / b as f64).abs() < 1e-4, "cell ({i}, {j}): {u} vs {}", su / sw / b as f64);
            }
            let (tx, ty) = out.pooled.target(i, j);
            assert_eq!((tx, ty), (i as f32 + u, j as f32 + v));
            let interior = i > 1 && j > 1 && i + 2 < pw && j + 2 < ph;
            if interior && out.pooled.weight_x.data[j * pw + i] > 0.1 {
                errs.push(((u * 8.0 - 3.4).powi(2) + (v * 8.0 + 2.1).powi(2)).sqrt());
            }
        }
    }
    let e = median(errs);
    eprintln!("pooled 1/8 flow: median EPE {e:.4} input px");
    assert!(e < TRANSLATION_EPE_PX, "pooled median EPE {e}");
}

#[test]
fn pooling_a_constant_field_returns_it_whatever_the_weights() {
    let cfg = FlowConfig::default();
    let est = FlowEstimator::new(cfg.clone(), 8 * 40 + 5, 8 * 30 + 3).unwrap();
    let mut out = est.new_result();
    let mut rng = duv_core::rng::Rng::new(9);
    out.flow.dx.data.fill(1.25);
    out.flow.dy.data.fill(-0.5);
    for w in out.weight_x.data.iter_mut().chain(out.weight_y.data.iter_mut()) {
        *w = rng.uniform() as f32;
    }
    confidence::pool(&cfg, est.finest_level(), &mut out);
    let b = 4.0;
    let fw = out.flow.width();
    for j in 0..out.pooled.flow.height() {
        for i in 0..out.pooled.flow.width() {
            let (u, v) = out.pooled.flow.get(i, j);
            assert!((u - 1.25 / b).abs() < 1e-6 && (v + 0.5 / b).abs() < 1e-6, "({i}, {j}): {u} {v}");
            let mean: f32 =
                (0..16).map(|k| out.weight_x.data[(j * 4 + k / 4) * fw + i * 4 + k % 4]).sum::<f32>() / 16.0;
            assert!((out.pooled.weight_x.data[j * out.pooled.flow.width() + i] - mean).abs() < 1e-5);
        }
    }
}

#[test]
fn grid_conversions_follow_the_cell_centre_convention() {
    // Level-1 pixel 0 is centred on input 0.5; a 1/8 cell 0 on input 3.5.
    assert_eq!(cell_centre(2, 0.0), 0.5);
    assert_eq!(cell_centre(8, 1.0), 11.5);
    assert!((convert_coord(8, 2, 1.0) - 5.5).abs() < 1e-6);
    // A linear flow field on the 1/8 grid, read on the 1/2 grid.
    let f = FlowField::from_fn(W, H, 8, |x, y| (0.01 * x + 1.0, -0.02 * y));
    for (x, y) in [(40.0f32, 30.0f32), (100.5, 77.0)] {
        let (u, v) = f.sample_in_grid(2, x, y);
        let (xi, yi) = (cell_centre(2, x), cell_centre(2, y));
        assert!((u * 2.0 - (0.01 * xi + 1.0)).abs() < 1e-4, "{u}");
        assert!((v * 2.0 - (-0.02 * yi)).abs() < 1e-4, "{v}");
    }
}

#[test]
fn downsampling_keeps_pixel_centres() {
    // A ramp in x: level-1 pixel i must read the ramp at 2 i + 0.5.
    let (w, h) = (64, 16);
    let src: Vec<f32> = (0..w * h).map(|i| (i % w) as f32).collect();
    let mut dst = vec![0.0; (w / 2) * (h / 2)];
    let mut tmp = vec![0.0; w * h];
    pyramid::downsample(&src, w, h, &mut dst, &mut tmp);
    for x in 1..w / 2 - 1 {
        assert!((dst[3 * (w / 2) + x] - (2 * x) as f32 - 0.5).abs() < 1e-5);
    }
}

#[test]
fn local_normalisation_cancels_gain_and_offset() {
    let img = synth::camera_gray(&canvas(10), 0.0, 1);
    let (w, h) = (img.width, img.height);
    let changed: Vec<f32> = img.data.iter().map(|v| 0.6 * v + 0.2).collect();
    let (mut a, mut b) = (vec![0.0; w * h], vec![0.0; w * h]);
    let (mut s, mut q) = (vec![0.0; w * h], vec![0.0; w * h]);
    // eps small against the local contrast: invariance is then nearly exact.
    pyramid::local_normalize(&img.data, w, h, 3, 1e-4, &mut a, &mut s, &mut q);
    pyramid::local_normalize(&changed, w, h, 3, 1e-4, &mut b, &mut s, &mut q);
    let diffs: Vec<f32> = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).collect();
    assert!(median(diffs) < 1e-2);
}

#[test]
fn bad_inputs_are_refused_not_panicked_on() {
    let cfg = FlowConfig::default();
    let mut est = FlowEstimator::new(cfg.clone(), W, H).unwrap();
    let (good, _) = pair(&Translation(0.0, 0.0), 11);

    // Image of another size: the message names both sizes.
    let small = PlaneF32::new(160, 120);
    let err = est.prepare(&small).unwrap_err();
    assert!(matches!(err, FlowError::SizeMismatch { .. }));
    let msg = err.to_string();
    assert!(msg.contains("160x120") && msg.contains("320x240"), "{msg}");

    // NaN in the image.
    let mut nan = good.clone();
    nan.data[5 * W + 7] = f32::NAN;
    assert!(matches!(est.prepare(&nan), Err(FlowError::NonFinite { x: 7, y: 5, .. })));

    let a = est.prepare(&good).unwrap();
    let mut out = est.new_result();

    // Frames of another estimator (other size, or other features).
    let mut other = FlowEstimator::new(cfg.clone(), 160, 120).unwrap();
    let b_small = other.prepare(&synth::camera_gray(&synth::radiance(160, 120, 3), 0.0, 1)).unwrap();
    let err = est.estimate(&a, &b_small, None, &mut out).unwrap_err();
    assert!(err.to_string().contains("160x120"), "{err}");
    let mut census = FlowEstimator::new(FlowConfig { feature: FeatureKind::SoftCensus, ..cfg.clone() }, W, H).unwrap();
    let c = census.prepare(&good).unwrap();
    assert!(matches!(est.estimate(&a, &c, None, &mut out), Err(FlowError::ForeignFrame { what: "dst" })));

    // Seeds: non-finite, wrong grid.
    let mut seed = FlowField::constant(W, H, 8, 1.0, 0.0);
    seed.dy.data[3] = f32::INFINITY;
    assert!(matches!(est.estimate(&a, &a, Some(&seed), &mut out), Err(FlowError::NonFinite { what: "seed dy", .. })));
    let seed = FlowField::zeros(W / 8 + 1, H / 8, 8);
    assert!(matches!(est.estimate(&a, &a, Some(&seed), &mut out), Err(FlowError::SeedGrid { .. })));
    let seed = FlowField::zeros(W / 4, H / 4, 0);
    assert!(matches!(est.estimate(&a, &a, Some(&seed), &mut out), Err(FlowError::SeedGrid { .. })));

    // A wild but finite seed (a diverged BA): no panic, no confidence where it points away.
    let wild = FlowField::constant(W, H, 8, 1e30, -1e30);
    est.estimate(&a, &a, Some(&wild), &mut out).unwrap();
    assert!(out.stats.mean_flow_input_px.is_finite() && out.stats.mean_weight.is_finite(), "{:?}", out.stats);
    assert!(out.pooled.weight_x.data.iter().all(|w| w.is_finite()));

    // A result of another estimator.
    let mut wrong = other.new_result();
    assert!(matches!(est.estimate(&a, &a, None, &mut wrong), Err(FlowError::SizeMismatch { what: "result", .. })));

    // An all-black frame: no error, no confidence.
    let black = est.prepare(&PlaneF32::new(W, H)).unwrap();
    est.estimate(&black, &black, None, &mut out).unwrap();
    assert!(out.weight_x.data.iter().chain(&out.weight_y.data).all(|&w| w == 0.0));
    assert!(out.pooled.weight_x.data.iter().all(|&w| w == 0.0));
    assert!(out.flow.dx.data.iter().all(|v| v.is_finite()));
    est.estimate(&a, &black, None, &mut out).unwrap();
    assert!(out.flow.dx.data.iter().chain(&out.flow.dy.data).all(|v| v.is_finite()));
    assert!(out.stats.mean_weight < 0.05, "{:?}", out.stats);

    // Configurations and sizes that cannot work.
    let bad = |c: FlowConfig| FlowEstimator::new(c, W, H).unwrap_err();
    assert!(matches!(
        bad(FlowConfig { output_factor: 6, finest_level: Some(2), ..cfg.clone() }),
        FlowError::Config { field: "output_factor", .. }
    ));
    assert!(matches!(
        bad(FlowConfig { patch_stride: 0, ..cfg.clone() }),
        FlowError::Config { field: "patch_stride", .. }
    ));
    assert!(matches!(
        bad(FlowConfig { noise_sigma: f32::NAN, ..cfg.clone() }),
        FlowError::Config { field: "noise_sigma", .. }
    ));
    assert!(matches!(bad(FlowConfig { coarsest_level: Some(7), ..cfg.clone() }), FlowError::TooSmall { level: 7, .. }));
    assert!(matches!(FlowEstimator::new(cfg.clone(), 12, 12), Err(FlowError::TooSmall { .. })));
    // Odd sizes that do not divide by the output factor are fine.
    let mut odd = FlowEstimator::new(cfg, 8 * 25 + 7, 8 * 20 + 3).unwrap();
    let img = synth::camera_gray(&synth::radiance(8 * 25 + 7, 8 * 20 + 3, 4), CAMERA_NOISE, 1);
    let f = odd.prepare(&img).unwrap();
    let mut r = odd.new_result();
    odd.estimate(&f, &f, None, &mut r).unwrap();
    assert_eq!((r.pooled.flow.width(), r.pooled.flow.height()), (25, 20));
    let e = r.flow.dx.data.iter().chain(&r.flow.dy.data).fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(e < 0.05, "identical frames: max |flow| {e}");
}

#[test]
fn config_round_trips_through_toml_and_refuses_unknown_keys() {
    let cfg = FlowConfig { feature: FeatureKind::SoftCensus, coarsest_level_seeded: Some(2), ..FlowConfig::default() };
    let text = toml::to_string(&cfg).unwrap();
    assert_eq!(toml::from_str::<FlowConfig>(&text).unwrap(), cfg);
    assert_eq!(toml::from_str::<FlowConfig>("").unwrap(), FlowConfig::default());
    assert!(toml::from_str::<FlowConfig>("patch_sise = 8").is_err());
}

#[test]
fn a_pair_estimate_gives_both_edges_of_separate_estimates() {
    // Forward: bit-identical to `estimate` (same passes). Reverse: the backward pass with its
    // own confidences, as accurate as a separate dst -> src estimate on the inverse warp.
    let sim = similarity(2.0, 1.02, 2.5, -1.5);
    let (src, dst) = pair(&sim, 5);
    let mut est = FlowEstimator::new(FlowConfig::default(), src.width, src.height).unwrap();
    let (a, b) = (est.prepare(&src).unwrap(), est.prepare(&dst).unwrap());
    let (mut single, mut fwd, mut rev, mut rev_single) = (est.new_result(), est.new_result(), est.new_result(), est.new_result());
    est.estimate(&a, &b, None, &mut single).unwrap();
    est.estimate_pair(&a, &b, None, &mut fwd, &mut rev).unwrap();
    assert_eq!(single, fwd, "the pair's forward edge differs from a single estimate");
    est.estimate(&b, &a, None, &mut rev_single).unwrap();
    // The reverse flow field is the forward estimate's backward field; its weights are
    // computed for dst -> src (source texture of dst at the pixel).
    assert_eq!(rev.flow.dx.data, single.backward.dx.data);
    assert_eq!(rev.backward.dx.data, single.flow.dx.data);
    let inv = Homography::new(sim.m_inv);
    let (e_pair, e_sep) = (median_epe(&rev.flow, &inv), median_epe(&rev_single.flow, &inv));
    eprintln!("reverse edge: median EPE pair {e_pair:.4} px, separate {e_sep:.4} px");
    assert!(e_pair < WARP_EPE_PX && e_pair < 1.5 * e_sep + 0.02, "pair {e_pair} separate {e_sep}");
    let mean = |p: &PlaneF32| p.data.iter().sum::<f32>() / p.data.len() as f32;
    let (wp, ws) = (mean(&rev.weight_x), mean(&rev_single.weight_x));
    assert!((wp - ws).abs() < 0.1 * ws, "reverse weights: pair {wp}, separate {ws}");
    // Size checks apply to the reverse result too.
    let mut wrong = FlowEstimator::new(FlowConfig::default(), src.width / 2, src.height / 2).unwrap().new_result();
    assert!(matches!(est.estimate_pair(&a, &b, None, &mut fwd, &mut wrong), Err(FlowError::SizeMismatch { .. })));
}

#[test]
fn a_forward_only_estimate_matches_the_forward_pass_and_drops_only_the_check() {
    let warp = similarity(2.0, 1.02, 2.5, -1.5);
    let (src, dst) = pair(&warp, 5);
    let (mut est, both) = run(FlowConfig::default(), &src, &dst, None);
    let (a, b) = (est.prepare(&src).unwrap(), est.prepare(&dst).unwrap());
    let mut fwd = est.new_result();
    est.estimate_with(&a, &b, None, &mut fwd, false).unwrap();
    // The forward pass is the same computation either way.
    assert_eq!(fwd.flow.dx.data, both.flow.dx.data);
    assert_eq!(fwd.flow.dy.data, both.flow.dy.data);
    assert!(fwd.backward.dx.data.iter().chain(&fwd.backward.dy.data).all(|v| *v == 0.0));
    assert!(fwd.fb_error.data.iter().all(|e| *e == 0.0 || e.is_infinite()), "no forward-backward error without the check");
    // Without the check's factor no weight is lower, and somewhere (where the check
    // disagreed) it is higher.
    let pairs = fwd.weight_x.data.iter().zip(&both.weight_x.data);
    assert!(pairs.clone().all(|(f, b)| f >= b));
    assert!(pairs.clone().any(|(f, b)| *f > b + 1e-3));
    let e = median_epe(&fwd.flow, &warp);
    assert!(e < WARP_EPE_PX, "median EPE {e} px");
    // The configured `forward_backward` is still what `estimate` uses.
    let mut again = est.new_result();
    est.estimate(&a, &b, None, &mut again).unwrap();
    assert_eq!(again.weight_x.data, both.weight_x.data);
}

#[test]
fn a_coarse_screen_tells_an_overlapping_view_from_an_unrelated_one() {
    let warp = similarity(2.0, 1.02, 2.5, -1.5);
    let (src, dst) = pair(&warp, 5);
    let (other, _) = pair(&warp, 9);
    let (mut est, full) = run(FlowConfig::default(), &src, &dst, None);
    let (a, b, c) = (est.prepare(&src).unwrap(), est.prepare(&dst).unwrap(), est.prepare(&other).unwrap());
    let level = est.finest_level() + 1;
    let same = est.screen(&a, &b, None, level, 0.05).unwrap();
    let unrelated = est.screen(&a, &c, None, level, 0.05).unwrap();
    eprintln!("screen: overlapping {same:?}, unrelated {unrelated:?}, full estimate {:?}", full.stats);
    assert_eq!(same.level, level);
    assert!(same.confident_fraction > 0.8, "{same:?}");
    // Unrelated textured views still match here and there by chance (12 % of the cells here).
    assert!(unrelated.confident_fraction < 0.25 * same.confident_fraction, "{unrelated:?}");
    // The screen's flow is the estimate's at a coarser level: the same mean magnitude.
    let rel = (same.mean_flow_input_px - full.stats.mean_flow_input_px).abs() / full.stats.mean_flow_input_px;
    assert!(rel < 0.1, "screen {} px, estimate {} px", same.mean_flow_input_px, full.stats.mean_flow_input_px);
    // A stricter cell weight counts fewer cells.
    let strict = est.screen(&a, &b, None, level, 0.5).unwrap();
    assert!(strict.confident_fraction < same.confident_fraction, "{strict:?} vs {same:?}");
    // Levels outside finest ..= start, or whose cells do not divide the output grid's, are refused.
    for bad in [est.finest_level() - 1, est.coarsest_level() + 1, 4] {
        assert!(matches!(est.screen(&a, &b, None, bad, 0.05), Err(FlowError::Config { field: "screen level", .. })), "level {bad}");
    }
    let mut small = FlowEstimator::new(FlowConfig::default(), src.width / 2, src.height / 2).unwrap();
    let foreign = small.prepare(&PlaneF32::new(src.width / 2, src.height / 2)).unwrap();
    assert!(matches!(est.screen(&a, &foreign, None, level, 0.05), Err(FlowError::ForeignFrame { what: "dst" })));
}

/// The reference-pixel thresholds scale up with a wider input and with nothing else.
#[test]
fn forward_backward_thresholds_scale_with_the_input_width() {
    let cfg = FlowConfig::default();
    assert_eq!(cfg.at_input_width(REFERENCE_WIDTH_PX), cfg);
    assert_eq!(cfg.at_input_width(REFERENCE_WIDTH_PX / 2), cfg);
    let wide = cfg.at_input_width(2 * REFERENCE_WIDTH_PX);
    assert_eq!((wide.fb_sigma_px, wide.fb_max_px), (2.0 * cfg.fb_sigma_px, 2.0 * cfg.fb_max_px));
    assert_eq!(FlowConfig { fb_sigma_px: cfg.fb_sigma_px, fb_max_px: cfg.fb_max_px, ..wide.clone() }, cfg);
    let est = FlowEstimator::new(cfg.clone(), 2 * W, 2 * H).unwrap();
    assert_eq!(est.config(), &wide);
}
