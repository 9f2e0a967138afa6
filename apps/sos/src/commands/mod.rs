//! One module per subcommand.

pub mod compare;
pub mod eval;
pub mod export;
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
    write_atomic_bytes(path, text.as_bytes())
}

/// [`write_atomic`] of any bytes (an encoded image).
pub fn write_atomic_bytes(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {} for {}", parent.display(), path.display()))?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    std::fs::write(&tmp, bytes).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}

/// Prints the settings the run derived from its scene and writes the config it runs with,
/// every default and derived value filled in, to `<run>/resolved.toml`.
pub fn announce_resolved(session: &sos_core::train::Session) -> anyhow::Result<()> {
    eprintln!("scene extent: {}; near {:.3}", session.scene.extent, session.scene.near);
    for d in &session.derived {
        eprintln!("derived: {d}");
    }
    let mut text = String::from("# The config this run used: defaults and scene-derived settings filled in.\n");
    for d in &session.derived {
        text.push_str(&format!("# derived: {d}\n"));
    }
    text.push_str(&session.config.to_toml());
    write_atomic(&session.run_dir.join("resolved.toml"), &text)
}

/// Writes `text` to standard output: a full disk or a closed file is an error naming standard
/// output (where `print!` would panic); a reader that stopped early (a broken pipe, as with
/// `| head`) is not.
pub fn write_stdout(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
            Err(anyhow::Error::new(e).context("writing to standard output"))
        }
        _ => Ok(()),
    }
}
