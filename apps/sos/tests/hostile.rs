//! Hostile input against the `sos` binary: every case must exit with code 2 and a message that
//! names the file and the key (or the folder, or the checkpoint) at fault, before any training
//! starts: never a panic, an abort, a hang or a run that reports nonsense.
//!
//! The cases are generated from the configs `sos init` writes for every registered dataset and
//! field kind, so a new plugin's settings are attacked without editing this file: each float
//! becomes NaN, +inf and −inf; each bounded count a size no machine could serve.

mod common;

use std::path::Path;

use common::{sos, temp_dir, text};
use sos_core::plugin::{DatasetConfig, RadianceFieldConfig};
use sos_core::registry::registrations;
// Links every plugin crate's registrations into this test binary.
use sos_plugins as _;

/// A generated case: the config text and what the error must name.
struct Case {
    label: String,
    config: String,
    key: String,
}

/// The dotted path and TOML text of every float leaf of `table` (arrays index as `key[i]`).
fn float_leaves(value: &toml::Value, key: &str, out: &mut Vec<String>) {
    match value {
        toml::Value::Float(_) => out.push(key.to_string()),
        toml::Value::Table(t) => {
            for (k, v) in t {
                float_leaves(v, &if key.is_empty() { k.clone() } else { format!("{key}.{k}") }, out);
            }
        }
        toml::Value::Array(items) => {
            for (i, v) in items.iter().enumerate() {
                float_leaves(v, &format!("{key}[{i}]"), out);
            }
        }
        _ => {}
    }
}

/// `table` with the leaf at dotted `key` (with `[i]` indices) replaced by `new`.
fn replaced(table: &toml::Table, key: &str, new: toml::Value) -> toml::Table {
    fn go(value: &mut toml::Value, parts: &[&str], new: toml::Value) {
        let Some((first, rest)) = parts.split_first() else {
            *value = new;
            return;
        };
        let (name, indices) = match first.find('[') {
            Some(i) => (&first[..i], &first[i..]),
            None => (*first, ""),
        };
        let mut target = if name.is_empty() { value } else { &mut value[name] };
        for index in indices.trim_start_matches('[').trim_end_matches(']').split("][").filter(|s| !s.is_empty()) {
            target = &mut target[index.parse::<usize>().unwrap()];
        }
        go(target, rest, new);
    }
    let mut value = toml::Value::Table(table.clone());
    let parts: Vec<&str> = key.split('.').collect();
    go(&mut value, &parts, new);
    match value {
        toml::Value::Table(t) => t,
        _ => unreachable!(),
    }
}

/// The config `sos init` writes for a scene and field kind, as a table with the run's name set.
fn init_config(dir: &Path, scene: &str, field: &str) -> toml::Table {
    let out = sos(&["init", "--scene", scene, "--field", field], dir);
    assert!(out.status.success(), "sos init --scene {scene} --field {field}: {}", text(&out.stderr));
    toml::from_str(&text(&out.stdout)).expect("sos init writes TOML")
}

fn non_finite_cases(base: &toml::Table, tag: &str, keys_from: &toml::Value, prefix: &str) -> Vec<Case> {
    let mut leaves = Vec::new();
    float_leaves(keys_from, prefix, &mut leaves);
    let mut cases = Vec::new();
    for key in leaves {
        for (name, v) in [("nan", f64::NAN), ("inf", f64::INFINITY), ("-inf", f64::NEG_INFINITY)] {
            let config = toml::to_string(&replaced(base, &key, toml::Value::Float(v))).unwrap();
            cases.push(Case { label: format!("{tag}: {key} = {name}"), config, key: key.clone() });
        }
    }
    cases
}

fn run_cases(dir: &Path, cases: &[Case]) -> Vec<String> {
    let mut failures = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        let file = format!("case-{i:03}.toml");
        std::fs::write(dir.join(&file), &case.config).unwrap();
        let out = sos(&["train", &file], dir);
        let stderr = text(&out.stderr);
        // Named by its dotted path, or as a key of its section's table (`[scene] … key `views``).
        let path = case.key.split('[').next().unwrap_or("");
        let (section, leaf) = path.rsplit_once('.').unwrap_or(("", path));
        let key_named = stderr.contains(&case.key)
            || stderr.contains(path)
            || (stderr.contains(&format!("[{section}]")) && stderr.contains(&format!("`{leaf}`")));
        if out.status.code() != Some(2) || !stderr.contains(&file) || !key_named {
            failures.push(format!("{} (exit {:?}): {}", case.label, out.status.code(), stderr.trim()));
        }
    }
    failures
}

#[test]
fn every_non_finite_float_of_every_kind_is_refused_by_key() {
    let dir = temp_dir("sos-hostile", "non_finite");
    let mut cases = Vec::new();
    // Every section's floats with the default scene and each field kind.
    for field in registrations::<dyn RadianceFieldConfig>() {
        let base = init_config(&dir, "synthetic", field.kind);
        let tag = format!("field {}", field.kind);
        let sections = toml::Value::Table(base.clone());
        if field.kind == "voxel-grid" {
            cases.extend(non_finite_cases(&base, &tag, &sections, ""));
        } else {
            cases.extend(non_finite_cases(&base, &tag, &base["field"], "field"));
        }
    }
    // Every dataset adapter's floats, and the optional bounds every adapter takes.
    for scene in registrations::<dyn DatasetConfig>() {
        let base = init_config(&dir, scene.kind, "voxel-grid");
        let tag = format!("scene {}", scene.kind);
        cases.extend(non_finite_cases(&base, &tag, &base["scene"], "scene"));
    }
    let optional = [
        ("scene.near", "[scene]\nkind = \"synthetic\"\nnear = nan\n"),
        ("scene.aabb", "[scene]\nkind = \"blender\"\npath = \".\"\naabb = [[0.0, 0.0, 0.0], [1.0, inf, 1.0]]\n"),
        ("scene.aabb", "[scene]\nkind = \"colmap\"\npath = \".\"\naabb = [[-inf, 0.0, 0.0], [1.0, 1.0, 1.0]]\n"),
        ("scene.near", "[scene]\nkind = \"blender\"\npath = \".\"\nnear = inf\n"),
        ("scene.bd_factor", "[scene]\nkind = \"llff\"\npath = \".\"\nbd_factor = nan\n"),
        ("render.memory_gib", "[scene]\nkind = \"synthetic\"\n[render]\nmemory_gib = inf\n"),
        // Mask inference reads it from a checkpoint's head even when no stage 2 runs.
        ("segment.weight_threshold", "[scene]\nkind = \"synthetic\"\n[segment]\nsteps = 0\nweight_threshold = nan\n"),
        ("loss[0].weight", "[scene]\nkind = \"synthetic\"\n[[loss]]\nkind = \"appearance\"\nweight = nan\n"),
    ];
    for (key, config) in optional {
        cases.push(Case { label: format!("optional {key}"), config: config.into(), key: key.into() });
    }
    assert!(cases.len() >= 100, "only {} cases were generated", cases.len());
    let failures = run_cases(&dir, &cases);
    assert!(
        failures.is_empty(),
        "{} of {} cases not refused by key:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn counts_beyond_any_machine_are_refused_by_key() {
    let dir = temp_dir("sos-hostile", "counts");
    let base = init_config(&dir, "synthetic", "voxel-grid");
    let huge = [
        ("train.steps", 1_000_000_000_000i64),
        ("train.rays_per_step", 1_000_000_000_000),
        ("train.samples_per_ray", 1_000_000_000),
        ("segment.steps", 1_000_000_000_000),
        ("segment.patches", 1_000_000_000),
        ("masks.restarts", 1_000_000_000),
        ("masks.clusters", 1_000_000),
        ("masks.border_splits", 1_000_000),
        ("render.chunk", 1_000_000_000_000),
        ("train.occupancy_resolution", 100_000),
        ("head.outputs", 1_000_000_000),
        ("scene.views", 1_000_000_000),
        ("scene.render_path_views", 1_000_000_000),
        ("scene.width", 1_000_000),
        ("train.rays_per_step", 0),
        ("render.chunk", 0),
        ("masks.restarts", 0),
    ];
    let cases: Vec<Case> = huge
        .iter()
        .map(|&(key, v)| Case {
            label: format!("{key} = {v}"),
            config: toml::to_string(&replaced(&base, key, toml::Value::Integer(v))).unwrap(),
            key: key.into(),
        })
        .collect();
    let mut cases = cases;
    // Sizes within every bound that together need more memory than any machine here has:
    // refused by the memory estimate before the field is built.
    let grid = toml::Value::try_from([1024, 1024, 1024]).unwrap();
    cases.push(Case {
        label: "a 1024³ grid".into(),
        config: toml::to_string(&replaced(&base, "field.resolution", grid)).unwrap(),
        key: "field.resolution".into(),
    });
    // Checked by the field plugin when it is built, after the scene has loaded: named too.
    let flat = toml::Value::try_from([1, 64, 64]).unwrap();
    cases.push(Case {
        label: "a grid one vertex thick".into(),
        config: toml::to_string(&replaced(&base, "field.resolution", flat)).unwrap(),
        key: "field.resolution".into(),
    });
    let many = replaced(&base, "train.rays_per_step", toml::Value::Integer(1 << 20));
    cases.push(Case {
        label: "a million rays of 4096 samples".into(),
        config: toml::to_string(&replaced(&many, "train.samples_per_ray", toml::Value::Integer(4096))).unwrap(),
        key: "train.rays_per_step".into(),
    });
    let nerf = init_config(&dir, "synthetic", "nerf");
    let wide = replaced(&nerf, "field.width", toml::Value::Integer(4096));
    cases.push(Case {
        label: "nerf 32 x 4096 at 4096 rays".into(),
        config: toml::to_string(&replaced(
            &replaced(&wide, "field.depth", 32.into()),
            "train.rays_per_step",
            4096.into(),
        ))
        .unwrap(),
        key: "train.rays_per_step".into(),
    });
    let failures = run_cases(&dir, &cases);
    assert!(failures.is_empty(), "counts not refused by key:\n{}", failures.join("\n"));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn run_folders_in_use_or_unwritable_are_refused_before_training() {
    let dir = temp_dir("sos-hostile", "folders");
    let mut base = init_config(&dir, "synthetic", "voxel-grid");
    base.insert("name".into(), "busy".into());
    std::fs::write(dir.join("busy.toml"), toml::to_string(&base).unwrap()).unwrap();
    // Another live process (PID 1) holds the folder.
    let run = dir.join("runs").join("busy");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(run.join("run.lock"), "1").unwrap();
    let out = sos(&["train", "busy.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("process 1") && stderr.contains("busy"), "{stderr}");
    assert!(!stderr.contains("stage 1"), "the run started anyway: {stderr}");

    // `output_dir` names a file.
    std::fs::write(dir.join("not-a-folder"), "x").unwrap();
    base.insert("output_dir".into(), "not-a-folder".into());
    std::fs::write(dir.join("file.toml"), toml::to_string(&base).unwrap()).unwrap();
    let out = sos(&["train", "file.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("not-a-folder"), "{stderr}");

    // A run named `..` (or `.`) would write its checkpoint and masks beside `output_dir`.
    base.insert("output_dir".into(), "runs".into());
    for name in ["..", "."] {
        base.insert("name".into(), name.into());
        std::fs::write(dir.join("dots.toml"), toml::to_string(&base).unwrap()).unwrap();
        let out = sos(&["train", "dots.toml"], &dir);
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{stderr}");
        assert!(stderr.contains("dots.toml") && stderr.contains("name"), "{stderr}");
    }
    assert!(!dir.join("checkpoint.bin").exists() && !dir.join("runs/checkpoint.bin").exists());
    std::fs::remove_dir_all(dir).ok();
}

/// A small run config (two stage-1 steps, no stage 2) named `name`.
fn tiny(dir: &Path, name: &str) -> String {
    let mut base = init_config(dir, "synthetic", "voxel-grid");
    base.insert("name".into(), name.into());
    let set = |t: &mut toml::Table, section: &str, key: &str, v: toml::Value| {
        t.get_mut(section).and_then(toml::Value::as_table_mut).unwrap().insert(key.into(), v);
    };
    set(&mut base, "scene", "width", 32.into());
    set(&mut base, "scene", "height", 24.into());
    set(&mut base, "scene", "views", 8.into());
    set(&mut base, "scene", "hold_out_every", 4.into());
    set(&mut base, "field", "resolution", toml::Value::try_from([16, 16, 16]).unwrap());
    set(&mut base, "field", "initial_resolution", toml::Value::try_from([8, 8, 8]).unwrap());
    set(&mut base, "train", "steps", 2.into());
    set(&mut base, "train", "rays_per_step", 256.into());
    set(&mut base, "segment", "steps", 0.into());
    toml::to_string(&base).unwrap()
}

#[test]
fn damaged_checkpoints_are_refused_naming_the_file() {
    let dir = temp_dir("sos-hostile", "checkpoints");
    std::fs::write(dir.join("run.toml"), tiny(&dir, "ckpt")).unwrap();
    let out = sos(&["train", "run.toml"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let good = std::fs::read(dir.join("runs/ckpt/checkpoint.bin")).unwrap();
    let mut cases: Vec<(String, Vec<u8>)> = Vec::new();
    // Flipped bytes spread over the file (header, sections, checksum), cuts at several lengths.
    for k in 0..24 {
        let i = k * (good.len() - 1) / 23;
        let mut bad = good.clone();
        bad[i] ^= 0x5A;
        cases.push((format!("byte {i} flipped"), bad));
    }
    for cut in [0, 4, 8, 9, 16, good.len() / 3, good.len() / 2, good.len() - 9, good.len() - 1] {
        cases.push((format!("cut to {cut} bytes"), good[..cut].to_vec()));
    }
    cases.push(("not a checkpoint".into(), b"P6\n1 1\n255\n\0\0\0".to_vec()));
    let mut failures = Vec::new();
    for (i, (what, bytes)) in cases.iter().enumerate() {
        let file = format!("bad-{i:02}.bin");
        std::fs::write(dir.join(&file), bytes).unwrap();
        for command in ["eval", "segment"] {
            let out = sos(&[command, "run.toml", "--checkpoint", &file], &dir);
            let stderr = text(&out.stderr);
            if out.status.code() != Some(2) || !stderr.contains(&file) {
                failures.push(format!("{what}, sos {command} (exit {:?}): {}", out.status.code(), stderr.trim()));
            }
        }
    }
    assert!(failures.is_empty(), "damaged checkpoints not refused:\n{}", failures.join("\n"));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_checkpoint_holding_non_finite_parameters_is_refused_naming_the_section() {
    use sos_core::config::RunConfig;
    use sos_core::train::Session;
    let dir = temp_dir("sos-hostile", "non_finite_checkpoint");
    std::fs::write(dir.join("run.toml"), tiny(&dir, "nan")).unwrap();
    let mut session = Session::from_config(RunConfig::load(&dir.join("run.toml")).unwrap(), &dir).unwrap();
    let mut values = session.field.parameters();
    let n = values.len();
    values[n / 2] = f32::NAN;
    values[n - 1] = f32::INFINITY;
    session.field.set_parameters(&values).unwrap();
    session.save_checkpoint().unwrap();
    for command in ["eval", "segment"] {
        let out = sos(&[command, "run.toml"], &dir);
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "sos {command}: {stderr}");
        assert!(
            stderr.contains("checkpoint.bin") && stderr.contains("non-finite") && stderr.contains("field"),
            "{stderr}"
        );
    }
    let out = sos(&["train", "--resume", "run.toml"], &dir);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out.stderr));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn compare_refuses_what_is_not_a_mask_naming_the_file() {
    let dir = temp_dir("sos-hostile", "compare");
    let good = sos_core::image::GrayImage { width: 4, height: 3, data: vec![1.0; 12] };
    good.save_png(&dir.join("good.png")).unwrap();
    std::fs::write(dir.join("empty.png"), b"").unwrap();
    std::fs::write(dir.join("text.png"), b"not an image at all").unwrap();
    let png = std::fs::read(dir.join("good.png")).unwrap();
    std::fs::write(dir.join("cut.png"), &png[..png.len() / 2]).unwrap();
    std::fs::create_dir_all(dir.join("folder.png")).unwrap();
    std::fs::write(dir.join("blocker"), "x").unwrap();
    let cases: [(&[&str], &str); 9] = [
        (&["missing.png", "good.png"], "missing.png"),
        (&["good.png", "missing.png"], "missing.png"),
        (&["empty.png", "good.png"], "empty.png"),
        (&["good.png", "empty.png"], "empty.png"),
        (&["text.png", "good.png"], "text.png"),
        (&["good.png", "cut.png"], "cut.png"),
        (&["folder.png", "good.png"], "folder.png"),
        (&["good.png", "folder.png"], "folder.png"),
        (&["good.png", "good.png", "--out", "blocker/report.json"], "blocker"),
    ];
    let mut failures = Vec::new();
    for (args, named) in cases {
        let mut all = vec!["compare"];
        all.extend_from_slice(args);
        let out = sos(&all, &dir);
        let stderr = text(&out.stderr);
        if out.status.code() != Some(2) || !stderr.contains(named) || stderr.contains("panicked") {
            failures.push(format!("sos {} (exit {:?}): {}", all.join(" "), out.status.code(), stderr.trim()));
        }
    }
    assert!(failures.is_empty(), "compare accepted bad input:\n{}", failures.join("\n"));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_teacher_cell_as_wide_as_the_patch_is_refused_before_training() {
    let dir = temp_dir("sos-hostile", "wide_cell");
    let mut config: toml::Table = tiny(&dir, "wide_cell").parse().unwrap();
    let segment = config.get_mut("segment").and_then(toml::Value::as_table_mut).unwrap();
    segment.insert("steps".into(), 1.into());
    segment.insert("patch_size".into(), 16.into());
    let mut extractor = toml::Table::new();
    extractor.insert("kind".into(), "cell-stats".into());
    extractor.insert("cell".into(), 16.into());
    config.insert("extractor".into(), extractor.into());
    std::fs::write(dir.join("wide.toml"), toml::to_string(&config).unwrap()).unwrap();
    let out = sos(&["train", "wide.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    for part in ["wide.toml", "[extractor]", "`cell`", "segment.patch_size", "at most 8 px"] {
        assert!(stderr.contains(part), "the error does not name {part}: {stderr}");
    }
    assert!(!dir.join("runs/wide_cell/checkpoint.bin").exists(), "stage 1 ran");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_missing_scene_path_is_named_as_the_missing_key() {
    let dir = temp_dir("sos-hostile", "no_path");
    let mut failures = Vec::new();
    for scene in registrations::<dyn DatasetConfig>() {
        let mut base = init_config(&dir, scene.kind, "voxel-grid");
        let Some(table) = base.get_mut("scene").and_then(toml::Value::as_table_mut) else { continue };
        if table.remove("path").is_none() {
            continue; // a kind without a capture folder (the generator)
        }
        let file = format!("{}.toml", scene.kind);
        std::fs::write(dir.join(&file), toml::to_string(&base).unwrap()).unwrap();
        let out = sos(&["train", &file], &dir);
        let stderr = text(&out.stderr);
        if out.status.code() != Some(2) || !stderr.contains("[scene] path") || !stderr.contains("required") {
            failures.push(format!("{} (exit {:?}): {}", scene.kind, out.status.code(), stderr.trim()));
        }
    }
    assert!(failures.is_empty(), "a missing `path` not named:\n{}", failures.join("\n"));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_downscale_that_leaves_no_image_is_blamed() {
    let dir = temp_dir("sos-hostile", "downscale");
    let scene = sos_datasets::synthetic::generate(&sos_datasets::synthetic::SyntheticConfig {
        width: 64,
        height: 48,
        views: 8,
        ..Default::default()
    });
    let layout = dir.join("blender");
    sos_datasets::layouts::Format::Blender.write(&scene, &layout).unwrap();
    let config = format!("[scene]\nkind = \"blender\"\npath = \"{}\"\ndownscale = 16\n", layout.display());
    std::fs::write(dir.join("run.toml"), config).unwrap();
    let out = sos(&["train", "run.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("`downscale`") && stderr.contains("4x3"), "{stderr}");
    // LLFF: a factor that leaves no image, a width that would upsample to terabytes.
    let llff = dir.join("llff");
    sos_datasets::layouts::Format::Llff.write(&scene, &llff).unwrap();
    for (key, value) in [("factor", "16"), ("width", "1000000")] {
        let config = format!("[scene]\nkind = \"llff\"\npath = \"{}\"\n{key} = {value}\n", llff.display());
        std::fs::write(dir.join("llff.toml"), config).unwrap();
        let out = sos(&["train", "llff.toml"], &dir);
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{key} = {value}: {stderr}");
        assert!(stderr.contains(&format!("`{key}`")) && stderr.contains("llff.toml"), "{key} = {value}: {stderr}");
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_run_without_held_out_views_reports_no_score() {
    let dir = temp_dir("sos-hostile", "no_test_views");
    let mut config: toml::Table = toml::from_str(&tiny(&dir, "none")).unwrap();
    config["scene"].as_table_mut().unwrap().insert("hold_out_every".into(), 0.into());
    std::fs::write(dir.join("run.toml"), toml::to_string(&config).unwrap()).unwrap();
    for command in ["train", "eval"] {
        let out = sos(&[command, "run.toml"], &dir);
        let (stdout, stderr) = (text(&out.stdout), text(&out.stderr));
        assert!(out.status.success(), "sos {command}: {stderr}");
        assert!(stdout.contains("no held-out views"), "sos {command}: {stdout}");
        for nonsense in ["NaN", "nan", "inf", "120.00"] {
            assert!(!stdout.contains(nonsense), "sos {command} printed {nonsense}: {stdout}");
        }
    }
    std::fs::remove_dir_all(dir).ok();
}
