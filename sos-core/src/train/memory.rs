//! Keeping freed memory in the process. A training step allocates and frees the same large
//! buffers (network tapes, per-block activations) every step. glibc's allocator serves blocks
//! above its mmap threshold with fresh mappings and gives freed heap tops back to the kernel,
//! so every step would fault those pages in again and zero them: measured on the `nerf`
//! stage-1 step, that doubled its forward time. Raising the thresholds once per process keeps
//! the memory for reuse; peak memory is unchanged.

/// Largest mmap threshold glibc accepts (`HEAP_MAX_SIZE / 2` on 64-bit targets).
const MMAP_THRESHOLD: i32 = 32 << 20;

/// Tunes the allocator once per process (glibc only; a no-op elsewhere). Idempotent.
pub fn keep_freed_memory() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(tune);
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn tune() {
    // SAFETY: `mallopt` only adjusts allocator parameters; it is called once, before the
    // training threads allocate, with values glibc documents as valid.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn tune() {
    let _ = MMAP_THRESHOLD;
}
