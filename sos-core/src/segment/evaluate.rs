//! Evaluation of mask inference on held-out views: writes the mask, overlay and rendered
//! colour of every view, and measures NV-ARI, IoU(BG), IoU(FG), mIoU against ground-truth
//! masks (where a view has one) and PSNR/SSIM of the rendered colour.

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::error::RunError;
use crate::metrics::{
    adjusted_rand_index, binary_iou, mean_defined, median_relative_depth_error, ImageQualityReport, MetricError,
    SegmentationReport,
};
use crate::plugin::dataset::DatasetError;
use crate::scene::View;
use crate::segment::infer::{MaskInference, ViewMask};
use crate::train::session::Session;

/// What a view without a ground-truth mask reports instead of segmentation metrics.
pub const NO_GROUND_TRUTH: &str = "no ground truth";

/// Metrics of one held-out view.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ViewRecord {
    /// View name.
    pub view: String,
    /// ARI of the ground-truth mask against the k-means labels over all pixels.
    pub ari: Option<f64>,
    /// IoU of the background.
    pub iou_bg: Option<f64>,
    /// IoU of the foreground.
    pub iou_fg: Option<f64>,
    /// Mean of the defined IoUs.
    pub miou: Option<f64>,
    /// PSNR of the rendered colour, dB.
    pub psnr: f64,
    /// SSIM of the rendered colour.
    pub ssim: f64,
    /// Median relative error of the rendered depth against the view's ground-truth depth
    /// (absent when the view has none).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_error: Option<f64>,
    /// The same over the pixels of the ground-truth mask's object (absent without a mask).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object_depth_error: Option<f64>,
    /// Clusters k-means formed.
    pub clusters: usize,
    /// Fraction of pixels predicted foreground.
    pub foreground_fraction: f64,
    /// [`NO_GROUND_TRUTH`] when the view has no mask.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// Mask-inference results over a set of held-out views.
#[derive(Debug, Clone, Serialize)]
pub struct MaskEval {
    /// Per-view values, in scene order.
    pub views: Vec<ViewRecord>,
    /// Segmentation metrics over the views with a ground-truth mask.
    pub segmentation: SegmentationReport,
    /// PSNR/SSIM of the rendered colour over all views.
    pub image: ImageQualityReport,
    /// Mean over the views with a ground-truth depth of their median relative depth error
    /// (absent when no view has one).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub depth_error: Option<f64>,
    /// The same over the object's pixels (views with a ground-truth depth and mask).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub object_depth_error: Option<f64>,
    /// [`NO_GROUND_TRUTH`] when no view has a mask.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// Wall-clock seconds of rendering, clustering and measuring.
    pub seconds: f64,
}

/// Folders (under the run folder) the outputs of held-out views go to.
pub const MASKS_DIR: &str = "masks";
/// Overlays of held-out views.
pub const OVERLAYS_DIR: &str = "overlays";
/// Rendered colour of held-out views.
pub const TEST_DIR: &str = "test";
/// What each held-out view's mask was decided from ([`crate::segment::diagnostics`]).
pub const EVIDENCE_DIR: &str = "mask_evidence";
/// Rendered depth of held-out views ([`ViewMask::depth_image`]).
pub const DEPTH_DIR: &str = "depth";

/// Where one view's PNGs go, as folders under the run folder.
#[derive(Debug, Clone, Copy)]
pub struct ViewFolders<'a> {
    /// The binary mask (foreground 255).
    pub masks: &'a str,
    /// The mask drawn over the render.
    pub overlays: &'a str,
    /// The rendered colour, when written.
    pub images: Option<&'a str>,
    /// The mask's evidence image, when written (and the mask has one).
    pub evidence: Option<&'a str>,
    /// The rendered depth, when written (and rendered with the mask).
    pub depth: Option<&'a str>,
}

/// The folders of held-out views.
pub const HELD_OUT_FOLDERS: ViewFolders<'static> = ViewFolders {
    masks: MASKS_DIR,
    overlays: OVERLAYS_DIR,
    images: Some(TEST_DIR),
    evidence: Some(EVIDENCE_DIR),
    depth: Some(DEPTH_DIR),
};

/// Writes `<root>/<folder>/<name>.png` for each folder of `folders`.
pub fn write_view_pngs(mask: &ViewMask, root: &Path, folders: ViewFolders, name: &str) -> Result<(), RunError> {
    let file = format!("{name}.png");
    mask.mask_image().save_png(&root.join(folders.masks).join(&file))?;
    mask.overlay().save_png(&root.join(folders.overlays).join(&file))?;
    if let Some(images) = folders.images {
        mask.rgb.save_png(&root.join(images).join(&file))?;
    }
    if let (Some(dir), Some(evidence)) = (folders.evidence, &mask.evidence) {
        evidence.save_png(&root.join(dir).join(&file))?;
    }
    if let (Some(dir), Some(depth)) = (folders.depth, mask.depth_image()) {
        depth.save_png(&root.join(dir).join(&file))?;
    }
    Ok(())
}

/// Segments every held-out view of the session's scene, writes its PNGs into the run folder
/// (when `write`), and measures it.
pub fn evaluate_masks(session: &Session, inference: &MaskInference, write: bool) -> Result<MaskEval, RunError> {
    let started = Instant::now();
    let mut out = MaskEval {
        views: Vec::new(),
        segmentation: SegmentationReport::new(),
        image: ImageQualityReport::new(),
        depth_error: None,
        object_depth_error: None,
        note: None,
        seconds: 0.0,
    };
    for &i in &session.scene.test {
        let view = &session.scene.views[i];
        let mask = inference.segment(&view.camera, &view.name)?;
        if write {
            write_view_pngs(&mask, &session.run_dir, HELD_OUT_FOLDERS, &view.name)?;
        }
        out.views.push(measure_view(session, view, &mask, &mut out.segmentation, &mut out.image)?);
    }
    if out.views.iter().all(|v| v.note.is_some()) {
        out.note = Some(NO_GROUND_TRUTH.into());
    }
    out.depth_error = mean_defined(out.views.iter().map(|v| v.depth_error));
    out.object_depth_error = mean_defined(out.views.iter().map(|v| v.object_depth_error));
    out.seconds = started.elapsed().as_secs_f64();
    Ok(out)
}

/// Measures one view's mask and colour and adds them to the reports.
pub fn measure_view(
    session: &Session,
    view: &View,
    mask: &ViewMask,
    segmentation: &mut SegmentationReport,
    image: &mut ImageQualityReport,
) -> Result<ViewRecord, RunError> {
    let bad = |e: MetricError| {
        RunError::Dataset(DatasetError::Invalid {
            path: session.config_dir.clone(),
            message: format!("view {}: {e}", view.name),
        })
    };
    image.add_view(&view.name, &mask.rgb, &view.image).map_err(bad)?;
    let quality = image.views().last().expect("a view was just added").clone();
    let n = mask.foreground.len().max(1);
    let mut record = ViewRecord {
        view: view.name.clone(),
        ari: None,
        iou_bg: None,
        iou_fg: None,
        miou: None,
        psnr: quality.psnr,
        ssim: quality.ssim,
        depth_error: None,
        object_depth_error: None,
        clusters: mask.clusters,
        foreground_fraction: mask.foreground.iter().filter(|&&f| f).count() as f64 / n as f64,
        note: Some(NO_GROUND_TRUTH.into()),
    };
    let gt_mask: Option<Vec<bool>> = view
        .mask
        .as_ref()
        .map(|gt| gt.resized_nearest(mask.rgb.width, mask.rgb.height).data.iter().map(|&v| v >= 0.5).collect());
    if let Some(gt) = &gt_mask {
        // NV-ARI compares with the k-means labels themselves (all clusters), IoU with the mask.
        let ari = adjusted_rand_index(gt, &mask.labels).map_err(bad)?;
        let iou = binary_iou(gt, &mask.foreground).map_err(bad)?;
        segmentation.push(&view.name, ari, iou);
        record.ari = Some(ari);
        record.iou_bg = iou.bg;
        record.iou_fg = iou.fg;
        record.miou = iou.miou();
        record.note = None;
    }
    if let Some(truth) = view.depth.as_ref().filter(|_| !mask.depth.is_empty()) {
        let truth = truth.resized_nearest(mask.rgb.width, mask.rgb.height);
        record.depth_error = median_relative_depth_error(&truth.data, &mask.depth).map_err(bad)?;
        if let Some(gt) = &gt_mask {
            let (object_truth, object_rendered): (Vec<f32>, Vec<f32>) =
                truth.data.iter().zip(&mask.depth).zip(gt).filter(|(_, &fg)| fg).map(|(pair, _)| pair).unzip();
            record.object_depth_error = median_relative_depth_error(&object_truth, &object_rendered).map_err(bad)?;
        }
    }
    Ok(record)
}

impl MaskEval {
    /// A plain-text table: view, ARI, IoU BG, IoU FG, mIoU, PSNR, SSIM, then a mean row
    /// (segmentation means over the views with ground truth).
    pub fn to_table(&self) -> String {
        let num = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.4}"));
        // The depth column only for scenes that know their depth.
        let depth = self.depth_error.is_some();
        let mut rows: Vec<Vec<String>> = self
            .views
            .iter()
            .map(|v| {
                let mut row = vec![
                    v.view.clone(),
                    v.ari.map_or_else(|| NO_GROUND_TRUTH.to_string(), |a| format!("{a:.4}")),
                    num(v.iou_bg),
                    num(v.iou_fg),
                    num(v.miou),
                    format!("{:.2}", v.psnr),
                    format!("{:.4}", v.ssim),
                ];
                if depth {
                    row.extend([num(v.depth_error), num(v.object_depth_error)]);
                }
                row
            })
            .collect();
        let iou = self.segmentation.iou();
        let mut mean = vec![
            "mean".into(),
            self.segmentation.mean_ari().map_or_else(|| NO_GROUND_TRUTH.to_string(), |a| format!("{a:.4}")),
            num(iou.iou_bg),
            num(iou.iou_fg),
            num(iou.miou),
            self.image.mean_psnr().map_or_else(|| "-".into(), |p| format!("{p:.2}")),
            num(self.image.mean_ssim()),
        ];
        if depth {
            mean.extend([num(self.depth_error), num(self.object_depth_error)]);
        }
        rows.push(mean);
        let mut header = vec!["view", "ARI", "IoU BG", "IoU FG", "mIoU", "PSNR", "SSIM"];
        if depth {
            header.extend(["depth err", "object depth err"]);
        }
        let mut widths: Vec<usize> = header.iter().map(|h| h.len()).collect();
        for row in &rows {
            for (w, cell) in widths.iter_mut().zip(row) {
                *w = (*w).max(cell.len());
            }
        }
        let line = |cells: &[&str]| {
            let mut s = String::new();
            for (i, (cell, w)) in cells.iter().zip(&widths).enumerate() {
                if i == 0 {
                    s.push_str(&format!("{cell:<w$}"));
                } else {
                    s.push_str(&format!("  {cell:>w$}"));
                }
            }
            s.push('\n');
            s
        };
        let mut out = line(&header);
        let rules: Vec<String> = widths.iter().map(|&w| "-".repeat(w)).collect();
        out.push_str(&line(&rules.iter().map(String::as_str).collect::<Vec<_>>()));
        for row in &rows {
            out.push_str(&line(&row.iter().map(String::as_str).collect::<Vec<_>>()));
        }
        out
    }
}
