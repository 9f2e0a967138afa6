//! `sos`: the nerf-sos command line.
fn main() {}
