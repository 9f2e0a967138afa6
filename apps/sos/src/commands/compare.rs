//! `sos compare`: IoU and ARI of a predicted mask against a reference mask from elsewhere
//! (e.g. the reference implementation's `clus_000.png`), which is resized to the prediction's
//! size with nearest-neighbour sampling, as the reference's metric script does with its inputs.

use std::path::Path;

use anyhow::Context;
use sos_core::image::GrayImage;
use sos_core::metrics::{adjusted_rand_index, binary_iou_gray};

/// `sos compare`: a mask against a reference mask (IoU, mIoU, ARI), optionally written to `out`.
pub fn run(prediction: &Path, reference: &Path, out: Option<&Path>) -> anyhow::Result<()> {
    let pred = GrayImage::load(prediction).context("reading the predicted mask")?;
    let reference_full = GrayImage::load(reference).context("reading the reference mask")?;
    if pred.width == 0 || pred.height == 0 {
        anyhow::bail!("{}: the predicted mask has no pixels", prediction.display());
    }
    let reference_resized = reference_full.resized_nearest(pred.width, pred.height);
    let iou = binary_iou_gray(&reference_resized, &pred)?;
    let binary = |m: &GrayImage| m.data.iter().map(|&v| u8::from(v >= 0.5)).collect::<Vec<_>>();
    let ari = adjusted_rand_index(&binary(&reference_resized), &binary(&pred))?;
    let show = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.4}"));
    say!(
        "{} vs {} (resized {}x{} -> {}x{})",
        prediction.display(),
        reference.display(),
        reference_full.width,
        reference_full.height,
        pred.width,
        pred.height
    )?;
    say!("IoU(FG) {}  IoU(BG) {}  mIoU {}  ARI {ari:.4}", show(iou.fg), show(iou.bg), show(iou.miou()))?;
    if let Some(out) = out {
        let report = serde_json::json!({
            "prediction": prediction,
            "reference": reference,
            "size": [pred.width, pred.height],
            "iou_fg": iou.fg,
            "iou_bg": iou.bg,
            "miou": iou.miou(),
            "ari": ari,
        });
        super::write_json(out, &report)?;
    }
    Ok(())
}
