//! The segmentation head over a whole stage-2 batch of ray samples, in chunks.
//!
//! A step has about a million surviving samples. The forward pass runs the head chunk by
//! chunk (the field's segmentation input of a chunk stays in cache) and keeps each chunk's
//! tape for the backward pass in a [`HeadTapes`] that lives across steps, so its buffers are
//! allocated and page-faulted once, not every step (fresh gigabytes per step made the
//! backward pass slow and erratic). When a batch's tapes would exceed the memory budget, the
//! backward pass instead recomputes each chunk's input and forward pass: one extra head
//! forward in exchange for buffers that stay in cache.
//!
//! The segmentation input comes from the render when it kept it ([`HeadSamples::seg_input`]:
//! for NeRF it is the trunk's output, which the render computes anyway), else from the field,
//! chunk by chunk.

use crate::camera::Vec3;
use crate::nn::{CompactTape, MlpTape};
use crate::plugin::RadianceField;
use crate::segment::head::SegHead;

/// Samples per chunk: large enough for full-speed GEMMs, small enough to stay in cache.
const CHUNK: usize = 8192;

/// The per-chunk tapes of the last forward pass, reused from step to step, with the hidden
/// activations in bfloat16 ([`CompactTape`]: half the memory, gradients within its bound).
/// Their budget is the head's share of
/// [`MemoryBudget`](crate::render::memory_budget::MemoryBudget): a million samples of a 43-wide
/// input and a 128-wide hidden layer take 0.43 GB, NeRF's 319-wide input 1.5 GB; when the
/// render kept the input, the tapes hold only the hidden layer (0.26 GB).
#[derive(Debug)]
pub struct HeadTapes {
    tapes: Vec<CompactTape>,
    /// The full-precision tape a chunk's forward pass records into before it is stored.
    scratch: MlpTape,
    /// Chunks of the last forward pass that have a tape (0 when it was over budget).
    used: usize,
    budget: usize,
}

impl HeadTapes {
    /// Tapes kept only while a batch's tapes take at most `budget` bytes.
    pub fn with_budget(budget: usize) -> Self {
        HeadTapes { tapes: Vec::new(), scratch: MlpTape::default(), used: 0, budget }
    }

    /// Whether the tapes of `samples` fit the budget; with `input_kept`, the tapes hold no copy
    /// of the input (the caller keeps it until the backward pass).
    fn fits(&self, field: &dyn RadianceField, head: &SegHead, samples: usize, input_kept: bool) -> bool {
        let layers = &head.mlp.layers;
        let hidden: usize = layers[..layers.len() - 1].iter().map(|l| l.out_dim).sum();
        let input = if input_kept { 0 } else { field.seg_input_dim() };
        samples.saturating_mul(CompactTape::bytes_per_sample(hidden, input)) <= self.budget
    }
}

/// The samples the head runs on.
#[derive(Debug, Clone, Copy)]
pub struct HeadSamples<'a> {
    /// Sample positions.
    pub positions: &'a [Vec3],
    /// The field's segmentation input at them, `[n, seg_input_dim]`, when the render kept it
    /// ([`crate::render::renderer::Rendered::seg_input`]); empty to compute it chunk by chunk.
    pub seg_input: &'a [f32],
}

impl<'a> HeadSamples<'a> {
    /// Samples whose segmentation input is computed here.
    pub fn at(positions: &'a [Vec3]) -> Self {
        HeadSamples { positions, seg_input: &[] }
    }

    /// Chunk `i`'s segmentation input: the kept one, or computed into `buffer`.
    fn chunk_input<'b>(&'b self, field: &dyn RadianceField, i: usize, buffer: &'b mut Vec<f32>) -> &'b [f32] {
        let dim = field.seg_input_dim();
        let chunk = &self.positions[i * CHUNK..((i + 1) * CHUNK).min(self.positions.len())];
        if self.input_kept() {
            return &self.seg_input[i * CHUNK * dim..][..chunk.len() * dim];
        }
        buffer.resize(chunk.len() * dim, 0.0);
        field.seg_input(chunk, buffer);
        buffer
    }

    /// Whether the render kept the input (else it is computed chunk by chunk).
    fn input_kept(&self) -> bool {
        !self.seg_input.is_empty()
    }

    fn check(&self, field: &dyn RadianceField) {
        assert!(
            self.seg_input.is_empty() || self.seg_input.len() == self.positions.len() * field.seg_input_dim(),
            "head_pass: the kept segmentation input is not [n, seg_input_dim]"
        );
    }
}

/// Gathers `run(chunk index, input, rows)`, each chunk's logits, into `[n, outputs]`.
fn over_chunks(
    field: &dyn RadianceField,
    head: &SegHead,
    samples: HeadSamples,
    mut run: impl FnMut(usize, &[f32], usize) -> Vec<f32>,
) -> Vec<f32> {
    samples.check(field);
    let d = head.outputs();
    let n = samples.positions.len();
    let mut logits = vec![0.0f32; n * d];
    let mut buffer = Vec::new();
    for (i, out) in logits.chunks_mut(CHUNK * d).enumerate() {
        let x = samples.chunk_input(field, i, &mut buffer);
        out.copy_from_slice(&run(i, x, out.len() / d));
    }
    logits
}

/// Logits of every sample, `[n, outputs]`, without a tape.
pub fn sample_logits(field: &dyn RadianceField, head: &SegHead, positions: &[Vec3]) -> Vec<f32> {
    over_chunks(field, head, HeadSamples::at(positions), |_, x, n| head.infer(x, n))
}

/// Logits of every sample, `[n, outputs]`, keeping the chunks' tapes in `tapes` when they fit
/// its budget, for [`backward`].
pub fn forward(field: &dyn RadianceField, head: &SegHead, samples: HeadSamples, tapes: &mut HeadTapes) -> Vec<f32> {
    tapes.used = 0;
    let input_kept = samples.input_kept();
    if !tapes.fits(field, head, samples.positions.len(), input_kept) {
        return over_chunks(field, head, samples, |_, x, n| head.infer(x, n));
    }
    let (kept, scratch) = (&mut tapes.tapes, &mut tapes.scratch);
    let logits = over_chunks(field, head, samples, |i, x, n| {
        if i == kept.len() {
            kept.push(CompactTape::default());
        }
        let logits =
            if input_kept { head.forward_into_without_input(x, n, scratch) } else { head.forward_into(x, n, scratch) };
        kept[i].store(scratch);
        logits
    });
    tapes.used = samples.positions.len().div_ceil(CHUNK);
    logits
}

/// Accumulates the head's parameter gradients for `grad_logits = ∂L/∂(sample logits)`,
/// `[n, outputs]`, from the tapes of the [`forward`] pass over the same samples, or by
/// recomputing each chunk's forward pass where it kept none.
pub fn backward(
    field: &dyn RadianceField,
    head: &mut SegHead,
    samples: HeadSamples,
    grad_logits: &[f32],
    tapes: &HeadTapes,
) {
    samples.check(field);
    let d = head.outputs();
    let n = samples.positions.len();
    assert_eq!(grad_logits.len(), n * d, "head_pass::backward: gradient is not [n, outputs]");
    let taped = tapes.used > 0;
    assert!(!taped || tapes.used == n.div_ceil(CHUNK), "head_pass::backward: the tapes are from another batch");
    let (mut buffer, mut tape) = (Vec::new(), MlpTape::default());
    for (i, grad) in grad_logits.chunks(CHUNK * d).enumerate() {
        // Samples that no loss reaches (weight below every threshold) need no pass at all.
        if grad.iter().all(|&g| g == 0.0) {
            continue;
        }
        if taped {
            tapes.tapes[i].restore(&mut tape);
            if samples.input_kept() {
                let x = samples.chunk_input(field, i, &mut buffer);
                head.backward_with_input(&tape, x, grad);
            } else {
                head.backward(&tape, grad);
            }
        } else {
            let x = samples.chunk_input(field, i, &mut buffer);
            let (_, tape) = head.forward(x, grad.len() / d);
            head.backward(&tape, grad);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::HeadConfig;
    use crate::plugin::FieldTape;

    /// A field that only has a segmentation input (a few smooth functions of the position).
    struct Features;

    impl RadianceField for Features {
        fn density(&self, _: &[Vec3], d: &mut [f32]) {
            d.fill(0.0);
        }
        fn forward(&self, _: &[Vec3], _: &[Vec3], d: &mut [f32], _: &mut [[f32; 3]], _: bool) -> FieldTape {
            d.fill(0.0);
            None
        }
        fn backward(&mut self, _: &[Vec3], _: &[Vec3], _: FieldTape, _: &[f32], _: &[[f32; 3]]) {}
        fn step(&mut self, _: f32) {}
        fn seg_input_dim(&self) -> usize {
            5
        }
        fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
            for (p, row) in positions.iter().zip(out.chunks_exact_mut(5)) {
                row.copy_from_slice(&[p[0], p[1], p[2], (3.0 * p[0]).sin(), p[1] * p[2]]);
            }
        }
        fn save_state(&self) -> Vec<u8> {
            Vec::new()
        }
        fn load_state(&mut self, _: &[u8]) -> Result<(), crate::error::StateError> {
            Ok(())
        }
        fn num_parameters(&self) -> usize {
            0
        }
        fn parameters(&self) -> Vec<f32> {
            Vec::new()
        }
        fn set_parameters(&mut self, _: &[f32]) -> Result<(), crate::error::StateError> {
            Ok(())
        }
        fn gradients(&self) -> Vec<f32> {
            Vec::new()
        }
        fn gradients_finite(&self) -> bool {
            true
        }
        fn discard_gradients(&mut self) {}
    }

    /// Chunked passes equal one pass over the whole batch (forward values and gradients),
    /// with tapes kept and with tapes recomputed.
    #[test]
    fn chunked_passes_match_the_whole_batch() {
        let field = Features;
        let n = 2 * CHUNK + 123;
        let positions: Vec<Vec3> = (0..n)
            .map(|i| {
                let t = i as f32 / n as f32;
                [t - 0.5, (7.0 * t).sin() * 0.4, (3.0 * t).cos() * 0.4]
            })
            .collect();
        let config = HeadConfig { hidden: vec![16], outputs: 2 };
        let head = SegHead::new(&config, field.seg_input_dim(), 1e-3, 1);
        let mut whole = head.clone();

        let mut input = vec![0.0; n * field.seg_input_dim()];
        field.seg_input(&positions, &mut input);
        let (expected, tape) = whole.forward(&input, n);
        let close = |got: &[f32]| {
            for (a, b) in got.iter().zip(&expected) {
                assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{a} vs {b}");
            }
        };
        close(&sample_logits(&field, &head, &positions));

        let grad: Vec<f32> = (0..n * 2).map(|i| ((i * 37 % 101) as f32 / 101.0 - 0.5) * 1e-3).collect();
        whole.backward(&tape, &grad);
        // `Σ_s |h_sj| |g_sk|` for each output-layer weight `(j, k)`, `[16, 2]` row-major.
        const OUTPUT_WEIGHT: usize = 2;
        let mut hidden = vec![0.0f32; n * 16];
        head.mlp.layers[0].forward_act(&input, n, &mut hidden, crate::nn::Activation::Relu);
        let mut abs_hg = [0.0f32; 16 * 2];
        for (h, g) in hidden.chunks_exact(16).zip(grad.chunks_exact(2)) {
            for j in 0..16 {
                for k in 0..2 {
                    abs_hg[j * 2 + k] += h[j].abs() * g[k].abs();
                }
            }
        }
        let moved: Vec<Vec3> = positions.iter().map(|p| [p[0] + 1.0, p[1], p[2]]).collect();
        // Kept tapes (reused over two passes, the first on a larger batch) and recomputed ones,
        // each with the input computed here and with the input a render kept.
        for (budget, kept_input) in [(usize::MAX, false), (0, false), (usize::MAX, true), (0, true)] {
            let mut chunked = head.clone();
            let mut tapes = HeadTapes::with_budget(budget);
            let more: Vec<Vec3> = positions.iter().chain(&positions[..CHUNK]).copied().collect();
            forward(&field, &chunked, HeadSamples::at(&more), &mut tapes);
            // The kept input must be used as given: its positions are moved, so recomputing
            // from them would give other logits.
            let samples = if kept_input {
                HeadSamples { positions: &moved, seg_input: &input }
            } else {
                HeadSamples::at(&positions)
            };
            close(&forward(&field, &chunked, samples, &mut tapes));
            assert_eq!(tapes.used > 0, budget > 0);
            backward(&field, &mut chunked, samples, &grad, &tapes);
            // Kept tapes hold the hidden layer in bfloat16: the output layer's weight gradient
            // `Σ h g` may move by 2^-8 of `Σ |h| |g|` (the compact tape's bound); the rest is
            // exact up to summation order.
            let rounding = if budget > 0 { 2f32.powi(-8) } else { 0.0 };
            let (gw, gc) = (whole.mlp.params_mut(), chunked.mlp.params_mut());
            for (p, (pw, pc)) in gw.iter().zip(&gc).enumerate() {
                let scale = pw.grad.iter().fold(0.0f32, |m, g| m.max(g.abs())).max(1e-12);
                for (e, (a, b)) in pw.grad.iter().zip(&pc.grad).enumerate() {
                    let bound = if p == OUTPUT_WEIGHT { abs_hg[e] } else { 0.0 };
                    assert!(
                        (a - b).abs() <= 1e-4 * scale + rounding * bound,
                        "gradient {a} vs {b} (parameter {p}, budget {budget})"
                    );
                }
            }
        }
    }
}
