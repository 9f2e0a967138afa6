//! A small `.npy` reader and writer for float arrays (`poses_bounds.npy`).
//!
//! Reads format versions 1, 2 and 3 with dtype `<f8` or `<f4`, C order, 1-D or 2-D. The header
//! is parsed defensively: sizes are bounded and checked against the file length, so a hostile
//! or truncated file gives an error naming it, never a panic or a huge allocation.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;

const MAGIC: &[u8] = b"\x93NUMPY";
/// Larger headers are not produced by numpy for 1-D/2-D arrays; refuse to scan them.
const MAX_HEADER: usize = 1 << 16;

/// A float array read from `.npy`, widened to `f64`, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Dimensions (one or two).
    pub shape: Vec<usize>,
    /// Values in C order.
    pub data: Vec<f64>,
}

fn invalid(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid { path: path.to_path_buf(), message: message.into() }
}

/// Reads a `.npy` file.
pub fn read_npy(path: &Path) -> Result<NpyArray, DatasetError> {
    let bytes = std::fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => {
            DatasetError::Missing { path: path.to_path_buf(), hint: "expected a .npy file here".into() }
        }
        _ => invalid(path, format!("cannot read: {e}")),
    })?;
    parse_npy(&bytes).map_err(|m| invalid(path, format!("{m}; re-save it with numpy.save")))
}

/// Parses `.npy` bytes; the error says what is wrong (without the path).
pub fn parse_npy(bytes: &[u8]) -> Result<NpyArray, String> {
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err("not a .npy file (bad magic bytes)".into());
    }
    let major = bytes[6];
    let (header_len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err("truncated .npy header".into());
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(format!("unsupported .npy format version {v}")),
    };
    if header_len > MAX_HEADER || start + header_len > bytes.len() {
        return Err(format!("truncated or oversized .npy header ({header_len} bytes)"));
    }
    let header =
        std::str::from_utf8(&bytes[start..start + header_len]).map_err(|_| "header is not text".to_string())?;
    let descr = dict_value(header, "descr").ok_or("header has no 'descr'")?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    let width = match descr {
        "<f8" => 8,
        "<f4" => 4,
        d => return Err(format!("dtype {d} is not supported (only little-endian <f8 or <f4)")),
    };
    match dict_value(header, "fortran_order") {
        Some("False") => {}
        Some("True") => return Err("Fortran-order array; save numpy.ascontiguousarray(a) instead".into()),
        _ => return Err("header has no valid 'fortran_order'".into()),
    }
    let shape = parse_shape(dict_value(header, "shape").ok_or("header has no 'shape'")?)?;
    if shape.is_empty() || shape.len() > 2 {
        return Err(format!("expected a 1-D or 2-D array, got shape {shape:?}"));
    }
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| format!("shape {shape:?} overflows"))?;
    let body = &bytes[start + header_len..];
    let want = count.checked_mul(width).ok_or_else(|| format!("shape {shape:?} overflows"))?;
    if body.len() < want {
        return Err(format!("truncated: shape {shape:?} needs {want} data bytes, file has {}", body.len()));
    }
    let data = body[..want]
        .chunks_exact(width)
        .map(|c| match width {
            8 => f64::from_le_bytes(c.try_into().expect("chunk of 8")),
            _ => f32::from_le_bytes(c.try_into().expect("chunk of 4")) as f64,
        })
        .collect();
    Ok(NpyArray { shape, data })
}

/// The raw text of `'key': value` in a numpy header dict (value up to the next top-level comma
/// or closing brace).
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let pos = header.find(&format!("'{key}'")).or_else(|| header.find(&format!("\"{key}\"")))?;
    let rest = &header[pos + key.len() + 2..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    let end = if rest.starts_with('(') { rest.find(')')? + 1 } else { rest.find([',', '}']).unwrap_or(rest.len()) };
    Some(rest[..end].trim())
}

fn parse_shape(text: &str) -> Result<Vec<usize>, String> {
    let inner = text.strip_prefix('(').and_then(|t| t.strip_suffix(')')).ok_or_else(|| format!("bad shape {text}"))?;
    inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("bad shape {text}")))
        .collect()
}

/// Writes a C-order `<f8` array in `.npy` format version 1.0.
pub fn write_npy(path: &Path, shape: &[usize], data: &[f64]) -> Result<(), DatasetError> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(invalid(path, format!("shape {shape:?} does not match {} values", data.len())));
    }
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_text = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape_text}, }}");
    // numpy pads the header with spaces and a newline to a multiple of 64 bytes.
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + 8 * data.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&[1, 0]);
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| invalid(parent, format!("cannot create: {e}")))?;
    }
    std::fs::write(path, bytes).map_err(|e| invalid(path, format!("cannot write: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("sos-npy-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(format!("{name}.npy"))
    }

    #[test]
    fn round_trips_and_reads_f4_and_v2() {
        let path = temp("rt");
        let data: Vec<f64> = (0..34 * 17).map(|i| i as f64 * 0.25 - 3.0).collect();
        write_npy(&path, &[34, 17], &data).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!((bytes.len() - data.len() * 8) % 64, 0, "header not 64-aligned");
        let back = read_npy(&path).unwrap();
        assert_eq!(back.shape, vec![34, 17]);
        assert_eq!(back.data, data);

        // Version 2 header, <f4, 1-D, as numpy writes it.
        let mut v2 = MAGIC.to_vec();
        v2.extend_from_slice(&[2, 0]);
        let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (3,), }\n";
        v2.extend_from_slice(&(header.len() as u32).to_le_bytes());
        v2.extend_from_slice(header.as_bytes());
        for v in [1.5f32, -2.0, 3.25] {
            v2.extend_from_slice(&v.to_le_bytes());
        }
        let a = parse_npy(&v2).unwrap();
        assert_eq!((a.shape, a.data), (vec![3], vec![1.5, -2.0, 3.25]));
        std::fs::remove_dir_all(path.parent().unwrap()).ok();
    }

    #[test]
    fn hostile_inputs_are_errors_naming_the_file() {
        let path = temp("bad");
        write_npy(&path, &[4, 17], &vec![1.0; 68]).unwrap();
        let good = std::fs::read(&path).unwrap();
        let header_end = good.len() - 68 * 8;
        let mut cases: Vec<(&str, Vec<u8>)> = vec![
            ("truncated data", good[..good.len() - 9].to_vec()),
            ("truncated header", good[..20].to_vec()),
            ("empty", Vec::new()),
            ("bad magic", b"PK\x03\x04 not numpy at all".to_vec()),
        ];
        let with_header = |h: &str| {
            let mut b = MAGIC.to_vec();
            b.extend_from_slice(&[1, 0]);
            b.extend_from_slice(&(h.len() as u16).to_le_bytes());
            b.extend_from_slice(h.as_bytes());
            b.extend_from_slice(&good[header_end..]);
            b
        };
        cases.push(("big endian", with_header("{'descr': '>f8', 'fortran_order': False, 'shape': (4, 17), }")));
        cases.push(("fortran", with_header("{'descr': '<f8', 'fortran_order': True, 'shape': (4, 17), }")));
        cases.push(("3-D", with_header("{'descr': '<f8', 'fortran_order': False, 'shape': (2, 2, 17), }")));
        cases.push((
            "overflow",
            with_header("{'descr': '<f8', 'fortran_order': False, 'shape': (99999999999999, 99999999999), }"),
        ));
        cases.push(("garbage shape", with_header("{'descr': '<f8', 'fortran_order': False, 'shape': (a, b), }")));
        cases.push(("no shape", with_header("{'descr': '<f8', 'fortran_order': False}")));
        let mut huge = good.clone();
        huge[8] = 0xff;
        huge[9] = 0xff;
        cases.push(("header length past the end", huge));
        for (what, bytes) in cases {
            std::fs::write(&path, bytes).unwrap();
            let err = read_npy(&path).expect_err(what).to_string();
            assert!(err.contains("bad.npy"), "{what}: {err}");
        }
        let missing = read_npy(&path.with_file_name("nope.npy")).unwrap_err().to_string();
        assert!(missing.contains("nope.npy") && missing.contains("missing"), "{missing}");
        std::fs::remove_dir_all(path.parent().unwrap()).ok();
    }
}
