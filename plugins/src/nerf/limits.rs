//! The checks of the settings `nerf` and `nerf++` share (sampling, network sizes, learning
//! rate), in one order so that both kinds name the same key first; each kind keeps its own
//! bounds.

use sos_core::error::BuildError;

use super::NerfConfig;

/// What differs between the kinds' checks.
pub struct Limits {
    /// The field kind errors name.
    pub kind: &'static str,
    /// Largest `coarse_samples`.
    pub max_coarse_samples: usize,
}

impl Limits {
    /// A [`BuildError::Invalid`] of this kind.
    pub fn invalid(&self, key: &str, reason: impl Into<String>) -> BuildError {
        BuildError::Invalid { kind: self.kind.into(), key: key.into(), reason: reason.into() }
    }

    /// Checks the ranges the types cannot express.
    pub fn check(&self, config: &NerfConfig) -> Result<(), BuildError> {
        if let Some(sampling) = config.sampling() {
            if !(2..=self.max_coarse_samples).contains(&sampling.coarse_samples) {
                return Err(self.invalid("coarse_samples", format!("must be in 2..={}", self.max_coarse_samples)));
            }
            if sampling.fine_samples > 4096 {
                return Err(self.invalid("fine_samples", "must be at most 4096"));
            }
        }
        if config.pos_frequencies > 16 || config.dir_frequencies > 16 {
            return Err(self.invalid("pos_frequencies", "`pos_frequencies` and `dir_frequencies` must be at most 16"));
        }
        if !(1..=32).contains(&config.depth) {
            return Err(self.invalid("depth", "must be in 1..=32"));
        }
        if !(1..=4096).contains(&config.width) || !(1..=4096).contains(&config.view_width) {
            return Err(self.invalid("width", "`width` and `view_width` must be in 1..=4096"));
        }
        if config.skip >= config.depth {
            let depth = config.depth;
            return Err(
                self.invalid("skip", format!("must be 0 (no skip) or a trunk layer in 1..{depth} (depth = {depth})"))
            );
        }
        if !(config.lr > 0.0 && config.lr.is_finite()) {
            return Err(self.invalid("lr", "must be a positive number"));
        }
        Ok(())
    }
}

/// Test helper: building `config` fails with [`BuildError::Invalid`] naming `key`.
#[cfg(test)]
pub fn assert_rejects(
    config: &dyn sos_core::plugin::RadianceFieldConfig,
    extent: &sos_core::scene::SceneExtent,
    key: &str,
) {
    match config.build(extent, 0) {
        Err(BuildError::Invalid { key: k, .. }) => assert_eq!(k, key),
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("{key} should be rejected"),
    }
}
