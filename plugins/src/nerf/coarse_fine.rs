//! The fine and coarse levels of the NeRF-style fields (`nerf`, `nerf++`): the fine level is
//! the field, the coarse level is the renderer's proposal network. Both levels are always
//! built and saved, fine first, so that checkpoints load whatever `hierarchical` says and the
//! switch is a pure ablation.

use sos_core::camera::Vec3;
use sos_core::plugin::field::{FrozenPass, Hierarchical, HierarchicalSampling};
use sos_core::plugin::{FieldTape, RadianceField};

use super::field::{mlp_gradients, mlp_parameters, read_params, set_mlp_parameters, write_params};
use super::network::NerfMlp;

/// One level of a [`CoarseFine`] field: a field in its own right whose networks a checkpoint
/// lists in this order.
pub trait Level: RadianceField {
    /// The level's networks, in checkpoint order.
    fn mlps(&self) -> Vec<&NerfMlp>;

    /// [`Level::mlps`], mutable (to load a checkpoint).
    fn mlps_mut(&mut self) -> Vec<&mut NerfMlp>;
}

/// The [`RadianceField`] methods of a [`Level`] that depend on its networks alone (gradient
/// checks, state, parameters), for an `impl RadianceField` block of a level kind.
macro_rules! network_methods {
    () => {
        fn gradients_finite(&self) -> bool {
            $crate::nerf::Level::mlps(self).iter().all(|m| m.gradients_finite())
        }

        fn discard_gradients(&mut self) {
            $crate::nerf::Level::mlps_mut(self).into_iter().for_each($crate::nerf::NerfMlp::zero_grad);
        }

        fn save_state(&self) -> Vec<u8> {
            $crate::nerf::write_params(&$crate::nerf::Level::mlps(self))
        }

        fn load_state(&mut self, bytes: &[u8]) -> Result<(), sos_core::error::StateError> {
            $crate::nerf::read_params(bytes, &mut $crate::nerf::Level::mlps_mut(self))
        }

        fn num_parameters(&self) -> usize {
            $crate::nerf::Level::mlps(self).iter().map(|m| m.num_parameters()).sum()
        }

        fn parameters(&self) -> Vec<f32> {
            $crate::nerf::mlp_parameters(&$crate::nerf::Level::mlps(self))
        }

        fn set_parameters(&mut self, values: &[f32]) -> Result<(), sos_core::error::StateError> {
            $crate::nerf::set_mlp_parameters(&mut $crate::nerf::Level::mlps_mut(self), values)
        }

        fn gradients(&self) -> Vec<f32> {
            $crate::nerf::mlp_gradients(&$crate::nerf::Level::mlps(self))
        }
    };
}

pub(crate) use network_methods;

/// A fine and a coarse level of one kind, as one field.
pub struct CoarseFine<L> {
    fine: L,
    coarse: L,
    /// The proposal pass the renderer runs with the coarse level; `None` leaves the coarse
    /// level unused and untrained.
    sampling: Option<Hierarchical>,
}

impl<L: Level> CoarseFine<L> {
    /// Builds both levels with `level`: the fine one seeded `seed ^ 0xF1`, the coarse one
    /// `seed ^ 0xC0`, so that runs with one seed keep their initialisation.
    pub fn build(seed: u64, sampling: Option<Hierarchical>, level: impl Fn(u64) -> L) -> Self {
        CoarseFine { fine: level(seed ^ 0xF1), coarse: level(seed ^ 0xC0), sampling }
    }

    /// The fine level.
    pub fn fine(&self) -> &L {
        &self.fine
    }

    /// Both levels, fine first.
    pub fn networks(&self) -> [&L; 2] {
        [&self.fine, &self.coarse]
    }

    /// Both levels, fine first.
    pub fn networks_mut(&mut self) -> [&mut L; 2] {
        [&mut self.fine, &mut self.coarse]
    }
}

impl<L: Level> RadianceField for CoarseFine<L> {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        self.fine.density(positions, density);
    }

    fn forward(&self, p: &[Vec3], d: &[Vec3], density: &mut [f32], rgb: &mut [[f32; 3]], record: bool) -> FieldTape {
        self.fine.forward(p, d, density, rgb, record)
    }

    fn backward(&mut self, p: &[Vec3], d: &[Vec3], tape: FieldTape, gd: &[f32], gc: &[[f32; 3]]) {
        self.fine.backward(p, d, tape, gd, gc);
    }

    fn step(&mut self, lr_factor: f32) {
        self.fine.step(lr_factor);
        if self.sampling.is_some() {
            self.coarse.step(lr_factor);
        }
    }

    fn gradients_finite(&self) -> bool {
        self.fine.gradients_finite() && self.coarse.gradients_finite()
    }

    fn discard_gradients(&mut self) {
        self.fine.discard_gradients();
        self.coarse.discard_gradients();
    }

    fn seg_input_dim(&self) -> usize {
        self.fine.seg_input_dim()
    }

    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
        self.fine.seg_input(positions, out);
    }

    fn save_state(&self) -> Vec<u8> {
        let nets: Vec<&NerfMlp> = self.fine.mlps().into_iter().chain(self.coarse.mlps()).collect();
        write_params(&nets)
    }

    fn load_state(&mut self, bytes: &[u8]) -> Result<(), sos_core::error::StateError> {
        let mut nets = self.fine.mlps_mut();
        nets.extend(self.coarse.mlps_mut());
        read_params(bytes, &mut nets)
    }

    fn num_parameters(&self) -> usize {
        self.fine.num_parameters() + if self.sampling.is_some() { self.coarse.num_parameters() } else { 0 }
    }

    fn parameters(&self) -> Vec<f32> {
        mlp_parameters(&self.trained())
    }

    fn set_parameters(&mut self, values: &[f32]) -> Result<(), sos_core::error::StateError> {
        let with_coarse = self.sampling.is_some();
        let mut nets = self.fine.mlps_mut();
        if with_coarse {
            nets.extend(self.coarse.mlps_mut());
        }
        set_mlp_parameters(&mut nets, values)
    }

    fn gradients(&self) -> Vec<f32> {
        mlp_gradients(&self.trained())
    }

    fn hierarchical(&self) -> Option<&dyn HierarchicalSampling> {
        self.sampling.is_some().then_some(self as &dyn HierarchicalSampling)
    }

    fn hierarchical_mut(&mut self) -> Option<&mut dyn HierarchicalSampling> {
        if self.sampling.is_some() {
            Some(self)
        } else {
            None
        }
    }

    // The fine level renders; its fused pass is the field's.
    fn frozen_pass(&self) -> Option<&dyn FrozenPass> {
        self.fine.frozen_pass()
    }
}

impl<L: Level> CoarseFine<L> {
    /// The networks training updates: the fine level's, and the coarse level's when it
    /// proposes samples.
    fn trained(&self) -> Vec<&NerfMlp> {
        let mut nets = self.fine.mlps();
        if self.sampling.is_some() {
            nets.extend(self.coarse.mlps());
        }
        nets
    }
}

/// Present only when `hierarchical` sampling is configured (see the getters above).
impl<L: Level> HierarchicalSampling for CoarseFine<L> {
    fn sampling(&self) -> Hierarchical {
        self.sampling.expect("hierarchical() hands this out only with sampling")
    }

    fn proposal(&self) -> Option<&dyn RadianceField> {
        Some(&self.coarse)
    }

    fn proposal_mut(&mut self) -> Option<&mut dyn RadianceField> {
        Some(&mut self.coarse)
    }
}
