//! Running a matrix: each run in its own process, results written as they finish, finished
//! runs never repeated, the report regenerated after every run.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use toml::Value;

use super::matrix::{Generate, PlannedRun};
use super::record::{Outcome, RunRecord, Status};
use super::report;

/// Sub-folder of the output folder holding each run's own folder (`<id>/`) and config.
pub const WORK_DIR: &str = "work";

/// What describes a result folder (`<out>/bench.json`), so that `merge` and the report know
/// the baseline and the file the runs came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BenchMeta {
    /// The benchmark file, as given.
    pub file: String,
    /// The profile.
    pub profile: String,
    /// The baseline method of the speed-up column.
    pub baseline: String,
    /// `i/n` when this folder holds one shard.
    pub shard: Option<String>,
    /// Runs in the whole matrix (all shards).
    pub matrix_runs: usize,
    /// The quality of the time-to-target column, if the file names one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<super::target::Target>,
}

impl BenchMeta {
    /// Reads `<dir>/bench.json`.
    pub fn load(dir: &Path) -> anyhow::Result<BenchMeta> {
        let path = dir.join("bench.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}: not a benchmark result folder", path.display()))?;
        serde_json::from_str(&text).with_context(|| format!("{} is not a benchmark description", path.display()))
    }
}

/// How the runner counts what it did.
#[derive(Debug, Default)]
pub struct Tally {
    /// Runs executed now and finished.
    pub ran: usize,
    /// Runs whose result was already there.
    pub cached: usize,
    /// Runs that could not run here.
    pub skipped: usize,
    /// Ids of runs that failed.
    pub failed: Vec<String>,
}

/// What earlier work a run may stand on.
#[derive(Debug, Default)]
pub struct Reuse {
    /// A run may start from an earlier finished run's stage 1 with the same stage-1 settings.
    pub share_stage1: bool,
    /// Methods whose finished results run again (`--rerun`), e.g. to time them beside a new
    /// row in one invocation. With `share_stage1`, such a run starts from its previous result's
    /// stage 1 when that result trained its own and kept its checkpoint.
    pub rerun: Vec<String>,
}

/// Where a rerun's previous result is moved while the rerun starts from its stage 1.
const PREVIOUS_SUFFIX: &str = ".previous";

/// Runs `runs` (a matrix or one shard of it) into `out`, standing on earlier work as `reuse`
/// allows.
pub fn run_all(
    runs: &[PlannedRun],
    out: &Path,
    meta: &BenchMeta,
    curve_points: usize,
    commit: &str,
    progress: bool,
    reuse: &Reuse,
) -> anyhow::Result<Tally> {
    let share_stage1 = reuse.share_stage1;
    let runs_dir = out.join("runs");
    let work_dir = out.join(WORK_DIR);
    for d in [&runs_dir, &work_dir, &out.join("logs")] {
        std::fs::create_dir_all(d).with_context(|| format!("creating {} (is `--out` writable?)", d.display()))?;
    }
    crate::commands::write_json(&out.join("bench.json"), meta)?;
    remove_leftovers(&runs_dir, &work_dir)?;
    let mut records: Vec<RunRecord> = Vec::new();
    let existing: Vec<RunRecord> = std::fs::read_dir(&runs_dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .filter_map(|p| RunRecord::load(&p).ok())
        .collect();
    // Finished results this invocation keeps as they are (same config, not rerun): their work
    // folders hold those very runs, so they can give their stage 1 to any run of the matrix,
    // also to one that comes before them in the order.
    let kept: Vec<&RunRecord> = existing
        .iter()
        .filter(|r| {
            r.status == Status::Done
                && !reuse.rerun.contains(&r.key.method)
                && runs.iter().any(|p| p.key.id == r.key.id && p.hash == r.hash)
        })
        .collect();

    let bar = if progress { ProgressBar::new(runs.len() as u64) } else { ProgressBar::hidden() };
    bar.set_style(
        ProgressStyle::with_template("bench {bar:30} {pos}/{len} {msg} [{elapsed_precise}<{eta_precise}]")
            .expect("valid template"),
    );
    let mut tally = Tally::default();
    let mut changed = false;
    for (n, run) in runs.iter().enumerate() {
        bar.set_message(run.key.id.clone());
        let path = runs_dir.join(format!("{}.json", run.key.id));
        let started = Instant::now();
        let rerun = reuse.rerun.contains(&run.key.method);
        let done = |r: &RunRecord| !rerun && r.status == Status::Done && r.hash == run.hash;
        let mut cached = false;
        // A finished result stands even where its data or weights are missing now.
        let (record, how) = if let Some(r) = existing.iter().chain(&records).find(|r| r.key.id == run.key.id && done(r))
        {
            tally.cached += 1;
            cached = true;
            (r.clone(), "cached".into())
        } else if let Some(reason) = &run.skip {
            tally.skipped += 1;
            (RunRecord::new(run, Status::Skipped, Some(reason.clone()), None, commit), format!("skipped: {reason}"))
        } else if let Some(r) = existing.iter().chain(&records).find(|r| done(r)) {
            // Another run of the matrix has this very config (a sweep point at the default).
            tally.cached += 1;
            let mut copy = r.clone();
            let note = format!("same config as `{}`: its result is reused", r.key.id);
            copy.key = run.key.clone();
            copy.wall_seconds = None;
            if let Some(o) = copy.outcome.as_mut() {
                o.notes.push(note.clone());
                // No checkpoint of this run's own exists: it is no stage 1 to share.
                o.stage1 = None;
            }
            (copy, note)
        } else {
            // This invocation's records and the results it keeps: each is the latest of its
            // id, and its work folder holds that very run (an older record of a rerun id would
            // not).
            let previous = if rerun && share_stage1 { set_previous_aside(run, &existing, &work_dir)? } else { None };
            let source = match &run.stage1_of {
                // Another build's stage 2 starts from this very run, whatever `--own-stage1` says.
                Some(id) => records.iter().rev().find(|r| &r.key.id == id && r.status == Status::Done),
                None => previous.as_ref().or_else(|| {
                    records
                        .iter()
                        .chain(kept.iter().copied())
                        .find(|r| share_stage1 && shares_stage1(r, run, &work_dir))
                }),
            };
            let program = program_id(run);
            let (mut record, how) = match execute(run, out, curve_points, source) {
                Ok(outcome) => {
                    tally.ran += 1;
                    let summary = summary_line(&outcome, started.elapsed().as_secs_f64());
                    (RunRecord::new(run, Status::Done, None, Some(outcome), commit), summary)
                }
                Err(e) => {
                    tally.failed.push(run.key.id.clone());
                    let message = format!("{e:#}");
                    let first = message.lines().next().unwrap_or("").to_string();
                    (RunRecord::new(run, Status::Failed, Some(message), None, commit), format!("FAILED: {first}"))
                }
            };
            if let Some(p) = &previous {
                let _ = std::fs::remove_dir_all(work_dir.join(&p.key.id));
                // The stage 1 it started from is its own id's: it stays a source for others.
                if let (Some(o), Some(before)) = (record.outcome.as_mut(), p.outcome.as_ref()) {
                    o.stage1 = before.stage1.clone();
                }
            }
            record.wall_seconds = Some(started.elapsed().as_secs_f64());
            record.program = program;
            (record, how)
        };
        // Unchanged records are not rewritten, so a rerun of a finished matrix writes nothing.
        let unchanged = cached
            || (record.status == Status::Skipped
                && existing.iter().any(|old| old.key.id == run.key.id && same_skip(old, &record)));
        if !unchanged {
            record.save(&path)?;
            changed = true;
        }
        records.push(record);
        let line = format!("[{}/{}] {}: {how}", n + 1, runs.len(), run.key.id);
        if bar.is_hidden() {
            eprintln!("{line}");
        } else {
            bar.println(line);
        }
        bar.inc(1);
        if !unchanged {
            report::write(out, &records, meta).context("writing the report")?;
        }
    }
    bar.finish_and_clear();
    if changed || !out.join("report.json").exists() {
        report::write(out, &records, meta).context("writing the report")?;
    }
    Ok(tally)
}

/// For a rerun: moves its previous result's folder aside (to `<id>.previous`) when that
/// result can give it its stage 1, and returns that result's record under the moved folder's
/// name. The rerun removes it when done.
fn set_previous_aside(run: &PlannedRun, existing: &[RunRecord], work_dir: &Path) -> anyhow::Result<Option<RunRecord>> {
    let Some(old) = existing.iter().find(|r| r.key.id == run.key.id) else { return Ok(None) };
    let mut moved = old.clone();
    moved.key.id = format!("{}{PREVIOUS_SUFFIX}", run.key.id);
    let (from, to) = (work_dir.join(&run.key.id), work_dir.join(&moved.key.id));
    // Already aside when a rerun was killed: the record is still that result's.
    if !to.join(CHECKPOINT).is_file() {
        if to.exists() {
            std::fs::remove_dir_all(&to).with_context(|| format!("removing {}", to.display()))?;
        }
        if !from.join(CHECKPOINT).is_file() {
            return Ok(None);
        }
        std::fs::rename(&from, &to).with_context(|| format!("moving {} aside", from.display()))?;
    }
    if shares_stage1(&moved, run, work_dir) {
        Ok(Some(moved))
    } else {
        std::fs::remove_dir_all(&to).with_context(|| format!("removing {}", to.display()))?;
        Ok(None)
    }
}

/// Whether an earlier skip record says the same (its time aside), so it need not be rewritten.
fn same_skip(old: &RunRecord, new: &RunRecord) -> bool {
    old.status == Status::Skipped && old.error == new.error && old.hash == new.hash && old.commit == new.commit
}

/// What a finished run prints.
fn summary_line(o: &Outcome, seconds: f64) -> String {
    let f = |v: Option<f64>, d: usize| v.map_or_else(|| "-".into(), |v| format!("{v:.d$}"));
    format!(
        "done in {seconds:.0} s (run time {:.1} s): mIoU {}, NV-ARI {}, PSNR {} dB",
        o.timing.total,
        f(o.metrics.miou, 3),
        f(o.metrics.nv_ari, 3),
        f(o.metrics.psnr, 2)
    )
}

/// Removes what a killed runner leaves: temporary files of unfinished writes.
fn remove_leftovers(runs_dir: &Path, work_dir: &Path) -> anyhow::Result<()> {
    for dir in [runs_dir, work_dir] {
        for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
            let p = e?.path();
            if p.to_string_lossy().ends_with(".tmp") {
                std::fs::remove_file(&p).with_context(|| format!("removing leftover {}", p.display()))?;
            }
        }
    }
    Ok(())
}

/// Whether `run` can start from `source`'s stage 1: a finished run with the same stage-1
/// settings that ran its own stage 1, whose checkpoint holds the field as stage 1 left it (its
/// stage 2 ran, so the final checkpoint was written, and did not train the field) and is
/// still in the work folder; `run` must leave the field frozen too (joint training would go on
/// from stage 1's optimiser state, which that checkpoint does not keep). The shared run gets
/// the result its own stage 1 would give (stage 1 is deterministic per seed; stage 2 draws
/// from its own seed).
fn shares_stage1(source: &RunRecord, run: &PlannedRun, work_dir: &Path) -> bool {
    let ran_own_stage1 = source.outcome.as_ref().is_some_and(|o| o.stage1.is_some());
    source.status == Status::Done
        && source.key.id != run.key.id
        && source.stage1_hash.as_deref() == Some(run.stage1_hash.as_str())
        && ran_own_stage1
        && leaves_field_frozen(&source.config)
        && leaves_field_frozen(&toml::to_string(&run.config).unwrap_or_default())
        && work_dir.join(&source.key.id).join(CHECKPOINT).is_file()
}

/// The final checkpoint of a run.
pub(super) const CHECKPOINT: &str = "checkpoint.bin";

/// Whether a run config (TOML) runs stage 2 with the field frozen: stage 2 has steps and no
/// photometric term (which trains the field jointly).
pub(super) fn leaves_field_frozen(config: &str) -> bool {
    let Ok(config) = config.parse::<toml::Table>() else { return false };
    let segment = config.get("segment").and_then(Value::as_table);
    let number = |key: &str| {
        segment.and_then(|s| s.get(key)).and_then(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64)))
    };
    number("steps").is_some_and(|s| s > 0.0) && number("photometric_weight").unwrap_or(0.0) == 0.0
}

/// Runs one planned run in a child process and returns what it measured; with `stage1_from`,
/// the run starts from that run's stage 1 (see [`shares_stage1`]).
fn execute(
    run: &PlannedRun,
    out: &Path,
    curve_points: usize,
    stage1_from: Option<&RunRecord>,
) -> anyhow::Result<Outcome> {
    if let Some(g) = &run.generate {
        ensure_generated(g, out)?;
    }
    let work = out.join(WORK_DIR);
    let absolute =
        |p: &Path| if p.is_absolute() { p.to_path_buf() } else { std::env::current_dir().unwrap_or_default().join(p) };
    let run_dir = work.join(&run.key.id);
    // A run killed midway left a partial folder: start it over cleanly.
    if run_dir.exists() {
        std::fs::remove_dir_all(&run_dir)
            .with_context(|| format!("removing the unfinished run {}", run_dir.display()))?;
    }
    let log_path = out.join("logs").join(format!("{}.log", run.key.id));
    if let Some(program) = &run.program {
        return super::program::execute(run, program, &absolute(&work), &log_path, stage1_from);
    }
    let config_path = work.join(format!("{}.toml", run.key.id));
    std::fs::write(&config_path, run_config_text(run, &absolute(&work))?)
        .with_context(|| format!("writing {}", config_path.display()))?;
    let outcome_path = work.join(format!("{}.outcome.json", run.key.id));
    let _ = std::fs::remove_file(&outcome_path);
    let log = std::fs::File::create(&log_path).with_context(|| format!("creating {}", log_path.display()))?;
    let exe = own_binary()?;
    let mut command = Command::new(exe);
    command
        .arg("bench-exec")
        .arg(&config_path)
        .arg("--config-dir")
        .arg(absolute(&run.config_dir))
        .arg("--outcome")
        .arg(&outcome_path)
        .arg("--curve-points")
        .arg(curve_points.to_string());
    if let Some([w, h]) = run.view_size {
        command.arg("--view-size").arg(w.to_string()).arg(h.to_string());
    }
    // The child gets the very record the runner checked.
    let source_record = work.join(format!("{}.stage1-source.json", run.key.id));
    if let Some(source) = stage1_from {
        crate::commands::write_json(&source_record, source)?;
        command
            .arg("--stage1-checkpoint")
            .arg(absolute(&work.join(&source.key.id).join(CHECKPOINT)))
            .arg("--stage1-record")
            .arg(absolute(&source_record));
    }
    let status = command
        .stdin(Stdio::null())
        .stdout(log.try_clone()?)
        .stderr(log)
        .status()
        .context("starting the run's process")?;
    let _ = std::fs::remove_file(&source_record);
    if !status.success() {
        bail!("{} (log: {})\n{}", describe(status), log_path.display(), error_lines(&log_path));
    }
    let text = std::fs::read_to_string(&outcome_path).with_context(|| format!("reading {}", outcome_path.display()))?;
    let outcome: Outcome =
        serde_json::from_str(&text).with_context(|| format!("{} is not an outcome", outcome_path.display()))?;
    std::fs::remove_file(&outcome_path).ok();
    Ok(outcome)
}

/// The run's config as its process reads it: named after the run, writing into `work/<id>`.
pub(super) fn run_config_text(run: &PlannedRun, work: &Path) -> anyhow::Result<String> {
    let mut config = run.config.clone();
    if let Value::Table(t) = &mut config {
        t.insert("name".into(), Value::String(run.key.id.clone()));
        t.insert("output_dir".into(), Value::String(work.display().to_string()));
    }
    Ok(toml::to_string(&config)?)
}

/// The first 12 hex digits of the SHA-256 of the binary that runs `run` (a method's own
/// build, or this one); `None` when it cannot be read. Hashed for each run, not once: the
/// binary may be rebuilt while the matrix runs (see [`own_binary`]).
fn program_id(run: &PlannedRun) -> Option<String> {
    let path = match &run.program {
        Some(p) => p.clone(),
        None => own_binary().ok()?,
    };
    let bytes = std::fs::read(path).ok()?;
    Some(super::matrix::hash_bytes(&bytes)[..12].to_string())
}

/// The binary to start runs with: this one, or, when it was rebuilt while the matrix runs
/// (Linux then names the running file `<path> (deleted)`), the new one at the same path.
fn own_binary() -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("finding the running `sos` binary")?;
    let name = exe.to_string_lossy();
    match name.strip_suffix(" (deleted)") {
        Some(path) if Path::new(path).exists() => Ok(PathBuf::from(path)),
        _ => Ok(exe),
    }
}

fn describe(status: std::process::ExitStatus) -> String {
    match status.code() {
        Some(c) => format!("the run exited with code {c}"),
        None => "the run was killed by a signal".into(),
    }
}

/// The `error:` lines of a run's log, or its last lines.
fn error_lines(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let errors: Vec<&str> = text.lines().filter(|l| l.starts_with("error")).collect();
    if errors.is_empty() {
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(8)..].join("\n")
    } else {
        errors.join("\n")
    }
}

/// Writes a generated scene once: into a temporary folder renamed into place, so that
/// concurrent shards and interrupted writes never leave a half-written layout in use.
fn ensure_generated(g: &Generate, out: &Path) -> anyhow::Result<()> {
    let dir = g.dir(out);
    if dir.join(".complete").exists() {
        return Ok(());
    }
    let tmp: PathBuf = dir.with_extension(format!("{}.partial", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let scene = sos_datasets::synthetic::generate(&g.synthetic);
    g.layout
        .write(&scene, &tmp)
        .with_context(|| format!("writing the {} layout to {}", g.layout.name(), tmp.display()))?;
    std::fs::write(tmp.join(".complete"), toml::to_string(&g.spec)?)?;
    if dir.exists() {
        std::fs::remove_dir_all(&dir).with_context(|| format!("replacing the incomplete {}", dir.display()))?;
    }
    match std::fs::rename(&tmp, &dir) {
        Ok(()) => Ok(()),
        // Another shard finished the same scene first.
        Err(_) if dir.join(".complete").exists() => {
            let _ = std::fs::remove_dir_all(&tmp);
            Ok(())
        }
        Err(e) => Err(e).with_context(|| format!("moving {} into place", dir.display())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_stage_two_that_ran_with_the_field_frozen_leaves_a_stage_one_checkpoint() {
        assert!(leaves_field_frozen("[segment]\nsteps = 100\nphotometric_weight = 0.0\n"));
        assert!(leaves_field_frozen("[segment]\nsteps = 100\n"));
        // No stage 2: no final checkpoint is written after stage 1.
        assert!(!leaves_field_frozen("[segment]\nsteps = 0\n"));
        assert!(!leaves_field_frozen("[train]\nsteps = 10\n"));
        // Joint training changes the field in stage 2.
        assert!(!leaves_field_frozen("[segment]\nsteps = 100\nphotometric_weight = 0.5\n"));
        assert!(!leaves_field_frozen("not toml ["));
    }
}
