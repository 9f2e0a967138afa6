//! The 2D teacher role: a frozen backbone that turns image patches into feature maps.

use std::path::{Path, PathBuf};

use crate::derived::{DerivedSetting, PatchFacts};
use crate::error::{BuildError, ExtractError};
use crate::image::RgbImage;
use crate::registry::Registration;

/// Features of one image: a `[channels, height, width]` grid (channel-first, as the reference's
/// `f ∈ R^{B×C×h×w}`), a global \[CLS\]-like vector for pair mining, and optionally a saliency
/// map (e.g. DINO's last-layer \[CLS\] attention) used to pick the foreground cluster.
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

impl FeatureMap {
    /// The map of an image an extractor cannot read (no pixels, or a buffer of the wrong
    /// length): one cell of `channels` zeros, a descriptor of `cls_len` zeros and zero
    /// saliency.
    pub fn zeros(channels: usize, cls_len: usize) -> FeatureMap {
        FeatureMap {
            channels,
            height: 1,
            width: 1,
            data: vec![0.0; channels],
            cls: vec![0.0; cls_len],
            saliency: Some(vec![0.0]),
        }
    }
}

/// A frozen 2D feature extractor (hot path).
pub trait FeatureExtractor: Send + Sync {
    /// Extracts features of each image, one map per image in order. Images may have any
    /// size; implementations resize as their preprocessing specifies. Fails when the backbone
    /// cannot run (e.g. ONNX Runtime rejects the batch), never with a partial result.
    fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError>;

    /// Extracts features of patches cut from larger views: `views[i]` is the whole view that
    /// `patches[i]` was cut from, sampled at the patch's pixel spacing (so a patch cell and a
    /// view cell of the same size cover the same area). Stage 2 shows the teacher patches
    /// this way. An extractor whose features compare a cell with the rest of its image (a
    /// background prior such as distinctness from the image border) compares with the view
    /// here: a patch's border is not the view's background, and a per-patch prior marks
    /// every patch's centre as the object. The default ignores the views.
    fn extract_in_views(&self, patches: &[RgbImage], views: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
        let _ = views;
        self.extract(patches)
    }

    /// A string that changes whenever the features would change (kind, settings, weights
    /// hash); used as the teacher-feature cache key.
    fn identity(&self) -> String;
}

/// Configuration of a feature extractor, chosen by `[extractor] kind = "..."`.
#[typetag::serde(tag = "kind")]
pub trait FeatureExtractorConfig: std::fmt::Debug + Send + Sync {
    /// Validates the settings, loads weights (relative paths resolved with
    /// [`BuildContext::resolve`]) and builds the extractor.
    fn build(&self, ctx: &BuildContext) -> Result<Box<dyn FeatureExtractor>, BuildError>;

    /// Fills the settings left unset that follow from the patches the teacher is shown (e.g.
    /// a cell size giving a fixed grid per patch) and returns what it chose. Called once per
    /// run before [`FeatureExtractorConfig::build`]; a teacher with fixed input needs nothing.
    fn derive_for(&mut self, _patch: &PatchFacts) -> Vec<DerivedSetting> {
        Vec::new()
    }

    /// Refuses settings that cannot work for the patches the teacher is shown (e.g. a cell
    /// as wide as the patch: one teacher feature per patch, nothing to correlate within it).
    /// Called once per run with stage 2, after [`FeatureExtractorConfig::derive_for`].
    fn check_for(&self, _patch: &PatchFacts) -> Result<(), BuildError> {
        Ok(())
    }
}

/// What building an extractor needs from the run besides its own settings.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BuildContext {
    /// Folder of the config file (empty: the working directory).
    pub config_dir: PathBuf,
}

impl BuildContext {
    /// A context for a config file in `config_dir`.
    pub fn new(config_dir: impl Into<PathBuf>) -> Self {
        BuildContext { config_dir: config_dir.into() }
    }

    /// A path from the config: absolute paths as they are, relative ones against the config
    /// file's folder (like every other path of a run config), so a run does not depend on
    /// the working directory.
    pub fn resolve(&self, path: &Path) -> PathBuf {
        if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.config_dir.join(path)
        }
    }
}

inventory::collect!(Registration<dyn FeatureExtractorConfig>);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_resolve_against_the_config_folder_absolute_ones_stay() {
        let ctx = BuildContext::new("configs/run");
        assert_eq!(ctx.resolve(Path::new("models/dino.pth")), Path::new("configs/run/models/dino.pth"));
        assert_eq!(ctx.resolve(Path::new("../weights/a.pth")), Path::new("configs/run/../weights/a.pth"));
        let absolute = std::env::temp_dir().join("dino.pth");
        assert_eq!(ctx.resolve(&absolute), absolute);
        // A config in the working directory has an empty folder: paths stay relative to it.
        assert_eq!(BuildContext::default().resolve(Path::new("w.pth")), Path::new("w.pth"));
    }
}
