//! Error types of the core. Every message names the file or key at fault and what to do.

use std::path::PathBuf;

/// A configuration file could not be read or is invalid.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config {path}: {source}")]
    Read {
        /// File that failed.
        path: PathBuf,
        /// Underlying I/O error.
        source: std::io::Error,
    },
    /// TOML syntax, an unknown kind, an unknown key or a value of the wrong type.
    #[error("invalid config {path}: {message}")]
    Parse {
        /// File that failed.
        path: PathBuf,
        /// What serde/toml reported, including the key and the allowed values.
        message: String,
    },
    /// A value parsed but is out of its allowed range.
    #[error("invalid config {path}: key `{key}`: {reason}")]
    Invalid {
        /// File that failed (may be empty for configs built in code).
        path: PathBuf,
        /// Dotted key, e.g. `field.resolution`.
        key: String,
        /// What is allowed.
        reason: String,
    },
}

/// A field's saved parameters (a checkpoint's `field` section) cannot be restored.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StateError {
    /// The bytes end before the state does.
    #[error("{kind} state is truncated (the checkpoint is incomplete or damaged)")]
    Truncated {
        /// Field kind.
        kind: String,
    },
    /// The bytes are not a state this kind writes.
    #[error("{kind} state is malformed: {reason}")]
    Malformed {
        /// Field kind.
        kind: String,
        /// What could not be read.
        reason: String,
    },
    /// A well-formed state of another shape than this config builds.
    #[error("{kind} state does not fit this config: {reason}")]
    Mismatch {
        /// Field kind.
        kind: String,
        /// What differs, and which keys may have changed.
        reason: String,
    },
}

/// A plugin could not be built from its (parsed) configuration.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// A hyperparameter is out of range.
    #[error("{kind}: key `{key}`: {reason}")]
    Invalid {
        /// Plugin kind.
        kind: String,
        /// Offending key.
        key: String,
        /// What is allowed.
        reason: String,
    },
    /// A resource the plugin needs (weights, library) is missing or unreadable.
    #[error("{kind}: {message}")]
    Resource {
        /// Plugin kind.
        kind: String,
        /// What is wrong and how to fix it.
        message: String,
    },
}

/// A feature extractor (2D teacher) failed on a batch of images.
#[derive(Debug, thiserror::Error)]
#[error("feature extractor `{extractor}`: {message}")]
pub struct ExtractError {
    /// Extractor kind, e.g. `onnx`.
    pub extractor: String,
    /// What failed (model file, output, batch) and, where possible, what to do.
    pub message: String,
}

impl ExtractError {
    /// An error of the extractor `extractor` from anything displayable.
    pub fn new(extractor: impl Into<String>, message: impl std::fmt::Display) -> Self {
        ExtractError { extractor: extractor.into(), message: message.to_string() }
    }
}

/// Reading or writing data (images, masks, checkpoints, outputs) failed.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// A file could not be read or written.
    #[error("{path}: {message}")]
    File {
        /// File at fault.
        path: PathBuf,
        /// What happened and, where possible, what to do.
        message: String,
    },
}

impl IoError {
    /// Builds an [`IoError::File`] from anything displayable.
    pub fn file(path: impl Into<PathBuf>, message: impl std::fmt::Display) -> Self {
        IoError::File { path: path.into(), message: message.to_string() }
    }
}

/// Why a run (training, rendering, evaluation) stopped.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The scene could not be loaded.
    #[error("cannot load the scene")]
    Dataset(#[from] crate::plugin::dataset::DatasetError),
    /// The scene of a config file could not be loaded.
    #[error("{config}: cannot load the scene")]
    Scene {
        /// The config file (or its folder) whose `[scene]` failed.
        config: PathBuf,
        /// Why.
        source: crate::plugin::dataset::DatasetError,
    },
    /// A plugin could not be built.
    #[error(transparent)]
    Build(#[from] BuildError),
    /// The plugin of a config file's section could not be built.
    #[error("{config}: [{section}]")]
    Plugin {
        /// The config file (or its folder).
        config: PathBuf,
        /// The config section, e.g. `field`.
        section: &'static str,
        /// Why.
        source: BuildError,
    },
    /// Reading or writing a file failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// A checkpoint is missing, corrupt or from another configuration.
    #[error("checkpoint {path}: {message}")]
    Checkpoint {
        /// Checkpoint file.
        path: PathBuf,
        /// What is wrong and what to do.
        message: String,
    },
    /// A run folder cannot be used.
    #[error("run folder {path}: {message}")]
    RunDir {
        /// The folder.
        path: PathBuf,
        /// What is wrong and what to do.
        message: String,
    },
    /// Training diverged.
    #[error("training diverged: {0}")]
    Diverged(String),
    /// The 2D teacher failed; `context` says on which images (stage-2 patches of which
    /// views, or which rendered view).
    #[error("2D teacher on {context}")]
    Teacher {
        /// What the teacher was given.
        context: String,
        /// The extractor's error.
        source: ExtractError,
    },
}
