//! The byte layout of a field's saved state (a checkpoint's `field` section) that the
//! workspace's fields share: the length of a JSON header as a little-endian `u64`, the header
//! (what the field needs to check that the values fit its config), then every value as a
//! little-endian `f32`. A field is free to save its state otherwise; [`RadianceField::load_state`]
//! only reads what [`RadianceField::save_state`] of the same kind wrote.
//!
//! [`RadianceField::load_state`]: super::RadianceField::load_state
//! [`RadianceField::save_state`]: super::RadianceField::save_state

use crate::error::StateError;

/// A state: `header`, then the values of `parts` one part after another.
pub fn write(header: &serde_json::Value, parts: &[&[f32]]) -> Vec<u8> {
    let header = header.to_string();
    let total: usize = parts.iter().map(|p| p.len()).sum();
    let mut out = Vec::with_capacity(8 + header.len() + 4 * total);
    out.extend_from_slice(&(header.len() as u64).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for part in parts {
        for v in *part {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// The header of a state [`write()`] made and the bytes of its values. Errors name the field
/// `kind`: [`StateError::Truncated`] when the bytes end inside the header,
/// [`StateError::Malformed`] when the header is not JSON.
pub fn read<'a>(kind: &str, bytes: &'a [u8]) -> Result<(serde_json::Value, &'a [u8]), StateError> {
    let truncated = || StateError::Truncated { kind: kind.into() };
    let malformed = |reason: String| StateError::Malformed { kind: kind.into(), reason };
    let len = u64::from_le_bytes(bytes.get(..8).ok_or_else(truncated)?.try_into().expect("8 bytes"));
    let end =
        usize::try_from(len).ok().and_then(|l| l.checked_add(8)).ok_or_else(|| malformed("header length".into()))?;
    let header = serde_json::from_slice(bytes.get(8..end).ok_or_else(truncated)?)
        .map_err(|e| malformed(format!("header: {e}")))?;
    Ok((header, &bytes[end..]))
}

/// The `count` values of a state's value bytes (the body [`read`] returns):
/// [`StateError::Truncated`] when there are fewer, [`StateError::Malformed`] when bytes follow
/// the last value.
pub fn values(kind: &str, body: &[u8], count: usize) -> Result<Vec<f32>, StateError> {
    if body.len() < 4 * count {
        return Err(StateError::Truncated { kind: kind.into() });
    }
    if body.len() > 4 * count {
        return Err(StateError::Malformed {
            kind: kind.into(),
            reason: format!("{} bytes after the last value", body.len() - 4 * count),
        });
    }
    Ok(body.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().expect("4 bytes"))).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn states_round_trip_and_damage_is_named() {
        let header = serde_json::json!({ "sizes": [2, 1] });
        let bytes = write(&header, &[&[1.5, -0.0], &[f32::MIN_POSITIVE]]);
        let (back, body) = read("k", &bytes).unwrap();
        assert_eq!(back, header);
        let v = values("k", body, 3).unwrap();
        assert_eq!(
            v.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            [1.5f32, -0.0, f32::MIN_POSITIVE].map(f32::to_bits)
        );
        for cut in [0, 7, 9, bytes.len() - 1] {
            let err = read("k", &bytes[..cut]).and_then(|(_, body)| values("k", body, 3).map(|_| ()));
            assert!(matches!(err, Err(StateError::Truncated { .. })), "cut at {cut}");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(values("k", read("k", &longer).unwrap().1, 3), Err(StateError::Malformed { .. })));
        let mut huge = bytes;
        huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(read("k", &huge), Err(StateError::Malformed { .. })));
    }
}
