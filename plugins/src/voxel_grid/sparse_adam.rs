//! Adam over a large parameter array where each step touches few entries: only the touched
//! vertices are updated ("lazy" moments), which keeps a step proportional to the rays traced
//! rather than to the grid size.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Vertices per parallel task.
const TASK_VERTICES: usize = 1 << 14;

/// Lazy Adam state for a grid with `channels` values per vertex.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SparseAdam {
    /// First moments.
    m: Vec<f32>,
    /// Second moments.
    v: Vec<f32>,
    /// Steps applied so far (for bias correction).
    step: u32,
    beta1: f32,
    beta2: f32,
}

impl SparseAdam {
    /// Zero state for `len` parameters.
    pub fn new(len: usize, beta1: f32, beta2: f32) -> Self {
        SparseAdam { m: vec![0.0; len], v: vec![0.0; len], step: 0, beta1, beta2 }
    }

    /// Updates the parameters of the vertices flagged in `touched` (`channels` values each)
    /// with per-channel learning rates `lr[channel]`, then zeroes their gradients and flags.
    pub fn step(&mut self, params: &mut [f32], grads: &mut [f32], touched: &mut [bool], channels: usize, lr: &[f32]) {
        self.step += 1;
        let bc1 = 1.0 - self.beta1.powi(self.step as i32);
        let bc2 = 1.0 - self.beta2.powi(self.step as i32);
        let (b1, b2) = (self.beta1, self.beta2);
        let span = TASK_VERTICES * channels;
        // Parallel over vertex ranges: every task owns disjoint slices of all five arrays.
        params
            .par_chunks_mut(span)
            .zip(grads.par_chunks_mut(span))
            .zip(self.m.par_chunks_mut(span).zip(self.v.par_chunks_mut(span)))
            .zip(touched.par_chunks_mut(TASK_VERTICES))
            .for_each(|(((p, g), (m, v)), flags)| {
                for (vertex, flag) in flags.iter_mut().enumerate() {
                    if !*flag {
                        continue;
                    }
                    *flag = false;
                    for c in 0..channels {
                        let i = vertex * channels + c;
                        let gi = g[i];
                        g[i] = 0.0;
                        let mi = b1 * m[i] + (1.0 - b1) * gi;
                        let vi = b2 * v[i] + (1.0 - b2) * gi * gi;
                        m[i] = mi;
                        v[i] = vi;
                        p[i] -= lr[c] * (mi / bc1) / ((vi / bc2).sqrt() + 1e-15);
                    }
                }
            });
    }
}
