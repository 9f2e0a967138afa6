//! `nerf++`: NeRF++ for unbounded scenes. The scene's foreground sphere (`SceneExtent::
//! Unbounded`: centre `c`, radius `R`, chosen by the dataset so that every camera lies inside)
//! is normalised to the unit sphere, `x = (p − c) / R`. A foreground NeRF MLP models `|x| ≤ 1`;
//! outside, a background NeRF MLP sees the inverted-sphere parametrisation
//! `(x / r, 1 / r)` with `r = |x|` (a bounded 4-D input however far the point), encoded with
//! the same positional encoding.
//!
//! Compositing follows NeRF++: every ray's samples inside the sphere come first, then those
//! outside, in one front-to-back pass, so the background's contribution is weighted by the
//! foreground's transmittance, `C = C_fg + T_fg · C_bg`. The renderer spaces candidates
//! uniformly in distance inside the sphere and uniformly in inverse distance outside (the
//! extent's `SphereThenDisparity` spacing). Densities are returned in world units: the
//! foreground's network density is per unit of `x` (`σ = σ_net / R`), the background's per
//! unit of `1 / r` (`σ = σ_net / (R r²)`, exact for rays leaving radially, as they do far
//! out), so equal network outputs mean equal opacity per step of the inverted sphere.
//!
//! For bounded and forward-facing scenes there is no background region: the field is a
//! single (foreground) NeRF on the scene's unit-cube mapping, like `nerf`, and no background
//! network is built (`background = "auto"`); `"off"` drops it for unbounded scenes too (an
//! ablation: nothing beyond the sphere).
//!
//! The segmentation input is the fine level's final trunk activation (foreground or
//! background network) followed by the encoded mip-NeRF 360 contraction of `x`
//! (`x` inside the sphere, `(2 − 1/r) x / r` outside), continuous across the sphere.

mod field;

use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{RadianceField, RadianceFieldConfig};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;

use crate::nerf::limits::Limits;
use crate::nerf::{nerf_settings, DensityActivation, NerfConfig, NerfShape};
pub use field::{NerfPpField, NerfPpNet, Space};

/// Whether the background network exists.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Background {
    /// Only for unbounded scenes.
    Auto,
    /// Never (everything beyond the unit sphere is empty).
    Off,
}

nerf_settings! {
    /// Settings of the `nerf++` field. The network settings apply to the foreground and the
    /// background network alike (NeRF++ uses `skip = 4`), and the coarse pass's stratified
    /// samples lie half inside the sphere, half outside.
    pub struct NerfPpConfig {
        /// Background network: `auto` (unbounded scenes only) or `off`.
        pub background: Background,
    }
}

impl Default for NerfPpConfig {
    fn default() -> Self {
        NerfPpConfig {
            hierarchical: true,
            coarse_samples: 128,
            fine_samples: 256,
            background: Background::Auto,
            pos_frequencies: 10,
            dir_frequencies: 4,
            depth: 8,
            width: 256,
            skip: 4,
            view_width: 128,
            density_activation: DensityActivation::Relu,
            lr: 5e-4,
        }
    }
}

impl NerfPpConfig {
    /// The network sizes for inputs of `in_dim` coordinates.
    pub fn shape(&self, in_dim: usize) -> NerfShape {
        NerfShape { in_dim, ..NerfConfig::from(self).shape() }
    }

    /// Checks the ranges the types cannot express.
    pub fn validate(&self) -> Result<(), BuildError> {
        LIMITS.check(&self.into())
    }
}

/// The bounds of `nerf++`'s checks.
const LIMITS: Limits = Limits { kind: "nerf++", max_coarse_samples: 2048 };

sos_core::plugin_kind! {
    kind: "nerf++",
    summary: "NeRF++: foreground NeRF in the unit sphere + inverted-sphere background NeRF, for unbounded scenes",
    default: || Box::new(NerfPpConfig::default()),
    impl RadianceFieldConfig for NerfPpConfig {
        fn build(&self, extent: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError> {
            self.validate()?;
            let space = match *extent {
                SceneExtent::Unbounded { center, radius } => {
                    if !(radius > 0.0 && radius.is_finite()) {
                        return Err(LIMITS.invalid("scene", "the scene's foreground sphere needs a positive radius"));
                    }
                    Space::Sphere { center, radius, background: self.background == Background::Auto }
                }
                _ => Space::Cube(Contraction::new(extent)),
            };
            Ok(Box::new(NerfPpField::new(self.clone(), space, seed)))
        }

        fn memory_estimate(&self) -> Option<sos_core::plugin::FieldMemory> {
            // Foreground and background, each with a coarse and a fine network.
            let nerf = crate::nerf::NerfConfig::from(self);
            Some(crate::nerf::network_memory(&nerf.shape(), 4))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invalid_settings_name_their_key() {
        let extent = SceneExtent::Unbounded { center: [0.0; 3], radius: 2.0 };
        for (cfg, key) in [
            (NerfPpConfig { skip: 8, ..Default::default() }, "skip"),
            (NerfPpConfig { coarse_samples: 0, ..Default::default() }, "coarse_samples"),
            (NerfPpConfig { width: 0, ..Default::default() }, "width"),
        ] {
            crate::nerf::limits::assert_rejects(&cfg, &extent, key);
        }
        let bad_sphere = SceneExtent::Unbounded { center: [0.0; 3], radius: 0.0 };
        assert!(NerfPpConfig::default().build(&bad_sphere, 0).is_err());
        let cfg: NerfPpConfig = toml::from_str("background = \"off\"\nwidth = 64").unwrap();
        assert_eq!(cfg.background, Background::Off);
        assert!(toml::from_str::<NerfPpConfig>("backgroud = \"off\"").is_err());
    }
}
