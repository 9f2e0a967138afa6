//! The nerf-sos command line as a library: [`run`] parses the arguments and runs any command
//! (`train`, `segment`, `render`, `export`, `eval`, `compare`, `bench`, `list`, `init`) with every
//! plugin linked into the calling program. Every failure prints the chain of causes (file,
//! key, what to do) and exits with code 2.

pub mod allocator;
pub mod bench;
mod cli;
pub mod commands;
pub mod console;

pub use cli::run;

// Force-link every plugin crate of the workspace so their registrations are present.
use sos_plugins as _;
