//! `sos`: the nerf-sos command line. Every command lives in the `sos` library, so a plugin
//! crate outside this workspace gets the same binary by linking its plugins and calling
//! [`sos::run`].

/// An allocator that keeps freed pages for the next training step (see `sos::allocator`).
#[global_allocator]
static ALLOCATOR: sos::allocator::MiMalloc = sos::allocator::MiMalloc;

fn main() -> std::process::ExitCode {
    sos::run()
}
