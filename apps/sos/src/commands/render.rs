//! `sos render`: held-out views and the novel camera path from a checkpoint; with a
//! segmentation head also their masks and overlays.

use std::path::Path;

use indicatif::ProgressBar;
use sos_core::segment::evaluate::{write_view_pngs, ViewFolders};
use sos_core::segment::infer::{saliency_extractor, MaskInference};
use sos_core::segment::store::load_with_head;
use sos_core::train::evaluate::evaluate_views;
use sos_core::train::Session;

use super::stage2;

/// `sos render`: held-out views and the camera path, with masks when a head exists.
pub fn run(config: &Path, checkpoint: Option<&Path>, progress: bool) -> anyhow::Result<()> {
    let mut session = Session::open(config)?;
    // Refuses a folder another run uses, or one that cannot be written, before any work.
    let _claim = session.claim_run_dir()?;
    let (loaded, _) = load_with_head(&mut session, checkpoint)?;
    let extractor = match &loaded {
        Some(_) => saliency_extractor(&session)?,
        None => None,
    };
    match &loaded {
        Some(l) => {
            stage2::masks(&session, &l.head, extractor.as_deref(), true)?;
        }
        None => {
            let eval = evaluate_views(&session, true)?;
            say!("rendered {} held-out views to {}", eval.views.len(), session.run_dir.join("test").display())?;
        }
    }
    let inference = match &loaded {
        Some(l) => Some(MaskInference::new(&session, &l.head, extractor.as_deref())?),
        None => None,
    };
    render_camera_path(&session, inference.as_ref(), progress)
}

/// When `render.camera_path` is set: the camera path at the end of a training command, with
/// masks from the head stage 2 just trained (`trained`), colour alone without one.
pub(super) fn camera_path_after_training(
    session: &Session,
    trained: Option<&super::stage2::Stage2>,
    progress: bool,
) -> anyhow::Result<()> {
    if !session.config.render.camera_path {
        return Ok(());
    }
    let inference = match trained {
        Some(s2) => Some(MaskInference::new(session, &s2.seg.head, Some(s2.seg.teacher.extractor()))?),
        None => None,
    };
    render_camera_path(session, inference.as_ref(), progress)
}

/// Renders the scene's novel camera path into the run folder: colour frames, and with a head
/// (`inference`) their masks and overlays from the same pass; a bar on a terminal when
/// `progress`.
pub(super) fn render_camera_path(
    session: &Session,
    inference: Option<&MaskInference>,
    progress: bool,
) -> anyhow::Result<()> {
    let path = &session.scene.render_path;
    if let Some(why) = session.scene.render_path_problem() {
        anyhow::bail!("{why}");
    }
    let bar = if progress { ProgressBar::new(path.len() as u64) } else { ProgressBar::hidden() };
    for (i, cam) in path.iter().enumerate() {
        let name = format!("{i:04}");
        match inference {
            // One render gives colour and logits.
            Some(inf) => {
                let mask = inf.segment(cam, &name)?;
                let folders = ViewFolders {
                    masks: "path_masks",
                    overlays: "path_overlays",
                    images: Some("path"),
                    evidence: None,
                    depth: None,
                };
                write_view_pngs(&mask, &session.run_dir, folders, &name)?;
            }
            None => {
                let (img, _) = session.render_view(cam);
                img.save_png(&session.run_dir.join("path").join(format!("{name}.png")))?;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    if !path.is_empty() {
        say!("rendered {} camera-path frames to {}", path.len(), session.run_dir.join("path").display())?;
        if inference.is_some() {
            say!("camera-path masks in {}", session.run_dir.join("path_masks").display())?;
        }
    }
    Ok(())
}
