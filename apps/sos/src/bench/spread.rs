//! How one method or sweep point does across the scenes of a benchmark: mean and worst mIoU
//! and NV-ARI over scenes, the worst scene named, and, for a method, that scene's held-out
//! masks copied next to the report (`worst/<method>/`), so a default is judged on its worst
//! world, not its average, and a swept setting on every scene it ran on.

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};
use sos_core::segment::evaluate::{DEPTH_DIR, EVIDENCE_DIR, MASKS_DIR, OVERLAYS_DIR};

use super::record::DEPTH_ERROR;
use super::report::SceneTable;

/// Sub-folder of the report that holds the worst scene's mask images.
pub const WORST_DIR: &str = "worst";

/// One method over every scene it finished on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AcrossScenes {
    /// The report row: a method, or `<sweep>: <label>` for a sweep point.
    pub method: String,
    /// Scenes with a finished run.
    pub scenes: usize,
    /// Mean over scenes of the per-scene mean mIoU.
    pub miou_mean: f64,
    /// Lowest per-scene mean mIoU, and its scene.
    pub miou_worst: (f64, String),
    /// Mean over scenes of the per-scene mean NV-ARI.
    pub nv_ari_mean: f64,
    /// Lowest per-scene mean NV-ARI, and its scene.
    pub nv_ari_worst: (f64, String),
    /// Mean over scenes of the per-scene depth error, and the largest with its scene: only
    /// when every scene measured it (generated scenes know their depth).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_error: Option<(f64, (f64, String))>,
}

/// One scene a row ran on: its name, mIoU, NV-ARI and (where measured) depth error.
type SceneResult<'a> = (&'a str, f64, f64, Option<f64>);

/// The spread of every method and sweep point over at least two scenes with mIoU and NV-ARI:
/// methods first, then sweep points, each in the order the tables first list them.
pub fn across_scenes(tables: &[SceneTable]) -> Vec<AcrossScenes> {
    let mut variants: Vec<(bool, &str)> = Vec::new();
    for row in tables.iter().flat_map(|t| &t.rows) {
        let key = (row.sweep.is_some(), row.variant.as_str());
        if !variants.contains(&key) {
            variants.push(key);
        }
    }
    // A stable sort keeps each group in its first-listed order.
    variants.sort_by_key(|&(swept, _)| swept);
    variants
        .into_iter()
        .filter_map(|(_, method)| {
            let per_scene: Vec<SceneResult> = tables
                .iter()
                .filter_map(|t| {
                    let row = t.rows.iter().find(|r| r.variant == method)?;
                    let metric = |name: &str| row.metrics.get(name).map(|s| s.mean);
                    Some((t.scene.as_str(), metric("mIoU")?, metric("NV-ARI")?, metric(DEPTH_ERROR)))
                })
                .collect();
            if per_scene.len() < 2 {
                return None;
            }
            let n = per_scene.len() as f64;
            let worst = |pick: fn(&SceneResult) -> f64| {
                let w = per_scene.iter().min_by(|a, b| pick(a).total_cmp(&pick(b))).expect("at least two scenes");
                (pick(w), w.0.to_string())
            };
            Some(AcrossScenes {
                method: method.to_string(),
                scenes: per_scene.len(),
                miou_mean: per_scene.iter().map(|s| s.1).sum::<f64>() / n,
                miou_worst: worst(|s| s.1),
                nv_ari_mean: per_scene.iter().map(|s| s.2).sum::<f64>() / n,
                nv_ari_worst: worst(|s| s.2),
                depth_error: depth_spread(&per_scene),
            })
        })
        .collect()
}

/// The mean and the largest (with its scene) of the scenes' depth errors, when all have one.
fn depth_spread(per_scene: &[SceneResult]) -> Option<(f64, (f64, String))> {
    let known: Vec<(&str, f64)> = per_scene.iter().map(|&(scene, _, _, d)| Some((scene, d?))).collect::<Option<_>>()?;
    let largest = known.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let mean = known.iter().map(|k| k.1).sum::<f64>() / known.len() as f64;
    Some((mean, (largest.1, largest.0.to_string())))
}

/// The Markdown section (empty without a method over several scenes).
pub fn markdown(spread: &[AcrossScenes]) -> String {
    if spread.is_empty() {
        return String::new();
    }
    let mut md = String::from(
        "\n## Across scenes\n\nPer-scene means, then the mean and the worst over scenes. The worst mIoU scene's \
         held-out masks, overlays, mask evidence (clusters, support planes, focus voters) and rendered depth are in \
         `worst/<method>/` for each method.\n\n",
    );
    // Depth columns where some row measured depth on every scene (a row without shows dashes).
    let with_depth = spread.iter().any(|s| s.depth_error.is_some());
    md.push_str("| method | scenes | mIoU mean | mIoU worst | NV-ARI mean | NV-ARI worst |");
    md.push_str(if with_depth { " depth err mean | depth err largest |\n" } else { "\n" });
    md.push_str(if with_depth { "|---|---|---|---|---|---|---|---|\n" } else { "|---|---|---|---|---|---|\n" });
    for s in spread {
        md.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} ({}) | {:.3} | {:.3} ({}) |",
            s.method,
            s.scenes,
            s.miou_mean,
            s.miou_worst.0,
            s.miou_worst.1,
            s.nv_ari_mean,
            s.nv_ari_worst.0,
            s.nv_ari_worst.1
        ));
        if with_depth {
            match &s.depth_error {
                Some((mean, (largest, scene))) => md.push_str(&format!(" {mean:.3} | {largest:.3} ({scene}) |")),
                None => md.push_str(" - | - |"),
            }
        }
        md.push('\n');
    }
    md
}

/// Copies the held-out masks, overlays, mask evidence and rendered depth of each method's
/// worst-mIoU scene (its first seed's run folder under `work_dir`, found by
/// `run_dir_of(scene, method)`) into `<out>/worst/<method>/`, replacing what an earlier report
/// put there.
pub fn copy_worst_masks(
    out: &Path,
    spread: &[AcrossScenes],
    run_dir_of: impl Fn(&str, &str) -> Option<PathBuf>,
) -> anyhow::Result<()> {
    for s in spread {
        let Some(run_dir) = run_dir_of(&s.miou_worst.1, &s.method) else { continue };
        let images: Vec<(&str, PathBuf)> = [MASKS_DIR, OVERLAYS_DIR, EVIDENCE_DIR, DEPTH_DIR]
            .into_iter()
            .flat_map(|sub| {
                let entries = std::fs::read_dir(run_dir.join(sub)).into_iter().flatten().flatten();
                entries.map(|e| e.path()).filter(|p| p.extension().is_some_and(|e| e == "png")).map(move |p| (sub, p))
            })
            .collect();
        // A run folder that is gone (a report rewritten from records alone) leaves the images an
        // earlier report copied in place.
        if images.is_empty() {
            continue;
        }
        let dest = out.join(WORST_DIR).join(&s.method);
        if dest.exists() {
            std::fs::remove_dir_all(&dest).with_context(|| format!("clearing {}", dest.display()))?;
        }
        for (sub, path) in &images {
            let target = dest.join(sub);
            std::fs::create_dir_all(&target).with_context(|| format!("creating {}", target.display()))?;
            let to = target.join(path.file_name().expect("a listed file"));
            std::fs::copy(path, &to).with_context(|| format!("copying {} to {}", path.display(), to.display()))?;
        }
        let note = format!(
            "The held-out masks of `{}` with `{}` (mIoU {:.3}), its worst scene.\n",
            s.miou_worst.1, s.method, s.miou_worst.0
        );
        crate::commands::write_atomic(&dest.join("README.md"), &note)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;
    use crate::bench::report::{Row, Stat};

    fn row(variant: &str, miou: f64, ari: f64, sweep: bool) -> Row {
        let stat = |mean| Stat { mean, std: 0.0, n: 1 };
        Row {
            variant: variant.into(),
            method: variant.into(),
            sweep: sweep.then(|| ("s".to_string(), "p".to_string())),
            seeds: vec![0],
            metrics: BTreeMap::from([("mIoU".to_string(), stat(miou)), ("NV-ARI".to_string(), stat(ari))]),
            seconds: BTreeMap::new(),
            stage2_step: None,
            view: None,
            peak_rss_mib: None,
            cores_busy: None,
            cpu_stolen: None,
            speedup: None,
            to_target: None,
            target_missed: 0,
            problems: Vec::new(),
        }
    }

    #[test]
    fn mean_and_worst_over_scenes_name_the_worst_scene() {
        let tables = vec![
            SceneTable { scene: "a".into(), rows: vec![row("default", 0.9, 0.8, false), row("x", 0.1, 0.1, true)] },
            SceneTable { scene: "b".into(), rows: vec![row("default", 0.7, 0.9, false)] },
            SceneTable { scene: "c".into(), rows: vec![row("other", 0.5, 0.5, false)] },
        ];
        let spread = across_scenes(&tables);
        assert_eq!(spread.len(), 1, "`other` and the sweep point `x` have one scene each: {spread:?}");
        let s = &spread[0];
        assert_eq!((s.method.as_str(), s.scenes), ("default", 2));
        assert!((s.miou_mean - 0.8).abs() < 1e-12 && s.miou_worst == (0.7, "b".into()));
        assert!((s.nv_ari_mean - 0.85).abs() < 1e-12 && s.nv_ari_worst == (0.8, "a".into()));
        assert!(markdown(&spread).contains("| default | 2 | 0.800 | 0.700 (b) | 0.850 | 0.800 (a) |"));
        assert!(markdown(&[]).is_empty());
        // A sweep point on two scenes gets its row, after the methods.
        let mut tables = tables;
        tables[1].rows.push(row("x", 0.3, 0.2, true));
        let spread = across_scenes(&tables);
        let rows: Vec<(&str, usize)> = spread.iter().map(|s| (s.method.as_str(), s.scenes)).collect();
        assert_eq!(rows, [("default", 2), ("x", 2)]);
        assert!((spread[1].miou_mean - 0.2).abs() < 1e-12 && spread[1].miou_worst == (0.1, "a".into()));
        assert!(spread.iter().all(|s| s.depth_error.is_none()) && !markdown(&spread).contains("depth err"));
    }

    #[test]
    fn depth_errors_spread_only_when_every_scene_measured_one() {
        let with_depth = |v: &str, miou: f64, depth: Option<f64>| {
            let mut r = row(v, miou, miou, false);
            if let Some(d) = depth {
                r.metrics.insert(DEPTH_ERROR.to_string(), Stat { mean: d, std: 0.0, n: 1 });
            }
            r
        };
        let tables = vec![
            SceneTable {
                scene: "a".into(),
                rows: vec![with_depth("default", 0.9, Some(0.02)), with_depth("y", 0.9, Some(0.1))],
            },
            SceneTable {
                scene: "b".into(),
                rows: vec![with_depth("default", 0.5, Some(0.9)), with_depth("y", 0.9, None)],
            },
        ];
        let spread = across_scenes(&tables);
        let (mean, (largest, scene)) = spread[0].depth_error.clone().unwrap();
        assert!((mean - 0.46).abs() < 1e-12 && largest == 0.9 && scene == "b", "{spread:?}");
        assert!(spread[1].depth_error.is_none(), "one scene of `y` has no depth");
        let md = markdown(&spread);
        assert!(md.contains("| depth err mean | depth err largest |"), "{md}");
        assert!(md.contains("| 0.460 | 0.900 (b) |") && md.contains("| y | 2 |") && md.contains(" - | - |"), "{md}");
    }

    #[test]
    fn the_worst_scenes_masks_are_copied() {
        let root = std::env::temp_dir().join(format!("sos-spread-{}", std::process::id()));
        std::fs::remove_dir_all(&root).ok();
        let run = root.join("work/b__default__s0");
        std::fs::create_dir_all(run.join("masks")).unwrap();
        std::fs::write(run.join("masks/v0.png"), b"png").unwrap();
        std::fs::write(run.join("masks/notes.txt"), b"x").unwrap();
        let spread = vec![AcrossScenes {
            method: "default".into(),
            scenes: 2,
            miou_mean: 0.8,
            miou_worst: (0.7, "b".into()),
            nv_ari_mean: 0.8,
            nv_ari_worst: (0.7, "b".into()),
            depth_error: None,
        }];
        copy_worst_masks(&root, &spread, |scene, method| Some(root.join(format!("work/{scene}__{method}__s0"))))
            .unwrap();
        let dest = root.join("worst/default");
        assert_eq!(std::fs::read(dest.join("masks/v0.png")).unwrap(), b"png");
        assert!(!dest.join("masks/notes.txt").exists());
        assert!(std::fs::read_to_string(dest.join("README.md")).unwrap().contains("`b`"));
        // Without the run folder (records only), the copied images stay.
        std::fs::remove_dir_all(root.join("work")).unwrap();
        copy_worst_masks(&root, &spread, |scene, method| Some(root.join(format!("work/{scene}__{method}__s0"))))
            .unwrap();
        assert_eq!(std::fs::read(dest.join("masks/v0.png")).unwrap(), b"png");
        std::fs::remove_dir_all(&root).ok();
    }
}
