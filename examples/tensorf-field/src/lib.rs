//! An example plugin crate: a new radiance-field kind, `tensorf`, written outside the main
//! crates, whose forward and backward passes are expressed with the
//! [dfdx](https://docs.rs/dfdx/0.13) autodiff library instead of hand-written gradients.
//!
//! The field is TensoRF's vector-matrix (VM) decomposition (Chen et al., ECCV 2022). The
//! scene's unit cube (the [`Contraction`] of its
//! extent) is factorised into three axis-aligned planes, each paired with a line along the
//! remaining axis:
//! - density: `σ = softplus(Σ_pairs Σ_r P_r(u_a, u_b) · L_r(u_c) + shift) / cell`;
//! - appearance: the same products with their own components, mapped by a basis matrix to a
//!   feature vector, then a small MLP on the feature and the encoded view direction gives the
//!   colour.
//!
//! Interpolation (bilinear on the planes, linear on the lines) is a `gather` of corner rows
//! times constant weights, so dfdx differentiates it as it does everything else; the
//! `backward` of the [`RadianceField`] trait re-runs the
//! forward pass on a dfdx tape and back-propagates `Σ σ·∂L/∂σ + Σ c·∂L/∂c`.
//!
//! Linking this crate registers the kind: `use sos_example_tensorf as _;`.

mod adam;
mod config;
mod field;
mod graph;
mod layout;
mod resample;
mod samples;
mod state;

use sos_core::error::BuildError;
use sos_core::plugin::{RadianceField, RadianceFieldConfig};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;

pub use config::TensorfConfig;
pub use field::TensorfField;

/// The `kind = "..."` name of the field, for error messages before the macro's constant exists.
const KIND: &str = "tensorf";

sos_core::plugin_kind! {
    kind: "tensorf",
    summary: "TensoRF vector-matrix planes and lines + colour MLP, gradients by dfdx autodiff (example plugin crate)",
    default: || Box::new(TensorfConfig::default()),
    impl RadianceFieldConfig for TensorfConfig {
        fn build(&self, extent: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError> {
            self.validate()?;
            Ok(Box::new(TensorfField::new(self.clone(), Contraction::new(extent), extent, seed)))
        }
    }
}
