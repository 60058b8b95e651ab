//! Gradients of the mapping CPU references against central differences in f64 (house habit 4),
//! the SSIM loss against the evaluator's SSIM, and a medium-fitting sanity run.
//!
//! Image sizes are odd and prime-ish (23x17, 11x17) so that no pass lines up with the SSIM
//! window, the medium's row bands or any other block size.

use duv_core::rng::Rng;
use duv_core::{Image, PinholeCamera, Se3};
use duv_eval::image::{ssim as eval_ssim, SsimConvention};
use duv_map::adam::{AdamGroup, AdamGroupConfig};
use duv_map::loss::{total_loss, LossConfig, LossWorkspace, RenderedView, TargetView};
use duv_map::medium::{MediumConfig, MediumGrid, MediumNet, MediumPlanes, MediumWorkspace, C_MED, MEDIUM_CHANNELS, SIGMA_ATT, SIGMA_BS};
use nalgebra::{Translation3, UnitQuaternion, Vector3};

/// Largest accepted relative error on a non-negligible gradient component.
const REL_TOL: f64 = 1e-3;
/// Components below this fraction of the largest one are negligible: only their absolute
/// error is bounded, by `NEGLIGIBLE * max |g|`.
const NEGLIGIBLE: f64 = 1e-4;
/// Central-difference step.
const STEP: f64 = 1e-6;
/// The evaluator computes SSIM in f64; the loss's f32 SSIM must agree to this.
const SSIM_VALUE_TOL: f64 = 1e-5;

const W: usize = 23;
const H: usize = 17;

fn random_image<const C: usize>(w: usize, h: usize, lo: f64, hi: f64, rng: &mut Rng) -> Image<f64, C> {
    Image::from_vec(w, h, (0..w * h * C).map(|_| rng.range(lo, hi)).collect()).unwrap()
}

fn to_f32<const C: usize>(img: &Image<f64, C>) -> Image<f32, C> {
    Image::from_vec(img.width, img.height, img.data.iter().map(|&v| v as f32).collect()).unwrap()
}

/// Compares `analytic` with central differences of `f` at `x0` for the components `indices`;
/// returns the largest relative error over the non-negligible ones.
fn check_gradient(name: &str, x0: &[f64], analytic: &[f64], indices: impl Iterator<Item = usize>, mut f: impl FnMut(&[f64]) -> f64) -> f64 {
    let mut x = x0.to_vec();
    let mut pairs = Vec::new();
    for i in indices {
        x[i] = x0[i] + STEP;
        let up = f(&x);
        x[i] = x0[i] - STEP;
        let down = f(&x);
        x[i] = x0[i];
        pairs.push((i, analytic[i], (up - down) / (2.0 * STEP)));
    }
    let scale = pairs.iter().map(|p| p.2.abs()).fold(0.0, f64::max);
    assert!(scale > 0.0, "{name}: numeric gradient is zero everywhere");
    let mut worst = 0.0f64;
    let mut significant = 0;
    for &(i, a, n) in &pairs {
        if n.abs() >= NEGLIGIBLE * scale {
            let rel = (a - n).abs() / n.abs();
            assert!(rel <= REL_TOL, "{name}[{i}]: analytic {a:e}, numeric {n:e}, relative error {rel:e}");
            worst = worst.max(rel);
            significant += 1;
        } else {
            assert!((a - n).abs() <= NEGLIGIBLE * scale, "{name}[{i}]: analytic {a:e}, numeric {n:e} (negligible component, scale {scale:e})");
        }
    }
    assert!(significant > 0, "{name}: no significant component");
    println!("{name}: {} components ({significant} significant), max relative error {worst:.2e}", pairs.len());
    worst
}

/// A complete synthetic view: rendered images and targets, with every term active.
struct Scene {
    color: Image<f64, 3>,
    depth: Image<f64, 1>,
    var: Image<f64, 1>,
    alpha: Image<f64, 1>,
    medium: MediumPlanes<f64>,
    image: Image<f64, 3>,
    track_d: Image<f64, 1>,
    track_v: Image<f64, 1>,
}

impl Scene {
    fn new(seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let color = random_image::<3>(W, H, 0.05, 0.95, &mut rng);
        // Target away from every |C - I| kink of the L1 term.
        let image = Image::from_vec(W, H, color.data.iter().map(|&c| (c + if rng.uniform() < 0.5 { -1.0 } else { 1.0 } * rng.range(0.01, 0.2)).clamp(0.0, 1.0)).collect()).unwrap();
        let depth = random_image::<1>(W, H, 0.2, 1.0, &mut rng);
        let var = random_image::<1>(W, H, 1e-3, 2e-2, &mut rng);
        let alpha = random_image::<1>(W, H, 0.03, 0.97, &mut rng);
        let medium = random_image::<MEDIUM_CHANNELS>(W, H, 0.05, 0.5, &mut rng);
        let track_d = Image::from_vec(W, H, depth.data.iter().map(|&d| d + rng.range(-0.1, 0.1)).collect()).unwrap();
        // Every 7th pixel invalid (infinite, NaN or huge variance), the rest informative.
        let track_v = Image::from_vec(
            W,
            H,
            (0..W * H).map(|i| if i % 7 == 3 { [f64::INFINITY, f64::NAN, 1e9][i % 3] } else { rng.range(2e-3, 5e-2) }).collect(),
        )
        .unwrap();
        Scene { color, depth, var, alpha, medium, image, track_d, track_v }
    }

    fn loss(&self, ws: &mut LossWorkspace<f64>, config: &LossConfig) -> f64 {
        let rendered = RenderedView { color: &self.color, depth: &self.depth, depth_variance: &self.var, alpha: &self.alpha, medium: Some(&self.medium) };
        let target = TargetView { image: &self.image, depth: &self.track_d, depth_variance: &self.track_v };
        total_loss(ws, config, &rendered, &target).unwrap().total
    }
}

/// A config with only `term` switched on (by its weight field name), or all terms for "all".
fn only(term: &str) -> LossConfig {
    let all = LossConfig { photometric_weight: 0.7, mahalanobis_weight: 0.3, kl_weight: 0.2, smoothness_weight: 0.5, accuracy_weight: 0.4, medium_variation_weight: 0.6, ..LossConfig::default() };
    let none = LossConfig { photometric_weight: 0.0, mahalanobis_weight: 0.0, kl_weight: 0.0, smoothness_weight: 0.0, accuracy_weight: 0.0, medium_variation_weight: 0.0, ..all };
    match term {
        "all" => all,
        "l1" => LossConfig { photometric_weight: 1.0, ssim_lambda: 0.0, ..none },
        "ssim" => LossConfig { photometric_weight: 1.0, ssim_lambda: 1.0, ..none },
        "photometric" => LossConfig { photometric_weight: 1.0, ..none },
        "mahalanobis" => LossConfig { mahalanobis_weight: 1.0, ..none },
        "kl" => LossConfig { kl_weight: 1.0, ..none },
        "kl_one_sided" => LossConfig { kl_weight: 1.0, kl_one_sided: true, ..none },
        "smoothness" => LossConfig { smoothness_weight: 1.0, ..none },
        "accuracy" => LossConfig { accuracy_weight: 1.0, ..none },
        "medium_variation" => LossConfig { medium_variation_weight: 1.0, ..none },
        _ => panic!("unknown term {term}"),
    }
}

#[test]
fn loss_gradients_match_central_differences() {
    let base = Scene::new(11);
    let mut ws = LossWorkspace::<f64>::new(W + 4, H + 2);
    let mut worst = 0.0f64;
    for term in ["l1", "ssim", "photometric", "mahalanobis", "kl", "kl_one_sided", "smoothness", "accuracy", "medium_variation", "all"] {
        let config = only(term);
        base.loss(&mut ws, &config);
        let g = ws.grads().clone();
        type Pick = fn(&mut Scene) -> &mut Vec<f64>;
        let inputs: [(&str, Pick, &Vec<f64>); 5] = [
            ("dC", |s| &mut s.color.data, &g.d_color.data),
            ("dD", |s| &mut s.depth.data, &g.d_depth.data),
            ("dV", |s| &mut s.var.data, &g.d_depth_variance.data),
            ("dA", |s| &mut s.alpha.data, &g.d_alpha.data),
            ("dMedium", |s| &mut s.medium.data, &g.d_medium.data),
        ];
        for (name, pick, analytic) in inputs {
            let mut scene = Scene::new(11);
            let x0 = pick(&mut scene).clone();
            if analytic.iter().all(|&v| v == 0.0) {
                // This term does not depend on the input: the loss must not move either.
                let mut x = x0.clone();
                x.iter_mut().for_each(|v| *v += 1e-3);
                *pick(&mut scene) = x;
                let moved = scene.loss(&mut ws, &config);
                *pick(&mut scene) = x0.clone();
                assert!((moved - scene.loss(&mut ws, &config)).abs() < 1e-15, "{term} {name}: zero gradient but the loss moves");
                continue;
            }
            let label = format!("{term} {name}");
            let n = x0.len();
            worst = worst.max(check_gradient(&label, &x0, analytic, 0..n, |x| {
                pick(&mut scene).copy_from_slice(x);
                scene.loss(&mut ws, &config)
            }));
        }
    }
    println!("loss gradients: max relative error {worst:.2e}");
}

#[test]
fn ssim_loss_equals_one_minus_evaluator_ssim() {
    for (w, h, seed) in [(W, H, 3), (41, 29, 4), (7, 5, 5)] {
        let mut rng = Rng::new(seed);
        let a = random_image::<3>(w, h, 0.0, 1.0, &mut rng);
        // A related image (blurred-ish plus noise) so that SSIM is neither ~0 nor ~1.
        let b = Image::from_vec(w, h, a.data.iter().map(|&v| (0.7 * v + 0.15 + rng.range(-0.1, 0.1)).clamp(0.0, 1.0)).collect()).unwrap();
        let (a32, b32) = (to_f32(&a), to_f32(&b));
        let reference = eval_ssim(&a32, &b32, SsimConvention::Same).unwrap();
        let mut ws32 = LossWorkspace::<f32>::new(w, h);
        let ours32 = ws32.ssim_value(&a32, &b32).unwrap();
        let mut ws64 = LossWorkspace::<f64>::new(w, h);
        let ours64 = ws64.ssim_value(&a, &b).unwrap();
        // The loss: photometric with lambda = 1 is 1 - SSIM.
        let mut d = Image::<f32, 3>::new(w, h);
        let s = ws32.ssim(&a32, &b32, 1.0, &mut d).unwrap();
        println!("{w}x{h}: evaluator {reference:.9}, loss f32 {ours32:.9}, loss f64 {ours64:.12}");
        assert!((ours32 - reference).abs() < SSIM_VALUE_TOL, "{ours32} vs {reference}");
        assert!(((1.0 - s) - (1.0 - reference)).abs() < SSIM_VALUE_TOL);
        assert!((ours64 - reference).abs() < 1e-9, "{ours64} vs {reference}");
    }
}

#[test]
fn f32_gradients_follow_the_f64_ones() {
    // The runtime precision: the f32 upstream gradients agree with the f64 ones to f32 accuracy.
    let s = Scene::new(5);
    let cfg = only("all");
    let mut ws64 = LossWorkspace::<f64>::new(W, H);
    s.loss(&mut ws64, &cfg);
    let (c, d, v, a, m, i, td, tv) = (to_f32(&s.color), to_f32(&s.depth), to_f32(&s.var), to_f32(&s.alpha), to_f32(&s.medium), to_f32(&s.image), to_f32(&s.track_d), to_f32(&s.track_v));
    let mut ws32 = LossWorkspace::<f32>::new(W, H);
    let rendered = RenderedView { color: &c, depth: &d, depth_variance: &v, alpha: &a, medium: Some(&m) };
    let target = TargetView { image: &i, depth: &td, depth_variance: &tv };
    total_loss(&mut ws32, &cfg, &rendered, &target).unwrap();
    let (g32, g64) = (ws32.grads(), ws64.grads());
    for (name, x, y) in [
        ("dC", &g32.d_color.data, &g64.d_color.data),
        ("dD", &g32.d_depth.data, &g64.d_depth.data),
        ("dV", &g32.d_depth_variance.data, &g64.d_depth_variance.data),
        ("dA", &g32.d_alpha.data, &g64.d_alpha.data),
        ("dMedium", &g32.d_medium.data, &g64.d_medium.data),
    ] {
        let scale = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let err = x.iter().zip(y.iter()).fold(0.0f64, |m, (&a, &b)| m.max((a as f64 - b).abs()));
        assert!(err <= 1e-3 * scale, "{name}: f32 differs from f64 by {err:e} (scale {scale:e})");
    }
}

fn test_camera(w: usize, h: usize) -> (PinholeCamera, Se3) {
    let cam = PinholeCamera::from_hfov(70.0, w, h).unwrap();
    let world_from_cam = Se3::from_parts(Translation3::new(0.3, -1.0, 2.0), UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -0.5, 0.2)));
    (cam, world_from_cam)
}

#[test]
fn medium_mlp_gradients_match_central_differences() {
    let (w, h) = (11, 17); // three row bands of the backward pass: 8 + 8 + 1
    let (cam, pose) = test_camera(w, h);
    let config = MediumConfig { head_init_scale: 1.0, seed: 99, ..MediumConfig::default() };
    let net = MediumNet::<f64>::new(&config).unwrap();
    let mut rng = Rng::new(8);
    let upstream = random_image::<MEDIUM_CHANNELS>(w, h, -1.0, 1.0, &mut rng);
    let mut grads = vec![0.0; net.param_count()];
    let mut ws = MediumWorkspace::new(&net, h);
    ws.backward(&net, &cam, &pose, &upstream, &mut grads).unwrap();
    // Accumulation: a second call adds the same again.
    let mut twice = grads.clone();
    ws.backward(&net, &cam, &pose, &upstream, &mut twice).unwrap();
    assert!(twice.iter().zip(&grads).all(|(t, g)| (t - 2.0 * g).abs() <= 1e-12 * g.abs().max(1.0)));

    // L = sum upstream . planes; its central differences over a sample of every tensor.
    let lay = net.layout();
    let mut planes = MediumPlanes::<f64>::new(w, h);
    let sample: Vec<usize> = (lay.w1..lay.b1)
        .step_by(17)
        .chain(lay.b1..lay.w2)
        .chain((lay.w2..lay.b2).step_by(29))
        .chain(lay.b2..lay.w_heads)
        .chain((lay.w_heads..lay.b_heads).step_by(3))
        .chain(lay.b_heads..lay.len)
        .collect();
    let mut probe = net.clone();
    let worst = check_gradient("medium params", net.params(), &grads, sample.into_iter(), |p| {
        probe.params_mut().copy_from_slice(p);
        probe.forward(&cam, &pose, &mut planes).unwrap();
        planes.data.iter().zip(&upstream.data).map(|(a, b)| a * b).sum()
    });
    println!("medium MLP: max relative error {worst:.2e}");
}

#[test]
fn medium_mlp_fits_a_constant_water_in_a_few_hundred_steps() {
    let (w, h) = (19, 13);
    let (cam, pose) = test_camera(w, h);
    let mut net = MediumNet::<f32>::new(&MediumConfig::default()).unwrap();
    // Coastal water, away from the initial medium in every channel.
    let target: [f32; MEDIUM_CHANNELS] = [0.06, 0.35, 0.45, 0.45, 0.12, 0.08, 0.35, 0.10, 0.07];
    let mut ws = MediumWorkspace::new(&net, h);
    let mut adam = AdamGroup::new(AdamGroupConfig { lr: 1e-2, eps: 1e-8, ..AdamGroupConfig::default() }, 1, net.param_count(), net.param_count()).unwrap();
    let mut planes = MediumPlanes::<f32>::new(w, h);
    let mut upstream = MediumPlanes::<f32>::new(w, h);
    let mut grads = vec![0.0f32; net.param_count()];
    let n = (w * h * MEDIUM_CHANNELS) as f32;
    let max_rel_error = |planes: &MediumPlanes<f32>| planes.data.chunks_exact(MEDIUM_CHANNELS).flat_map(|px| (0..MEDIUM_CHANNELS).map(move |k| ((px[k] - target[k]) / target[k]).abs())).fold(0.0f32, f32::max);
    let mut steps = 0;
    for step in 0..400 {
        net.forward(&cam, &pose, &mut planes).unwrap();
        if max_rel_error(&planes) < 0.02 {
            steps = step;
            break;
        }
        // Mean squared relative error.
        for (d, px) in upstream.data.chunks_exact_mut(MEDIUM_CHANNELS).zip(planes.data.chunks_exact(MEDIUM_CHANNELS)) {
            for k in 0..MEDIUM_CHANNELS {
                d[k] = 2.0 * (px[k] - target[k]) / (target[k] * target[k]) / n;
            }
        }
        grads.fill(0.0);
        ws.backward(&net, &cam, &pose, &upstream, &mut grads).unwrap();
        adam.step(net.params_mut(), &grads).unwrap();
        steps = step + 1;
    }
    net.forward(&cam, &pose, &mut planes).unwrap();
    let err = max_rel_error(&planes);
    println!("medium fit: max relative error {err:.4} after {steps} Adam steps");
    assert!(err < 0.02, "max relative error {err} after {steps} steps");
    let s = net.summary_along_axis(&pose);
    for c in 0..3 {
        assert!((s.b_inf[c] / target[C_MED + c] as f64 - 1.0).abs() < 0.02);
        assert!((s.beta_d[c] / target[SIGMA_ATT + c] as f64 - 1.0).abs() < 0.02);
        assert!((s.beta_b[c] / target[SIGMA_BS + c] as f64 - 1.0).abs() < 0.02);
    }
}

#[test]
fn ssim_window_is_the_evaluators() {
    let ours = duv_map::loss::ssim_kernel();
    let theirs = duv_eval::image::gaussian_kernel();
    assert_eq!(ours, theirs);
}

/// Largest accepted difference between the grid-interpolated medium (1/8 grid) and the exact
/// per-pixel network, as a fraction of each channel's value, at 320x240 and 70 degrees.
const GRID_REL_TOL: f64 = 5e-3;

#[test]
fn medium_grid_gradients_match_central_differences() {
    // 23x29 on a 3-pixel grid: 9x11 nodes, two node-row bands (8 + 3), the last node column
    // and row past the border; and the same view on an 8-pixel grid (4x5 nodes).
    for step in [3usize, 8] {
        let (w, h) = (23, 29);
        let (cam, pose) = test_camera(w, h);
        let config = MediumConfig { head_init_scale: 1.0, seed: 7, ..MediumConfig::default() };
        let net = MediumNet::<f64>::new(&config).unwrap();
        let mut rng = Rng::new(9 + step as u64);
        let upstream = random_image::<MEDIUM_CHANNELS>(w, h, -1.0, 1.0, &mut rng);
        let mut ws = MediumWorkspace::with_grid(&net, w, h, step);
        let grid = ws.grid().unwrap();
        assert_eq!(grid, MediumGrid::new(w, h, step));
        assert!((grid.nodes_x - 1) * step >= w - 1 && (grid.nodes_y - 1) * step >= h - 1);
        let mut grads = vec![0.0; net.param_count()];
        ws.backward(&net, &cam, &pose, &upstream, &mut grads).unwrap();
        let lay = net.layout();
        let sample: Vec<usize> = (lay.w1..lay.b1)
            .step_by(19)
            .chain(lay.b1..lay.w2)
            .chain((lay.w2..lay.b2).step_by(31))
            .chain((lay.w_heads..lay.b_heads).step_by(5))
            .chain(lay.b_heads..lay.len)
            .collect();
        let mut probe = net.clone();
        let mut planes = MediumPlanes::<f64>::new(w, h);
        let worst = check_gradient(&format!("medium grid step {step}"), net.params(), &grads, sample.into_iter(), |p| {
            probe.params_mut().copy_from_slice(p);
            ws.forward(&probe, &cam, &pose, &mut planes).unwrap();
            planes.data.iter().zip(&upstream.data).map(|(a, b)| a * b).sum()
        });
        println!("medium grid step {step}: max relative error {worst:.2e}");
    }
}

#[test]
fn medium_grid_interpolation_is_exact_at_nodes_and_linear_between() {
    // The interpolated planes equal the network at every node pixel and are the bilinear mix
    // of the four nodes around any other pixel (checked against the per-pixel network at the nodes).
    let (w, h, step) = (41, 26, 8);
    let (cam, pose) = test_camera(w, h);
    let net = MediumNet::<f64>::new(&MediumConfig { head_init_scale: 1.0, seed: 3, ..MediumConfig::default() }).unwrap();
    let mut exact = MediumPlanes::<f64>::new(w, h);
    net.forward(&cam, &pose, &mut exact).unwrap();
    let mut ws = MediumWorkspace::with_grid(&net, w, h, step);
    let mut interp = MediumPlanes::<f64>::new(w, h);
    ws.forward(&net, &cam, &pose, &mut interp).unwrap();
    for y in (0..h).step_by(step) {
        for x in (0..w).step_by(step) {
            for k in 0..MEDIUM_CHANNELS {
                let i = (y * w + x) * MEDIUM_CHANNELS + k;
                assert!((interp.data[i] - exact.data[i]).abs() < 1e-12, "node ({x}, {y}) channel {k}");
            }
        }
    }
    // Pixel (13, 11) lies in the cell of nodes (8, 8)-(16, 16) at fractions 5/8 and 3/8.
    let (fx, fy) = (5.0 / 8.0, 3.0 / 8.0);
    let at = |x: usize, y: usize, k: usize| exact.data[(y * w + x) * MEDIUM_CHANNELS + k];
    for k in 0..MEDIUM_CHANNELS {
        let want = (1.0 - fx) * (1.0 - fy) * at(8, 8, k) + fx * (1.0 - fy) * at(16, 8, k) + (1.0 - fx) * fy * at(8, 16, k) + fx * fy * at(16, 16, k);
        assert!((interp.data[(11 * w + 13) * MEDIUM_CHANNELS + k] - want).abs() < 1e-12, "channel {k}");
    }
    // The wrong view size is refused.
    let small = PinholeCamera::from_hfov(70.0, w - 1, h).unwrap();
    let mut wrong = MediumPlanes::<f64>::new(w - 1, h);
    assert!(ws.forward(&net, &small, &pose, &mut wrong).is_err());
}

#[test]
fn medium_grid_follows_the_per_pixel_network() {
    // A network with full-size random heads (more directional variation than a trained
    // water), 320x240 at 70 degrees, 1/8 grid.
    let (w, h) = (320, 240);
    let (cam, pose) = test_camera(w, h);
    let net = MediumNet::<f32>::new(&MediumConfig { head_init_scale: 1.0, seed: 5, ..MediumConfig::default() }).unwrap();
    let mut exact = MediumPlanes::<f32>::new(w, h);
    net.forward(&cam, &pose, &mut exact).unwrap();
    let mut ws = MediumWorkspace::with_grid(&net, w, h, 8);
    let mut interp = MediumPlanes::<f32>::new(w, h);
    ws.forward(&net, &cam, &pose, &mut interp).unwrap();
    let mut worst = 0.0f64;
    let mut spread = [(f64::INFINITY, f64::NEG_INFINITY); MEDIUM_CHANNELS];
    for (a, b) in exact.data.chunks_exact(MEDIUM_CHANNELS).zip(interp.data.chunks_exact(MEDIUM_CHANNELS)) {
        for k in 0..MEDIUM_CHANNELS {
            worst = worst.max(((a[k] - b[k]) as f64).abs() / (a[k] as f64).abs());
            spread[k] = (spread[k].0.min(a[k] as f64), spread[k].1.max(a[k] as f64));
        }
    }
    // The test network must vary over the view, or the comparison says nothing.
    let max_spread = spread.iter().map(|(lo, hi)| (hi - lo) / hi).fold(0.0, f64::max);
    println!("medium grid 1/8 vs per pixel: max relative difference {worst:.2e}; largest channel spread over the view {max_spread:.3}");
    assert!(max_spread > 0.05, "test network is nearly constant over the view: {spread:?}");
    assert!(worst < GRID_REL_TOL, "grid medium differs by {worst:e} relative");
}
