//! Helpers shared by tests: reading the reference fixtures.

pub mod fixture;
