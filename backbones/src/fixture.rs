//! Compact numeric fixtures: JSON files whose arrays are `{"shape": [...], "f32le": "<base64>"}`
//! (little-endian `f32` values, row-major, base64 with padding), a few times smaller than the
//! reference fixtures' decimal lists and exact for `f32` data.
//!
//! The repository keeps such a copy of the ViT fixtures (`fixtures/vit_tiny*/`) so that the
//! parity tests run in a clone without the shared reference folder; the
//! `vit_fixture_pack` tool of `sos-tools` writes it from the reference files.

use std::collections::BTreeMap;

const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// A row-major `f32` array.
#[derive(Debug, Clone, PartialEq)]
pub struct F32Array {
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Values, row-major.
    pub data: Vec<f32>,
}

/// Standard base64 (RFC 4648 alphabet, `=` padding).
pub fn base64_encode(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * i)) as usize & 63] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Decodes standard base64 (padding optional); `None` on any other character or a
/// dangling sextet.
pub fn base64_decode(text: &str) -> Option<Vec<u8>> {
    let mut value = [255u8; 256];
    for (i, &c) in ALPHABET.iter().enumerate() {
        value[c as usize] = i as u8;
    }
    let digits: Vec<u8> = text.trim_end_matches('=').bytes().collect();
    if digits.len() % 4 == 1 {
        return None;
    }
    let mut out = Vec::with_capacity(digits.len() * 3 / 4);
    for chunk in digits.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            let v = value[c as usize];
            if v == 255 {
                return None;
            }
            n |= (v as u32) << (18 - 6 * i);
        }
        for i in 0..chunk.len() - 1 {
            out.push((n >> (16 - 8 * i)) as u8);
        }
    }
    Some(out)
}

impl F32Array {
    /// Number of values the shape holds.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }

    /// The JSON form `{"shape": [...], "f32le": "..."}`.
    pub fn to_json(&self) -> serde_json::Value {
        let bytes: Vec<u8> = self.data.iter().flat_map(|v| v.to_le_bytes()).collect();
        serde_json::json!({ "shape": self.shape, "f32le": base64_encode(&bytes) })
    }

    /// Reads a reference fixture's array `{"shape": [...], "data": [numbers]}` (decimal
    /// `float64` lists), requiring every value to be an `f32` (the ViT fixtures are; the
    /// tolerance of 1e-12 only absorbs JSON number parsing, which need not round exactly).
    pub fn from_reference_json(value: &serde_json::Value) -> Result<F32Array, String> {
        let shape = shape_of(value)?;
        let data = value["data"]
            .as_array()
            .ok_or("no `data` list")?
            .iter()
            .map(|x| {
                let v = x.as_f64().ok_or("`data` entries must be numbers")?;
                let f = v as f32;
                if (f as f64 - v).abs() <= 1e-12 * v.abs() {
                    Ok(f)
                } else {
                    Err(format!("value {v} is not exactly a float32"))
                }
            })
            .collect::<Result<Vec<_>, String>>()?;
        F32Array::checked(shape, data)
    }

    /// Reads the JSON form; the error says what is malformed.
    pub fn from_json(value: &serde_json::Value) -> Result<F32Array, String> {
        let shape = shape_of(value)?;
        let text = value["f32le"].as_str().ok_or("no `f32le` string")?;
        let bytes = base64_decode(text).ok_or("`f32le` is not valid base64")?;
        if bytes.len() % 4 != 0 {
            return Err("`f32le` length is not a multiple of 4 bytes".into());
        }
        let data: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        F32Array::checked(shape, data)
    }

    /// The array of `shape` and `data`, which must hold as many values as the shape.
    fn checked(shape: Vec<usize>, data: Vec<f32>) -> Result<F32Array, String> {
        let array = F32Array { shape, data };
        if array.numel() != array.data.len() {
            return Err(format!("shape {:?} needs {} values, found {}", array.shape, array.numel(), array.data.len()));
        }
        Ok(array)
    }
}

/// The `shape` list of a JSON array (either form).
fn shape_of(value: &serde_json::Value) -> Result<Vec<usize>, String> {
    value["shape"]
        .as_array()
        .ok_or("no `shape` list")?
        .iter()
        .map(|d| d.as_u64().map(|d| d as usize).ok_or_else(|| "`shape` entries must be integers".to_string()))
        .collect()
}

/// A compact fixture file: a `doc` string and named arrays (in a nested `arrays` table).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CompactFixture {
    /// What the arrays are and how they were made.
    pub doc: String,
    /// Arrays by name.
    pub arrays: BTreeMap<String, F32Array>,
}

impl CompactFixture {
    /// Parses the file's text.
    pub fn parse(text: &str) -> Result<CompactFixture, String> {
        let value: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("not JSON: {e}"))?;
        let doc = value["doc"].as_str().unwrap_or_default().to_string();
        let table = value["arrays"].as_object().ok_or("no `arrays` table")?;
        let arrays = table
            .iter()
            .map(|(name, v)| {
                F32Array::from_json(v).map(|a| (name.clone(), a)).map_err(|e| format!("array `{name}`: {e}"))
            })
            .collect::<Result<_, _>>()?;
        Ok(CompactFixture { doc, arrays })
    }

    /// The file's text (pretty enough to diff: one array per line).
    pub fn to_text(&self) -> String {
        let mut out = String::from("{\n");
        out.push_str(&format!("  \"doc\": {},\n  \"arrays\": {{\n", serde_json::Value::from(self.doc.as_str())));
        let n = self.arrays.len();
        for (i, (name, a)) in self.arrays.iter().enumerate() {
            let comma = if i + 1 < n { "," } else { "" };
            out.push_str(&format!("    {}: {}{comma}\n", serde_json::Value::from(name.as_str()), a.to_json()));
        }
        out.push_str("  }\n}\n");
        out
    }

    /// The array `name`, or an error naming it.
    pub fn get(&self, name: &str) -> Result<&F32Array, String> {
        self.arrays.get(name).ok_or_else(|| format!("fixture has no array `{name}`"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trips_every_length() {
        let bytes: Vec<u8> = (0..=255u8).chain(0..40).collect();
        for len in 0..bytes.len() {
            let text = base64_encode(&bytes[..len]);
            assert_eq!(text.len() % 4, 0);
            assert_eq!(base64_decode(&text).unwrap(), &bytes[..len], "length {len}");
        }
        // Known vectors (RFC 4648 section 10).
        assert_eq!(base64_encode(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64_encode(b"fooba"), "Zm9vYmE=");
        assert_eq!(base64_encode(b"foob"), "Zm9vYg==");
        assert_eq!(base64_decode("Zm9vYg").unwrap(), b"foob");
        assert!(base64_decode("Zm9v!").is_none());
        assert!(base64_decode("Z").is_none());
    }

    #[test]
    fn arrays_round_trip_exactly_and_bad_ones_are_reported() {
        let a = F32Array { shape: vec![2, 3], data: vec![0.1, -2.5, f32::MIN_POSITIVE, 1e30, -0.0, 7.0] };
        let mut fx = CompactFixture { doc: "test \"quoted\"".into(), ..Default::default() };
        fx.arrays.insert("a".into(), a.clone());
        let back = CompactFixture::parse(&fx.to_text()).unwrap();
        assert_eq!(back, fx);
        let bad = serde_json::json!({ "shape": [4], "f32le": base64_encode(&[0u8; 12]) });
        assert!(F32Array::from_json(&bad).unwrap_err().contains("needs 4 values"));
        assert!(CompactFixture::parse("{}").unwrap_err().contains("arrays"));
        assert!(back.get("b").unwrap_err().contains("`b`"));
        let reference = serde_json::json!({ "shape": [2], "data": [0.5, -3.0] });
        assert_eq!(F32Array::from_reference_json(&reference).unwrap().data, vec![0.5, -3.0]);
        let inexact = serde_json::json!({ "shape": [1], "data": [0.1] });
        assert!(F32Array::from_reference_json(&inexact).unwrap_err().contains("float32"));
    }
}
