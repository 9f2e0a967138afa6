//! Ray sampling, empty-space skipping and volume compositing.

pub mod composite;
pub mod contraction;
pub mod density_pass;
pub mod distortion;
pub mod memory_budget;
pub mod occupancy;
pub mod rays;
pub mod renderer;
pub mod sampler;
