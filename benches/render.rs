//! Renderer timings: one forward + backward pass of the CPU reference renderer at 320x240
//! with 20k and 100k random Gaussians in front of the camera (depth 1-10 m, 0.7-4 px
//! standard deviation, random per-pixel medium, a random linear loss). Prints the median of
//! several runs for the whole iteration, the two passes and every stage (from the tracing
//! spans `map.*`).
//!
//! Run: `cargo bench --bench render` (release profile; no criterion, plain `main`).

#[path = "../tests/common/render_scene.rs"]
mod render_scene;

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use duv_core::rng::Rng;
use duv_map::gaussians::GaussianGrads;
use duv_map::render::{MediumPlanes, RasterCapacity, RasterWorkspace, RenderConfig, RenderError, RenderOutput};
use render_scene::{camera, random_gaussians, random_medium, random_upstream, world_from_cam};
use tracing::span;
use tracing_subscriber::layer::{Context, SubscriberExt};
use tracing_subscriber::registry::LookupSpan;

const RUNS: usize = 9;

/// Sums the busy time of every `map.*` span per name, per run.
struct StageTimes {
    current: Mutex<BTreeMap<&'static str, Duration>>,
}

struct Entered(Instant);

impl<S: tracing::Subscriber + for<'a> LookupSpan<'a>> tracing_subscriber::Layer<S> for &'static StageTimes {
    fn on_enter(&self, id: &span::Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            span.extensions_mut().replace(Entered(Instant::now()));
        }
    }
    fn on_exit(&self, id: &span::Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id) {
            if let Some(Entered(t)) = span.extensions_mut().remove::<Entered>() {
                *self.current.lock().unwrap().entry(span.name()).or_default() += t.elapsed();
            }
        }
    }
}

fn median_ms(samples: &mut [Duration]) -> f64 {
    samples.sort();
    samples[samples.len() / 2].as_secs_f64() * 1e3
}

fn main() {
    let times: &'static StageTimes = Box::leak(Box::new(StageTimes { current: Mutex::new(BTreeMap::new()) }));
    let subscriber = tracing_subscriber::registry()
        .with(times)
        .with(tracing_subscriber::filter::Targets::new().with_target("duv", tracing::Level::DEBUG));
    tracing::subscriber::set_global_default(subscriber).unwrap();

    let (w, h) = (320, 240);
    let cam = camera(w, h, 0.5 * w as f64 / 35f64.to_radians().tan());
    let cam_from_world = world_from_cam().inverse();
    let config = RenderConfig::default();
    println!("renderer: {w}x{h}, {} rayon threads, median of {RUNS} runs", rayon::current_num_threads());
    for n in [20_000, 100_000] {
        let mut rng = Rng::new(n as u64);
        let gaussians = random_gaussians(&mut rng, n, n, &cam, &world_from_cam(), (1.0, 10.0), (0.7, 4.0), (-2.0, 3.0));
        let medium = random_medium(&mut rng, w, h);
        let upstream = random_upstream(&mut rng, w, h);
        let mut out = RenderOutput::new(w, h);
        let mut grads = GaussianGrads::with_capacity(n);
        let mut medium_grads = MediumPlanes::new(w, h);
        // Size the intersection buffer from the overflow report, as a board calibration would.
        let mut cap = RasterCapacity { width: w, height: h, max_gaussians: n, max_intersections: 4 * n };
        let mut ws = RasterWorkspace::new(cap).unwrap();
        let stats = match ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out) {
            Err(RenderError::TileOverflow { needed, .. }) => {
                cap.max_intersections = needed as usize;
                ws = RasterWorkspace::new(cap).unwrap();
                ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out).unwrap()
            }
            other => other.unwrap(),
        };
        grads.reset(n).unwrap();
        ws.backward(&gaussians, &medium, &out, &upstream, &mut grads, &mut medium_grads).unwrap();

        let (mut total, mut fwd, mut bwd) = (Vec::new(), Vec::new(), Vec::new());
        let mut stages: BTreeMap<&'static str, Vec<Duration>> = BTreeMap::new();
        for _ in 0..RUNS {
            grads.reset(n).unwrap();
            times.current.lock().unwrap().clear();
            let t0 = Instant::now();
            ws.forward(&gaussians, &cam, &cam_from_world, &medium, &config, &mut out).unwrap();
            let t1 = Instant::now();
            ws.backward(&gaussians, &medium, &out, &upstream, &mut grads, &mut medium_grads).unwrap();
            let t2 = Instant::now();
            fwd.push(t1 - t0);
            bwd.push(t2 - t1);
            total.push(t2 - t0);
            for (name, d) in times.current.lock().unwrap().iter() {
                stages.entry(name).or_default().push(*d);
            }
        }
        let mean_blended = out.alpha.data.iter().map(|&a| a as f64).sum::<f64>() / (w * h) as f64;
        let terminated = out.final_t.data.iter().filter(|&&t| t < 2e-4).count() as f64 / (w * h) as f64;
        println!(
            "{n} Gaussians: {} visible, {} tile intersections ({:.1} per visible Gaussian), mean alpha {mean_blended:.3}, \
             {:.0}% of pixels stopped early",
            stats.visible,
            stats.intersections,
            stats.intersections as f64 / stats.visible.max(1) as f64,
            100.0 * terminated
        );
        println!("  forward + backward : {:8.2} ms", median_ms(&mut total));
        println!("    forward          : {:8.2} ms", median_ms(&mut fwd));
        println!("    backward         : {:8.2} ms", median_ms(&mut bwd));
        for (name, samples) in stages.iter_mut() {
            println!("      {name:<15}: {:8.2} ms", median_ms(samples));
        }
    }
}
