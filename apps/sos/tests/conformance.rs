//! The conformance suite over every kind linked into `sos`, of every role: no list to edit,
//! a new plugin is checked as soon as it is linked.

use sos_plugins as _;

#[test]
fn every_linked_kind_of_every_role_conforms() {
    sos_core::testing::conformance::check_all();
}
