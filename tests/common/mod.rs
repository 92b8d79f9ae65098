//! Shared helpers for the integration tests.
#![allow(dead_code)]
use std::path::PathBuf;

/// Path of the built `colmap-lidar` binary.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_colmap-lidar"))
}

/// True when Debian's `colmap` binary is on PATH. Tests that need it print a
/// loud message and return early when it is absent; CI installs it.
pub fn have_colmap() -> bool {
    let found = std::process::Command::new("colmap")
        .arg("help")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok();
    if !found {
        eprintln!(
            "\n!!!!! SKIPPED: the `colmap` binary is not installed (run scripts/setup.sh) !!!!!\n"
        );
    }
    found
}
