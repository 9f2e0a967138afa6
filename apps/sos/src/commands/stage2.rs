//! Shared stage-2 steps of `sos train`, `sos segment`, `sos eval` and `sos render`: training
//! the head and saving it with the field, and mask inference on the held-out views.

use std::time::Instant;

use anyhow::Context;
use sos_core::plugin::FeatureExtractor;
use sos_core::segment::evaluate::{evaluate_masks, MaskEval};
use sos_core::segment::head::SegHead;
use sos_core::segment::infer::MaskInference;
use sos_core::segment::store::{save_with_head, HeadMeta};
use sos_core::segment::train::{train_segmentation_observed, SegStepStats, Segmenter};
use sos_core::train::Session;

use crate::console::Console;

/// A trained stage 2.
pub struct Stage2 {
    /// Head, teacher and the rest.
    pub seg: Segmenter,
    /// Losses of the last step.
    pub stats: SegStepStats,
    /// Training wall-clock seconds.
    pub seconds: f64,
}

/// Trains a built stage 2 ([`Segmenter::build`]), then saves the head next to the field in the run's checkpoint.
pub fn train(session: &mut Session, mut seg: Segmenter, progress: bool) -> anyhow::Result<Stage2> {
    let started = Instant::now();
    eprintln!(
        "stage 2: {} steps of {} patches of {}x{} rays, head with {} parameters",
        session.config.segment.steps,
        session.config.segment.patches,
        session.config.segment.patch_size,
        session.config.segment.patch_size,
        seg.head.mlp.num_parameters()
    );
    let stats = train_segmentation_observed(session, &mut seg, &mut Console::new(progress))?;
    seg.release_step_buffers();
    let seconds = started.elapsed().as_secs_f64();
    eprintln!("stage 2 done: {} steps, last loss {:+.5}, {:.1} s", seg.step, stats.total, seconds);
    save_with_head(session, &seg.head, HeadMeta { steps: seg.step }).context("saving the segmentation head")?;
    Ok(Stage2 { seg, stats, seconds })
}

/// Segments the held-out views (PNGs into the run folder when `write`) and prints the table.
pub fn masks(
    session: &Session,
    head: &SegHead,
    extractor: Option<&dyn FeatureExtractor>,
    write: bool,
) -> anyhow::Result<MaskEval> {
    let inference = MaskInference::new(session, head, extractor)?;
    let eval = evaluate_masks(session, &inference, write)?;
    super::write_stdout(&eval.to_table())?;
    if write {
        say!(
            "masks of {} held-out views in {} ({:.1} s)",
            eval.views.len(),
            session.run_dir.join(sos_core::segment::evaluate::MASKS_DIR).display(),
            eval.seconds
        )?;
    }
    Ok(eval)
}

/// The JSON record of stage 2: its settings, timing, last losses and mask metrics.
pub fn report(
    session: &Session,
    steps: usize,
    seconds: Option<f64>,
    stats: Option<&SegStepStats>,
    eval: &MaskEval,
) -> serde_json::Value {
    serde_json::json!({
        "steps": steps,
        "config": {
            "segment": session.config.segment,
            "head": session.config.head,
            "masks": session.config.masks,
        },
        "train_seconds": seconds,
        "last_step": stats,
        "masks_seconds": eval.seconds,
        "test": eval,
    })
}

/// The config's seeds: the run's and, where the scene kind has one, the scene's.
pub fn seeds(session: &Session) -> serde_json::Value {
    let scene_seed =
        toml::Value::try_from(&session.config.scene).ok().and_then(|v| v.get("seed").and_then(|s| s.as_integer()));
    serde_json::json!({ "run": session.config.seed, "scene": scene_seed })
}
