//! Dataset adapters and the synthetic scene generator of nerf-sos.
//!
//! Kinds: `synthetic` (procedural room, [`synthetic`]).

pub mod pose;
pub mod synthetic;

pub use synthetic::{generate, SyntheticConfig};
