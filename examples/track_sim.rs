//! Tracks a generated sequence in memory and prints ATE and timings; the tool the tracker's
//! test thresholds were measured with.
//!
//! ```text
//! cargo run --release --example track_sim -- WATER TRAJECTORY FRAMES WIDTH HEIGHT SPEED DEPTH_FACTOR|auto [noloop] [threads=N] [prefix] [scales] [trace] [set:KEY=VALUE,...]
//! ```

#[path = "../tests/common/track_sim.rs"]
mod track_sim;

use duv_sim::{SimRenderer, TrajectoryKind, WaterPreset};
use std::time::Instant;

fn main() {
    tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::from_default_env()).with_writer(std::io::stderr).init();
    let a: Vec<String> = std::env::args().collect();
    let get = |i: usize, d: &str| a.get(i).cloned().unwrap_or_else(|| d.to_string());
    let water = match get(1, "coastal").as_str() {
        "clear" => WaterPreset::Clear,
        "turbid" => WaterPreset::Turbid,
        _ => WaterPreset::Coastal,
    };
    let traj = match get(2, "survey").as_str() {
        "loop" => TrajectoryKind::Loop,
        "hover" => TrajectoryKind::Hover,
        _ => TrajectoryKind::Survey,
    };
    let frames: usize = get(3, "60").parse().unwrap();
    let (w, h): (usize, usize) = (get(4, "160").parse().unwrap(), get(5, "120").parse().unwrap());
    let speed: f64 = get(6, "0.5").parse().unwrap();
    let factor: Option<usize> = get(7, "auto").parse().ok();
    let no_loop = a.iter().any(|s| s == "noloop");
    let threads = a.iter().find_map(|s| s.strip_prefix("threads=")).map(|s| s.parse().unwrap()).unwrap_or(2);
    let sim = track_sim::sim_config(water, traj, frames, w, h, speed);
    let renderer = SimRenderer::new(&sim).unwrap();
    let images = track_sim::render_all(&renderer);
    let mut cfg = track_sim::small_tracker_config();
    cfg.depth_factor = factor;
    cfg.loop_closure = !no_loop;
    for kv in a.iter().filter_map(|s| s.strip_prefix("set:")) {
        let text = kv.replace(',', "\n");
        let patch: toml::Table = toml::from_str(&text).unwrap();
        let mut base = toml::Value::try_from(&cfg).unwrap();
        let table = base.as_table_mut().unwrap();
        for (k, v) in patch {
            match (table.get_mut(&k), v) {
                (Some(toml::Value::Table(dst)), toml::Value::Table(src)) => {
                    for (k2, v2) in src {
                        dst.insert(k2, v2);
                    }
                }
                (_, v) => {
                    table.insert(k, v);
                }
            }
        }
        cfg = base.try_into().unwrap();
    }
    if a.iter().any(|s| s == "trace") {
        // Scale of every live keyframe after each insertion (true depth x estimated inverse depth).
        let f = cfg.resolved_depth_factor(w, h);
        let gt_depth: Vec<_> = (0..frames).map(|i| renderer.render(i).depth_m).collect();
        let mut tracker = duv_track::Tracker::new(renderer.camera(), &cfg, track_sim::capacity(threads)).unwrap();
        for fr in &images {
            let out = tracker.track(fr).unwrap();
            if out.new_keyframe.is_none() {
                continue;
            }
            let mut line = format!("frame {:3}:", fr.seq);
            let n = tracker.num_keyframes();
            for k in tracker.keyframes().skip(n.saturating_sub(10)) {
                let gt = &gt_depth[k.seq as usize];
                let mut ratios: Vec<f32> = Vec::new();
                for y in 0..k.inv_depth.height {
                    for x in 0..k.inv_depth.width {
                        let z = gt.data[(y * f + f / 2) * gt.width + x * f + f / 2];
                        if z > 0.0 {
                            ratios.push(z * k.inv_depth.data[y * k.inv_depth.width + x]);
                        }
                    }
                }
                ratios.sort_by(|a, b| a.total_cmp(b));
                line += &format!(" {}:{:.3}", k.id, ratios.get(ratios.len() / 2).copied().unwrap_or(f32::NAN));
            }
            println!("{line}");
        }
        return;
    }
    let t0 = Instant::now();
    let r = track_sim::run(&renderer, &images, &cfg, track_sim::capacity(threads));
    let secs = t0.elapsed().as_secs_f64();
    let c = r.tracker.counters();
    let loops = r.tracker.edges().filter(|e| e.2).count();
    println!(
        "ATE {:.4} m = {:.3}% of {:.2} m; {:.1} fps; kf {} live {} pruned {} evicted {}; loops {} (edges {}); lost {} reloc {}",
        r.ate_rmse_m,
        r.ate_percent,
        r.path_m,
        frames as f64 / secs,
        c.keyframes_inserted,
        r.tracker.num_keyframes(),
        c.keyframes_pruned,
        c.keyframes_evicted,
        c.loops_closed,
        loops,
        c.lost_frames,
        c.relocalisations
    );
    if a.iter().any(|s| s == "prefix") {
        let mut line = String::from("ATE % of prefix:");
        for n in (40..=frames).step_by(20) {
            let (_, p, _) = track_sim::ate(&renderer.poses()[..n], &r.trajectory.frames[..n]);
            line += &format!(" {n}:{p:.2}");
        }
        println!("{line}");
        let states: String = r.outputs.iter().map(|o| match o.state {
            duv_track::TrackingState::Tracking => if o.new_keyframe.is_some() { 'K' } else { '.' },
            duv_track::TrackingState::Initializing => 'i',
            duv_track::TrackingState::Relocalised => 'R',
            duv_track::TrackingState::Lost(_) => 'L',
        }).collect();
        println!("{states}");
    }
    if a.iter().any(|s| s == "ause") {
        // AUSE at the depth grid (no upsampling) and at full resolution, scale from the alignment.
        let ev = duv_eval::trajectory::evaluate_trajectory(&renderer.poses()[..frames], &r.trajectory.frames, &Default::default(), "gt", "est").unwrap();
        let scale = ev.report.alignment.scale;
        let f = r.tracker.depth_factor();
        let opts = duv_eval::AuseOptions::default();
        let (mut low_sum, mut full_sum, mut rnd_sum, mut n) = (0.0, 0.0, 0.0, 0);
        let mut inv = duv_core::PlaneF32::new(w, h);
        let mut var = duv_core::PlaneF32::new(w, h);
        for k in r.tracker.keyframes() {
            let Some(v) = k.variance else { continue };
            let gt = renderer.render(k.seq as usize).depth_m;
            let (mut e, mut u) = (Vec::new(), Vec::new());
            for y in 0..k.inv_depth.height {
                for x in 0..k.inv_depth.width {
                    let z = gt.data[(y * f + f / 2) * gt.width + x * f + f / 2];
                    if z > 0.0 {
                        e.push((1.0 / z as f64 - k.inv_depth.data[y * k.inv_depth.width + x] as f64 / scale).abs());
                        u.push(v.data[y * k.inv_depth.width + x] as f64);
                    }
                }
            }
            let Ok(lo) = duv_eval::ause::ause(&e, &u, &opts) else { continue };
            r.tracker.upsample_keyframe(k.id, &mut inv, &mut var).unwrap();
            let (mut e2, mut u2) = (Vec::new(), Vec::new());
            for ((&z, &d), &vv) in gt.data.iter().zip(&inv.data).zip(&var.data) {
                if z > 0.0 {
                    e2.push((1.0 / z as f64 - d as f64 / scale).abs());
                    u2.push(vv as f64);
                }
            }
            let Ok(fu) = duv_eval::ause::ause(&e2, &u2, &opts) else { continue };
            low_sum += lo.ause;
            full_sum += fu.ause;
            rnd_sum += fu.ause_random;
            n += 1;
        }
        println!("AUSE over {n} keyframes: depth grid {:.3}, full resolution {:.3}, random {:.3}", low_sum / n as f64, full_sum / n as f64, rnd_sum / n as f64);
    }
    // Metric scale of each keyframe's depth map (median of true depth x estimated inverse
    // depth at the depth-grid pixel centres): its drift along the run.
    if a.iter().any(|s| s == "scales") {
        let f = cfg.resolved_depth_factor(w, h);
        let mut line = String::from("kf depth scale:");
        for k in r.tracker.keyframes() {
            let gt = renderer.render(k.seq as usize).depth_m;
            let mut ratios: Vec<f32> = Vec::new();
            for y in 0..k.inv_depth.height {
                for x in 0..k.inv_depth.width {
                    let z = gt.data[(y * f + f / 2) * gt.width + x * f + f / 2];
                    if z > 0.0 {
                        ratios.push(z * k.inv_depth.data[y * k.inv_depth.width + x]);
                    }
                }
            }
            ratios.sort_by(|a, b| a.total_cmp(b));
            line += &format!(" {}:{:.3}", k.id, ratios.get(ratios.len() / 2).copied().unwrap_or(f32::NAN));
        }
        println!("{line}");
    }
    // Loop edges against the ground truth: relative pose of the two keyframes.
    let kfs: Vec<_> = r.tracker.keyframes().map(|k| (k.id, k.seq, k.world_from_cam)).collect();
    for (from, to, is_loop) in r.tracker.edges() {
        if !is_loop {
            continue;
        }
        let f = kfs.iter().find(|k| k.0 == from).unwrap();
        let t = kfs.iter().find(|k| k.0 == to).unwrap();
        let gt = renderer.pose(f.1 as usize).world_from_cam.inv_mul(&renderer.pose(t.1 as usize).world_from_cam);
        let est = f.2.inv_mul(&t.2);
        println!(
            "loop edge kf {from} (frame {}) -> kf {to} (frame {}): gt |t| {:.3} m rot {:.2} deg; est |t| {:.3} rot {:.2} deg",
            f.1,
            t.1,
            gt.translation.vector.norm(),
            gt.rotation.angle().to_degrees(),
            est.translation.vector.norm(),
            est.rotation.angle().to_degrees()
        );
    }
}
