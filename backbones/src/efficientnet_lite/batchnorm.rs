//! Inference BatchNorm folded into the convolution before it: `γ·(conv(x) − μ)/√(σ² + ε) + β`
//! is `conv'(x) + b'` with every weight of output channel `o` scaled by `s_o = γ_o/√(σ²_o + ε)`
//! and `b'_o = β_o − μ_o·s_o`. Folding once at load time removes a pass over every
//! activation; it is done in f64 so that it adds only the final rounding to f32.

/// A BatchNorm layer's parameters and running statistics.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchNorm {
    /// `γ`.
    pub weight: Vec<f32>,
    /// `β`.
    pub bias: Vec<f32>,
    /// Running mean `μ`.
    pub mean: Vec<f32>,
    /// Running variance `σ²`.
    pub var: Vec<f32>,
    /// `ε`.
    pub eps: f64,
}

impl BatchNorm {
    /// The identity (γ = 1, β = 0, μ = 0, σ² = 1 − ε), for synthetic networks.
    pub fn identity(channels: usize, eps: f64) -> BatchNorm {
        BatchNorm {
            weight: vec![1.0; channels],
            bias: vec![0.0; channels],
            mean: vec![0.0; channels],
            var: vec![(1.0 - eps) as f32; channels],
            eps,
        }
    }

    /// Channels.
    pub fn channels(&self) -> usize {
        self.weight.len()
    }

    /// Folds into a convolution whose weights are `[out_channels, per_channel]` row-major
    /// (PyTorch's layout, `per_channel = in·k·k`); returns the folded weights and bias.
    ///
    /// # Panics
    /// If `weight` does not hold `channels()` rows or the statistics differ in length (the
    /// loader checks every shape first).
    pub fn fold(&self, weight: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let c = self.channels();
        assert!(c > 0 && weight.len().is_multiple_of(c), "BatchNorm::fold: {} weights for {c} channels", weight.len());
        assert!([self.bias.len(), self.mean.len(), self.var.len()].iter().all(|&n| n == c), "BatchNorm::fold: lengths");
        let per = weight.len() / c;
        let mut w = Vec::with_capacity(weight.len());
        let mut b = Vec::with_capacity(c);
        for o in 0..c {
            let s = self.weight[o] as f64 / (self.var[o] as f64 + self.eps).sqrt();
            w.extend(weight[o * per..(o + 1) * per].iter().map(|&v| (v as f64 * s) as f32));
            b.push((self.bias[o] as f64 - self.mean[o] as f64 * s) as f32);
        }
        (w, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folded_layer_equals_conv_then_batchnorm() {
        // A 1x1 "convolution" of 3 inputs to 2 outputs at one pixel, then BatchNorm, in f64.
        let w = [0.5f32, -1.0, 2.0, 0.25, 0.75, -0.5];
        let bn = BatchNorm {
            weight: vec![1.5, 0.8],
            bias: vec![-0.2, 0.3],
            mean: vec![0.4, -1.1],
            var: vec![0.09, 2.5],
            eps: 1e-3,
        };
        let x = [1.2f64, -0.7, 0.3];
        let (fw, fb) = bn.fold(&w);
        for o in 0..2 {
            let conv: f64 = (0..3).map(|i| w[o * 3 + i] as f64 * x[i]).sum();
            let want =
                bn.weight[o] as f64 * (conv - bn.mean[o] as f64) / (bn.var[o] as f64 + 1e-3).sqrt() + bn.bias[o] as f64;
            let got: f64 = (0..3).map(|i| fw[o * 3 + i] as f64 * x[i]).sum::<f64>() + fb[o] as f64;
            assert!((got - want).abs() < 1e-6 * want.abs().max(1.0), "channel {o}: {got} vs {want}");
        }
        let (iw, ib) = BatchNorm::identity(2, 1e-3).fold(&w);
        assert!(iw.iter().zip(&w).all(|(a, b)| (a - b).abs() <= 1e-7 * b.abs()) && ib == [0.0, 0.0]);
    }
}
