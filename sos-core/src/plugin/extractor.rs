//! The 2D teacher role: a frozen backbone that turns image patches into feature maps.

use crate::error::BuildError;
use crate::image::RgbImage;
use crate::registry::Registration;

/// Features of one image: a `[channels, height, width]` grid (channel-first, as the reference's
/// `f ∈ R^{B×C×h×w}`), a global [CLS]-like vector for pair mining, and optionally a saliency
/// map (e.g. DINO's last-layer [CLS] attention) used to pick the foreground cluster.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureMap {
    /// Number of channels.
    pub channels: usize,
    /// Grid height.
    pub height: usize,
    /// Grid width.
    pub width: usize,
    /// Values, `[channels, height, width]` row-major.
    pub data: Vec<f32>,
    /// Global descriptor of the image.
    pub cls: Vec<f32>,
    /// Saliency per grid cell, `[height, width]`, larger = more likely foreground.
    pub saliency: Option<Vec<f32>>,
}

/// A frozen 2D feature extractor (hot path).
pub trait FeatureExtractor: Send + Sync {
    /// Extracts features of each image. Images may have any size; implementations resize as
    /// their preprocessing specifies.
    fn extract(&self, images: &[RgbImage]) -> Vec<FeatureMap>;

    /// A string that changes whenever the features would change (kind, settings, weights
    /// hash); used as the teacher-feature cache key.
    fn identity(&self) -> String;
}

/// Configuration of a feature extractor, chosen by `[extractor] kind = "..."`.
#[typetag::serde(tag = "kind")]
pub trait FeatureExtractorConfig: std::fmt::Debug + Send + Sync {
    /// Validates the settings, loads weights and builds the extractor.
    fn build(&self) -> Result<Box<dyn FeatureExtractor>, BuildError>;
}

inventory::collect!(Registration<dyn FeatureExtractorConfig>);
