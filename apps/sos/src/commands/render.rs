//! `sos render`: held-out views and the novel camera path from a checkpoint.

use std::path::Path;

use indicatif::ProgressBar;
use sos_core::train::evaluate::evaluate_views;
use sos_core::train::Session;

pub fn run(config: &Path, checkpoint: Option<&Path>) -> anyhow::Result<()> {
    let mut session = Session::open(config)?;
    session.load_checkpoint(checkpoint)?;
    let eval = evaluate_views(&session, true)?;
    println!("rendered {} held-out views to {}", eval.views.len(), session.run_dir.join("test").display());
    let path = session.scene.render_path.clone();
    let bar = ProgressBar::new(path.len() as u64);
    for (i, cam) in path.iter().enumerate() {
        let (img, _) = session.render_view(cam);
        img.save_png(&session.run_dir.join("path").join(format!("{i:04}.png")))?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    if !path.is_empty() {
        println!("rendered {} camera-path frames to {}", path.len(), session.run_dir.join("path").display());
    }
    Ok(())
}
