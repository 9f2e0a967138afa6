//! One module per subcommand.

pub mod compare;
pub mod eval;
pub mod init;
pub mod list;
pub mod render;
pub mod segment;
pub mod stage2;
pub mod train;

use std::path::Path;

use anyhow::Context;
use serde::Serialize;

/// Writes pretty JSON atomically.
pub fn write_json(path: &Path, value: &impl Serialize) -> anyhow::Result<()> {
    write_atomic(path, &serde_json::to_string_pretty(value)?)
}

/// Writes a text file atomically (a temporary file renamed into place), creating its folder:
/// a killed process leaves the old file or the new one, never half of one.
pub fn write_atomic(path: &Path, text: &str) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}
