//! Pair miners and contrastive losses of nerf-sos.
//!
//! - [`cls_cosine`]: the reference pair miner (CLS cosine-similarity argmin, `kind = "cls-cosine"`).
//! - [`random`]: a random-derangement miner (`kind = "random"`, the reference's `--rand_neg`).
//! - [`appearance`]: the STEGO-style appearance contrastive loss on sampled teacher features
//!   (`kind = "appearance"`).
//! - [`geometry`]: the inverse-L1 geometry contrastive loss over pixel pairs (drawn, or all)
//!   (`kind = "geometry"`), plus the depth clip the renderer applies.
//!
//! The numerics follow the reference implementation (see the reference spec, §5–§7, §12, §14).

pub mod appearance;
pub mod cls_cosine;
pub mod geometry;
pub mod normalize;
pub mod random;
mod validate;

pub use appearance::{AppearanceConfig, AppearanceLoss};
pub use cls_cosine::{ClsCosineConfig, ClsCosineMiner};
pub use geometry::{clip_depth, GeometryConfig, GeometryLoss};
pub use random::{RandomConfig, RandomMiner};

/// Layout of a batch of patches: `n_patches` patches of `patch × patch` rays with `d_seg`
/// logit channels each, stored `[n_patches, d_seg, patch, patch]` row-major.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PatchShape {
    /// Number of patches.
    pub n_patches: usize,
    /// Logit channels per ray.
    pub d_seg: usize,
    /// Rays per patch side.
    pub patch: usize,
}

impl PatchShape {
    /// Rays per patch (`patch²`).
    pub fn pixels(&self) -> usize {
        self.patch * self.patch
    }

    /// Length of a logit buffer of this shape.
    pub fn logits_len(&self) -> usize {
        self.n_patches * self.d_seg * self.pixels()
    }
}

#[cfg(test)]
pub(crate) mod fixtures;
