//! Dataset adapters and the synthetic scene generator of nerf-sos.
//!
//! Dataset kinds (each a [`sos_core::plugin::DatasetConfig`] registered with the registry):
//! - `synthetic`: procedural ray-traced room with one object and exact masks ([`synthetic`]);
//! - `llff`: forward-facing LLFF captures ([`llff`]);
//! - `blender`: NeRF-synthetic layout ([`blender`]);
//! - `colmap`: COLMAP sparse models, binary or text ([`colmap`]);
//! - `blendedmvs`: BlendedMVS, original or NSVF layout ([`blendedmvs`]);
//! - `co3d`: one CO3Dv2 sequence ([`co3d`]);
//! - `tanks-temples`: Tanks and Temples in NeRF++'s layout ([`tanks_temples`]).
//!
//! Supporting modules: [`adapter`] (registration, hold-out split and scene assembly shared by
//! the adapters), [`npy`] (`.npy` reading/writing), [`pose`] (pose algebra, LLFF
//! recentring, spherify and spirals, convention conversions), [`export`] (writing scenes in
//! every layout), [`layouts`] (write and reopen one scene in each layout), [`text`] (camera
//! and annotation files), [`views`] (checked cameras, images and masks), [`image_files`]
//! (image and mask lookup), [`colmap_points`] (COLMAP's sparse points) and [`forward_facing`]
//! (forward-facing captures read from layouts without an NDC frame).

#![warn(missing_docs)]

pub mod adapter;
pub mod blendedmvs;
pub mod blender;
pub mod co3d;
pub mod colmap;
pub mod colmap_points;
pub mod export;
pub mod forward_facing;
pub mod image_files;
pub mod layouts;
pub mod llff;
pub mod npy;
pub mod pose;
pub mod synthetic;
pub mod tanks_temples;
pub mod text;
pub mod views;

pub use blendedmvs::{load_blendedmvs, BlendedMvsConfig};
pub use blender::{load_blender, BlenderConfig};
pub use co3d::{load_co3d, Co3dConfig};
pub use colmap::{load_colmap, ColmapConfig};
pub use export::{
    write_blendedmvs, write_blender, write_co3d, write_colmap, write_llff, write_nsvf, write_tanks_temples,
};
pub use layouts::Format;
pub use llff::{load_llff, LlffConfig};
pub use synthetic::{generate, Rig, SyntheticConfig};
pub use tanks_temples::{load_tanks_temples, TanksTemplesConfig};
