//! The segmentation head over a whole stage-2 batch of ray samples, in chunks.
//!
//! A step has about a million surviving samples. Taping the head over all of them at once
//! allocates and first-touches some 2 GB per step (the input copy, the 128-wide hidden layer and
//! the backward's two ping-pong buffers), which made the backward pass slow and erratic. Here
//! the forward pass keeps only the per-sample logits, and the backward pass recomputes each
//! chunk's segmentation input and taped forward before back-propagating it: one extra head
//! forward in exchange for buffers that stay in cache.

use crate::camera::Vec3;
use crate::plugin::RadianceField;
use crate::segment::head::SegHead;

/// Samples per chunk: large enough for full-speed GEMMs, small enough to stay in cache.
const CHUNK: usize = 8192;

/// Logits of every sample, `[n, outputs]`, without a tape.
pub fn sample_logits(field: &dyn RadianceField, head: &SegHead, positions: &[Vec3]) -> Vec<f32> {
    let (dim, d) = (field.seg_input_dim(), head.outputs());
    let mut logits = vec![0.0f32; positions.len() * d];
    let mut input = vec![0.0f32; positions.len().min(CHUNK) * dim];
    for (chunk, out) in positions.chunks(CHUNK).zip(logits.chunks_mut(CHUNK * d)) {
        let x = &mut input[..chunk.len() * dim];
        field.seg_input(chunk, x);
        out.copy_from_slice(&head.infer(x, chunk.len()));
    }
    logits
}

/// Accumulates the head's parameter gradients for `grad_logits = ∂L/∂(sample logits)`,
/// `[n, outputs]`, recomputing the forward pass chunk by chunk.
pub fn backward(field: &dyn RadianceField, head: &mut SegHead, positions: &[Vec3], grad_logits: &[f32]) {
    let (dim, d) = (field.seg_input_dim(), head.outputs());
    assert_eq!(grad_logits.len(), positions.len() * d, "head_pass::backward: gradient is not [n, outputs]");
    let mut input = vec![0.0f32; positions.len().min(CHUNK) * dim];
    for (chunk, grad) in positions.chunks(CHUNK).zip(grad_logits.chunks(CHUNK * d)) {
        // Samples that no loss reaches (weight below every threshold) need no pass at all.
        if grad.iter().all(|&g| g == 0.0) {
            continue;
        }
        let x = &mut input[..chunk.len() * dim];
        field.seg_input(chunk, x);
        let (_, tape) = head.forward(x, chunk.len());
        head.backward(&tape, grad);
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
        fn load_state(&mut self, _: &[u8]) -> Result<(), String> {
            Ok(())
        }
        fn num_parameters(&self) -> usize {
            0
        }
    }

    /// Chunked passes equal one pass over the whole batch (forward values and gradients).
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
        let mut chunked = SegHead::new(&config, field.seg_input_dim(), 1e-3, 1);
        let mut whole = chunked.clone();

        let mut input = vec![0.0; n * field.seg_input_dim()];
        field.seg_input(&positions, &mut input);
        let (expected, tape) = whole.forward(&input, n);
        let got = sample_logits(&field, &chunked, &positions);
        for (a, b) in got.iter().zip(&expected) {
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{a} vs {b}");
        }

        let grad: Vec<f32> = (0..n * 2).map(|i| ((i * 37 % 101) as f32 / 101.0 - 0.5) * 1e-3).collect();
        whole.backward(&tape, &grad);
        backward(&field, &mut chunked, &positions, &grad);
        let (gw, gc) = (whole.mlp.params_mut(), chunked.mlp.params_mut());
        for (pw, pc) in gw.iter().zip(&gc) {
            let scale = pw.grad.iter().fold(0.0f32, |m, g| m.max(g.abs())).max(1e-12);
            for (a, b) in pw.grad.iter().zip(&pc.grad) {
                assert!((a - b).abs() <= 1e-4 * scale, "gradient {a} vs {b}");
            }
        }
    }
}
