//! Multi-layer perceptron with an optional input skip connection.

use rand::Rng;
use serde::{Deserialize, Serialize};

use super::activation::{add_column_sums, Activation};
use super::linear::Linear;
use super::matmul::MatRef;
use super::param::Param;

/// Rows per block in [`Mlp::infer`]: bounds its scratch memory to two
/// `INFER_CHUNK × max_width` buffers while keeping the GEMMs large enough to run at full speed.
const INFER_CHUNK: usize = 4096;

/// A stack of [`Linear`] layers with `hidden` applied after every layer but the last and
/// `output` after the last.
///
/// With a skip connection at layer `s` (NeRF's trunk), layer `s` receives the concatenation
/// `[input, h_{s−1}]` (input first), so its `in_dim` is `dims[0] + dims[s]`. The concatenation
/// is never materialised: the product is split over the two row blocks of the weight.
///
/// # Shapes
/// Inputs `[n, dims[0]]`, outputs `[n, dims[last]]`, all row-major.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Mlp {
    /// The layers, input to output.
    pub layers: Vec<Linear>,
    /// Activation after each hidden layer.
    pub hidden: Activation,
    /// Activation after the last layer.
    pub output: Activation,
    /// Index of the layer that also receives the network input (never 0).
    #[serde(default)]
    pub skip_at: Option<usize>,
}

/// What [`Mlp::backward`] needs from a forward pass.
#[derive(Clone, Debug, Default)]
pub struct MlpTape {
    n: usize,
    /// `[n, in_dim]`: the network input.
    input: Vec<f32>,
    /// `hidden[i]`: `[n, layers[i].out_dim]`, activated output of hidden layer `i`.
    hidden: Vec<Vec<f32>>,
    /// `[n, out_dim]`: the activated output; empty when the output activation is the identity
    /// (its derivative does not need it).
    output: Vec<f32>,
}

impl MlpTape {
    /// Batch size of the recorded forward pass.
    pub fn batch_size(&self) -> usize {
        self.n
    }

    /// Batch size, input, hidden activations and output, for [`super::CompactTape`].
    pub(super) fn parts(&self) -> (usize, &[f32], &[Vec<f32>], &[f32]) {
        (self.n, &self.input, &self.hidden, &self.output)
    }

    /// [`MlpTape::parts`], to overwrite.
    pub(super) fn parts_mut(&mut self) -> (&mut usize, &mut Vec<f32>, &mut Vec<Vec<f32>>, &mut Vec<f32>) {
        (&mut self.n, &mut self.input, &mut self.hidden, &mut self.output)
    }
}

impl Mlp {
    /// A plain MLP with layer widths `dims` (`dims[0]` inputs, `dims[last]` outputs).
    pub fn new(dims: &[usize], hidden: Activation, output: Activation, rng: &mut impl Rng) -> Self {
        Self::with_skip(dims, None, hidden, output, rng)
    }

    /// Like [`Mlp::new`], but layer `skip_at` (if any, `1 ≤ skip_at < dims.len() − 1`) receives
    /// `[input, h]` and so has `dims[0] + dims[skip_at]` inputs.
    pub fn with_skip(
        dims: &[usize],
        skip_at: Option<usize>,
        hidden: Activation,
        output: Activation,
        rng: &mut impl Rng,
    ) -> Self {
        assert!(dims.len() >= 2, "Mlp: need at least input and output widths");
        let num_layers = dims.len() - 1;
        if let Some(s) = skip_at {
            assert!((1..num_layers).contains(&s), "Mlp: skip_at {s} must be in 1..{num_layers}");
        }
        let layers = (0..num_layers)
            .map(|i| {
                let extra = if skip_at == Some(i) { dims[0] } else { 0 };
                Linear::new(dims[i] + extra, dims[i + 1], rng)
            })
            .collect();
        Self { layers, hidden, output, skip_at }
    }

    /// Input width.
    pub fn in_dim(&self) -> usize {
        self.layers[0].in_dim
    }

    /// Output width.
    pub fn out_dim(&self) -> usize {
        self.layers.last().expect("Mlp has layers").out_dim
    }

    /// Why this network cannot run, if it cannot: no layers, a weight or bias whose length
    /// does not match its layer's widths, or a layer whose input is not the previous output
    /// (a deserialised network is input like any other).
    pub fn shape_error(&self) -> Option<String> {
        if self.layers.is_empty() {
            return Some("the network has no layers".into());
        }
        for (i, l) in self.layers.iter().enumerate() {
            if l.in_dim == 0 || l.out_dim == 0 {
                return Some(format!("layer {i} has a zero width ({} -> {})", l.in_dim, l.out_dim));
            }
            if l.in_dim.checked_mul(l.out_dim) != Some(l.weight.len()) || l.bias.len() != l.out_dim {
                return Some(format!(
                    "layer {i} maps {} to {} but holds {} weights and {} biases",
                    l.in_dim,
                    l.out_dim,
                    l.weight.len(),
                    l.bias.len()
                ));
            }
            if i > 0 && self.layers[i - 1].out_dim != l.in_dim {
                return Some(format!(
                    "layer {i} takes {} inputs but layer {} gives {}",
                    l.in_dim,
                    i - 1,
                    self.layers[i - 1].out_dim
                ));
            }
        }
        None
    }

    /// Number of trainable scalars.
    pub fn num_parameters(&self) -> usize {
        self.layers.iter().map(Linear::num_parameters).sum()
    }

    /// All parameters in a fixed order (per layer: weight, bias), e.g. for [`super::Adam`].
    pub fn params_mut(&mut self) -> Vec<&mut Param> {
        self.layers.iter_mut().flat_map(|l| [&mut l.weight, &mut l.bias]).collect()
    }

    /// Zeros every gradient.
    pub fn zero_grad(&mut self) {
        self.params_mut().into_iter().for_each(Param::zero_grad);
    }

    fn act(&self, layer: usize) -> Activation {
        if layer + 1 == self.layers.len() {
            self.output
        } else {
            self.hidden
        }
    }

    /// The column blocks forming layer `l`'s input: `x` for layer 0, `[x, prev]` at the skip,
    /// otherwise `prev` (the previous layer's activated output).
    fn blocks<'a>(&self, l: usize, x: &'a [f32], prev: &'a [f32], n: usize) -> Vec<MatRef<'a>> {
        let in0 = self.in_dim();
        if l == 0 {
            vec![MatRef::new(x, n, in0)]
        } else if self.skip_at == Some(l) {
            vec![MatRef::new(x, n, in0), MatRef::new(prev, n, self.layers[l].in_dim - in0)]
        } else {
            vec![MatRef::new(prev, n, self.layers[l].in_dim)]
        }
    }

    /// Forward pass that records what [`Mlp::backward`] needs.
    ///
    /// # Shapes
    /// `x`: `[n, in_dim]`; returns `[n, out_dim]`.
    pub fn forward(&self, x: &[f32], n: usize) -> (Vec<f32>, MlpTape) {
        let mut tape = MlpTape::default();
        let out = self.forward_into(x, n, &mut tape);
        (out, tape)
    }

    /// [`Mlp::forward`] into an existing tape, whose buffers are reused: a caller that tapes
    /// many same-sized batches step after step allocates (and page-faults) them only once.
    ///
    /// # Shapes
    /// `x`: `[n, in_dim]`; returns `[n, out_dim]`.
    pub fn forward_into(&self, x: &[f32], n: usize, tape: &mut MlpTape) -> Vec<f32> {
        self.record(x, n, tape, true)
    }

    /// [`Mlp::forward_into`] without a copy of the input in the tape, for callers that keep
    /// `x` until the backward pass anyway: pass it again to [`Mlp::backward_with_input`].
    pub fn forward_into_without_input(&self, x: &[f32], n: usize, tape: &mut MlpTape) -> Vec<f32> {
        self.record(x, n, tape, false)
    }

    fn record(&self, x: &[f32], n: usize, tape: &mut MlpTape, copy_input: bool) -> Vec<f32> {
        assert_eq!(x.len(), n * self.in_dim(), "Mlp::forward: input is not [n, in_dim]");
        let num_layers = self.layers.len();
        tape.n = n;
        tape.input.clear();
        if copy_input {
            tape.input.extend_from_slice(x);
        }
        tape.hidden.resize_with(num_layers - 1, Vec::new);
        let mut out = Vec::new();
        for (l, layer) in self.layers.iter().enumerate() {
            let mut y = if l + 1 < num_layers {
                let mut y = std::mem::take(&mut tape.hidden[l]);
                // Every element is overwritten below: only a change of size needs a resize.
                y.resize(n * layer.out_dim, 0.0);
                y
            } else {
                vec![0.0f32; n * layer.out_dim]
            };
            {
                let prev: &[f32] = if l == 0 { &[] } else { &tape.hidden[l - 1] };
                layer.forward_blocks(&self.blocks(l, x, prev, n), &mut y, self.act(l));
            }
            if l + 1 < num_layers {
                tape.hidden[l] = y;
            } else {
                out = y;
            }
        }
        tape.output.clear();
        if self.output != Activation::Identity {
            tape.output.extend_from_slice(&out);
        }
        out
    }

    /// Forward pass without a tape, processed in blocks of rows to bound memory.
    ///
    /// # Shapes
    /// `x`: `[n, in_dim]`; returns `[n, out_dim]`.
    pub fn infer(&self, x: &[f32], n: usize) -> Vec<f32> {
        let (in_dim, out_dim) = (self.in_dim(), self.out_dim());
        assert_eq!(x.len(), n * in_dim, "Mlp::infer: input is not [n, in_dim]");
        let num_layers = self.layers.len();
        let max_hidden = self.layers[..num_layers - 1].iter().map(|l| l.out_dim).max().unwrap_or(0);
        let rows = n.min(INFER_CHUNK);
        let mut a = vec![0.0f32; rows * max_hidden];
        let mut b = vec![0.0f32; rows * max_hidden];
        let mut out = vec![0.0f32; n * out_dim];
        for (xc, oc) in x.chunks(INFER_CHUNK * in_dim).zip(out.chunks_mut(INFER_CHUNK * out_dim)) {
            let m = xc.len() / in_dim;
            let mut prev_len = 0;
            for (l, layer) in self.layers.iter().enumerate() {
                let blocks = self.blocks(l, xc, &a[..prev_len], m);
                if l + 1 == num_layers {
                    layer.forward_blocks(&blocks, oc, self.act(l));
                } else {
                    let len = m * layer.out_dim;
                    layer.forward_blocks(&blocks, &mut b[..len], self.act(l));
                    prev_len = len;
                    std::mem::swap(&mut a, &mut b);
                }
            }
        }
        out
    }

    /// Backward pass for `dy = ∂L/∂output`: **accumulates** parameter gradients and, if
    /// `want_dx`, returns `∂L/∂input` (including the skip connection's contribution).
    ///
    /// # Shapes
    /// `dy`: `[n, out_dim]` with `n = tape.batch_size()`; returns `[n, in_dim]`.
    pub fn backward(&mut self, tape: &MlpTape, dy: &[f32], want_dx: bool) -> Option<Vec<f32>> {
        self.backward_with_input(tape, &tape.input, dy, want_dx)
    }

    /// [`Mlp::backward`] for a tape recorded by [`Mlp::forward_into_without_input`], with the
    /// same input it was given.
    pub fn backward_with_input(
        &mut self,
        tape: &MlpTape,
        input: &[f32],
        dy: &[f32],
        want_dx: bool,
    ) -> Option<Vec<f32>> {
        let n = tape.n;
        let (in_dim, out_dim) = (self.in_dim(), self.out_dim());
        let num_layers = self.layers.len();
        assert_eq!(dy.len(), n * out_dim, "Mlp::backward: dy is not [n, out_dim]");
        assert_eq!(input.len(), n * in_dim, "Mlp::backward: input (or tape) from another network or batch");
        assert_eq!(tape.hidden.len(), num_layers - 1, "Mlp::backward: tape from another network");
        for (h, l) in tape.hidden.iter().zip(&self.layers) {
            assert_eq!(h.len(), n * l.out_dim, "Mlp::backward: tape from another network");
        }
        let (hidden_act, skip_at) = (self.hidden, self.skip_at);
        let mut dx_input = want_dx.then(|| vec![0.0f32; n * in_dim]);

        // Two ping-pong buffers for ∂L/∂(pre-activation), sized for the widest hidden layer.
        let max_hidden = self.layers[..num_layers - 1].iter().map(|l| l.out_dim).max().unwrap_or(0);
        let mut cur = vec![0.0f32; n * max_hidden.max(out_dim)];
        let mut nxt = vec![0.0f32; n * max_hidden];

        // Gradient w.r.t. the last pre-activation; for the identity it is `dy` itself (no copy).
        let last = num_layers - 1;
        let out_is_identity = self.output == Activation::Identity;
        if out_is_identity {
            add_column_sums(dy, &mut self.layers[last].bias.grad);
        } else {
            let g = &mut cur[..n * out_dim];
            g.copy_from_slice(dy);
            self.output.backward_bias(&tape.output, g, &mut self.layers[last].bias.grad);
        }

        for l in (0..num_layers).rev() {
            let width = self.layers[l].out_dim;
            let g_data: &[f32] = if l == last && out_is_identity { dy } else { &cur[..n * width] };
            let g = MatRef::new(g_data, n, width);
            let prev: &[f32] = if l == 0 { &[] } else { &tape.hidden[l - 1] };
            let blocks = self.blocks(l, input, prev, n);
            let dprev = &mut nxt[..prev.len()];
            let layer = &mut self.layers[l];
            if l == 0 {
                // With a skip, the skip layer already wrote its share of ∂L/∂input.
                layer.backward_blocks(&blocks, g, &mut [dx_input.as_deref_mut()], skip_at.is_some());
            } else if skip_at == Some(l) {
                layer.backward_blocks(&blocks, g, &mut [dx_input.as_deref_mut(), Some(dprev)], false);
            } else {
                layer.backward_blocks(&blocks, g, &mut [Some(dprev)], false);
            }
            if l > 0 {
                let dprev = &mut nxt[..prev.len()];
                hidden_act.backward_bias(prev, dprev, &mut self.layers[l - 1].bias.grad);
                std::mem::swap(&mut cur, &mut nxt);
            }
        }
        dx_input
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::linear::tests::check_grad;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn dot(y: &[f32], r: &[f32]) -> f64 {
        y.iter().zip(r).map(|(&a, &b)| a as f64 * b as f64).sum()
    }

    /// A tape without its input, given the input again, gives the same outputs and gradients
    /// bit for bit; given another input, other gradients.
    #[test]
    fn tape_without_input_matches_the_full_tape() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mlp = Mlp::new(&[6, 8, 3], Activation::Relu, Activation::Identity, &mut rng);
        let n = 40;
        let x: Vec<f32> = (0..n * 6).map(|i| ((i * 31 % 17) as f32 / 17.0) - 0.4).collect();
        let dy: Vec<f32> = (0..n * 3).map(|i| ((i * 7 % 11) as f32 / 11.0) - 0.5).collect();
        let grads = |m: &mut Mlp| m.params_mut().iter().flat_map(|p| p.grad.clone()).collect::<Vec<f32>>();
        let (mut full, mut lean, mut other) = (mlp.clone(), mlp.clone(), mlp.clone());
        let (mut t1, mut t2) = (MlpTape::default(), MlpTape::default());
        let y1 = full.forward_into(&x, n, &mut t1);
        let y2 = lean.forward_into_without_input(&x, n, &mut t2);
        assert_eq!(y1, y2);
        let dx1 = full.backward(&t1, &dy, true);
        let dx2 = lean.backward_with_input(&t2, &x, &dy, true);
        assert_eq!((dx1, grads(&mut full)), (dx2, grads(&mut lean)));
        let moved: Vec<f32> = x.iter().map(|v| v + 0.5).collect();
        other.backward_with_input(&t2, &moved, &dy, false);
        assert_ne!(grads(&mut other), grads(&mut full), "the given input is the one used");
    }

    /// Gradients of `L = Σ y ⊙ r` w.r.t. every weight, bias and input against central
    /// differences, for networks with and without a skip connection.
    #[test]
    fn backward_matches_finite_differences() {
        let configs = [
            (vec![3, 5, 4, 2], Some(2), Activation::Sigmoid, Activation::Softplus),
            (vec![4, 6, 5, 3], Some(1), Activation::Softplus, Activation::Identity),
            (vec![2, 4, 3], None, Activation::Sigmoid, Activation::Sigmoid),
        ];
        for (ci, (dims, skip, hidden, output)) in configs.into_iter().enumerate() {
            let mut rng = ChaCha8Rng::seed_from_u64(10 + ci as u64);
            let mut mlp = Mlp::with_skip(&dims, skip, hidden, output, &mut rng);
            let n = 4;
            let x: Vec<f32> = (0..n * dims[0]).map(|_| rng.gen_range(-1.0..1.0)).collect();
            let r: Vec<f32> = (0..n * mlp.out_dim()).map(|_| rng.gen_range(-1.0..1.0)).collect();
            let (_, tape) = mlp.forward(&x, n);
            let dx = mlp.backward(&tape, &r, true).expect("asked for dx");
            let base = mlp.clone();
            let eval = |m: &Mlp, x: &[f32]| dot(&m.forward(x, n).0, &r);

            check_grad(&format!("config {ci} dx"), &mut x.clone(), &dx, |xp| eval(&base, xp));
            for l in 0..base.layers.len() {
                let mut w = base.layers[l].weight.value.clone();
                check_grad(&format!("config {ci} layer {l} dW"), &mut w, &base.layers[l].weight.grad, |wp| {
                    let mut m = base.clone();
                    m.layers[l].weight.value.copy_from_slice(wp);
                    eval(&m, &x)
                });
                let mut b = base.layers[l].bias.value.clone();
                check_grad(&format!("config {ci} layer {l} db"), &mut b, &base.layers[l].bias.grad, |bp| {
                    let mut m = base.clone();
                    m.layers[l].bias.value.copy_from_slice(bp);
                    eval(&m, &x)
                });
            }
        }
    }

    #[test]
    fn skip_layer_sees_input_first() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mlp = Mlp::with_skip(&[3, 8, 8, 8, 1], Some(2), Activation::Relu, Activation::Identity, &mut rng);
        assert_eq!(mlp.layers.iter().map(|l| l.in_dim).collect::<Vec<_>>(), vec![3, 8, 11, 8]);
        assert_eq!(mlp.in_dim(), 3);
        // Zeroing the rows of the skip layer's weight that read h (rows 3..) must leave an
        // output that depends on x only through those first 3 rows.
        let mut m = mlp.clone();
        m.layers[2].weight.value[3 * 8..].iter_mut().for_each(|w| *w = 0.0);
        let x = vec![0.5, -1.0, 2.0];
        let mut manual = vec![0.0; 8];
        m.layers[2].forward_act(&[x.clone(), vec![0.0; 8]].concat(), 1, &mut manual, Activation::Relu);
        let mut want = vec![0.0; 1];
        m.layers[3].forward(&manual, 1, &mut want);
        let got = m.infer(&x, 1);
        assert!((got[0] - want[0]).abs() < 1e-5, "{got:?} vs {want:?}");
    }

    #[test]
    fn infer_matches_forward_across_chunks() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mlp = Mlp::with_skip(&[5, 16, 16, 3], Some(2), Activation::Relu, Activation::Sigmoid, &mut rng);
        let n = INFER_CHUNK + 77;
        let x: Vec<f32> = (0..n * 5).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let (y, tape) = mlp.forward(&x, n);
        assert_eq!(tape.batch_size(), n);
        let z = mlp.infer(&x, n);
        assert_eq!(y.len(), z.len());
        for (a, b) in y.iter().zip(&z) {
            assert!((a - b).abs() <= 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn backward_accumulates_and_zero_grad_clears() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut mlp = Mlp::new(&[3, 4, 2], Activation::Relu, Activation::Identity, &mut rng);
        let x: Vec<f32> = (0..6).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let (_, tape) = mlp.forward(&x, 2);
        let dy = vec![1.0, -1.0, 0.5, 2.0];
        assert!(mlp.backward(&tape, &dy, false).is_none());
        let once = mlp.layers[0].weight.grad.clone();
        mlp.backward(&tape, &dy, false);
        for (a, b) in mlp.layers[0].weight.grad.iter().zip(&once) {
            assert!((a - 2.0 * b).abs() < 1e-6);
        }
        assert!(once.iter().any(|&g| g != 0.0));
        mlp.zero_grad();
        assert!(mlp.params_mut().iter().all(|p| p.grad.iter().all(|&g| g == 0.0)));
        assert_eq!(mlp.num_parameters(), 3 * 4 + 4 + 4 * 2 + 2);
    }

    #[test]
    fn serde_round_trip() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut mlp = Mlp::with_skip(&[4, 8, 8, 2], Some(2), Activation::Softplus, Activation::Sigmoid, &mut rng);
        mlp.layers[1].weight.grad[0] = 3.0; // not stored
        let json = serde_json::to_string(&mlp).unwrap();
        let back: Mlp = serde_json::from_str(&json).unwrap();
        assert_eq!(back.skip_at, Some(2));
        assert_eq!((back.hidden, back.output), (Activation::Softplus, Activation::Sigmoid));
        for (a, b) in back.layers.iter().zip(&mlp.layers) {
            assert_eq!(a.weight.value, b.weight.value);
            assert_eq!(a.bias.value, b.bias.value);
            assert!(a.weight.grad.len() == a.weight.value.len() && a.weight.grad.iter().all(|&g| g == 0.0));
        }
        let x: Vec<f32> = (0..12).map(|_| rng.gen_range(-1.0..1.0)).collect();
        assert_eq!(back.infer(&x, 3), mlp.infer(&x, 3));
    }
}
