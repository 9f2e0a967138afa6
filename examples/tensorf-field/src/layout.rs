//! The field's parameter tensors: their order, shapes, learning-rate groups and initial values.
//! One fixed order serves the dfdx graph, the optimiser, `parameters()` and the saved state.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sos_core::encoding::positional_encoding_dim;

use crate::config::TensorfConfig;
use crate::samples::{LINES, PLANES};

/// Which learning rate a tensor follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Group {
    /// Planes and lines (`lr_grid`).
    Grid,
    /// Basis matrix and colour MLP (`lr_network`).
    Network,
}

/// One parameter tensor, a row-major `[rows, cols]` matrix.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Spec {
    /// Name in messages, e.g. `density_plane_xy`.
    pub name: String,
    /// Rows (vertices for planes and lines, inputs for layers).
    pub rows: usize,
    /// Columns (components for planes and lines, outputs for layers).
    pub cols: usize,
    /// Learning-rate group.
    pub group: Group,
}

impl Spec {
    /// Number of values.
    pub fn len(&self) -> usize {
        self.rows * self.cols
    }
}

// Order of the tensors: density planes xy, xz, yz (`[res_a·res_b, density_components]`),
// density lines z, y, x (`[res_c, density_components]`), the same six for the appearance,
// three basis matrices `[appearance_components, features]`, then the colour MLP.

/// Hidden weights of the colour MLP, `[features + view encoding, hidden]`.
pub const W1: usize = 15;
/// Hidden bias, `[1, hidden]`.
pub const B1: usize = 16;
/// Output bias, `[1, 3]` (after the output weights `[hidden, 3]`).
pub const B2: usize = 18;
/// Number of tensors.
pub const COUNT: usize = 19;

const AXES: [char; 3] = ['x', 'y', 'z'];

/// The ordered list of parameter tensors a config describes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    /// Every tensor, in order.
    pub specs: Vec<Spec>,
}

/// Width of the colour MLP's view-direction input.
pub fn view_dim(config: &TensorfConfig) -> usize {
    positional_encoding_dim(3, config.view_frequencies)
}

impl Layout {
    /// The layout of `config` with planes and lines of `res` vertices per axis.
    pub fn new(config: &TensorfConfig, res: [usize; 3]) -> Self {
        let spec = |name: String, rows, cols, group| Spec { name, rows, cols, group };
        let mut specs = Vec::with_capacity(COUNT);
        for (prefix, comps) in [("density", config.density_components), ("appearance", config.appearance_components)] {
            for (a, b) in PLANES {
                specs.push(spec(format!("{prefix}_plane_{}{}", AXES[a], AXES[b]), res[a] * res[b], comps, Group::Grid));
            }
            for c in LINES {
                specs.push(spec(format!("{prefix}_line_{}", AXES[c]), res[c], comps, Group::Grid));
            }
        }
        for k in 0..3 {
            specs.push(spec(format!("basis_{k}"), config.appearance_components, config.features, Group::Network));
        }
        specs.push(spec("mlp_hidden_weight".into(), config.features + view_dim(config), config.hidden, Group::Network));
        specs.push(spec("mlp_hidden_bias".into(), 1, config.hidden, Group::Network));
        specs.push(spec("mlp_output_weight".into(), config.hidden, 3, Group::Network));
        specs.push(spec("mlp_output_bias".into(), 1, 3, Group::Network));
        debug_assert_eq!(specs.len(), COUNT);
        Layout { specs }
    }

    /// Total number of scalars.
    pub fn total(&self) -> usize {
        self.specs.iter().map(Spec::len).sum()
    }

    /// Initial values from a seed: planes and lines uniform with standard deviation
    /// `init_scale` (TensoRF draws them from `0.1·N(0, 1)`); layers uniform in `±1/√fan_in`
    /// (PyTorch's default); the output bias zero, so colours start near grey.
    pub fn initial_values(&self, config: &TensorfConfig, seed: u64) -> Vec<Vec<f32>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        self.specs
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let bound = match i {
                    B2 => 0.0,
                    B1 => 1.0 / (self.specs[W1].rows as f32).sqrt(),
                    _ if s.group == Group::Grid => config.init_scale * 3f32.sqrt(),
                    _ => 1.0 / (s.rows as f32).sqrt(),
                };
                (0..s.len()).map(|_| if bound > 0.0 { rng.gen_range(-bound..bound) } else { 0.0 }).collect()
            })
            .collect()
    }
}
