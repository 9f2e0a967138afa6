//! End-to-end tests of `sos bench`: a tiny matrix runs, writes its records, report and plots;
//! a rerun is all cached and rewrites nothing; bad key paths fail before any run; missing
//! data is a skip (a finished run's result stays) and a broken run a recorded failure (exit
//! code 3); shards merge into the single-process result; leftovers of a killed run are cleaned
//! up.

use std::path::{Path, PathBuf};

mod common;

use common::{sos, text};
use sos_datasets::layouts::Format;
use sos_datasets::synthetic::{generate, SyntheticConfig};

fn temp_dir(test: &str) -> PathBuf {
    common::temp_dir("sos-bench", test)
}

/// A 32x24 scene, 40 + 4 steps: a run takes a second or two.
const BASE: &str = r#"
[scene]
kind = "synthetic"
width = 32
height = 24
views = 8
hold_out_every = 4
render_path_views = 2

[field]
kind = "voxel-grid"
resolution = [16, 16, 16]
initial_resolution = [16, 16, 16]
upsample_at = []

[train]
steps = 40
rays_per_step = 512
checkpoint_every = 0

[render]
chunk = 2048

[segment]
steps = 4
patches = 2
patch_size = 8
stride = 2
offset_grid = 0
"#;

/// Writes `base.toml` and `bench.toml` (with `extra` appended) into `dir`.
fn write_bench(dir: &Path, extra: &str) {
    std::fs::write(dir.join("base.toml"), BASE).unwrap();
    let bench = format!(
        r#"[bench]
curve_points = 3
seeds = [0, 1]
out = "results"
target = {{ miou = 0.01 }}

[scenes.tiny]
config = "base.toml"

[scenes.missing]
config = "base.toml"
set = {{ scene = {{ kind = "llff", path = "no/such/folder" }} }}

[methods.default]
[methods.short]
set = {{ "segment.steps" = 2 }}

{extra}
"#
    );
    std::fs::write(dir.join("bench.toml"), bench).unwrap();
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

#[test]
fn a_matrix_runs_reports_caches_and_merges_from_shards() {
    let dir = temp_dir("matrix");
    write_bench(&dir, "[[sweep]]\nname = \"steps\"\nscenes = [\"tiny\"]\nvary = { \"segment.steps\" = [2, 4] }\n");
    let out = sos(&["bench", "bench.toml"], &dir);
    let stderr = text(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let results = dir.join("results").join("all");
    // 2 scenes x 2 methods x 2 seeds + 2 sweep points x 2 seeds.
    let runs: Vec<_> = std::fs::read_dir(results.join("runs")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(runs.len(), 12, "{runs:?}");
    let done = json(&results.join("runs/tiny__default__s0.json"));
    assert_eq!(done["status"], "done");
    for key in ["psnr", "ssim", "nv_ari", "iou_fg", "iou_bg", "miou"] {
        let v = done["outcome"]["metrics"][key].as_f64().unwrap_or_else(|| panic!("{key}: {done:#}"));
        assert!(v.is_finite());
    }
    assert!(done["outcome"]["peak_rss_mib"].as_f64().unwrap() > 1.0);
    assert!(done["config"].as_str().unwrap().contains("[field]"));
    assert_eq!(done["hash"].as_str().unwrap().len(), 64);
    assert!(done["machine"]["cores"].as_u64().unwrap() >= 1);
    let curve1 = done["outcome"]["curves"]["stage1"].as_array().unwrap();
    let curve2 = done["outcome"]["curves"]["stage2"].as_array().unwrap();
    assert_eq!((curve1.len(), curve2.len()), (3, 3), "{done:#}");
    let times: Vec<f64> = curve1.iter().map(|p| p["seconds"].as_f64().unwrap()).collect();
    assert!(times.windows(2).all(|w| w[0] <= w[1]), "{times:?}");
    // The stage-2 curve's last point is the final result.
    assert_eq!(curve2[2]["miou"], done["outcome"]["metrics"]["miou"]);
    // One view with its mask is timed at the scene's own size, off the run's time.
    let view = &done["outcome"]["view"];
    assert_eq!((view["width"].as_u64(), view["height"].as_u64()), (Some(32), Some(24)), "{done:#}");
    assert!(view["seconds"].as_f64().unwrap() > 0.0);
    assert_eq!(done["outcome"]["stage2_steps"], 4);

    // The record names the program that ran it: this very binary.
    use sha2::Digest;
    let binary = std::fs::read(env!("CARGO_BIN_EXE_sos")).unwrap();
    let digest: String = sha2::Sha256::digest(&binary).iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(done["program"].as_str(), Some(&digest[..12]), "{done:#}");

    let skipped = json(&results.join("runs/missing__default__s0.json"));
    assert_eq!(skipped["status"], "skipped");
    assert!(skipped["error"].as_str().unwrap().contains("path missing"), "{skipped:#}");
    assert!(skipped.get("program").is_none(), "a skipped run ran no program: {skipped:#}");
    // The sweep point equal to the default reuses its result.
    let reused = json(&results.join("runs/tiny__steps-1-4__s0.json"));
    assert_eq!(reused["hash"], done["hash"]);
    assert_eq!(reused["outcome"]["metrics"], done["outcome"]["metrics"]);

    let report = json(&results.join("report.json"));
    assert_eq!(report["counts"]["done"], 8);
    assert_eq!(report["counts"]["skipped"], 4);
    let md = std::fs::read_to_string(results.join("report.md")).unwrap();
    assert!(md.contains("## tiny") && md.contains("| default |") && md.contains("steps: 2"), "{md}");
    assert!(md.contains(&format!(", program {};", &digest[..12])), "{md}");
    // Every tiny run meets the low target at its first evaluation: the time to it is the
    // training clock to that point plus the mask time, within the run's total.
    assert!(md.contains("To target is the wall time until the run's held-out masks met mIoU ≥ 0.01"), "{md}");
    let tiny = report["scenes"].as_array().unwrap().iter().find(|s| s["scene"] == "tiny").unwrap();
    let default_row = &tiny["rows"][0];
    assert_eq!(default_row["variant"], "default");
    let to_target = default_row["to_target"]["mean"].as_f64().unwrap_or_else(|| panic!("{default_row:#}"));
    let total = default_row["seconds"]["total"]["mean"].as_f64().unwrap();
    let step = default_row["stage2_step"]["mean"].as_f64().unwrap();
    let stage2 = default_row["seconds"]["stage2"]["mean"].as_f64().unwrap();
    assert!((step - stage2 / 4.0).abs() < 1e-9, "{step} vs {stage2}");
    assert_eq!(default_row["view"][1], serde_json::json!([32, 24]));
    assert!(md.contains("(32×24)"), "{md}");
    assert!(to_target > 0.0 && to_target <= total + 1e-9, "{to_target} vs {total}");
    assert_eq!(default_row["target_missed"], 0);
    let own = |seed: u64| {
        let run = json(&results.join(format!("runs/tiny__default__s{seed}.json")));
        let (t, curve) = (&run["outcome"]["timing"], &run["outcome"]["curves"]["stage2"]);
        ["setup", "stage1", "masks"].iter().map(|k| t[k].as_f64().unwrap()).sum::<f64>()
            + curve[0]["seconds"].as_f64().unwrap()
    };
    assert!((to_target - (own(0) + own(1)) / 2.0).abs() < 1e-9, "{to_target} vs {} {}", own(0), own(1));
    for plot in [
        "miou_vs_time",
        "miou_vs_time_by_scene",
        "psnr_vs_stage1_time",
        "psnr_vs_stage1_time_by_scene",
        "tiny_miou_vs_time",
        "sweep_steps",
        "sweep_steps_time",
    ] {
        for ext in ["svg", "png"] {
            let p = results.join("plots").join(format!("{plot}.{ext}"));
            assert!(std::fs::metadata(&p).map(|m| m.len() > 100).unwrap_or(false), "{} missing", p.display());
        }
    }

    // A rerun does nothing: every result is cached and no record is rewritten.
    let stamp = |p: &Path| std::fs::metadata(p).unwrap().modified().unwrap();
    let before = stamp(&results.join("runs/tiny__default__s0.json"));
    let report_written = stamp(&results.join("report.json"));
    let started = std::time::Instant::now();
    let again = sos(&["bench", "bench.toml"], &dir);
    assert!(again.status.success(), "{}", text(&again.stderr));
    assert!(text(&again.stdout).contains("0 ran, 8 cached"), "{}", text(&again.stdout));
    assert!(started.elapsed().as_secs_f64() < 5.0);
    assert_eq!(stamp(&results.join("runs/tiny__default__s0.json")), before);
    assert_eq!(stamp(&results.join("report.json")), report_written);

    // Two shards merged give the single-process metrics, run for run.
    for i in 0..2 {
        let shard = format!("{i}/2");
        let out_dir = format!("shard{i}");
        let out = sos(&["bench", "bench.toml", "--shard", &shard, "--out", &out_dir], &dir);
        assert!(out.status.success(), "{}", text(&out.stderr));
    }
    let merged = sos(&["bench", "merge", "shard0", "shard1", "--out", "merged"], &dir);
    assert!(merged.status.success(), "{}", text(&merged.stderr));
    let diff = sos(&["bench", "diff", "merged", "results/all"], &dir);
    assert!(diff.status.success(), "{}{}", text(&diff.stdout), text(&diff.stderr));
    // ... and diff notices a difference.
    let single = dir.join("merged/runs/tiny__default__s0.json");
    let mut record = json(&single);
    record["outcome"]["metrics"]["miou"] = serde_json::json!(0.123);
    std::fs::write(&single, serde_json::to_string(&record).unwrap()).unwrap();
    let diff = sos(&["bench", "diff", "merged", "results/all"], &dir);
    assert_eq!(diff.status.code(), Some(2));
    assert!(text(&diff.stderr).contains("tiny__default__s0: mIoU"), "{}", text(&diff.stderr));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn runs_that_differ_only_after_stage_one_share_it_with_the_same_result() {
    let dir = temp_dir("shared-stage1");
    // Joint training goes on from stage 1's optimiser state, which a checkpoint after stage 2
    // does not keep: such a run trains its own stage 1.
    let joint =
        "[methods.joint]\nset = { \"segment.photometric_weight\" = 0.1, \"segment.logits\" = \"composited\" }\n";
    write_bench(&dir, joint);
    // `--list` counts them: two seeds each of `default`, `short` and `joint` on the scene that
    // exists; `short` shares `default`'s stage 1.
    let list = sos(&["bench", "bench.toml", "--list"], &dir);
    assert!(list.status.success(), "{}", text(&list.stderr));
    let last = |out: &std::process::Output| text(&out.stdout).lines().last().unwrap_or_default().to_string();
    let counted = "6 runs to run here, 4 of them with a stage 1 of their own (the others share one) in a fresh";
    assert!(last(&list).starts_with(counted), "{}", last(&list));
    let out = sos(&["bench", "bench.toml", "--out", "together"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    // `short` changes only stage 2's steps: it starts from `default`'s stage 1 (which runs
    // first) and counts that stage's time and curve as its own.
    let source = json(&dir.join("together/runs/tiny__default__s0.json"));
    let shared = json(&dir.join("together/runs/tiny__short__s0.json"));
    let notes = shared["outcome"]["notes"].to_string();
    assert!(notes.contains("stage 1 shared with `tiny__default__s0`"), "{notes}");
    assert_eq!(shared["outcome"]["curves"]["stage1"], source["outcome"]["curves"]["stage1"]);
    assert_eq!(shared["outcome"]["timing"]["stage1"], source["outcome"]["timing"]["stage1"]);
    assert!(shared["outcome"]["stage1"].is_null() && source["outcome"]["stage1"].is_object(), "{shared:#}");
    // Its peak memory is at least the stage-1 run's; its CPU time covers only its own process.
    let peak = |r: &serde_json::Value| r["outcome"]["peak_rss_mib"].as_f64().unwrap();
    assert!(peak(&shared) >= peak(&source), "{} < {}", peak(&shared), peak(&source));
    assert!(shared["outcome"]["cpu_seconds"].is_null() && source["outcome"]["cpu_seconds"].is_number());
    let joint = json(&dir.join("together/runs/tiny__joint__s0.json"));
    assert!(joint["outcome"]["stage1"].is_object(), "{joint:#}");
    // Its stage 1 is `default`'s, so is its stage-1 curve, to the last point: measured as
    // stage 1 ends, before stage 2 trains the field on.
    let psnrs = |r: &serde_json::Value| -> Vec<serde_json::Value> {
        r["outcome"]["curves"]["stage1"].as_array().unwrap().iter().map(|p| p["psnr"].clone()).collect()
    };
    assert_eq!(psnrs(&joint), psnrs(&source));
    assert_eq!(psnrs(&joint).len(), 3, "{joint:#}");
    // Shards keep the runs of one stage 1 together: two shards, one seed each, share as well.
    for i in 0..2 {
        let (shard, out_dir) = (format!("{i}/2"), format!("shard{i}"));
        let out = sos(&["bench", "bench.toml", "--shard", &shard, "--out", &out_dir], &dir);
        assert!(out.status.success(), "{}", text(&out.stderr));
    }
    let sharded: Vec<String> = (0..2)
        .flat_map(|i| std::fs::read_dir(dir.join(format!("shard{i}/runs"))).unwrap())
        .map(|e| std::fs::read_to_string(e.unwrap().path()).unwrap())
        .collect();
    assert_eq!(sharded.iter().filter(|r| r.contains("stage 1 shared with")).count(), 2);
    // With `--own-stage1` every run trains its own stage 1, with the same metrics.
    let list = sos(&["bench", "bench.toml", "--list", "--own-stage1"], &dir);
    let own = "6 runs to run here, 6 of them with a stage 1 of their own (the others share one) in a fresh";
    assert!(last(&list).starts_with(own), "{}", last(&list));
    let out = sos(&["bench", "bench.toml", "--own-stage1", "--out", "alone"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let alone = json(&dir.join("alone/runs/tiny__short__s0.json"));
    assert!(!alone["outcome"]["notes"].to_string().contains("shared"), "{alone:#}");
    let diff = sos(&["bench", "diff", "alone", "together"], &dir);
    assert!(diff.status.success(), "{}{}", text(&diff.stdout), text(&diff.stderr));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_profile_times_its_view_at_the_size_it_names() {
    let dir = temp_dir("view-size");
    let profile = "[profiles.big]\nscenes = [\"tiny\"]\nmethods = [\"default\"]\nseeds = [0]\nview_size = [48, 36]\n";
    write_bench(&dir, profile);
    let out = sos(&["bench", "bench.toml", "--profile", "big"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let run = json(&dir.join("results/big/runs/tiny__default__s0.json"));
    let view = &run["outcome"]["view"];
    assert_eq!((view["width"].as_u64(), view["height"].as_u64()), (Some(48), Some(36)), "{run:#}");
    // The runner's own clock of the run, evaluations and view included, adds up in the report.
    let wall = run["wall_seconds"].as_f64().unwrap();
    assert!(wall >= run["outcome"]["timing"]["total"].as_f64().unwrap(), "{run:#}");
    let md = std::fs::read_to_string(dir.join("results/big/report.md")).unwrap();
    assert!(md.contains("Wall time of the runs: ") && md.contains("over 1 runs"), "{md}");
    // A size of zero is refused before any run, naming the profile.
    write_bench(&dir, "[profiles.bad]\nview_size = [0, 36]\n");
    let out = sos(&["bench", "bench.toml", "--profile", "bad"], &dir);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("profile `bad`, `view_size` is 0x36"), "{}", text(&out.stderr));
    // So is a learning curve of a quadrillion points (a check on every step for ever).
    write_bench(&dir, "[profiles.bad]\ncurve_points = 1000000000000000\n");
    let out = sos(&["bench", "bench.toml", "--profile", "bad", "--list"], &dir);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("profile `bad`, `curve_points` is 1000000000000000"), "{}", text(&out.stderr));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn an_unknown_key_path_fails_before_any_run() {
    let dir = temp_dir("badpath");
    write_bench(&dir, "[[sweep]]\nname = \"typo\"\nvary = { \"segment.stpes\" = [1, 2] }\n");
    let out = sos(&["bench", "bench.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("bench.toml") && stderr.contains("sweep `typo`") && stderr.contains("segment.stpes"),
        "{stderr}"
    );
    assert!(!dir.join("results").exists(), "nothing may run");

    // So is a target outside (0, 1].
    let bench = std::fs::read_to_string(dir.join("bench.toml")).unwrap().replace("miou = 0.01", "miou = 95");
    std::fs::write(dir.join("bench.toml"), bench).unwrap();
    let out = sos(&["bench", "bench.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("bench.target") && stderr.contains("not in (0, 1]"), "{stderr}");
    assert!(!dir.join("results").exists(), "nothing may run");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_finished_run_stays_cached_when_its_data_goes_missing() {
    let dir = temp_dir("data-gone");
    let scene = generate(&SyntheticConfig { width: 32, height: 24, views: 8, ..SyntheticConfig::default() });
    Format::Llff.write(&scene, &dir.join("capture")).unwrap();
    let path = Format::Llff.scene_dir(&dir.join("capture"));
    write_bench(&dir, "");
    let bench = std::fs::read_to_string(dir.join("bench.toml")).unwrap();
    let bench = bench
        .replace("seeds = [0, 1]", "seeds = [0]")
        .replace("[methods.short]\nset = { \"segment.steps\" = 2 }\n", "")
        .replace("\"no/such/folder\"", &format!("{:?}", path.display().to_string()));
    std::fs::write(dir.join("bench.toml"), bench).unwrap();
    let run_bench = |dir: &Path| sos(&["bench", "bench.toml"], dir);
    let out = run_bench(&dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let record = dir.join("results/all/runs/missing__default__s0.json");
    assert_eq!(json(&record)["status"], "done", "the capture exists: the run happens");
    let before = std::fs::read_to_string(&record).unwrap();

    std::fs::remove_dir_all(dir.join("capture")).unwrap();
    let out = run_bench(&dir);
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(stdout.contains("0 ran, 2 cached, 0 skipped"), "{stdout}");
    assert_eq!(std::fs::read_to_string(&record).unwrap(), before, "the finished result is kept");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_failing_run_is_recorded_and_the_matrix_goes_on() {
    let dir = temp_dir("failing");
    // An all-black teacher-free... a patch larger than the views fails inside the run.
    write_bench(&dir, "[methods.broken]\nset = { segment = { patch_size = 200, stride = 1 } }\n");
    std::fs::write(
        dir.join("bench.toml"),
        std::fs::read_to_string(dir.join("bench.toml")).unwrap().replace("seeds = [0, 1]", "seeds = [0]"),
    )
    .unwrap();
    // Leftovers of a killed runner: a temporary record and a half-finished run folder.
    let results = dir.join("results").join("all");
    std::fs::create_dir_all(results.join("runs")).unwrap();
    std::fs::create_dir_all(results.join("work/tiny__default__s0")).unwrap();
    std::fs::write(results.join("runs/tiny__default__s0.json.tmp"), "{").unwrap();
    std::fs::write(results.join("work/tiny__default__s0/checkpoint.bin.tmp"), "x").unwrap();
    let out = sos(&["bench", "bench.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "failed runs, not bad input: {stderr}");
    assert!(stderr.contains("1 runs failed: tiny__broken__s0"), "{stderr}");
    let failed = json(&results.join("runs/tiny__broken__s0.json"));
    assert_eq!(failed["status"], "failed");
    assert!(failed["error"].as_str().unwrap().contains("patch"), "{failed:#}");
    assert_eq!(json(&results.join("runs/tiny__default__s0.json"))["status"], "done");
    assert!(!results.join("runs/tiny__default__s0.json.tmp").exists());
    assert!(!results.join("work/tiny__default__s0/checkpoint.bin.tmp").exists());
    let md = std::fs::read_to_string(results.join("report.md")).unwrap();
    assert!(md.contains("failed"), "{md}");
    // Merged, the failure still shows in the exit code (and the merged report is written).
    let merged = sos(&["bench", "merge", "results/all", "--out", "merged"], &dir);
    assert_eq!(merged.status.code(), Some(3), "{}", text(&merged.stderr));
    assert!(dir.join("merged/report.md").exists());
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_method_of_another_build_runs_its_own_train_beside_this_builds_rows() {
    let dir = temp_dir("program");
    // "Another build" is this very binary on the scene's own config, so its row must give the
    // metrics of this build's row (training is deterministic per seed).
    let program = env!("CARGO_BIN_EXE_sos");
    let methods = format!(
        "[methods.other]\nprogram = \"{program}\"\nconfig = \"base.toml\"\nscenes = [\"tiny\"]\n[profiles.builds]\nscenes = [\"tiny\", \"missing\"]\nmethods = [\"default\", \"other\"]\nseeds = [0]\n"
    );
    write_bench(&dir, &methods);
    let out = sos(&["bench", "bench.toml", "--profile", "builds"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let runs = dir.join("results/builds/runs");
    assert!(!runs.join("missing__other__s0.json").exists(), "the method names its scenes");
    let ours = json(&runs.join("tiny__default__s0.json"));
    let other = json(&runs.join("tiny__other__s0.json"));
    assert_eq!(other["status"], "done", "{other:#}");
    for metric in ["miou", "nv_ari", "psnr", "ssim"] {
        let (a, b) = (&ours["outcome"]["metrics"][metric], &other["outcome"]["metrics"][metric]);
        assert!(a.as_f64().is_some() && a == b, "{metric}: {a} against {b}");
    }
    let o = &other["outcome"];
    assert!(o["peak_rss_mib"].as_f64().unwrap() > 1.0 && o["timing"]["total"].as_f64().unwrap() > 0.0, "{o:#}");
    assert_eq!(o["stage2_steps"].as_u64(), Some(4));
    let md = std::fs::read_to_string(dir.join("results/builds/report.md")).unwrap();
    assert!(md.lines().any(|l| l.starts_with("| other |")), "{md}");
    // A build that fails is a recorded failure naming its log.
    let broken = dir.join("broken.sh");
    std::fs::write(&broken, "#!/bin/sh\nexit 7\n").unwrap();
    std::process::Command::new("chmod").arg("+x").arg(&broken).status().unwrap();
    let bench = std::fs::read_to_string(dir.join("bench.toml")).unwrap().replace(program, "broken.sh");
    std::fs::write(dir.join("bench.toml"), bench).unwrap();
    let out = sos(&["bench", "bench.toml", "--profile", "builds"], &dir);
    assert_eq!(out.status.code(), Some(3), "a failed run: {}", text(&out.stderr));
    let failed = json(&runs.join("tiny__other__s0.json"));
    assert!(failed["error"].as_str().unwrap().contains("exited with code 7"), "{failed:#}");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn another_builds_stage_two_starts_from_this_builds_stage_one_and_a_rerun_from_its_own() {
    let dir = temp_dir("stage1-of");
    // "Another build" is this very binary again: its `sos segment` on the `default` run's
    // stage-1 checkpoint must give that run's masks (stage 2 is deterministic per seed).
    let program = env!("CARGO_BIN_EXE_sos");
    let methods = format!(
        "[methods.after]\nprogram = \"{program}\"\nconfig = \"base.toml\"\nscenes = [\"tiny\"]\nstage1_of = \"default\"\n\
         [profiles.p]\nscenes = [\"tiny\"]\nmethods = [\"after\", \"default\"]\nseeds = [0]\n"
    );
    write_bench(&dir, &methods);
    let list = sos(&["bench", "bench.toml", "--profile", "p", "--list"], &dir);
    let listed = text(&list.stdout);
    assert!(listed.contains("2 runs to run here, 1 of them with a stage 1 of their own"), "{listed}");
    let out = sos(&["bench", "bench.toml", "--profile", "p"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let (runs, work) = (dir.join("results/p/runs"), dir.join("results/p/work"));
    let ours = json(&runs.join("tiny__default__s0.json"));
    let after = json(&runs.join("tiny__after__s0.json"));
    assert_eq!(after["status"], "done", "{after:#}");
    for metric in ["miou", "nv_ari", "iou_fg"] {
        let (a, b) = (&ours["outcome"]["metrics"][metric], &after["outcome"]["metrics"][metric]);
        assert!(a.as_f64().is_some() && a == b, "{metric}: {a} against {b}");
    }
    assert_eq!(after["outcome"]["timing"]["stage1"], ours["outcome"]["timing"]["stage1"]);
    let notes = after["outcome"]["notes"].to_string();
    assert!(notes.contains("stage-1 checkpoint of `tiny__default__s0`"), "{notes}");
    assert!(!work.join("tiny__after__s0.stage1.bin").exists(), "the handed-over copy is removed");
    // `--rerun default` runs it again from its previous stage 1, to the same result; the rest
    // stays cached.
    let out = sos(&["bench", "bench.toml", "--profile", "p", "--rerun", "default"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(text(&out.stdout).contains("1 ran, 1 cached"), "{}", text(&out.stdout));
    let again = json(&runs.join("tiny__default__s0.json"));
    assert_eq!(again["outcome"]["metrics"], ours["outcome"]["metrics"]);
    assert_eq!(again["outcome"]["timing"]["stage1"], ours["outcome"]["timing"]["stage1"]);
    let notes = again["outcome"]["notes"].to_string();
    assert!(notes.contains("stage 1 shared with `tiny__default__s0.previous`"), "{notes}");
    assert!(
        work.join("tiny__default__s0/checkpoint.bin").is_file() && !work.join("tiny__default__s0.previous").exists()
    );
    // A method added later shares the stage 1 of a result kept from before, though its id
    // comes first.
    let added = "[methods.aa-short]\nset = { \"segment.steps\" = 2 }\n[profiles.q]\nscenes = [\"tiny\"]\n\
                 methods = [\"aa-short\", \"default\", \"after\"]\nseeds = [0]\n";
    write_bench(&dir, &format!("{methods}{added}"));
    let out = sos(&["bench", "bench.toml", "--profile", "q", "--out", "results/p"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(text(&out.stdout).contains("1 ran, 2 cached"), "{}", text(&out.stdout));
    let notes = json(&runs.join("tiny__aa-short__s0.json"))["outcome"]["notes"].to_string();
    assert!(notes.contains("stage 1 shared with `tiny__default__s0`"), "{notes}");
    // A method the file does not define is refused.
    let out = sos(&["bench", "bench.toml", "--profile", "p", "--rerun", "nope"], &dir);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("`--rerun nope`"), "{}", text(&out.stderr));
    std::fs::remove_dir_all(dir).ok();
}
