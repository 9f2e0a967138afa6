//! Helpers for tests, behind the `testing` feature: the conformance suite every plugin must
//! pass, reading the reference fixtures, blank scenes.

pub mod conformance;
pub mod fixture;
pub mod scene;
