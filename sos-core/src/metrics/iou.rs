//! Binary intersection-over-union, as the reference's offline `get_metrics.py`.

use serde::Serialize;

use super::MetricError;
use crate::image::GrayImage;

/// Per-image IoU of the two classes of a binary segmentation.
///
/// `IoU_c = TP_c / (GT_c + Pred_c − TP_c)`. A class that is absent from both the ground truth
/// and the prediction has a 0/0 IoU; the reference then produces NaN (and NaN means). Here it
/// is `None` instead, and [`mean_iou`] skips it (like `np.nanmean`), so one empty class does
/// not poison the averages. With real scenes both classes are present in the ground truth,
/// so the values then equal the reference's.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BinaryIou {
    /// IoU of class 0 (background), `None` when absent from both masks.
    pub bg: Option<f64>,
    /// IoU of class 1 (foreground), `None` when absent from both masks.
    pub fg: Option<f64>,
}

impl BinaryIou {
    /// Mean of the defined class IoUs (`None` only for an empty image).
    pub fn miou(&self) -> Option<f64> {
        mean_defined([self.bg, self.fg].into_iter())
    }
}

/// IoU(BG), IoU(FG) and mIoU averaged over images.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct IouSummary {
    /// Mean over images of IoU(BG) (images where it is undefined are skipped).
    pub iou_bg: Option<f64>,
    /// Mean over images of IoU(FG) (images where it is undefined are skipped).
    pub iou_fg: Option<f64>,
    /// Mean of all defined per-image class IoUs, i.e. `(iou_bg + iou_fg) / 2` when every
    /// image has both classes (the reference's `np.mean` of the `[images, 2]` array).
    pub miou: Option<f64>,
}

/// Per-class IoU of a binary prediction against a binary ground truth (`true` = foreground).
pub fn binary_iou(gt: &[bool], pred: &[bool]) -> Result<BinaryIou, MetricError> {
    if gt.len() != pred.len() {
        return Err(MetricError::SizeMismatch {
            what: "IoU: ground-truth and predicted masks",
            left: gt.len(),
            right: pred.len(),
        });
    }
    // Confusion counts: [gt][pred].
    let mut cm = [[0u64; 2]; 2];
    for (&g, &p) in gt.iter().zip(pred) {
        cm[g as usize][p as usize] += 1;
    }
    let class = |c: usize| {
        let tp = cm[c][c];
        let union = cm[c][0] + cm[c][1] + cm[0][c] + cm[1][c] - tp;
        (union > 0).then(|| tp as f64 / union as f64)
    };
    Ok(BinaryIou { bg: class(0), fg: class(1) })
}

/// [`binary_iou`] of two grey masks of the same size, each thresholded at `>= 0.5` (the
/// reference thresholds the resized prediction so; resize the prediction to the ground
/// truth's size first, e.g. with [`GrayImage::resized_nearest`]).
pub fn binary_iou_gray(gt: &GrayImage, pred: &GrayImage) -> Result<BinaryIou, MetricError> {
    if (gt.width, gt.height) != (pred.width, pred.height) {
        return Err(MetricError::SizeMismatch {
            what: "IoU: ground-truth and predicted mask pixel counts",
            left: gt.width * gt.height,
            right: pred.width * pred.height,
        });
    }
    let bin = |m: &GrayImage| m.data.iter().map(|&v| v >= 0.5).collect::<Vec<_>>();
    binary_iou(&bin(gt), &bin(pred))
}

/// Averages per-image IoUs over images (the reference's IoU(BG), IoU(FG), mIoU).
pub fn mean_iou(per_image: &[BinaryIou]) -> IouSummary {
    IouSummary {
        iou_bg: mean_defined(per_image.iter().map(|v| v.bg)),
        iou_fg: mean_defined(per_image.iter().map(|v| v.fg)),
        miou: mean_defined(per_image.iter().flat_map(|v| [v.bg, v.fg])),
    }
}

/// Mean of the `Some` values, `None` if there are none.
pub(crate) fn mean_defined(values: impl Iterator<Item = Option<f64>>) -> Option<f64> {
    let (sum, count) = values.flatten().fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (count > 0).then(|| sum / count as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::fixture;

    fn bools(a: &fixture::Array) -> Vec<bool> {
        a.data.iter().map(|&v| v >= 0.5).collect()
    }

    #[test]
    fn reproduces_reference_fixture_per_image_and_mean() {
        let fx = fixture::load();
        let mut all = Vec::new();
        for (i, case) in fx.masks.iter().enumerate() {
            let iou = binary_iou(&bools(&case.gt), &bools(&case.pred)).unwrap();
            let close = |a: Option<f64>, b: f64| (a.unwrap() - b).abs() < 1e-12;
            assert!(close(iou.bg, case.iou_bg), "case {i} bg {:?} vs {}", iou.bg, case.iou_bg);
            assert!(close(iou.fg, case.iou_fg), "case {i} fg {:?} vs {}", iou.fg, case.iou_fg);
            assert!(close(iou.miou(), case.miou), "case {i} miou {:?}", iou.miou());
            all.push(iou);
        }
        let n = fx.masks.len() as f64;
        let s = mean_iou(&all);
        let bg = fx.masks.iter().map(|c| c.iou_bg).sum::<f64>() / n;
        let fg = fx.masks.iter().map(|c| c.iou_fg).sum::<f64>() / n;
        assert!((s.iou_bg.unwrap() - bg).abs() < 1e-12);
        assert!((s.iou_fg.unwrap() - fg).abs() < 1e-12);
        assert!((s.miou.unwrap() - (bg + fg) / 2.0).abs() < 1e-12);
    }

    #[test]
    fn gray_masks_threshold_at_half_and_check_size() {
        let g = |w, h, data: Vec<f32>| GrayImage { width: w, height: h, data };
        let gt = g(2, 2, vec![0.0, 1.0, 1.0, 0.0]);
        let pred = g(2, 2, vec![0.49, 0.5, 1.0, 1.0]);
        let iou = binary_iou_gray(&gt, &pred).unwrap();
        assert_eq!(iou.fg, Some(2.0 / 3.0));
        assert_eq!(iou.bg, Some(0.5));
        assert!(binary_iou_gray(&gt, &g(1, 4, vec![0.0; 4])).is_err());
        assert!(binary_iou(&[true], &[true, false]).is_err());
    }

    #[test]
    fn class_absent_from_both_is_undefined_and_skipped() {
        let iou = binary_iou(&[false, false], &[false, false]).unwrap();
        assert_eq!(iou, BinaryIou { bg: Some(1.0), fg: None });
        assert_eq!(iou.miou(), Some(1.0));
        let other = binary_iou(&[true, false], &[true, true]).unwrap();
        let s = mean_iou(&[iou, other]);
        assert_eq!(s.iou_fg, Some(0.5));
        assert_eq!(s.iou_bg, Some(0.5));
        assert_eq!(s.miou, Some(0.5)); // mean of 1.0 (bg), 0.0 (bg), 0.5 (fg)
        assert_eq!(mean_iou(&[]).miou, None);
        let empty = binary_iou(&[], &[]).unwrap();
        assert_eq!((empty.bg, empty.fg, empty.miou()), (None, None, None));
    }
}
