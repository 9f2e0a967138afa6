//! `sos eval`: metrics of a trained run on its held-out views (segmentation metrics too when
//! the checkpoint holds a segmentation head).

use std::path::Path;

use sos_core::segment::infer::saliency_extractor;
use sos_core::segment::store::load_with_head;
use sos_core::train::evaluate::evaluate_views;
use sos_core::train::Session;

use super::stage2;

/// `sos eval`: PSNR/SSIM of the held-out views, and segmentation metrics when a head exists.
pub fn run(config: &Path, checkpoint: Option<&Path>) -> anyhow::Result<()> {
    let mut session = Session::open(config)?;
    // Refuses a folder another run uses, or one that cannot be written, before any work.
    let _claim = session.claim_run_dir()?;
    let (loaded, ckpt_path) = load_with_head(&mut session, checkpoint)?;
    let eval = evaluate_views(&session, false)?;
    let mut report = serde_json::json!({
        "scene": session.scene.name,
        "field": session.field_kind,
        "seeds": stage2::seeds(&session),
        "steps": session.step,
        "test": eval,
    });
    say!("{:<24} {:>8} {:>8}", "view", "PSNR", "SSIM")?;
    for v in &eval.views {
        say!("{:<24} {:>8.2} {:>8.4}", v.view, v.psnr, v.ssim)?;
    }
    super::train::print_image_eval(&eval)?;
    match loaded {
        Some(loaded) => {
            say!()?;
            let extractor = saliency_extractor(&session)?;
            let masks = stage2::masks(&session, &loaded.head, extractor.as_deref(), false)?;
            report["stage2"] = stage2::report(&session, loaded.meta.steps, None, None, &masks);
        }
        None => eprintln!(
            "note: {} has no segmentation head, so no segmentation metrics; run `sos segment` first",
            ckpt_path.display()
        ),
    }
    super::write_json(&session.run_dir.join("eval.json"), &report)?;
    Ok(())
}
