//! Random worlds (`world = "random"`): a seeded family of synthetic scenes nobody tuned for.
//! The seed draws the rig (for `rig = "random"`), the foreground composite, the cameras, the
//! room or open world around them, the materials, the distractors and the light; see the
//! [`super`] module documentation for the ranges.

mod blueprint;
mod composition;
mod distractors;
mod draw;
mod environment;
mod framing;
mod palette;
mod rigs;
mod scene;
mod world;

pub use blueprint::draw as blueprint;
pub use scene::generate;

#[cfg(test)]
mod tests;
