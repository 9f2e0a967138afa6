//! The contrastive-loss role: compares teacher (appearance or geometry) correlations with the
//! correlations of rendered segmentation logits over a batch of patches.

use rand::RngCore;

use crate::error::BuildError;
use crate::plugin::extractor::FeatureMap;
use crate::registry::Registration;

/// Everything a contrastive loss may look at for one training step.
///
/// # Shapes
/// - `logits`: `[n_patches, d_seg, patch, patch]` (channel-first per patch, rows then columns)
/// - `points`: `[n_patches, 3, patch, patch]` expected 3D point of each ray (world frame)
/// - `features`: `n_patches` teacher feature maps
/// - `negatives`: `[n_patches]` negative partner of each patch (from a [`crate::plugin::PairMiner`])
#[derive(Debug, Clone, Copy)]
pub struct PatchBatch<'a> {
    /// Number of patches.
    pub n_patches: usize,
    /// Rays per patch side.
    pub patch: usize,
    /// Logit channels per ray.
    pub d_seg: usize,
    /// Rendered segmentation logits.
    pub logits: &'a [f32],
    /// Rendered 3D points (depth-derived); treated as constants.
    pub points: &'a [f32],
    /// Teacher features of the patches; treated as constants.
    pub features: &'a [FeatureMap],
    /// Negative partner of each patch.
    pub negatives: &'a [usize],
}

/// A loss value split into named, unweighted terms (the trainer weights them).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LossValue {
    /// Total of the terms, as the loss defines it (e.g. λ_id·id + λ_neg·neg).
    pub total: f64,
    /// Named parts for logging.
    pub terms: Vec<(String, f64)>,
}

/// A contrastive loss (hot path).
pub trait ContrastiveLoss: Send + Sync {
    /// Computes the loss and ADDS `grad_scale · ∂loss/∂logits` into `grad_logits` (same layout
    /// as `batch.logits`).
    fn loss_and_grad(
        &self,
        batch: &PatchBatch,
        rng: &mut dyn RngCore,
        grad_scale: f32,
        grad_logits: &mut [f32],
    ) -> LossValue;
}

/// Configuration of a contrastive loss; one `[[loss]]` entry holds `weight` beside it.
#[typetag::serde(tag = "kind")]
pub trait ContrastiveLossConfig: std::fmt::Debug + Send + Sync {
    /// Validates the settings and builds the loss.
    fn build(&self) -> Result<Box<dyn ContrastiveLoss>, BuildError>;
}

inventory::collect!(Registration<dyn ContrastiveLossConfig>);
