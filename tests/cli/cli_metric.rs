//! Metric outputs end to end (issue 40): `duv sim` writes `nav.csv`, `duv run` on the dataset
//! writes its trajectory, keyframe depth and `metric.json` in metres; `--no-nav` and a `sim:`
//! source without `nav=on` stay in map units and say why; `duv eval --align se3` refuses map
//! units; a nav file with a broken line is an error naming it.

use duv_core::io::pfm::read_pfm;
use duv_core::io::tum::read_trajectory;
use duv_pipeline::metric::MetricRecord;
use nalgebra::Vector3;
use std::path::Path;
use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

fn ok(c: &mut Command) -> (String, String) {
    let res = c.output().unwrap();
    let (o, e) = (String::from_utf8_lossy(&res.stdout).to_string(), String::from_utf8_lossy(&res.stderr).to_string());
    assert!(res.status.success(), "stdout:\n{o}\nstderr:\n{e}");
    (o, e)
}

/// The Sim(3) scale that takes `est` onto the ground truth (Umeyama over the common frames).
fn scale_to_truth(est: &Path, gt: &Path) -> f64 {
    let est = read_trajectory(est).unwrap();
    let gt = read_trajectory(gt).unwrap();
    let pairs: Vec<(Vector3<f64>, Vector3<f64>)> = est.iter().filter_map(|e| gt.iter().find(|g| g.t_ns == e.t_ns).map(|g| (e.world_from_cam.translation.vector, g.world_from_cam.translation.vector))).collect();
    let (src, dst): (Vec<_>, Vec<_>) = pairs.into_iter().unzip();
    duv_core::align::umeyama(&src, &dst, true).unwrap().scaling()
}

#[test]
fn a_dataset_with_nav_csv_gives_metric_outputs_and_without_it_map_units() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    ok(duv().args(["sim", "--water", "coastal", "--frames", "120", "--width", "160", "--height", "120", "--no-progress", "--out"]).arg(&data));
    assert!(data.join("nav.csv").is_file());
    let run = dir.path().join("run");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--source", &format!("tum:{}", data.display()), "--out"]).arg(&run));
    assert!(stdout.contains("outputs in metres: 1 map unit = "), "{stdout}");
    assert!(stdout.contains("metric: ATE with SE(3) alignment"), "{stdout}");
    let m = MetricRecord::read(&run).unwrap().unwrap();
    assert_eq!(m.length_unit, "m", "{m:?}");
    assert!(m.from_altitude.is_some(), "the altimeter sees the scale on this survey: {m:?}");
    assert_eq!(m.nav_samples, 120);
    // The trajectory is metric: the scale to the truth is 1 (the target: 2 %).
    let s = scale_to_truth(&run.join("trajectory.txt"), &data.join("groundtruth.txt"));
    assert!((s - 1.0).abs() < 0.02, "Sim(3) scale to the truth {s}");
    // So is the keyframes' depth: its median against the truth's range at the same frames is
    // checked through the camera's height above the seabed (about 2 m, the generator's
    // altitude): inverse depth in 1/m is around 1/2..1/6 at the image centre.
    let kf = std::fs::read_to_string(run.join("keyframes.txt")).unwrap();
    let id: u64 = kf.lines().find(|l| !l.starts_with('#')).unwrap().split_whitespace().next().unwrap().parse().unwrap();
    let inv = read_pfm(&run.join("keyframes").join(format!("{id:06}_invdepth.pfm"))).unwrap();
    let centre = inv.data[(inv.height / 2) * inv.width + inv.width / 2] as f64;
    assert!(centre > 1.0 / 8.0 && centre < 1.0, "inverse depth at the centre {centre} 1/m");
    // duv eval with SE(3) alignment takes the metric run.
    ok(duv().args(["eval", "--align", "se3", "--gt"]).arg(&data).arg("--run").arg(&run).arg("--out").arg(dir.path().join("eval-se3")));

    // --no-nav: map units, said so.
    let flat = dir.path().join("run-no-nav");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--no-nav", "--source", &format!("tum:{}", data.display()), "--out"]).arg(&flat));
    assert!(stdout.contains("outputs in map units (scale unknown): navigation input turned off"), "{stdout}");
    let m = MetricRecord::read(&flat).unwrap().unwrap();
    assert_eq!(m.length_unit, "map");
    assert!(m.metres_per_map_unit.is_none());
    // ... which duv eval refuses to compare with metres without a scale, unless told.
    let res = duv().args(["eval", "--align", "se3", "--gt"]).arg(&data).arg("--run").arg(&flat).arg("--out").arg(dir.path().join("eval-refused")).output().unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success() && err.contains("map units") && err.contains("--allow-map-units"), "{err}");
    ok(duv().args(["eval", "--align", "se3", "--allow-map-units", "--gt"]).arg(&data).arg("--run").arg(&flat).arg("--out").arg(dir.path().join("eval-allowed")));
}

#[test]
fn sim_sources_have_nav_only_when_asked_and_a_broken_nav_file_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--source", "sim:coastal,frames=40", "--width", "160", "--height", "120", "--out"]).arg(&plain));
    assert!(stdout.contains("outputs in map units (scale unknown): the source has no navigation input"), "{stdout}");
    let nav = dir.path().join("nav");
    let (stdout, _) = ok(duv().args(["run", "--no-map", "--no-progress", "--source", "sim:coastal,frames=100,nav=on", "--width", "160", "--height", "120", "--out"]).arg(&nav));
    assert!(stdout.contains("outputs in metres"), "{stdout}");
    assert_eq!(MetricRecord::read(&nav).unwrap().unwrap().length_unit, "m");
    // A bad option value.
    let res = duv().args(["run", "--no-map", "--source", "sim:coastal,nav=yes", "--out"]).arg(dir.path().join("bad")).output().unwrap();
    assert!(!res.status.success() && String::from_utf8_lossy(&res.stderr).contains("nav=\"yes\""), "{}", String::from_utf8_lossy(&res.stderr));
    // A nav file with a cell that is not a number: the error names the file and the line.
    let data = dir.path().join("data");
    ok(duv().args(["sim", "--frames", "10", "--width", "64", "--height", "48", "--no-progress", "--out"]).arg(&data));
    let text = std::fs::read_to_string(data.join("nav.csv")).unwrap();
    let lines: Vec<String> = text.lines().map(str::to_string).collect();
    let broken: Vec<String> = lines.iter().enumerate().map(|(i, l)| if i == 3 { let mut f: Vec<&str> = l.split(',').collect(); f[1] = "deep"; f.join(",") } else { l.clone() }).collect();
    std::fs::write(data.join("nav.csv"), broken.join("\n") + "\n").unwrap();
    let res = duv().args(["run", "--no-map", "--source", &format!("tum:{}", data.display()), "--out"]).arg(dir.path().join("broken")).output().unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success() && err.contains("nav.csv") && err.contains("line 4"), "{err}");
}
