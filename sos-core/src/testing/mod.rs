//! Helpers shared by tests: reading the reference fixtures, blank scenes.

pub mod fixture;
pub mod scene;
