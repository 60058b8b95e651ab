//! Mapping CPU-reference timings at 320x240: the total loss with every term (forward and the
//! upstream gradients), the photometric term alone, and the medium MLP forward and backward
//! over every pixel. Prints the median of several runs.
//!
//! Run: `cargo bench --bench map_loss` (release profile; no criterion, plain `main`).

use std::time::{Duration, Instant};

use duv_core::rng::Rng;
use duv_core::{Image, PinholeCamera, Se3};
use duv_map::loss::{total_loss, LossConfig, LossWorkspace, RenderedView, TargetView};
use duv_map::medium::{MediumConfig, MediumNet, MediumPlanes, MediumWorkspace, MEDIUM_CHANNELS};

const RUNS: usize = 15;
const W: usize = 320;
const H: usize = 240;

fn random<const C: usize>(lo: f64, hi: f64, rng: &mut Rng) -> Image<f32, C> {
    Image::from_vec(W, H, (0..W * H * C).map(|_| rng.range(lo, hi) as f32).collect()).unwrap()
}

fn median_ms(mut samples: Vec<Duration>) -> f64 {
    samples.sort();
    samples[samples.len() / 2].as_secs_f64() * 1e3
}

fn time(mut f: impl FnMut()) -> f64 {
    f();
    median_ms((0..RUNS).map(|_| {
        let t = Instant::now();
        f();
        t.elapsed()
    }).collect())
}

fn main() {
    let mut rng = Rng::new(1);
    let color = random::<3>(0.0, 1.0, &mut rng);
    let image = random::<3>(0.0, 1.0, &mut rng);
    let depth = random::<1>(0.2, 1.0, &mut rng);
    let var = random::<1>(1e-3, 1e-2, &mut rng);
    let alpha = random::<1>(0.0, 1.0, &mut rng);
    let track_d = random::<1>(0.2, 1.0, &mut rng);
    let track_v = random::<1>(1e-3, 1e-2, &mut rng);
    let medium = random::<MEDIUM_CHANNELS>(0.05, 0.5, &mut rng);
    let mut ws = LossWorkspace::<f32>::new(W, H);
    let rendered = RenderedView { color: &color, depth: &depth, depth_variance: &var, alpha: &alpha, medium: Some(&medium) };
    let target = TargetView { image: &image, depth: &track_d, depth_variance: &track_v };
    let all = LossConfig::default();
    let photometric_only = LossConfig { mahalanobis_weight: 0.0, kl_weight: 0.0, smoothness_weight: 0.0, accuracy_weight: 0.0, medium_variation_weight: 0.0, ..all };
    let t_all = time(|| {
        total_loss(&mut ws, &all, &rendered, &target).unwrap();
    });
    let t_photo = time(|| {
        total_loss(&mut ws, &photometric_only, &rendered, &target).unwrap();
    });

    let cam = PinholeCamera::from_hfov(70.0, W, H).unwrap();
    let pose = Se3::identity();
    let net = MediumNet::<f32>::new(&MediumConfig::default()).unwrap();
    let mut planes = MediumPlanes::<f32>::new(W, H);
    let mut medium_ws = MediumWorkspace::new(&net, H);
    let upstream = random::<MEDIUM_CHANNELS>(-1e-5, 1e-5, &mut rng);
    let mut grads = vec![0.0f32; net.param_count()];
    let t_fwd = time(|| net.forward(&cam, &pose, &mut planes).unwrap());
    let t_bwd = time(|| {
        grads.fill(0.0);
        medium_ws.backward(&net, &cam, &pose, &upstream, &mut grads).unwrap();
    });
    let mut grid_ws = MediumWorkspace::with_grid(&net, W, H, 8);
    let t_grid_fwd = time(|| grid_ws.forward(&net, &cam, &pose, &mut planes).unwrap());
    let t_grid_bwd = time(|| {
        grads.fill(0.0);
        grid_ws.backward(&net, &cam, &pose, &upstream, &mut grads).unwrap();
    });

    let threads = rayon::current_num_threads();
    println!("map CPU reference, {W}x{H}, {threads} rayon threads, median of {RUNS} runs");
    println!("  total loss, every term, forward + upstream gradients  {t_all:8.2} ms");
    println!("  photometric only (L1 + SSIM), forward + gradient      {t_photo:8.2} ms");
    println!("  medium MLP forward (every pixel)                      {t_fwd:8.2} ms");
    println!("  medium MLP backward (recomputes the forward)          {t_bwd:8.2} ms");
    println!("  medium MLP forward + backward                         {:8.2} ms", t_fwd + t_bwd);
    println!("  medium on the 1/8 grid, forward (MLP + interpolation) {t_grid_fwd:8.2} ms");
    println!("  medium on the 1/8 grid, backward (adjoint + MLP)      {t_grid_bwd:8.2} ms");
}
