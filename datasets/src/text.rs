//! Reading and writing the small text and binary files of capture layouts (camera files, pose
//! matrices, JSON annotations), with errors that name the file, the place and the fix.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;

/// An [`DatasetError::Invalid`] for `path`.
pub fn invalid(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid { path: path.to_path_buf(), message: message.into() }
}

/// Reads a file; a missing file is [`DatasetError::Missing`] with `hint`.
pub fn read_bytes(path: &Path, hint: &str) -> Result<Vec<u8>, DatasetError> {
    std::fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => DatasetError::Missing { path: path.to_path_buf(), hint: hint.to_string() },
        _ => invalid(path, format!("cannot read: {e}")),
    })
}

/// Reads a UTF-8 text file; a missing file is [`DatasetError::Missing`] with `hint`.
pub fn read_text(path: &Path, hint: &str) -> Result<String, DatasetError> {
    let bytes = read_bytes(path, hint)?;
    String::from_utf8(bytes).map_err(|_| invalid(path, "not UTF-8 text; re-save it as plain text"))
}

/// Writes `contents` to `path`, creating the parent folder.
pub fn write_file(path: &Path, contents: &[u8]) -> Result<(), DatasetError> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| invalid(parent, format!("cannot create the folder: {e}")))?;
    }
    std::fs::write(path, contents).map_err(|e| invalid(path, format!("cannot write: {e}")))
}

/// Parses one whitespace-separated number; `what` says where it is (e.g. "line 3").
pub fn number(path: &Path, token: &str, what: &str) -> Result<f64, DatasetError> {
    let v: f64 = token.parse().map_err(|_| {
        invalid(path, format!("{what}: expected a number, found {token:?}; fix or regenerate the file"))
    })?;
    if !v.is_finite() {
        return Err(invalid(path, format!("{what}: value {token} is not finite (NaN or inf); fix the camera")));
    }
    Ok(v)
}

/// All whitespace-separated numbers of `text` (every one must be finite).
pub fn numbers(path: &Path, text: &str) -> Result<Vec<f64>, DatasetError> {
    let mut out = Vec::new();
    for (l, line) in text.lines().enumerate() {
        for tok in line.split_whitespace() {
            out.push(number(path, tok, &format!("line {}", l + 1))?);
        }
    }
    Ok(out)
}

/// A 4x4 matrix stored as 16 whitespace-separated numbers (row-major).
pub fn matrix4(path: &Path, text: &str) -> Result<[[f64; 4]; 4], DatasetError> {
    let v = numbers(path, text)?;
    if v.len() != 16 {
        return Err(invalid(
            path,
            format!("expected a 4x4 matrix (16 numbers), found {} numbers; write the full matrix", v.len()),
        ));
    }
    let mut m = [[0.0; 4]; 4];
    for (k, x) in v.into_iter().enumerate() {
        m[k / 4][k % 4] = x;
    }
    Ok(m)
}

/// Formats a 4x4 matrix as four lines of four numbers (shortest exact representation).
pub fn format_matrix4(m: &[[f64; 4]; 4]) -> String {
    m.iter()
        .map(|r| {
            let row: Vec<String> = r.iter().map(|x| format!("{x}")).collect();
            row.join(" ") + "\n"
        })
        .collect()
}

/// A bounds-checked little-endian reader over the bytes of a binary file.
pub struct Reader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `bytes` (read from `path`).
    pub fn new(path: &'a Path, bytes: &'a [u8]) -> Self {
        Reader { path, bytes, pos: 0 }
    }

    /// Bytes not read yet.
    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], DatasetError> {
        if self.remaining() < n {
            return Err(invalid(
                self.path,
                format!("truncated at byte {} while reading {what}; re-export the model", self.pos),
            ));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    /// Skips `n` bytes.
    pub fn skip(&mut self, n: usize, what: &str) -> Result<(), DatasetError> {
        self.take(n, what).map(|_| ())
    }

    /// A little-endian `u64`.
    pub fn u64(&mut self, what: &str) -> Result<u64, DatasetError> {
        let b = self.take(8, what)?;
        Ok(u64::from_le_bytes(b.try_into().expect("8 bytes")))
    }

    /// A little-endian `i32`.
    pub fn i32(&mut self, what: &str) -> Result<i32, DatasetError> {
        let b = self.take(4, what)?;
        Ok(i32::from_le_bytes(b.try_into().expect("4 bytes")))
    }

    /// A little-endian `f64`.
    pub fn f64(&mut self, what: &str) -> Result<f64, DatasetError> {
        let b = self.take(8, what)?;
        Ok(f64::from_le_bytes(b.try_into().expect("8 bytes")))
    }

    /// A NUL-terminated UTF-8 string.
    pub fn c_string(&mut self, what: &str) -> Result<String, DatasetError> {
        let rest = &self.bytes[self.pos..];
        let end = rest.iter().position(|&b| b == 0).ok_or_else(|| {
            invalid(self.path, format!("truncated: {what} has no terminating NUL byte; re-export the model"))
        })?;
        let s = std::str::from_utf8(&rest[..end])
            .map_err(|_| invalid(self.path, format!("{what} is not UTF-8")))?
            .to_string();
        self.pos += end + 1;
        Ok(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_and_matrices() {
        let p = Path::new("m.txt");
        let m = matrix4(p, "1 0 0 2\n0 1 0 3\n0 0 1 4\n0 0 0 1\n").unwrap();
        assert_eq!(m[2][3], 4.0);
        assert_eq!(matrix4(p, &format_matrix4(&m)).unwrap(), m);
        let err = matrix4(p, "1 0 0\n").unwrap_err().to_string();
        assert!(err.contains("m.txt") && err.contains("16 numbers"), "{err}");
        let err = numbers(p, "1 2\n3 nan").unwrap_err().to_string();
        assert!(err.contains("line 2") && err.contains("not finite"), "{err}");
        let err = numbers(p, "1 x").unwrap_err().to_string();
        assert!(err.contains("\"x\""), "{err}");
    }

    #[test]
    fn reader_reports_truncation() {
        let p = Path::new("cameras.bin");
        let bytes = [1u8, 0, 0, 0, 0, 0, 0, 0, 7, 0];
        let mut r = Reader::new(p, &bytes);
        assert_eq!(r.u64("count").unwrap(), 1);
        let err = r.i32("camera id").unwrap_err().to_string();
        assert!(err.contains("cameras.bin") && err.contains("truncated"), "{err}");
        let mut r = Reader::new(p, b"abc\0de");
        assert_eq!(r.c_string("name").unwrap(), "abc");
        assert!(r.c_string("name").is_err());
    }
}
