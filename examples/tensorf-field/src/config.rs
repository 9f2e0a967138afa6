//! The `[field] kind = "tensorf"` settings, their defaults and their checks.

use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;

/// Settings of the `tensorf` field. Every key is optional; unknown keys are refused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TensorfConfig {
    /// Final vertices per axis `[x, y, z]` of the planes and lines in the unit cube.
    pub resolution: [usize; 3],
    /// Vertices per axis at the start of training (unused without `upsample_at`).
    pub initial_resolution: [usize; 3],
    /// Fractions of the stage-1 steps at which the planes and lines are resampled to a finer
    /// resolution (TensoRF's `upsamp_list`); resolutions are spaced geometrically from
    /// `initial_resolution` to `resolution`.
    pub upsample_at: Vec<f32>,
    /// Components per plane-line pair of the density (TensoRF: 16).
    pub density_components: usize,
    /// Components per plane-line pair of the appearance (TensoRF: 48).
    pub appearance_components: usize,
    /// Width of the appearance feature the basis matrix makes of the components (TensoRF: 27).
    pub features: usize,
    /// Hidden width of the colour MLP (one ReLU layer).
    pub hidden: usize,
    /// Positional-encoding octaves of the view direction fed to the colour MLP.
    pub view_frequencies: usize,
    /// Opacity of one cell-length of space at initialisation (sets the softplus shift).
    pub alpha_init: f32,
    /// Standard deviation of the initial plane and line values.
    pub init_scale: f32,
    /// Adam learning rate of the planes and lines (decayed by the stage-1 schedule).
    pub lr_grid: f32,
    /// Adam learning rate of the basis matrix and the colour MLP.
    pub lr_network: f32,
    /// Positional-encoding octaves of the contracted position in the segmentation input.
    pub seg_frequencies: usize,
}

impl Default for TensorfConfig {
    fn default() -> Self {
        TensorfConfig {
            resolution: [128, 128, 128],
            initial_resolution: [32, 32, 32],
            upsample_at: vec![0.15, 0.3, 0.5],
            density_components: 4,
            appearance_components: 16,
            features: 27,
            hidden: 64,
            view_frequencies: 2,
            alpha_init: 1e-3,
            init_scale: 0.1,
            // TensoRF uses 0.02 and 1e-3 over 30k steps of 4096 rays; stage 1 here is a few
            // hundred to a few thousand steps.
            lr_grid: 0.1,
            lr_network: 0.01,
            seg_frequencies: 6,
        }
    }
}

impl TensorfConfig {
    /// The resolution after `stage` of the `upsample_at` growths: `initial_resolution` at 0,
    /// `resolution` after the last (and throughout when `upsample_at` is empty).
    pub fn resolution_at(&self, stage: usize) -> [usize; 3] {
        let n = self.upsample_at.len();
        if stage >= n {
            return self.resolution;
        }
        let f = stage as f32 / n as f32;
        std::array::from_fn(|a| {
            let (lo, hi) = (self.initial_resolution[a] as f32, self.resolution[a] as f32);
            (lo * (hi / lo).powf(f)).round() as usize
        })
    }

    fn invalid(key: &str, reason: impl Into<String>) -> BuildError {
        BuildError::Invalid { kind: super::KIND.into(), key: key.into(), reason: reason.into() }
    }

    /// Checks the ranges the types cannot express; the error names the offending key.
    pub fn validate(&self) -> Result<(), BuildError> {
        if self.resolution.iter().any(|r| !(2..=2048).contains(r)) {
            return Err(Self::invalid("resolution", "each entry must be in 2..=2048"));
        }
        if (0..3).any(|a| !(2..=self.resolution[a]).contains(&self.initial_resolution[a])) {
            return Err(Self::invalid("initial_resolution", "each entry must be in 2..=resolution"));
        }
        if self.upsample_at.iter().any(|f| !(0.0..1.0).contains(f)) || self.upsample_at.windows(2).any(|w| w[0] > w[1])
        {
            return Err(Self::invalid("upsample_at", "fractions must be in [0, 1) and in increasing order"));
        }
        for (key, v) in [
            ("density_components", self.density_components),
            ("appearance_components", self.appearance_components),
            ("features", self.features),
            ("hidden", self.hidden),
        ] {
            if !(1..=512).contains(&v) {
                return Err(Self::invalid(key, "must be in 1..=512"));
            }
        }
        if self.view_frequencies > 8 {
            return Err(Self::invalid("view_frequencies", "must be at most 8"));
        }
        if self.seg_frequencies > 12 {
            return Err(Self::invalid("seg_frequencies", "must be at most 12"));
        }
        if !(self.alpha_init > 0.0 && self.alpha_init < 1.0) {
            return Err(Self::invalid("alpha_init", "must be in (0, 1)"));
        }
        if !(self.init_scale > 0.0 && self.init_scale.is_finite()) {
            return Err(Self::invalid("init_scale", "must be a positive number"));
        }
        for (key, v) in [("lr_grid", self.lr_grid), ("lr_network", self.lr_network)] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(Self::invalid(key, "must be a positive number"));
            }
        }
        Ok(())
    }
}
