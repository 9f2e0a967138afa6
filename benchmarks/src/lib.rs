//! Shared setup of the speed benchmarks (`cargo bench -p sos-benchmarks`, in `benches/`): the
//! allocator and thread pool `sos` runs with, criterion's settings, and the reading back of what
//! criterion measured so that a benchmark can print the ratios of the functions it compares.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use criterion::Criterion;

/// The same allocator as the `sos` binary, so benchmarks time what users run.
#[global_allocator]
static ALLOCATOR: sos::allocator::MiMalloc = sos::allocator::MiMalloc;

/// Rayon threads of the timing runs: `RAYON_NUM_THREADS`, or 2 (the project machine's cores)
/// when it is unset or not a number. 0 lets rayon choose, as rayon itself does.
pub fn threads() -> usize {
    threads_from(std::env::var("RAYON_NUM_THREADS").ok().as_deref())
}

fn threads_from(value: Option<&str>) -> usize {
    value.and_then(|s| s.trim().parse().ok()).unwrap_or(2)
}

/// Prepares a timing process as `sos` runs: the allocator keeps freed memory and the global
/// rayon pool gets [`threads`] threads. Call it first (it also links this crate, and with it the
/// allocator above); later calls change nothing. Returns the pool's thread count.
pub fn setup() -> usize {
    sos::allocator::keep_freed_memory();
    // Only the first call builds the global pool; later ones find it built.
    let _ = rayon::ThreadPoolBuilder::new().num_threads(threads()).build_global();
    rayon::current_num_threads()
}

/// Criterion's folder for its results: `CRITERION_HOME`, else `criterion/` in the Cargo target
/// folder of the running benchmark (`target/<profile>/deps/<bench>` → `target/criterion`).
pub fn criterion_dir() -> PathBuf {
    if let Some(home) = std::env::var_os("CRITERION_HOME") {
        return PathBuf::from(home);
    }
    std::env::current_exe()
        .ok()
        .and_then(|exe| Some(exe.parent()?.parent()?.parent()?.join("criterion")))
        .unwrap_or_else(|| PathBuf::from("target/criterion"))
}

/// Criterion with a benchmark's defaults, for `criterion_group!`'s `config`: results in
/// [`criterion_dir`], `samples` samples over `measurement_s` seconds after `warm_up_s` seconds
/// of warm-up. The command line (`--sample-size`, `--warm-up-time`, `--measurement-time`, a
/// name filter), which `criterion_group!` reads after this, overrides them.
pub fn criterion(samples: usize, warm_up_s: f64, measurement_s: f64) -> Criterion {
    Criterion::default()
        .output_directory(&criterion_dir())
        .sample_size(samples)
        .warm_up_time(Duration::from_secs_f64(warm_up_s))
        .measurement_time(Duration::from_secs_f64(measurement_s))
}

/// What criterion measured for the benchmarks of one group in this process, read back from its
/// `estimates.json` files once the group has finished, to print the ratios of the compared
/// functions.
pub struct GroupResults {
    dir: PathBuf,
    /// Whole seconds since the epoch when the group started: results older than this are a
    /// previous run's.
    started_s: u64,
}

impl GroupResults {
    /// Watches group `group` (create it before the group's benchmarks run).
    pub fn new(group: &str) -> Self {
        Self::in_dir(&criterion_dir(), group)
    }

    fn in_dir(dir: &Path, group: &str) -> Self {
        Self { dir: dir.join(group), started_s: epoch_seconds(SystemTime::now()) }
    }

    /// Median seconds per iteration of benchmark `function` of the group, as criterion
    /// measured it in this process; `None` where it did not run now (filtered out, `--test`,
    /// `--list`) or left no readable estimate.
    pub fn median(&self, function: &str) -> Option<f64> {
        let path = self.dir.join(function).join("new").join("estimates.json");
        let modified = std::fs::metadata(&path).and_then(|m| m.modified()).ok()?;
        // A second's slack: file times come from the kernel's coarse clock, which may lag the
        // clock the group read when it started, across a second's boundary.
        if epoch_seconds(modified) + 1 < self.started_s {
            return None;
        }
        let estimates: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).ok()?).ok()?;
        // Criterion's wall-clock measurement is in nanoseconds.
        Some(estimates["median"]["point_estimate"].as_f64()? * 1e-9)
    }
}

fn epoch_seconds(t: SystemTime) -> u64 {
    t.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs())
}

/// The median of `values` (NaN when empty).
pub fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
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

    #[test]
    fn threads_default_to_two() {
        assert_eq!(threads_from(None), 2);
        assert_eq!(threads_from(Some("x")), 2);
        assert_eq!(threads_from(Some(" 4 ")), 4);
        assert_eq!(threads_from(Some("0")), 0);
    }

    #[test]
    fn reads_this_runs_median_only() {
        let dir = std::env::temp_dir().join(format!("sos-benchmarks-results-{}", std::process::id()));
        let results = GroupResults::in_dir(&dir, "group");
        assert_eq!(results.median("f"), None);
        let new = dir.join("group/f/new");
        std::fs::create_dir_all(&new).unwrap();
        std::fs::write(new.join("estimates.json"), r#"{"median":{"point_estimate":2.5e6}}"#).unwrap();
        let got = results.median("f").unwrap();
        assert!((got - 2.5e-3).abs() < 1e-12, "{got}");
        // The same file seen by a group that started after it was written is a previous run's.
        let later = GroupResults { started_s: results.started_s + 10, ..GroupResults::in_dir(&dir, "group") };
        assert_eq!(later.median("f"), None);
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert!(median(&[]).is_nan());
    }
}
