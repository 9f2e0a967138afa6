//! Helpers of the `sos` binary's end-to-end tests.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const SOS: &str = env!("CARGO_BIN_EXE_sos");

/// A fresh temporary folder for one test, `<prefix>-<test>-<pid>`.
pub fn temp_dir(prefix: &str, test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("{prefix}-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs the `sos` binary in `cwd`.
pub fn sos(args: &[&str], cwd: &Path) -> Output {
    Command::new(SOS).args(args).current_dir(cwd).output().expect("the sos binary runs")
}

/// Output bytes as text.
pub fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}
