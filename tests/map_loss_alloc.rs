//! No allocation per iteration after warm-up (house habit 7): a counting global allocator
//! shows that one mapping iteration of the CPU references (medium forward per pixel and on the
//! 1/8 direction grid, total loss with every term, medium backward of both, Adam step)
//! allocates nothing once the workspaces exist and have run once. Its own test binary, because the global allocator is per binary.
//!
//! The passes run on rayon threads, so the count covers the threads of a dedicated pool (marked
//! by its start handler) as well as the calling thread; counting is armed only inside the pool
//! job, after warm-up, so the one-off job injection into the pool is not counted.

use duv_core::rng::Rng;
use duv_core::{Image, PinholeCamera, Se3};
use duv_map::adam::{AdamGroup, AdamGroupConfig};
use duv_map::loss::{total_loss, LossConfig, LossWorkspace, RenderedView, TargetView};
use duv_map::medium::{MediumConfig, MediumNet, MediumPlanes, MediumWorkspace};
use duv_core::alloc::{self, CountScope, CountingAllocator};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

fn random<const C: usize>(w: usize, h: usize, lo: f64, hi: f64, rng: &mut Rng) -> Image<f32, C> {
    Image::from_vec(w, h, (0..w * h * C).map(|_| rng.range(lo, hi) as f32).collect()).unwrap()
}

#[test]
fn a_mapping_iteration_allocates_nothing_after_warm_up() {
    // Odd size, smaller than the workspaces' capacity (the gradient images are resized within it).
    let (w, h) = (67, 45);
    let cam = PinholeCamera::from_hfov(70.0, w, h).unwrap();
    let pose = Se3::identity();
    let mut rng = Rng::new(5);
    let color = random::<3>(w, h, 0.0, 1.0, &mut rng);
    let image = random::<3>(w, h, 0.0, 1.0, &mut rng);
    let depth = random::<1>(w, h, 0.2, 1.0, &mut rng);
    let var = random::<1>(w, h, 1e-3, 1e-2, &mut rng);
    let alpha = random::<1>(w, h, 0.0, 1.0, &mut rng);
    let track_d = random::<1>(w, h, 0.2, 1.0, &mut rng);
    let mut track_v = random::<1>(w, h, 1e-3, 1e-2, &mut rng);
    track_v.data[10] = f32::INFINITY;

    let mut net = MediumNet::<f32>::new(&MediumConfig::default()).unwrap();
    let mut medium_ws = MediumWorkspace::new(&net, 64);
    // The mapper's medium: the 1/8 direction grid, forward and adjoint.
    let mut grid_ws = MediumWorkspace::with_grid(&net, w, h, 8);
    let mut grid_planes = MediumPlanes::<f32>::new(w, h);
    let mut loss_ws = LossWorkspace::<f32>::new(80, 64);
    let mut adam = AdamGroup::new(AdamGroupConfig::default(), 1, net.param_count(), net.param_count()).unwrap();
    let mut planes = MediumPlanes::<f32>::new(w, h);
    let mut grads = vec![0.0f32; net.param_count()];
    let config = LossConfig::default();

    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).start_handler(|_| alloc::mark_current_thread(true)).build().unwrap();
    let mut iteration = || {
        net.forward(&cam, &pose, &mut planes).unwrap();
        let rendered = RenderedView { color: &color, depth: &depth, depth_variance: &var, alpha: &alpha, medium: Some(&planes) };
        let target = TargetView { image: &image, depth: &track_d, depth_variance: &track_v };
        let terms = total_loss(&mut loss_ws, &config, &rendered, &target).unwrap();
        grads.fill(0.0);
        medium_ws.backward(&net, &cam, &pose, &loss_ws.grads().d_medium, &mut grads).unwrap();
        grid_ws.forward(&net, &cam, &pose, &mut grid_planes).unwrap();
        grid_ws.backward(&net, &cam, &pose, &loss_ws.grads().d_medium, &mut grads).unwrap();
        adam.step(net.params_mut(), &grads).unwrap();
        terms.total
    };
    let counted = pool.install(|| {
        iteration();
        alloc::mark_current_thread(true);
        let mut totals = [0.0; 3];
        let counted = alloc::count_allocations(CountScope::MarkedThreads, || {
            for t in totals.iter_mut() {
                *t = iteration();
            }
        });
        assert!(totals.iter().all(|t| t.is_finite()));
        // Self-check: allocations inside parallel jobs are seen.
        use rayon::prelude::*;
        let probe = alloc::count_allocations(CountScope::MarkedThreads, || {
            (0..64usize).into_par_iter().for_each(|i| drop(std::hint::black_box(vec![0u8; i + 1])));
        });
        assert!(probe >= 64, "the counting allocator misses parallel jobs");
        counted
    });
    assert_eq!(counted, 0, "{counted} allocations in 3 mapping iterations after warm-up");
}
