//! Adam over a large parameter array where each step touches few entries: only the touched
//! vertices are updated ("lazy" moments), which keeps a step proportional to the rays traced
//! rather than to the grid size.

use serde::{Deserialize, Serialize};

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

    /// Updates the parameters of the `touched` vertices (`channels` each) with per-channel
    /// learning rates `lr[channel]`, then zeroes their gradients.
    pub fn step(&mut self, params: &mut [f32], grads: &mut [f32], touched: &[u32], channels: usize, lr: &[f32]) {
        self.step += 1;
        let bc1 = 1.0 - self.beta1.powi(self.step as i32);
        let bc2 = 1.0 - self.beta2.powi(self.step as i32);
        let (b1, b2) = (self.beta1, self.beta2);
        for &vtx in touched {
            let base = vtx as usize * channels;
            for c in 0..channels {
                let i = base + c;
                let g = grads[i];
                grads[i] = 0.0;
                let m = b1 * self.m[i] + (1.0 - b1) * g;
                let v = b2 * self.v[i] + (1.0 - b2) * g * g;
                self.m[i] = m;
                self.v[i] = v;
                params[i] -= lr[c] * (m / bc1) / ((v / bc2).sqrt() + 1e-15);
            }
        }
    }
}
