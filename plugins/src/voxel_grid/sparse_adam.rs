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

    /// The state as bytes (see [`sos_core::plugin::state`]): step and betas, then both moments.
    pub fn to_bytes(&self) -> Vec<u8> {
        let header =
            serde_json::json!({ "step": self.step, "beta1": self.beta1, "beta2": self.beta2, "len": self.m.len() });
        sos_core::plugin::state::write(&header, &[&self.m, &self.v])
    }

    /// Restores [`SparseAdam::to_bytes`]; the moments must have this state's length.
    pub fn load_bytes(&mut self, kind: &str, bytes: &[u8]) -> Result<(), sos_core::error::StateError> {
        use sos_core::error::StateError;
        let (header, body) = sos_core::plugin::state::read(kind, bytes)?;
        let malformed = |reason: &str| StateError::Malformed { kind: kind.into(), reason: reason.into() };
        let len = header["len"].as_u64().ok_or_else(|| malformed("optimizer state without a length"))? as usize;
        if len != self.m.len() {
            return Err(StateError::Mismatch {
                kind: kind.into(),
                reason: format!("optimizer state for {len} values, the grid has {}", self.m.len()),
            });
        }
        let step = header["step"].as_u64().ok_or_else(|| malformed("optimizer state without a step"))?;
        // A decay of 1 or more divides by zero in the bias correction: every value turns NaN.
        let beta = |k: &str| {
            let b = header[k].as_f64().ok_or_else(|| malformed("optimizer state without betas"))?;
            if (0.0..1.0).contains(&b) {
                Ok(b as f32)
            } else {
                Err(malformed("optimizer betas must be in [0, 1)"))
            }
        };
        let values = sos_core::plugin::state::values(kind, body, 2 * len)?;
        let (m, v) = values.split_at(len);
        self.m.copy_from_slice(m);
        self.v.copy_from_slice(v);
        self.step = u32::try_from(step).map_err(|_| malformed("optimizer step out of range"))?;
        (self.beta1, self.beta2) = (beta("beta1")?, beta("beta2")?);
        Ok(())
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
                    let r = vertex * channels..(vertex + 1) * channels;
                    // Whole-vertex slices zipped rather than indexed: no bounds check per
                    // channel, so the update is vectorised (the same IEEE operations, lane-wise).
                    let lanes = p[r.clone()]
                        .iter_mut()
                        .zip(&mut g[r.clone()])
                        .zip(m[r.clone()].iter_mut().zip(&mut v[r]))
                        .zip(lr);
                    for (((p, g), (m, v)), lr) in lanes {
                        let gi = *g;
                        *g = 0.0;
                        let mi = b1 * *m + (1.0 - b1) * gi;
                        let vi = b2 * *v + (1.0 - b2) * gi * gi;
                        *m = mi;
                        *v = vi;
                        *p -= lr * (mi / bc1) / ((vi / bc2).sqrt() + 1e-15);
                    }
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_round_trips_and_steps_on_identically() {
        let (channels, vertices) = (2, 5);
        let lr = [0.1f32, 0.01];
        let mut a = SparseAdam::new(channels * vertices, 0.9, 0.99);
        let mut params = vec![1.0f32; channels * vertices];
        let mut grads: Vec<f32> = (0..channels * vertices).map(|i| i as f32 - 4.0).collect();
        let mut touched = vec![true, false, true, true, false];
        a.step(&mut params, &mut grads, &mut touched, channels, &lr);
        let mut b = SparseAdam::new(channels * vertices, 0.5, 0.5);
        b.load_bytes("test", &a.to_bytes()).unwrap();
        // The same next step from both.
        let (mut pa, mut pb) = (params.clone(), params);
        for (adam, p) in [(&mut a, &mut pa), (&mut b, &mut pb)] {
            let mut g: Vec<f32> = (0..channels * vertices).map(|i| 0.5 - i as f32 * 0.1).collect();
            adam.step(p, &mut g, &mut [true; 5], channels, &lr);
        }
        assert_eq!(pa, pb);
        assert!(SparseAdam::new(3, 0.9, 0.99).load_bytes("test", &a.to_bytes()).is_err());
    }

    #[test]
    fn a_state_whose_decay_would_turn_every_value_nan_is_refused() {
        for (beta1, beta2) in [(1.0, 0.99), (0.9, 1.0), (-0.1, 0.99), (0.9, 7.0)] {
            let bytes = SparseAdam::new(4, beta1, beta2).to_bytes();
            let err = SparseAdam::new(4, 0.9, 0.99).load_bytes("test", &bytes).expect_err("bad decays load");
            assert!(err.to_string().contains("[0, 1)"), "{err}");
        }
    }
}
