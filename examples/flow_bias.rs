//! Flow bias on generated water: pooled flow against the flow the true depth and poses induce,
//! unseeded or seeded by the true flow times a gain (a scale error of the BA estimate).
//!
//! ```text
//! cargo run --release --example flow_bias -- clear|coastal|turbid [GAP_FRAMES] [SEED_GAIN] [SCENE_SEED]
//! ```
//! A negative SEED_GAIN runs unseeded; `ROWS=1` prints the gain, weight and error of every row.
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use duv_track::flow::{FlowConfig, FlowEstimator};
use nalgebra::Vector3;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let water = match a.get(1).map(|s| s.as_str()) { Some("turbid") => WaterPreset::Turbid, Some("clear") => WaterPreset::Clear, _ => WaterPreset::Coastal };
    let gap: usize = a.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    let seed_gain: f32 = a.get(3).and_then(|s| s.parse().ok()).unwrap_or(-1.0);
    let scene_seed: u64 = a.get(4).and_then(|s| s.parse().ok()).unwrap_or(1);
    let mut cfg = SimConfig::preset(water, TrajectoryKind::Survey);
    cfg.frames = 120;
    cfg.seed = scene_seed;
    let r = SimRenderer::new(&cfg).unwrap();
    let cam = *r.camera();
    let mut est = FlowEstimator::new(FlowConfig::default(), cam.width, cam.height).unwrap();
    let mut res = est.new_result();
    for i in [5usize, 20, 40, 60, 100] {
        let (fa, fb) = (r.render(i), r.render(i + gap));
        let ga = fa.rgb.to_gray_f32();
        let gb = fb.rgb.to_gray_f32();
        let pa = est.prepare(&ga).unwrap();
        let pb = est.prepare(&gb).unwrap();
        let rel = fb.world_from_cam.inv_mul(&fa.world_from_cam);
        let (pw, ph) = est.pooled_size();
        // Seed: the true flow times `seed_gain` (a scale error of the BA estimate).
        let mut seed = duv_track::flow::FlowField::zeros(pw, ph, 8);
        for y in 0..ph {
            for x in 0..pw {
                let (u, v) = (x * 8 + 4, y * 8 + 4);
                let z = fa.depth_m.data[v * cam.width + u] as f64;
                if z <= 0.0 { continue; }
                let (cx, cy) = (x as f64 * 8.0 + 3.5, y as f64 * 8.0 + 3.5);
                let p = Vector3::new((cx - cam.cx) / cam.fx * z, (cy - cam.cy) / cam.fy * z, z);
                let q = rel * nalgebra::Point3::from(p);
                let (qu, qv) = (cam.fx * q.x / q.z + cam.cx, cam.fy * q.y / q.z + cam.cy);
                seed.dx.data[y * pw + x] = ((qu - cx) / 8.0) as f32 * seed_gain;
                seed.dy.data[y * pw + x] = ((qv - cy) / 8.0) as f32 * seed_gain;
            }
        }
        est.estimate(&pa, &pb, if seed_gain >= 0.0 { Some(&seed) } else { None }, &mut res).unwrap();
        let c = 8usize;
        let (mut num, mut den, mut wsum, mut err) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        let mut rows = vec![(0.0f64, 0.0f64); ph];
        // Per row: summed weight, summed true flow magnitude and weighted error (input px).
        let mut row_stats = vec![(0.0f64, 0.0f64, 0.0f64); ph];
        for (y, row) in rows.iter_mut().enumerate() {
            for x in 0..pw {
                let (u, v) = (x * c + c / 2, y * c + c / 2);
                let z = fa.depth_m.data[v * cam.width + u] as f64;
                if z <= 0.0 { continue; }
                let (cx, cy) = (x as f64 * 8.0 + 3.5, y as f64 * 8.0 + 3.5);
                let p = Vector3::new((cx - cam.cx) / cam.fx * z, (cy - cam.cy) / cam.fy * z, z);
                let q = rel * nalgebra::Point3::from(p);
                let (qu, qv) = (cam.fx * q.x / q.z + cam.cx, cam.fy * q.y / q.z + cam.cy);
                let (gx, gy) = ((qu - cx) / 8.0, (qv - cy) / 8.0);
                let k = y * pw + x;
                let (ex, ey) = (res.pooled.flow.dx.data[k] as f64, res.pooled.flow.dy.data[k] as f64);
                let w = 0.5 * (res.pooled.weight_x.data[k] + res.pooled.weight_y.data[k]) as f64;
                num += w * (ex * gx + ey * gy);
                den += w * (gx * gx + gy * gy);
                wsum += w;
                err += w * ((ex - gx).powi(2) + (ey - gy).powi(2)).sqrt();
                row.0 += w * (ex * gx + ey * gy);
                let stats = &mut row_stats[y];
                stats.0 += w;
                stats.1 += (gx * gx + gy * gy).sqrt() * c as f64;
                stats.2 += w * ((ex - gx).powi(2) + (ey - gy).powi(2)).sqrt() * c as f64;
                row.1 += w * (gx * gx + gy * gy);
            }
        }
        if std::env::var("ROWS").is_ok() {
            for (y, (&(n, d), &(w, g, e))) in rows.iter().zip(&row_stats).enumerate() {
                let (gain, mean_w, mean_flow, w_err) = (n / d.max(1e-9), w / pw as f64, g / pw as f64, e / w.max(1e-9));
                println!("  row {y:2}: gain {gain:.3}, mean weight {mean_w:.3}, true flow {mean_flow:.2} px, weighted error {w_err:.2} px");
            }
        }
        let rowr: Vec<String> = rows.iter().step_by(5).map(|(n, d)| format!("{:.3}", n / d.max(1e-9))).collect();
        println!("{water:?} frame {i}+{gap}: flow gain (est.gt/gt.gt) {:.4}, mean weighted err {:.3} px, mean weight {:.3}; gain per row band {}", num / den, err / wsum, wsum / (pw * ph) as f64, rowr.join(" "));
    }
}
