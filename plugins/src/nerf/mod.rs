//! `nerf`: the reference NeRF backbone, so that results compare with the paper. Positional
//! encoding with 10 (position) and 4 (direction) octaves, an 8 x 256 ReLU trunk whose layer 5
//! also reads the encoded position, a density head, a 128-wide view branch, and separate coarse
//! and fine networks with 64 stratified + 128 importance samples per ray.
//!
//! Positions enter the networks through the scene's unit-cube mapping scaled to `[−1, 1]³`
//! (an affine box for bounded scenes, NDC-like disparity for forward-facing ones, the
//! mip-NeRF 360 contraction for unbounded ones). The segmentation input is the fine
//! network's final trunk activation followed by the encoded position, `256 + 63 = 319` wide,
//! so the default head is the reference's `319 → 128 → 2`.
//!
//! Ablation switches: `hierarchical = false` drops the coarse network and the importance pass
//! (the renderer then marches `train.samples_per_ray` candidates with occupancy skipping, which
//! makes the proposal redundant once the occupancy grid is baked); the occupancy grid, early
//! termination and stage-2 weight thresholding are the core's `train.occupancy`,
//! `train.early_stop` and `segment.weight_threshold`.

mod coarse_fine;
mod field;
pub(crate) mod limits;
pub mod network;

use sos_core::error::BuildError;
use sos_core::plugin::field::Hierarchical;
use sos_core::plugin::{RadianceField, RadianceFieldConfig};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;

pub(crate) use coarse_fine::network_methods;
pub use coarse_fine::{CoarseFine, Level};
pub use field::{
    mlp_gradients, mlp_parameters, normalised_coords, read_params, set_mlp_parameters, write_params, NerfField, NerfNet,
};
use limits::Limits;
pub use network::{DensityActivation, NerfMlp, NerfShape, NerfTape};

/// Declares a field config with the settings of a NeRF-style field (sampling, network sizes,
/// density activation, learning rate), each a `[field]` key, plus the config's own fields,
/// whose keys come after the sampling ones. Unknown keys are refused, and
/// `NerfConfig::from(&config)` gives the settings of one network and of the sampling.
macro_rules! nerf_settings {
    (
        $(#[$meta:meta])*
        pub struct $name:ident {
            $($(#[$own_meta:meta])* pub $own:ident: $own_ty:ty,)*
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
        #[serde(default, deny_unknown_fields)]
        pub struct $name {
            /// Coarse network + importance sampling (the reference); `false` uses the fine
            /// network alone on occupancy-skipped candidates.
            pub hierarchical: bool,
            /// Stratified samples per ray of the coarse pass.
            pub coarse_samples: usize,
            /// Importance samples per ray added for the fine pass.
            pub fine_samples: usize,
            $($(#[$own_meta])* pub $own: $own_ty,)*
            /// Positional-encoding octaves of the position.
            pub pos_frequencies: usize,
            /// Positional-encoding octaves of the view direction.
            pub dir_frequencies: usize,
            /// Trunk layers.
            pub depth: usize,
            /// Trunk width.
            pub width: usize,
            /// Trunk layer that also reads the encoded input (0 = no skip).
            pub skip: usize,
            /// Width of the view-dependent colour branch.
            pub view_width: usize,
            /// Density activation: `relu` (the reference) or `softplus`.
            pub density_activation: $crate::nerf::DensityActivation,
            /// Adam learning rate (decayed by the stage-1 schedule).
            pub lr: f32,
        }

        impl From<&$name> for $crate::nerf::NerfConfig {
            fn from(c: &$name) -> Self {
                $crate::nerf::NerfConfig {
                    hierarchical: c.hierarchical,
                    coarse_samples: c.coarse_samples,
                    fine_samples: c.fine_samples,
                    pos_frequencies: c.pos_frequencies,
                    dir_frequencies: c.dir_frequencies,
                    depth: c.depth,
                    width: c.width,
                    skip: c.skip,
                    view_width: c.view_width,
                    density_activation: c.density_activation,
                    lr: c.lr,
                }
            }
        }
    };
}

pub(crate) use nerf_settings;

nerf_settings! {
    /// Settings of the `nerf` field.
    pub struct NerfConfig {}
}

impl Default for NerfConfig {
    fn default() -> Self {
        NerfConfig {
            hierarchical: true,
            coarse_samples: 64,
            fine_samples: 128,
            pos_frequencies: 10,
            dir_frequencies: 4,
            depth: 8,
            width: 256,
            skip: 5,
            view_width: 128,
            density_activation: DensityActivation::Relu,
            lr: 5e-4,
        }
    }
}

impl NerfConfig {
    /// The network sizes this config describes.
    pub fn shape(&self) -> NerfShape {
        NerfShape {
            in_dim: 3,
            pos_frequencies: self.pos_frequencies,
            dir_frequencies: self.dir_frequencies,
            depth: self.depth,
            width: self.width,
            skip: (self.skip > 0).then_some(self.skip),
            view_width: self.view_width,
        }
    }

    /// The proposal pass this config asks for (`None` when not `hierarchical`).
    pub fn sampling(&self) -> Option<Hierarchical> {
        self.hierarchical
            .then_some(Hierarchical { coarse_samples: self.coarse_samples, fine_samples: self.fine_samples })
    }

    /// Checks the ranges the types cannot express.
    pub fn validate(&self) -> Result<(), BuildError> {
        LIMITS.check(self)
    }
}

/// Memory of `networks` networks of `shape`: weights with their gradients and Adam moments,
/// and per recorded sample every layer's activations before and after the nonlinearity.
pub(crate) fn network_memory(shape: &NerfShape, networks: u64) -> sos_core::plugin::FieldMemory {
    let (depth, width, view) = (shape.depth as u64, shape.width as u64, shape.view_width as u64);
    let input = (shape.in_dim * (1 + 2 * shape.pos_frequencies)) as u64;
    let weights = input * width + depth * width * width + width * view + 4 * (width + view);
    let activations = depth * width + view + input;
    sos_core::plugin::FieldMemory {
        parameter_bytes: networks * weights * 4 * 4,
        parameter_key: "field.width".into(),
        bytes_per_sample: networks * activations * 4 * 2,
    }
}

/// The bounds of `nerf`'s checks.
const LIMITS: Limits = Limits { kind: "nerf", max_coarse_samples: 1024 };

sos_core::plugin_kind! {
    kind: "nerf",
    summary: "the reference NeRF MLP (PE 10/4, 8x256 trunk with skip, view branch, coarse + fine networks)",
    default: || Box::new(NerfConfig::default()),
    impl RadianceFieldConfig for NerfConfig {
        fn build(&self, extent: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError> {
            self.validate()?;
            Ok(Box::new(NerfField::new(self.clone(), Contraction::new(extent), seed)))
        }

        fn memory_estimate(&self) -> Option<sos_core::plugin::FieldMemory> {
            Some(network_memory(&self.shape(), if self.hierarchical { 2 } else { 1 }))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invalid_settings_name_their_key() {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        for (cfg, key) in [
            (NerfConfig { skip: 8, ..Default::default() }, "skip"),
            (NerfConfig { coarse_samples: 1, ..Default::default() }, "coarse_samples"),
            (NerfConfig { lr: -1.0, ..Default::default() }, "lr"),
            (NerfConfig { depth: 0, skip: 0, ..Default::default() }, "depth"),
        ] {
            limits::assert_rejects(&cfg, &extent, key);
        }
        assert!(NerfConfig::default().build(&extent, 0).is_ok());
    }

    #[test]
    fn config_parses_from_toml_and_rejects_unknown_keys() {
        let cfg: NerfConfig = toml::from_str("hierarchical = false\ndensity_activation = \"softplus\"").unwrap();
        assert!(!cfg.hierarchical);
        assert_eq!(cfg.density_activation, DensityActivation::Softplus);
        assert!(toml::from_str::<NerfConfig>("widht = 3").is_err());
    }
}
