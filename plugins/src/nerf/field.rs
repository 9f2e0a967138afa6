//! The runtime of the `nerf` field: a fine network and, for hierarchical sampling, a separate
//! coarse (proposal) network, each a [`NerfMlp`] with its own Adam state, paired by
//! [`CoarseFine`].

use std::any::Any;

use rand::SeedableRng;
use sos_core::camera::Vec3;
use sos_core::nn::{Adam, Param};
use sos_core::plugin::{state, FieldTape, RadianceField};
use sos_core::render::contraction::Contraction;

use super::coarse_fine::{CoarseFine, Level};
use super::network::{DensityActivation, NerfMlp, NerfShape, NerfTape};
use super::NerfConfig;

/// One network of the `nerf` field as a field in its own right (the coarse network is handed
/// to the renderer this way).
pub struct NerfNet {
    /// The MLP.
    pub mlp: NerfMlp,
    adam: Adam,
    contraction: Contraction,
}

/// Network input of world points: the scene's unit-cube mapping, scaled to `[−1, 1]³`.
pub fn normalised_coords(contraction: &Contraction, positions: &[Vec3]) -> Vec<f32> {
    let mut out = Vec::with_capacity(positions.len() * 3);
    for p in positions {
        let u = contraction.to_unit(*p);
        out.extend(u.iter().map(|v| 2.0 * v - 1.0));
    }
    out
}

impl NerfNet {
    /// A freshly initialised network.
    pub fn new(shape: NerfShape, act: DensityActivation, lr: f32, contraction: Contraction, seed: u64) -> Self {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        NerfNet { mlp: NerfMlp::new(shape, act, &mut rng), adam: Adam::new(lr), contraction }
    }

    fn coords(&self, positions: &[Vec3]) -> Vec<f32> {
        normalised_coords(&self.contraction, positions)
    }

    /// Applies and clears the accumulated gradients.
    pub fn apply_gradients(&mut self, lr_factor: f32) {
        let mut params = self.mlp.params_mut();
        self.adam.step(&mut params, lr_factor);
    }
}

/// Downcasts a field tape to the network's tape.
fn nerf_tape(tape: FieldTape) -> Option<Box<NerfTape>> {
    tape.and_then(|t| (t as Box<dyn Any>).downcast::<NerfTape>().ok())
}

impl RadianceField for NerfNet {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        self.mlp.density(&self.coords(positions), density);
    }

    fn forward(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
    ) -> FieldTape {
        let tape = self.mlp.forward(&self.coords(positions), directions, density, rgb, record);
        tape.map(|t| Box::new(t) as Box<dyn Any + Send + Sync>)
    }

    fn backward(
        &mut self,
        positions: &[Vec3],
        directions: &[Vec3],
        tape: FieldTape,
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    ) {
        let tape = match nerf_tape(tape) {
            Some(t) => t,
            None => {
                // Forward ran without recording: recompute it with a tape.
                let n = positions.len();
                let (mut d, mut c) = (vec![0.0; n], vec![[0.0; 3]; n]);
                let coords = self.coords(positions);
                Box::new(self.mlp.forward(&coords, directions, &mut d, &mut c, true).expect("recording forward"))
            }
        };
        self.mlp.backward(&tape, grad_density, grad_rgb);
    }

    fn step(&mut self, lr_factor: f32) {
        self.apply_gradients(lr_factor);
    }

    crate::nerf::network_methods!();

    fn seg_input_dim(&self) -> usize {
        self.mlp.width() + self.mlp.pe_dim()
    }

    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
        self.mlp.features(&self.coords(positions), out);
    }

    fn frozen_pass(&self) -> Option<&dyn sos_core::plugin::FrozenPass> {
        Some(self)
    }
}

impl sos_core::plugin::FrozenPass for NerfNet {
    fn forward_with_seg_input(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        self.mlp.forward_with_features(&self.coords(positions), directions, density, rgb, seg_input);
    }

    fn density_state_dim(&self) -> usize {
        self.mlp.width()
    }

    fn density_with_state(&self, positions: &[Vec3], density: &mut [f32], state: &mut [f32]) {
        self.mlp.density_with_trunk(&self.coords(positions), density, state);
    }

    fn colour_from_state(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        state: &[f32],
        rows: &[u32],
        rgb: &mut [[f32; 3]],
        seg_input: Option<&mut [f32]>,
    ) {
        let coords = if seg_input.is_some() { self.coords(positions) } else { Vec::new() };
        self.mlp.colour_from_trunk(state, rows, &coords, directions, rgb, seg_input);
    }
}

/// The parameters of networks, one after another (see [`RadianceField::parameters`]).
pub fn mlp_parameters(nets: &[&NerfMlp]) -> Vec<f32> {
    sos_core::nn::param::flat_values(nets.iter().flat_map(|m| m.params()))
}

/// The gradients of networks, laid out as [`mlp_parameters`].
pub fn mlp_gradients(nets: &[&NerfMlp]) -> Vec<f32> {
    sos_core::nn::param::flat_grads(nets.iter().flat_map(|m| m.params()))
}

/// Overwrites networks' parameters from values laid out as [`mlp_parameters`].
pub fn set_mlp_parameters(nets: &mut [&mut NerfMlp], values: &[f32]) -> Result<(), sos_core::error::StateError> {
    let mut params: Vec<_> = nets.iter_mut().flat_map(|m| m.params_mut()).collect();
    sos_core::nn::param::assign_flat(&mut params, values).map_err(|want| sos_core::error::StateError::Mismatch {
        kind: "nerf".into(),
        reason: format!("{} parameter values given for {want} parameters", values.len()),
    })
}

/// Writes networks as a [`sos_core::plugin::state`] whose JSON header lists the parameter sizes,
/// then every parameter's values in [`NerfMlp::params`] order.
pub fn write_params(nets: &[&NerfMlp]) -> Vec<u8> {
    let sizes: Vec<Vec<usize>> = nets.iter().map(|m| m.params().iter().map(|p| p.len()).collect()).collect();
    let header = serde_json::json!({ "format": "nerf-params-1", "sizes": sizes });
    let values: Vec<&[f32]> = nets.iter().flat_map(|m| m.params()).map(|p| &p.value[..]).collect();
    state::write(&header, &values)
}

/// Restores networks written by [`write_params`]; the sizes must match the configured networks.
pub fn read_params(bytes: &[u8], nets: &mut [&mut NerfMlp]) -> Result<(), sos_core::error::StateError> {
    use sos_core::error::StateError;
    let kind = "nerf";
    let (header, body) = state::read(kind, bytes)?;
    let sizes: Vec<Vec<usize>> = serde_json::from_value(header["sizes"].clone())
        .map_err(|e| StateError::Malformed { kind: kind.into(), reason: format!("header: {e}") })?;
    let want: Vec<Vec<usize>> = nets.iter().map(|m| m.params().iter().map(|p| p.len()).collect()).collect();
    if sizes != want {
        return Err(StateError::Mismatch {
            kind: kind.into(),
            reason: format!(
                "it holds {} network(s) with {} parameters but the config builds {} with {} \
                 (were depth, width, frequencies or `hierarchical` changed?)",
                sizes.len(),
                sizes.iter().flatten().sum::<usize>(),
                want.len(),
                want.iter().flatten().sum::<usize>()
            ),
        });
    }
    let values = state::values(kind, body, sizes.iter().flatten().sum())?;
    let mut rest = &values[..];
    for m in nets.iter_mut() {
        for p in m.params_mut() {
            let (chunk, tail) = rest.split_at(p.len());
            p.value.copy_from_slice(chunk);
            Param::zero_grad(p);
            rest = tail;
        }
    }
    Ok(())
}

/// The `nerf` field (see the module docs of [`super`]): a fine and a coarse [`NerfNet`].
pub type NerfField = CoarseFine<NerfNet>;

impl CoarseFine<NerfNet> {
    /// Builds both networks.
    pub fn new(config: NerfConfig, contraction: Contraction, seed: u64) -> Self {
        let shape = config.shape();
        let act = config.density_activation;
        CoarseFine::build(seed, config.sampling(), |seed| NerfNet::new(shape, act, config.lr, contraction, seed))
    }
}

impl Level for NerfNet {
    fn mlps(&self) -> Vec<&NerfMlp> {
        vec![&self.mlp]
    }

    fn mlps_mut(&mut self) -> Vec<&mut NerfMlp> {
        vec![&mut self.mlp]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sos_core::plugin::field::Hierarchical;
    use sos_core::scene::SceneExtent;

    fn tiny_config() -> NerfConfig {
        NerfConfig {
            depth: 3,
            width: 8,
            skip: 2,
            view_width: 4,
            pos_frequencies: 2,
            dir_frequencies: 1,
            ..Default::default()
        }
    }

    fn field(seed: u64) -> NerfField {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        NerfField::new(tiny_config(), Contraction::new(&extent), seed)
    }

    #[test]
    fn state_round_trips_and_rejects_other_shapes() {
        let a = field(1);
        let mut b = field(2);
        let p = vec![[0.1, 0.2, -0.3], [0.5, -0.5, 0.0]];
        let dirs = vec![[0.0, 0.0, 1.0]; 2];
        let eval = |f: &NerfField| {
            let (mut d, mut c) = (vec![0.0; 2], vec![[0.0; 3]; 2]);
            f.forward(&p, &dirs, &mut d, &mut c, false);
            (d, c)
        };
        assert_ne!(eval(&a).1, eval(&b).1);
        let bytes = a.save_state();
        b.load_state(&bytes).unwrap();
        assert_eq!(eval(&a), eval(&b));
        assert_eq!(b.save_state(), bytes);
        assert_eq!(a.networks()[1].mlp, b.networks()[1].mlp);
        assert!(matches!(b.load_state(&bytes[..bytes.len() - 4]), Err(sos_core::error::StateError::Truncated { .. })));
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let mut wide = NerfField::new(NerfConfig { width: 9, ..tiny_config() }, Contraction::new(&extent), 0);
        let err = wide.load_state(&bytes).unwrap_err();
        assert!(matches!(err, sos_core::error::StateError::Mismatch { .. }), "{err}");
        assert!(err.to_string().contains("width"), "{err}");
    }

    #[test]
    fn segmentation_input_is_trunk_features_then_encoding() {
        let f = field(3);
        assert_eq!(f.seg_input_dim(), 8 + 3 * 5);
        let reference = NerfField::new(
            NerfConfig::default(),
            Contraction::new(&SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] }),
            0,
        );
        assert_eq!(reference.seg_input_dim(), 319, "the reference head is 319 -> 128 -> 2");
        let mut out = vec![0.0; 2 * f.seg_input_dim()];
        f.seg_input(&[[0.5, 0.0, 0.0], [0.0, 0.5, 0.0]], &mut out);
        // Coordinates in [−1, 1]³: x = 0.5 maps to 0.5.
        assert!((out[8] - 0.5).abs() < 1e-6);
        assert!(out[..8].iter().all(|&v| v >= 0.0), "trunk features are post-ReLU");
    }

    #[test]
    fn hierarchical_switch_hands_out_the_coarse_network() {
        let mut f = field(0);
        let h = f.hierarchical().expect("hierarchical sampling is on by default");
        assert_eq!(h.sampling(), Hierarchical { coarse_samples: 64, fine_samples: 128 });
        assert!(h.proposal().is_some());
        assert!(f.hierarchical_mut().and_then(|h| h.proposal_mut()).is_some());
        let n_both = f.num_parameters();
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let f = NerfField::new(NerfConfig { hierarchical: false, ..tiny_config() }, Contraction::new(&extent), 0);
        assert!(f.hierarchical().is_none());
        assert_eq!(2 * f.num_parameters(), n_both);
    }
}
