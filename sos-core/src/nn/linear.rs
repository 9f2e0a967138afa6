//! Fully connected layer `y = x·W + b`.

use rand::Rng;
use serde::{Deserialize, Serialize};

use super::activation::{add_column_sums, Activation};
use super::matmul::{matmul, MatRef};
use super::param::Param;

/// A dense layer `y = x·W + b` on row-major batches.
///
/// # Shapes
/// - `weight`: `[in_dim, out_dim]` row-major (so row `i` holds the weights leaving input `i`);
/// - `bias`: `[out_dim]`;
/// - inputs `x`: `[n, in_dim]`, outputs `y`: `[n, out_dim]`, both row-major.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Linear {
    /// Input features.
    pub in_dim: usize,
    /// Output features.
    pub out_dim: usize,
    /// `[in_dim, out_dim]` row-major.
    pub weight: Param,
    /// `[out_dim]`.
    pub bias: Param,
}

impl Linear {
    /// PyTorch's default initialisation: `W` and `b` drawn from `U(−1/√in_dim, 1/√in_dim)`.
    pub fn new(in_dim: usize, out_dim: usize, rng: &mut impl Rng) -> Self {
        assert!(in_dim > 0 && out_dim > 0, "Linear::new: dimensions must be positive");
        let bound = 1.0 / (in_dim as f32).sqrt();
        let mut draw = |len: usize| -> Vec<f32> { (0..len).map(|_| rng.gen_range(-bound..=bound)).collect() };
        let weight = Param::new(draw(in_dim * out_dim));
        let bias = Param::new(draw(out_dim));
        Self { in_dim, out_dim, weight, bias }
    }

    /// Number of trainable scalars (`in_dim·out_dim + out_dim`).
    pub fn num_parameters(&self) -> usize {
        self.weight.len() + self.bias.len()
    }

    /// `y = x·W + b` (overwrites `y`).
    ///
    /// # Shapes
    /// `x`: `[n, in_dim]`, `y`: `[n, out_dim]`.
    pub fn forward(&self, x: &[f32], n: usize, y: &mut [f32]) {
        self.forward_act(x, n, y, Activation::Identity);
    }

    /// `y = f(x·W + b)` with the bias add and activation fused into one pass after the GEMM.
    ///
    /// # Shapes
    /// `x`: `[n, in_dim]`, `y`: `[n, out_dim]`.
    pub fn forward_act(&self, x: &[f32], n: usize, y: &mut [f32], act: Activation) {
        self.forward_blocks(&[MatRef::new(x, n, self.in_dim)], y, act);
    }

    /// Backward of `y = x·W + b` given `dy = ∂L/∂y`: **accumulates** `∂L/∂W` into
    /// `weight.grad` and `∂L/∂b` into `bias.grad`, and **overwrites** `dx = ∂L/∂x` if given.
    ///
    /// # Shapes
    /// `x`, `dx`: `[n, in_dim]`; `dy`: `[n, out_dim]`.
    pub fn backward(&mut self, x: &[f32], dy: &[f32], n: usize, dx: Option<&mut [f32]>) {
        let g = MatRef::new(dy, n, self.out_dim);
        add_column_sums(dy, &mut self.bias.grad);
        self.backward_blocks(&[MatRef::new(x, n, self.in_dim)], g, &mut [dx], false);
    }

    /// Forward for an input given as column blocks `[x₀, x₁, …]` (concatenated along features,
    /// first block first) without materialising the concatenation: `y = f(Σ xᵢ·Wᵢ + b)`, where
    /// `Wᵢ` are the matching consecutive row blocks of `W`.
    ///
    /// # Shapes
    /// Each block is `[n, wᵢ]` with `Σ wᵢ = in_dim`; `y`: `[n, out_dim]`.
    pub fn forward_blocks(&self, blocks: &[MatRef<'_>], y: &mut [f32], act: Activation) {
        self.check_blocks(blocks);
        let mut row = 0;
        for (i, x) in blocks.iter().enumerate() {
            let w = &self.weight.value[row * self.out_dim..(row + x.cols) * self.out_dim];
            matmul(*x, MatRef::new(w, x.cols, self.out_dim), y, i > 0);
            row += x.cols;
        }
        act.forward_bias(y, &self.bias.value);
    }

    /// Weight and input gradients for a block input (see [`Linear::forward_blocks`]), given
    /// `g = ∂L/∂(pre-activation)`. The bias gradient is left to the caller (it is fused with the
    /// activation backward). `dxs[i]`, when present, receives `g·Wᵢᵀ`, added to its contents
    /// when `accumulate_dx`, else overwriting them.
    ///
    /// # Shapes
    /// Blocks as in `forward_blocks`; `g`: `[n, out_dim]`; `dxs[i]`: `[n, wᵢ]`.
    pub fn backward_blocks(
        &mut self,
        blocks: &[MatRef<'_>],
        g: MatRef<'_>,
        dxs: &mut [Option<&mut [f32]>],
        accumulate_dx: bool,
    ) {
        self.check_blocks(blocks);
        assert_eq!(dxs.len(), blocks.len(), "backward: one dx slot per input block");
        assert_eq!((g.rows, g.cols), (blocks[0].rows, self.out_dim), "backward: dy shape");
        let mut row = 0;
        for (x, dx) in blocks.iter().zip(dxs.iter_mut()) {
            let range = row * self.out_dim..(row + x.cols) * self.out_dim;
            // ∂L/∂Wᵢ += xᵢᵀ·g
            matmul(x.t(), g, &mut self.weight.grad[range.clone()], true);
            if let Some(dx) = dx {
                // ∂L/∂xᵢ = g·Wᵢᵀ
                let w = MatRef::new(&self.weight.value[range], x.cols, self.out_dim);
                matmul(g, w.t(), dx, accumulate_dx);
            }
            row += x.cols;
        }
    }

    fn check_blocks(&self, blocks: &[MatRef<'_>]) {
        assert!(!blocks.is_empty(), "Linear: no input");
        assert!(blocks.iter().all(|b| !b.transposed && b.rows == blocks[0].rows), "Linear: block rows differ");
        let width: usize = blocks.iter().map(|b| b.cols).sum();
        assert_eq!(width, self.in_dim, "Linear: input has {width} features, layer expects {}", self.in_dim);
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// Checks an analytic gradient against central differences of `loss` (f32 evaluation,
    /// f64 accumulation) for every coordinate of `x`.
    pub(crate) fn check_grad(what: &str, x: &mut [f32], analytic: &[f32], mut loss: impl FnMut(&[f32]) -> f64) {
        assert_eq!(x.len(), analytic.len());
        let h = 1e-2f32;
        for i in 0..x.len() {
            let x0 = x[i];
            x[i] = x0 + h;
            let lp = loss(x);
            x[i] = x0 - h;
            let lm = loss(x);
            x[i] = x0;
            let fd = (lp - lm) / (2.0 * h as f64);
            let an = analytic[i] as f64;
            assert!(
                (fd - an).abs() <= 2e-3 + 1e-2 * fd.abs().max(an.abs()),
                "{what}[{i}]: analytic {an} vs finite difference {fd}"
            );
        }
    }

    /// `L = Σ y ⊙ r` for fixed random `r`, so `∂L/∂y = r`.
    fn dot(y: &[f32], r: &[f32]) -> f64 {
        y.iter().zip(r).map(|(&a, &b)| a as f64 * b as f64).sum()
    }

    #[test]
    fn init_is_within_pytorch_bounds() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let l = Linear::new(16, 8, &mut rng);
        assert!(l.weight.value.iter().chain(&l.bias.value).all(|v| v.abs() <= 0.25));
        assert!(l.weight.value.iter().any(|v| v.abs() > 0.2), "should span the range");
        assert_eq!((l.weight.grad.len(), l.bias.grad.len()), (128, 8));
    }

    #[test]
    fn forward_matches_definition() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let (n, i, o) = (3, 5, 2);
        let l = Linear::new(i, o, &mut rng);
        let x: Vec<f32> = (0..n * i).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let mut y = vec![0.0; n * o];
        l.forward(&x, n, &mut y);
        for r in 0..n {
            for c in 0..o {
                let want = l.bias.value[c] + (0..i).map(|k| x[r * i + k] * l.weight.value[k * o + c]).sum::<f32>();
                assert!((y[r * o + c] - want).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (n, i, o) = (4, 7, 3);
        let mut layer = Linear::new(i, o, &mut rng);
        let x: Vec<f32> = (0..n * i).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let r: Vec<f32> = (0..n * o).map(|_| rng.gen_range(-1.0..1.0)).collect();
        // Pre-fill grads to check that backward accumulates rather than overwrites.
        layer.weight.grad.iter_mut().for_each(|g| *g = 1.0);
        layer.bias.grad.iter_mut().for_each(|g| *g = 1.0);
        let mut dx = vec![123.0; n * i];
        layer.backward(&x, &r, n, Some(&mut dx));
        let dw: Vec<f32> = layer.weight.grad.iter().map(|g| g - 1.0).collect();
        let db: Vec<f32> = layer.bias.grad.iter().map(|g| g - 1.0).collect();

        let eval = |l: &Linear, x: &[f32]| {
            let mut y = vec![0.0; n * o];
            l.forward(x, n, &mut y);
            dot(&y, &r)
        };
        check_grad("dx", &mut x.clone(), &dx, |xp| eval(&layer, xp));
        let mut w = layer.weight.value.clone();
        check_grad("dW", &mut w, &dw, |wp| {
            let mut l = layer.clone();
            l.weight.value.copy_from_slice(wp);
            eval(&l, &x)
        });
        let mut b = layer.bias.value.clone();
        check_grad("db", &mut b, &db, |bp| {
            let mut l = layer.clone();
            l.bias.value.copy_from_slice(bp);
            eval(&l, &x)
        });
    }
}
