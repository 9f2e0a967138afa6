//! Dataset adapters and the synthetic scene generator of nerf-sos.
//!
//! Dataset kinds (each a [`sos_core::plugin::DatasetConfig`] registered with the registry):
//! - `synthetic`: procedural ray-traced room with one object and exact masks ([`synthetic`]);
//! - `llff`: forward-facing LLFF captures ([`llff`]);
//! - `blender`: NeRF-synthetic layout ([`blender`]).
//!
//! Supporting modules: [`npy`] (`.npy` reading/writing), [`pose`] (LLFF pose averaging,
//! recentring, spiral paths), [`export`] (writing scenes in the LLFF / Blender layouts) and
//! [`image_files`] (image and mask lookup).

#![warn(missing_docs)]

pub mod blender;
pub mod export;
pub mod image_files;
pub mod llff;
pub mod npy;
pub mod pose;
pub mod synthetic;

pub use blender::{load_blender, BlenderConfig};
pub use export::{write_blender, write_llff};
pub use llff::{load_llff, LlffConfig};
pub use synthetic::{generate, Rig, SyntheticConfig};
