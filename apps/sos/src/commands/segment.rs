//! `sos segment`: stage 2 from a stage-1 checkpoint, then mask inference on the held-out
//! views; with `--masks-only`, inference with the head already saved in the checkpoint.

use std::path::Path;
use std::time::Instant;

use anyhow::{bail, Context};
use sos_core::segment::infer::saliency_extractor;
use sos_core::segment::store::load_with_head;
use sos_core::segment::train::Segmenter;
use sos_core::train::Session;

use super::stage2;

/// `sos segment`: stage 2 and masks from a stage-1 checkpoint.
pub fn run(config: &Path, checkpoint: Option<&Path>, masks_only: bool, progress: bool) -> anyhow::Result<()> {
    let started = Instant::now();
    let mut session = Session::open(config)?;
    // Refuses a folder another run uses, or one that cannot be written, before any work.
    let _claim = session.claim_run_dir()?;
    // Training a new head needs only the field: a saved head of another shape (the `[head]`
    // settings changed since) is replaced, not refused.
    let (loaded, ckpt_path) = if masks_only {
        load_with_head(&mut session, checkpoint)?
    } else {
        (None, session.load_checkpoint_sections(checkpoint)?.1)
    };
    eprintln!("loaded {} (stage 1 at step {})", ckpt_path.display(), session.step);
    let metrics_path = session.run_dir.join("metrics.json");
    let (section, trained) = if masks_only {
        let Some(loaded) = loaded else {
            bail!(
                "checkpoint {} has no segmentation head; run `sos segment {}` without --masks-only to train one",
                ckpt_path.display(),
                config.display()
            );
        };
        let extractor = saliency_extractor(&session)?;
        let masks = stage2::masks(&session, &loaded.head, extractor.as_deref(), true)?;
        (stage2::report(&session, loaded.meta.steps, None, None, &masks), None)
    } else {
        if session.config.segment.steps == 0 {
            bail!(
                "invalid config {}: key `segment.steps` is 0, so there is no stage 2 to run; set it above 0 \
                 or pass --masks-only",
                config.display()
            );
        }
        let seg = Segmenter::build(&session)?;
        let s2 = stage2::train(&mut session, seg, progress)?;
        let extractor = Some(s2.seg.teacher.extractor());
        let masks = stage2::masks(&session, &s2.seg.head, extractor, session.config.render.test_views)?;
        (stage2::report(&session, s2.seg.step, Some(s2.seconds), Some(&s2.stats), &masks), Some(s2))
    };
    // Keep the stage-1 record of `sos train` and replace its stage-2 part.
    let mut report = std::fs::read(&metrics_path)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .filter(serde_json::Value::is_object)
        .unwrap_or_else(|| {
            serde_json::json!({
                "scene": session.scene.name,
                "field": session.field_kind,
                "seeds": stage2::seeds(&session),
                "steps": session.step,
            })
        });
    report["stage2"] = section;
    report["segment_seconds"] = started.elapsed().as_secs_f64().into();
    super::write_json(&metrics_path, &report).context("writing metrics")?;
    say!("metrics in {}", metrics_path.display())?;
    // Inference alone (`--masks-only`) trains nothing, so it renders no path.
    match &trained {
        Some(s2) => super::render::camera_path_after_training(&session, Some(s2), progress),
        None => Ok(()),
    }
}
