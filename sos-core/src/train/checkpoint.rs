//! Checkpoints: the step reached, the field's parameters and the config that produced them,
//! written atomically (temporary file + rename) so an interrupted run never leaves a broken one.

use std::io::Write;
use std::path::Path;

use crate::error::RunError;

const MAGIC: &[u8; 8] = b"SOSCKPT1";

/// What a checkpoint holds besides the field parameters.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CheckpointMeta {
    /// Stage-1 steps completed.
    pub step: usize,
    /// Field kind (checked on load).
    pub field_kind: String,
    /// The run's config, as TOML.
    pub config: String,
    /// The scene's extent the field was built for (checked on load; absent in checkpoints
    /// written before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub extent: Option<String>,
}

/// Writes `meta` and the named binary sections atomically.
pub fn save(path: &Path, meta: &CheckpointMeta, sections: &[(&str, &[u8])]) -> Result<(), RunError> {
    let err = |e: std::io::Error| RunError::Checkpoint { path: path.to_path_buf(), message: e.to_string() };
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(err)?;
    }
    let tmp = path.with_extension("tmp");
    {
        let mut f = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(err)?);
        let header = serde_json::to_vec(meta).expect("checkpoint meta serialises");
        f.write_all(MAGIC).map_err(err)?;
        write_block(&mut f, &header).map_err(err)?;
        f.write_all(&(sections.len() as u64).to_le_bytes()).map_err(err)?;
        for (name, bytes) in sections {
            write_block(&mut f, name.as_bytes()).map_err(err)?;
            write_block(&mut f, bytes).map_err(err)?;
        }
        f.into_inner().map_err(|e| err(e.into_error()))?.sync_all().map_err(err)?;
    }
    std::fs::rename(&tmp, path).map_err(err)
}

fn write_block(f: &mut impl Write, bytes: &[u8]) -> std::io::Result<()> {
    f.write_all(&(bytes.len() as u64).to_le_bytes())?;
    f.write_all(bytes)
}

/// A loaded checkpoint.
#[derive(Debug)]
pub struct Checkpoint {
    /// Metadata.
    pub meta: CheckpointMeta,
    /// Named binary sections (e.g. `field`, `head`).
    pub sections: Vec<(String, Vec<u8>)>,
}

impl Checkpoint {
    /// The bytes of section `name`.
    pub fn section(&self, name: &str) -> Option<&[u8]> {
        self.sections.iter().find(|(n, _)| n == name).map(|(_, b)| b.as_slice())
    }
}

/// Reads a checkpoint written by [`save`].
pub fn load(path: &Path) -> Result<Checkpoint, RunError> {
    let fail = |message: String| RunError::Checkpoint { path: path.to_path_buf(), message };
    let bytes = std::fs::read(path)
        .map_err(|e| fail(format!("{e}; run `sos train` first or pass the checkpoint of a finished run")))?;
    if bytes.len() < 8 || &bytes[..8] != MAGIC {
        return Err(fail("not a nerf-sos checkpoint".into()));
    }
    let mut pos = 8;
    let block = |pos: &mut usize| -> Result<Vec<u8>, RunError> {
        let len = read_u64(&bytes, *pos).ok_or_else(|| fail("truncated".into()))? as usize;
        let start = *pos + 8;
        let data = bytes.get(start..start.saturating_add(len)).ok_or_else(|| fail("truncated".into()))?;
        *pos = start + len;
        Ok(data.to_vec())
    };
    let meta: CheckpointMeta =
        serde_json::from_slice(&block(&mut pos)?).map_err(|e| fail(format!("bad header: {e}")))?;
    let n = read_u64(&bytes, pos).ok_or_else(|| fail("truncated".into()))? as usize;
    pos += 8;
    let mut sections = Vec::new();
    for _ in 0..n.min(64) {
        let name = String::from_utf8_lossy(&block(&mut pos)?).into_owned();
        let data = block(&mut pos)?;
        sections.push((name, data));
    }
    Ok(Checkpoint { meta, sections })
}

fn read_u64(bytes: &[u8], pos: usize) -> Option<u64> {
    Some(u64::from_le_bytes(bytes.get(pos..pos + 8)?.try_into().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects_truncation() {
        let dir = std::env::temp_dir().join(format!("sos-ckpt-{}", std::process::id()));
        let path = dir.join("c.bin");
        let meta = CheckpointMeta { step: 7, field_kind: "voxel-grid".into(), config: "x = 1".into(), extent: None };
        save(&path, &meta, &[("field", &[1, 2, 3]), ("head", &[])]).unwrap();
        let c = load(&path).unwrap();
        assert_eq!(c.meta, meta);
        assert_eq!(c.section("field"), Some(&[1u8, 2, 3][..]));
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 2]).unwrap();
        assert!(load(&path).unwrap_err().to_string().contains("truncated"));
        std::fs::remove_dir_all(dir).ok();
    }
}
