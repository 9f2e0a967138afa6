//! Small helpers shared by the config `build()` methods.

use sos_core::error::BuildError;

/// A [`BuildError::Invalid`] for `kind`/`key`.
pub(crate) fn invalid(kind: &str, key: &str, reason: impl Into<String>) -> BuildError {
    BuildError::Invalid { kind: kind.to_string(), key: key.to_string(), reason: reason.into() }
}

/// Whether `v` survives the losses' `f32` arithmetic: finite there, and not a non-zero value
/// that rounds to zero (`1e-50` would turn an `epsilon` into a division by zero).
fn fits_f32(v: f64) -> bool {
    let f = v as f32;
    f.is_finite() && (f != 0.0 || v == 0.0)
}

/// Requires a finite value (in `f32`).
pub(crate) fn finite(kind: &str, key: &str, v: f64) -> Result<(), BuildError> {
    if fits_f32(v) {
        Ok(())
    } else {
        Err(invalid(kind, key, format!("must be a finite number within 32-bit floats, got {v}")))
    }
}

/// Requires a finite value ≥ 0 (in `f32`).
pub(crate) fn non_negative(kind: &str, key: &str, v: f64) -> Result<(), BuildError> {
    if fits_f32(v) && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(kind, key, format!("must be a finite number >= 0 within 32-bit floats, got {v}")))
    }
}

/// Requires a finite value > 0 (in `f32`).
pub(crate) fn positive(kind: &str, key: &str, v: f64) -> Result<(), BuildError> {
    if fits_f32(v) && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(kind, key, format!("must be a number > 0 within 32-bit floats (1e-38 to 3e38), got {v}")))
    }
}
