//! The root configuration of a run, read from TOML. Plugin sections are chosen by their
//! `kind`; every section rejects unknown keys, so a typo is an error naming the key.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::ConfigError;
use crate::plugin::{DatasetConfig, RadianceFieldConfig};

/// Everything a run needs.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Name of the run; outputs go to `<output_dir>/<name>/`.
    #[serde(default = "default_name")]
    pub name: String,
    /// Folder for run outputs, relative to the config file.
    #[serde(default = "default_output_dir")]
    pub output_dir: PathBuf,
    /// Seed of every random choice (sampling, initialisation, k-means).
    #[serde(default)]
    pub seed: u64,
    /// The scene: `kind` = a registered dataset adapter.
    pub scene: Box<dyn DatasetConfig>,
    /// The radiance field: `kind` = a registered field.
    pub field: Box<dyn RadianceFieldConfig>,
    /// Stage 1: photometric training.
    #[serde(default)]
    pub train: TrainConfig,
    /// Rendering of held-out views and camera paths.
    #[serde(default)]
    pub render: RenderConfig,
}

fn default_name() -> String {
    "run".into()
}

fn default_output_dir() -> PathBuf {
    PathBuf::from("runs")
}

/// Stage-1 (photometric) training settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimisation steps.
    pub steps: usize,
    /// Random rays per step (drawn from all training views).
    pub rays_per_step: usize,
    /// Learning-rate factor at the last step (exponential decay from 1).
    pub final_lr_factor: f32,
    /// Candidate samples per ray across the scene extent (before skipping).
    pub samples_per_ray: usize,
    /// Stop marching a ray once its transmittance is below this; 0 disables.
    pub early_stop: f32,
    /// Use the occupancy grid to skip empty space.
    pub occupancy: bool,
    /// Occupancy cells per side.
    pub occupancy_resolution: usize,
    /// Re-probe the occupancy grid every this many steps.
    pub occupancy_every: usize,
    /// Opacity over one candidate interval below which a cell counts as empty.
    pub occupancy_alpha: f32,
    /// Steps before empty-space skipping starts.
    pub occupancy_warmup: usize,
    /// Write a checkpoint every this many steps (and at the end); 0 = only at the end.
    pub checkpoint_every: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            steps: 3000,
            rays_per_step: 4096,
            final_lr_factor: 0.1,
            samples_per_ray: 384,
            early_stop: 1e-4,
            occupancy: true,
            occupancy_resolution: 128,
            occupancy_every: 16,
            occupancy_alpha: 1e-3,
            occupancy_warmup: 256,
            checkpoint_every: 1000,
        }
    }
}

/// Rendering settings for evaluation, `sos render` and camera paths.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderConfig {
    /// Rays rendered at once.
    pub chunk: usize,
    /// Render every held-out view when training ends.
    pub test_views: bool,
    /// Render the scene's novel camera path when training ends.
    pub camera_path: bool,
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig { chunk: 16384, test_views: true, camera_path: false }
    }
}

impl RunConfig {
    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<RunConfig, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Read { path: path.to_path_buf(), source })?;
        RunConfig::parse(&text, path)
    }

    /// Parses config text; `path` is only used in messages.
    pub fn parse(text: &str, path: &Path) -> Result<RunConfig, ConfigError> {
        let cfg: RunConfig = toml::from_str(text)
            .map_err(|e| ConfigError::Parse { path: path.to_path_buf(), message: e.to_string() })?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Checks ranges the types cannot express.
    pub fn validate(&self, path: &Path) -> Result<(), ConfigError> {
        let invalid = |key: &str, reason: &str| ConfigError::Invalid {
            path: path.to_path_buf(),
            key: key.into(),
            reason: reason.into(),
        };
        let t = &self.train;
        if t.rays_per_step == 0 {
            return Err(invalid("train.rays_per_step", "must be at least 1"));
        }
        if t.samples_per_ray < 2 {
            return Err(invalid("train.samples_per_ray", "must be at least 2"));
        }
        if !(t.final_lr_factor > 0.0 && t.final_lr_factor <= 1.0) {
            return Err(invalid("train.final_lr_factor", "must be in (0, 1]"));
        }
        if !(0.0..1.0).contains(&t.early_stop) {
            return Err(invalid("train.early_stop", "must be in [0, 1)"));
        }
        if t.occupancy && !(8..=512).contains(&t.occupancy_resolution) {
            return Err(invalid("train.occupancy_resolution", "must be in 8..=512"));
        }
        if t.occupancy_every == 0 {
            return Err(invalid("train.occupancy_every", "must be at least 1"));
        }
        if !(t.occupancy_alpha >= 0.0 && t.occupancy_alpha < 1.0) {
            return Err(invalid("train.occupancy_alpha", "must be in [0, 1)"));
        }
        if self.render.chunk == 0 {
            return Err(invalid("render.chunk", "must be at least 1"));
        }
        if self.name.is_empty() || self.name.contains(['/', '\\']) {
            return Err(invalid("name", "must be a non-empty file name without slashes"));
        }
        Ok(())
    }

    /// Serialises back to TOML (what `sos init` writes and what checkpoints record).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("a run config always serialises")
    }
}
