//! The radiance-field role. A field maps world points and view directions to density and
//! colour, can back-propagate into its own parameters, and exposes a per-sample segmentation
//! input so that the core attaches the segmentation head to every field automatically.

use std::any::Any;

use crate::camera::Vec3;
use crate::error::BuildError;
use crate::registry::Registration;
use crate::scene::SceneExtent;

/// What a field's forward pass kept for its backward pass (activations, interpolation
/// weights…). Fields that can recompute everything return `None`.
pub type FieldTape = Option<Box<dyn Any + Send + Sync>>;

/// Coarse-to-fine sampling a field asks the renderer for (NeRF's hierarchical sampling): a
/// proposal pass over `coarse_samples` stratified candidates, then `fine_samples` more drawn by
/// inverse CDF from the proposal's weights; the field itself is evaluated on the union.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Hierarchical {
    /// Stratified proposal samples per ray (the reference: 64).
    pub coarse_samples: usize,
    /// Importance samples per ray added to the proposal's (the reference: 128).
    pub fine_samples: usize,
}

/// A trainable radiance field (hot path).
///
/// # Shapes
/// All slices are packed per sample: `positions[n]`, `directions[n]` (unit vectors),
/// `density[n]` (post-activation, `>= 0`), `rgb[n]` (in `(0, 1)`), `seg_input[n * seg_input_dim]`.
pub trait RadianceField: Send + Sync {
    /// Density (post-activation) at world positions; the cheap path used for empty-space
    /// skipping and occupancy updates.
    fn density(&self, positions: &[Vec3], density: &mut [f32]);

    /// Density and colour at samples. When `record` is true the returned tape holds what
    /// [`RadianceField::backward`] needs.
    fn forward(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
    ) -> FieldTape;

    /// Accumulates parameter gradients given `∂L/∂density` and `∂L/∂rgb` at the samples of
    /// the matching [`RadianceField::forward`] call.
    fn backward(
        &mut self,
        positions: &[Vec3],
        directions: &[Vec3],
        tape: FieldTape,
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    );

    /// Adds the field's own regularisers (e.g. total variation) to the accumulated
    /// gradients; returns their value for logging.
    fn regularize(&mut self) -> f64 {
        0.0
    }

    /// Applies accumulated gradients (the field owns its optimiser state) scaled by the
    /// schedule's learning-rate factor, then clears them.
    fn step(&mut self, lr_factor: f32);

    /// Whether every gradient accumulated since the last [`RadianceField::step`] is finite
    /// (trainers check it before stepping; the default trusts the field).
    fn gradients_finite(&self) -> bool {
        true
    }

    /// Drops the gradients accumulated since the last step without applying them (a step with
    /// a non-finite loss or gradient is skipped this way). Fields that accumulate must
    /// implement it; the default does nothing.
    fn discard_gradients(&mut self) {}

    /// Called at the start of every stage-1 step; grids use it to grow coarse-to-fine.
    /// Returns true when the parametrisation changed (so occupancy must be rebuilt).
    fn begin_step(&mut self, _step: usize, _total_steps: usize) -> bool {
        false
    }

    /// Fraction of its final spatial detail the field currently resolves (grids growing
    /// coarse-to-fine return their current/final resolution); the renderer scales the number
    /// of candidate samples by it, so coarse stages are cheap.
    fn detail_fraction(&self) -> f32 {
        1.0
    }

    /// Hierarchical sampling this field wants, if any (default: single-pass marching).
    fn hierarchical(&self) -> Option<Hierarchical> {
        None
    }

    /// The separate proposal ("coarse") network of a hierarchical field; `None` when the
    /// field proposes its own samples. Its gradients are applied by the owner's
    /// [`RadianceField::step`].
    fn coarse(&self) -> Option<&dyn RadianceField> {
        None
    }

    /// Mutable access to the proposal network, for its backward pass.
    fn coarse_mut(&mut self) -> Option<&mut dyn RadianceField> {
        None
    }

    /// Width of the per-sample segmentation input.
    fn seg_input_dim(&self) -> usize;

    /// Per-sample segmentation input (e.g. interpolated features plus the positional encoding
    /// of the contracted position), `[n, seg_input_dim]`. Treated as constant in stage 2.
    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]);

    /// Density, colour and segmentation input at the same samples, without a tape (stage 2,
    /// where the field is frozen). Fields whose segmentation input falls out of their forward
    /// pass (NeRF's final trunk activations) override this to run that pass once.
    fn forward_with_seg_input(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        self.forward(positions, directions, density, rgb, false);
        self.seg_input(positions, seg_input);
    }

    /// Width of the per-sample state that [`RadianceField::density_with_state`] writes so that
    /// [`RadianceField::colour_from_state`] needs no second pass of the density network (NeRF's
    /// final trunk activations); 0, the default, for fields that keep none. A frozen render
    /// with a density pass (early termination, weight threshold) then evaluates the network's
    /// trunk once per kept sample instead of twice.
    fn density_state_dim(&self) -> usize {
        0
    }

    /// [`RadianceField::density`] that also writes each sample's state,
    /// `state[n * density_state_dim]`. Only called when [`RadianceField::density_state_dim`]
    /// is positive.
    fn density_with_state(&self, positions: &[Vec3], density: &mut [f32], state: &mut [f32]) {
        debug_assert!(state.is_empty(), "a field with state must override density_with_state");
        self.density(positions, density);
    }

    /// Colour, and the segmentation input when `seg_input` is given, of samples whose state an
    /// earlier [`RadianceField::density_with_state`] wrote: sample `j` reads state row
    /// `rows[j]`. Equal to the matching outputs of [`RadianceField::forward`] and
    /// [`RadianceField::seg_input`]; the default recomputes them that way.
    fn colour_from_state(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        _state: &[f32],
        _rows: &[u32],
        rgb: &mut [[f32; 3]],
        seg_input: Option<&mut [f32]>,
    ) {
        let mut density = vec![0.0; positions.len()];
        self.forward(positions, directions, &mut density, rgb, false);
        if let Some(seg) = seg_input {
            self.seg_input(positions, seg);
        }
    }

    /// Serialises all parameters (checkpoints).
    fn save_state(&self) -> Vec<u8>;

    /// Restores parameters written by [`RadianceField::save_state`] of the same kind.
    fn load_state(&mut self, bytes: &[u8]) -> Result<(), String>;

    /// Number of trainable scalars (reported by `sos train`).
    fn num_parameters(&self) -> usize;
}

/// Configuration of a radiance field, chosen by `[field] kind = "..."`.
#[typetag::serde(tag = "kind")]
pub trait RadianceFieldConfig: std::fmt::Debug + Send + Sync {
    /// Validates the settings and builds an initialised field for a scene of this extent.
    fn build(&self, extent: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError>;
}

inventory::collect!(Registration<dyn RadianceFieldConfig>);
