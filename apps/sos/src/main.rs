//! `sos`: the nerf-sos command line. Every command lives in the `sos` library, so a plugin
//! crate outside this workspace gets the same binary by linking its plugins and calling
//! [`sos::run`].

/// An allocator that keeps freed pages for the next training step (see `train::memory`).
#[global_allocator]
static ALLOCATOR: sos_core::train::memory::MiMalloc = sos_core::train::memory::MiMalloc;

fn main() -> std::process::ExitCode {
    sos::run()
}
