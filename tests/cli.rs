//! The `duv` binary as a user meets it: help lists every subcommand, board checking works,
//! and failures are reported as errors with a non-zero exit, never a panic.

use std::process::Command;

fn duv() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_duv"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

#[test]
fn help_lists_every_subcommand() {
    let out = duv().arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    for sub in ["demo", "run", "sim", "refine", "eval", "board", "dataset"] {
        assert!(text.lines().any(|l| l.trim_start().starts_with(sub)), "`duv --help` does not list {sub}:\n{text}");
    }
}

#[test]
fn board_check_passes_on_repo_boards_and_fails_on_a_broken_one() {
    let out = duv().arg("board").output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().filter(|l| l.starts_with("ok")).count(), 3, "{text}");
    assert!(text.lines().any(|l| l.contains("jetson-orin-nx-16gb") && l.ends_with("| log frames jpeg q90")), "{text}");
    assert!(text.lines().any(|l| l.contains(" sim ") && l.ends_with("| log frames raw")), "{text}");

    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    let sim = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/boards/sim.toml")).unwrap();
    std::fs::write(&bad, sim.replace("frame_queue = 4", "frame_queue = 0")).unwrap();
    let out = duv().arg("board").arg(&bad).output().unwrap();
    assert!(!out.status.success());
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert!(stdout.contains("bad.toml: budgets.frame_queue = 0 is invalid"), "{stdout}");
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(!stderr.contains("panicked"), "{stderr}");
}
