//! Degenerate scenes end to end: all-black images, a single training view, collinear cameras.
//! A short two-stage run on each either completes with finite metrics or stops with a clear
//! `RunError`; no reported metric is NaN or infinite. Only a field that renders NaN reports
//! NaN, rather than passing for a perfect render.

use std::path::Path;

use sos_core::camera::{normalize, Camera, Vec3};
use sos_core::config::RunConfig;
use sos_core::error::RunError;
use sos_core::image::RgbImage;
use sos_core::plugin::{FieldTape, RadianceField};
use sos_core::segment::evaluate::{evaluate_masks, MaskEval};
use sos_core::segment::infer::MaskInference;
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::evaluate::{evaluate_views, ImageEval};
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;
use sos_datasets::synthetic::OBJECT_CENTRE;
// Links every plugin (datasets, extractors, losses) so the config kinds resolve.
use sos_plugins as _;

/// A tiny session on the synthetic scene: 40x30 views, a 16³ grid, 30 + 4 steps; `field` and
/// `extra` are more lines for the `[field]` table and the end of the config.
fn session(tag: &str, views: usize, hold_out_every: usize, field: &str, extra: &str) -> Session {
    let text = format!(
        r#"
name = "degenerate-{tag}"
[scene]
kind = "synthetic"
width = 40
height = 30
views = {views}
hold_out_every = {hold_out_every}
render_path_views = 2
[field]
kind = "voxel-grid"
resolution = [16, 16, 16]
initial_resolution = [16, 16, 16]
upsample_at = []
{field}
[train]
steps = 30
rays_per_step = 512
samples_per_ray = 48
occupancy = false
checkpoint_every = 0
[segment]
steps = 4
patches = 2
patch_size = 8
stride = 2
[masks]
restarts = 2
{extra}
"#
    );
    let config = RunConfig::parse(&text, Path::new("degenerate.toml")).unwrap();
    // In Cargo's scratch folder for integration tests, emptied first: reruns reuse it.
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("degenerate-{tag}"));
    std::fs::remove_dir_all(&dir).ok();
    Session::from_config(config, &dir).unwrap()
}

/// What a run reported.
struct Outcome {
    stage1: ImageEval,
    masks: MaskEval,
    /// The summary `sos train` writes from the mask pass.
    test: ImageEval,
}

/// Stage 1, its evaluation, stage 2 and mask inference, as `sos train` runs them.
fn two_stages(session: &mut Session) -> Result<Outcome, RunError> {
    let result = (|| {
        train_photometric(session)?;
        let stage1 = evaluate_views(session, false)?;
        let mut seg = Segmenter::build(session)?;
        train_segmentation(session, &mut seg)?;
        let inference = MaskInference::new(session, &seg.head, Some(seg.teacher.extractor()))?;
        let masks = evaluate_masks(session, &inference, false)?;
        let test = ImageEval::from_report(&masks.image, 1, masks.seconds);
        Ok(Outcome { stage1, masks, test })
    })();
    std::fs::remove_dir_all(&session.run_dir).ok();
    result
}

fn assert_image_eval_finite(eval: &ImageEval, what: &str) {
    for (name, v) in [("psnr", eval.psnr), ("psnr_mean_per_view", eval.psnr_mean_per_view), ("ssim", eval.ssim)] {
        assert!(v.is_finite(), "{what}: {name} = {v}");
    }
    for v in &eval.views {
        assert!(v.psnr.is_finite() && v.mse.is_finite() && v.ssim.is_finite(), "{what}: {v:?}");
    }
}

/// Every reported number is finite; segmentation metrics exist where the view has a mask.
fn assert_finite_metrics(out: &Outcome, test_views: usize, what: &str) {
    assert_image_eval_finite(&out.stage1, &format!("{what}, stage 1"));
    assert_image_eval_finite(&out.test, &format!("{what}, mask pass"));
    assert_eq!(out.masks.views.len(), test_views, "{what}");
    for v in &out.masks.views {
        let ari = v.ari.unwrap_or_else(|| panic!("{what}: view {} has a mask but no ARI", v.view));
        assert!(ari.is_finite() && (-0.5..=1.0).contains(&ari), "{what}: {v:?}");
        for iou in [v.iou_bg, v.iou_fg, v.miou].into_iter().flatten() {
            assert!((0.0..=1.0).contains(&iou), "{what}: {v:?}");
        }
        assert!(v.miou.is_some(), "{what}: {v:?}");
        assert!(v.psnr.is_finite() && v.ssim.is_finite(), "{what}: {v:?}");
        assert!((0.0..=1.0).contains(&v.foreground_fraction) && v.clusters >= 1, "{what}: {v:?}");
    }
    let seg = &out.masks.segmentation;
    assert!(seg.mean_ari().is_some_and(f64::is_finite), "{what}");
    assert!(seg.iou().miou.is_some_and(f64::is_finite), "{what}");
    // JSON writes non-finite numbers as null: none may appear but the undefined IoUs.
    let json = serde_json::to_value(&out.masks).unwrap();
    let mut nulls = Vec::new();
    find_nulls(&json, String::new(), &mut nulls);
    nulls.retain(|p| !(p.ends_with("iou_bg") || p.ends_with("iou_fg")));
    assert!(nulls.is_empty(), "{what}: null metrics {nulls:?}");
    let json = serde_json::to_value(&out.test).unwrap();
    find_nulls(&json, String::new(), &mut nulls);
    assert!(nulls.is_empty(), "{what}: null metrics {nulls:?}");
}

fn find_nulls(v: &serde_json::Value, path: String, out: &mut Vec<String>) {
    match v {
        serde_json::Value::Null => out.push(path),
        serde_json::Value::Array(a) => {
            a.iter().enumerate().for_each(|(i, v)| find_nulls(v, format!("{path}/{i}"), out))
        }
        serde_json::Value::Object(o) => o.iter().for_each(|(k, v)| find_nulls(v, format!("{path}/{k}"), out)),
        _ => {}
    }
}

#[test]
fn all_black_images_give_finite_metrics() {
    let mut s = session("black", 6, 3, "", "");
    for v in &mut s.scene.views {
        v.image = RgbImage::new(v.image.width, v.image.height);
    }
    let tests = s.scene.test.len();
    let out = two_stages(&mut s).expect("an all-black scene trains");
    assert_finite_metrics(&out, tests, "all black");
    // A field that learnt black renders black: a high but finite PSNR.
    assert!(out.test.psnr > 20.0, "{}", out.test.psnr);
}

#[test]
fn all_black_images_with_other_mask_rules_and_random_negatives_give_finite_metrics() {
    let masks = "normalize = true\nsoftmax = true\nforeground = \"saliency\"\nkeep = \"all\"";
    let mut s = session("black-random", 6, 3, "", &format!("{masks}\n[miner]\nkind = \"random\""));
    for v in &mut s.scene.views {
        v.image = RgbImage::new(v.image.width, v.image.height);
    }
    let tests = s.scene.test.len();
    let out = two_stages(&mut s).expect("an all-black scene trains");
    assert_finite_metrics(&out, tests, "all black, saliency rule, random miner");
}

#[test]
fn a_single_training_view_gives_finite_metrics() {
    let mut s = session("single", 2, 2, "", "");
    assert_eq!((s.scene.train.len(), s.scene.test.len()), (1, 1));
    let out = two_stages(&mut s).expect("one training view is enough to run");
    assert_finite_metrics(&out, 1, "single view");
}

#[test]
fn collinear_cameras_give_finite_metrics() {
    let mut s = session("collinear", 6, 3, "", "");
    // Every camera on one line through the object, looking along it (the same way).
    let axis = normalize([0.0, 0.4, 1.0]);
    let c = OBJECT_CENTRE;
    for (i, v) in s.scene.views.iter_mut().enumerate() {
        let d = 1.6 + 0.15 * i as f32;
        let eye = [c[0] + d * axis[0], c[1] + d * axis[1], c[2] + d * axis[2]];
        let cam = &v.camera;
        v.camera = Camera::look_at(eye, c, [0.0, 1.0, 0.0], cam.width, cam.height, cam.fx);
    }
    s.scene.validate().expect("the collinear scene is well formed");
    let f0 = s.scene.views[0].camera.forward();
    assert!(s.scene.views.iter().all(|v| (sos_core::camera::dot(v.camera.forward(), f0) - 1.0).abs() < 1e-5));
    let tests = s.scene.test.len();
    let out = two_stages(&mut s).expect("collinear cameras run");
    assert_finite_metrics(&out, tests, "collinear");
}

/// Voxel-grid keys of a field whose every voxel starts with opacity `alpha`.
fn initial_opacity(alpha: f64) -> String {
    format!("alpha_init = {alpha:e}")
}

#[test]
fn an_empty_field_gives_finite_metrics() {
    // Opacity 1e-30 per voxel: every ray stays empty through both stages (no head samples).
    let mut s = session("empty", 6, 3, &initial_opacity(1e-30), "");
    let tests = s.scene.test.len();
    let out = two_stages(&mut s).expect("an empty field runs");
    assert_finite_metrics(&out, tests, "empty field");
    // Nothing rendered: zero logits everywhere, one cluster, one class in every mask.
    for v in &out.masks.views {
        assert!(v.foreground_fraction == 0.0 || v.foreground_fraction == 1.0, "{v:?}");
        assert_eq!(v.ari, Some(0.0), "{v:?}");
    }
}

#[test]
fn an_opaque_field_gives_finite_metrics() {
    let mut s = session("opaque", 6, 3, &initial_opacity(0.9999), "");
    let tests = s.scene.test.len();
    let out = two_stages(&mut s).expect("an opaque field runs");
    assert_finite_metrics(&out, tests, "opaque field");
}

/// The wrapped field with NaN colours: a diverged field.
struct NanColour(Box<dyn RadianceField>);

impl RadianceField for NanColour {
    sos_core::pass_on_field_methods!(0);

    fn forward(&self, p: &[Vec3], dirs: &[Vec3], d: &mut [f32], c: &mut [[f32; 3]], record: bool) -> FieldTape {
        let tape = self.0.forward(p, dirs, d, c, record);
        c.iter_mut().for_each(|c| *c = [f32::NAN; 3]);
        tape
    }
    fn backward(&mut self, p: &[Vec3], dirs: &[Vec3], tape: FieldTape, gd: &[f32], gc: &[[f32; 3]]) {
        self.0.backward(p, dirs, tape, gd, gc);
    }
    fn step(&mut self, lr_factor: f32) {
        self.0.step(lr_factor);
    }
}

#[test]
fn a_nan_render_is_not_reported_as_a_perfect_one() {
    let mut s = session("nan", 6, 3, "", "");
    s.field = Box::new(NanColour(s.config.field.build(&s.scene.extent, 0).unwrap()));
    let eval = evaluate_views(&s, false).unwrap();
    assert!(!eval.views.is_empty());
    // The 120 dB floor is for exact renders only: NaN must stay visible.
    assert!(eval.psnr.is_nan() && eval.views.iter().all(|v| v.psnr.is_nan()), "{:?}", eval.views);
}
