//! Checkpoints: the step reached, the field's parameters and the config that produced them,
//! written atomically (temporary file + rename) so an interrupted run never leaves a broken one,
//! and closed by a checksum of everything before it, so a flipped or lost byte is refused on
//! load instead of restoring a damaged field.

use std::io::Write;
use std::path::Path;

use crate::error::RunError;

/// Checkpoints with a trailing checksum.
const MAGIC: &[u8; 8] = b"SOSCKPT2";
/// Checkpoints without one (still read).
const MAGIC_UNCHECKED: &[u8; 8] = b"SOSCKPT1";
/// Bytes of the trailing checksum: FNV-1a, 64 bits, little-endian.
const CHECKSUM_BYTES: usize = 8;

/// FNV-1a (64 bits) of `bytes`: not a cryptographic hash, but any single flipped bit or byte
/// changes it, which is what a checkpoint needs to catch damage on disk or in transfer.
fn checksum(bytes: &[u8]) -> u64 {
    checksum_more(FNV_OFFSET, bytes)
}

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

/// FNV-1a of `bytes` continued from the state `hash`.
fn checksum_more(hash: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(hash, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}

/// A writer that keeps the checksum of everything written through it, so a checkpoint streams
/// to its file instead of being assembled in memory first (a copy of the field's size).
struct Checksummed<W> {
    inner: W,
    hash: u64,
}

impl<W: Write> Write for Checksummed<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hash = checksum_more(self.hash, &buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// The suffix of a temporary checkpoint being written; a leftover one is from a killed run.
pub const TEMPORARY_EXTENSION: &str = "tmp";

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
    /// Where stage 1's random stream stood (ChaCha8 word position, decimal), so a resumed run
    /// draws the rays an uninterrupted one would.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rng_position: Option<String>,
    /// The step at which stage 1 stopped on its converged loss (`train.stop_when_converged`):
    /// stage 1 is complete at `step` although the config asks for more.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub converged_at: Option<usize>,
}

/// Checkpoint section holding the field's optimiser state
/// ([`crate::plugin::RadianceField::save_optimizer_state`]).
pub const OPTIMIZER_SECTION: &str = "optimizer";
/// Checkpoint section holding the occupancy grid ([`crate::render::occupancy::OccupancyGrid::to_bytes`]).
pub const OCCUPANCY_SECTION: &str = "occupancy";

/// Writes `meta` and the named binary sections atomically.
pub fn save(path: &Path, meta: &CheckpointMeta, sections: &[(&str, &[u8])]) -> Result<(), RunError> {
    let err = |e: std::io::Error| RunError::Checkpoint { path: path.to_path_buf(), message: e.to_string() };
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(err)?;
    }
    let tmp = path.with_extension(TEMPORARY_EXTENSION);
    let header = serde_json::to_vec(meta).expect("checkpoint meta serialises");
    let file = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(err)?);
    let mut f = Checksummed { inner: file, hash: FNV_OFFSET };
    f.write_all(MAGIC).map_err(err)?;
    write_block(&mut f, &header).map_err(err)?;
    f.write_all(&(sections.len() as u64).to_le_bytes()).map_err(err)?;
    for (name, data) in sections {
        write_block(&mut f, name.as_bytes()).map_err(err)?;
        write_block(&mut f, data).map_err(err)?;
    }
    let (mut file, sum) = (f.inner, f.hash);
    file.write_all(&sum.to_le_bytes()).map_err(err)?;
    file.into_inner().map_err(|e| err(e.into_error()))?.sync_all().map_err(err)?;
    std::fs::rename(&tmp, path).map_err(err)
}

fn write_block(f: &mut impl Write, bytes: &[u8]) -> std::io::Result<()> {
    f.write_all(&(bytes.len() as u64).to_le_bytes())?;
    f.write_all(bytes)
}

/// A loaded checkpoint: the file's bytes, read once, and where each section lies in them (a
/// copy per section would double the field's memory while it loads).
#[derive(Debug)]
pub struct Checkpoint {
    /// Metadata.
    pub meta: CheckpointMeta,
    bytes: Vec<u8>,
    sections: Vec<(String, std::ops::Range<usize>)>,
}

impl Checkpoint {
    /// The bytes of section `name`.
    pub fn section(&self, name: &str) -> Option<&[u8]> {
        self.sections.iter().find(|(n, _)| n == name).map(|(_, range)| &self.bytes[range.clone()])
    }
}

/// Reads a checkpoint written by [`save`].
pub fn load(path: &Path) -> Result<Checkpoint, RunError> {
    let fail = |message: String| RunError::Checkpoint { path: path.to_path_buf(), message };
    let bytes = std::fs::read(path)
        .map_err(|e| fail(format!("{e}; run `sos train` first or pass the checkpoint of a finished run")))?;
    let end = match bytes.get(..8) {
        Some(m) if m == MAGIC => {
            let body =
                bytes.len().checked_sub(CHECKSUM_BYTES).filter(|&n| n >= 8).ok_or_else(|| fail("truncated".into()))?;
            let stored = read_u64(&bytes, body).ok_or_else(|| fail("truncated".into()))?;
            if checksum(&bytes[..body]) != stored {
                return Err(fail(
                    "its checksum does not match its contents (the file is damaged or cut short); \
                     rerun `sos train` to write it again"
                        .into(),
                ));
            }
            body
        }
        Some(m) if m == MAGIC_UNCHECKED => bytes.len(),
        _ => return Err(fail("not a nerf-sos checkpoint".into())),
    };
    let body = &bytes[..end];
    let mut pos = 8;
    let block = |pos: &mut usize| -> Result<std::ops::Range<usize>, RunError> {
        let len = read_u64(body, *pos).ok_or_else(|| fail("truncated".into()))? as usize;
        let start = *pos + 8;
        let stop = start.checked_add(len).filter(|&stop| stop <= body.len()).ok_or_else(|| fail("truncated".into()))?;
        *pos = stop;
        Ok(start..stop)
    };
    let header = block(&mut pos)?;
    let meta: CheckpointMeta = serde_json::from_slice(&body[header]).map_err(|e| fail(format!("bad header: {e}")))?;
    let n = read_u64(body, pos).ok_or_else(|| fail("truncated".into()))? as usize;
    pos += 8;
    let mut sections = Vec::new();
    for _ in 0..n.min(64) {
        let name = String::from_utf8_lossy(&body[block(&mut pos)?]).into_owned();
        let data = block(&mut pos)?;
        sections.push((name, data));
    }
    Ok(Checkpoint { meta, bytes, sections })
}

/// Writes the checkpoint at `from` to `to` in the format without a checksum, the one builds
/// from before checksums read (every build reads it), after checking `from`'s checksum: for
/// handing this build's stage 1 to an older build (`sos bench`'s `stage1_of`).
pub fn save_unchecked_copy(from: &Path, to: &Path) -> Result<(), RunError> {
    let checked = load(from)?;
    let err = |e: std::io::Error| RunError::Checkpoint { path: to.to_path_buf(), message: e.to_string() };
    let mut bytes = checked.bytes;
    if bytes[..8] == MAGIC[..] {
        bytes.truncate(bytes.len() - CHECKSUM_BYTES);
        bytes[..8].copy_from_slice(MAGIC_UNCHECKED);
    }
    let tmp = to.with_extension(TEMPORARY_EXTENSION);
    std::fs::write(&tmp, &bytes).map_err(err)?;
    std::fs::rename(&tmp, to).map_err(err)
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
        let meta = CheckpointMeta {
            step: 7,
            field_kind: "voxel-grid".into(),
            config: "x = 1".into(),
            extent: None,
            rng_position: None,
            converged_at: None,
        };
        save(&path, &meta, &[("field", &[1, 2, 3]), ("head", &[])]).unwrap();
        let c = load(&path).unwrap();
        assert_eq!(c.meta, meta);
        assert_eq!(c.section("field"), Some(&[1u8, 2, 3][..]));
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 2]).unwrap();
        let cut = load(&path).unwrap_err().to_string();
        assert!(cut.contains("checksum") || cut.contains("truncated"), "{cut}");
        std::fs::write(&path, &bytes[..12]).unwrap();
        assert!(load(&path).unwrap_err().to_string().contains("truncated"));
        std::fs::write(&path, &bytes[..5]).unwrap();
        assert!(load(&path).unwrap_err().to_string().contains("not a nerf-sos checkpoint"));
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn every_flipped_byte_is_caught() {
        let dir = std::env::temp_dir().join(format!("sos-ckpt-flip-{}", std::process::id()));
        let path = dir.join("c.bin");
        let meta = CheckpointMeta {
            step: 3,
            field_kind: "k".into(),
            config: "y = 2".into(),
            extent: None,
            rng_position: None,
            converged_at: None,
        };
        save(&path, &meta, &[("field", &[9, 8, 7, 6, 5])]).unwrap();
        let good = std::fs::read(&path).unwrap();
        for i in 0..good.len() {
            let mut bad = good.clone();
            bad[i] ^= 0x10;
            std::fs::write(&path, &bad).unwrap();
            assert!(load(&path).is_err(), "a flipped byte at {i} of {} passed", good.len());
        }
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn checkpoints_without_a_checksum_still_load() {
        let dir = std::env::temp_dir().join(format!("sos-ckpt-v1-{}", std::process::id()));
        let path = dir.join("c.bin");
        let meta = CheckpointMeta {
            step: 1,
            field_kind: "k".into(),
            config: String::new(),
            extent: None,
            rng_position: None,
            converged_at: None,
        };
        save(&path, &meta, &[("field", &[1])]).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.truncate(bytes.len() - CHECKSUM_BYTES);
        bytes[..8].copy_from_slice(MAGIC_UNCHECKED);
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(load(&path).unwrap().section("field"), Some(&[1u8][..]));
        // The unchecked copy of a checked checkpoint is exactly that file, and copies of it stay so.
        let checked = dir.join("checked.bin");
        save(&checked, &meta, &[("field", &[1])]).unwrap();
        let copy = dir.join("copy.bin");
        save_unchecked_copy(&checked, &copy).unwrap();
        assert_eq!(std::fs::read(&copy).unwrap(), bytes);
        save_unchecked_copy(&path, &copy).unwrap();
        assert_eq!(std::fs::read(&copy).unwrap(), bytes);
        let mut damaged = std::fs::read(&checked).unwrap();
        damaged[20] ^= 1;
        std::fs::write(&checked, &damaged).unwrap();
        assert!(save_unchecked_copy(&checked, &copy).unwrap_err().to_string().contains("checksum"));
        std::fs::remove_dir_all(dir).ok();
    }
}
