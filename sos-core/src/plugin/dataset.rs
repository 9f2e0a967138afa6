//! The dataset role: a config that opens a scene from disk (or generates one).

use std::path::Path;

use crate::derived::DerivedSetting;
use crate::registry::Registration;
use crate::scene::Scene;

/// Configuration of a dataset adapter, chosen in TOML by `[scene] kind = "..."`.
#[typetag::serde(tag = "kind")]
pub trait DatasetConfig: std::fmt::Debug + Send + Sync {
    /// Loads (or generates) the scene. Relative paths in the config are resolved against
    /// `config_dir`. Errors name the file at fault and how to fix it.
    fn open(&self, config_dir: &Path) -> Result<Scene, DatasetError>;

    /// The settings this adapter chose for `scene` (opened from this config, relative paths
    /// against `config_dir`) because the
    /// config left them unset, e.g. the extent derived from the cameras; printed at the start
    /// of a run and recorded with its results.
    fn derived(&self, _config_dir: &Path, _scene: &Scene) -> Vec<DerivedSetting> {
        Vec::new()
    }
}

inventory::collect!(Registration<dyn DatasetConfig>);

/// Why a scene could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A required file or folder is missing.
    #[error("{path}: missing; {hint}")]
    Missing {
        /// What was looked for.
        path: std::path::PathBuf,
        /// What to do.
        hint: String,
    },
    /// A file exists but its content is wrong.
    #[error("{path}: {message}")]
    Invalid {
        /// File at fault.
        path: std::path::PathBuf,
        /// What is wrong and what to do.
        message: String,
    },
    /// Image or mask decoding failed.
    #[error(transparent)]
    Io(#[from] crate::error::IoError),
}
