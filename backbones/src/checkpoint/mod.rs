//! A checkpoint's tensors by name, whatever the file format: PyTorch's zip checkpoints
//! (`torch.save` since 1.6, as the official DINO `.pth` files), its legacy format (before 1.6,
//! or `_use_new_zipfile_serialization=False`, as the EfficientNet-Lite0 weights) and
//! `.safetensors`. The file is read once; tensors are converted to `f32` on request, so a
//! tensor the model does not use may have any type.
//!
//! - [`torch_zip`] and [`torch_legacy`] are the two `torch.save` containers, [`torch_pickle`]
//!   what both pickle (state dicts, tensor rebuild calls), on the [`pickle`] machine;
//! - [`zip`] is the part of the ZIP format the zip container needs, [`safetensors`] the other
//!   format.

pub mod pickle;
pub mod safetensors;
pub mod torch_legacy;
pub mod torch_pickle;
pub mod torch_zip;
pub mod zip;

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use sos_core::error::BuildError;

/// Element type of a stored tensor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DType {
    /// 32-bit float, the only type the models read.
    F32,
    /// Anything else, by the name the file gives it (e.g. `HalfStorage`, `F16`).
    Other(String),
}

impl DType {
    /// Bytes per element, where known.
    pub fn size(&self) -> Option<usize> {
        match self {
            DType::F32 => Some(4),
            DType::Other(_) => None,
        }
    }
}

impl std::fmt::Display for DType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DType::F32 => f.write_str("float32"),
            DType::Other(name) => f.write_str(name),
        }
    }
}

/// Which kind of file a checkpoint was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// PyTorch's zip checkpoint (`torch.save` since PyTorch 1.6).
    TorchZip,
    /// PyTorch's legacy checkpoint: consecutive pickles, then the raw storages.
    TorchLegacy,
    /// safetensors.
    Safetensors,
}

/// Where one tensor's values lie in the file.
#[derive(Debug, Clone, PartialEq)]
pub struct TensorEntry {
    /// Element type.
    pub dtype: DType,
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Element strides of each dimension.
    pub stride: Vec<usize>,
    /// Offset of the first element, in elements, from the start of `storage`.
    pub offset: usize,
    /// Byte range of the tensor's storage in the file.
    pub storage: Range<usize>,
}

impl TensorEntry {
    /// Number of elements (saturating: absurd shapes are caught by the bounds check).
    pub fn numel(&self) -> usize {
        self.shape.iter().fold(1usize, |a, &d| a.saturating_mul(d))
    }
}

/// Why a checkpoint could not be read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// The file could not be read.
    #[error("{path}: cannot read the file: {source}")]
    Io {
        /// File at fault.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The file is truncated, corrupt or in a layout this reader does not handle.
    #[error("{path}: {message}")]
    Format {
        /// File at fault.
        path: PathBuf,
        /// What is wrong and what to do.
        message: String,
    },
    /// A tensor the model needs is not stored as float32.
    #[error(
        "{path}: tensor `{name}` is stored as {dtype}; only float32 weights are supported \
         (save the state dict again after converting it with `.float()`)"
    )]
    DType {
        /// File at fault.
        path: PathBuf,
        /// Tensor name.
        name: String,
        /// Its stored type.
        dtype: DType,
    },
    /// A tensor the model needs is absent.
    #[error("{path}: no tensor `{name}`")]
    Missing {
        /// File at fault.
        path: PathBuf,
        /// Tensor name.
        name: String,
    },
}

/// The tensors of a checkpoint file.
#[derive(Debug, Clone)]
pub struct StateDict {
    path: PathBuf,
    format: Format,
    bytes: Vec<u8>,
    entries: BTreeMap<String, TensorEntry>,
}

impl StateDict {
    /// Reads the weights file of the teacher `kind` for its `build`. A missing file, or one this
    /// reader cannot read, is a [`BuildError::Resource`] that says how to get the file
    /// (`get`, before "or set `weights` …") and what it must be (`must_be`, after
    /// "`weights` must be").
    pub fn load_weights(kind: &str, path: &Path, get: &str, must_be: &str) -> Result<StateDict, BuildError> {
        let resource = |message: String| BuildError::Resource { kind: kind.into(), message };
        if !path.is_file() {
            let shown = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
            return Err(resource(format!(
                "weights file `{}` not found: {get}, or set `weights` in `[extractor]` to where it is (a relative \
                 path is resolved against the config file's folder). `kind = \"cell-stats\"` needs no weights",
                shown.display()
            )));
        }
        StateDict::load(path).map_err(|e| match e {
            CheckpointError::Format { .. } | CheckpointError::Io { .. } => {
                resource(format!("{e}. `weights` must be {must_be}"))
            }
            other => resource(other.to_string()),
        })
    }

    /// Reads a checkpoint, recognising the format from its first bytes.
    pub fn load(path: &Path) -> Result<StateDict, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io { path: path.into(), source })?;
        StateDict::from_bytes(bytes, path)
    }

    /// Reads a checkpoint from its bytes; `path` is only used in messages.
    pub fn from_bytes(bytes: Vec<u8>, path: &Path) -> Result<StateDict, CheckpointError> {
        let format_error = |message: String| CheckpointError::Format { path: path.into(), message };
        let (format, entries) = if bytes.starts_with(b"PK\x03\x04") || bytes.starts_with(b"PK\x05\x06") {
            (Format::TorchZip, torch_zip::read_entries(&bytes).map_err(format_error)?)
        } else if safetensors::looks_like(&bytes) {
            (Format::Safetensors, safetensors::read_entries(&bytes).map_err(format_error)?)
        } else if bytes.first() == Some(&0x80) {
            let entries = torch_legacy::read_entries(&bytes)
                .map_err(|m| format_error(format!("PyTorch checkpoint in the legacy (non-zip) format: {m}")))?;
            (Format::TorchLegacy, entries)
        } else if bytes.is_empty() {
            return Err(format_error("the file is empty (an interrupted download?)".into()));
        } else {
            return Err(format_error(
                "not a PyTorch zip checkpoint (.pth), a legacy PyTorch checkpoint nor a .safetensors file: the file \
                 does not start like any of them (an HTML error page saved by a failed download?)"
                    .into(),
            ));
        };
        for (name, e) in &entries {
            check_bounds(e)
                .map_err(|m| format_error(format!("tensor `{name}`: {m} (the file is corrupt or truncated)")))?;
        }
        Ok(StateDict { path: path.into(), format, bytes, entries })
    }

    /// The file it was read from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's format.
    pub fn format(&self) -> Format {
        self.format
    }

    /// Tensor names, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.entries.keys().map(String::as_str)
    }

    /// Number of tensors.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether the file holds no tensor.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The entry of `name`, if present.
    pub fn entry(&self, name: &str) -> Option<&TensorEntry> {
        self.entries.get(name)
    }

    /// Shape of `name`, if present.
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.entries.get(name).map(|e| e.shape.as_slice())
    }

    /// Values of `name` as a dense row-major `f32` array (strided tensors are gathered).
    pub fn f32(&self, name: &str) -> Result<Vec<f32>, CheckpointError> {
        let e = self
            .entries
            .get(name)
            .ok_or_else(|| CheckpointError::Missing { path: self.path.clone(), name: name.into() })?;
        if e.dtype != DType::F32 {
            return Err(CheckpointError::DType { path: self.path.clone(), name: name.into(), dtype: e.dtype.clone() });
        }
        let storage = &self.bytes[e.storage.clone()];
        let read = |i: usize| {
            let b = &storage[i * 4..i * 4 + 4];
            f32::from_le_bytes([b[0], b[1], b[2], b[3]])
        };
        let n = e.numel();
        let mut out = Vec::with_capacity(n);
        if is_contiguous(&e.shape, &e.stride) {
            out.extend((e.offset..e.offset + n).map(read));
        } else {
            let mut index = vec![0usize; e.shape.len()];
            for _ in 0..n {
                let at = e.offset + index.iter().zip(&e.stride).map(|(i, s)| i * s).sum::<usize>();
                out.push(read(at));
                for d in (0..index.len()).rev() {
                    index[d] += 1;
                    if index[d] < e.shape[d] {
                        break;
                    }
                    index[d] = 0;
                }
            }
        }
        // A diverged training run saves NaN weights; named here, they are not blamed on
        // whatever later trains on the model's features.
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            return Err(CheckpointError::Format {
                path: self.path.clone(),
                message: format!(
                    "tensor `{name}` holds {} at element {i}; the weights are damaged (or saved from a \
                     diverged run): use the published file",
                    out[i]
                ),
            });
        }
        Ok(out)
    }

    /// A 64-bit hash of the file's bytes (cache keys change when the weights do).
    pub fn content_hash(&self) -> u64 {
        content_hash(&self.bytes)
    }
}

/// Row-major strides of `shape`.
pub fn contiguous_strides(shape: &[usize]) -> Vec<usize> {
    let mut stride = vec![1usize; shape.len()];
    for d in (0..shape.len().saturating_sub(1)).rev() {
        // Saturating: an absurd shape is refused by the bounds check, not by an overflow.
        stride[d] = stride[d + 1].saturating_mul(shape[d + 1]);
    }
    stride
}

fn is_contiguous(shape: &[usize], stride: &[usize]) -> bool {
    shape.iter().zip(stride).zip(contiguous_strides(shape)).all(|((&n, &s), c)| n <= 1 || s == c)
}

/// Checks that every element of the tensor lies inside its storage.
fn check_bounds(e: &TensorEntry) -> Result<(), String> {
    if e.shape.len() != e.stride.len() {
        return Err(format!("{} dimensions but {} strides", e.shape.len(), e.stride.len()));
    }
    let Some(size) = e.dtype.size() else { return Ok(()) }; // checked when (never) read
    if !e.storage.len().is_multiple_of(size) {
        return Err(format!("storage of {} bytes is not a whole number of {size}-byte elements", e.storage.len()));
    }
    if e.numel() == 0 {
        return Ok(());
    }
    // Zero or overlapping strides could declare any number of elements over a few bytes, and
    // reading them would allocate that many: no saved weight repeats its storage.
    if e.numel() > e.storage.len() / size {
        return Err(format!(
            "shape {:?} holds {} elements, more than its storage of {}",
            e.shape,
            e.numel(),
            e.storage.len() / size
        ));
    }
    let last = e
        .shape
        .iter()
        .zip(&e.stride)
        .try_fold(e.offset, |acc, (&n, &s)| (n - 1).checked_mul(s).and_then(|x| x.checked_add(acc)));
    match last {
        Some(last) if last < e.storage.len() / size => Ok(()),
        _ => Err(format!(
            "shape {:?} (strides {:?}, offset {}) reaches past its storage of {} elements",
            e.shape,
            e.stride,
            e.offset,
            e.storage.len() / size
        )),
    }
}

/// A fast non-cryptographic 64-bit hash (8-byte words, multiply–rotate mixing).
pub fn content_hash(bytes: &[u8]) -> u64 {
    const K: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut h = 0x243F_6A88_85A3_08D3u64 ^ (bytes.len() as u64).wrapping_mul(K);
    let mut words = bytes.chunks_exact(8);
    for w in &mut words {
        let v = u64::from_le_bytes([w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7]]);
        h = (h ^ v).wrapping_mul(K).rotate_left(31);
    }
    let mut tail = [0u8; 8];
    tail[..words.remainder().len()].copy_from_slice(words.remainder());
    h = (h ^ u64::from_le_bytes(tail)).wrapping_mul(K);
    h ^= h >> 29;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^ (h >> 32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strides_and_bounds() {
        assert_eq!(contiguous_strides(&[2, 3, 4]), vec![12, 4, 1]);
        assert!(is_contiguous(&[2, 1, 4], &[4, 99, 1]));
        assert!(!is_contiguous(&[2, 3], &[1, 2]));
        let e = |shape: Vec<usize>, stride: Vec<usize>, offset, bytes| TensorEntry {
            dtype: DType::F32,
            shape,
            stride,
            offset,
            storage: 0..bytes,
        };
        assert!(check_bounds(&e(vec![2, 3], vec![3, 1], 0, 24)).is_ok());
        assert!(check_bounds(&e(vec![2, 3], vec![3, 1], 1, 24)).is_err());
        assert!(check_bounds(&e(vec![3, 2], vec![1, 3], 0, 24)).is_ok());
        assert!(check_bounds(&e(vec![2], vec![1], 0, 7)).is_err());
        assert!(check_bounds(&e(vec![0, 5], vec![5, 1], 0, 0)).is_ok());
        assert!(check_bounds(&e(vec![usize::MAX, 2], vec![usize::MAX, 1], 0, 8)).is_err());
        // A billion elements of stride 0 over one float.
        assert!(check_bounds(&e(vec![1 << 30], vec![0], 0, 4)).is_err());
    }

    #[test]
    fn hash_depends_on_every_byte_and_length() {
        let a: Vec<u8> = (0..100u8).collect();
        let h = content_hash(&a);
        for i in [0, 7, 8, 63, 99] {
            let mut b = a.clone();
            b[i] ^= 1;
            assert_ne!(content_hash(&b), h, "byte {i}");
        }
        assert_ne!(content_hash(&a[..99]), h);
        assert_ne!(content_hash(&[0]), content_hash(&[0, 0]));
        assert_eq!(content_hash(&a), h);
    }

    #[test]
    fn unknown_formats_are_named() {
        let err = |bytes: &[u8]| StateDict::from_bytes(bytes.to_vec(), Path::new("w.pth")).unwrap_err().to_string();
        assert!(err(b"").contains("empty"));
        assert!(err(b"<html>404</html>").contains("not a PyTorch zip checkpoint"));
        assert!(err(&[0x80, 0x02, 0x8a, 0x0a]).contains("legacy"));
        assert!(err(b"<html>").starts_with("w.pth: "));
    }
}
