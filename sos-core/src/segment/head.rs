//! The segmentation head the core attaches to every radiance field: an MLP from the field's
//! per-sample segmentation input to raw logits, volume-rendered with the field's weights.

use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use crate::config::HeadConfig;
use crate::nn::{Activation, Adam, Mlp, MlpTape};

/// The head and its optimiser.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SegHead {
    /// `seg_input_dim → hidden… → outputs`, ReLU between layers, raw logits out.
    pub mlp: Mlp,
    /// Adam state.
    pub adam: Adam,
}

impl SegHead {
    /// A freshly initialised head for a field with `input_dim` segmentation inputs.
    pub fn new(config: &HeadConfig, input_dim: usize, lr: f32, seed: u64) -> Self {
        let mut dims = vec![input_dim];
        dims.extend(&config.hidden);
        dims.push(config.outputs);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x5E6_4EAD);
        SegHead { mlp: Mlp::new(&dims, Activation::Relu, Activation::Identity, &mut rng), adam: Adam::new(lr) }
    }

    /// Logit channels.
    pub fn outputs(&self) -> usize {
        self.mlp.out_dim()
    }

    /// Logits of `n` samples with a tape for [`SegHead::backward`].
    pub fn forward(&self, input: &[f32], n: usize) -> (Vec<f32>, MlpTape) {
        self.mlp.forward(input, n)
    }

    /// [`SegHead::forward`] into a tape whose buffers are reused.
    pub fn forward_into(&self, input: &[f32], n: usize, tape: &mut MlpTape) -> Vec<f32> {
        self.mlp.forward_into(input, n, tape)
    }

    /// Logits without a tape (inference).
    pub fn infer(&self, input: &[f32], n: usize) -> Vec<f32> {
        self.mlp.infer(input, n)
    }

    /// Accumulates gradients given `∂L/∂logits`.
    pub fn backward(&mut self, tape: &MlpTape, grad_logits: &[f32]) {
        self.mlp.backward(tape, grad_logits, false);
    }

    /// [`SegHead::forward_into`] without a copy of `input` in the tape (see
    /// [`crate::nn::Mlp::forward_into_without_input`]).
    pub fn forward_into_without_input(&self, input: &[f32], n: usize, tape: &mut MlpTape) -> Vec<f32> {
        self.mlp.forward_into_without_input(input, n, tape)
    }

    /// [`SegHead::backward`] for a tape without its input, given that input again.
    pub fn backward_with_input(&mut self, tape: &MlpTape, input: &[f32], grad_logits: &[f32]) {
        self.mlp.backward_with_input(tape, input, grad_logits, false);
    }

    /// Applies the accumulated gradients.
    pub fn step(&mut self, lr_factor: f32) {
        let mut params = self.mlp.params_mut();
        self.adam.step(&mut params, lr_factor);
    }

    /// Serialised parameters and optimiser state (checkpoint section `head`).
    pub fn to_bytes(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("head serialises")
    }

    /// Restores a head written by [`SegHead::to_bytes`].
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        serde_json::from_slice(bytes).map_err(|e| format!("segmentation head: {e}"))
    }
}
