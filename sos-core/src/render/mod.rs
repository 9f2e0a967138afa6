//! Ray sampling, empty-space skipping and volume compositing.

pub mod composite;
pub mod contraction;
pub mod occupancy;
pub mod rays;
pub mod renderer;
pub mod sampler;
