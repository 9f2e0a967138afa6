//! Helpers of the `sos` binary's end-to-end tests.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const SOS: &str = env!("CARGO_BIN_EXE_sos");

/// A fresh folder for one test, `<prefix>-<test>` in Cargo's scratch folder for integration
/// tests (`target/tmp`). It is emptied first, so every run of the suite reuses it instead of
/// leaving another copy behind.
pub fn temp_dir(prefix: &str, test: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("{prefix}-{test}"));
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
