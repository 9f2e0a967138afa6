//! PyTorch's legacy checkpoint format (`torch.save` before 1.6, or with
//! `_use_new_zipfile_serialization=False`): pickles one after the other, then the raw storages.
//!
//! 1. the magic number `0x1950a86a20f9469cfc6c`;
//! 2. the protocol version, 1001;
//! 3. system information `{"protocol_version", "little_endian", "type_sizes"}`;
//! 4. the saved object, whose persistent ids `("storage", type, key, location, numel,
//!    view_metadata)` name the storages (see [`super::torch_pickle`]);
//! 5. the list of storage keys, in the order their data follows;
//!
//! then, for each key, its element count as 8 little-endian bytes and the elements.
//!
//! Nothing is copied and every count is checked against the file's length before it is
//! used, so a truncated or hostile file gives an error, never a panic or a large allocation.

use std::collections::{BTreeMap, HashMap};
use std::ops::Range;

use super::pickle::{self, Value};
use super::torch_pickle::{read_state_dict, storage_refs, StorageRef};
use super::TensorEntry;

/// `0x1950a86a20f9469cfc6c` as pickle's little-endian integer bytes.
const MAGIC: [u8; 10] = [0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20, 0x6a, 0xa8, 0x50, 0x19];
/// The only legacy protocol version PyTorch has written.
const PROTOCOL_VERSION: i64 = 1001;

/// Runs the pickle at `*at` and moves past it.
fn next_pickle(bytes: &[u8], at: &mut usize, what: &str) -> Result<Value, String> {
    let rest = bytes.get(*at..).unwrap_or_default();
    let (value, used) = pickle::load_prefix(rest).map_err(|e| format!("{what} (the pickle at byte {}): {e}", *at))?;
    *at += used;
    Ok(value)
}

/// Whether the system-information dict says the file was written little-endian (absent:
/// assumed, as PyTorch itself does).
fn little_endian(sys_info: &Value) -> bool {
    let Value::Dict(d) = sys_info else { return true };
    let flag = d.borrow().iter().find(|(k, _)| k.as_str() == Some("little_endian")).map(|(_, v)| v.as_int());
    flag != Some(Some(0))
}

/// Tensor name → where its values are, for a legacy PyTorch checkpoint.
pub fn read_entries(bytes: &[u8]) -> Result<BTreeMap<String, TensorEntry>, String> {
    let mut at = 0;
    let magic = next_pickle(bytes, &mut at, "the magic number")?;
    if !matches!(&magic, Value::BigInt(b) if b[..] == MAGIC) {
        return Err(format!(
            "the file starts with a pickle of {} rather than torch.save's magic number: not a PyTorch checkpoint",
            magic.describe()
        ));
    }
    let version = next_pickle(bytes, &mut at, "the protocol version")?;
    if version.as_int() != Some(PROTOCOL_VERSION) {
        return Err(format!("protocol version {} is not {PROTOCOL_VERSION} (corrupt file?)", version.describe()));
    }
    let sys_info = next_pickle(bytes, &mut at, "the system information")?;
    if !little_endian(&sys_info) {
        return Err("the checkpoint was saved on a big-endian machine; save it again on a little-endian one".into());
    }
    let root = next_pickle(bytes, &mut at, "the saved object")?;
    let keys = next_pickle(bytes, &mut at, "the list of storage keys")?;
    let keys = keys.items().ok_or_else(|| format!("the list of storage keys is a {}", keys.describe()))?;

    let mut by_key: HashMap<String, StorageRef> = HashMap::new();
    for r in storage_refs(&root)? {
        if let Some(other) = by_key.get(&r.key) {
            if other.type_name != r.type_name {
                return Err(format!(
                    "storage `{}` is named both a {} and a {} (corrupt file)",
                    r.key, other.type_name, r.type_name
                ));
            }
            continue;
        }
        by_key.insert(r.key.clone(), r);
    }

    let mut ranges: HashMap<String, Range<usize>> = HashMap::new();
    for key in keys {
        let key = match &key {
            Value::Str(s) => s.to_string(),
            Value::Int(i) => i.to_string(),
            other => return Err(format!("a storage key is a {} (corrupt file)", other.describe())),
        };
        let r = by_key.get(&key).ok_or_else(|| {
            format!(
                "storage `{key}` has data but no tensor refers to it, so its element size is unknown (corrupt file)"
            )
        })?;
        let size = r.element_size().ok_or_else(|| {
            format!("storage `{key}` is a {}, whose element size this reader does not know", r.type_name)
        })?;
        let header = at.checked_add(8).and_then(|end| bytes.get(at..end)).ok_or_else(|| {
            format!("the file ends at byte {} before the size of storage `{key}` (truncated download?)", bytes.len())
        })?;
        let count = u64::from_le_bytes(header.try_into().map_err(|_| "8-byte storage size")?);
        if let Some(n) = r.numel.filter(|&n| n != count) {
            return Err(format!("storage `{key}` holds {count} elements but the pickle says {n} (corrupt file)"));
        }
        let start = at + 8;
        let end = usize::try_from(count)
            .ok()
            .and_then(|c| c.checked_mul(size))
            .and_then(|len| start.checked_add(len))
            .filter(|&end| end <= bytes.len())
            .ok_or_else(|| {
                format!(
                    "storage `{key}` ({count} elements of {size} bytes from byte {start}) runs past the end of the file \
                     at byte {} (truncated download?)",
                    bytes.len()
                )
            })?;
        if ranges.insert(key.clone(), start..end).is_some() {
            return Err(format!("storage `{key}` is listed twice (corrupt file)"));
        }
        at = end;
    }

    read_state_dict(&root, &|s: &StorageRef| {
        if s.is_view {
            return Err("its storage is a view into another one (PyTorch before 0.4), which this reader does not \
                        support; load the file with PyTorch and save it again"
                .into());
        }
        ranges
            .get(&s.key)
            .cloned()
            .ok_or_else(|| format!("storage `{}` is not among the file's storages (truncated or corrupt file)", s.key))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A protocol-2 unicode string.
    fn text(s: &str) -> Vec<u8> {
        let mut b = vec![b'X'];
        b.extend((s.len() as u32).to_le_bytes());
        b.extend(s.as_bytes());
        b
    }

    /// A legacy file holding `{"w": tensor[2] of storage "0"}`, written as torch lays it out;
    /// `view` replaces the id's view metadata, `little` the byte-order flag, `keys` the list.
    fn file(view: &[u8], little: bool, keys: &[&str], values: &[f32]) -> Vec<u8> {
        let mut b = vec![0x80, 2, 0x8a, 10];
        b.extend(MAGIC);
        b.extend(b".\x80\x02M\xe9\x03.\x80\x02}(");
        b.extend(text("little_endian"));
        b.push(if little { 0x88 } else { 0x89 });
        b.extend(b"u.\x80\x02}");
        b.extend(text("w"));
        b.extend(b"ctorch._utils\n_rebuild_tensor_v2\n((");
        b.extend(text("storage"));
        b.extend(b"ctorch\nFloatStorage\n");
        b.extend(text("0"));
        b.extend(text("cpu"));
        b.extend(b"K\x02");
        b.extend(view);
        b.extend(b"tQK\x00K\x02\x85K\x01\x85\x89NtRs.\x80\x02](");
        for k in keys {
            b.extend(text(k));
        }
        b.extend(b"e.");
        for _ in keys {
            b.extend(2u64.to_le_bytes());
            b.extend(values.iter().flat_map(|v| v.to_le_bytes()));
        }
        b
    }

    #[test]
    fn hand_written_file_and_the_cases_torch_does_not_write() {
        let good = file(b"N", true, &["0"], &[1.5, -2.0]);
        let entries = read_entries(&good).unwrap();
        let w = &entries["w"];
        assert_eq!((w.shape.clone(), w.stride.clone(), w.offset), (vec![2], vec![1], 0));
        assert_eq!(&good[w.storage.clone()], [1.5f32.to_le_bytes(), (-2.0f32).to_le_bytes()].concat());
        let err = |bytes: Vec<u8>| read_entries(&bytes).unwrap_err();
        assert!(err(file(b"N", false, &["0"], &[1.0, 2.0])).contains("big-endian"));
        assert!(err(file(b"K\x01", true, &["0"], &[1.0, 2.0])).contains("view"));
        assert!(err(file(b"N", true, &["0", "7"], &[1.0, 2.0])).contains("no tensor refers to it"));
        assert!(err(file(b"N", true, &["0", "0"], &[1.0, 2.0])).contains("listed twice"));
        assert!(err(file(b"N", true, &[], &[])).contains("not among the file's storages"));
        let mut wrong_version = good.clone();
        wrong_version[18] = 0xea; // 1001 -> 1002
        assert!(err(wrong_version).contains("protocol version 1002 is not 1001"));
    }
}
