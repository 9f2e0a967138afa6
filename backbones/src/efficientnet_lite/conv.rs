//! The three convolutions of EfficientNet-Lite, each with its BatchNorm folded in (a bias)
//! and an optional ReLU6, with TensorFlow's "SAME" padding:
//!
//! - [`Conv2d`]: a dense `k×k` convolution of a channel-first input (the stem), as one GEMM
//!   over unfolded patches;
//! - [`Pointwise`]: a 1x1 convolution, one GEMM over every pixel of the batch, optionally
//!   adding a residual;
//! - [`Depthwise`]: a `k×k` per-channel convolution, one task per output row, vectorised
//!   along the channels.

use rayon::prelude::*;
use sos_core::nn::{matmul, MatRef};

use super::tensor::{add_bias_activate, Nhwc};

/// TensorFlow "SAME" padding (the published `Conv2d*SamePadding`): `(output size, padding
/// before)` of a side; the padding after is whatever completes `⌈input/stride⌉` outputs.
pub fn same_padding(input: usize, kernel: usize, stride: usize) -> (usize, usize) {
    let out = input.div_ceil(stride);
    let total = ((out.saturating_sub(1)) * stride + kernel).saturating_sub(input);
    (out, total / 2)
}

/// Input index of output `o` and kernel tap `k`, or `None` in the padding.
fn source(o: usize, k: usize, stride: usize, pad: usize, size: usize) -> Option<usize> {
    (o * stride + k).checked_sub(pad).filter(|&i| i < size)
}

/// The `[cols, rows]` transpose of a row-major `[rows, cols]` matrix: PyTorch's
/// output-channel-major weights turned input-major for the GEMMs and channel loops here.
fn transposed(m: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    let mut t = vec![0.0; rows * cols];
    for r in 0..rows {
        for c in 0..cols {
            t[c * rows + r] = m[r * cols + c];
        }
    }
    t
}

/// A dense `kernel × kernel` convolution, weights `[in·k·k, out]` (PyTorch's `[out, in, k, k]`
/// transposed).
#[derive(Debug, Clone, PartialEq)]
pub struct Conv2d {
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Kernel side.
    pub kernel: usize,
    /// Stride.
    pub stride: usize,
    /// `[cin·k·k, cout]` row-major, rows ordered `(c, ky, kx)`.
    pub weight: Vec<f32>,
    /// `[cout]`.
    pub bias: Vec<f32>,
    /// Clamp to `[0, 6]` after the bias.
    pub relu6: bool,
}

impl Conv2d {
    /// From PyTorch's `[cout, cin, k, k]` weights (BatchNorm already folded in).
    pub fn from_torch(weight: &[f32], bias: Vec<f32>, cin: usize, kernel: usize, stride: usize, relu6: bool) -> Conv2d {
        let cout = bias.len();
        let k = cin * kernel * kernel;
        assert_eq!(weight.len(), cout * k, "Conv2d::from_torch: weight size");
        let w = transposed(weight, cout, k);
        Conv2d { cin, cout, kernel, stride, weight: w, bias, relu6 }
    }

    /// Output of a channel-first batch `[batch, cin, height, width]`, channel-last.
    ///
    /// # Panics
    /// If `x` does not hold `batch·cin·height·width` values.
    pub fn apply_nchw(&self, x: &[f32], batch: usize, height: usize, width: usize) -> Nhwc {
        assert_eq!(x.len(), batch * self.cin * height * width, "Conv2d: input size");
        let (k, s) = (self.kernel, self.stride);
        let (oh, pad_y) = same_padding(height, k, s);
        let (ow, pad_x) = same_padding(width, k, s);
        let cols_per_row = self.cin * k * k;
        let mut cols = vec![0.0f32; batch * oh * ow * cols_per_row];
        cols.par_chunks_mut(ow * cols_per_row).enumerate().for_each(|(row, out)| {
            let (b, oy) = (row / oh, row % oh);
            for (ox, col) in out.chunks_exact_mut(cols_per_row).enumerate() {
                for c in 0..self.cin {
                    let plane = &x[(b * self.cin + c) * height * width..][..height * width];
                    for ky in 0..k {
                        let Some(iy) = source(oy, ky, s, pad_y, height) else { continue };
                        for kx in 0..k {
                            if let Some(ix) = source(ox, kx, s, pad_x, width) {
                                col[(c * k + ky) * k + kx] = plane[iy * width + ix];
                            }
                        }
                    }
                }
            }
        });
        let mut out = Nhwc::zeros(batch, oh, ow, self.cout);
        let rows = out.pixels();
        matmul(
            MatRef::new(&cols, rows, cols_per_row),
            MatRef::new(&self.weight, cols_per_row, self.cout),
            &mut out.data,
            false,
        );
        add_bias_activate(&mut out.data, &self.bias, self.relu6);
        out
    }
}

/// A 1x1 convolution, weights `[cin, cout]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Pointwise {
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// `[cin, cout]` row-major.
    pub weight: Vec<f32>,
    /// `[cout]`.
    pub bias: Vec<f32>,
    /// Clamp to `[0, 6]` after the bias (never together with a residual).
    pub relu6: bool,
}

impl Pointwise {
    /// From PyTorch's `[cout, cin, 1, 1]` weights (BatchNorm already folded in).
    pub fn from_torch(weight: &[f32], bias: Vec<f32>, cin: usize, relu6: bool) -> Pointwise {
        let cout = bias.len();
        assert_eq!(weight.len(), cout * cin, "Pointwise::from_torch: weight size");
        let mut w = vec![0.0; cin * cout];
        for o in 0..cout {
            for i in 0..cin {
                w[i * cout + o] = weight[o * cin + i];
            }
        }
        Pointwise { cin, cout, weight: w, bias, relu6 }
    }

    /// `x·W + b` (then ReLU6), plus `residual` when given (the MBConv skip connection).
    ///
    /// # Panics
    /// If `x` has other than `cin` channels or `residual` another shape than the output.
    pub fn apply(&self, x: &Nhwc, residual: Option<&Nhwc>) -> Nhwc {
        assert_eq!(x.channels, self.cin, "Pointwise: input channels");
        let (rows, accumulate, mut out) = match residual {
            Some(r) => {
                assert_eq!((r.batch, r.height, r.width, r.channels), (x.batch, x.height, x.width, self.cout));
                (x.pixels(), true, r.clone())
            }
            None => (x.pixels(), false, Nhwc::zeros(x.batch, x.height, x.width, self.cout)),
        };
        matmul(
            MatRef::new(&x.data, rows, self.cin),
            MatRef::new(&self.weight, self.cin, self.cout),
            &mut out.data,
            accumulate,
        );
        add_bias_activate(&mut out.data, &self.bias, self.relu6);
        out
    }
}

/// A `kernel × kernel` depthwise convolution, weights tap-major `[k·k, channels]` so that each
/// tap is one contiguous multiply-add along the channels of a pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct Depthwise {
    /// Channels.
    pub channels: usize,
    /// Kernel side.
    pub kernel: usize,
    /// Stride.
    pub stride: usize,
    /// `[k·k, channels]` row-major.
    pub weight: Vec<f32>,
    /// `[channels]`.
    pub bias: Vec<f32>,
    /// Clamp to `[0, 6]` after the bias.
    pub relu6: bool,
}

impl Depthwise {
    /// From PyTorch's `[channels, 1, k, k]` weights (BatchNorm already folded in).
    pub fn from_torch(weight: &[f32], bias: Vec<f32>, kernel: usize, stride: usize, relu6: bool) -> Depthwise {
        let c = bias.len();
        let taps = kernel * kernel;
        assert_eq!(weight.len(), c * taps, "Depthwise::from_torch: weight size");
        let w = transposed(weight, c, taps);
        Depthwise { channels: c, kernel, stride, weight: w, bias, relu6 }
    }

    /// The convolution of `x`, channel-last.
    ///
    /// # Panics
    /// If `x` has other than `channels` channels.
    pub fn apply(&self, x: &Nhwc) -> Nhwc {
        let c = self.channels;
        assert_eq!(x.channels, c, "Depthwise: input channels");
        let (k, s) = (self.kernel, self.stride);
        let (oh, pad_y) = same_padding(x.height, k, s);
        let (ow, pad_x) = same_padding(x.width, k, s);
        let mut out = Nhwc::zeros(x.batch, oh, ow, c);
        let (h, w) = (x.height, x.width);
        out.data.par_chunks_mut(ow * c).enumerate().for_each(|(row, orow)| {
            let (b, oy) = (row / oh, row % oh);
            let image = &x.data[b * h * w * c..(b + 1) * h * w * c];
            for (ox, acc) in orow.chunks_exact_mut(c).enumerate() {
                acc.copy_from_slice(&self.bias);
                for ky in 0..k {
                    let Some(iy) = source(oy, ky, s, pad_y, h) else { continue };
                    for kx in 0..k {
                        let Some(ix) = source(ox, kx, s, pad_x, w) else { continue };
                        let px = &image[(iy * w + ix) * c..][..c];
                        let tap = &self.weight[(ky * k + kx) * c..][..c];
                        for ((a, &v), &t) in acc.iter_mut().zip(px).zip(tap) {
                            *a += v * t;
                        }
                    }
                }
                if self.relu6 {
                    acc.iter_mut().for_each(|v| *v = v.clamp(0.0, 6.0));
                }
            }
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A value pattern without symmetries.
    fn pattern(n: usize, seed: usize) -> Vec<f32> {
        (0..n).map(|i| ((((i + seed) * 2654435761) % 1999) as f32 / 999.5 - 1.0) * 1.3).collect()
    }

    /// Grouped convolution in f64 with plain loops over a zero-padded NCHW input, as PyTorch
    /// defines it (`groups = 1`: dense, `groups = cin`: depthwise); output NCHW.
    #[allow(clippy::too_many_arguments)]
    fn naive(
        x: &[f32],
        cin: usize,
        h: usize,
        w: usize,
        wt: &[f32],
        cout: usize,
        k: usize,
        s: usize,
        groups: usize,
    ) -> (Vec<f64>, usize, usize) {
        let (oh, ow) = (h.div_ceil(s), w.div_ceil(s));
        let ph = ((oh - 1) * s + k).saturating_sub(h);
        let pw = ((ow - 1) * s + k).saturating_sub(w);
        let (top, left) = (ph / 2, pw / 2);
        let (gin, gout) = (cin / groups, cout / groups);
        let mut out = vec![0.0f64; cout * oh * ow];
        for o in 0..cout {
            let g = o / gout;
            for oy in 0..oh {
                for ox in 0..ow {
                    let mut acc = 0.0f64;
                    for ci in 0..gin {
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) =
                                    ((oy * s + ky) as isize - top as isize, (ox * s + kx) as isize - left as isize);
                                if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                    continue;
                                }
                                let c = g * gin + ci;
                                acc += x[(c * h + iy as usize) * w + ix as usize] as f64
                                    * wt[((o * gin + ci) * k + ky) * k + kx] as f64;
                            }
                        }
                    }
                    out[(o * oh + oy) * ow + ox] = acc;
                }
            }
        }
        (out, oh, ow)
    }

    fn nchw_to_nhwc(x: &[f32], c: usize, h: usize, w: usize) -> Nhwc {
        let mut t = Nhwc::zeros(1, h, w, c);
        for ch in 0..c {
            for p in 0..h * w {
                t.data[p * c + ch] = x[ch * h * w + p];
            }
        }
        t
    }

    fn max_err(got: &Nhwc, want: &[f64], bias: &[f32], relu6: bool) -> f64 {
        let (c, np) = (got.channels, got.height * got.width);
        let chw = got.image_chw(0);
        (0..c * np)
            .map(|i| {
                let mut v = want[i] + bias[i / np] as f64;
                if relu6 {
                    v = v.clamp(0.0, 6.0);
                }
                (chw[i] as f64 - v).abs()
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn same_padding_matches_tensorflow() {
        // (input, kernel, stride) -> (output, padding before); TF pads the extra pixel after.
        assert_eq!(same_padding(224, 3, 2), (112, 0));
        assert_eq!(same_padding(112, 5, 2), (56, 1));
        assert_eq!(same_padding(11, 3, 2), (6, 1));
        assert_eq!(same_padding(7, 5, 1), (7, 2));
        assert_eq!(same_padding(1, 5, 2), (1, 2));
        assert_eq!(same_padding(2, 1, 1), (2, 0));
    }

    #[test]
    fn depthwise_matches_plain_loops_at_odd_sizes_and_strides() {
        for (c, h, w, k, s) in [
            (5usize, 9usize, 7usize, 3usize, 1usize),
            (7, 11, 10, 5, 2),
            (3, 4, 5, 3, 2),
            (16, 6, 6, 5, 1),
            (2, 1, 3, 5, 2),
        ] {
            let x = pattern(c * h * w, c + h);
            let wt = pattern(c * k * k, k + s);
            let bias = pattern(c, 7);
            for relu6 in [false, true] {
                let dw = Depthwise::from_torch(&wt, bias.clone(), k, s, relu6);
                let got = dw.apply(&nchw_to_nhwc(&x, c, h, w));
                let (want, oh, ow) = naive(&x, c, h, w, &wt, c, k, s, c);
                assert_eq!((got.height, got.width), (oh, ow));
                let err = max_err(&got, &want, &bias, relu6);
                assert!(err < 1e-5, "c{c} {h}x{w} k{k} s{s}: {err}");
            }
        }
    }

    #[test]
    fn dense_and_pointwise_match_plain_loops() {
        for (cin, cout, h, w, k, s) in
            [(3usize, 8usize, 11usize, 10usize, 3usize, 2usize), (3, 5, 6, 9, 3, 1), (4, 6, 5, 5, 1, 1)]
        {
            let x = pattern(cin * h * w, cin * h);
            let wt = pattern(cout * cin * k * k, cout);
            let bias = pattern(cout, 3);
            let conv = Conv2d::from_torch(&wt, bias.clone(), cin, k, s, true);
            let got = conv.apply_nchw(&x, 1, h, w);
            let (want, _, _) = naive(&x, cin, h, w, &wt, cout, k, s, 1);
            assert!(max_err(&got, &want, &bias, true) < 1e-5, "dense {cin}->{cout} k{k} s{s}");
            if k == 1 {
                let pw = Pointwise::from_torch(&wt, bias.clone(), cin, false);
                let input = nchw_to_nhwc(&x, cin, h, w);
                let got = pw.apply(&input, None);
                assert!(max_err(&got, &want, &bias, false) < 1e-5);
                // With a residual: the same plus the residual's values.
                let res = nchw_to_nhwc(&pattern(cout * h * w, 11), cout, h, w);
                let with = pw.apply(&input, Some(&res));
                for ((a, b), r) in with.data.iter().zip(&got.data).zip(&res.data) {
                    assert!((a - (b + r)).abs() < 1e-5);
                }
            }
        }
    }
}
