//! `sos train`: stage 1, then evaluation of the held-out views.

use std::path::Path;
use std::time::Instant;

use anyhow::Context;
use sos_core::train::evaluate::evaluate_views;
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;

pub fn run(config: &Path, resume: bool, progress: bool) -> anyhow::Result<()> {
    let started = Instant::now();
    let mut session = Session::open(config)?;
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
    if resume && session.checkpoint_path().exists() {
        session.load_checkpoint(None)?;
        eprintln!("resumed at step {}", session.step);
    }
    let stats = train_photometric(&mut session, progress)?;
    let train_seconds = started.elapsed().as_secs_f64();
    eprintln!("stage 1 done: {} steps, last batch PSNR {:.2} dB, {:.1} s", session.step, stats.psnr, train_seconds);
    let eval = evaluate_views(&session, session.config.render.test_views)?;
    let report = serde_json::json!({
        "scene": session.scene.name,
        "field": session.field_kind,
        "steps": session.step,
        "train_seconds": train_seconds,
        "test": eval,
    });
    super::write_json(&session.run_dir.join("metrics.json"), &report).context("writing metrics")?;
    println!("held-out PSNR {:.2} dB (mean of per-view {:.2} dB) over {} views", eval.psnr, eval.psnr_mean_per_view, eval.views.len());
    println!("render speed {:.0} rays/s; outputs in {}", eval.render_rays_per_second, session.run_dir.display());
    Ok(())
}
