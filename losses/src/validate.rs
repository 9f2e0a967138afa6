//! Small helpers shared by the config `build()` methods.

use sos_core::error::BuildError;

/// A [`BuildError::Invalid`] for `kind`/`key`.
pub(crate) fn invalid(kind: &str, key: &str, reason: impl Into<String>) -> BuildError {
    BuildError::Invalid { kind: kind.to_string(), key: key.to_string(), reason: reason.into() }
}

/// Requires a finite value.
pub(crate) fn finite(kind: &str, key: &str, v: f64) -> Result<(), BuildError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(invalid(kind, key, format!("must be a finite number, got {v}")))
    }
}

/// Requires a finite value ≥ 0.
pub(crate) fn non_negative(kind: &str, key: &str, v: f64) -> Result<(), BuildError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(kind, key, format!("must be a finite number >= 0, got {v}")))
    }
}

/// Requires a finite value > 0.
pub(crate) fn positive(kind: &str, key: &str, v: f64) -> Result<(), BuildError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(kind, key, format!("must be a finite number > 0, got {v}")))
    }
}
