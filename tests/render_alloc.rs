//! No allocation per render after warm-up (house habit 7): a counting global allocator shows
//! that `RasterWorkspace::forward` and `backward` allocate nothing, on any thread (rayon
//! workers included), once the workspace, the outputs and the gradient buffers exist and one
//! render has run. Its own test binary, because the global allocator is per binary, and a
//! single test, because the counter is global.
//!
//! The renders run inside the rayon pool (`ThreadPool::install`), as the mapping thread is
//! meant to: parallel work started from a thread outside the pool goes through rayon's global
//! injector queue, which allocates a new block every 63 injected jobs (about one allocation
//! every few renders). From a pool thread, work goes to the thread's own deque instead.

#[path = "common/render_scene.rs"]
mod render_scene;

use duv_core::rng::Rng;
use duv_map::gaussians::GaussianGrads;
use duv_map::render::{MediumPlanes, RasterCapacity, RasterWorkspace, RenderConfig, RenderError, RenderOutput};
use render_scene::{camera, random_gaussians, random_medium, random_upstream, world_from_cam};
use duv_core::alloc::{self, CountScope, CountingAllocator};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Allocations made by any thread while `f` runs.
fn count_allocations(f: impl FnOnce()) -> usize {
    alloc::count_allocations(CountScope::AllThreads, f)
}

#[test]
fn render_forward_and_backward_allocate_nothing_after_warm_up() {
    // 77x45 crosses tile boundaries both ways; 600 Gaussians of a 1000 capacity.
    let (w, h) = (77, 45);
    let cam = camera(w, h, 60.0);
    let pose = world_from_cam().inverse();
    let mut rng = Rng::new(17);
    let gaussians = random_gaussians(&mut rng, 600, 1000, &cam, &world_from_cam(), (1.0, 6.0), (1.0, 6.0), (-1.0, 3.0));
    let medium = random_medium(&mut rng, w, h);
    let upstream = random_upstream(&mut rng, w, h);
    let config = RenderConfig::default();
    let mut ws = RasterWorkspace::new(RasterCapacity { width: 96, height: 64, max_gaussians: 1000, max_intersections: 20_000 }).unwrap();
    let mut out = RenderOutput::new(w, h);
    let mut grads = GaussianGrads::with_capacity(1000);
    let mut medium_grads = MediumPlanes::new(w, h);

    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    pool.install(|| {
        // Warm-up: first render.
        grads.reset(gaussians.len()).unwrap();
        let first = ws.forward(&gaussians, &cam, &pose, &medium, &config, &mut out).unwrap();
        ws.backward(&gaussians, &medium, &out, &upstream, &mut grads, &mut medium_grads).unwrap();
        let first_out = out.clone();
        let first_grads = grads.clone();

        let mut stats = None;
        let n = count_allocations(|| {
            for _ in 0..3 {
                grads.reset(gaussians.len()).unwrap();
                stats = Some(ws.forward(&gaussians, &cam, &pose, &medium, &config, &mut out).unwrap());
                ws.backward(&gaussians, &medium, &out, &upstream, &mut grads, &mut medium_grads).unwrap();
            }
        });
        assert_eq!(n, 0, "allocations in warmed-up renders");
        // The counted renders did the same work (and the pipeline is deterministic).
        assert_eq!(stats, Some(first));
        assert!(first.intersections > 1000);
        assert_eq!(out, first_out);
        assert_eq!(grads, first_grads);
        // An overflow is reported without allocating either.
        let mut small =
            RasterWorkspace::new(RasterCapacity { width: 96, height: 64, max_gaussians: 1000, max_intersections: 100 }).unwrap();
        let mut result = None;
        let n = count_allocations(|| result = Some(small.forward(&gaussians, &cam, &pose, &medium, &config, &mut out)));
        assert_eq!(n, 0);
        assert!(matches!(result, Some(Err(RenderError::TileOverflow { .. }))));
        // And the counter does count, on other threads too.
        assert!(count_allocations(|| drop(std::hint::black_box(vec![0u8; 16]))) > 0);
        assert!(count_allocations(|| std::thread::scope(|s| drop(s.spawn(|| std::hint::black_box(vec![0u8; 16])).join()))) > 0);
    });
}
