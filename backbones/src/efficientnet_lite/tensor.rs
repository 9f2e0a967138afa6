//! Activations of a batch, channel-last (`[batch, height, width, channels]`): a 1x1
//! convolution is then one GEMM over all pixels of the batch, and a depthwise convolution
//! runs along contiguous channels.

use rayon::prelude::*;

/// Pixels per task of the element-wise passes.
const PIXELS_PER_TASK: usize = 256;

/// A channel-last activation tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct Nhwc {
    /// Images.
    pub batch: usize,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// Channels.
    pub channels: usize,
    /// `[batch, height, width, channels]` row-major.
    pub data: Vec<f32>,
}

impl Nhwc {
    /// A tensor of zeros.
    pub fn zeros(batch: usize, height: usize, width: usize, channels: usize) -> Nhwc {
        Nhwc { batch, height, width, channels, data: vec![0.0; batch * height * width * channels] }
    }

    /// Pixels over the whole batch.
    pub fn pixels(&self) -> usize {
        self.batch * self.height * self.width
    }

    /// One image channel-first, `[channels, height, width]`.
    pub fn image_chw(&self, b: usize) -> Vec<f32> {
        let (c, np) = (self.channels, self.height * self.width);
        let src = &self.data[b * np * c..(b + 1) * np * c];
        let mut out = vec![0.0f32; c * np];
        for (p, px) in src.chunks_exact(c).enumerate() {
            for (k, &v) in px.iter().enumerate() {
                out[k * np + p] = v;
            }
        }
        out
    }

    /// Mean over the pixels of image `b`, per channel (global average pooling).
    pub fn image_mean(&self, b: usize) -> Vec<f32> {
        let (c, np) = (self.channels, self.height * self.width);
        // Summed in f64: the pooled vector is a mean of up to thousands of values.
        let mut sum = vec![0.0f64; c];
        for px in self.data[b * np * c..(b + 1) * np * c].chunks_exact(c) {
            for (s, &v) in sum.iter_mut().zip(px) {
                *s += v as f64;
            }
        }
        sum.into_iter().map(|s| (s / np.max(1) as f64) as f32).collect()
    }

    /// Euclidean norm over the channels at each pixel of image `b`, `[height, width]`.
    pub fn image_channel_norm(&self, b: usize) -> Vec<f32> {
        let (c, np) = (self.channels, self.height * self.width);
        self.data[b * np * c..(b + 1) * np * c]
            .chunks_exact(c)
            .map(|px| px.iter().map(|&v| v as f64 * v as f64).sum::<f64>().sqrt() as f32)
            .collect()
    }
}

/// Adds `bias` to every pixel and clamps to `[0, 6]` when `relu6`, in parallel.
pub fn add_bias_activate(data: &mut [f32], bias: &[f32], relu6: bool) {
    let c = bias.len();
    data.par_chunks_mut(c * PIXELS_PER_TASK).for_each(|chunk| {
        for px in chunk.chunks_exact_mut(c) {
            for (v, b) in px.iter_mut().zip(bias) {
                *v += b;
            }
            if relu6 {
                px.iter_mut().for_each(|v| *v = v.clamp(0.0, 6.0));
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_conversions_pooling_and_norms() {
        // 2 images of 1x2 pixels, 3 channels: value = 100·b + 10·pixel + channel.
        let data = (0..2).flat_map(|b| (0..2).flat_map(move |p| (0..3).map(move |c| (100 * b + 10 * p + c) as f32)));
        let t = Nhwc { batch: 2, height: 1, width: 2, channels: 3, data: data.collect() };
        assert_eq!(t.image_chw(1), vec![100.0, 110.0, 101.0, 111.0, 102.0, 112.0]);
        assert_eq!(t.image_mean(0), vec![5.0, 6.0, 7.0]);
        let n = t.image_channel_norm(0);
        assert!((n[1] - (100.0f32 + 121.0 + 144.0).sqrt()).abs() < 1e-5);
        let mut d = vec![-1.0, 5.5, 3.0, 9.0];
        add_bias_activate(&mut d, &[0.5, 1.0], true);
        assert_eq!(d, vec![0.0, 6.0, 3.5, 6.0]);
    }
}
