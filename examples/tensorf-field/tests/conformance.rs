//! The core's conformance suite on the `tensorf` kind: shapes, gradients against finite
//! differences, determinism, growth, saved states, and a few steps of both stages.

use sos_example_tensorf as _; // registers `tensorf`
use sos_plugins as _; // the built-in scene, teacher, miner and losses of the two-stage run

#[test]
fn tensorf_conforms() {
    sos_core::testing::conformance::check_field_kind("tensorf");
}
