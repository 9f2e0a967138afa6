//! `voxel-grid`: a CPU-friendly radiance field in the spirit of DVGO and Plenoxels — a dense
//! grid of density and spherical-harmonic colour coefficients, trilinearly interpolated, with
//! the density activation applied after interpolation (sharp surfaces from a coarse grid),
//! grown coarse-to-fine and optimised with sparse Adam plus total variation.
//!
//! Space is parametrised by the scene's [`Contraction`]: an affine box for bounded scenes,
//! normalised disparity for forward-facing ones, the mip-NeRF 360 contraction for unbounded.

mod field;
mod grid;
mod sparse_adam;

use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{RadianceField, RadianceFieldConfig};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;

pub use field::VoxelGridField;

/// Settings of the `voxel-grid` field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VoxelGridConfig {
    /// Final vertices per axis `[x, y, z]` in the unit cube.
    pub resolution: [usize; 3],
    /// Vertices per axis at the start of training.
    pub initial_resolution: [usize; 3],
    /// Fractions of the stage-1 steps at which the grid grows; resolutions are spaced
    /// geometrically from `initial_resolution` to `resolution`.
    pub upsample_at: Vec<f32>,
    /// Spherical-harmonic degree of the colour (0 = view-independent, up to 3).
    pub sh_degree: usize,
    /// Opacity of one voxel-length of space at initialisation (sets the softplus shift).
    pub alpha_init: f32,
    /// Adam learning rate of the density.
    pub lr_density: f32,
    /// Adam learning rate of the colour coefficients.
    #[serde(alias = "lr_color")]
    pub lr_colour: f32,
    /// Total-variation weight on the density (per touched vertex and axis).
    pub tv_density: f32,
    /// Total-variation weight on the colour coefficients.
    #[serde(alias = "tv_color")]
    pub tv_colour: f32,
    /// Positional-encoding octaves of the contracted position in the segmentation input.
    pub seg_frequencies: usize,
}

impl Default for VoxelGridConfig {
    fn default() -> Self {
        VoxelGridConfig {
            resolution: [160, 160, 160],
            initial_resolution: [32, 32, 32],
            upsample_at: vec![0.15, 0.3, 0.5],
            sh_degree: 1,
            alpha_init: 1e-3,
            lr_density: 0.1,
            lr_colour: 0.05,
            // Off by default: at initialisation the softplus slope makes photometric density
            // gradients tiny, and any total variation would dominate Adam's normalised steps.
            tv_density: 0.0,
            tv_colour: 0.0,
            seg_frequencies: 6,
        }
    }
}

/// Vertices a side a grid may have, in a config and in a checkpoint (which is input too).
pub(crate) const RESOLUTION_RANGE: std::ops::RangeInclusive<usize> = 2..=1024;

impl VoxelGridConfig {
    fn invalid(key: &str, reason: impl Into<String>) -> BuildError {
        BuildError::Invalid { kind: "voxel-grid".into(), key: key.into(), reason: reason.into() }
    }

    fn validate(&self) -> Result<(), BuildError> {
        for a in 0..3 {
            if !RESOLUTION_RANGE.contains(&self.resolution[a]) {
                return Err(Self::invalid("resolution", format!("each entry must be in {RESOLUTION_RANGE:?}")));
            }
            if !(2..=self.resolution[a]).contains(&self.initial_resolution[a]) {
                return Err(Self::invalid("initial_resolution", "each entry must be in 2..=resolution"));
            }
        }
        if self.sh_degree > 3 {
            return Err(Self::invalid("sh_degree", "must be 0, 1, 2 or 3"));
        }
        if !(self.alpha_init > 0.0 && self.alpha_init < 1.0) {
            return Err(Self::invalid("alpha_init", "must be in (0, 1)"));
        }
        if self.upsample_at.iter().any(|f| !(0.0..1.0).contains(f)) {
            return Err(Self::invalid("upsample_at", "fractions must be in [0, 1)"));
        }
        for (key, v) in [("lr_density", self.lr_density), ("lr_colour", self.lr_colour)] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(Self::invalid(key, "must be a positive number"));
            }
        }
        for (key, v) in [("tv_density", self.tv_density), ("tv_colour", self.tv_colour)] {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(Self::invalid(key, "must be zero or positive"));
            }
        }
        if self.seg_frequencies > 12 {
            return Err(Self::invalid("seg_frequencies", "must be at most 12"));
        }
        Ok(())
    }
}

sos_core::plugin_kind! {
    kind: "voxel-grid",
    summary: "dense density + spherical-harmonics grid, coarse-to-fine (DVGO/Plenoxels-style), fast on CPU",
    default: || Box::new(VoxelGridConfig::default()),
    impl RadianceFieldConfig for VoxelGridConfig {
        fn build(&self, extent: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError> {
            self.validate()?;
            let _ = seed; // The grid starts empty and uniform; nothing random to draw.
            Ok(Box::new(VoxelGridField::new(self.clone(), Contraction::new(extent), extent)))
        }

        fn memory_estimate(&self) -> Option<sos_core::plugin::FieldMemory> {
            // Density and the colour's SH coefficients per vertex, each with its gradient and
            // two Adam moments; per sample the 8 corners' indices and weights and the features.
            let channels = 1 + 3 * (self.sh_degree as u64 + 1).pow(2);
            let vertices = self.resolution.iter().map(|&r| r as u64).product::<u64>();
            Some(sos_core::plugin::FieldMemory {
                parameter_bytes: vertices.saturating_mul(channels * 4 * 4),
                parameter_key: "field.resolution".into(),
                bytes_per_sample: 8 * 8 + channels * 4,
            })
        }
    }
}
