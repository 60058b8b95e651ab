//! Whether the generator's clean image (`J`, no water) is as bright from afar as up close: the
//! survey rendered at 320x240 against the same frames rendered 4x finer and boxed down 4x4,
//! mean ratio per channel by range. A ratio above 1 that grows with range is a generated
//! surface brighter than what a pixel covers, which the water model reads as weaker
//! attenuation (see the README's mapping figures).
//!
//! ```text
//! cargo run --release --example sim_range_brightness -- [clear|coastal|turbid] [FRAME,FRAME,...]
//! ```
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};

const FINER: usize = 4;
const RANGE_EDGES_M: [f32; 8] = [0.0, 2.0, 3.0, 4.0, 6.0, 8.0, 11.0, 40.0];

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let water = match a.get(1).map(|s| s.as_str()) { Some("turbid") => WaterPreset::Turbid, Some("coastal") => WaterPreset::Coastal, _ => WaterPreset::Clear };
    let frames: Vec<usize> = a.get(2).map(|s| s.split(',').map(|f| f.parse().expect("frame index")).collect()).unwrap_or(vec![0, 25, 50, 75, 99]);
    let (w, h) = (320, 240);
    let renderer = |w: usize, h: usize| {
        let mut cfg = SimConfig::preset(water, TrajectoryKind::Survey);
        (cfg.frames, cfg.width, cfg.height, cfg.vignetting) = (100, w, h, 0.0);
        SimRenderer::new(&cfg).expect("generated survey")
    };
    let (coarse, fine) = (renderer(w, h), renderer(w * FINER, h * FINER));
    // Per range bin: sums of the coarse and the boxed fine value per channel, and the pixel count.
    let mut bins = vec![([0f64; 3], [0f64; 3], 0usize); RANGE_EDGES_M.len() - 1];
    for i in frames {
        let (c, f) = (coarse.render(i), fine.render(i));
        for y in 0..h {
            for x in 0..w {
                let range = c.range_m.data[y * w + x];
                let Some(bin) = RANGE_EDGES_M.windows(2).position(|e| range >= e[0] && range < e[1]) else { continue };
                for ch in 0..3 {
                    let mut boxed = 0.0;
                    for dy in 0..FINER {
                        for dx in 0..FINER {
                            boxed += f.clear.data[((y * FINER + dy) * w * FINER + x * FINER + dx) * 3 + ch] as f64;
                        }
                    }
                    bins[bin].0[ch] += c.clear.data[(y * w + x) * 3 + ch] as f64;
                    bins[bin].1[ch] += boxed / (FINER * FINER) as f64;
                }
                bins[bin].2 += 1;
            }
        }
    }
    println!("{water:?} survey, J at {w}x{h} over J at {}x{} boxed {FINER}x{FINER}, by range", w * FINER, h * FINER);
    for (k, (c, f, n)) in bins.iter().enumerate().filter(|(_, b)| b.2 > 0) {
        println!("{:5.1}-{:5.1} m  {n:7} px  R {:.4}  G {:.4}  B {:.4}", RANGE_EDGES_M[k], RANGE_EDGES_M[k + 1], c[0] / f[0], c[1] / f[1], c[2] / f[2]);
    }
}
