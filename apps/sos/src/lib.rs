//! The nerf-sos command line as a library: [`run`] parses the arguments and runs any command
//! (`train`, `segment`, `render`, `export`, `eval`, `compare`, `bench`, `list`, `init`) with every
//! plugin linked into the calling program. Every failure prints the chain of causes (file,
//! key, what to do) and exits with code 2.

/// `println!` for a command's output: when standard output cannot be written (a full disk, a
/// closed file) it returns an error naming standard output instead of panicking; a reader that
/// stopped early (`| head`) is not an error.
macro_rules! say {
    () => {
        $crate::commands::write_stdout("\n")
    };
    ($($arg:tt)*) => {
        $crate::commands::write_stdout(&format!("{}\n", format_args!($($arg)*)))
    };
}

pub mod allocator;
pub mod bench;
mod cli;
pub mod commands;
pub mod console;

pub use cli::run;

// Force-link every plugin crate of the workspace so their registrations are present.
use sos_plugins as _;
