//! `onnx`: any exported backbone run by ONNX Runtime (cargo feature `onnx`).
//!
//! ONNX Runtime is loaded from its shared library at run time (`ort` with `load-dynamic`):
//! `runtime` in the config, else the `ORT_DYLIB_PATH` environment variable. The library
//! ships in the `onnxruntime` Python wheel (`onnxruntime/capi/libonnxruntime.so.*`), so
//! `pip install onnxruntime` (or `pip download onnxruntime` and unzip the wheel) provides it;
//! nothing is downloaded at build time.
//!
//! The model takes one float input `[batch, 3, input_size, input_size]` (named `input`),
//! preprocessed like `dino-vit`'s (nearest resize, per-channel `mean`/`std`, optionally
//! twice). Outputs, by name:
//! - `tokens`: `[batch, prefix + h·w, C]` tokens (the first `prefix_tokens` are \[CLS\] and
//!   the like, the rest a square-ish patch grid row-major) or a `[batch, C, h, w]` map (CNNs);
//! - `cls` (optional): `[batch, C]` global descriptor; default token 0 when there are prefix
//!   tokens, else the mean of the map;
//! - `saliency` (optional): `[batch, prefix + h·w]`, `[batch, h·w]` or `[batch, h, w]`, e.g.
//!   DINO's last-layer \[CLS\] attention.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use ort::environment::Environment;
use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;
use ort::value::Tensor;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::error::{BuildError, ExtractError};
use sos_core::image::RgbImage;
use sos_core::plugin::{BuildContext, FeatureExtractor, FeatureExtractorConfig, FeatureMap};

use crate::checkpoint::content_hash;
use crate::dino_vit::patch_map;
use crate::dino_vit::preprocess::{Preprocess, Resize, IMAGENET_MEAN, IMAGENET_STD};

const KIND: &str = OnnxConfig::KIND;
/// Bump when the features change, so cached teacher features are recomputed.
const VERSION: u32 = 1;

/// How to get ONNX Runtime, for error messages.
pub const RUNTIME_HINT: &str = "ONNX Runtime is loaded from its shared library at run time: `pip install onnxruntime` \
    (or `pip download onnxruntime` and unzip the wheel) and set ORT_DYLIB_PATH to the \
    `onnxruntime/capi/libonnxruntime.so.<version>` file inside it (or `runtime` in `[extractor]`); \
    `python3 -c \"import onnxruntime, os; print(os.path.dirname(onnxruntime.__file__))\"` prints the folder";

/// Settings of the `onnx` extractor (`[extractor] kind = "onnx"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OnnxConfig {
    /// The `.onnx` file (a relative path: against the config file's folder).
    pub model: PathBuf,
    /// The ONNX Runtime shared library (a relative path: against the config file's folder);
    /// default: the `ORT_DYLIB_PATH` environment variable.
    pub runtime: Option<PathBuf>,
    /// Name of the model's image input.
    pub input: String,
    /// Side of the (square) model input.
    pub input_size: usize,
    /// Which images are resized to `input_size` (`always` for fixed-size exports).
    pub resize: Resize,
    /// Intermediate nearest-upsample side when resizing (0: direct; 384: the reference's).
    pub reference_upsample: usize,
    /// Channel means subtracted (RGB, on `[0, 1]` values).
    pub mean: [f32; 3],
    /// Channel standard deviations divided by.
    pub std: [f32; 3],
    /// Normalise twice, as the reference does before DINO.
    pub double_normalize: bool,
    /// Output with the features (tokens `[B, T, C]` or a map `[B, C, h, w]`).
    pub tokens: String,
    /// Tokens before the patch grid in a `[B, T, C]` output (1 for \[CLS\]; 5 for DINOv2 with
    /// registers).
    pub prefix_tokens: usize,
    /// Output with a `[B, C]` global descriptor (optional).
    pub cls: Option<String>,
    /// Output with a saliency map (optional; e.g. `cls_attn`).
    pub saliency: Option<String>,
    /// ONNX Runtime intra-op threads (0: as many as the rayon pool).
    pub threads: usize,
    /// Images per run when the model's batch dimension is symbolic.
    pub batch: usize,
}

impl Default for OnnxConfig {
    fn default() -> Self {
        OnnxConfig {
            model: PathBuf::from("weights/backbone.onnx"),
            runtime: None,
            input: "image".into(),
            input_size: 224,
            resize: Resize::Always,
            reference_upsample: 0,
            mean: IMAGENET_MEAN,
            std: IMAGENET_STD,
            double_normalize: false,
            tokens: "tokens".into(),
            prefix_tokens: 1,
            cls: None,
            saliency: None,
            threads: 0,
            batch: 8,
        }
    }
}

fn invalid(key: &str, reason: impl Into<String>) -> BuildError {
    BuildError::Invalid { kind: KIND.into(), key: key.into(), reason: reason.into() }
}

fn resource(message: impl Into<String>) -> BuildError {
    BuildError::Resource { kind: KIND.into(), message: message.into() }
}

/// The process's ONNX Runtime environment (ONNX Runtime allows one per process).
static ENVIRONMENT: Mutex<Option<Environment>> = Mutex::new(None);

/// Loads ONNX Runtime from `runtime` (or `ORT_DYLIB_PATH`) once per process.
fn environment(runtime: Option<&Path>) -> Result<Environment, BuildError> {
    // A configured library must exist even when ONNX Runtime is already loaded (it can only
    // be loaded once per process; later configurations share it).
    if let Some(p) = runtime {
        if !p.is_file() {
            return Err(resource(format!(
                "ONNX Runtime library `{}` (`runtime`) not found. {RUNTIME_HINT}",
                p.display()
            )));
        }
    }
    let mut env = ENVIRONMENT.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(e) = env.as_ref() {
        return Ok(e.clone());
    }
    let path = match runtime {
        Some(p) => p.to_path_buf(),
        None => match std::env::var_os("ORT_DYLIB_PATH") {
            Some(p) if !p.is_empty() => PathBuf::from(p),
            _ => return Err(resource(format!("no ONNX Runtime library configured. {RUNTIME_HINT}"))),
        },
    };
    if !path.is_file() {
        return Err(resource(format!(
            "ONNX Runtime library `{}` (ORT_DYLIB_PATH) not found. {RUNTIME_HINT}",
            path.display()
        )));
    }
    let built = ort::init_from(&path)
        .map_err(|e| resource(format!("cannot load ONNX Runtime from `{}`: {e}. {RUNTIME_HINT}", path.display())))?
        .with_name("nerf-sos")
        .build()
        .map_err(|e| resource(format!("cannot start ONNX Runtime from `{}`: {e}", path.display())))?;
    *env = Some(built.clone());
    Ok(built)
}

/// A loaded ONNX model with one float input.
pub struct OnnxModel {
    session: Mutex<Session>,
    input: String,
    /// Input dimensions as declared (`-1` or `0` for symbolic ones).
    pub input_dims: Vec<i64>,
    /// Output names.
    pub outputs: Vec<String>,
}

/// A float output: dimensions and values.
#[derive(Debug, Clone, PartialEq)]
pub struct Output {
    /// Dimensions.
    pub dims: Vec<usize>,
    /// Values, row-major.
    pub data: Vec<f32>,
}

impl OnnxModel {
    /// Loads `model` with ONNX Runtime from `runtime` (or `ORT_DYLIB_PATH`), running on
    /// `threads` intra-op threads (0: ONNX Runtime's default).
    pub fn load(model: &Path, runtime: Option<&Path>, input: &str, threads: usize) -> Result<OnnxModel, BuildError> {
        if !model.is_file() {
            return Err(resource(format!(
                "ONNX model `{}` not found; export the backbone to ONNX (see backbones/README.md: \
                 `torch.onnx.export`, or `sos-tools`' `vit_onnx_export` for a DINO ViT checkpoint) \
                 and set `model` in `[extractor]` to its path (a relative path is resolved against the \
                 config file's folder)",
                model.display()
            )));
        }
        let env = environment(runtime)?;
        let fail = |what: &str, e: String| resource(format!("ONNX model `{}`: {what}: {e}", model.display()));
        let mut builder = Session::builder(&env)
            .map_err(|e| fail("session options", e.to_string()))?
            .with_optimization_level(GraphOptimizationLevel::All)
            .map_err(|e| fail("session options", e.to_string()))?;
        if threads > 0 {
            builder = builder.with_intra_threads(threads).map_err(|e| fail("session options", e.to_string()))?;
        }
        let session = builder.commit_from_file(model).map_err(|e| fail("cannot load it", e.to_string()))?;
        let Some(inlet) = session.inputs().iter().find(|i| i.name() == input) else {
            let names: Vec<&str> = session.inputs().iter().map(|i| i.name()).collect();
            return Err(invalid(
                "input",
                format!("`{}` has no input `{input}`; its inputs are {names:?}", model.display()),
            ));
        };
        let input_dims = inlet.dtype().tensor_shape().map(|s| s.to_vec()).unwrap_or_default();
        let outputs = session.outputs().iter().map(|o| o.name().to_string()).collect();
        Ok(OnnxModel { session: Mutex::new(session), input: input.into(), input_dims, outputs })
    }

    /// Runs the model on `data` of shape `dims`, returning the named float outputs.
    pub fn run(&self, data: Vec<f32>, dims: &[usize], names: &[&str]) -> Result<Vec<Output>, String> {
        let tensor = Tensor::from_array((dims.to_vec(), data)).map_err(|e| e.to_string())?;
        let mut session = self.session.lock().unwrap_or_else(|e| e.into_inner());
        let outputs = session.run(ort::inputs![self.input.as_str() => tensor]).map_err(|e| e.to_string())?;
        names
            .iter()
            .map(|name| {
                let value = outputs.get(*name).ok_or_else(|| format!("no output `{name}`"))?;
                let (shape, values) =
                    value.try_extract_tensor::<f32>().map_err(|e| format!("output `{name}` is not float32: {e}"))?;
                Ok(Output { dims: shape.iter().map(|&d| d.max(0) as usize).collect(), data: values.to_vec() })
            })
            .collect()
    }
}

impl OnnxConfig {
    /// Checks the settings that do not need the files.
    pub fn validate(&self) -> Result<(), BuildError> {
        if !(8..=4096).contains(&self.input_size) {
            return Err(invalid("input_size", "must be between 8 and 4096 pixels"));
        }
        if self.std.iter().any(|&s| !(s.is_finite() && s > 0.0)) || self.mean.iter().any(|m| !m.is_finite()) {
            return Err(invalid("std", "means must be finite and standard deviations positive"));
        }
        if !(1..=256).contains(&self.batch) {
            return Err(invalid("batch", "must be between 1 and 256"));
        }
        if self.input.is_empty() || self.tokens.is_empty() {
            return Err(invalid("tokens", "input and output names must not be empty"));
        }
        Ok(())
    }
}

sos_core::plugin_kind! {
    kind: "onnx",
    summary: "any exported backbone (.onnx) through ONNX Runtime, loaded at run time (ORT_DYLIB_PATH)",
    default: || Box::new(OnnxConfig::default()),
    impl FeatureExtractorConfig for OnnxConfig {
        fn build(&self, ctx: &BuildContext) -> Result<Box<dyn FeatureExtractor>, BuildError> {
            let resolved = OnnxConfig {
                model: ctx.resolve(&self.model),
                runtime: self.runtime.as_deref().map(|r| ctx.resolve(r)),
                ..self.clone()
            };
            Ok(Box::new(OnnxExtractor::new(resolved)?))
        }
    }
}

/// The `onnx` extractor.
pub struct OnnxExtractor {
    config: OnnxConfig,
    model: OnnxModel,
    preprocess: Preprocess,
    /// Images per run.
    batch: usize,
    model_hash: u64,
}

impl OnnxExtractor {
    /// Loads the runtime and the model and checks the configured names against it.
    pub fn new(config: OnnxConfig) -> Result<OnnxExtractor, BuildError> {
        config.validate()?;
        let threads = if config.threads > 0 { config.threads } else { rayon::current_num_threads() };
        let model = OnnxModel::load(&config.model, config.runtime.as_deref(), &config.input, threads)?;
        let wanted = [
            Some(("tokens", &config.tokens)),
            config.cls.as_ref().map(|c| ("cls", c)),
            config.saliency.as_ref().map(|s| ("saliency", s)),
        ];
        for (key, name) in wanted.into_iter().flatten() {
            if !model.outputs.contains(name) {
                return Err(invalid(
                    key,
                    format!("`{}` has no output `{name}`; its outputs are {:?}", config.model.display(), model.outputs),
                ));
            }
        }
        let dims = &model.input_dims;
        if dims.len() != 4 || (dims[1] > 0 && dims[1] != 3) {
            return Err(invalid(
                "input",
                format!("input `{}` has dimensions {dims:?}, expected [batch, 3, h, w]", config.input),
            ));
        }
        let s = config.input_size as i64;
        if (dims[2] > 0 && dims[2] != s) || (dims[3] > 0 && dims[3] != s) {
            return Err(invalid(
                "input_size",
                format!("{} does not match the model's input {}x{}", config.input_size, dims[2], dims[3]),
            ));
        }
        let batch = if dims[0] > 0 { dims[0] as usize } else { config.batch };
        let bytes = std::fs::read(&config.model).map_err(|e| resource(format!("{}: {e}", config.model.display())))?;
        let preprocess = Preprocess {
            input_size: config.input_size,
            resize: config.resize,
            reference_upsample: config.reference_upsample,
            mean: config.mean,
            std: config.std,
            double_normalize: config.double_normalize,
            // Unresized inputs must have the model's size anyway: crop/enlarge to it.
            patch: 1,
        };
        Ok(OnnxExtractor { model_hash: content_hash(&bytes), config, model, preprocess, batch })
    }

    /// The loaded model.
    pub fn model(&self) -> &OnnxModel {
        &self.model
    }

    /// Features of a batch of preprocessed `[3, s, s]` inputs.
    fn run_batch(&self, inputs: &[Vec<f32>]) -> Result<Vec<FeatureMap>, String> {
        let s = self.config.input_size;
        let n = inputs.len();
        // Fixed-batch models get padding copies of the last image.
        let run_n = if self.model.input_dims[0] > 0 { self.batch } else { n };
        let mut data = Vec::with_capacity(run_n * 3 * s * s);
        for i in 0..run_n {
            data.extend_from_slice(&inputs[i.min(n - 1)]);
        }
        let mut names = vec![self.config.tokens.as_str()];
        names.extend(self.config.cls.as_deref());
        names.extend(self.config.saliency.as_deref());
        let outs = self.model.run(data, &[run_n, 3, s, s], &names)?;
        for (out, name) in outs.iter().zip(&names) {
            check_batch(out, name, run_n)?;
        }
        let tokens = &outs[0];
        let cls_out = self.config.cls.as_ref().map(|_| &outs[1]);
        let sal_out = self.config.saliency.as_ref().map(|_| &outs[names.len() - 1]);
        (0..n).map(|b| self.feature_map(tokens, cls_out, sal_out, b)).collect()
    }

    fn feature_map(
        &self,
        tokens: &Output,
        cls: Option<&Output>,
        saliency: Option<&Output>,
        b: usize,
    ) -> Result<FeatureMap, String> {
        let (channels, height, width, data, mut global) = match tokens.dims.as_slice() {
            [_, t, c] => {
                let prefix = self.config.prefix_tokens;
                let np = t.checked_sub(prefix).filter(|&np| np > 0).ok_or("fewer tokens than `prefix_tokens`")?;
                let (h, w) = grid_of(np);
                let x = &tokens.data[b * t * c..(b + 1) * t * c];
                let global = (prefix > 0).then(|| x[..*c].to_vec());
                (*c, h, w, patch_map(x, prefix, *c, np), global)
            }
            [_, c, h, w] => {
                let len = c * h * w;
                (*c, *h, *w, tokens.data[b * len..(b + 1) * len].to_vec(), None)
            }
            other => {
                return Err(format!(
                    "output `{}` has dimensions {other:?}, expected [B, T, C] or [B, C, h, w]",
                    self.config.tokens
                ))
            }
        };
        if let Some(out) = cls {
            let c = out.data.len() / out.dims.first().copied().unwrap_or(1).max(1);
            global = Some(out.data[b * c..(b + 1) * c].to_vec());
        }
        let np = height * width;
        let global = global.unwrap_or_else(|| {
            (0..channels).map(|k| data[k * np..(k + 1) * np].iter().sum::<f32>() / np as f32).collect()
        });
        let saliency = match saliency {
            Some(out) => {
                let per = out.data.len() / out.dims.first().copied().unwrap_or(1).max(1);
                let row = &out.data[b * per..(b + 1) * per];
                if per == np {
                    Some(row.to_vec())
                } else if per == np + self.config.prefix_tokens {
                    Some(row[self.config.prefix_tokens..].to_vec())
                } else {
                    return Err(format!("saliency output has {per} values per image for a {height}x{width} grid"));
                }
            }
            None => None,
        };
        Ok(FeatureMap { channels, height, width, data, cls: global, saliency })
    }
}

/// Checks that an output holds as many values as its dimensions say and one row per image of
/// the batch: a graph that folds the batch into another axis would otherwise be read out of
/// range.
fn check_batch(out: &Output, name: &str, images: usize) -> Result<(), String> {
    let declared = out.dims.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    if declared != Some(out.data.len()) {
        return Err(format!("output `{name}` has dimensions {:?} but {} values", out.dims, out.data.len()));
    }
    if out.dims.first().copied().unwrap_or(0) != images {
        return Err(format!(
            "output `{name}` has dimensions {:?} for a batch of {images} images; the model must keep the batch \
             as its first axis",
            out.dims
        ));
    }
    Ok(())
}

/// A patch grid `(h, w)` with `h·w = n` for a square input: the most square factorisation.
fn grid_of(n: usize) -> (usize, usize) {
    let mut h = (n as f64).sqrt() as usize;
    while h > 1 && !n.is_multiple_of(h) {
        h -= 1;
    }
    (h.max(1), n / h.max(1))
}

impl FeatureExtractor for OnnxExtractor {
    fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
        let inputs: Vec<Option<Vec<f32>>> = self
            .preprocess
            .apply_all(images)
            .into_par_iter()
            .zip(images)
            .map(|(t, img)| {
                t.map(|t| {
                    if t.height == self.config.input_size && t.width == self.config.input_size {
                        t.data
                    } else {
                        // Only `resize = "never"`/`"patches"` on other sizes gets here: resize.
                        Preprocess { resize: Resize::Always, ..self.preprocess.clone() }.apply(img).data
                    }
                })
            })
            .collect();
        let ok: Vec<usize> = (0..images.len()).filter(|&i| inputs[i].is_some()).collect();
        let mut maps: Vec<Option<FeatureMap>> = vec![None; images.len()];
        let mut channels = 1;
        for chunk in ok.chunks(self.batch) {
            let batch: Vec<Vec<f32>> = chunk.iter().filter_map(|&i| inputs[i].clone()).collect();
            let out = self.run_batch(&batch).map_err(|e| {
                ExtractError::new(
                    KIND,
                    format!(
                        "running `{}` on a batch of {} images failed: {e}",
                        self.config.model.display(),
                        batch.len()
                    ),
                )
            })?;
            for (&i, m) in chunk.iter().zip(out) {
                channels = m.channels;
                maps[i] = Some(m);
            }
        }
        // Only empty or malformed images are left: zero maps, as `dino-vit` gives them.
        Ok(maps.into_iter().map(|m| m.unwrap_or_else(|| FeatureMap::zeros(channels, channels))).collect())
    }

    fn identity(&self) -> String {
        let c = &self.config;
        format!(
            "{KIND}/v{VERSION} model={:016x} input={} input_size={} resize={} reference_upsample={} mean={:?} std={:?} \
             double_normalize={} tokens={} prefix_tokens={} cls={:?} saliency={:?}",
            self.model_hash,
            c.input,
            c.input_size,
            c.resize.name(),
            c.reference_upsample,
            c.mean,
            c.std,
            c.double_normalize,
            c.tokens,
            c.prefix_tokens,
            c.cls,
            c.saliency
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outputs_must_keep_one_row_per_image() {
        let out = |dims: Vec<usize>, len: usize| Output { dims, data: vec![0.0; len] };
        assert!(check_batch(&out(vec![2, 5, 8], 80), "tokens", 2).is_ok());
        // The batch folded into the token axis: read per image, it would run out of range.
        let err = check_batch(&out(vec![1, 10, 8], 80), "tokens", 2).unwrap_err();
        assert!(err.contains("`tokens`") && err.contains("first axis"), "{err}");
        let err = check_batch(&out(vec![2, 5, 8], 79), "tokens", 2).unwrap_err();
        assert!(err.contains("79 values"), "{err}");
    }
}
