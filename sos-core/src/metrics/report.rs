//! Per-view metric values, their aggregates, and plain-text tables.

use std::fmt::Write as _;

use serde::Serialize;

use super::iou::{binary_iou, mean_defined, mean_iou, BinaryIou, IouSummary};
use super::psnr::{mean_psnr, mse, psnr_from_mse, psnr_of_mean_mse};
use super::ssim::ssim;
use super::{adjusted_rand_index, MetricError};
use crate::image::RgbImage;

/// Segmentation metrics of one test view.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SegmentationView {
    /// View name (e.g. the image file stem).
    pub name: String,
    /// Adjusted Rand index of the predicted labels against the ground-truth mask.
    pub ari: f64,
    /// IoU of the background class (`None` if absent from both masks).
    pub iou_bg: Option<f64>,
    /// IoU of the foreground class (`None` if absent from both masks).
    pub iou_fg: Option<f64>,
    /// Mean of the defined class IoUs.
    pub miou: Option<f64>,
}

/// Segmentation metrics of a set of test views and their means (NV-ARI, IoU(BG), IoU(FG),
/// mIoU). Serialises as `{views: [...], mean_ari, iou_bg, iou_fg, miou}`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SegmentationReport {
    views: Vec<SegmentationView>,
    mean_ari: Option<f64>,
    #[serde(flatten)]
    iou: Option<IouSummary>,
}

impl SegmentationReport {
    /// An empty report.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a view from already computed values.
    pub fn push(&mut self, name: impl Into<String>, ari: f64, iou: BinaryIou) {
        self.views.push(SegmentationView { name: name.into(), ari, iou_bg: iou.bg, iou_fg: iou.fg, miou: iou.miou() });
        self.mean_ari = mean_defined(self.views.iter().map(|v| Some(v.ari)));
        let per_view: Vec<BinaryIou> = self.views.iter().map(|v| BinaryIou { bg: v.iou_bg, fg: v.iou_fg }).collect();
        self.iou = Some(mean_iou(&per_view));
    }

    /// Computes and adds a view: `gt` and `pred` are per-pixel foreground flags of the same
    /// image (ARI is invariant to swapping the prediction's labels; IoU is not).
    pub fn add_view(&mut self, name: impl Into<String>, gt: &[bool], pred: &[bool]) -> Result<(), MetricError> {
        let iou = binary_iou(gt, pred)?;
        let ari = adjusted_rand_index(gt, pred)?;
        self.push(name, ari, iou);
        Ok(())
    }

    /// Per-view values, in insertion order.
    pub fn views(&self) -> &[SegmentationView] {
        &self.views
    }

    /// Mean ARI over views (NV-ARI), `None` for no views.
    pub fn mean_ari(&self) -> Option<f64> {
        self.mean_ari
    }

    /// IoU(BG), IoU(FG) and mIoU over views.
    pub fn iou(&self) -> IouSummary {
        self.iou.unwrap_or(IouSummary { iou_bg: None, iou_fg: None, miou: None })
    }

    /// A plain-text table: one row per view, then a `mean` row.
    pub fn to_table(&self) -> String {
        let iou = self.iou();
        let mut rows: Vec<[String; 5]> = self
            .views
            .iter()
            .map(|v| [v.name.clone(), num(Some(v.ari)), num(v.iou_bg), num(v.iou_fg), num(v.miou)])
            .collect();
        rows.push(["mean".into(), num(self.mean_ari), num(iou.iou_bg), num(iou.iou_fg), num(iou.miou)]);
        table(&["view", "ARI", "IoU(BG)", "IoU(FG)", "mIoU"], &rows)
    }
}

/// Image-quality metrics of one rendered test view.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImageQualityView {
    /// View name.
    pub name: String,
    /// Mean squared error over pixels and channels.
    pub mse: f64,
    /// `−10·log10(mse)` (120 dB for an exact reproduction, see [`super::PSNR_MSE_FLOOR`]).
    pub psnr: f64,
    /// SSIM (Gaussian window, see [`super::ssim`]).
    pub ssim: f64,
}

/// Image-quality metrics of a set of views: both PSNR conventions and the mean SSIM.
/// Serialises as `{views: [...], psnr_of_mean_mse, mean_psnr, mean_ssim}`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ImageQualityReport {
    views: Vec<ImageQualityView>,
    psnr_of_mean_mse: Option<f64>,
    mean_psnr: Option<f64>,
    mean_ssim: Option<f64>,
}

impl ImageQualityReport {
    /// An empty report.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a view from already computed values (`mse` over pixels and channels).
    pub fn push(&mut self, name: impl Into<String>, mse: f64, ssim: f64) {
        self.views.push(ImageQualityView { name: name.into(), mse, psnr: psnr_from_mse(mse), ssim });
        let mses: Vec<f64> = self.views.iter().map(|v| v.mse).collect();
        self.psnr_of_mean_mse = psnr_of_mean_mse(&mses);
        self.mean_psnr = mean_psnr(&mses);
        self.mean_ssim = mean_defined(self.views.iter().map(|v| Some(v.ssim)));
    }

    /// Computes and adds a view from a rendered image and its ground truth.
    pub fn add_view(&mut self, name: impl Into<String>, rendered: &RgbImage, gt: &RgbImage) -> Result<(), MetricError> {
        let s = ssim(rendered, gt)?;
        let m = mse(&rendered.data, &gt.data)?;
        self.push(name, m, s);
        Ok(())
    }

    /// Per-view values, in insertion order.
    pub fn views(&self) -> &[ImageQualityView] {
        &self.views
    }

    /// PSNR of the mean MSE (the reference's in-loop value).
    pub fn psnr_of_mean_mse(&self) -> Option<f64> {
        self.psnr_of_mean_mse
    }

    /// Mean of per-view PSNRs (the reference's offline value).
    pub fn mean_psnr(&self) -> Option<f64> {
        self.mean_psnr
    }

    /// Mean SSIM over views.
    pub fn mean_ssim(&self) -> Option<f64> {
        self.mean_ssim
    }

    /// A plain-text table: one row per view, then `mean` (mean PSNR) and `mean-mse` (PSNR of
    /// the mean MSE) rows.
    pub fn to_table(&self) -> String {
        let mut rows: Vec<[String; 4]> = self
            .views
            .iter()
            .map(|v| [v.name.clone(), format!("{:.6}", v.mse), num2(Some(v.psnr)), num(Some(v.ssim))])
            .collect();
        let mean_mse = mean_defined(self.views.iter().map(|v| Some(v.mse)));
        rows.push(["mean".into(), num(mean_mse), num2(self.mean_psnr), num(self.mean_ssim)]);
        rows.push(["psnr(mean mse)".into(), String::new(), num2(self.psnr_of_mean_mse), String::new()]);
        table(&["view", "MSE", "PSNR", "SSIM"], &rows)
    }
}

fn num(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.4}"))
}

fn num2(v: Option<f64>) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.2}"))
}

/// Formats rows under a header: first column left-aligned, the others right-aligned, a dashed
/// rule under the header.
fn table<const N: usize>(header: &[&str; N], rows: &[[String; N]]) -> String {
    let mut widths = header.map(str::len);
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.len());
        }
    }
    let mut out = String::new();
    let mut line = |cells: &[&str]| {
        for (i, (cell, w)) in cells.iter().zip(&widths).enumerate() {
            if i == 0 {
                let _ = write!(out, "{cell:<w$}");
            } else {
                let _ = write!(out, "  {cell:>w$}");
            }
        }
        out.push('\n');
    };
    line(header);
    let rule: Vec<String> = widths.iter().map(|&w| "-".repeat(w)).collect();
    line(&rule.iter().map(String::as_str).collect::<Vec<_>>());
    for row in rows {
        line(&row.iter().map(String::as_str).collect::<Vec<_>>());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::fixture;

    #[test]
    fn segmentation_report_aggregates_fixture_views() {
        let fx = fixture::load();
        let mut report = SegmentationReport::new();
        assert_eq!(report.mean_ari(), None);
        for (i, case) in fx.masks.iter().enumerate() {
            let b = |a: &fixture::Array| a.data.iter().map(|&v| v >= 0.5).collect::<Vec<_>>();
            report.add_view(format!("view{i}"), &b(&case.gt), &b(&case.pred)).unwrap();
        }
        let n = fx.masks.len() as f64;
        let ari = fx.masks.iter().map(|c| c.ari).sum::<f64>() / n;
        let miou = fx.masks.iter().map(|c| c.miou).sum::<f64>() / n;
        assert!((report.mean_ari().unwrap() - ari).abs() < 1e-12);
        assert!((report.iou().miou.unwrap() - miou).abs() < 1e-12);
        assert_eq!(report.views().len(), 3);
        assert!((report.views()[1].ari - fx.masks[1].ari).abs() < 1e-12);

        let table = report.to_table();
        assert_eq!(table.lines().count(), 2 + 3 + 1, "{table}");
        assert!(table.contains("view1") && table.contains("mIoU"), "{table}");
        assert!(table.lines().last().unwrap().starts_with("mean"), "{table}");
        assert!(table.contains(&format!("{ari:.4}")), "{table}");

        let json = serde_json::to_value(&report).unwrap();
        assert!((json["mean_ari"].as_f64().unwrap() - ari).abs() < 1e-12);
        assert!((json["miou"].as_f64().unwrap() - miou).abs() < 1e-12);
        assert_eq!(json["views"].as_array().unwrap().len(), 3);
        assert_eq!(json["views"][0]["name"], "view0");
    }

    #[test]
    fn image_quality_report_has_both_psnr_conventions() {
        let fx = fixture::load();
        let mut report = ImageQualityReport::new();
        for (i, case) in fx.images.iter().enumerate() {
            let (h, w) = (case.a.shape[2], case.a.shape[3]);
            let to_rgb = |p: Vec<f32>| {
                let mut img = RgbImage::new(w, h);
                for ch in 0..3 {
                    for k in 0..h * w {
                        img.data[k * 3 + ch] = p[ch * h * w + k];
                    }
                }
                img
            };
            report.add_view(format!("v{i}"), &to_rgb(case.a.f32()), &to_rgb(case.b.f32())).unwrap();
        }
        let n = fx.images.len() as f64;
        let mean_psnr = fx.images.iter().map(|c| c.psnr).sum::<f64>() / n;
        let mean_ssim = fx.images.iter().map(|c| c.ssim).sum::<f64>() / n;
        assert!((report.mean_psnr().unwrap() - mean_psnr).abs() < 1e-6);
        assert!((report.mean_ssim().unwrap() - mean_ssim).abs() < 1e-6);
        let mses: Vec<f64> = report.views().iter().map(|v| v.mse).collect();
        let expected = -10.0 * (mses.iter().sum::<f64>() / n).log10();
        assert!((report.psnr_of_mean_mse().unwrap() - expected).abs() < 1e-12);
        assert!(report.psnr_of_mean_mse().unwrap() <= report.mean_psnr().unwrap());

        let table = report.to_table();
        assert_eq!(table.lines().count(), 2 + 2 + 2, "{table}");
        assert!(table.contains("SSIM") && table.contains("v1"), "{table}");
        let json = serde_json::to_value(&report).unwrap();
        assert!(json["psnr_of_mean_mse"].is_f64() && json["mean_psnr"].is_f64());

        let mut bad = ImageQualityReport::new();
        assert!(bad.add_view("x", &RgbImage::new(2, 2), &RgbImage::new(3, 2)).is_err());
        assert!(bad.views().is_empty());
    }
}
