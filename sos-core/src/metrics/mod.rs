//! Segmentation and image-quality metrics, matching the reference implementation.
//!
//! - [`adjusted_rand_index`]: sklearn's `adjusted_rand_score` (NV-ARI).
//! - [`binary_iou`], [`mean_iou`]: the offline script's per-image IoU(BG)/IoU(FG) and their means.
//! - [`mse`], [`psnr_from_mse`], [`psnr_of_mean_mse`], [`mean_psnr`]: both PSNR conventions.
//! - [`ssim`], [`ssim_planar`]: the reference's Gaussian-window SSIM.
//! - [`median_relative_depth_error`]: rendered depth against a ground-truth depth map.
//! - [`SegmentationReport`], [`ImageQualityReport`]: per-view values, aggregates and a text table.

mod ari;
mod depth;
mod iou;
mod psnr;
mod report;
mod ssim;

pub use ari::adjusted_rand_index;
pub use depth::median_relative_depth_error;
pub(crate) use iou::mean_defined;
pub use iou::{binary_iou, binary_iou_gray, mean_iou, BinaryIou, IouSummary};
pub use psnr::{mean_psnr, mse, psnr_from_mse, psnr_of_mean_mse, PSNR_MSE_FLOOR};
pub use report::{ImageQualityReport, ImageQualityView, SegmentationReport, SegmentationView};
pub use ssim::{ssim, ssim_planar, SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW};

/// A metric could not be computed from its inputs.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetricError {
    /// Two inputs that must match element for element have different sizes.
    #[error("{what}: sizes differ ({left} vs {right}); resize one to the other first")]
    SizeMismatch {
        /// What was compared, e.g. `"ground-truth and predicted labels"`.
        what: &'static str,
        /// Size of the first input.
        left: usize,
        /// Size of the second input.
        right: usize,
    },
    /// An input has no elements, so the metric is undefined.
    #[error("{what}: input is empty")]
    Empty {
        /// What was empty.
        what: &'static str,
    },
}

/// Parsed reference fixture shared by the metric tests.
#[cfg(test)]
pub(crate) mod fixture {
    use serde::Deserialize;

    /// A row-major array as stored in the fixture files.
    #[derive(Deserialize)]
    pub struct Array {
        pub shape: Vec<usize>,
        pub data: Vec<f64>,
    }

    #[derive(Deserialize)]
    pub struct MaskCase {
        pub gt: Array,
        pub pred: Array,
        pub ari: f64,
        pub iou_bg: f64,
        pub iou_fg: f64,
        pub miou: f64,
    }

    #[derive(Deserialize)]
    pub struct ImageCase {
        pub a: Array,
        pub b: Array,
        pub psnr: f64,
        pub ssim: f64,
    }

    #[derive(Deserialize)]
    pub struct Fixture {
        pub masks: Vec<MaskCase>,
        pub images: Vec<ImageCase>,
    }

    pub fn load() -> Fixture {
        serde_json::from_str(include_str!("../../../fixtures/metrics/metrics.json")).expect("metrics fixture parses")
    }

    impl Array {
        /// Values as integer labels.
        pub fn labels(&self) -> Vec<u8> {
            self.data.iter().map(|&v| v as u8).collect()
        }

        /// Values as `f32`.
        pub fn f32(&self) -> Vec<f32> {
            self.data.iter().map(|&v| v as f32).collect()
        }
    }
}
