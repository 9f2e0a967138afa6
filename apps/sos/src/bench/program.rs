//! A run of another `sos` build (a method with `program` and `config`): its own `sos train` on
//! its own config, timed and read back from the `metrics.json` it writes, so that one report
//! sets builds side by side (e.g. a release against the commit an optimisation started from).
//!
//! With `stage1_of` it instead runs its `sos segment --checkpoint` on the stage-1 checkpoint of
//! this build's run of that method, handed over in the format without a checksum that every
//! build reads: both builds' stage 2 on one field.
//!
//! Such a run has no learning curves and no timed view: an older build cannot sample them. Its
//! stage times are the ones it wrote; its peak memory and CPU time come from the kernel's
//! accounting of the child process.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context};
use serde_json::Value as Json;

use sos_core::train::checkpoint::save_unchecked_copy;

use super::matrix::{hash_text, PlannedRun};
use super::record::{cpu_ticks, stolen_between, Metrics, Outcome, RunRecord, Timing};
use super::runner::CHECKPOINT;

/// What the kernel accounted for a finished child process.
struct ChildUsage {
    /// Exit code, or `None` when a signal ended it.
    code: Option<i32>,
    /// Peak resident memory, MiB.
    peak_rss_mib: f64,
    /// User + system CPU seconds.
    cpu_seconds: f64,
}

/// Runs `run` with `program train <config>` in `work/<id>` (or, with `stage1_of`,
/// `program segment <config> --checkpoint` on `source`'s checkpoint) and returns what it
/// measured.
pub fn execute(
    run: &PlannedRun,
    program: &Path,
    work: &Path,
    log_path: &Path,
    source: Option<&RunRecord>,
) -> anyhow::Result<Outcome> {
    let run_dir = work.join(&run.key.id);
    let handed_over = match &run.stage1_of {
        Some(id) => {
            let source = source.with_context(|| {
                format!("it starts from the stage 1 of `{id}`, which did not finish in this run of the matrix")
            })?;
            let checkpoint = work.join(&source.key.id).join(CHECKPOINT);
            let copy = work.join(format!("{}.stage1.bin", run.key.id));
            save_unchecked_copy(&checkpoint, &copy).with_context(|| {
                format!(
                    "handing the stage 1 of `{id}` over (its folder {} must hold its checkpoint)",
                    checkpoint.display()
                )
            })?;
            Some((source, copy))
        }
        None => None,
    };
    // The config stays beside its original so that its relative paths (data, weights) resolve.
    let config_path = run.config_dir.join(format!(".sos-bench-{}.toml", &hash_text(&run.key.id)[..12]));
    std::fs::write(&config_path, super::runner::run_config_text(run, work)?)
        .with_context(|| format!("writing {} (is the program's config folder writable?)", config_path.display()))?;
    let log = std::fs::File::create(log_path).with_context(|| format!("creating {}", log_path.display()))?;
    let ticks = cpu_ticks();
    let started = Instant::now();
    let mut command = Command::new(program);
    match &handed_over {
        Some((_, copy)) => command.arg("segment").arg(&config_path).arg("--checkpoint").arg(copy),
        None => command.arg("train").arg(&config_path),
    };
    let child = command
        .stdin(Stdio::null())
        .stdout(log.try_clone()?)
        .stderr(log)
        .spawn()
        .with_context(|| format!("starting {}", program.display()));
    let usage = child.and_then(wait_with_usage);
    let wall = started.elapsed().as_secs_f64();
    let _ = std::fs::remove_file(&config_path);
    if let Some((_, copy)) = &handed_over {
        let _ = std::fs::remove_file(copy);
    }
    let usage = usage?;
    if usage.code != Some(0) {
        let how = usage.code.map_or_else(|| "was killed by a signal".to_string(), |c| format!("exited with code {c}"));
        bail!("{} {how} (log: {})", program.display(), log_path.display());
    }
    let metrics_path = run_dir.join("metrics.json");
    let text = std::fs::read_to_string(&metrics_path)
        .with_context(|| format!("reading {}: the program wrote no metrics", metrics_path.display()))?;
    let written: Json =
        serde_json::from_str(&text).with_context(|| format!("{} is not JSON", metrics_path.display()))?;
    let mut outcome = outcome_from_metrics(&written, wall);
    outcome.peak_rss_mib = Some(usage.peak_rss_mib);
    outcome.cpu_seconds = Some(usage.cpu_seconds);
    outcome.cpu_stolen = ticks.zip(cpu_ticks()).and_then(|(a, b)| stolen_between(a, b));
    match handed_over {
        Some((source, _)) => {
            take_stage1(&mut outcome, source);
            outcome.notes.push(format!(
                "stage 2 by another build, {} (its own `sos segment` on its own config, from the stage-1 \
                 checkpoint of `{}`, whose stage-1 time it counts): no learning curves or timed view",
                program.display(),
                source.key.id
            ));
        }
        None => outcome.notes.push(format!(
            "run by another build, {} (its own `sos train` on its own config): no learning curves or timed view",
            program.display()
        )),
    }
    Ok(outcome)
}

/// Counts the stage 1 a run started from as its own (its time, in the total too, and its
/// summary), as a run of this build that shares a stage 1 does.
fn take_stage1(outcome: &mut Outcome, source: &RunRecord) {
    let Some(o) = &source.outcome else { return };
    outcome.timing.total += o.timing.stage1 - outcome.timing.stage1;
    outcome.timing.stage1 = o.timing.stage1;
    outcome.stage1 = o.stage1.clone();
    // As for a run of this build that shares a stage 1: its peak is at least the stage-1
    // run's, and its CPU time, covering only its own process, makes no share of the total.
    outcome.peak_rss_mib = match (outcome.peak_rss_mib, o.peak_rss_mib) {
        (Some(own), Some(stage1)) => Some(own.max(stage1)),
        (own, stage1) => own.or(stage1),
    };
    outcome.cpu_seconds = None;
}

/// Waits for `child` and reads its resource usage (`wait4`, which reaps it: the only call that
/// gives one child's own peak memory; std's `Child::wait` drops it).
#[allow(unsafe_code)]
fn wait_with_usage(child: std::process::Child) -> anyhow::Result<ChildUsage> {
    let pid = child.id();
    let mut status: libc::c_int = 0;
    // SAFETY: `rusage` is plain data the kernel fills; `status` is a valid out-pointer.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: waits for our own child; both pointers are valid for the call.
        let r = unsafe { libc::wait4(pid as libc::pid_t, &mut status, 0, &mut usage) };
        if r == pid as libc::pid_t {
            break;
        }
        let e = std::io::Error::last_os_error();
        if e.kind() != std::io::ErrorKind::Interrupted {
            return Err(e).context("waiting for the program");
        }
    }
    let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    Ok(ChildUsage {
        code: libc::WIFEXITED(status).then(|| libc::WEXITSTATUS(status)),
        // Linux reports `ru_maxrss` in KiB.
        peak_rss_mib: usage.ru_maxrss as f64 / 1024.0,
        cpu_seconds: seconds(usage.ru_utime) + seconds(usage.ru_stime),
    })
}

/// The outcome `sos train`'s `metrics.json` describes: held-out colour under `test`, masks
/// under `stage2.test.segmentation`, phase times under `timing` (the program's total when it
/// wrote one, else the measured wall time). `sos segment` of older builds writes colour under
/// `stage2.test.image` and its times as `stage2.train_seconds`, `stage2.masks_seconds` and
/// `segment_seconds`, read where the first are absent. A value that is missing or not finite
/// is left out, with a note.
fn outcome_from_metrics(m: &Json, wall: f64) -> Outcome {
    let mut notes = Vec::new();
    let at = |path: &[&str]| path.iter().try_fold(m, |v, k| v.get(k)).and_then(Json::as_f64);
    let number = |path: &[&str]| {
        let fallback: &[&str] = match path {
            ["test", "psnr"] => &["stage2", "test", "image", "psnr_of_mean_mse"],
            ["test", "ssim"] => &["stage2", "test", "image", "mean_ssim"],
            ["timing", "stage2_seconds"] => &["stage2", "train_seconds"],
            ["timing", "masks_seconds"] => &["stage2", "masks_seconds"],
            ["timing", "total_seconds"] => &["segment_seconds"],
            _ => &[],
        };
        at(path).or_else(|| at(fallback))
    };
    let mut metric = |name: &str, path: &[&str]| match number(path) {
        Some(v) if v.is_finite() => Some(v),
        Some(v) => {
            notes.push(format!("{name} was {v}; left out"));
            None
        }
        None => None,
    };
    let seg = |key: &'static str| ["stage2", "test", "segmentation", key];
    let metrics = Metrics {
        psnr: metric("PSNR", &["test", "psnr"]),
        ssim: metric("SSIM", &["test", "ssim"]),
        nv_ari: metric("NV-ARI", &seg("mean_ari")),
        iou_fg: metric("IoU FG", &seg("iou_fg")),
        iou_bg: metric("IoU BG", &seg("iou_bg")),
        miou: metric("mIoU", &seg("miou")),
        depth_error: metric("depth error", &["stage2", "test", "depth_error"]),
        object_depth_error: metric("object depth error", &["stage2", "test", "object_depth_error"]),
    };
    let phase = |key: &str| number(&["timing", key]).filter(|v| v.is_finite() && *v >= 0.0).unwrap_or(0.0);
    let (stage1, stage2, masks) = (phase("stage1_seconds"), phase("stage2_seconds"), phase("masks_seconds"));
    let total = number(&["timing", "total_seconds"]).filter(|v| v.is_finite() && *v > 0.0).unwrap_or(wall);
    let timing =
        Timing { setup: (total - stage1 - stage2 - masks).max(0.0), stage1, stage2, masks, curve_eval: 0.0, total };
    let stage2_steps = number(&["stage2", "steps"]).filter(|s| *s > 0.0).map(|s| s as usize);
    Outcome { metrics, timing, notes, stage2_steps, ..Default::default() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_and_times_are_read_where_sos_train_writes_them() {
        let m: Json = serde_json::json!({
            "test": { "psnr": 27.5, "ssim": 0.9 },
            "stage2": { "steps": 100, "test": { "segmentation": { "mean_ari": 0.96, "iou_fg": 0.95, "iou_bg": 0.99, "miou": 0.97 } } },
            "timing": { "stage1_seconds": 120.0, "stage2_seconds": 100.0, "masks_seconds": 10.0, "total_seconds": 235.0 }
        });
        let o = outcome_from_metrics(&m, 240.0);
        assert_eq!(o.metrics.miou, Some(0.97));
        assert_eq!(o.metrics.nv_ari, Some(0.96));
        assert_eq!(o.metrics.psnr, Some(27.5));
        assert_eq!(o.timing.total, 235.0);
        assert_eq!(o.timing.setup, 5.0);
        assert_eq!(o.stage2_steps, Some(100));
        assert!(o.notes.is_empty());
    }

    #[test]
    fn an_older_builds_segment_metrics_are_read_where_it_writes_them() {
        let m: Json = serde_json::json!({
            "segment_seconds": 2680.9,
            "stage2": {
                "steps": 100, "train_seconds": 2548.6, "masks_seconds": 121.3,
                "test": { "image": { "psnr_of_mean_mse": 22.54, "mean_ssim": 0.72 },
                          "segmentation": { "mean_ari": 0.93, "iou_fg": 0.92, "iou_bg": 0.98, "miou": 0.95 } }
            }
        });
        let o = outcome_from_metrics(&m, 2700.0);
        assert_eq!((o.metrics.psnr, o.metrics.ssim, o.metrics.miou), (Some(22.54), Some(0.72), Some(0.95)));
        assert_eq!((o.timing.stage1, o.timing.stage2, o.timing.masks, o.timing.total), (0.0, 2548.6, 121.3, 2680.9));
        assert!((o.timing.setup - 11.0).abs() < 1e-9, "{}", o.timing.setup);
        assert_eq!(o.stage2_steps, Some(100));
    }

    #[test]
    fn missing_values_stay_empty_and_the_wall_time_stands_in_for_the_total() {
        // Stage 1 only, and a total that is not a number.
        let m: Json = serde_json::json!({ "test": { "psnr": null }, "timing": { "stage1_seconds": 50.0 } });
        let o = outcome_from_metrics(&m, 61.0);
        assert_eq!(o.metrics, Metrics::default());
        assert_eq!(o.timing.total, 61.0);
        assert_eq!(o.timing.setup, 11.0);
        assert_eq!(o.stage2_steps, None);
    }

    #[test]
    fn a_child_reports_its_exit_code_memory_and_cpu_time() {
        let child = Command::new("sh").arg("-c").arg("exit 3").spawn().unwrap();
        let u = wait_with_usage(child).unwrap();
        assert_eq!(u.code, Some(3));
        assert!(u.peak_rss_mib > 0.0 && u.cpu_seconds >= 0.0);
    }
}
