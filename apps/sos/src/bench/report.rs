//! The benchmark report: `report.json` and `report.md` (a table per scene, one row per method
//! or sweep point: metrics as mean ± std over seeds, stage times, peak memory, speed-up
//! against the baseline) and the plots under `plots/`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::plot::{write_chart, Chart, Series};
use super::record::{RunRecord, Status, DEPTH_ERROR, OBJECT_DEPTH_ERROR};
use super::runner::BenchMeta;
use super::spread::{self, across_scenes, AcrossScenes};
use super::target::Target;

/// Mean and standard deviation over seeds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Stat {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (0 for one seed).
    pub std: f64,
    /// Values averaged.
    pub n: usize,
}

impl Stat {
    /// The statistic of the finite values, if any.
    pub fn of(values: impl IntoIterator<Item = f64>) -> Option<Stat> {
        let v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        let n = v.len();
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = if n > 1 { v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64 } else { 0.0 };
        Some(Stat { mean, std: var.sqrt(), n })
    }
}

/// One row of a scene's table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// The method, or `<sweep>: <label>`.
    pub variant: String,
    /// The method (the varied one, for a sweep point).
    pub method: String,
    /// The sweep and point, if any.
    pub sweep: Option<(String, String)>,
    /// Seeds with a finished run.
    pub seeds: Vec<u64>,
    /// Metrics by name (`mIoU`, `NV-ARI`, `IoU FG`, `IoU BG`, `PSNR`, `SSIM`).
    pub metrics: BTreeMap<String, Stat>,
    /// Phase seconds by name (`stage1`, `stage2`, `masks`, `total`).
    pub seconds: BTreeMap<String, Stat>,
    /// Seconds per stage-2 step (stage-2 time over its steps).
    #[serde(default)]
    pub stage2_step: Option<Stat>,
    /// Seconds of one view with its mask, and the view's size.
    #[serde(default)]
    pub view: Option<(Stat, [u32; 2])>,
    /// Largest peak resident memory over seeds, MiB.
    pub peak_rss_mib: Option<f64>,
    /// CPU time over wall time of the run processes: the cores kept busy.
    #[serde(default)]
    pub cores_busy: Option<Stat>,
    /// Share of the machine's CPU time its hypervisor took for other guests (0 = not shared).
    #[serde(default)]
    pub cpu_stolen: Option<Stat>,
    /// The baseline row's total time over this row's (above 1: faster than the baseline).
    pub speedup: Option<f64>,
    /// Wall seconds to the benchmark's target quality, over the seeds that reached it (see
    /// [`super::target`]).
    #[serde(default)]
    pub to_target: Option<Stat>,
    /// Finished seeds that never reached the target.
    #[serde(default)]
    pub target_missed: usize,
    /// Runs that failed or were skipped, with why.
    pub problems: Vec<String>,
}

/// Every row of one scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneTable {
    /// Scene name.
    pub scene: String,
    /// Rows: methods first, then sweep points in order.
    pub rows: Vec<Row>,
}

/// `report.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// What the folder holds.
    pub meta: BenchMeta,
    /// Commits the runs were made at.
    pub commits: Vec<String>,
    /// Programs (binary hashes) that ran them, where the records name one.
    #[serde(default)]
    pub programs: Vec<String>,
    /// Machines (CPU, cores, memory) the runs ran on.
    pub machines: Vec<String>,
    /// When the last run finished (UTC).
    pub finished: String,
    /// Runs finished, failed and skipped.
    pub counts: BTreeMap<String, usize>,
    /// What the folder's runs cost on their machines.
    #[serde(default)]
    pub wall: WallTime,
    /// One table per scene.
    pub scenes: Vec<SceneTable>,
    /// Each method's mean and worst over scenes.
    #[serde(default)]
    pub across: Vec<AcrossScenes>,
}

/// The wall time a result folder's runs took: what one machine running the profile from
/// scratch spends on them (the shards of a merged folder add up).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WallTime {
    /// Seconds summed over the runs that carry a time.
    pub seconds: f64,
    /// Runs that carry one (they ran, or failed, here or in a merged shard).
    pub runs: usize,
    /// Finished or failed runs without one: results reused from a run with the same config,
    /// which cost nothing, and records written by builds that kept no time.
    pub untimed: usize,
}

impl WallTime {
    fn of(records: &[RunRecord]) -> WallTime {
        let mut w = WallTime::default();
        for r in records.iter().filter(|r| r.status != Status::Skipped) {
            match r.wall_seconds {
                Some(s) if s.is_finite() => {
                    w.seconds += s;
                    w.runs += 1;
                }
                _ => w.untimed += 1,
            }
        }
        w
    }

    /// `Wall time of the runs: 1 h 42 min over 57 runs ...` for the report's header.
    fn describe(&self) -> String {
        let minutes = (self.seconds / 60.0).round() as u64;
        let time = if minutes >= 60 {
            format!("{} h {:02} min", minutes / 60, minutes % 60)
        } else {
            format!("{minutes} min")
        };
        let mut line = format!(
            "Wall time of the runs: {time} over {} runs (each run's process from its config to its outcome, \
             learning-curve evaluations and the timed view included)",
            self.runs
        );
        if self.untimed > 0 {
            line.push_str(&format!(
                "; {} more carry no time (a result reused from a run with the same config, or a record of a build \
                 that kept none)",
                self.untimed
            ));
        }
        line + ".\n"
    }
}

/// Builds the report of `records`.
pub fn build(records: &[RunRecord], meta: &BenchMeta) -> Report {
    let mut by_scene: BTreeMap<&str, Vec<&RunRecord>> = BTreeMap::new();
    for r in records {
        by_scene.entry(&r.key.scene).or_default().push(r);
    }
    let scenes: Vec<SceneTable> = by_scene.into_iter().map(|(scene, runs)| scene_table(scene, &runs, meta)).collect();
    let across = across_scenes(&scenes);
    let mut counts = BTreeMap::new();
    for r in records {
        let key = match r.status {
            Status::Done => "done",
            Status::Failed => "failed",
            Status::Skipped => "skipped",
        };
        *counts.entry(key.to_string()).or_insert(0) += 1;
    }
    // Sorted and deduplicated, from the runs that ran (a skipped run has none of these).
    let distinct = |f: &dyn Fn(&RunRecord) -> Option<String>| {
        let mut v: Vec<String> = records.iter().filter(|r| r.status != Status::Skipped).filter_map(f).collect();
        v.sort();
        v.dedup();
        v
    };
    Report {
        meta: meta.clone(),
        commits: distinct(&|r| Some(r.commit.clone())),
        programs: distinct(&|r| r.program.clone()),
        machines: distinct(&|r| {
            Some(format!("{} ({} cores, {} GiB)", r.machine.cpu, r.machine.cores, r.machine.memory_gib))
        }),
        finished: records
            .iter()
            .filter(|r| r.status == Status::Done)
            .map(|r| r.finished.clone())
            .max()
            .unwrap_or_default(),
        counts,
        wall: WallTime::of(records),
        scenes,
        across,
    }
}

fn scene_table(scene: &str, runs: &[&RunRecord], meta: &BenchMeta) -> SceneTable {
    let baseline = meta.baseline.as_str();
    // Methods first (baseline leading), then sweep points in sweep order.
    let mut variants: Vec<(&str, Option<(&str, usize)>)> = Vec::new();
    for r in runs {
        let key = (r.key.variant.as_str(), r.key.sweep.as_ref().map(|s| (s.name.as_str(), s.index)));
        if !variants.contains(&key) {
            variants.push(key);
        }
    }
    variants
        .sort_by_key(|(v, s)| (s.is_some(), *v != baseline, s.map(|s| s.0.to_string()), s.map(|s| s.1), v.to_string()));
    let mut rows: Vec<Row> = variants
        .iter()
        .map(|(variant, _)| {
            let mine: Vec<&&RunRecord> = runs.iter().filter(|r| r.key.variant == *variant).collect();
            row(variant, &mine, meta.target.as_ref())
        })
        .collect();
    let base_total = rows.iter().find(|r| r.variant == baseline).and_then(|r| r.seconds.get("total")).map(|s| s.mean);
    for r in &mut rows {
        r.speedup = match (base_total, r.seconds.get("total")) {
            (Some(b), Some(t)) if t.mean > 0.0 => Some(b / t.mean),
            _ => None,
        };
    }
    SceneTable { scene: scene.to_string(), rows }
}

fn row(variant: &str, runs: &[&&RunRecord], target: Option<&Target>) -> Row {
    let done: Vec<&RunRecord> = runs.iter().filter(|r| r.status == Status::Done).map(|r| **r).collect();
    let outcomes: Vec<_> = done.iter().filter_map(|r| r.outcome.as_ref()).collect();
    let mut metrics = BTreeMap::new();
    for (i, (name, _)) in super::record::Metrics::default().named().iter().enumerate() {
        if let Some(s) = Stat::of(outcomes.iter().filter_map(|o| o.metrics.named()[i].1)) {
            metrics.insert(name.to_string(), s);
        }
    }
    let mut seconds = BTreeMap::new();
    for (i, (name, _)) in super::record::Timing::default().named().iter().enumerate() {
        if let Some(s) = Stat::of(outcomes.iter().map(|o| o.timing.named()[i].1)) {
            seconds.insert(name.to_string(), s);
        }
    }
    let problems = runs
        .iter()
        .filter(|r| r.status != Status::Done)
        .map(|r| {
            let why = r.error.as_deref().unwrap_or("").lines().next().unwrap_or("").to_string();
            format!("seed {}: {} ({why})", r.key.seed, if r.status == Status::Failed { "failed" } else { "skipped" })
        })
        .collect();
    let times: Vec<Option<f64>> = target.map_or(Vec::new(), |t| outcomes.iter().map(|o| t.time_to(o)).collect());
    let first = runs[0];
    Row {
        variant: variant.to_string(),
        method: first.key.method.clone(),
        sweep: first.key.sweep.as_ref().map(|s| (s.name.clone(), s.label.clone())),
        seeds: done.iter().map(|r| r.key.seed).collect(),
        metrics,
        seconds,
        stage2_step: Stat::of(
            outcomes.iter().filter_map(|o| o.stage2_steps.filter(|&n| n > 0).map(|n| o.timing.stage2 / n as f64)),
        ),
        view: Stat::of(outcomes.iter().filter_map(|o| o.view.as_ref().map(|v| v.seconds)))
            .zip(outcomes.iter().find_map(|o| o.view.as_ref().map(|v| [v.width, v.height]))),
        peak_rss_mib: outcomes
            .iter()
            .filter_map(|o| o.peak_rss_mib)
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v)))),
        cores_busy: Stat::of(outcomes.iter().filter_map(|o| {
            let wall = o.timing.total + o.timing.curve_eval;
            o.cpu_seconds.filter(|_| wall > 0.0).map(|c| c / wall)
        })),
        cpu_stolen: Stat::of(outcomes.iter().filter_map(|o| o.cpu_stolen)),
        speedup: None,
        to_target: Stat::of(times.iter().flatten().copied()),
        target_missed: times.iter().filter(|t| t.is_none()).count(),
        problems,
    }
}

/// A view's time with its size: `0.93 (504×378)`.
fn view_text(view: Option<&(Stat, [u32; 2])>) -> String {
    view.map_or("-".into(), |(s, [w, h])| format!("{} ({w}×{h})", fmt_stat(Some(s), 2)))
}

/// A share as a whole percentage (the mean over seeds).
fn percent(s: Option<&Stat>) -> String {
    s.map_or("-".into(), |s| format!("{:.0}%", 100.0 * s.mean))
}

fn fmt_stat(s: Option<&Stat>, digits: usize) -> String {
    match s {
        None => "-".into(),
        Some(s) if s.n > 1 => format!("{:.digits$} ± {:.digits$}", s.mean, s.std),
        Some(s) => format!("{:.digits$}", s.mean),
    }
}

impl Report {
    /// `, program <hash>` (or `programs …`) for records that name the binary that ran them.
    fn programs_note(&self) -> String {
        match self.programs.len() {
            0 => String::new(),
            1 => format!(", program {}", self.programs[0]),
            _ => format!(", programs {}", self.programs.join(", ")),
        }
    }

    /// The Markdown report.
    pub fn to_markdown(&self) -> String {
        let mut md = format!(
            "# Benchmark `{}`, profile `{}`\n\nWritten by `sos bench`. Last run finished {} UTC; commit {}{}; {}.\n",
            self.meta.file,
            self.meta.profile,
            self.finished,
            self.commits.join(", "),
            self.programs_note(),
            self.machines.join("; ")
        );
        md.push_str(&format!(
            "Runs: {}. Metrics are means over held-out views, then mean ± std over seeds; times in seconds \
             (`total` is the run's time to its result, learning-curve evaluations excluded); speed-up is \
             against the `{}` row of the same scene; view s is one view with its mask at the size shown (the \
             median of three, kept off the run's time); cores busy is the run's CPU time over its wall time \
             (well below the core count: serial phases, or a machine shared with other work); CPU stolen is \
             the share of the machine's CPU time its hypervisor gave to other guests during the run (above \
             a few percent, the times are not those of an idle machine); depth err, where a scene knows its \
             depth, is the median over a view's surface pixels of the rendered depth's relative error (capped \
             at 1; an empty ray counts 1), then the mean over views; object depth err the same over the \
             ground-truth object's pixels.\n",
            self.counts.iter().map(|(k, v)| format!("{v} {k}")).collect::<Vec<_>>().join(", "),
            self.meta.baseline
        ));
        if self.wall.runs > 0 {
            md.push_str(&self.wall.describe());
        }
        if let Some(t) = &self.meta.target {
            md.push_str(&format!(
                "To target is the wall time until the run's held-out masks met {}: setup, stage 1, stage 2 up to \
                 the first learning-curve evaluation that met it, and the run's mask time (an upper bound, as \
                 fine as the curve's points; `never` when no evaluation met it).\n",
                t.describe()
            ));
        }
        let with_target = self.meta.target.is_some();
        for scene in &self.scenes {
            md.push_str(&format!("\n## {}\n\n", scene.scene));
            md.push_str(&table(&scene.rows, true, with_target));
        }
        md.push_str(&spread::markdown(&self.across));
        md.push_str("\n## Plots\n\nIn `plots/`: `miou_vs_time` and `psnr_vs_stage1_time` (each method's mean over scenes, with the Pareto front; `_by_scene`: every scene's methods), per scene `<scene>_miou_vs_time` with the Pareto front, per sweep `sweep_<name>` (mIoU) and `sweep_<name>_time`.\n");
        md
    }

    /// The compact table of every scene's rows (for the README).
    pub fn summary_markdown(&self) -> String {
        let mut md = String::from("| scene | method | mIoU | NV-ARI | PSNR dB | stage 1 s | stage 2 s | total s | view s | peak MiB | cores busy | CPU stolen |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
        for scene in &self.scenes {
            for r in &scene.rows {
                let m = |k: &str, d| fmt_stat(r.metrics.get(k), d);
                let s = |k: &str| fmt_stat(r.seconds.get(k), 1);
                let status = if r.seeds.is_empty() { format!(" ({})", r.problems.join("; ")) } else { String::new() };
                md.push_str(&format!(
                    "| {} | {}{status} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
                    scene.scene,
                    r.variant,
                    m("mIoU", 3),
                    m("NV-ARI", 3),
                    m("PSNR", 2),
                    s("stage1"),
                    s("stage2"),
                    s("total"),
                    view_text(r.view.as_ref()),
                    r.peak_rss_mib.map_or("-".into(), |p| format!("{p:.0}")),
                    fmt_stat(r.cores_busy.as_ref(), 2),
                    percent(r.cpu_stolen.as_ref())
                ));
            }
        }
        md
    }
}

/// A row's time to the target: the mean over the seeds that reached it, and how many did not.
fn to_target_text(r: &Row) -> String {
    match (&r.to_target, r.target_missed) {
        (None, 0) => "-".into(),
        (None, _) => "never".into(),
        (Some(s), 0) => fmt_stat(Some(s), 1),
        (Some(s), missed) => format!("{} ({missed} never)", fmt_stat(Some(s), 1)),
    }
}

/// One scene's rows as a Markdown table (with the time-to-target column when the benchmark
/// names a target).
fn table(rows: &[Row], with_problems: bool, with_target: bool) -> String {
    let target_head = if with_target { " to target s |" } else { "" };
    let target_rule = if with_target { "---|" } else { "" };
    // The depth column only where a run measured it (scenes that know their depth).
    let with_depth = rows.iter().any(|r| r.metrics.contains_key(DEPTH_ERROR));
    let (depth_head, depth_rule) = if with_depth { (" depth err | object depth err |", "---|---|") } else { ("", "") };
    let mut md = format!(
        "| method | seeds | mIoU | NV-ARI | IoU FG | IoU BG | PSNR dB | SSIM |{depth_head} stage 1 s | stage 2 s | stage-2 step s | masks s | total s |{target_head} speed-up | view s | peak MiB | cores busy | CPU stolen |\n\
         |---|---|---|---|---|---|---|---|{depth_rule}---|---|---|---|---|{target_rule}---|---|---|---|---|\n",
    );
    let mut notes = Vec::new();
    for r in rows {
        let m = |k: &str, d| fmt_stat(r.metrics.get(k), d);
        let s = |k: &str| fmt_stat(r.seconds.get(k), 1);
        let target_cell = if with_target { format!(" {} |", to_target_text(r)) } else { String::new() };
        let depth_cell =
            if with_depth { format!(" {} | {} |", m(DEPTH_ERROR, 3), m(OBJECT_DEPTH_ERROR, 3)) } else { String::new() };
        md.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |{depth_cell} {} | {} | {} | {} | {} |{target_cell} {} | {} | {} | {} | {} |\n",
            r.variant,
            r.seeds.len(),
            m("mIoU", 3),
            m("NV-ARI", 3),
            m("IoU FG", 3),
            m("IoU BG", 3),
            m("PSNR", 2),
            m("SSIM", 3),
            s("stage1"),
            s("stage2"),
            fmt_stat(r.stage2_step.as_ref(), 3),
            s("masks"),
            s("total"),
            r.speedup.map_or("-".into(), |x| format!("{x:.2}×")),
            view_text(r.view.as_ref()),
            r.peak_rss_mib.map_or("-".into(), |p| format!("{p:.0}")),
            fmt_stat(r.cores_busy.as_ref(), 2),
            percent(r.cpu_stolen.as_ref())
        ));
        if with_problems {
            notes.extend(r.problems.iter().map(|p| format!("- `{}`, {p}\n", r.variant)));
        }
    }
    if !notes.is_empty() {
        md.push('\n');
        md.extend(notes);
    }
    md
}

/// Writes `report.json`, `report.md` and the plots of `records` into `out`.
pub fn write(out: &Path, records: &[RunRecord], meta: &BenchMeta) -> anyhow::Result<Report> {
    let report = build(records, meta);
    crate::commands::write_json(&out.join("report.json"), &report)?;
    let md = out.join("report.md");
    crate::commands::write_atomic(&md, &report.to_markdown())?;
    write_plots(out, &report, records)?;
    spread::copy_worst_masks(out, &report.across, |scene, method| {
        records
            .iter()
            .filter(|r| r.status == Status::Done && r.key.sweep.is_none())
            .filter(|r| r.key.scene == scene && r.key.variant == method)
            .min_by_key(|r| r.key.seed)
            .map(|r| out.join(super::runner::WORK_DIR).join(&r.key.id))
    })?;
    Ok(report)
}

/// Mean (run time, metric) of a row.
fn point(r: &Row, time: &str, metric: &str) -> Option<(f64, f64)> {
    Some((r.seconds.get(time)?.mean, r.metrics.get(metric)?.mean))
}

fn write_plots(out: &Path, report: &Report, records: &[RunRecord]) -> anyhow::Result<()> {
    let dir = out.join("plots");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    for (stem, time, metric, x_label, y_label, what) in [
        ("miou_vs_time", "total", "mIoU", "run time (s)", "mIoU", "mIoU against run time"),
        (
            "psnr_vs_stage1_time",
            "stage1",
            "PSNR",
            "stage-1 time (s)",
            "held-out PSNR (dB)",
            "PSNR against stage-1 time",
        ),
    ] {
        // Each method's mean over the scenes it finished, the Pareto front marked.
        let mut per_method: BTreeMap<&str, Vec<(f64, f64)>> = BTreeMap::new();
        // Every scene's method rows: one series per scene.
        let mut per_scene: Vec<Series> = Vec::new();
        for scene in &report.scenes {
            let rows = scene.rows.iter().filter(|r| r.sweep.is_none());
            let points: Vec<(f64, f64)> = rows
                .filter_map(|r| {
                    let p = point(r, time, metric)?;
                    per_method.entry(&r.method).or_default().push(p);
                    Some(p)
                })
                .collect();
            per_scene.push(Series { label: scene.scene.clone(), points });
        }
        let methods = per_method
            .into_iter()
            .map(|(m, ps)| {
                let n = ps.len() as f64;
                let mean = ps.iter().fold((0.0, 0.0), |(x, y), p| (x + p.0 / n, y + p.1 / n));
                Series { label: m.to_string(), points: vec![mean] }
            })
            .collect();
        let chart = |title: String, series: Vec<Series>, pareto: bool| Chart {
            title,
            x_label: x_label.into(),
            y_label: y_label.into(),
            x_categories: None,
            series,
            lines: false,
            pareto,
        };
        write_chart(&chart(format!("{what}: each method's mean over scenes"), methods, true), &dir.join(stem))?;
        write_chart(&chart(format!("{what}: every scene"), per_scene, false), &dir.join(format!("{stem}_by_scene")))?;
    }
    // Per scene: a point per row, the Pareto front of time against mIoU marked.
    for scene in &report.scenes {
        let series: Vec<Series> = scene
            .rows
            .iter()
            .filter_map(|r| point(r, "total", "mIoU").map(|p| Series { label: r.variant.clone(), points: vec![p] }))
            .collect();
        if series.is_empty() {
            continue;
        }
        let chart = Chart {
            title: format!("{}: mIoU against run time", scene.scene),
            x_label: "run time (s)".into(),
            y_label: "mIoU".into(),
            x_categories: None,
            series,
            lines: false,
            pareto: true,
        };
        write_chart(&chart, &dir.join(format!("{}_miou_vs_time", scene.scene)))?;
    }
    // Per sweep: the metric and the time against the swept value, a series per scene.
    let mut sweeps: BTreeMap<&str, Vec<&RunRecord>> = BTreeMap::new();
    for r in records.iter().filter(|r| r.status == Status::Done) {
        if let Some(s) = &r.key.sweep {
            sweeps.entry(&s.name).or_default().push(r);
        }
    }
    for (name, runs) in sweeps {
        let numeric = runs.iter().all(|r| r.key.sweep.as_ref().and_then(|s| s.x).is_some());
        let mut labels: Vec<(usize, String)> =
            runs.iter().filter_map(|r| r.key.sweep.as_ref().map(|s| (s.index, s.label.clone()))).collect();
        labels.sort();
        labels.dedup();
        for (suffix, y_label, get) in [
            (
                "",
                "mIoU",
                (|r: &RunRecord| r.outcome.as_ref().and_then(|o| o.metrics.miou)) as fn(&RunRecord) -> Option<f64>,
            ),
            ("_time", "run time (s)", |r: &RunRecord| r.outcome.as_ref().map(|o| o.timing.total)),
        ] {
            let mut by_scene: BTreeMap<&str, BTreeMap<usize, Vec<f64>>> = BTreeMap::new();
            for r in &runs {
                let s = r.key.sweep.as_ref().expect("sweep runs");
                if let Some(y) = get(r) {
                    by_scene.entry(&r.key.scene).or_default().entry(s.index).or_default().push(y);
                }
            }
            let x_of = |index: usize| -> f64 {
                if numeric {
                    runs.iter()
                        .find_map(|r| r.key.sweep.as_ref().filter(|s| s.index == index).and_then(|s| s.x))
                        .unwrap_or(index as f64)
                } else {
                    labels.iter().position(|(i, _)| *i == index).unwrap_or(0) as f64
                }
            };
            let series = by_scene
                .into_iter()
                .map(|(scene, points)| Series {
                    label: scene.to_string(),
                    points: points
                        .into_iter()
                        .map(|(i, ys)| (x_of(i), ys.iter().sum::<f64>() / ys.len() as f64))
                        .collect(),
                })
                .collect();
            let chart = Chart {
                title: format!("sweep {name}: {y_label}"),
                x_label: if numeric {
                    labels.first().map_or(String::new(), |_| "swept value".into())
                } else {
                    String::new()
                },
                y_label: y_label.into(),
                x_categories: (!numeric).then(|| labels.iter().map(|(_, l)| l.clone()).collect()),
                series,
                lines: true,
                pareto: false,
            };
            write_chart(&chart, &dir.join(format!("sweep_{name}{suffix}")))?;
        }
    }
    Ok(())
}

/// Replaces the block between `<!-- sos-bench:<profile>:begin -->` and its `end` marker in
/// `readme` with the report's summary table and its mIoU-against-time plot.
pub fn update_readme(readme: &Path, report: &Report, out: &Path) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(readme).with_context(|| format!("reading {}", readme.display()))?;
    let begin = format!("<!-- sos-bench:{}:begin -->", report.meta.profile);
    let end = format!("<!-- sos-bench:{}:end -->", report.meta.profile);
    let (Some(b), Some(e)) = (text.find(&begin), text.find(&end)) else {
        anyhow::bail!(
            "{} has no `{begin}` ... `{end}` block to fill; add the two lines where the table goes",
            readme.display()
        );
    };
    let base = match readme.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let plot = relative(&out.join("plots").join("miou_vs_time_by_scene.svg"), &base);
    let block = format!(
        "{begin}\n_Written by `sos bench --profile {}`; last run {} UTC, commit {}, {}._\n\n{}\n![mIoU against run time]({})\n",
        report.meta.profile,
        report.finished,
        report.commits.join(", "),
        report.machines.join("; "),
        report.summary_markdown(),
        plot.display()
    );
    let updated = format!("{}{block}{}", &text[..b], &text[e..]);
    crate::commands::write_atomic(readme, &updated)
}

/// `path` relative to `base` when it lies under it.
fn relative(path: &Path, base: &Path) -> PathBuf {
    let abs = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let (p, b) = (abs(path), abs(base));
    p.strip_prefix(&b).map(Path::to_path_buf).unwrap_or(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_skip_non_finite_values() {
        let s = Stat::of([1.0, 3.0, f64::NAN]).unwrap();
        assert_eq!((s.mean, s.n), (2.0, 2));
        assert!((s.std - 2f64.sqrt()).abs() < 1e-12);
        assert!(Stat::of([f64::INFINITY]).is_none());
        assert_eq!(Stat::of([5.0]).unwrap().std, 0.0);
    }

    fn record(id: &str, status: &str, wall: Option<f64>) -> RunRecord {
        serde_json::from_value(serde_json::json!({
            "id": id, "scene": "s", "method": "m", "variant": "m", "sweep": null, "seed": 0,
            "hash": "h", "status": status, "error": null, "config": "", "commit": "c",
            "machine": { "cpu": "cpu", "cores": 2, "memory_gib": 1.0, "host": "vm" },
            "finished": "2026-01-01 00:00", "outcome": null, "wall_seconds": wall,
        }))
        .unwrap()
    }

    fn table_row(variant: &str, metrics: serde_json::Value) -> Row {
        serde_json::from_value(serde_json::json!({
            "variant": variant, "method": variant, "sweep": null, "seeds": [0], "metrics": metrics,
            "seconds": {}, "peak_rss_mib": null, "speedup": null, "problems": [],
        }))
        .unwrap()
    }

    #[test]
    fn depth_columns_appear_only_where_a_run_measured_depth() {
        let stat = |mean: f64| serde_json::json!({ "mean": mean, "std": 0.0, "n": 1 });
        let plain = table_row("a", serde_json::json!({ "mIoU": stat(0.9) }));
        let md = table(std::slice::from_ref(&plain), false, false);
        assert!(!md.contains("depth err"), "{md}");
        let measured = table_row(
            "b",
            serde_json::json!({ "mIoU": stat(0.8), "depth err": stat(0.25), "object depth err": stat(0.5) }),
        );
        let md = table(&[plain, measured], false, false);
        let lines: Vec<&str> = md.lines().collect();
        assert!(lines[0].contains("| SSIM | depth err | object depth err | stage 1 s |"), "{md}");
        // Every line has the header's cells; the row without depth shows dashes.
        let cells = |l: &str| l.matches('|').count();
        assert!(lines[..4].iter().all(|l| cells(l) == cells(lines[0])), "{md}");
        assert!(lines[2].contains("| - | - |") && lines[3].contains("| 0.250 | 0.500 |"), "{md}");
    }

    #[test]
    fn the_wall_time_adds_up_the_runs_that_carry_one() {
        let records = [
            record("a", "done", Some(3000.0)),
            record("b", "failed", Some(660.0)),
            // Reused another's result, and an older record: no time.
            record("c", "done", None),
            record("d", "done", None),
            // Skipped runs cost nothing and count nowhere.
            record("e", "skipped", None),
        ];
        let w = WallTime::of(&records);
        assert_eq!((w.seconds, w.runs, w.untimed), (3660.0, 2, 2));
        let line = w.describe();
        assert!(line.starts_with("Wall time of the runs: 1 h 01 min over 2 runs"), "{line}");
        assert!(line.contains("2 more carry no time"), "{line}");
    }
}
