//! How long the closed-form medium estimate takes on generated keyframes of a given size, as
//! the mapper runs it at 4, 8 and 16 keyframes.
//!
//! ```text
//! cargo run --release --example medium_estimate_time -- [WIDTH HEIGHT] [turbid|coastal|clear]
//! ```
use duv_map::medium_estimate::{estimate_medium, MediumEstimateConfig};
use duv_sim::keyframes::sim_keyframes;
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use std::time::Instant;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let w: usize = a.get(1).map_or(640, |v| v.parse().expect("WIDTH"));
    let h: usize = a.get(2).map_or(480, |v| v.parse().expect("HEIGHT"));
    let water = match a.get(3).map(|s| s.as_str()) { Some("clear") => WaterPreset::Clear, Some("coastal") => WaterPreset::Coastal, _ => WaterPreset::Turbid };
    let mut cfg = SimConfig::preset(water, TrajectoryKind::Survey);
    (cfg.frames, cfg.width, cfg.height) = (160, w, h);
    let r = SimRenderer::new(&cfg).expect("generated survey");
    let kfs = sim_keyframes(&r, 10, 16);
    for n in [4, 8, 16] {
        let refs: Vec<_> = kfs.iter().take(n).map(|k| &k.keyframe).collect();
        let t0 = Instant::now();
        let e = estimate_medium(&refs, [0.3; 3], &MediumEstimateConfig::default());
        let s = t0.elapsed().as_secs_f64();
        match e {
            Ok(e) => println!("{w}x{h}, {n} keyframes: {s:.3} s, {} samples, pairs {:?}, beta_D {:.3?} beta_B {:.3?} B_inf {:.3?}", e.samples, e.attenuation_pairs, e.medium.beta_d, e.medium.beta_b, e.medium.b_inf),
            Err(e) => println!("{w}x{h}, {n} keyframes: {s:.3} s, {e}"),
        }
    }
}
