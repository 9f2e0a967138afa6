//! `sos-tensorf`: the `sos` command line with the `tensorf` field linked in.

use sos_example_tensorf as _; // registers `[field] kind = "tensorf"`
use sos_plugins as _; // the built-in scenes, fields, teachers, miners and losses

/// The allocator of the `sos` binary: it keeps freed pages for the next step's tensors.
#[global_allocator]
static ALLOCATOR: sos::allocator::MiMalloc = sos::allocator::MiMalloc;

fn main() -> std::process::ExitCode {
    sos::run()
}
