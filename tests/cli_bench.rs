//! `duv bench track` end to end on a tiny sequence: the table, the JSON with both loop-closure
//! settings and real figures, and a clear error for an unknown sequence.

use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

#[test]
fn bench_track_on_a_tiny_survey_writes_json_and_table() {
    let dir = tempfile::tempdir().unwrap();
    let res = duv()
        .args(["bench", "track", "--sequences", "survey", "--sizes", "160x120", "--frames", "64", "--runs", "1", "--loop-closure", "both"])
        .arg("--out")
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&res.stdout);
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(res.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(stdout.contains("| survey | 160x120 | 64 | on |") && stdout.contains("| survey | 160x120 | 64 | off |"), "{stdout}");
    let md = std::fs::read_to_string(dir.path().join("bench_track.md")).unwrap();
    assert_eq!(md, stdout);
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("bench_track.json")).unwrap()).unwrap();
    let cases = json["cases"].as_array().unwrap();
    assert_eq!(cases.len(), 2);
    for c in cases {
        let m = &c["median"];
        let num = |k: &str| m[k].as_f64().unwrap_or_else(|| panic!("{k} missing: {m}"));
        assert!(num("fps") > 0.0 && num("cpu_ms_per_frame") > 0.0);
        assert!(num("latency_p99_ms") >= num("latency_p50_ms") && num("latency_p50_ms") > 0.0);
        assert!(num("flow_ms") > 0.0 && num("ba_ms") > 0.0);
        // 64 frames of a 0.5 m/s survey at 10 fps: about 3 m of path, tracked to a few percent.
        assert!((2.5..4.0).contains(&num("path_m")), "{m}");
        assert!(num("ate_percent_of_path") < 5.0, "{m}");
        assert!(num("ause") < num("ause_random"), "{m}");
        assert!(num("rss_peak_mib") > 1.0 && num("tracker_heap_peak_mib") > 1.0, "{m}");
        assert_eq!(c["all"].as_array().unwrap().len(), 1);
    }
}

#[test]
fn bench_track_rejects_an_unknown_sequence() {
    let res = duv().args(["bench", "track", "--sequences", "reef", "--runs", "1"]).output().unwrap();
    assert!(!res.status.success());
    assert!(String::from_utf8_lossy(&res.stderr).contains("unknown sequence \"reef\""));
}
