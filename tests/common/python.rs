//! The Python interpreter the independent checks run under (the `mcap`, `rosbags` and
//! `pycolmap` packages from PyPI): `DUV_PYTHON`, else the venv `.ci/run` makes, else `python3`.
//! Under `CI=true`, or when `DUV_PYTHON` is set, a missing package fails the test instead of
//! skipping it.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The first interpreter that runs `import {imports}`; `None` (the caller skips) only outside
/// CI and without `DUV_PYTHON`.
pub fn python_with(imports: &str, package: &str) -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let set = std::env::var_os("DUV_PYTHON").map(PathBuf::from);
    let candidates: Vec<PathBuf> = set.clone().into_iter().chain([root.join("target/py-mcap/bin/python"), PathBuf::from("python3")]).collect();
    let found = candidates.into_iter().find(|py| Command::new(py).args(["-c", &format!("import {imports}")]).output().is_ok_and(|o| o.status.success()));
    if found.is_none() {
        assert!(std::env::var("CI").as_deref() != Ok("true"), "CI=true but no Python with the `{package}` package (run .ci/run, or set DUV_PYTHON)");
        assert!(set.is_none(), "DUV_PYTHON is set but cannot import the `{package}` package");
        eprintln!("SKIPPED the {package} check: no Python with the `{package}` package (pip install {package}, or run .ci/run)");
    }
    found
}
