//! Milliseconds per flow edge (forward + backward + confidence + pooling) and per `prepare`,
//! median over runs, on procedural underwater images.
//!
//! ```text
//! cargo run --release --example flow_bench -- [THREADS] [RUNS] [FINEST]
//! ```
//! THREADS (default 2) sizes the rayon pool the estimator runs inside, as the tracker would;
//! FINEST restricts the run to one finest level. With one thread the mean CPU time per edge of
//! the worker (Linux `schedstat`) is printed too: on a shared machine it is the steadier figure.

use duv_core::ImageRgbF32;
use duv_track::flow::synth::{self, Water};
use duv_track::flow::{FlowConfig, FlowEstimator, FlowField};
use std::time::Instant;

fn views(w: usize, h: usize) -> (duv_core::PlaneF32, duv_core::PlaneF32) {
    let margin = w / 8;
    let canvas: ImageRgbF32 = synth::radiance(w + 2 * margin, h + 2 * margin, 1);
    // Motion of about 2 % of the width plus a small rotation.
    let (a, s) = (1.5f32.to_radians(), 1.01f32);
    let (cx, cy) = (w as f32 / 2.0, h as f32 / 2.0);
    let (tx, ty) = (0.02 * w as f32, -0.01 * h as f32);
    let inv = move |x: f32, y: f32| {
        let (px, py) = (x - cx - tx, y - cy - ty);
        let (c, sn) = (a.cos() / s, a.sin() / s);
        (cx + c * px + sn * py, cy - sn * px + c * py)
    };
    let mut src = synth::render(&canvas, margin, w, h, |x, y| (x, y));
    let mut dst = synth::render(&canvas, margin, w, h, inv);
    synth::through_water(&mut src, &Water::default());
    synth::through_water(&mut dst, &Water::default());
    (synth::camera_gray(&src, 0.003, 1), synth::camera_gray(&dst, 0.003, 2))
}

/// CPU time of the calling thread in ns, from `/proc/thread-self/schedstat` (Linux).
fn thread_cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat").ok()?.split_whitespace().next()?.parse().ok()
}

fn median_ms(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let threads: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(2);
    let runs: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(21);
    let only_finest: Option<usize> = args.get(3).and_then(|s| s.parse().ok());
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("thread pool");
    println!("threads {threads}, median of {runs} runs");
    println!(
        "{:>9} {:>6} {:>8} {:>10} {:>12} {:>12} {:>12} {:>12}",
        "size", "finest", "levels", "prepare ms", "edge ms", "fwd-only ms", "seeded ms", "edge cpu ms"
    );
    for (w, h) in [(320, 240), (640, 480)] {
        let (a, b) = views(w, h);
        for finest in [1, 2].into_iter().filter(|f| only_finest.is_none_or(|o| o == *f)) {
            let cfg = FlowConfig {
                finest_level: Some(finest),
                coarsest_level_seeded: Some(finest + 1),
                ..FlowConfig::default()
            };
            let fwd_only = FlowConfig { forward_backward: false, ..cfg.clone() };
            pool.install(|| {
                let mut est = FlowEstimator::new(cfg.clone(), w, h).expect("estimator");
                let mut est_fwd = FlowEstimator::new(fwd_only, w, h).expect("estimator");
                let mut fa = est.new_frame();
                let mut fb = est.new_frame();
                let mut out = est.new_result();
                let seed = FlowField::constant(w, h, 8, 0.02 * w as f32, -0.01 * h as f32);
                let (mut t_prep, mut t_edge, mut t_fwd, mut t_seed) = (vec![], vec![], vec![], vec![]);
                for _ in 0..runs {
                    let t = Instant::now();
                    est.prepare_into(&a, &mut fa).expect("prepare");
                    t_prep.push(t.elapsed().as_secs_f64() * 1e3);
                    est.prepare_into(&b, &mut fb).expect("prepare");
                    let t = Instant::now();
                    est.estimate(&fa, &fb, None, &mut out).expect("estimate");
                    t_edge.push(t.elapsed().as_secs_f64() * 1e3);
                    let t = Instant::now();
                    est_fwd.estimate(&fa, &fb, None, &mut out).expect("estimate");
                    t_fwd.push(t.elapsed().as_secs_f64() * 1e3);
                    let t = Instant::now();
                    est.estimate(&fa, &fb, Some(&seed), &mut out).expect("estimate");
                    t_seed.push(t.elapsed().as_secs_f64() * 1e3);
                }
                // CPU time of back-to-back edges (schedstat may tick coarsely: average many).
                let c0 = thread_cpu_ns();
                for _ in 0..runs {
                    est.estimate(&fa, &fb, None, &mut out).expect("estimate");
                }
                let cpu_ms = c0.zip(thread_cpu_ns()).map(|(a, b)| (b - a) as f64 * 1e-6 / runs as f64);
                println!(
                    "{:>9} {:>6} {:>8} {:>10.2} {:>12.2} {:>12.2} {:>12.2} {:>12}",
                    format!("{w}x{h}"),
                    finest,
                    format!("{}..={}", finest, est.coarsest_level()),
                    median_ms(t_prep),
                    median_ms(t_edge),
                    median_ms(t_fwd),
                    median_ms(t_seed),
                    match cpu_ms {
                        Some(ms) if threads == 1 => format!("{ms:.2}"),
                        _ => "-".into(),
                    },
                );
            });
        }
    }
}
