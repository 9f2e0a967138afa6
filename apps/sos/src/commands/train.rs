//! `sos train`: stage 1, then (when `segment.steps > 0`) stage 2 and mask inference, which
//! also measures the held-out colour; without stage 2, an evaluation of the held-out views.

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use sos_core::segment::train::Segmenter;
use sos_core::train::evaluate::{evaluate_views, overfitting_warning, ImageEval};
use sos_core::train::face_pileup::face_pileup_warning;
use sos_core::train::photometric::{train_photometric_observed, StepStats};
use sos_core::train::Session;

use super::stage2;
use crate::console::Console;

/// `sos train`: stage 1, then stage 2 and masks (or an evaluation without stage 2).
pub fn run(config: &Path, resume: bool, progress: bool) -> anyhow::Result<()> {
    let started = Instant::now();
    let mut session = Session::open(config)?;
    // Stage 2's teacher is loaded now: a missing weights file should not wait for stage 1.
    let segmenter = if session.config.segment.steps > 0 { Some(Segmenter::build(&session)?) } else { None };
    // Refuses a folder another run uses, or one that cannot be written, before any work (and
    // after every config error, which leaves no folder behind).
    let _claim = session.claim_run_dir()?;
    eprintln!(
        "scene `{}`: {} views ({} train, {} test), {}x{}; field `{}` with {} parameters",
        session.scene.name,
        session.scene.views.len(),
        session.scene.train.len(),
        session.scene.test.len(),
        session.scene.views[0].camera.width,
        session.scene.views[0].camera.height,
        session.field_kind,
        session.field.num_parameters()
    );
    super::announce_resolved(&session)?;
    if resume && session.checkpoint_path().exists() {
        session.load_checkpoint(None)?;
        eprintln!("resumed at step {}", session.step);
    }
    let stats = train_photometric_observed(&mut session, &mut Console::new(progress))?;
    let train_seconds = started.elapsed().as_secs_f64();
    eprintln!("stage 1 done: {} steps, last batch PSNR {:.2} dB, {:.1} s", session.step, stats.psnr, train_seconds);
    let metrics_path = session.run_dir.join("metrics.json");
    let mut report = serde_json::json!({
        "scene": session.scene.name,
        "field": session.field_kind,
        "seeds": stage2::seeds(&session),
        "steps": session.step,
        "rays_per_step": session.config.train.rays_per_step,
        "train_seconds": train_seconds,
        "timing": { "stage1_seconds": train_seconds },
        "derived": session.derived,
    });
    if let Some(step) = session.converged_at {
        report["stage1_converged_at"] = step.into();
    }
    if let Some(faces) = stats.faces {
        report["stage1_faces"] = serde_json::to_value(faces)?;
    }
    let trained = match segmenter {
        None => {
            let eval_started = Instant::now();
            let eval = evaluate_views(&session, session.config.render.test_views)?;
            report["timing"]["stage1_eval_seconds"] = eval_started.elapsed().as_secs_f64().into();
            print_image_eval(&eval)?;
            record_warnings(&stats, &eval, &mut report);
            say!("render speed {:.0} rays/s; outputs in {}", eval.render_rays_per_second, session.run_dir.display())?;
            report["test"] = serde_json::to_value(&eval)?;
            None
        }
        Some(seg) => {
            // Written now so stage-1 results survive a failing stage 2.
            super::write_json(&metrics_path, &report).context("writing metrics")?;
            let s2 = stage2::train(&mut session, seg, progress)?;
            // Mask inference renders and measures the held-out colour as well, so the field's
            // image quality comes from that pass instead of a second rendering of the views.
            let extractor = Some(s2.seg.teacher.extractor());
            let masks = stage2::masks(&session, &s2.seg.head, extractor, session.config.render.test_views)?;
            let camera = |i: usize| &session.scene.views[i].camera;
            let rays = session.scene.test.iter().map(|&i| camera(i).width as usize * camera(i).height as usize).sum();
            let eval = ImageEval::from_report(&masks.image, rays, masks.seconds);
            print_image_eval(&eval)?;
            record_warnings(&stats, &eval, &mut report);
            report["test"] = serde_json::to_value(&eval)?;
            report["stage2"] = stage2::report(&session, s2.seg.step, Some(s2.seconds), Some(&s2.stats), &masks);
            report["timing"]["stage2_seconds"] = s2.seconds.into();
            report["timing"]["masks_seconds"] = masks.seconds.into();
            Some(s2)
        }
    };
    report["timing"]["total_seconds"] = started.elapsed().as_secs_f64().into();
    super::write_json(&metrics_path, &report).context("writing metrics")?;
    say!("metrics in {}", metrics_path.display())?;
    super::render::camera_path_after_training(&session, trained.as_ref(), progress)
}

/// Prints (and records in the metrics) warnings about stage 1: content cut off by the box,
/// held-out views far worse than the training rays.
fn record_warnings(stats: &StepStats, eval: &ImageEval, report: &mut serde_json::Value) {
    let warnings: Vec<String> = stats
        .faces
        .as_ref()
        .and_then(face_pileup_warning)
        .into_iter()
        .chain(overfitting_warning(stats.psnr, eval.psnr))
        .collect();
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if !warnings.is_empty() {
        report["warnings"] = serde_json::json!(warnings);
    }
}

/// The held-out quality line (a notice instead when the scene holds out no views).
pub(super) fn print_image_eval(eval: &ImageEval) -> anyhow::Result<()> {
    if eval.views.is_empty() {
        return say!("no held-out views: PSNR and SSIM not measured (set the scene's hold-out, e.g. `hold_out_every`)");
    }
    if ![eval.psnr, eval.psnr_mean_per_view, eval.ssim].iter().all(|v| v.is_finite()) {
        return say!(
            "held-out PSNR and SSIM not measured: the field renders non-finite colours on {} views \
             (it diverged; retrain with a lower learning rate)",
            eval.views.len()
        );
    }
    say!(
        "held-out PSNR {:.2} dB (mean of per-view {:.2} dB), SSIM {:.4}, over {} views",
        eval.psnr,
        eval.psnr_mean_per_view,
        eval.ssim,
        eval.views.len()
    )
}
