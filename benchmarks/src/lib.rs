//! Shared helpers for the benchmark binaries.

/// The same allocator as the `sos` binary, so benchmarks time what users run.
#[global_allocator]
static ALLOCATOR: sos::allocator::MiMalloc = sos::allocator::MiMalloc;

/// Tunes the allocator as `sos` does (call first in a timing binary's `main`; calling it also
/// links this crate, and with it the allocator above).
pub fn allocate_like_sos() {
    sos::allocator::keep_freed_memory();
}

/// CPU seconds (user + system, all threads) this process has used so far, from
/// `/proc/self/stat` (Linux; `None` elsewhere). Unlike wall-clock time it does not count
/// time the cores spend on other processes, but it does count idle spinning of thread pools,
/// which grows when the machine is shared.
pub fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // /proc reports in USER_HZ clock ticks, 100 per second on Linux.
    Some((utime + stime) / 100.0)
}

/// The 1-minute load average (Linux), to print beside timings.
pub fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg").ok()?.split_whitespace().next()?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_grows_with_work() {
        let Some(before) = process_cpu_seconds() else { return };
        let mut x = 0u64;
        let start = std::time::Instant::now();
        while start.elapsed().as_millis() < 300 {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
        }
        std::hint::black_box(x);
        let after = process_cpu_seconds().unwrap();
        assert!(after >= before && after - before < 10.0, "{before} -> {after}");
        assert!(load_average().is_some_and(|l| l >= 0.0));
    }
}
