//! Every board profile in `boards/` parses, validates, and gives the capacities its comments
//! promise; broken variants of a real board are refused with messages that name the key.

use duv_core::config::{Board, BoardError};
use std::path::{Path, PathBuf};

fn boards_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("boards")
}

#[test]
fn every_board_file_parses() {
    let files = Board::files_in(&boards_dir()).unwrap();
    assert!(files.len() >= 3, "expected sim + two real AUV boards, found {files:?}");
    let mut names = Vec::new();
    for f in &files {
        let b = Board::load(f).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(b.schema_version, 1);
        assert_eq!(f.file_stem().unwrap().to_str().unwrap(), b.name, "file name and board name differ");
        names.push(b.name);
    }
    for required in ["sim", "jetson-orin-nx-16gb", "x86-igpu-nuc"] {
        assert!(names.iter().any(|n| n == required), "missing board {required}");
    }
}

#[test]
fn sim_board_is_ci_sized() {
    let b = Board::load(&boards_dir().join("sim.toml")).unwrap();
    assert_eq!((b.camera.width, b.camera.height), (320, 240));
    assert!(b.budgets.max_gaussians <= 100_000);
    assert!(b.budgets.ba_window <= b.budgets.max_keyframes);
    // 2 cores and a CPU mapper: the mapper takes one core at most and yields to tracking.
    assert_eq!(b.threads.mapping, 1);
    assert_eq!(b.threads.mapping_nice, 19);
}

/// Where a board pins both stages, tracking and mapping get cores of their own, and every
/// board lowers mapping's priority.
#[test]
fn tracking_owns_its_cores_on_every_board() {
    for f in Board::files_in(&boards_dir()).unwrap() {
        let b = Board::load(&f).unwrap();
        let t = &b.threads;
        if let (Some(track), Some(map)) = (&t.tracking_cores, &t.mapping_cores) {
            assert!(track.iter().all(|c| !map.contains(c)), "{}: tracking {track:?} and mapping {map:?} share a core", f.display());
        }
        assert!(t.mapping_nice >= 10, "{}: mapping_nice {}", f.display(), t.mapping_nice);
    }
    let orin = Board::load(&boards_dir().join("jetson-orin-nx-16gb.toml")).unwrap();
    assert_eq!(orin.threads.tracking_cores, Some(vec![2, 3, 4, 5]));
}

#[test]
fn real_boards_hold_the_targets() {
    // TARGETS.md: <= 2 GB GPU for 640x480 with 300k Gaussians; the Orin profile must allow both.
    let orin = Board::load(&boards_dir().join("jetson-orin-nx-16gb.toml")).unwrap();
    assert_eq!(orin.budgets.max_gaussians, 300_000);
    assert!(orin.budgets.gpu_mb >= 2048);
    assert_eq!((orin.camera.width, orin.camera.height), (640, 480));
}

#[test]
fn every_budget_of_zero_is_refused_by_name() {
    let path = boards_dir().join("sim.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    for key in ["host_mb", "gpu_mb", "max_gaussians", "max_keyframes", "map_keyframes", "ba_window", "frame_queue", "keyframe_queue", "log_queue_mb"] {
        let broken: String = text
            .lines()
            .map(|l| if l.trim_start().starts_with(&format!("{key} =")) { format!("{key} = 0") } else { l.to_string() })
            .collect::<Vec<_>>()
            .join("\n");
        assert_ne!(broken, text, "{key} not found in sim.toml");
        let err = Board::parse(&path, &broken).unwrap_err();
        assert!(matches!(err, BoardError::Invalid { .. }), "{key}: {err}");
        assert!(err.to_string().contains(&format!("budgets.{key}")), "{key}: {err}");
        assert!(err.to_string().contains("sim.toml"), "{err}");
    }
}

#[test]
fn unknown_key_and_missing_file_are_named() {
    let path = boards_dir().join("sim.toml");
    let text = std::fs::read_to_string(&path).unwrap().replace("[threads]", "[threads]\nturbo = 3");
    let err = Board::parse(&path, &text).unwrap_err().to_string();
    assert!(err.contains("unknown field `turbo`") && err.contains("sim.toml"), "{err}");
    let err = Board::load(Path::new("boards/does-not-exist.toml")).unwrap_err().to_string();
    assert!(err.contains("does-not-exist.toml"), "{err}");
}

/// The host plan counts the mapper's keyframes (8-bit and f32 image, inverse depth, variance,
/// target variance: 27 bytes a pixel) and every real board holds its plan; a board whose
/// mapper keyframes do not fit is refused with that line in the numbers.
#[test]
fn host_plan_counts_the_mapper_keyframes() {
    for f in Board::files_in(&boards_dir()).unwrap() {
        let b = Board::load(&f).unwrap();
        let (w, h) = (b.camera.width as usize, b.camera.height as usize);
        let plan = duv_pipeline::budget::plan(&b, w, h).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        assert_eq!(plan.map_keyframe_bytes, b.budgets.map_keyframes as usize * w * h * 27, "{}", f.display());
        assert!(plan.total_bytes > plan.map_keyframe_bytes + plan.keyframe_store_bytes, "{}", f.display());
        assert!(plan.headroom_bytes() > 0, "{}", f.display());
    }
    let path = boards_dir().join("jetson-orin-nx-16gb.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let line = text.lines().find(|l| l.starts_with("map_keyframes =")).unwrap();
    let greedy = Board::parse(&path, &text.replace(line, "map_keyframes = 512")).unwrap();
    // 512 keyframes of 640x480 at 27 bytes a pixel: 4050 MiB, over the 3072 MiB host budget.
    let err = duv_pipeline::budget::plan(&greedy, 640, 480).unwrap_err().to_string();
    assert!(err.contains("mapper keyframes 512 x 7.91 MiB = 4050.0 MiB"), "{err}");
    assert!(err.contains("budgets.host_mb = 3072"), "{err}");
}
