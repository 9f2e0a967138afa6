//! `dino-vit`: the reference's 2D teacher, a DINO ViT (S/16, S/8, B/16 or B/8) run natively on
//! the CPU from the official checkpoint files.
//!
//! - [`crate::checkpoint`] reads the `.pth` (PyTorch's zip + pickle format) and
//!   `.safetensors` files into a [`StateDict`];
//! - [`model`] is the forward pass, [`preprocess`] the reference's input pipeline,
//!   [`interpolate`] DINO's position-embedding interpolation;
//! - [`onnx_export`] writes the same network as an ONNX graph (for the `onnx` extractor and
//!   the ONNX Runtime comparison, without Python).
//!
//! Features per image: the last block's patch tokens before the final norm as a
//! `[dim, grid_h, grid_w]` map, its \[CLS\] token as the global descriptor, and the last
//! block's \[CLS\] attention over the patches (mean over heads) as the saliency map.

pub mod arch;
pub mod fastmath;
pub mod interpolate;
pub mod model;
pub mod onnx_export;
pub mod preprocess;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use sos_core::error::{BuildError, ExtractError};
use sos_core::image::RgbImage;
use sos_core::plugin::{BuildContext, FeatureExtractor, FeatureExtractorConfig, FeatureMap};

pub use crate::checkpoint::{CheckpointError, StateDict};
pub use arch::Arch;
pub use model::{LoadError, Vit, VitOutput, VitShape};
pub use preprocess::{Preprocess, Resize};

const KIND: &str = DinoVitConfig::KIND;
/// Bump when the features change, so cached teacher features are recomputed.
const VERSION: u32 = 1;

/// Settings of the `dino-vit` extractor (`[extractor] kind = "dino-vit"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DinoVitConfig {
    /// The checkpoint: an official DINO backbone `.pth` (or a training checkpoint holding
    /// one under `teacher`), or the same state dict as `.safetensors`. A relative path is
    /// resolved against the config file's folder.
    pub weights: PathBuf,
    /// `vits16`, `vits8`, `vitb16`, `vitb8`, or `auto` (taken from the checkpoint). A named
    /// architecture must match the checkpoint.
    pub arch: Arch,
    /// Attention heads; default `width / 64` (all DINO ViTs).
    pub heads: Option<usize>,
    /// Side that resized images get (the reference: 224).
    pub input_size: usize,
    /// Which images are resized: `patches` (the reference: stage-2 patches yes, whole views
    /// for the foreground choice no), `always` or `never`.
    pub resize: Resize,
    /// Side of the reference's intermediate nearest upsample (384) when resizing; 0 resizes
    /// directly. Both give the same input for 64-px patches.
    pub reference_upsample: usize,
    /// Normalise with the ImageNet statistics twice, as the reference does (`false`: once).
    pub double_normalize: bool,
    /// Images per forward pass (a batch of equal-sized inputs).
    pub batch: usize,
}

impl Default for DinoVitConfig {
    fn default() -> Self {
        DinoVitConfig {
            weights: PathBuf::from("weights").join(Arch::Vits16.official_file()),
            arch: Arch::Auto,
            heads: None,
            input_size: 224,
            resize: Resize::Patches,
            reference_upsample: preprocess::REFERENCE_UPSAMPLE,
            double_normalize: true,
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

/// Where to get the official weights, for error messages.
fn download_hint(arch: Arch) -> String {
    let shown = if arch == Arch::Auto { Arch::Vits16 } else { arch };
    format!(
        "download {} (the official DINO {} backbone weights, listed at {}) from {}; for the other \
         architectures the files are dino_deitsmall16_pretrain.pth (vits16, the reference's), \
         dino_deitsmall8_pretrain.pth (vits8), dino_vitbase16_pretrain.pth (vitb16) and \
         dino_vitbase8_pretrain.pth (vitb8), each at https://dl.fbaipublicfiles.com/dino/<name>/<name>.pth",
        shown.official_file(),
        shown.name(),
        arch::DINO_README,
        shown.official_url()
    )
}

impl DinoVitConfig {
    /// Checks the settings that do not need the weights.
    pub fn validate(&self) -> Result<(), BuildError> {
        if self.weights.as_os_str().is_empty() {
            return Err(invalid("weights", "must name a checkpoint file"));
        }
        if !(8..=4096).contains(&self.input_size) {
            return Err(invalid("input_size", "must be between 8 and 4096 pixels"));
        }
        if self.reference_upsample > 8192 {
            return Err(invalid("reference_upsample", "must be 0 (off) or at most 8192"));
        }
        if !(1..=256).contains(&self.batch) {
            return Err(invalid("batch", "must be between 1 and 256"));
        }
        if self.heads == Some(0) {
            return Err(invalid("heads", "must be at least 1"));
        }
        Ok(())
    }

    /// The preprocessing for a model with this patch size.
    pub fn preprocess(&self, patch: usize) -> Preprocess {
        Preprocess {
            input_size: self.input_size,
            resize: self.resize,
            reference_upsample: self.reference_upsample,
            double_normalize: self.double_normalize,
            ..Preprocess::reference(patch)
        }
    }

    /// Reads the checkpoint and builds the model, with errors that name the file and the fix.
    /// `weights` is opened as it is (relative to the working directory); [`FeatureExtractorConfig::build`]
    /// resolves it against the config file's folder first.
    pub fn load_model(&self) -> Result<(Vit, u64), BuildError> {
        self.validate()?;
        let path = &self.weights;
        let hint = download_hint(self.arch);
        let sd = StateDict::load_weights(
            KIND,
            path,
            &format!("{hint} and save it there"),
            &format!("a DINO ViT checkpoint as published (.pth) or its state dict as .safetensors: {hint}"),
        )?;
        let heads = self.heads.or(self.arch.dims().map(|d| d.3));
        let not_dino = |e: LoadError| match e {
            LoadError::NotDino(reason) => resource(format!(
                "`{}` is not a DINO ViT checkpoint: {reason}. Expected the backbone state dict of DINO's \
                 VisionTransformer (`cls_token`, `pos_embed`, `patch_embed.proj.*`, `blocks.N.*`, `norm.*`): {}",
                path.display(),
                download_hint(self.arch)
            )),
            LoadError::Checkpoint(e) => resource(e.to_string()),
        };
        let shape = VitShape::detect(&sd, heads).map_err(not_dino)?;
        if let Some((dim, patch, depth, _)) = self.arch.dims() {
            if (shape.dim, shape.patch, shape.depth) != (dim, patch, depth) {
                let found = Arch::from_dims(shape.dim, shape.patch, shape.depth)
                    .map(|a| format!(" (`{}`)", a.name()))
                    .unwrap_or_default();
                return Err(invalid(
                    "arch",
                    format!(
                        "`{}` holds a ViT of width {}, {}-px patches and {} blocks{found}, not `{}`; set `arch` \
                         to match (or to \"auto\"), or point `weights` at {}",
                        path.display(),
                        shape.dim,
                        shape.patch,
                        shape.depth,
                        self.arch.name(),
                        self.arch.official_file()
                    ),
                ));
            }
        }
        // An input smaller than one patch gives the model no token at all.
        if self.input_size < shape.patch {
            return Err(invalid(
                "input_size",
                format!("must be at least the model's patch of {} px, got {}", shape.patch, self.input_size),
            ));
        }
        let model = Vit::from_state_dict(&sd, shape).map_err(not_dino)?;
        Ok((model, sd.content_hash()))
    }
}

sos_core::plugin_kind! {
    kind: "dino-vit",
    summary: "DINO ViT-S/16, S/8, B/16 or B/8 from the official .pth (or .safetensors) weights, on the CPU (the reference's teacher)",
    default: || Box::new(DinoVitConfig::default()),
    impl FeatureExtractorConfig for DinoVitConfig {
        fn build(&self, ctx: &BuildContext) -> Result<Box<dyn FeatureExtractor>, BuildError> {
            let resolved = DinoVitConfig { weights: ctx.resolve(&self.weights), ..self.clone() };
            let (model, hash) = resolved.load_model()?;
            let pre = self.preprocess(model.shape.patch);
            Ok(Box::new(DinoVit::new(model, pre, format!("{hash:016x}"), self.batch)))
        }
    }
}

/// The `dino-vit` extractor.
#[derive(Debug, Clone)]
pub struct DinoVit {
    model: Arc<Vit>,
    preprocess: Preprocess,
    weights_id: String,
    batch: usize,
}

impl DinoVit {
    /// An extractor around a model; `weights_id` names the weights in [`FeatureExtractor::identity`]
    /// (e.g. their hash).
    pub fn new(model: Vit, preprocess: Preprocess, weights_id: String, batch: usize) -> DinoVit {
        DinoVit { model: Arc::new(model), preprocess, weights_id, batch: batch.max(1) }
    }

    /// Loads an extractor from a checkpoint with the reference's preprocessing.
    pub fn from_file(weights: &Path) -> Result<DinoVit, BuildError> {
        let config = DinoVitConfig { weights: weights.into(), ..Default::default() };
        let (model, hash) = config.load_model()?;
        let pre = config.preprocess(model.shape.patch);
        Ok(DinoVit::new(model, pre, format!("{hash:016x}"), config.batch))
    }

    /// The model.
    pub fn model(&self) -> &Vit {
        &self.model
    }

    /// The preprocessing.
    pub fn preprocessing(&self) -> &Preprocess {
        &self.preprocess
    }
}

/// One image's `np` patch tokens, rows of `dim` after `prefix` leading tokens (\[CLS\] and the
/// like) in `tokens`, as a channel-first `[dim, np]` map.
pub fn patch_map(tokens: &[f32], prefix: usize, dim: usize, np: usize) -> Vec<f32> {
    let mut data = vec![0.0f32; dim * np];
    for i in 0..np {
        for (c, &v) in tokens[(prefix + i) * dim..(prefix + i + 1) * dim].iter().enumerate() {
            data[c * np + i] = v;
        }
    }
    data
}

/// Splits a forward pass into one feature map per image.
pub fn feature_maps(out: &VitOutput) -> Vec<FeatureMap> {
    let (d, n, np) = (out.dim, out.tokens_per_image(), out.grid_h * out.grid_w);
    (0..out.batch)
        .map(|b| {
            let tokens = &out.tokens[b * n * d..(b + 1) * n * d];
            FeatureMap {
                channels: d,
                height: out.grid_h,
                width: out.grid_w,
                data: patch_map(tokens, 1, d, np),
                cls: tokens[..d].to_vec(),
                saliency: Some(out.cls_attn[b * n + 1..(b + 1) * n].to_vec()),
            }
        })
        .collect()
}

impl FeatureExtractor for DinoVit {
    fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
        let d = self.model.shape.dim;
        // The native forward cannot fail on valid inputs; invalid ones get empty maps.
        Ok(self.preprocess.extract_in_runs(
            images,
            self.batch,
            || FeatureMap::zeros(d, d),
            |batch, n, h, w| feature_maps(&self.model.forward(batch, n, h, w)),
        ))
    }

    fn identity(&self) -> String {
        let s = &self.model.shape;
        let p = &self.preprocess;
        format!(
            "{KIND}/v{VERSION} weights={} dim={} patch={} depth={} heads={} input_size={} resize={} \
             reference_upsample={} double_normalize={}",
            self.weights_id,
            s.dim,
            s.patch,
            s.depth,
            s.heads,
            p.input_size,
            p.resize.name(),
            p.reference_upsample,
            p.double_normalize
        )
    }
}
