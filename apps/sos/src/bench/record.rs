//! The result file of one run (`<out>/runs/<run-id>.json`): what ran (the resolved config and
//! its hash, the commit, the machine), how it went (status, error), and what it measured
//! (metrics, stage times, peak memory, learning curves).

use std::path::Path;

use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};

use super::matrix::{PlannedRun, RunKey};

/// How a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Status {
    /// Finished; its metrics are valid.
    Done,
    /// Failed; `error` says why.
    Failed,
    /// Not run here; `error` says why (missing data or weights, a kind not built in).
    Skipped,
}

/// The name of [`Metrics::depth_error`] in reports.
pub const DEPTH_ERROR: &str = "depth err";
/// The name of [`Metrics::object_depth_error`] in reports.
pub const OBJECT_DEPTH_ERROR: &str = "object depth err";

/// Held-out metrics; a value that is absent was not measured or not finite.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// PSNR of the mean squared error over held-out views, dB.
    pub psnr: Option<f64>,
    /// Mean SSIM over held-out views.
    pub ssim: Option<f64>,
    /// Mean adjusted Rand index over held-out views (NV-ARI).
    pub nv_ari: Option<f64>,
    /// Mean foreground IoU.
    pub iou_fg: Option<f64>,
    /// Mean background IoU.
    pub iou_bg: Option<f64>,
    /// Mean IoU over both classes.
    pub miou: Option<f64>,
    /// Mean over held-out views of the median relative error of the rendered depth, for
    /// scenes that know their depth (generated ones).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_error: Option<f64>,
    /// The same over the pixels of the ground-truth object.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object_depth_error: Option<f64>,
}

impl Metrics {
    /// The metrics by name, in report order.
    pub fn named(&self) -> [(&'static str, Option<f64>); 8] {
        [
            ("mIoU", self.miou),
            ("NV-ARI", self.nv_ari),
            ("IoU FG", self.iou_fg),
            ("IoU BG", self.iou_bg),
            ("PSNR", self.psnr),
            ("SSIM", self.ssim),
            (DEPTH_ERROR, self.depth_error),
            (OBJECT_DEPTH_ERROR, self.object_depth_error),
        ]
    }
}

/// Wall-clock seconds of a run's phases. Learning-curve evaluations are not part of any
/// stage: they are counted apart, in `curve_eval`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// Loading the scene and building field and teacher.
    pub setup: f64,
    /// Stage 1 (photometric training).
    pub stage1: f64,
    /// Stage 2 (segmentation head).
    pub stage2: f64,
    /// Masks and metrics of the held-out views (or their evaluation without stage 2).
    pub masks: f64,
    /// Learning-curve evaluations.
    pub curve_eval: f64,
    /// The run's time to its result: everything but the curve evaluations.
    pub total: f64,
}

impl Timing {
    /// The phases the report shows, by name.
    pub fn named(&self) -> [(&'static str, f64); 4] {
        [("stage1", self.stage1), ("stage2", self.stage2), ("masks", self.masks), ("total", self.total)]
    }
}

/// One stage-1 point of the learning curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stage1Point {
    /// Steps done.
    pub step: usize,
    /// Stage-1 training seconds so far (evaluations excluded).
    pub seconds: f64,
    /// Held-out PSNR, dB.
    pub psnr: Option<f64>,
}

/// One stage-2 point of the learning curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stage2Point {
    /// Steps done.
    pub step: usize,
    /// Stage-2 training seconds so far (evaluations excluded).
    pub seconds: f64,
    /// Held-out mIoU.
    pub miou: Option<f64>,
    /// Held-out NV-ARI.
    pub nv_ari: Option<f64>,
}

/// Learning curves of both stages.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Curves {
    /// Held-out PSNR during stage 1.
    pub stage1: Vec<Stage1Point>,
    /// Held-out mIoU and NV-ARI during stage 2.
    pub stage2: Vec<Stage2Point>,
}

/// What the run process measured (written by `sos bench-exec`, read by the runner).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    /// Held-out metrics.
    pub metrics: Metrics,
    /// Phase times.
    pub timing: Timing,
    /// Peak resident memory of the run's process, MiB.
    pub peak_rss_mib: Option<f64>,
    /// CPU seconds (user + system) the run's process used; over the wall time, the cores it
    /// kept busy (below the core count on a shared machine or in serial phases).
    #[serde(default)]
    pub cpu_seconds: Option<f64>,
    /// Share of the machine's CPU time that its hypervisor gave to other guests during the
    /// run (`steal` in `/proc/stat`): above a few percent, the times are those of a shared
    /// machine, not of an idle one.
    #[serde(default)]
    pub cpu_stolen: Option<f64>,
    /// Learning curves.
    pub curves: Curves,
    /// Notes (e.g. a metric that was not finite).
    #[serde(default)]
    pub notes: Vec<String>,
    /// The settings the run derived from its scene.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub derived: Vec<sos_core::derived::DerivedSetting>,
    /// What its stage 1 left for runs that share it (absent in a run that shared another's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage1: Option<Stage1Summary>,
    /// Steps stage 2 ran (absent without stage 2): with `timing.stage2`, the time of a step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage2_steps: Option<usize>,
    /// The time of one view with its mask, as a user waits for it (absent without stage 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view: Option<ViewTime>,
}

/// How long one view with its mask takes: the first held-out camera (the first training one
/// when none is held out) at `width x height`, rendered, clustered and cleaned up as `sos
/// render` does, the median of [`ViewTime::REPEATS`] repeats. Not part of any stage's time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewTime {
    /// View width, pixels.
    pub width: u32,
    /// View height, pixels.
    pub height: u32,
    /// Median wall seconds.
    pub seconds: f64,
}

impl ViewTime {
    /// Repeats of the view; the median is kept, so one disturbed repeat does not count.
    pub const REPEATS: usize = 3;
}

/// What a run's stage 1 gives a run that shares it besides the field: the stage's notes and
/// the training rays' PSNR (for the overfitting warning).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stage1Summary {
    /// Notes about stage 1 (it stopped early, content piled up at the extent's faces).
    pub notes: Vec<String>,
    /// PSNR of the training rays at the end of stage 1 (absent when not finite).
    pub train_psnr: Option<f64>,
    /// Steps stage 1 ran.
    pub steps: usize,
}

/// The machine a run ran on.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Machine {
    /// CPU model.
    pub cpu: String,
    /// Logical cores available to the process.
    pub cores: usize,
    /// Physical memory, GiB.
    pub memory_gib: f64,
    /// Host name.
    pub host: String,
}

impl Machine {
    /// This machine (Linux `/proc`; fields stay empty elsewhere).
    pub fn here() -> Machine {
        let cpu = cpu_model(&std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default());
        let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
        let kib = meminfo
            .lines()
            .find_map(|l| l.strip_prefix("MemTotal:"))
            .and_then(|v| v.split_whitespace().next()?.parse::<f64>().ok())
            .unwrap_or(0.0);
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default().trim().to_string();
        Machine {
            cpu,
            cores: std::thread::available_parallelism().map_or(1, usize::from),
            memory_gib: (kib / (1024.0 * 1024.0) * 10.0).round() / 10.0,
            host,
        }
    }
}

/// `<out>/runs/<run-id>.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    /// Who the run is in the matrix (its fields sit at the top level of the JSON).
    #[serde(flatten)]
    pub key: RunKey,
    /// Hash of the resolved config (and generated scene): equal hashes, equal results.
    pub hash: String,
    /// Hash of what decides its stage 1 (see [`PlannedRun::stage1_hash`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage1_hash: Option<String>,
    /// How it ended.
    pub status: Status,
    /// Why it failed or was skipped.
    pub error: Option<String>,
    /// The fully resolved run config (TOML).
    pub config: String,
    /// Commit of the checkout that ran it (`unknown` outside git; `+dirty` with local changes).
    pub commit: String,
    /// The program that ran it: the first 12 hex digits of the SHA-256 of its binary (this
    /// `sos`, or a method's other build). The checkout and the binary can differ, e.g. when a
    /// long profile runs one build throughout. Absent for runs that did not execute (skipped,
    /// or a result reused) and in records of older builds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
    /// The machine.
    pub machine: Machine,
    /// When the run finished (UTC, `YYYY-MM-DD HH:MM`).
    pub finished: String,
    /// What it measured (absent unless done).
    pub outcome: Option<Outcome>,
    /// Wall seconds the runner spent on it, from writing its config to reading its outcome:
    /// curve evaluations, the timed view and a layout written for it included. Absent for a
    /// run that reused another's result (it cost nothing) and in records of older builds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wall_seconds: Option<f64>,
}

impl RunRecord {
    /// A record of `run` with its status; `outcome` for a finished run.
    pub fn new(
        run: &PlannedRun,
        status: Status,
        error: Option<String>,
        outcome: Option<Outcome>,
        commit: &str,
    ) -> RunRecord {
        RunRecord {
            key: run.key.clone(),
            hash: run.hash.clone(),
            stage1_hash: Some(run.stage1_hash.clone()),
            status,
            error,
            config: toml::to_string(&run.config).unwrap_or_default(),
            commit: commit.to_string(),
            program: None,
            machine: Machine::here(),
            finished: utc_now(),
            outcome,
            wall_seconds: None,
        }
    }

    /// Reads a record; errors name the file.
    /// A record is input too (merged from other machines): its hash must be the hex digest a
    /// report shortens.
    pub fn load(path: &Path) -> anyhow::Result<RunRecord> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let record: RunRecord =
            serde_json::from_str(&text).with_context(|| format!("{} is not a run record", path.display()))?;
        if record.hash.len() < 12 || !record.hash.bytes().all(|b| b.is_ascii_hexdigit()) {
            bail!("{}: its config `hash` `{}` is not a hex digest; the record was edited", path.display(), record.hash);
        }
        Ok(record)
    }

    /// Writes the record atomically (a killed process leaves the old file or the new one).
    pub fn save(&self, path: &Path) -> anyhow::Result<()> {
        crate::commands::write_json(path, self)
    }
}

/// Every record in `<dir>/runs/`, sorted by id.
pub fn load_all(dir: &Path) -> anyhow::Result<Vec<RunRecord>> {
    let runs = dir.join("runs");
    let entries = std::fs::read_dir(&runs)
        .with_context(|| format!("reading {}: not a benchmark result folder", runs.display()))?;
    let mut out = Vec::new();
    for e in entries {
        let path = e.with_context(|| format!("reading {}", runs.display()))?.path();
        if path.extension().is_some_and(|x| x == "json") {
            let record = RunRecord::load(&path)?;
            // The id names the record's copy in a merged folder: it must be this file's name.
            if path.file_stem().and_then(|s| s.to_str()) != Some(record.key.id.as_str()) {
                bail!(
                    "{}: its `id` `{}` is not its file's name; the record was renamed or edited",
                    path.display(),
                    record.key.id
                );
            }
            out.push(record);
        }
    }
    out.sort_by(|a, b| a.key.id.cmp(&b.key.id));
    Ok(out)
}

/// The CPU's name from `/proc/cpuinfo`: x86's `model name`, else the fields other
/// architectures use (`Model` or `Hardware` on ARM boards, `cpu model` on MIPS, `cpu` on
/// POWER, `uarch` on RISC-V), else `unknown` with the architecture.
fn cpu_model(cpuinfo: &str) -> String {
    ["model name", "Model", "Hardware", "cpu model", "cpu", "uarch"]
        .iter()
        .find_map(|key| {
            cpuinfo.lines().find_map(|l| {
                let (k, v) = l.split_once(':')?;
                (k.trim() == *key && !v.trim().is_empty()).then(|| v.trim().to_string())
            })
        })
        .unwrap_or_else(|| format!("unknown {}", std::env::consts::ARCH))
}

/// The current commit of the checkout holding `dir`, with `+dirty` for local changes to
/// tracked files, except those inside benchmark result folders (see [`changes_code`]).
pub fn commit_of(dir: &Path) -> String {
    let git = |args: &[&str]| {
        std::process::Command::new("git")
            .arg("-C")
            .arg(if dir.as_os_str().is_empty() { Path::new(".") } else { dir })
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
    };
    let (Some(head), Some(top)) = (git(&["rev-parse", "--short=12", "HEAD"]), git(&["rev-parse", "--show-toplevel"]))
    else {
        return "unknown".into();
    };
    let head = head.trim();
    let dirty = git(&["status", "--porcelain", "--untracked-files=no"])
        .is_some_and(|status| changes_code(Path::new(top.trim()), &status));
    if dirty {
        format!("{head}+dirty")
    } else {
        head.to_string()
    }
}

/// Whether `git status --porcelain` output (paths relative to the checkout's top `top`) lists a
/// change outside every benchmark result folder (a folder holding `bench.json`, at any depth
/// above the file). A benchmark rewrites its own reports as it runs, and a run folder's
/// records may be pruned by hand: neither is a change to what the runs ran.
pub fn changes_code(top: &Path, porcelain: &str) -> bool {
    porcelain.lines().filter(|l| l.len() > 3).any(|line| {
        let path = &line[3..];
        // A rename lists `old -> new`; a path with unusual characters comes quoted.
        let path = path.rsplit(" -> ").next().unwrap_or(path);
        if path.starts_with('"') {
            return true;
        }
        let file = top.join(path);
        !file.ancestors().skip(1).take_while(|d| d.starts_with(top)).any(|d| d.join("bench.json").is_file())
    })
}

/// The peak resident memory of this process so far, MiB (Linux `VmHWM`).
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kib: f64 = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?.split_whitespace().next()?.parse().ok()?;
    Some(kib / 1024.0)
}

/// CPU seconds (user + system) this process has used so far (Linux `/proc/self/stat`, in
/// the kernel's 100 Hz clock ticks).
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line, 12 and 13 after the name.
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// The machine's CPU time counters so far: (stolen, all), in clock ticks (Linux `/proc/stat`).
pub fn cpu_ticks() -> Option<(u64, u64)> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let values: Vec<u64> = line.split_whitespace().skip(1).filter_map(|v| v.parse().ok()).collect();
    // user nice system idle iowait irq softirq steal [guest guest_nice, already in user]
    Some((*values.get(7)?, values.iter().take(8).sum()))
}

/// The share of CPU time stolen between two [`cpu_ticks`] readings.
pub fn stolen_between(start: (u64, u64), end: (u64, u64)) -> Option<f64> {
    let all = end.1.checked_sub(start.1)?;
    (all > 0).then(|| end.0.saturating_sub(start.0) as f64 / all as f64)
}

/// The current UTC time as `YYYY-MM-DD HH:MM`.
pub fn utc_now() -> String {
    let secs = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let (days, rem) = (secs / 86_400, secs % 86_400);
    let (y, m, d) = civil_from_days(days as i64);
    format!("{y:04}-{m:02}-{d:02} {:02}:{:02}", rem / 3600, rem % 3600 / 60)
}

/// Gregorian date of a day count since 1970-01-01 (Howard Hinnant's `civil_from_days`).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + i64::from(m <= 2), m, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cpu_is_named_on_x86_and_on_arm_boards() {
        let x86 = "processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel\t\t: 1\nmodel name\t: AMD EPYC 7B13\n";
        assert_eq!(cpu_model(x86), "AMD EPYC 7B13");
        let arm =
            "processor\t: 0\nBogoMIPS\t: 108.00\nCPU part\t: 0xd08\n\nModel\t\t: Raspberry Pi 4 Model B Rev 1.4\n";
        assert_eq!(cpu_model(arm), "Raspberry Pi 4 Model B Rev 1.4");
        assert!(cpu_model("processor\t: 0\n").starts_with("unknown "));
    }

    #[test]
    fn a_benchmarks_own_result_folders_do_not_make_a_checkout_dirty() {
        let top = std::env::temp_dir().join(format!("sos-record-dirty-{}", std::process::id()));
        let results = top.join("benchmarks/reports/quick");
        std::fs::create_dir_all(results.join("runs")).unwrap();
        std::fs::write(results.join("bench.json"), "{}").unwrap();
        let report = " M benchmarks/reports/quick/report.md\n D benchmarks/reports/quick/runs/a__default__s0.json\n";
        assert!(!changes_code(&top, report), "the benchmark's own folder");
        assert!(!changes_code(&top, ""), "nothing changed");
        assert!(changes_code(&top, &format!("{report} M sos-core/src/lib.rs\n")), "code changed");
        assert!(changes_code(&top, "M  benchmarks/run_all.toml\n"), "the benchmark file is not a result");
        assert!(changes_code(&top, "R  a.rs -> sos-core/src/b.rs\n"), "a renamed source file");
        assert!(!changes_code(&top, "R  x.md -> benchmarks/reports/quick/x.md\n"), "renamed into the results");
        std::fs::remove_dir_all(&top).ok();
    }

    #[test]
    fn a_record_whose_id_or_hash_was_edited_is_refused_with_its_path() {
        let dir = std::env::temp_dir().join(format!("sos-record-load-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let write = |file: &str, id: &str, hash: &str| {
            let json = serde_json::json!({
                "id": id, "scene": "s", "method": "m", "variant": "m", "sweep": null, "seed": 0,
                "hash": hash, "status": "failed", "error": "x", "config": "", "commit": "c",
                "machine": { "cpu": "cpu", "cores": 2, "memory_gib": 1.0, "host": "vm" },
                "finished": "2026-01-01 00:00", "outcome": null,
            });
            let path = dir.join(file);
            std::fs::write(&path, json.to_string()).unwrap();
            path
        };
        assert!(RunRecord::load(&write("s__m__s0.json", "s__m__s0", "0123456789abcdef")).is_ok());
        // Shorter than the 12 digits a report shows, and not hex.
        for (file, hash) in [("s__m__s3.json", "h"), ("s__m__s4.json", "0123456789abcdeg")] {
            let err = format!("{:#}", RunRecord::load(&write(file, "s__m__s3", hash)).unwrap_err());
            assert!(err.contains("not a hex digest") && err.contains(file), "{err}");
            std::fs::remove_file(dir.join(file)).unwrap();
        }
        // In a result folder, an id that would name a file outside the merged folder, or
        // another record's file.
        let runs = dir.join("runs");
        std::fs::create_dir_all(&runs).unwrap();
        std::fs::rename(dir.join("s__m__s0.json"), runs.join("s__m__s0.json")).unwrap();
        assert_eq!(load_all(&dir).unwrap().len(), 1);
        for id in ["../../escaped", "s__m__s0"] {
            std::fs::rename(write("s__m__s1.json", id, "0123456789abcdef"), runs.join("s__m__s1.json")).unwrap();
            let err = format!("{:#}", load_all(&dir).unwrap_err());
            assert!(err.contains("is not its file's name") && err.contains("s__m__s1.json"), "{err}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn dates_follow_the_gregorian_calendar() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(11_016), (2000, 2, 29));
        assert_eq!(civil_from_days(20_788), (2026, 12, 1));
    }

    #[test]
    fn this_machine_has_cores_and_memory() {
        let m = Machine::here();
        assert!(m.cores >= 1);
        if cfg!(target_os = "linux") {
            assert!(m.memory_gib > 0.0 && m.cpu != "unknown", "{m:?}");
            assert!(peak_rss_mib().is_some_and(|p| p > 0.0));
            // Burn a little CPU so the count is positive.
            let mut x = 0u64;
            let t = std::time::Instant::now();
            while t.elapsed().as_millis() < 30 {
                x = x.wrapping_mul(31).wrapping_add(7);
            }
            assert!(x != 1 && cpu_seconds().is_some_and(|c| c > 0.0));
            let (stolen, all) = cpu_ticks().unwrap();
            assert!(stolen <= all && all > 0);
        }
        assert_eq!(stolen_between((10, 100), (30, 300)), Some(0.1));
        assert_eq!(stolen_between((10, 100), (10, 100)), None);
    }
}
