//! The EfficientNet-Lite0 architecture (TensorFlow's `efficientnet_lite_builder.py`, as the
//! published PyTorch port `efficientnet_lite_pytorch` builds it): a 3x3 stride-2 stem of 32
//! channels, seven stages of MBConv blocks without squeeze-excite, and a 1x1 head of 1280
//! channels; ReLU6 everywhere, BatchNorm epsilon 1e-3, TensorFlow "SAME" padding.

/// Output channels of the stem (not scaled in the Lite models).
pub const STEM_CHANNELS: usize = 32;
/// Output channels of the head convolution (not scaled in the Lite models).
pub const HEAD_CHANNELS: usize = 1280;
/// BatchNorm epsilon of every layer (the builder's `batch_norm_epsilon`).
pub const BN_EPS: f64 = 1e-3;
/// Number of MBConv stages.
pub const STAGES: usize = 7;
/// The total stride of the network: inputs whose sides are multiples of it are padded alike by
/// TensorFlow's dynamic "SAME" padding and by the published port's padding fixed for 224 px.
pub const NETWORK_STRIDE: usize = 32;

/// One stage row of the builder: `r{repeats}_k{kernel}_s{stride}_e{expand}_i{input}_o{output}`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StageSpec {
    /// Blocks in the stage.
    pub repeats: usize,
    /// Depthwise kernel side.
    pub kernel: usize,
    /// Stride of the stage's first block.
    pub stride: usize,
    /// Expansion ratio of the inverted bottleneck (1: no expansion convolution).
    pub expand: usize,
    /// Input channels of the first block.
    pub input: usize,
    /// Output channels of every block.
    pub output: usize,
}

/// EfficientNet-Lite0's stages (width and depth multipliers 1.0).
pub const LITE0: [StageSpec; STAGES] = [
    StageSpec { repeats: 1, kernel: 3, stride: 1, expand: 1, input: 32, output: 16 },
    StageSpec { repeats: 2, kernel: 3, stride: 2, expand: 6, input: 16, output: 24 },
    StageSpec { repeats: 2, kernel: 5, stride: 2, expand: 6, input: 24, output: 40 },
    StageSpec { repeats: 3, kernel: 3, stride: 2, expand: 6, input: 40, output: 80 },
    StageSpec { repeats: 3, kernel: 5, stride: 1, expand: 6, input: 80, output: 112 },
    StageSpec { repeats: 4, kernel: 5, stride: 2, expand: 6, input: 112, output: 192 },
    StageSpec { repeats: 1, kernel: 3, stride: 1, expand: 6, input: 192, output: 320 },
];

/// One MBConv block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockSpec {
    /// Stage it belongs to (1-based, as in the docs and the config).
    pub stage: usize,
    /// Depthwise kernel side.
    pub kernel: usize,
    /// Depthwise stride.
    pub stride: usize,
    /// Input channels.
    pub input: usize,
    /// Channels after the expansion (equal to `input` without one).
    pub hidden: usize,
    /// Output channels.
    pub output: usize,
}

impl BlockSpec {
    /// Whether the block has the 1x1 expansion convolution.
    pub fn has_expansion(&self) -> bool {
        self.hidden != self.input
    }

    /// Whether the input is added to the output (same shape, stride 1).
    pub fn has_residual(&self) -> bool {
        self.stride == 1 && self.input == self.output
    }
}

/// The 16 blocks of EfficientNet-Lite0 in order: the first block of a stage has its stride
/// and input width, the others stride 1 and the stage's output width.
pub fn lite0_blocks() -> Vec<BlockSpec> {
    let mut blocks = Vec::new();
    for (i, s) in LITE0.iter().enumerate() {
        for r in 0..s.repeats {
            let input = if r == 0 { s.input } else { s.output };
            let stride = if r == 0 { s.stride } else { 1 };
            blocks.push(BlockSpec {
                stage: i + 1,
                kernel: s.kernel,
                stride,
                input,
                hidden: input * s.expand,
                output: s.output,
            });
        }
    }
    blocks
}

/// Stride of a stage's output relative to the input image (`stage` is 1-based).
pub fn stage_stride(stage: usize) -> usize {
    LITE0.iter().take(stage).fold(2, |acc, s| acc * s.stride)
}

/// Channels of a stage's output (`stage` is 1-based).
pub fn stage_channels(stage: usize) -> usize {
    LITE0[stage - 1].output
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lite0_has_16_blocks_and_the_published_strides() {
        let blocks = lite0_blocks();
        assert_eq!(blocks.len(), 16);
        assert_eq!((1..=STAGES).map(stage_stride).collect::<Vec<_>>(), [2, 4, 8, 16, 16, 32, 32]);
        assert_eq!((1..=STAGES).map(stage_channels).collect::<Vec<_>>(), [16, 24, 40, 80, 112, 192, 320]);
        assert!(!blocks[0].has_expansion() && !blocks[0].has_residual());
        assert!(blocks[1].has_expansion() && !blocks[1].has_residual() && blocks[2].has_residual());
        assert_eq!(
            (blocks[8].input, blocks[8].hidden, blocks[8].stride, blocks[8].has_residual()),
            (80, 480, 1, false)
        );
        assert_eq!(blocks.iter().map(|b| b.stride).product::<usize>() * 2, NETWORK_STRIDE);
        assert_eq!(blocks.last().map(|b| (b.stage, b.output)), Some((7, 320)));
    }
}
