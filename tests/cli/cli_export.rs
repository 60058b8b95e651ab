//! `duv export` end to end on a short `sim:` run: the COLMAP model read back by `pycolmap`
//! (COLMAP's own reader) reprojects the map's points where our camera model puts them, the
//! nerfstudio frames match `keyframes.txt`, `--restored` takes the renders' restored panel, the
//! exported `map.ply` read by `@playcanvas/splat-transform` (an independent splat tool) holds
//! what our PLY reader reads; and bad input is refused naming the file.
//!
//! The external tools are found through `DUV_PYTHON` (a Python with `pycolmap`) and
//! `DUV_SPLAT_TRANSFORM` (the `splat-transform` executable), else where `.ci/run` installs them
//! (`target/py-mcap`, `target/node`); without them the checks are skipped, saying so, except
//! under `CI=true` (or with the variable set), where that is a failure.

use duv_core::io::png_io::read_image;
use duv_core::pose::se3_from_tum;
use duv_core::{PinholeCamera, Se3};
use duv_map::ply::read_ply;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Our camera model against pycolmap's projection of the exported model, px.
const PYCOLMAP_TOL_PX: f64 = 1e-6;
/// splat-transform's CSV against our PLY reader (f32 values printed and parsed back).
const SPLAT_VALUE_TOL: f64 = 1e-6;
/// COLMAP's and nerfstudio's pixel origin is the first pixel's corner, ours its centre.
const PIXEL_CENTRE_OFFSET: f64 = 0.5;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

fn ci() -> bool {
    std::env::var("CI").as_deref() == Ok("true")
}

/// The first of `candidates` that runs `args` successfully.
fn first_working(candidates: Vec<PathBuf>, args: &[&str]) -> Option<PathBuf> {
    candidates.into_iter().find(|p| Command::new(p).args(args).output().is_ok_and(|o| o.status.success()))
}

/// A Python that imports `pycolmap` (fails the test under CI without one).
fn python_with_pycolmap() -> Option<PathBuf> {
    let found = crate::python::python_with("pycolmap", "pycolmap");
    if let Some(py) = &found {
        eprintln!("pycolmap from {}", py.display());
    }
    found
}

/// `splat-transform`: `DUV_SPLAT_TRANSFORM`, the copy `.ci/run` installs, or on the PATH.
fn splat_transform() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let set = std::env::var_os("DUV_SPLAT_TRANSFORM").map(PathBuf::from);
    let found = first_working(set.clone().into_iter().chain([root.join("target/node/node_modules/.bin/splat-transform"), PathBuf::from("splat-transform")]).collect(), &["--version"]);
    match &found {
        None => {
            assert!(!ci(), "CI=true but no splat-transform (run .ci/run, or set DUV_SPLAT_TRANSFORM)");
            assert!(set.is_none(), "DUV_SPLAT_TRANSFORM is set but does not run");
            eprintln!("SKIPPED the splat-transform check: not installed (npm install --prefix target/node @playcanvas/splat-transform, or run .ci/run)");
        }
        Some(p) => eprintln!("splat-transform at {}", p.display()),
    }
    found
}

fn camera_of(run: &Path) -> PinholeCamera {
    let text = std::fs::read_to_string(run.join("calibration.txt")).unwrap();
    let v: Vec<f64> = text.split_whitespace().map(|s| s.parse().unwrap()).collect();
    assert_eq!(v.len(), 6, "an undistorted pinhole: {text}");
    PinholeCamera::new(v[0], v[1], v[2], v[3], v[4] as usize, v[5] as usize).unwrap()
}

/// `keyframes.txt`: (id, world_from_cam).
fn keyframes_of(run: &Path) -> Vec<(u64, Se3)> {
    let text = std::fs::read_to_string(run.join("keyframes.txt")).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|s| s.parse().unwrap()).collect();
            (v[0] as u64, se3_from_tum([v[2], v[3], v[4], v[5], v[6], v[7], v[8]]).unwrap())
        })
        .collect()
}

fn run_sim(dir: &Path) -> PathBuf {
    let run = dir.join("run");
    let res = duv()
        .args(["run", "--source", "sim:coastal,frames=60", "--width", "160", "--height", "120", "--no-progress"])
        .args(["--map-iterations", "4", "--map-final-iterations", "10", "--out"])
        .arg(&run)
        .output()
        .unwrap();
    assert!(res.status.success(), "duv run: {}", String::from_utf8_lossy(&res.stderr));
    run
}

fn export(run: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    duv().args(["export", "--run"]).arg(run).arg("--out").arg(out).args(extra).output().unwrap()
}

#[test]
fn export_of_a_sim_run_reads_back_in_pycolmap_and_splat_transform() {
    let dir = tempfile::tempdir().unwrap();
    let run = run_sim(dir.path());
    let out = dir.path().join("export");
    let res = export(&run, &out, &[]);
    let stdout = String::from_utf8_lossy(&res.stdout);
    assert!(res.status.success(), "stdout:\n{stdout}\nstderr:\n{}", String::from_utf8_lossy(&res.stderr));
    let cam = camera_of(&run);
    let keyframes = keyframes_of(&run);
    let map = read_ply(&run.join("map.ply"), 1 << 20).unwrap();
    assert!(keyframes.len() >= 4 && map.len() > 1000, "{} keyframes, {} Gaussians", keyframes.len(), map.len());
    assert!(stdout.contains(&format!("exported {} keyframes", keyframes.len())) && stdout.contains(&format!("{} points (of {} Gaussians)", map.len(), map.len())), "{stdout}");
    assert!(stdout.contains("length unit map"), "a sim run without nav is in map units: {stdout}");

    // Every keyframe image, copied as it is.
    for (id, _) in &keyframes {
        let name = format!("{id:06}.png");
        assert_eq!(std::fs::read(out.join("images").join(&name)).unwrap(), std::fs::read(run.join("keyframes").join(&name)).unwrap(), "{name}");
    }
    // nerfstudio: each frame's matrix is the keyframe's pose with y and z of the camera flipped.
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("transforms.json")).unwrap()).unwrap();
    let frames = json["frames"].as_array().unwrap();
    assert_eq!(frames.len(), keyframes.len());
    // (serde_json's reader may round the last digit: compared within 1e-12.)
    for (key, want) in [("fl_x", cam.fx), ("fl_y", cam.fy), ("cx", cam.cx + PIXEL_CENTRE_OFFSET), ("cy", cam.cy + PIXEL_CENTRE_OFFSET)] {
        assert!((json[key].as_f64().unwrap() - want).abs() < 1e-12, "{key}: {} vs {want}", json[key]);
    }
    assert_eq!(json["duv_length_unit"], "map");
    for (fr, (id, pose)) in frames.iter().zip(&keyframes) {
        assert_eq!(fr["file_path"], format!("images/{id:06}.png"));
        let m = pose.to_homogeneous();
        for r in 0..4 {
            for c in 0..4 {
                let want = if (c == 1 || c == 2) && r < 3 { -m[(r, c)] } else { m[(r, c)] };
                assert!((fr["transform_matrix"][r][c].as_f64().unwrap() - want).abs() < 1e-12, "keyframe {id} [{r}][{c}]");
            }
        }
    }

    // pycolmap: counts, the camera, and every 20th map point projected into each keyframe
    // against our camera model (in COLMAP's pixel convention), where it is in view.
    if let Some(py) = python_with_pycolmap() {
        let xyz: Vec<[f64; 3]> = (0..map.len()).step_by(20).map(|i| map.get(i).mean.map(|v| v as f64)).collect();
        let mut pixels = serde_json::Map::new();
        let mut in_view = 0;
        for (id, pose) in &keyframes {
            let row: Vec<serde_json::Value> = xyz
                .iter()
                .map(|p| {
                    let pc = pose.inverse_transform_point(&nalgebra::Point3::from(*p)).coords;
                    match cam.project(&pc).filter(|uv| cam.contains(uv)) {
                        Some(uv) => {
                            in_view += 1;
                            serde_json::json!([uv.x + PIXEL_CENTRE_OFFSET, uv.y + PIXEL_CENTRE_OFFSET])
                        }
                        None => serde_json::Value::Null,
                    }
                })
                .collect();
            pixels.insert(format!("{id:06}.png"), row.into());
        }
        assert!(in_view > 100, "{in_view} points in view");
        let expected = serde_json::json!({ "points_xyz": xyz, "pixels": pixels });
        let expected_path = dir.path().join("expected.json");
        std::fs::write(&expected_path, expected.to_string()).unwrap();
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/check_colmap.py");
        let res = Command::new(&py).arg(&script).arg(out.join("sparse/0")).arg(&expected_path).output().unwrap();
        assert!(res.status.success(), "check_colmap.py: {}", String::from_utf8_lossy(&res.stderr));
        let got: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
        eprintln!("pycolmap: {got}");
        assert_eq!(got["images"].as_u64(), Some(keyframes.len() as u64), "{got}");
        assert_eq!(got["registered_images"].as_u64(), Some(keyframes.len() as u64), "{got}");
        assert_eq!(got["points"].as_u64(), Some(map.len() as u64), "{got}");
        assert_eq!((got["cameras"].as_u64(), got["camera_model"].as_str()), (Some(1), Some("PINHOLE")), "{got}");
        assert_eq!((got["width"].as_u64(), got["height"].as_u64()), (Some(cam.width as u64), Some(cam.height as u64)));
        assert_eq!(got["unknown_images"].as_array().map(Vec::len), Some(0), "{got}");
        assert_eq!((got["compared"].as_u64(), got["missing_projections"].as_u64()), (Some(in_view as u64), Some(0)), "{got}");
        for key in ["max_error_project_point_px", "max_error_img_from_cam_px"] {
            assert!(got[key].as_f64().unwrap() < PYCOLMAP_TOL_PX, "{key}: {got}");
        }
        let first = map.get(0);
        for (a, v) in got["first_points_xyz"][0].as_array().unwrap().iter().enumerate() {
            assert!((v.as_f64().unwrap() - first.mean[a] as f64).abs() < 1e-12, "{got}");
        }
    }

    // splat-transform reads the exported map.ply; its CSV holds what our reader reads.
    if let Some(tool) = splat_transform() {
        let csv = dir.path().join("map.csv");
        let res = Command::new(&tool).arg("-w").arg(out.join("map.ply")).arg(&csv).output().unwrap();
        assert!(res.status.success(), "splat-transform: {}{}", String::from_utf8_lossy(&res.stdout), String::from_utf8_lossy(&res.stderr));
        let text = std::fs::read_to_string(&csv).unwrap();
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("no column {name} in {header:?}"));
        let rows: Vec<Vec<f64>> = lines.filter(|l| !l.is_empty()).map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
        assert_eq!(rows.len(), map.len(), "Gaussians splat-transform read");
        let mut compared = 0;
        for (i, row) in rows.iter().enumerate() {
            let g = map.get(i);
            let mut want: Vec<(String, f32)> = Vec::new();
            for k in 0..3 {
                want.push((["x", "y", "z"][k].into(), g.mean[k]));
                want.push((format!("scale_{k}"), g.log_scale[k]));
                want.push((format!("f_dc_{k}"), g.f_dc[k]));
            }
            for k in 0..4 {
                want.push((format!("rot_{k}"), g.rotation[k]));
            }
            // The file's f_rest is channel-major (`f_rest_{c * 3 + k}`), ours coefficient-major.
            for c in 0..3 {
                for k in 0..3 {
                    want.push((format!("f_rest_{}", c * 3 + k), g.f_rest[k * 3 + c]));
                }
            }
            want.push(("opacity".into(), g.opacity_logit));
            for (name, w) in want {
                let got = row[col(&name)];
                assert!((got - w as f64).abs() <= SPLAT_VALUE_TOL * (1.0 + (w as f64).abs()), "Gaussian {i} {name}: splat-transform {got}, ours {w}");
                compared += 1;
            }
        }
        eprintln!("splat-transform: {} Gaussians, {compared} values agree", rows.len());
    }

    // --restored: the third panel of each keyframe's render.
    let restored = dir.path().join("restored");
    let res = export(&run, &restored, &["--restored", "--format", "colmap"]);
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    assert!(!restored.join("transforms.json").exists() && restored.join("sparse/0/images.txt").is_file());
    for (id, _) in &keyframes {
        let name = format!("{id:06}.png");
        let panel = read_image(&run.join("renders").join(&name)).unwrap().to_rgb8();
        let img = read_image(&restored.join("images").join(&name)).unwrap().to_rgb8();
        assert_eq!((img.width, img.height, panel.width), (cam.width, cam.height, cam.width * 5));
        // The images sit under the panel's label strip.
        let top = panel.height - cam.height;
        assert_eq!(top, duv_map::stage::label_strip_height(cam.width));
        for y in 0..cam.height {
            let src = ((top + y) * panel.width + 2 * cam.width) * 3;
            assert_eq!(&img.data[y * cam.width * 3..(y + 1) * cam.width * 3], &panel.data[src..src + cam.width * 3], "{name} row {y}");
        }
    }
}

#[test]
fn export_refuses_bad_input_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let fails = |res: std::process::Output, needle: &str| {
        let stderr = String::from_utf8_lossy(&res.stderr);
        assert_eq!(res.status.code(), Some(if needle.contains("invalid value") { 2 } else { 1 }), "{stderr}");
        assert!(stderr.contains(needle), "{needle:?} not in: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    };
    let run = dir.path().join("run");
    fails(export(&run, &out, &[]), "not a run folder");
    std::fs::create_dir_all(run.join("keyframes")).unwrap();
    fails(export(&run, &out, &[]), "calibration.txt: missing");
    std::fs::write(run.join("calibration.txt"), "100 100 79.5 59.5 160 120\n").unwrap();
    fails(export(&run, &out, &[]), "keyframes.txt: missing");
    std::fs::write(run.join("keyframes.txt"), "0 0.0 0 0 0 0 0 0 1\n").unwrap();
    fails(export(&run, &out, &[]), "map.ply: missing");
    fails(export(&run, &out, &["--format", "ply"]), "invalid value 'ply'");
    assert!(!out.exists(), "nothing written");
}
