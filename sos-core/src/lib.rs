//! nerf-sos core: cameras and scenes, the plugin roles and their registry, rendering kernels
//! (sampling, occupancy, compositing), dense layers, the segmentation head, training, k-means
//! and metrics.

pub mod camera;
pub mod config;
pub mod derived;
pub mod encoding;
pub mod error;
pub mod image;
pub mod kmeans;
pub mod metrics;
pub mod nn;
pub mod plugin;
pub mod registry;

// Re-exported for `plugin_kind!`, so that plugin crates need not name inventory themselves.
#[doc(hidden)]
pub use inventory;
pub mod render;
pub mod scene;
pub mod segment;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod train;
