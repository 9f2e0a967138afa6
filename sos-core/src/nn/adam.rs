//! Adam optimiser (Kingma & Ba) with bias correction, as in PyTorch.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::param::Param;

/// Parameters with at least this many scalars are updated on the rayon pool.
const PAR_MIN_LEN: usize = 1 << 15;
const PAR_CHUNK_LEN: usize = 1 << 13;

/// Adam with bias-corrected moments:
/// `m ← β₁m + (1−β₁)g`, `v ← β₂v + (1−β₂)g²`,
/// `p ← p − lr·lr_factor·(m/(1−β₁ᵗ)) / (√(v/(1−β₂ᵗ)) + ε)`.
///
/// Moments are kept per parameter **by position** in the list given to [`Adam::step`], so always
/// pass the same parameters in the same order (e.g. from `Mlp::params_mut`). They are created on
/// the first step. The whole state serialises for checkpoints.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    /// Base learning rate.
    pub lr: f32,
    /// Decay of the first moment.
    pub beta1: f32,
    /// Decay of the second moment.
    pub beta2: f32,
    /// Added to the denominator for stability.
    pub eps: f32,
    /// Steps taken so far (`t` of the bias correction).
    pub t: u64,
    /// First moments, one vector per parameter.
    m: Vec<Vec<f32>>,
    /// Second moments, one vector per parameter.
    v: Vec<Vec<f32>>,
}

impl Adam {
    /// Adam with PyTorch's defaults `β₁ = 0.9`, `β₂ = 0.999`, `ε = 1e-8`.
    pub fn new(lr: f32) -> Self {
        Self::with_hyper(lr, 0.9, 0.999, 1e-8)
    }

    /// Adam with explicit hyper-parameters.
    pub fn with_hyper(lr: f32, beta1: f32, beta2: f32, eps: f32) -> Self {
        Self { lr, beta1, beta2, eps, t: 0, m: Vec::new(), v: Vec::new() }
    }

    /// Why this state cannot step parameters of the given lengths, if it cannot: decays
    /// outside `[0, 1)`, a learning rate or `eps` that is not a positive number, or moments
    /// kept for other parameters (a deserialised optimiser is input like any other).
    pub fn state_error(&self, param_lens: &[usize]) -> Option<String> {
        if !((0.0..1.0).contains(&self.beta1) && (0.0..1.0).contains(&self.beta2)) {
            return Some(format!("Adam decays {} and {} must be in [0, 1)", self.beta1, self.beta2));
        }
        if !(self.lr > 0.0 && self.lr.is_finite() && self.eps > 0.0 && self.eps.is_finite()) {
            return Some(format!("Adam's learning rate {} and eps {} must be positive numbers", self.lr, self.eps));
        }
        // `step` creates the moments on the first step only (`t == 0`).
        let fresh = self.m.is_empty() && self.v.is_empty() && self.t == 0;
        let matches = |moments: &[Vec<f32>]| {
            moments.len() == param_lens.len() && moments.iter().zip(param_lens).all(|(m, &n)| m.len() == n)
        };
        let consistent = matches(&self.m) && matches(&self.v);
        if !fresh && !consistent {
            return Some(format!("Adam holds moments for other parameters than the network's {}", param_lens.len()));
        }
        if self.m.iter().chain(&self.v).flatten().any(|x| !x.is_finite()) {
            return Some("Adam's moments hold a non-finite value".into());
        }
        None
    }

    /// One update of every parameter from its accumulated gradient, with learning rate
    /// `lr · lr_factor` (for schedules); the gradients are zeroed in the same pass.
    ///
    /// # Panics
    /// If the number or sizes of the parameters differ from earlier steps.
    pub fn step(&mut self, params: &mut [&mut Param], lr_factor: f32) {
        if self.m.is_empty() && self.t == 0 {
            self.m = params.iter().map(|p| vec![0.0; p.len()]).collect();
            self.v = self.m.clone();
        }
        assert_eq!(self.m.len(), params.len(), "Adam: parameter list changed between steps");
        self.t += 1;
        let t = self.t.min(i32::MAX as u64) as i32;
        // Bias corrections in f64: β₂ᵗ is close to 1 for many steps.
        let bc1 = 1.0 - (self.beta1 as f64).powi(t);
        let bc2 = 1.0 - (self.beta2 as f64).powi(t);
        let step_size = (self.lr as f64 * lr_factor as f64 / bc1) as f32;
        let inv_sqrt_bc2 = (1.0 / bc2.sqrt()) as f32;
        let (b1, b2, eps) = (self.beta1, self.beta2, self.eps);
        let update = move |p: &mut [f32], g: &mut [f32], m: &mut [f32], v: &mut [f32]| {
            for (((p, g), m), v) in p.iter_mut().zip(g.iter_mut()).zip(m.iter_mut()).zip(v.iter_mut()) {
                *m = b1 * *m + (1.0 - b1) * *g;
                *v = b2 * *v + (1.0 - b2) * *g * *g;
                *p -= step_size * *m / (v.sqrt() * inv_sqrt_bc2 + eps);
                *g = 0.0;
            }
        };
        for ((param, m), v) in params.iter_mut().zip(&mut self.m).zip(&mut self.v) {
            let len = param.value.len();
            assert!(
                m.len() == len && param.grad.len() == len,
                "Adam: parameter of {len} scalars (grad {}) does not match its state of {}",
                param.grad.len(),
                m.len()
            );
            let Param { value, grad } = &mut **param;
            if len >= PAR_MIN_LEN {
                value
                    .par_chunks_mut(PAR_CHUNK_LEN)
                    .zip(grad.par_chunks_mut(PAR_CHUNK_LEN))
                    .zip(m.par_chunks_mut(PAR_CHUNK_LEN))
                    .zip(v.par_chunks_mut(PAR_CHUNK_LEN))
                    .for_each(|(((p, g), m), v)| update(p, g, m, v));
            } else {
                update(value, grad, m, v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Minimises `Σ cᵢ(pᵢ − tᵢ)²` (badly scaled on purpose) over a small and a rayon-sized param.
    #[test]
    fn converges_on_a_quadratic() {
        let target: Vec<f32> = (0..40_000).map(|i| ((i % 17) as f32 - 8.0) * 0.25).collect();
        let scale: Vec<f32> = (0..40_000).map(|i| if i % 2 == 0 { 0.1 } else { 10.0 }).collect();
        let mut big = Param::new(vec![0.0; 40_000]);
        let mut small = Param::new(vec![5.0, -5.0, 0.5]);
        let mut adam = Adam::new(0.05);
        let loss = |big: &Param, small: &Param| -> f64 {
            let a: f64 =
                big.value.iter().zip(&target).zip(&scale).map(|((p, t), c)| (c * (p - t) * (p - t)) as f64).sum();
            a + small.value.iter().map(|p| (p - 1.0) as f64 * (p - 1.0) as f64).sum::<f64>()
        };
        let start = loss(&big, &small);
        for step in 0..3000 {
            for ((g, p), (t, c)) in big.grad.iter_mut().zip(&big.value).zip(target.iter().zip(&scale)) {
                *g += 2.0 * c * (p - t);
            }
            for (g, p) in small.grad.iter_mut().zip(&small.value) {
                *g += 2.0 * (p - 1.0);
            }
            // A decaying schedule through lr_factor, to settle at the minimum.
            let factor = if step < 1500 { 1.0 } else { 0.1 };
            adam.step(&mut [&mut big, &mut small], factor);
            assert!(big.grad.iter().chain(&small.grad).all(|&g| g == 0.0), "step must zero grads");
        }
        let end = loss(&big, &small);
        assert!(end < 1e-6 * start, "loss {start} -> {end}");
        assert!(small.value.iter().all(|p| (p - 1.0).abs() < 1e-3), "{:?}", small.value);
        assert_eq!(adam.t, 3000);
    }

    #[test]
    fn first_step_moves_by_lr() {
        // With bias correction the first step is lr·sign(g), whatever |g|.
        let mut p = Param::new(vec![0.0, 0.0]);
        p.grad = vec![1e-3, -50.0];
        let mut adam = Adam::new(0.1);
        adam.step(&mut [&mut p], 1.0);
        assert!((p.value[0] + 0.1).abs() < 1e-4 && (p.value[1] - 0.1).abs() < 1e-4, "{:?}", p.value);
    }

    #[test]
    fn serde_round_trip_keeps_state() {
        let mut p = Param::new(vec![1.0, 2.0]);
        let mut adam = Adam::new(0.01);
        p.grad = vec![0.5, -0.5];
        adam.step(&mut [&mut p], 1.0);
        let json = serde_json::to_string(&adam).unwrap();
        let mut back: Adam = serde_json::from_str(&json).unwrap();
        assert_eq!(back, adam);
        let mut q = p.clone();
        p.grad = vec![0.3, 0.1];
        q.grad = p.grad.clone();
        adam.step(&mut [&mut p], 1.0);
        back.step(&mut [&mut q], 1.0);
        assert_eq!(p.value, q.value);
    }
}
