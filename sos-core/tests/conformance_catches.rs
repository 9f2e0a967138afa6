//! The conformance suite passes a correct field and fails each kind of broken one: a suite that
//! cannot fail would prove nothing about the plugins it passes.

use serde::{Deserialize, Serialize};
use sos_core::camera::Vec3;
use sos_core::error::{BuildError, StateError};
use sos_core::nn::activation::{sigmoid, softplus};
use sos_core::plugin::{FieldTape, FrozenPass, RadianceField, RadianceFieldConfig};
use sos_core::scene::SceneExtent;
use sos_core::testing::conformance::check_field;

/// How a [`Linear`] field is broken.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
enum Fault {
    #[default]
    None,
    /// `backward` doubles the colour gradient.
    WrongGradient,
    /// `gradients_finite` always says yes.
    BlindToNan,
    /// The fused pass shifts the colour by one ulp.
    FusedPassDiffers,
    /// `load_state` ignores what it is given.
    ForgetfulLoad,
}

/// density = softplus(w·p + b), rgb = sigmoid(c + u·d): small enough to check by hand.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct LinearConfig {
    fault: Fault,
}

#[typetag::serde(name = "test-linear")]
impl RadianceFieldConfig for LinearConfig {
    fn build(&self, _: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError> {
        let theta =
            (0..13).map(|i| (((i as u64 + 1) * (seed + 3) * 2654435761) % 1000) as f32 / 1000.0 - 0.5).collect();
        Ok(Box::new(Linear { theta, grad: vec![0.0; 13], fault: self.fault }))
    }
}

/// Parameters: w (3), b (1), c (3), u (3 x 3 diagonal-free: 3 used as a row), 13 in all.
struct Linear {
    theta: Vec<f32>,
    grad: Vec<f32>,
    fault: Fault,
}

impl Linear {
    fn pre_density(&self, p: &Vec3) -> f32 {
        self.theta[0] * p[0] + self.theta[1] * p[1] + self.theta[2] * p[2] + self.theta[3]
    }
    fn pre_colour(&self, d: &Vec3, k: usize) -> f32 {
        self.theta[4 + k] + self.theta[7 + k] * d[k] + self.theta[10 + k] * d[(k + 1) % 3]
    }
}

impl RadianceField for Linear {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        for (p, s) in positions.iter().zip(density) {
            *s = softplus(self.pre_density(p));
        }
    }
    fn forward(&self, p: &[Vec3], d: &[Vec3], density: &mut [f32], rgb: &mut [[f32; 3]], _: bool) -> FieldTape {
        self.density(p, density);
        for (d, c) in d.iter().zip(rgb) {
            *c = [0, 1, 2].map(|k| sigmoid(self.pre_colour(d, k)));
        }
        None
    }
    fn backward(&mut self, p: &[Vec3], d: &[Vec3], _: FieldTape, gd: &[f32], grgb: &[[f32; 3]]) {
        let scale = if self.fault == Fault::WrongGradient { 2.0 } else { 1.0 };
        for i in 0..p.len() {
            let g = gd[i] * sigmoid(self.pre_density(&p[i]));
            for a in 0..3 {
                self.grad[a] += g * p[i][a];
            }
            self.grad[3] += g;
            for k in 0..3 {
                let s = sigmoid(self.pre_colour(&d[i], k));
                let g = scale * grgb[i][k] * s * (1.0 - s);
                self.grad[4 + k] += g;
                self.grad[7 + k] += g * d[i][k];
                self.grad[10 + k] += g * d[i][(k + 1) % 3];
            }
        }
    }
    fn step(&mut self, lr_factor: f32) {
        for (t, g) in self.theta.iter_mut().zip(&mut self.grad) {
            *t -= 0.01 * lr_factor * *g;
            *g = 0.0;
        }
    }
    fn gradients_finite(&self) -> bool {
        self.fault == Fault::BlindToNan || self.grad.iter().all(|g| g.is_finite())
    }
    fn discard_gradients(&mut self) {
        self.grad.fill(0.0);
    }
    fn seg_input_dim(&self) -> usize {
        3
    }
    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
        for (p, o) in positions.iter().zip(out.chunks_exact_mut(3)) {
            o.copy_from_slice(p);
        }
    }
    fn save_state(&self) -> Vec<u8> {
        self.theta.iter().flat_map(|v| v.to_le_bytes()).collect()
    }
    fn load_state(&mut self, bytes: &[u8]) -> Result<(), StateError> {
        if bytes.len() != 4 * self.theta.len() {
            return Err(StateError::Truncated { kind: "test-linear".into() });
        }
        if self.fault != Fault::ForgetfulLoad {
            for (t, b) in self.theta.iter_mut().zip(bytes.chunks_exact(4)) {
                *t = f32::from_le_bytes(b.try_into().expect("4 bytes"));
            }
        }
        Ok(())
    }
    fn parameters(&self) -> Vec<f32> {
        self.theta.clone()
    }
    fn set_parameters(&mut self, values: &[f32]) -> Result<(), StateError> {
        if values.len() != self.theta.len() {
            return Err(StateError::Mismatch { kind: "test-linear".into(), reason: "length".into() });
        }
        self.theta.copy_from_slice(values);
        Ok(())
    }
    fn gradients(&self) -> Vec<f32> {
        self.grad.clone()
    }
    fn frozen_pass(&self) -> Option<&dyn FrozenPass> {
        Some(self)
    }
}

impl FrozenPass for Linear {
    fn forward_with_seg_input(
        &self,
        p: &[Vec3],
        d: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg: &mut [f32],
    ) {
        self.forward(p, d, density, rgb, false);
        self.seg_input(p, seg);
        if self.fault == Fault::FusedPassDiffers {
            rgb[0][0] = f32::from_bits(rgb[0][0].to_bits() + 1);
        }
    }
}

fn check(fault: Fault) {
    check_field("test-linear", &LinearConfig { fault });
}

#[test]
fn a_correct_field_passes() {
    check(Fault::None);
}

#[test]
#[should_panic(expected = "finite differences")]
fn a_wrong_backward_fails() {
    check(Fault::WrongGradient);
}

#[test]
#[should_panic(expected = "misses a NaN")]
fn a_gradient_check_blind_to_nan_fails() {
    check(Fault::BlindToNan);
}

#[test]
#[should_panic(expected = "fused forward_with_seg_input changes the colour")]
fn a_fused_pass_off_by_one_ulp_fails() {
    check(Fault::FusedPassDiffers);
}

#[test]
#[should_panic(expected = "parameters change through save/load")]
fn a_load_that_forgets_fails() {
    check(Fault::ForgetfulLoad);
}
