//! No allocation per frame after warm-up: `prepare_into` and `estimate` (forward, backward,
//! confidence, pooling, with and without a seed) run under a counting global allocator.
//!
//! Rayon's injector queue allocates a block every 63 calls made from outside a pool, so the
//! tracker runs the flow inside its pool, as this test does (see the `track::flow` docs).

use duv_core::PlaneF32;
use duv_track::flow::synth::{self, Water};
use duv_track::flow::{FeatureKind, FlowConfig, FlowEstimator, FlowField};
use duv_core::alloc::{self, CountScope, CountingAllocator};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Frames per measured loop. Each runs dozens of parallel loops: together far more than the
/// 63 after which rayon's injector would allocate, were the calls made from outside the pool.
const FRAMES: usize = 12;

fn frames(w: usize, h: usize) -> Vec<PlaneF32> {
    let margin = 24;
    let canvas = synth::radiance(w + 2 * margin, h + 2 * margin, 3);
    (0..3)
        .map(|k| {
            let d = 2.5 * k as f32;
            let mut v = synth::render(&canvas, margin, w, h, |x, y| (x - d, y + 0.4 * d));
            synth::through_water(&mut v, &Water::default());
            synth::camera_gray(&v, 0.003, k as u64)
        })
        .collect()
}

/// Allocations made by `f` on any thread.
fn count(f: impl FnOnce()) -> usize {
    alloc::count_allocations(CountScope::AllThreads, f)
}

fn no_allocation_after_warm_up(cfg: FlowConfig, w: usize, h: usize) {
    let images = frames(w, h);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    pool.install(|| {
        let mut est = FlowEstimator::new(cfg, w, h).unwrap();
        let mut a = est.new_frame();
        let mut b = est.new_frame();
        let mut out = est.new_result();
        let seed = FlowField::constant(w, h, 8, 2.5, -1.0);
        // Warm-up: thread-locals, tracing call sites, rayon worker deques.
        for _ in 0..2 {
            est.prepare_into(&images[0], &mut a).unwrap();
            est.prepare_into(&images[1], &mut b).unwrap();
            est.estimate(&a, &b, None, &mut out).unwrap();
            est.estimate(&a, &b, Some(&seed), &mut out).unwrap();
        }
        let first = out.clone();
        // The counter sees allocations, including those of the pool's workers.
        let probe = count(|| {
            rayon::join(|| std::hint::black_box(vec![1u8; 64]), || std::hint::black_box(vec![2u8; 64]));
        });
        assert!(probe >= 2, "counting allocator missed allocations: {probe}");
        let n = count(|| {
            for k in 0..FRAMES {
                est.prepare_into(&images[k % 3], &mut b).unwrap();
                est.estimate(&a, &b, if k % 2 == 0 { None } else { Some(&seed) }, &mut out).unwrap();
            }
        });
        assert_eq!(n, 0, "{n} allocations in {FRAMES} frames after warm-up");
        // Buffers reused, results reproducible.
        est.prepare_into(&images[1], &mut b).unwrap();
        est.estimate(&a, &b, Some(&seed), &mut out).unwrap();
        assert_eq!(out, first);
    });
}

#[test]
fn prepare_and_estimate_do_not_allocate_after_warm_up() {
    // Sizes that do not divide by the pyramid's factors or the patch grid.
    no_allocation_after_warm_up(FlowConfig::default(), 8 * 30 + 5, 8 * 22 + 3);
    no_allocation_after_warm_up(FlowConfig { feature: FeatureKind::SoftCensus, ..FlowConfig::default() }, 203, 157);
}
