//! The safetensors format: an 8-byte little-endian header length, a JSON header mapping each
//! tensor name to `{"dtype", "shape", "data_offsets": [begin, end]}` (offsets relative to the
//! end of the header; an optional `__metadata__` entry holds strings), then the data.

use std::collections::BTreeMap;

use super::{contiguous_strides, DType, TensorEntry};

/// Headers larger than this are not safetensors (the format caps them at 100 MB).
const MAX_HEADER: u64 = 100_000_000;

/// Whether the bytes start like a safetensors file (a plausible header length, then `{`).
pub fn looks_like(bytes: &[u8]) -> bool {
    if bytes.len() < 9 {
        return false;
    }
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"));
    (2..=MAX_HEADER).contains(&n) && bytes[8] == b'{'
}

/// Tensor name → where its values are.
pub fn read_entries(bytes: &[u8]) -> Result<BTreeMap<String, TensorEntry>, String> {
    let n = u64::from_le_bytes(
        bytes.get(..8).ok_or("file shorter than a safetensors header")?.try_into().expect("8 bytes"),
    );
    let header_end = usize::try_from(n)
        .ok()
        .and_then(|n| n.checked_add(8))
        .filter(|&end| end <= bytes.len())
        .ok_or("safetensors header runs past the end of the file (truncated download?)")?;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..header_end])
        .map_err(|e| format!("safetensors header is not valid JSON: {e}"))?;
    let table = header.as_object().ok_or("safetensors header is not a JSON object")?;
    let data_len = bytes.len() - header_end;
    let mut entries = BTreeMap::new();
    for (name, info) in table {
        if name == "__metadata__" {
            continue;
        }
        let bad = |what: &str| format!("tensor `{name}`: {what}");
        let dtype = match info["dtype"].as_str().ok_or_else(|| bad("no dtype"))? {
            "F32" => DType::F32,
            other => DType::Other(other.to_string()),
        };
        let shape = info["shape"]
            .as_array()
            .ok_or_else(|| bad("no shape"))?
            .iter()
            .map(|d| {
                d.as_u64().and_then(|d| usize::try_from(d).ok()).ok_or_else(|| bad("shape entries must be integers"))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let offsets = info["data_offsets"]
            .as_array()
            .filter(|o| o.len() == 2)
            .and_then(|o| Some((o[0].as_u64()? as usize, o[1].as_u64()? as usize)))
            .ok_or_else(|| bad("data_offsets must be two integers"))?;
        if offsets.0 > offsets.1 || offsets.1 > data_len {
            return Err(bad(&format!(
                "data {}..{} lies outside the {data_len} data bytes (truncated download?)",
                offsets.0, offsets.1
            )));
        }
        let numel = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or_else(|| bad("shape too large"))?;
        if let Some(size) = dtype.size() {
            if numel.checked_mul(size) != Some(offsets.1 - offsets.0) {
                return Err(bad(&format!("{numel} elements do not fill its {} bytes", offsets.1 - offsets.0)));
            }
        }
        let stride = contiguous_strides(&shape);
        let storage = header_end + offsets.0..header_end + offsets.1;
        entries.insert(name.clone(), TensorEntry { dtype, shape, stride, offset: 0, storage });
    }
    Ok(entries)
}
