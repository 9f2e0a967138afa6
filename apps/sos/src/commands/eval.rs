//! `sos eval`: metrics of a trained run on its held-out views.

use std::path::Path;

use sos_core::train::evaluate::evaluate_views;
use sos_core::train::Session;

pub fn run(config: &Path, checkpoint: Option<&Path>) -> anyhow::Result<()> {
    let mut session = Session::open(config)?;
    session.load_checkpoint(checkpoint)?;
    let eval = evaluate_views(&session, false)?;
    let report = serde_json::json!({ "scene": session.scene.name, "field": session.field_kind, "steps": session.step, "test": eval });
    super::write_json(&session.run_dir.join("eval.json"), &report)?;
    println!("{:<24} {:>8}", "view", "PSNR");
    for v in &eval.views {
        println!("{:<24} {:>8.2}", v.view, v.psnr);
    }
    println!("{:<24} {:>8.2}", "PSNR of mean MSE", eval.psnr);
    println!("{:<24} {:>8.2}", "mean PSNR", eval.psnr_mean_per_view);
    Ok(())
}
