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
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(value)?).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}
