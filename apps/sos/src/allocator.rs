//! Keeping freed memory in the process. A training step allocates and frees the same large
//! buffers (network tapes, per-block activations, sample positions and weights: hundreds of MB)
//! every step. An allocator that gives freed blocks back to the kernel makes every step fault
//! those pages in again and zero them: measured on the `nerf` stage-1 step that doubled its
//! forward time, and in stage 2 it was a third of the run in system time on the 2-core machine.
//!
//! The allocator is the program's choice, not the library's: `sos-core` never touches it. The
//! binaries install mimalloc ([`MiMalloc`]) and [`crate::run`] calls [`keep_freed_memory`]
//! first, which turns its purging off; where the system allocator serves the process (a program
//! that embeds the library without installing mimalloc) the same call raises glibc's
//! thresholds instead. Peak memory is unchanged either way; memory is only not returned before
//! the process ends.

/// The global allocator the `sos` and benchmark binaries install (`#[global_allocator]`).
pub use mimalloc::MiMalloc;

/// Largest mmap threshold glibc accepts (`HEAP_MAX_SIZE / 2` on 64-bit targets).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: i32 = 32 << 20;

/// mimalloc's `mi_option_purge_delay`: its position in `mi_option_t` (the same in the bundled
/// v2 and v3), which `libmimalloc-sys` does not name (checked by the test below).
const MIMALLOC_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Tunes whichever allocator serves the process to keep freed memory. Idempotent; call it
/// before the first large allocation (first thing in `main`).
pub fn keep_freed_memory() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        keep_mimalloc_pages();
        tune_glibc();
    });
}

#[allow(unsafe_code)]
fn keep_mimalloc_pages() {
    // SAFETY: `mi_option_set` only stores an integer in mimalloc's option table; -1 means
    // "never purge" and the index is in range for the bundled mimalloc.
    unsafe { libmimalloc_sys::mi_option_set(MIMALLOC_PURGE_DELAY, -1) }
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn tune_glibc() {
    // SAFETY: `mallopt` only adjusts allocator parameters, with values glibc documents as valid.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn tune_glibc() {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[allow(unsafe_code)]
    fn the_mimalloc_option_set_is_the_purge_delay() {
        // SAFETY (both): reading mimalloc's option table.
        keep_freed_memory();
        assert_eq!(unsafe { libmimalloc_sys::mi_option_get(MIMALLOC_PURGE_DELAY) }, -1);
        // The neighbouring option (NUMA nodes) keeps its default.
        assert_eq!(unsafe { libmimalloc_sys::mi_option_get(MIMALLOC_PURGE_DELAY + 1) }, 0);
    }
}
