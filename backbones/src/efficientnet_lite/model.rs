//! The EfficientNet-Lite0 forward pass (inference only) on the CPU, from the published
//! PyTorch port's state dict (`_conv_stem`, `_bn0`, `_blocks.N.{_expand_conv, _bn0,
//! _depthwise_conv, _bn1, _project_conv, _bn2}`, `_conv_head`, `_bn1`; the classifier `_fc`
//! is not used).
//!
//! Every BatchNorm is folded into the convolution before it when the weights are loaded. An
//! MBConv block is `x + BN(project(ReLU6(BN(depthwise(ReLU6(BN(expand(x))))))))`, the skip
//! only where the shape is kept; the head is `ReLU6(BN(conv1x1(x)))`.

use rand::{Rng, SeedableRng};

use super::arch::{self, BlockSpec, BN_EPS, HEAD_CHANNELS, STAGES, STEM_CHANNELS};
use super::batchnorm::BatchNorm;
use super::conv::{Conv2d, Depthwise, Pointwise};
use super::tensor::Nhwc;
use crate::checkpoint::{CheckpointError, StateDict};

/// Why a state dict is not an EfficientNet-Lite0.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// A tensor could not be read (missing, wrong type, corrupt).
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The names or shapes are not those of the published EfficientNet-Lite0.
    #[error("not an EfficientNet-Lite0 state dict: {0}")]
    NotLite(String),
}

/// One MBConv block with its BatchNorms folded in.
#[derive(Debug, Clone, PartialEq)]
pub struct MbConv {
    /// Its place in the architecture.
    pub spec: BlockSpec,
    /// 1x1 expansion with ReLU6 (absent when the expansion ratio is 1).
    pub expand: Option<Pointwise>,
    /// Depthwise convolution with ReLU6.
    pub depthwise: Depthwise,
    /// 1x1 projection, linear.
    pub project: Pointwise,
}

impl MbConv {
    /// The block's output.
    pub fn apply(&self, x: &Nhwc) -> Nhwc {
        let expanded = self.expand.as_ref().map(|e| e.apply(x, None));
        let mid = self.depthwise.apply(expanded.as_ref().unwrap_or(x));
        self.project.apply(&mid, self.spec.has_residual().then_some(x))
    }
}

/// What [`LiteNet::forward`] returns for a batch.
#[derive(Debug, Clone, PartialEq)]
pub struct LiteOutput {
    /// The output of each of the 7 stages (index 0 is stage 1).
    pub stages: Vec<Nhwc>,
    /// The head's activations, `ReLU6(BN(conv1x1))` with 1280 channels (the published
    /// `extract_features`).
    pub head: Nhwc,
}

/// EfficientNet-Lite0 with its weights.
#[derive(Debug, Clone, PartialEq)]
pub struct LiteNet {
    /// 3x3 stride-2 stem with ReLU6.
    pub stem: Conv2d,
    /// The 16 MBConv blocks.
    pub blocks: Vec<MbConv>,
    /// 1x1 head with ReLU6.
    pub head: Pointwise,
}

fn expect_shape(sd: &StateDict, name: &str, want: &[usize]) -> Result<(), LoadError> {
    match sd.shape(name) {
        None => Err(LoadError::NotLite(format!("tensor `{name}` is missing"))),
        Some(s) if s == want => Ok(()),
        Some(s) => Err(LoadError::NotLite(format!("tensor `{name}` has shape {s:?}, expected {want:?}"))),
    }
}

/// Reads a tensor after checking its shape.
fn get(sd: &StateDict, name: &str, want: &[usize]) -> Result<Vec<f32>, LoadError> {
    expect_shape(sd, name, want)?;
    Ok(sd.f32(name)?)
}

/// Reads the BatchNorm under `prefix` and folds it into the convolution weights `weight`.
fn folded(sd: &StateDict, prefix: &str, weight: &[f32], channels: usize) -> Result<(Vec<f32>, Vec<f32>), LoadError> {
    let part = |p: &str| get(sd, &format!("{prefix}.{p}"), &[channels]);
    let bn = BatchNorm {
        weight: part("weight")?,
        bias: part("bias")?,
        mean: part("running_mean")?,
        var: part("running_var")?,
        eps: BN_EPS,
    };
    if let Some(v) = bn.var.iter().find(|v| !(**v >= 0.0 && v.is_finite())) {
        return Err(LoadError::NotLite(format!("`{prefix}.running_var` holds {v}, not a variance")));
    }
    Ok(bn.fold(weight))
}

/// Checks that the state dict is the published Lite0 port's before reading any weight, so
/// that another network is named as such rather than by its first odd tensor.
fn check_family(sd: &StateDict) -> Result<(), LoadError> {
    if sd.shape("_conv_stem.weight").is_none() {
        let names: Vec<&str> = sd.names().take(5).collect();
        return Err(LoadError::NotLite(format!("it has no `_conv_stem.weight` (its first tensors are {names:?})")));
    }
    if sd.names().any(|n| n.contains("._se_reduce.")) {
        return Err(LoadError::NotLite(
            "its blocks have squeeze-excite layers (`_se_reduce`): this is an EfficientNet-B*, not a Lite model".into(),
        ));
    }
    let blocks = (0..).take_while(|i| sd.shape(&format!("_blocks.{i}._depthwise_conv.weight")).is_some()).count();
    let want = arch::lite0_blocks().len();
    if blocks != want {
        return Err(LoadError::NotLite(format!(
            "it has {blocks} MBConv blocks, EfficientNet-Lite0 has {want} (Lite1-4 are deeper and are not supported)"
        )));
    }
    Ok(())
}

impl LiteNet {
    /// Builds the network from the published port's state dict, checking every shape and
    /// folding every BatchNorm.
    pub fn from_state_dict(sd: &StateDict) -> Result<LiteNet, LoadError> {
        check_family(sd)?;
        let stem_w = get(sd, "_conv_stem.weight", &[STEM_CHANNELS, 3, 3, 3])?;
        let (w, b) = folded(sd, "_bn0", &stem_w, STEM_CHANNELS)?;
        let stem = Conv2d::from_torch(&w, b, 3, 3, 2, true);
        let mut blocks = Vec::new();
        for (i, spec) in arch::lite0_blocks().into_iter().enumerate() {
            let p = format!("_blocks.{i}");
            let expand = if spec.has_expansion() {
                let w = get(sd, &format!("{p}._expand_conv.weight"), &[spec.hidden, spec.input, 1, 1])?;
                let (w, b) = folded(sd, &format!("{p}._bn0"), &w, spec.hidden)?;
                Some(Pointwise::from_torch(&w, b, spec.input, true))
            } else {
                None
            };
            let k = spec.kernel;
            let w = get(sd, &format!("{p}._depthwise_conv.weight"), &[spec.hidden, 1, k, k])?;
            let (w, b) = folded(sd, &format!("{p}._bn1"), &w, spec.hidden)?;
            let depthwise = Depthwise::from_torch(&w, b, k, spec.stride, true);
            let w = get(sd, &format!("{p}._project_conv.weight"), &[spec.output, spec.hidden, 1, 1])?;
            let (w, b) = folded(sd, &format!("{p}._bn2"), &w, spec.output)?;
            let project = Pointwise::from_torch(&w, b, spec.hidden, false);
            blocks.push(MbConv { spec, expand, depthwise, project });
        }
        let last = arch::stage_channels(STAGES);
        let w = get(sd, "_conv_head.weight", &[HEAD_CHANNELS, last, 1, 1])?;
        let (w, b) = folded(sd, "_bn1", &w, HEAD_CHANNELS)?;
        Ok(LiteNet { stem, blocks, head: Pointwise::from_torch(&w, b, last, true) })
    }

    /// A network with deterministic random weights (He-uniform, so that activations keep
    /// their scale through the depth; biases small), for shape and timing tests.
    pub fn random(seed: u64) -> LiteNet {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut draw = |n: usize, fan_in: usize, gain: f32| -> Vec<f32> {
            let bound = (gain * 3.0 / fan_in as f32).sqrt();
            (0..n).map(|_| rng.gen_range(-bound..bound)).collect()
        };
        let stem = Conv2d::from_torch(&draw(STEM_CHANNELS * 27, 27, 2.0), draw(STEM_CHANNELS, 100, 1.0), 3, 3, 2, true);
        let blocks = arch::lite0_blocks()
            .into_iter()
            .map(|spec| {
                let (i, h, o, k) = (spec.input, spec.hidden, spec.output, spec.kernel);
                let expand = spec
                    .has_expansion()
                    .then(|| Pointwise::from_torch(&draw(h * i, i, 2.0), draw(h, 100, 1.0), i, true));
                let depthwise =
                    Depthwise::from_torch(&draw(h * k * k, k * k, 2.0), draw(h, 100, 1.0), k, spec.stride, true);
                let project = Pointwise::from_torch(&draw(o * h, h, 1.0), draw(o, 100, 1.0), h, false);
                MbConv { spec, expand, depthwise, project }
            })
            .collect();
        let last = arch::stage_channels(STAGES);
        let head =
            Pointwise::from_torch(&draw(HEAD_CHANNELS * last, last, 2.0), draw(HEAD_CHANNELS, 100, 1.0), last, true);
        LiteNet { stem, blocks, head }
    }

    /// Number of weights after folding (convolution weights and biases).
    pub fn num_parameters(&self) -> usize {
        let pw = |p: &Pointwise| p.weight.len() + p.bias.len();
        let blocks: usize = self
            .blocks
            .iter()
            .map(|b| {
                b.expand.as_ref().map_or(0, pw) + b.depthwise.weight.len() + b.depthwise.bias.len() + pw(&b.project)
            })
            .sum();
        self.stem.weight.len() + self.stem.bias.len() + blocks + pw(&self.head)
    }

    /// Runs a batch of normalised images `[batch, 3, height, width]` (NCHW). Padding is
    /// TensorFlow's "SAME" for any size; for sides that are multiples of 32 it is also what the
    /// published port (padding fixed for 224 px) applies.
    ///
    /// # Panics
    /// If `images` does not hold `batch·3·height·width` values (the extractor never passes
    /// such inputs).
    pub fn forward(&self, images: &[f32], batch: usize, height: usize, width: usize) -> LiteOutput {
        let mut x = self.stem.apply_nchw(images, batch, height, width);
        let mut stages = Vec::with_capacity(STAGES);
        for (i, block) in self.blocks.iter().enumerate() {
            x = block.apply(&x);
            let stage_ends = self.blocks.get(i + 1).is_none_or(|next| next.spec.stage != block.spec.stage);
            if stage_ends {
                stages.push(x.clone());
            }
        }
        let head = self.head.apply(&x, None);
        LiteOutput { stages, head }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_network_has_lite0_size_and_shapes() {
        let net = LiteNet::random(3);
        // EfficientNet-Lite0 has 4,652,008 trainable parameters; without the 1000-class
        // classifier (1,281,000) 3,371,008, whose 21,008 BatchNorm scale-shift pairs fold
        // into one bias per channel.
        assert_eq!(net.num_parameters(), 3_371_008 - 21_008);
        let (b, h, w) = (2, 64, 96);
        let images: Vec<f32> = (0..b * 3 * h * w).map(|i| ((i * 7919) % 255) as f32 / 64.0 - 2.0).collect();
        let out = net.forward(&images, b, h, w);
        let dims: Vec<(usize, usize, usize)> = out.stages.iter().map(|s| (s.height, s.width, s.channels)).collect();
        assert_eq!(dims, [(32, 48, 16), (16, 24, 24), (8, 12, 40), (4, 6, 80), (4, 6, 112), (2, 3, 192), (2, 3, 320)]);
        assert_eq!((out.head.batch, out.head.height, out.head.width, out.head.channels), (2, 2, 3, 1280));
        assert!(out.stages.iter().chain([&out.head]).all(|s| s.data.iter().all(|v| v.is_finite())));
        // Not degenerate: the head is neither all zeros nor saturated everywhere.
        let active = out.head.data.iter().filter(|&&v| v > 0.0 && v < 6.0).count();
        assert!(active > out.head.data.len() / 20, "{active} of {}", out.head.data.len());
    }
}
