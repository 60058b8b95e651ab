//! The underwater sequence generator against its contract: byte-determinism, the TUM RGB-D
//! folder layout, exact depth, the water image formation model, AUV-like trajectories, and
//! clear errors on bad input. CI-sized: small images, few frames, short max range.

use duv_core::{MediumParams, Timestamp};
use duv_core::io::{png_io, tum};
use duv_sim::writer::{depth_to_u16, SimManifest};
use duv_sim::{write_sequence, Burst, SimConfig, SimError, SimRenderer, TrajectoryKind, WaterPreset};
use nalgebra::{Point3, Vector2};
use std::path::Path;

/// A small, fast configuration: 64x48, a few frames, 8 m max range.
fn small(water: WaterPreset, trajectory: TrajectoryKind, frames: usize) -> SimConfig {
    SimConfig { frames, width: 64, height: 48, max_range_m: 8.0, ..SimConfig::preset(water, trajectory) }
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Data lines (not comments, not blank) of a text file.
fn data_lines(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(str::to_string)
        .collect()
}

#[test]
fn same_seed_gives_identical_files_and_another_seed_differs() {
    let cfg = small(WaterPreset::Coastal, TrajectoryKind::Survey, 4);
    let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    write_sequence(&cfg, dirs[0].path(), false).unwrap();
    write_sequence(&cfg, dirs[1].path(), false).unwrap();
    write_sequence(&SimConfig { seed: 2, ..cfg.clone() }, dirs[2].path(), false).unwrap();
    let files = ["rgb/000000.png", "rgb/000003.png", "depth/000002.png", "clear/000001.png", "groundtruth.txt", "rgb.txt", "depth.txt", "calibration.txt", "medium.json", "sim.json"];
    for f in files {
        assert_eq!(read(&dirs[0].path().join(f)), read(&dirs[1].path().join(f)), "{f} differs between identical runs");
    }
    for f in ["rgb/000000.png", "depth/000002.png", "clear/000001.png", "groundtruth.txt"] {
        assert_ne!(read(&dirs[0].path().join(f)), read(&dirs[2].path().join(f)), "{f} does not depend on the seed");
    }
}

#[test]
fn output_folder_has_every_file_with_the_right_lines() {
    let cfg = SimConfig { fps: 8.0, ..small(WaterPreset::Clear, TrajectoryKind::Survey, 5) };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("new").join("seq");
    let report = write_sequence(&cfg, &out, true).unwrap();
    assert_eq!(report.frames, 5);
    assert_eq!(report.out_dir, out);
    assert!(report.frames_per_sec > 0.0 && report.seconds > 0.0);
    let expected_path = cfg.speed_mps * 4.0 / cfg.fps;
    assert!((report.path_length_m - expected_path).abs() < 0.05 * expected_path, "{} vs {expected_path}", report.path_length_m);

    let cam = cfg.camera();
    for i in 0..5 {
        for (folder, bytes_per_px) in [("rgb", 3usize), ("clear", 3), ("depth", 2)] {
            let p = out.join(folder).join(format!("{i:06}.png"));
            assert!(p.is_file(), "{} missing", p.display());
            if folder == "depth" {
                let d = png_io::read_gray16(&p).unwrap();
                assert_eq!((d.width, d.height), (64, 48));
            } else {
                let img = png_io::read_image(&p).unwrap().to_rgb8();
                assert_eq!(img.data.len(), 64 * 48 * bytes_per_px);
            }
        }
    }
    assert!(!out.join("rgb/000005.png").exists());

    for (list, folder) in [("rgb.txt", "rgb"), ("depth.txt", "depth")] {
        let text = std::fs::read_to_string(out.join(list)).unwrap();
        assert!(text.starts_with('#'), "{list} has a comment header");
        let lines = data_lines(&out.join(list));
        assert_eq!(lines.len(), 5, "{list}");
        for (i, line) in lines.iter().enumerate() {
            let (stamp, file) = line.split_once(' ').unwrap();
            let t: Timestamp = stamp.parse().unwrap();
            assert_eq!(t, Timestamp::from_secs_f64(i as f64 / 8.0), "{list} line {i}");
            assert_eq!(stamp, t.to_string(), "formatted with Timestamp's Display");
            assert_eq!(file, format!("{folder}/{i:06}.png"));
        }
    }
    let gt = tum::read_trajectory(&out.join("groundtruth.txt")).unwrap();
    assert_eq!(gt.len(), 5);
    assert_eq!(gt[0].t_ns, Timestamp::ZERO);
    assert_eq!(gt[4].t_ns, Timestamp::from_ns(500_000_000));

    let calib = data_lines(&out.join("calibration.txt"));
    assert_eq!(calib.len(), 1);
    let v: Vec<f64> = calib[0].split_whitespace().map(|s| s.parse().unwrap()).collect();
    assert_eq!(v, vec![cam.fx, cam.fy, cam.cx, cam.cy, 64.0, 48.0]);

    let medium_text = std::fs::read_to_string(out.join("medium.json")).unwrap();
    for key in ["\"beta_D\"", "\"beta_B\"", "\"B_inf\""] {
        assert!(medium_text.contains(key), "{medium_text}");
    }
    let medium: MediumParams = serde_json::from_str(&medium_text).unwrap();
    assert_eq!(medium, cfg.medium());
    let manifest: SimManifest = serde_json::from_str(&std::fs::read_to_string(out.join("sim.json")).unwrap()).unwrap();
    assert_eq!(manifest.config, cfg);
    assert_eq!(manifest.camera, cam);
    assert_eq!(manifest.depth_scale, 5000.0);
}

#[test]
fn depth_png_is_rounded_z_and_z_is_the_camera_frame_depth_of_the_hit() {
    let cfg = small(WaterPreset::Coastal, TrajectoryKind::Hover, 3);
    let dir = tempfile::tempdir().unwrap();
    write_sequence(&cfg, dir.path(), false).unwrap();
    let renderer = SimRenderer::new(&cfg).unwrap();
    let cam = cfg.camera();
    let frame = renderer.render(2);
    let png = png_io::read_gray16(&dir.path().join("depth/000002.png")).unwrap();
    let mut valid = 0;
    for v in 0..48 {
        for u in 0..64 {
            let k = v * 64 + u;
            let (z, r) = (frame.depth_m.data[k], frame.range_m.data[k]);
            assert_eq!(png.data[k], depth_to_u16(z), "pixel ({u}, {v})");
            if r <= 0.0 {
                assert_eq!(z, 0.0);
                continue;
            }
            valid += 1;
            assert_eq!(png.data[k], (z as f64 * 5000.0).round().min(65535.0) as u16);
            // Re-derive the hit: along the pixel's ray by the range, into the camera frame.
            let ray = cam.ray(&Vector2::new(u as f64, v as f64)).unwrap();
            let p_in_world = frame.world_from_cam * Point3::from(ray * r as f64);
            let p_in_cam = frame.world_from_cam.inverse() * p_in_world;
            assert!((p_in_cam.z - z as f64).abs() < 1e-5 * (1.0 + z as f64), "({u}, {v}): z {z} vs {}", p_in_cam.z);
            assert!(z > 0.0 && (z as f64) < cfg.max_range_m && z <= r);
            // The hit lies on the seabed or on a structure above it, never under the seabed.
            let ground = renderer.scene().heightfield().height(p_in_world.x, p_in_world.y);
            assert!(p_in_world.z > ground - 1e-3, "({u}, {v}) is {} under the seabed", ground - p_in_world.z);
        }
    }
    assert!(valid > 64 * 48 * 3 / 4, "most pixels see the seabed: {valid}");
    assert_eq!(frame.t_ns, renderer.pose(2).t_ns);
}

#[test]
fn rendered_colour_follows_the_water_model_from_clear_and_range() {
    for (water, lamps) in [(WaterPreset::Coastal, false), (WaterPreset::Clear, true), (WaterPreset::Turbid, false)] {
        let cfg = SimConfig { noise_sigma: 0.0, vignetting: 0.0, lamps, ..small(water, TrajectoryKind::Survey, 2) };
        let renderer = SimRenderer::new(&cfg).unwrap();
        let m = cfg.medium();
        assert_eq!(*renderer.medium(), m);
        let frame = renderer.render(1);
        let mut checked = 0;
        for k in 0..64 * 48 {
            let r = frame.range_m.data[k] as f64;
            for c in 0..3 {
                let expected = if r > 0.0 {
                    let j = frame.clear.data[k * 3 + c] as f64 / 255.0;
                    j * (-m.beta_d[c] * r).exp() + m.b_inf[c] * (1.0 - (-m.beta_b[c] * r).exp())
                } else {
                    assert_eq!(frame.clear.data[k * 3 + c], 0, "nothing to see without water where nothing is hit");
                    m.b_inf[c]
                };
                let got = frame.rgb.data[k * 3 + c] as f64 / 255.0;
                // Quantisation of J (times transmission <= 1) and of I: at most one level.
                assert!((got - expected).abs() <= 1.0 / 255.0 + 1e-9, "{water:?} pixel {k} channel {c}: {got} vs {expected} (r = {r})");
                checked += 1;
            }
        }
        assert_eq!(checked, 64 * 48 * 3);
    }
}

#[test]
fn images_look_underwater_and_carry_texture() {
    let cfg = SimConfig { noise_sigma: 0.0, width: 96, height: 72, ..small(WaterPreset::Coastal, TrajectoryKind::Survey, 1) };
    let renderer = SimRenderer::new(&cfg).unwrap();
    let frame = renderer.render(0);
    let (w, h) = (96, 72);
    let mean = |y0: usize, y1: usize, c: usize| {
        let mut s = 0.0;
        for y in y0..y1 {
            for x in 0..w {
                s += frame.rgb.data[(y * w + x) * 3 + c] as f64;
            }
        }
        s / ((y1 - y0) * w) as f64
    };
    // Green cast in coastal water: green above red everywhere.
    assert!(mean(0, h, 1) > mean(0, h, 0) + 30.0, "green {} red {}", mean(0, h, 1), mean(0, h, 0));
    // Contrast falls with range: the top (far) rows vary less than the bottom (near) rows.
    let spread = |y0: usize, y1: usize| {
        let m = mean(y0, y1, 1);
        let mut s = 0.0;
        for y in y0..y1 {
            for x in 0..w {
                s += (frame.rgb.data[(y * w + x) * 3 + 1] as f64 - m).abs();
            }
        }
        s / ((y1 - y0) * w) as f64
    };
    // Range, counting rays that hit nothing as the max range.
    let mean_range = |y0: usize, y1: usize| {
        frame.range_m.data[y0 * w..y1 * w].iter().map(|&r| if r > 0.0 { r as f64 } else { cfg.max_range_m }).sum::<f64>() / ((y1 - y0) * w) as f64
    };
    assert!(mean_range(0, 12) > 2.0 * mean_range(60, 72), "far at the top, near at the bottom");
    // Pixel-scale texture near the camera: neighbouring pixels differ by a few levels.
    let mut grad = 0.0;
    for y in h / 2..h {
        for x in 0..w - 1 {
            grad += (frame.rgb.data[(y * w + x + 1) * 3 + 1] as f64 - frame.rgb.data[(y * w + x) * 3 + 1] as f64).abs();
        }
    }
    grad /= ((h / 2) * (w - 1)) as f64;
    assert!(grad > 2.5, "mean horizontal gradient {grad} levels");
    assert!(spread(h / 2, h) > 5.0, "near contrast {}", spread(h / 2, h));
}

#[test]
fn trajectories_keep_altitude_and_the_loop_closes() {
    for kind in [TrajectoryKind::Survey, TrajectoryKind::Loop, TrajectoryKind::Hover] {
        // The preset's path (full length), rendered small: only the poses matter here.
        let cfg = SimConfig { width: 32, height: 24, max_range_m: 6.0, ..SimConfig::preset(WaterPreset::Coastal, kind) };
        let renderer = SimRenderer::new(&cfg).unwrap();
        assert_eq!(renderer.len(), cfg.frames);
        for i in 0..renderer.len() {
            let alt = renderer.altitude_m(i).unwrap();
            assert!((1.0..=4.0).contains(&alt), "{kind:?} frame {i}: altitude {alt}");
            let p = renderer.pose(i);
            assert_eq!(p.t_ns, Timestamp::from_secs_f64(i as f64 / cfg.fps));
            // Forward-looking, pitched down by roughly the configured angle.
            let optical_axis = p.world_from_cam.rotation * nalgebra::Vector3::z();
            let pitch = (-optical_axis.z).asin().to_degrees();
            assert!((pitch - cfg.pitch_down_deg).abs() < 5.0, "{kind:?} frame {i}: pitch {pitch}");
        }
        // Smooth motion: no velocity jumps between consecutive frame pairs.
        let pos: Vec<_> = renderer.poses().iter().map(|p| p.world_from_cam.translation.vector).collect();
        for k in 2..pos.len() {
            let (v0, v1) = (pos[k - 1] - pos[k - 2], pos[k] - pos[k - 1]);
            assert!((v1 - v0).norm() < 0.2 * cfg.speed_mps / cfg.fps + 0.005, "{kind:?} frame {k}: velocity jumps by {}", (v1 - v0).norm());
        }
        if kind == TrajectoryKind::Loop {
            let (first, last) = (pos[0], pos[pos.len() - 1]);
            assert!((first - last).norm() < 1.0, "loop ends {} m from its start", (first - last).norm());
            assert!(renderer.path_length_m() > 10.0);
        }
    }
}

#[test]
fn yo_yo_altitude_swings_by_the_set_amount_and_keeps_the_plan() {
    // One 10 s cycle of +-0.6 m about 2 m; the planar path and the camera angles are the
    // constant-altitude survey's.
    let flat = SimConfig { frames: 101, width: 32, height: 24, max_range_m: 6.0, ..SimConfig::preset(WaterPreset::Turbid, TrajectoryKind::Survey) };
    let yoyo = SimConfig { altitude_swing_m: 0.6, altitude_period_s: 10.0, ..flat.clone() };
    let (a, b) = (SimRenderer::new(&flat).unwrap(), SimRenderer::new(&yoyo).unwrap());
    let alt: Vec<f64> = (0..b.len()).map(|i| b.altitude_m(i).unwrap() - a.altitude_m(i).unwrap()).collect();
    // Quarter and three-quarter cycle: highest and lowest.
    assert!((alt[25] - 0.6).abs() < 1e-9 && (alt[75] + 0.6).abs() < 1e-9, "{} {}", alt[25], alt[75]);
    assert!(alt[0].abs() < 1e-9 && alt[50].abs() < 1e-9 && alt[100].abs() < 1e-9);
    for i in 0..b.len() {
        let (pa, pb) = (a.pose(i).world_from_cam, b.pose(i).world_from_cam);
        let d = pb.translation.vector - pa.translation.vector;
        assert!(d.x.abs() < 1e-12 && d.y.abs() < 1e-12, "frame {i}: the plan moved");
        assert!(pa.rotation.angle_to(&pb.rotation) < 1e-12, "frame {i}: the camera turned");
    }
    // The images see the seabed from other ranges: at the top of the climb the median depth
    // is larger than flat's, at the bottom smaller (the 6 m max range trims the far end).
    let median_depth = |r: &SimRenderer, i: usize| {
        let mut d: Vec<f32> = r.render(i).depth_m.data.iter().copied().filter(|d| *d > 0.0).collect();
        d.sort_by(f32::total_cmp);
        d[d.len() / 2]
    };
    // The depth alone, without shading, is the rendered frame's.
    assert_eq!(b.depth_at(&b.pose(25).world_from_cam).data, b.render(25).depth_m.data);
    let (d_flat, d_up) = (median_depth(&a, 25), median_depth(&b, 25));
    assert!(d_up > d_flat * 1.12, "median depth at the top {d_up} m vs flat {d_flat} m");
    let (d_flat, d_down) = (median_depth(&a, 75), median_depth(&b, 75));
    assert!(d_down < d_flat * 0.85, "median depth at the bottom {d_down} m vs flat {d_flat} m");
}

#[test]
fn bad_input_is_a_clear_error_not_a_panic() {
    let base = small(WaterPreset::Coastal, TrajectoryKind::Survey, 2);
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (SimConfig { frames: 0, ..base.clone() }, "frames"),
        (SimConfig { width: 0, ..base.clone() }, "width"),
        (SimConfig { speed_mps: f64::NAN, ..base.clone() }, "speed_mps"),
        (SimConfig { fps: 0.0, ..base.clone() }, "fps"),
        (SimConfig { fps: -10.0, ..base.clone() }, "fps"),
        (SimConfig { altitude_m: f64::INFINITY, ..base.clone() }, "altitude_m"),
        (SimConfig { altitude_swing_m: 2.0, ..base.clone() }, "altitude_swing_m"),
    ];
    for (cfg, field) in cases {
        let e = write_sequence(&cfg, &dir.path().join("never"), false).unwrap_err();
        assert!(matches!(e, SimError::InvalidConfig { .. }), "{field}: {e:?}");
        assert!(e.to_string().contains(field), "{e}");
        assert!(SimRenderer::new(&cfg).is_err());
    }
    assert!(!dir.path().join("never").exists(), "nothing is written for an invalid config");
    // An output folder that cannot be created: its parent is a file.
    let file = dir.path().join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let e = write_sequence(&base, &file.join("seq"), false).unwrap_err();
    assert!(matches!(e, SimError::Io(_)), "{e:?}");
    assert!(e.to_string().contains("a-file"), "{e}");
}

#[test]
fn cli_writes_a_sequence_and_reports_errors() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cli");
    let run = |args: &[&str]| std::process::Command::new(env!("CARGO_BIN_EXE_duv")).arg("sim").args(args).output().unwrap();
    let ok = run(&["--out", out.to_str().unwrap(), "--frames", "3", "--width", "40", "--height", "30", "--water", "turbid", "--trajectory", "hover", "--lamps", "--no-progress", "--seed", "9"]);
    assert!(ok.status.success(), "{}", String::from_utf8_lossy(&ok.stderr));
    let stdout = String::from_utf8_lossy(&ok.stdout);
    assert!(stdout.contains("frames/s") && stdout.contains("path"), "{stdout}");
    let manifest: SimManifest = serde_json::from_str(&std::fs::read_to_string(out.join("sim.json")).unwrap()).unwrap();
    assert!(manifest.config.lamps && manifest.config.seed == 9 && manifest.config.water == WaterPreset::Turbid);
    assert_eq!(data_lines(&out.join("rgb.txt")).len(), 3);
    let bad = run(&["--out", out.to_str().unwrap(), "--frames", "0", "--no-progress"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("frames"), "{}", String::from_utf8_lossy(&bad.stderr));

    // --night is --lamps --lamp-backscatter 1 --snow 150, each overridable; sim.json records
    // the burst, medium.json keeps the base medium.
    let night_out = dir.path().join("night");
    let night = run(&["--out", night_out.to_str().unwrap(), "--frames", "3", "--width", "40", "--height", "30", "--night", "--snow", "20", "--burst", "0.1,0.2", "--no-progress"]);
    assert!(night.status.success(), "{}", String::from_utf8_lossy(&night.stderr));
    assert!(String::from_utf8_lossy(&night.stdout).contains("lamps, backscatter 1, snow 20/m3, burst 0.1+0.2 s x8"), "{}", String::from_utf8_lossy(&night.stdout));
    let manifest: SimManifest = serde_json::from_str(&std::fs::read_to_string(night_out.join("sim.json")).unwrap()).unwrap();
    let c = &manifest.config;
    assert!(c.lamps && c.lamp_backscatter == 1.0 && c.snow_per_m3 == 20.0, "{c:?}");
    assert_eq!(c.burst, Some(Burst { start_s: 0.1, duration_s: 0.2, factor: 8.0 }));
    let medium: MediumParams = serde_json::from_str(&std::fs::read_to_string(night_out.join("medium.json")).unwrap()).unwrap();
    let base = c.medium();
    let close = |a: [f64; 3], b: [f64; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-9);
    assert!(close(medium.beta_d, base.beta_d) && close(medium.beta_b, base.beta_b) && close(medium.b_inf, base.b_inf), "{medium:?} vs {base:?}");
    // The glow is the lamps' light: refused without them, by name.
    let glow = run(&["--out", dir.path().join("glow").to_str().unwrap(), "--frames", "2", "--lamp-backscatter", "1", "--no-progress"]);
    assert!(!glow.status.success());
    assert!(String::from_utf8_lossy(&glow.stderr).contains("lamp_backscatter"), "{}", String::from_utf8_lossy(&glow.stderr));
}
