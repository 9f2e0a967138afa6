//! Adam over the flattened parameter tensors, with one learning rate per tensor. dfdx's own
//! optimiser wants a `TensorCollection` model and one learning rate; TensoRF trains the grids
//! 20× faster than the networks, and this is a dozen lines.

/// First- and second-moment estimates of every tensor.
#[derive(Debug, Clone)]
pub struct Adam {
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
    steps: i32,
}

const BETA1: f32 = 0.9;
/// TensoRF's `betas = (0.9, 0.99)`.
const BETA2: f32 = 0.99;
const EPS: f32 = 1e-8;

impl Adam {
    /// Zero moments for tensors of these sizes.
    pub fn new(sizes: impl IntoIterator<Item = usize>) -> Self {
        let (m, v): (Vec<_>, Vec<_>) = sizes.into_iter().map(|n| (vec![0.0; n], vec![0.0; n])).unzip();
        Adam { m, v, steps: 0 }
    }

    /// Starts a step (advances the bias correction).
    pub fn begin_step(&mut self) {
        self.steps = self.steps.saturating_add(1);
    }

    /// Updates tensor `k` in place from its gradient with learning rate `lr`.
    pub fn update(&mut self, k: usize, values: &mut [f32], grads: &[f32], lr: f32) {
        let c1 = 1.0 - BETA1.powi(self.steps);
        let c2 = 1.0 - BETA2.powi(self.steps);
        let (m, v) = (&mut self.m[k], &mut self.v[k]);
        for i in 0..values.len() {
            let g = grads[i];
            m[i] = BETA1 * m[i] + (1.0 - BETA1) * g;
            v[i] = BETA2 * v[i] + (1.0 - BETA2) * g * g;
            values[i] -= lr * (m[i] / c1) / ((v[i] / c2).sqrt() + EPS);
        }
    }
}
