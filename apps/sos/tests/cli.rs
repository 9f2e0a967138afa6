//! End-to-end tests of the `sos` binary: plugin listing, `init` round trips, config errors
//! (exit code 2 naming the file and key), and a tiny two-stage run with its outputs.

use std::path::PathBuf;

use sos_core::config::RunConfig;
// Link the plugin registrations so configs with plugin kinds parse in this test binary.
use sos_plugins as _;

mod common;

use common::{sos, text};

fn temp_dir(test: &str) -> PathBuf {
    common::temp_dir("sos-cli", test)
}

/// The tiny run of the end-to-end tests: 80x60, 10 views, 24³ grid, 60 + `seg_steps` steps.
fn tiny_config(name: &str, train_steps: usize, seg_steps: usize) -> String {
    format!(
        r#"name = "{name}"
seed = 3

[scene]
kind = "synthetic"
width = 80
height = 60
views = 10
hold_out_every = 5
render_path_views = 2

[field]
kind = "voxel-grid"
resolution = [24, 24, 24]
initial_resolution = [16, 16, 16]

[train]
steps = {train_steps}
rays_per_step = 1024
checkpoint_every = 0

[render]
chunk = 4096

[segment]
steps = {seg_steps}
patches = 4
patch_size = 16
stride = 2
"#
    )
}

#[test]
fn list_names_the_default_plugins() {
    let out = sos(&["list"], &std::env::temp_dir());
    assert!(out.status.success(), "{}", text(&out.stderr));
    let stdout = text(&out.stdout);
    for kind in ["voxel-grid", "synthetic", "cell-stats", "cls-cosine", "appearance", "geometry"] {
        assert!(stdout.contains(kind), "`sos list` does not name {kind}:\n{stdout}");
    }
    // Each kind names the crate that declared it.
    for (kind, krate) in [
        ("voxel-grid", "sos-plugins"),
        ("synthetic", "sos-datasets"),
        ("cell-stats", "sos-backbones"),
        ("appearance", "sos-losses"),
    ] {
        let line = stdout.lines().find(|l| l.split_whitespace().next() == Some(kind)).expect("listed");
        assert!(line.contains(&format!("({krate})")), "`sos list` does not name {kind}'s crate {krate}: {line}");
    }
}

#[test]
fn colour_keys_are_spelled_colour_and_accept_color() {
    let path = std::path::Path::new("colour.toml");
    let base = "[scene]\nkind = \"synthetic\"\n[train]\n";
    for key in ["sample_colour_weight", "sample_color_weight"] {
        let config = RunConfig::parse(&format!("{base}{key} = 0.25\n"), path).expect(key);
        assert_eq!(config.train.sample_colour_weight, 0.25, "{key}");
        assert!(config.to_toml().contains("sample_colour_weight = 0.25"), "{key} is written as `colour`");
    }
    for (key, written) in [("lr_color", "lr_colour"), ("tv_color", "tv_colour"), ("lr_colour", "lr_colour")] {
        let text = format!("[scene]\nkind = \"synthetic\"\n[field]\nkind = \"voxel-grid\"\n{key} = 0.125\n");
        let config = RunConfig::parse(&text, path).expect(key);
        assert!(config.to_toml().contains(&format!("{written} = 0.125")), "{key} is written as `{written}`");
    }
}

#[test]
fn init_output_parses_back_and_round_trips() {
    let dir = temp_dir("init");
    let out = sos(&["init"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let written = text(&out.stdout);
    let path = dir.join("init.toml");
    let config = RunConfig::parse(&written, &path).expect("`sos init` output parses");
    let again = RunConfig::parse(&config.to_toml(), &path).expect("re-serialised config parses");
    assert_eq!(config.to_toml(), again.to_toml());
    assert!(written.contains("[masks]") && written.contains("[segment]"), "{written}");

    // Writing to a file works once and then refuses to overwrite.
    let out = sos(&["init", "run.toml"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(RunConfig::load(&dir.join("run.toml")).is_ok());
    let out = sos(&["init", "run.toml"], &dir);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("run.toml"), "{}", text(&out.stderr));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn printing_to_a_full_disk_is_an_error_not_a_panic() {
    let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") else { return };
    for command in ["init", "list"] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_sos"))
            .arg(command)
            .stdout(full.try_clone().unwrap())
            .output()
            .unwrap();
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{command}: {stderr}");
        assert!(stderr.contains("standard output") && !stderr.contains("panicked"), "{command}: {stderr}");
    }
}

#[test]
fn config_errors_exit_2_naming_the_file_and_key() {
    let dir = temp_dir("errors");
    let good = tiny_config("errors", 1, 0);
    let cases = [
        ("unknown-kind.toml", good.replace("kind = \"voxel-grid\"", "kind = \"voxel-grud\""), "voxel-grud"),
        ("unknown-key.toml", good.replace("resolution = [24", "resolutoin = [24"), "resolutoin"),
        ("bad-value.toml", good.replace("rays_per_step = 1024", "rays_per_step = 0"), "train.rays_per_step"),
    ];
    for (file, config, key) in cases {
        assert_ne!(config, good, "case {file} did not change the config");
        std::fs::write(dir.join(file), config).unwrap();
        for command in ["train", "segment", "eval"] {
            let out = sos(&[command, file], &dir);
            let stderr = text(&out.stderr);
            assert_eq!(out.status.code(), Some(2), "sos {command} {file}: {stderr}");
            assert!(stderr.contains(file) && stderr.contains(key), "sos {command} {file}: {stderr}");
        }
    }
    // A missing checkpoint names the file and what to do.
    std::fs::write(dir.join("good.toml"), &good).unwrap();
    let out = sos(&["segment", "good.toml", "--checkpoint", "missing.bin"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("missing.bin") && stderr.contains("sos train"), "{stderr}");
    std::fs::remove_dir_all(dir).ok();
}

/// Numbers at these JSON pointers must be present and finite.
fn assert_finite(json: &serde_json::Value, pointers: &[&str]) {
    for p in pointers {
        let v = json.pointer(p).unwrap_or_else(|| panic!("{p} missing in {json:#}"));
        let x = v.as_f64().unwrap_or_else(|| panic!("{p} is not a number: {v}"));
        assert!(x.is_finite(), "{p} = {x}");
    }
}

#[test]
fn tiny_two_stage_run_writes_masks_and_metrics() {
    let dir = temp_dir("e2e");
    std::fs::write(dir.join("tiny.toml"), tiny_config("tiny", 60, 10)).unwrap();
    let started = std::time::Instant::now();
    let out = sos(&["train", "tiny.toml", "--quiet"], &dir);
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{}\n{}", stdout, text(&out.stderr));
    assert!(started.elapsed().as_secs() < 60, "tiny run took {:?}", started.elapsed());
    // The built-in scene knows its depth: the table measures the geometry too.
    for header in ["ARI", "IoU BG", "IoU FG", "mIoU", "PSNR", "SSIM", "depth err", "mean"] {
        assert!(stdout.contains(header), "table lacks {header}:\n{stdout}");
    }

    let run = dir.join("runs").join("tiny");
    // hold_out_every = 5 of 10 views: two held-out views.
    let masks: Vec<PathBuf> = std::fs::read_dir(run.join("masks")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(masks.len(), 2, "{masks:?}");
    for m in &masks {
        let name = m.file_name().unwrap();
        assert!(run.join("overlays").join(name).is_file(), "no overlay for {name:?}");
        assert!(run.join("test").join(name).is_file(), "no rendered view for {name:?}");
        assert!(run.join("mask_evidence").join(name).is_file(), "no mask evidence for {name:?}");
        assert!(run.join("depth").join(name).is_file(), "no rendered depth for {name:?}");
        let bytes = std::fs::read(m).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
    }
    let metrics: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("metrics.json")).unwrap()).unwrap();
    assert_finite(
        &metrics,
        &[
            "/test/psnr",
            "/stage2/test/segmentation/mean_ari",
            "/stage2/test/segmentation/miou",
            "/stage2/test/image/mean_psnr",
            "/stage2/test/image/mean_ssim",
            "/stage2/test/depth_error",
            "/timing/stage1_seconds",
            "/timing/stage2_seconds",
            "/timing/masks_seconds",
            "/seeds/run",
            "/steps",
            "/stage2/steps",
        ],
    );
    assert_eq!(metrics["stage2"]["steps"], 10);
    assert_eq!(metrics["seeds"]["run"], 3);
    assert_eq!(metrics["stage2"]["test"]["views"].as_array().unwrap().len(), 2);
    let depth_error = metrics["stage2"]["test"]["depth_error"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&depth_error), "depth error {depth_error}");

    // The head was checkpointed: inference alone reproduces the masks exactly.
    let before: Vec<Vec<u8>> = masks.iter().map(|m| std::fs::read(m).unwrap()).collect();
    let out = sos(&["segment", "tiny.toml", "--masks-only"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let after: Vec<Vec<u8>> = masks.iter().map(|m| std::fs::read(m).unwrap()).collect();
    assert!(before == after, "masks from the saved head differ from those after training");

    // `eval` reports segmentation metrics from the saved head.
    let out = sos(&["eval", "tiny.toml"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let eval: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("eval.json")).unwrap()).unwrap();
    assert_finite(&eval, &["/stage2/test/segmentation/mean_ari", "/stage2/test/segmentation/iou_bg"]);
    assert_eq!(eval["stage2"]["test"]["segmentation"], metrics["stage2"]["test"]["segmentation"]);

    // `render` writes masks of the camera path too.
    let out = sos(&["render", "tiny.toml"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    for sub in ["path", "path_masks", "path_overlays"] {
        assert!(run.join(sub).join("0001.png").is_file(), "no {sub}/0001.png");
    }

    // A head of another shape than the config's: inference refuses it, saying what to do, and
    // `sos segment` trains a new one in its place.
    std::fs::write(dir.join("tiny.toml"), format!("{}\n[head]\noutputs = 3\n", tiny_config("tiny", 60, 2))).unwrap();
    let out = sos(&["segment", "tiny.toml", "--masks-only"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("2 logits") && stderr.contains("without --masks-only"), "{stderr}");
    let out = sos(&["segment", "tiny.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let out = sos(&["segment", "tiny.toml", "--masks-only"], &dir);
    assert!(out.status.success(), "the retrained head does not load: {}", text(&out.stderr));
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn masks_only_without_a_head_says_what_to_do() {
    let dir = temp_dir("nohead");
    std::fs::write(dir.join("s1.toml"), tiny_config("nohead", 2, 0)).unwrap();
    let out = sos(&["train", "s1.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(!dir.join("runs/nohead/masks").exists(), "stage 2 ran with segment.steps = 0");
    let out = sos(&["segment", "s1.toml", "--masks-only"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("checkpoint.bin") && stderr.contains("no segmentation head"), "{stderr}");
    // Stage 2 with steps = 0 is refused, naming the key.
    let out = sos(&["segment", "s1.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("s1.toml") && stderr.contains("segment.steps"), "{stderr}");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn ablations_run_from_config_alone() {
    // Appearance-only loss list and joint training (photometric weight > 0, trainable field).
    let dir = temp_dir("ablation");
    let config = format!(
        "{}photometric_weight = 1.0\nlogits = \"composited\"\n\n[[loss]]\nkind = \"appearance\"\nweight = 1.0\n",
        tiny_config("ablation", 30, 4)
    );
    std::fs::write(dir.join("ablation.toml"), config).unwrap();
    let out = sos(&["train", "ablation.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}\n{}", text(&out.stdout), text(&out.stderr));
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("runs/ablation/metrics.json")).unwrap()).unwrap();
    let terms: Vec<String> = metrics["stage2"]["last_step"]["terms"]
        .as_array()
        .expect("stage-2 terms are recorded")
        .iter()
        .map(|t| t[0].as_str().unwrap().to_owned())
        .collect();
    assert!(terms.iter().any(|t| t.starts_with("appearance")), "{terms:?}");
    assert!(terms.iter().any(|t| t == "photometric"), "{terms:?}");
    assert!(!terms.iter().any(|t| t.starts_with("geometry")), "{terms:?}");
    for t in metrics["stage2"]["last_step"]["terms"].as_array().unwrap() {
        assert!(t[1].as_f64().unwrap().is_finite(), "{t:?}");
    }
}

#[test]
fn render_settings_choose_what_a_finished_run_writes() {
    let dir = temp_dir("render-settings");
    let render = "chunk = 4096\ntest_views = false\ncamera_path = true\n";
    // Two stages: masks are measured but not written; the camera path gets frames and masks.
    std::fs::write(dir.join("both.toml"), tiny_config("both", 30, 4).replace("chunk = 4096\n", render)).unwrap();
    let out = sos(&["train", "both.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}\n{}", text(&out.stdout), text(&out.stderr));
    let run = dir.join("runs").join("both");
    for sub in ["masks", "overlays", "test", "mask_evidence"] {
        assert!(!run.join(sub).exists(), "{sub}/ written with render.test_views = false");
    }
    let metrics: serde_json::Value = serde_json::from_slice(&std::fs::read(run.join("metrics.json")).unwrap()).unwrap();
    assert_finite(&metrics, &["/stage2/test/segmentation/miou"]);
    for sub in ["path", "path_masks", "path_overlays"] {
        assert!(run.join(sub).join("0001.png").is_file(), "no {sub}/0001.png with render.camera_path = true");
    }
    // Stage 1 alone: colour frames of the path, nothing of masks.
    std::fs::write(dir.join("one.toml"), tiny_config("one", 30, 0).replace("chunk = 4096\n", render)).unwrap();
    let out = sos(&["train", "one.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let run = dir.join("runs").join("one");
    assert!(run.join("path").join("0001.png").is_file() && !run.join("path_masks").exists());
    assert!(!run.join("test").exists(), "test/ written with render.test_views = false");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn compare_scores_a_mask_against_a_resized_reference() {
    let dir = temp_dir("compare");
    // Reference at twice the prediction's size: the left half is foreground.
    let mut reference = sos_core::image::GrayImage { width: 40, height: 20, data: vec![0.0; 800] };
    for r in 0..20 {
        for c in 0..20 {
            reference.data[r * 40 + c] = 1.0;
        }
    }
    reference.save_png(&dir.join("reference.png")).unwrap();
    // Prediction: the left quarter is foreground, so IoU(FG) = 1/2 and IoU(BG) = 10/15.
    let mut pred = sos_core::image::GrayImage { width: 20, height: 10, data: vec![0.0; 200] };
    for r in 0..10 {
        for c in 0..5 {
            pred.data[r * 20 + c] = 1.0;
        }
    }
    pred.save_png(&dir.join("pred.png")).unwrap();
    let out = sos(&["compare", "pred.png", "reference.png", "--out", "cmp.json"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("cmp.json")).unwrap()).unwrap();
    assert!((json["iou_fg"].as_f64().unwrap() - 0.5).abs() < 1e-9, "{json}");
    assert!((json["iou_bg"].as_f64().unwrap() - 10.0 / 15.0).abs() < 1e-9, "{json}");
    assert!(text(&out.stdout).contains("IoU(FG) 0.5000"));

    // Its result line cannot be written: an error naming standard output, not a panic.
    if let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_sos"))
            .args(["compare", "pred.png", "reference.png"])
            .current_dir(&dir)
            .stdout(full)
            .output()
            .unwrap();
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{stderr}");
        assert!(stderr.contains("standard output") && !stderr.contains("panicked"), "{stderr}");
    }

    let missing = sos(&["compare", "pred.png", "nowhere.png"], &dir);
    assert_eq!(missing.status.code(), Some(2));
    assert!(text(&missing.stderr).contains("nowhere.png"), "{}", text(&missing.stderr));
}

#[test]
fn a_corrupt_dataset_file_exits_2_naming_it() {
    use sos_plugins::datasets::{generate, Format, SyntheticConfig};
    let dir = temp_dir("corrupt-colmap");
    let scene = generate(&SyntheticConfig {
        width: 40,
        height: 30,
        views: 6,
        hold_out_every: 3,
        render_path_views: 2,
        ..Default::default()
    });
    let data = dir.join("scene");
    Format::ColmapBin.write(&scene, &data).unwrap();
    let images_bin = data.join("sparse/0/images.bin");
    let bytes = std::fs::read(&images_bin).unwrap();
    std::fs::write(&images_bin, &bytes[..bytes.len() / 2]).unwrap();
    let config = tiny_config("corrupt", 1, 0).replace(
        "[scene]\nkind = \"synthetic\"\nwidth = 80\nheight = 60\nviews = 10\nhold_out_every = 5\nrender_path_views = 2\n",
        "[scene]\nkind = \"colmap\"\npath = \"scene\"\n",
    );
    assert!(config.contains("kind = \"colmap\""), "the scene section was not replaced");
    std::fs::write(dir.join("corrupt.toml"), config).unwrap();
    let out = sos(&["train", "corrupt.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("images.bin"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn missing_teacher_weights_exit_2_before_stage_1() {
    let dir = temp_dir("no-weights");
    std::fs::create_dir_all(dir.join("sub")).unwrap();
    // Thousands of stage-1 steps: the error must come before any of them.
    let config = format!(
        "{}\n[extractor]\nkind = \"dino-vit\"\nweights = \"models/dino.pth\"\n",
        tiny_config("no-weights", 5000, 10)
    );
    std::fs::write(dir.join("sub/dino.toml"), config).unwrap();
    let started = std::time::Instant::now();
    let out = sos(&["train", "sub/dino.toml", "--quiet"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(started.elapsed().as_secs() < 20, "took {:?}: {stderr}", started.elapsed());
    // Named where it was looked for: beside the config file, not in the working directory.
    let expected = dir.join("sub/models/dino.pth");
    assert!(stderr.contains(&expected.display().to_string()) && stderr.contains("not found"), "{stderr}");
    assert!(!stderr.contains("stage 1") && !stderr.contains("panicked"), "{stderr}");
    assert!(text(&out.stdout).is_empty(), "{}", text(&out.stdout));
    assert!(!dir.join("sub/runs").exists(), "outputs were written");
    std::fs::remove_dir_all(dir).ok();
}
