//! `sos bench merge` (result folders of many machines into one report) and `sos bench diff`
//! (two result folders, metric for metric).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use super::record::{load_all, RunRecord, Status};
use super::report;
use super::runner::BenchMeta;

/// Merges the runs of `dirs` into `out` and writes its report; returns it with the ids of the
/// failed runs. A run present in two folders must have one config hash; the first folder's
/// copy is kept.
pub fn merge(dirs: &[PathBuf], out: &Path) -> anyhow::Result<(report::Report, Vec<String>)> {
    let Some(first) = dirs.first() else {
        bail!("`sos bench merge` needs at least one result folder");
    };
    let mut meta = BenchMeta::load(first)?;
    let mut merged: BTreeMap<String, (RunRecord, &Path)> = BTreeMap::new();
    for dir in dirs {
        let other = BenchMeta::load(dir)?;
        // Machines may name the file by different paths: its name and the profile must agree.
        let name = |m: &BenchMeta| Path::new(&m.file).file_name().map(|n| n.to_os_string());
        if name(&other) != name(&meta) || other.profile != meta.profile {
            bail!(
                "{} holds profile `{}` of {} but {} holds profile `{}` of {}: merge folders of one benchmark",
                dir.display(),
                other.profile,
                other.file,
                first.display(),
                meta.profile,
                meta.file
            );
        }
        for r in load_all(dir)? {
            match merged.get(&r.key.id) {
                Some((kept, from)) if kept.hash != r.hash => bail!(
                    "run `{}` has config hash {} in {} but {} in {}: the folders come from different configs",
                    r.key.id,
                    &kept.hash[..12],
                    from.display(),
                    &r.hash[..12],
                    dir.display()
                ),
                Some(_) => {}
                None => {
                    merged.insert(r.key.id.clone(), (r, dir));
                }
            }
        }
    }
    let runs_dir = out.join("runs");
    std::fs::create_dir_all(&runs_dir).with_context(|| format!("creating {}", runs_dir.display()))?;
    let records: Vec<RunRecord> = merged.into_values().map(|(r, _)| r).collect();
    for r in &records {
        r.save(&runs_dir.join(format!("{}.json", r.key.id)))?;
    }
    meta.shard = None;
    crate::commands::write_json(&out.join("bench.json"), &meta)?;
    if records.len() < meta.matrix_runs {
        eprintln!("note: {} of the matrix's {} runs are present", records.len(), meta.matrix_runs);
    }
    let failed = records.iter().filter(|r| r.status == Status::Failed).map(|r| r.key.id.clone()).collect();
    Ok((report::write(out, &records, &meta)?, failed))
}

/// Compares the runs of two result folders: the same runs, statuses, config hashes and
/// metrics (exactly; runs are deterministic per seed). Errors list every difference.
pub fn diff(a: &Path, b: &Path) -> anyhow::Result<()> {
    let (ra, rb) = (load_all(a)?, load_all(b)?);
    let index = |rs: &[RunRecord]| rs.iter().map(|r| (r.key.id.clone(), r.clone())).collect::<BTreeMap<_, _>>();
    let (ia, ib) = (index(&ra), index(&rb));
    let mut differences = Vec::new();
    for id in ia.keys().chain(ib.keys()).collect::<std::collections::BTreeSet<_>>() {
        match (ia.get(id), ib.get(id)) {
            (Some(x), Some(y)) => {
                if x.hash != y.hash {
                    differences.push(format!("{id}: config hash {} vs {}", &x.hash[..12], &y.hash[..12]));
                } else if x.status != y.status {
                    differences.push(format!("{id}: status {:?} vs {:?}", x.status, y.status));
                } else if let (Some(ox), Some(oy)) = (&x.outcome, &y.outcome) {
                    for ((name, vx), (_, vy)) in ox.metrics.named().iter().zip(oy.metrics.named()) {
                        if *vx != vy {
                            differences.push(format!("{id}: {name} {vx:?} vs {vy:?}"));
                        }
                    }
                }
            }
            (Some(_), None) => differences.push(format!("{id}: only in {}", a.display())),
            (None, _) => differences.push(format!("{id}: only in {}", b.display())),
        }
    }
    if differences.is_empty() {
        say!("{} runs, identical metrics in {} and {}", ia.len(), a.display(), b.display())?;
        Ok(())
    } else {
        bail!(
            "{} differences between {} and {}:\n{}",
            differences.len(),
            a.display(),
            b.display(),
            differences.join("\n")
        )
    }
}
