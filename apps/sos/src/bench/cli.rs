//! The `sos bench` command line.

use std::path::PathBuf;

use anyhow::{anyhow, bail};
use clap::{Args, Subcommand};

pub use super::exec::ExecArgs;
use super::matrix::{plan, shard, PlannedRun};
use super::runner::{run_all, BenchMeta, Reuse};
use super::spec::BenchFile;
use super::{merge, record, report};

/// `sos bench`.
#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct BenchArgs {
    #[command(subcommand)]
    action: Option<BenchAction>,
    /// Benchmark file (e.g. `benchmarks/run_all.toml`).
    #[arg(required = true)]
    file: Option<PathBuf>,
    /// Profile to run (default: the file's `bench.default_profile`, else everything).
    #[arg(long)]
    profile: Option<String>,
    /// Result folder (default: the file's `bench.out`/`<profile>`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Run only slice I of N of the matrix (`0/2`, `1/2`), e.g. one task of a job array.
    #[arg(long, value_name = "I/N")]
    shard: Option<String>,
    /// Also write the summary table and plot into this README (between its
    /// `<!-- sos-bench:<profile>:begin/end -->` markers).
    #[arg(long)]
    readme: Option<PathBuf>,
    /// Print the matrix (run ids, skips) and stop.
    #[arg(long)]
    list: bool,
    /// Every run trains its own stage 1, even where an earlier run with the same stage-1
    /// settings could share its (e.g. to time each run whole, or to check that sharing changes
    /// no result).
    #[arg(long)]
    own_stage1: bool,
    /// Run this method's runs again even where a finished result with the same config exists
    /// (repeatable), e.g. to time them beside a new row in one invocation; each starts from its
    /// previous result's stage 1 when that result kept its checkpoint (not with `--own-stage1`).
    #[arg(long, value_name = "METHOD")]
    rerun: Vec<String>,
}

#[derive(Debug, Subcommand)]
enum BenchAction {
    /// Merge result folders (e.g. of sharded runs) into one folder and write its report (exit
    /// code 3 when some of the runs failed, as for the matrix run in one go).
    Merge {
        /// Result folders.
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// The merged folder.
        #[arg(long)]
        out: PathBuf,
        /// Also fill this README's block for the profile.
        #[arg(long)]
        readme: Option<PathBuf>,
    },
    /// Compare the metrics of every run of two result folders (exit code 2 when they differ).
    Diff {
        /// First result folder.
        a: PathBuf,
        /// Second result folder.
        b: PathBuf,
    },
}

/// Runs `sos bench`.
pub fn run(args: BenchArgs, progress: bool) -> anyhow::Result<()> {
    match args.action {
        Some(BenchAction::Merge { dirs, out, readme }) => {
            let (report, failed) = merge::merge(&dirs, &out)?;
            say!("merged {} folders into {}", dirs.len(), out.join("report.md").display())?;
            if let Some(readme) = readme {
                report::update_readme(&readme, &report, &out)?;
            }
            // The merged matrix answers as one run of it would.
            if failed.is_empty() {
                Ok(())
            } else {
                Err(RunsFailed { ids: failed, out }.into())
            }
        }
        Some(BenchAction::Diff { a, b }) => merge::diff(&a, &b),
        None => {
            let file_path = args
                .file
                .clone()
                .ok_or_else(|| anyhow!("name a benchmark file, e.g. `sos bench benchmarks/run_all.toml`"))?;
            run_file(&file_path, &args, progress)
        }
    }
}

fn parse_shard(text: &str) -> anyhow::Result<(usize, usize)> {
    let parsed = text.split_once('/').and_then(|(i, n)| Some((i.trim().parse().ok()?, n.trim().parse().ok()?)));
    match parsed {
        Some((i, n)) if n > 0 && i < n => Ok((i, n)),
        _ => bail!("`--shard {text}`: write I/N with 0 <= I < N, e.g. `--shard 0/2`"),
    }
}

fn run_file(file_path: &std::path::Path, args: &BenchArgs, progress: bool) -> anyhow::Result<()> {
    let (profile, shard_arg) = (args.profile.as_deref(), args.shard.as_deref());
    let (out, readme, list) = (args.out.clone(), args.readme.clone(), args.list);
    let shard_of = shard_arg.map(parse_shard).transpose()?;
    let file = BenchFile::load(file_path)?;
    let profile_name =
        profile.map(str::to_owned).or_else(|| file.bench.default_profile.clone()).unwrap_or_else(|| "all".into());
    let out = out.unwrap_or_else(|| file.dir().join(&file.bench.out).join(&profile_name));
    // Generated scenes are named by absolute path in the run configs, whose relative paths
    // resolve against the scene config's folder, not the working directory.
    let out = std::path::absolute(&out).map_err(|e| anyhow!("`--out {}`: {e}", out.display()))?;
    let matrix = plan(&file, profile, &out)?;
    let total = matrix.runs.len();
    let curve_points = matrix.curve_points;
    let runs = match shard_of {
        Some((i, n)) => shard(matrix.runs, i, n),
        None => matrix.runs,
    };
    let skips = runs.iter().filter(|r| r.skip.is_some()).count();
    eprintln!(
        "benchmark {}, profile `{}`: {} runs{} ({} skipped here), results in {}",
        file_path.display(),
        matrix.profile,
        runs.len(),
        shard_arg.map_or(String::new(), |s| format!(" (shard {s} of {total})")),
        skips,
        out.display()
    );
    if list {
        for r in &runs {
            say!(
                "{}  {}{}",
                r.key.id,
                &r.hash[..12],
                r.skip.as_ref().map_or(String::new(), |s| format!("  skipped: {s}"))
            )?;
        }
        let (to_run, stage1s) = stage1_count(&runs, !args.own_stage1);
        say!(
            "{to_run} runs to run here, {stage1s} of them with a stage 1 of their own (the others share one) \
             in a fresh result folder"
        )?;
        return Ok(());
    }
    let meta = BenchMeta {
        file: file_path.display().to_string(),
        profile: matrix.profile.clone(),
        baseline: file.bench.baseline.clone(),
        shard: shard_arg.map(str::to_owned),
        matrix_runs: total,
        target: file.bench.target,
    };
    let commit = record::commit_of(&file.dir());
    for method in &args.rerun {
        if !file.methods.contains_key(method) {
            bail!("`--rerun {method}`: no method `{method}` in {}", file_path.display());
        }
    }
    let reuse = Reuse { share_stage1: !args.own_stage1, rerun: args.rerun.clone() };
    let tally = run_all(&runs, &out, &meta, curve_points, &commit, progress, &reuse)?;
    say!(
        "{} ran, {} cached, {} skipped, {} failed; report in {}",
        tally.ran,
        tally.cached,
        tally.skipped,
        tally.failed.len(),
        out.join("report.md").display()
    )?;
    if let Some(readme) = readme {
        let records = record::load_all(&out)?;
        let ids: std::collections::BTreeSet<&str> = runs.iter().map(|r| r.key.id.as_str()).collect();
        let mine: Vec<_> = records.into_iter().filter(|r| ids.contains(r.key.id.as_str())).collect();
        report::update_readme(&readme, &report::build(&mine, &meta), &out)?;
        say!("updated {}", readme.display())?;
    }
    if !tally.failed.is_empty() {
        return Err(RunsFailed { ids: tally.failed, out }.into());
    }
    Ok(())
}

/// The matrix ran to its end and its report is written, but some runs failed: the command
/// exits with [`RunsFailed::EXIT_CODE`], which a cluster wrapper can tell apart from bad input
/// or a crash (exit code 2) and still merge after.
#[derive(Debug, thiserror::Error)]
#[error("{} runs failed: {} (their errors are in the report and in {}/logs)", ids.len(), ids.join(", "), out.display())]
pub struct RunsFailed {
    /// Ids of the failed runs.
    pub ids: Vec<String>,
    /// The result folder.
    pub out: PathBuf,
}

impl RunsFailed {
    /// The exit code of a matrix with failed runs.
    pub const EXIT_CODE: u8 = 3;
}

/// Runs that would run (not skipped, no other run with the same config) and how many of them
/// train a stage 1 of their own when run in order into a fresh result folder: the rest leave
/// the field frozen and share the stage 1 of an earlier run with the same stage-1 settings
/// that left it frozen too (as the runner decides, given that every run finishes), unless
/// `share` is off. Another build's run from a run's stage 1 (`stage1_of`) never has its own.
fn stage1_count(runs: &[PlannedRun], share: bool) -> (usize, usize) {
    let mut configs = std::collections::HashSet::new();
    let mut sources = std::collections::HashSet::new();
    let (mut to_run, mut stage1s) = (0, 0);
    for r in runs.iter().filter(|r| r.skip.is_none()) {
        if !configs.insert(r.hash.as_str()) {
            continue;
        }
        to_run += 1;
        if r.stage1_of.is_some() {
            continue;
        }
        let frozen = share && super::runner::leaves_field_frozen(&toml::to_string(&r.config).unwrap_or_default());
        if !(frozen && sources.contains(r.stage1_hash.as_str())) {
            stage1s += 1;
            if frozen {
                sources.insert(r.stage1_hash.as_str());
            }
        }
    }
    (to_run, stage1s)
}
