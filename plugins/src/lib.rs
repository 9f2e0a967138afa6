//! Radiance-field plugins of nerf-sos. Linking this crate links every plugin of the workspace
//! (fields, datasets, extractors, miners, losses), so binaries only need `use sos_plugins as _;`.

pub mod nerf;
pub mod nerf_pp;
pub mod voxel_grid;

pub use sos_backbones as backbones;
pub use sos_datasets as datasets;
pub use sos_losses as losses;
