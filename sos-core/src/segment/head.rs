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
        let head: SegHead = serde_json::from_slice(bytes).map_err(|e| format!("segmentation head: {e}"))?;
        if let Some(why) = head.mlp.shape_error() {
            return Err(format!("segmentation head: {why}"));
        }
        let lens: Vec<usize> = head.mlp.layers.iter().flat_map(|l| [l.weight.len(), l.bias.len()]).collect();
        if let Some(why) = head.adam.state_error(&lens) {
            return Err(format!("segmentation head: {why}"));
        }
        Ok(head)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn head() -> SegHead {
        SegHead::new(&HeadConfig { hidden: vec![5], outputs: 2 }, 4, 1e-3, 1)
    }

    /// The head's JSON with `edit` applied to it.
    fn edited(edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
        let mut json: serde_json::Value = serde_json::from_slice(&head().to_bytes()).unwrap();
        edit(&mut json);
        serde_json::to_vec(&json).unwrap()
    }

    #[test]
    fn a_saved_head_loads_back() {
        let h = head();
        let back = SegHead::from_bytes(&h.to_bytes()).unwrap();
        assert_eq!(back.mlp.layers.len(), 2);
        assert_eq!(back.infer(&[0.1, 0.2, 0.3, 0.4], 1), h.infer(&[0.1, 0.2, 0.3, 0.4], 1));
    }

    #[test]
    fn a_head_that_cannot_run_is_refused_when_read_not_when_used() {
        type Edit = Box<dyn FnOnce(&mut serde_json::Value)>;
        let cases: [(&str, Edit); 7] = [
            ("no layers", Box::new(|j| j["mlp"]["layers"] = serde_json::json!([]))),
            ("holds", Box::new(|j| j["mlp"]["layers"][0]["weight"]["value"] = serde_json::json!([0.5]))),
            ("holds", Box::new(|j| j["mlp"]["layers"][1]["bias"]["value"] = serde_json::json!([]))),
            ("zero width", Box::new(|j| j["mlp"]["layers"][0]["out_dim"] = serde_json::json!(0))),
            ("decays", Box::new(|j| j["adam"]["beta1"] = serde_json::json!(1.0))),
            ("other parameters", Box::new(|j| j["adam"]["m"] = serde_json::json!([[0.0]]))),
            // Steps taken but no moments kept: the next step would find none to update.
            ("other parameters", Box::new(|j| j["adam"]["t"] = serde_json::json!(5))),
        ];
        for (want, edit) in cases {
            let err = SegHead::from_bytes(&edited(edit)).expect_err("a broken head loads");
            assert!(err.contains(want), "`{err}` does not say `{want}`");
        }
        // Widths that do not chain: layer 1 takes 5 inputs; give layer 0 three outputs.
        let bytes = edited(|j| {
            j["mlp"]["layers"][0]["out_dim"] = serde_json::json!(3);
            j["mlp"]["layers"][0]["weight"]["value"] = serde_json::json!(vec![0.0; 12]);
            j["mlp"]["layers"][0]["bias"]["value"] = serde_json::json!(vec![0.0; 3]);
        });
        let err = SegHead::from_bytes(&bytes).expect_err("unchained layers load");
        assert!(err.contains("takes 5 inputs but layer 0 gives 3"), "{err}");
    }
}
