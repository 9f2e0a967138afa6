//! The radiance-field role. A field maps world points and view directions to density and
//! colour, can back-propagate into its own parameters, and exposes a per-sample segmentation
//! input so that the core attaches the segmentation head to every field automatically.

use std::any::Any;

use crate::camera::Vec3;
use crate::error::{BuildError, StateError};
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

/// A trainable radiance field (hot path): the methods every field implements. Optimisations
/// that only some fields can offer are capabilities a field opts into by returning itself
/// from the matching getter ([`RadianceField::hierarchical`], [`RadianceField::frozen_pass`],
/// [`RadianceField::coarse_to_fine`], [`RadianceField::regularized`]); a field that does not
/// opt in gets the core's plain path and loses nothing but speed.
///
/// # Shapes and units
/// All slices are packed per sample: `positions[n]` (world coordinates, the scene's units),
/// `directions[n]` (unit vectors), `density[n]` (post-activation, `>= 0`, per world unit of
/// ray length: a ray segment of length `δ` has opacity `1 − exp(−density · δ)`), `rgb[n]` (in
/// `(0, 1)`), `seg_input[n * seg_input_dim]`. The field lives in the coordinates of the
/// [`SceneExtent`] it was built for.
///
/// # Threading and determinism
/// The renderer calls the `&self` methods from several rayon workers at once, on disjoint
/// chunks of samples; `backward` is called once per chunk from one thread at a time. The
/// result of every method must depend only on its inputs and the parameters: no hidden
/// random state, no dependence on the chunking or the thread count. Runs are reproduced bit
/// for bit from a seed, so a field that sums over samples must do so in a fixed order.
///
/// # Gradients
/// `backward` accumulates; `step` applies and clears. The trainers ask
/// [`RadianceField::gradients_finite`] before every step and call
/// [`RadianceField::discard_gradients`] instead of stepping when it says no, so both are part
/// of the contract rather than defaults a field could forget.
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

    /// Applies accumulated gradients (the field owns its optimiser state) scaled by the
    /// schedule's learning-rate factor, then clears them.
    fn step(&mut self, lr_factor: f32);

    /// Whether every gradient accumulated since the last [`RadianceField::step`] is finite.
    fn gradients_finite(&self) -> bool;

    /// Drops the gradients accumulated since the last step without applying them (a step with
    /// a non-finite loss or gradient is skipped this way).
    fn discard_gradients(&mut self);

    /// Width of the per-sample segmentation input.
    fn seg_input_dim(&self) -> usize;

    /// Per-sample segmentation input (e.g. interpolated features plus the positional encoding
    /// of the contracted position), `[n, seg_input_dim]`. Treated as constant in stage 2.
    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]);

    /// Serialises all parameters (checkpoints).
    fn save_state(&self) -> Vec<u8>;

    /// Restores parameters written by [`RadianceField::save_state`] of the same kind.
    fn load_state(&mut self, bytes: &[u8]) -> Result<(), StateError>;

    /// Number of trainable scalars (reported by `sos train`).
    fn num_parameters(&self) -> usize {
        self.parameters().len()
    }

    /// Every trainable parameter, flattened in a fixed order. The conformance suite perturbs
    /// them one at a time to check [`RadianceField::backward`] against finite differences;
    /// training never calls it.
    fn parameters(&self) -> Vec<f32>;

    /// Position (as [`RadianceField::parameters`] lays them out) of the first parameter that
    /// is NaN or infinite, checked when a checkpoint is restored. The default copies the
    /// parameters; a field that holds them in one array should scan it in place.
    fn first_non_finite_parameter(&self) -> Option<usize> {
        self.parameters().iter().position(|v| !v.is_finite())
    }

    /// Overwrites every parameter from values laid out as [`RadianceField::parameters`]
    /// returns them (derived caches must follow).
    fn set_parameters(&mut self, values: &[f32]) -> Result<(), StateError>;

    /// The gradients accumulated since the last [`RadianceField::step`], laid out as
    /// [`RadianceField::parameters`].
    fn gradients(&self) -> Vec<f32>;

    /// The optimiser's state (moments, step count) for a checkpoint that a run resumes from
    /// exactly as if it had not stopped. Empty (the default) when the field cannot save it: a
    /// resumed run then restarts the optimiser, which trains on but not bit for bit.
    fn save_optimizer_state(&self) -> Vec<u8> {
        Vec::new()
    }

    /// Restores what [`RadianceField::save_optimizer_state`] wrote (after
    /// [`RadianceField::load_state`]); called only with non-empty bytes.
    fn load_optimizer_state(&mut self, _bytes: &[u8]) -> Result<(), StateError> {
        Ok(())
    }

    /// The field will not be trained again in this run (stage 2 with the field frozen): it may
    /// drop its gradients and optimiser state to free their memory. A later backward pass or
    /// [`RadianceField::load_optimizer_state`] must still work, starting the optimiser afresh.
    fn release_training_state(&mut self) {}

    /// Hierarchical sampling, when the field wants it (default: single-pass marching).
    fn hierarchical(&self) -> Option<&dyn HierarchicalSampling> {
        None
    }

    /// Mutable access to the hierarchical sampling, for the proposal's backward pass.
    fn hierarchical_mut(&mut self) -> Option<&mut dyn HierarchicalSampling> {
        None
    }

    /// A fused pass for frozen renders (default: the plain path of [`plain`]).
    fn frozen_pass(&self) -> Option<&dyn FrozenPass> {
        None
    }

    /// A parametrisation that grows during stage 1 (default: fixed).
    fn coarse_to_fine(&self) -> Option<&dyn CoarseToFine> {
        None
    }

    /// Mutable access to the growing parametrisation, to grow it.
    fn coarse_to_fine_mut(&mut self) -> Option<&mut dyn CoarseToFine> {
        None
    }

    /// The field's own regularisers (default: none).
    fn regularized(&mut self) -> Option<&mut dyn Regularized> {
        None
    }
}

/// Writes, inside a wrapper field's `impl RadianceField` block, the required methods that pass
/// on to the wrapped field unchanged: all but `forward`, `backward` and `step`, which the
/// wrapper writes itself. `$inner` is the member of `self` that holds the wrapped field
/// (`inner` for `self.inner`, `0` for `self.0`). The capability getters keep their defaults
/// unless the wrapper writes them.
#[macro_export]
macro_rules! pass_on_field_methods {
    ($inner:tt) => {
        fn density(&self, positions: &[$crate::camera::Vec3], density: &mut [f32]) {
            self.$inner.density(positions, density)
        }

        fn gradients_finite(&self) -> bool {
            self.$inner.gradients_finite()
        }

        fn discard_gradients(&mut self) {
            self.$inner.discard_gradients()
        }

        fn seg_input_dim(&self) -> usize {
            self.$inner.seg_input_dim()
        }

        fn seg_input(&self, positions: &[$crate::camera::Vec3], out: &mut [f32]) {
            self.$inner.seg_input(positions, out)
        }

        fn save_state(&self) -> Vec<u8> {
            self.$inner.save_state()
        }

        fn load_state(&mut self, bytes: &[u8]) -> Result<(), $crate::error::StateError> {
            self.$inner.load_state(bytes)
        }

        fn num_parameters(&self) -> usize {
            self.$inner.num_parameters()
        }

        fn parameters(&self) -> Vec<f32> {
            self.$inner.parameters()
        }

        fn first_non_finite_parameter(&self) -> Option<usize> {
            self.$inner.first_non_finite_parameter()
        }

        fn set_parameters(&mut self, values: &[f32]) -> Result<(), $crate::error::StateError> {
            self.$inner.set_parameters(values)
        }

        fn gradients(&self) -> Vec<f32> {
            self.$inner.gradients()
        }

        fn save_optimizer_state(&self) -> Vec<u8> {
            self.$inner.save_optimizer_state()
        }

        fn load_optimizer_state(&mut self, bytes: &[u8]) -> Result<(), $crate::error::StateError> {
            self.$inner.load_optimizer_state(bytes)
        }

        fn release_training_state(&mut self) {
            self.$inner.release_training_state()
        }
    };
}

/// Capability: NeRF's hierarchical sampling (see [`Hierarchical`]).
pub trait HierarchicalSampling: Send + Sync {
    /// Samples the renderer draws for the proposal and for the field.
    fn sampling(&self) -> Hierarchical;

    /// The separate proposal ("coarse") network; `None` when the field proposes its own
    /// samples. Its gradients are applied by the owner's [`RadianceField::step`].
    fn proposal(&self) -> Option<&dyn RadianceField>;

    /// Mutable access to the proposal network, for its backward pass.
    fn proposal_mut(&mut self) -> Option<&mut dyn RadianceField>;
}

/// Capability: a frozen render's fused passes, for fields whose colour and segmentation input
/// fall out of work the density already did (NeRF's final trunk activations). Each method has
/// the plain path as its default, so a field overrides only the passes it can fuse; every
/// override must equal the plain path bit for bit.
pub trait FrozenPass: RadianceField {
    /// Density, colour and segmentation input at the same samples, in one pass.
    fn forward_with_seg_input(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        plain::forward_then_seg_input(self, positions, directions, density, rgb, seg_input)
    }

    /// Width of the per-sample state [`FrozenPass::density_with_state`] writes so that
    /// [`FrozenPass::colour_from_state`] needs no second pass of the density network. A frozen
    /// render with a density pass (early termination, weight threshold) then evaluates the
    /// network's trunk once per kept sample instead of twice. 0: no state is kept.
    fn density_state_dim(&self) -> usize {
        0
    }

    /// Whether a frozen render that only terminates rays early (no weight threshold) finds
    /// where each ray turns opaque in a density-only pass first, so that the full pass runs on
    /// the samples before that point alone. That pays when the density is much cheaper than
    /// the colour (a network's view branch); a field whose density costs about as much as its
    /// colour (a grid: both interpolate the same corners) answers `false`, and its full pass
    /// runs on every candidate instead, one pass over the samples rather than two. What lies
    /// behind the point where the transmittance falls below `early_stop` adds at most that
    /// much to a pixel.
    fn early_termination_pass(&self) -> bool {
        true
    }

    /// [`RadianceField::density`] that also writes each sample's state,
    /// `state[n * density_state_dim]`.
    fn density_with_state(&self, positions: &[Vec3], density: &mut [f32], _state: &mut [f32]) {
        self.density(positions, density);
    }

    /// Colour, and the segmentation input when `seg_input` is given, of samples whose state an
    /// earlier [`FrozenPass::density_with_state`] wrote: sample `j` reads state row `rows[j]`.
    fn colour_from_state(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        _state: &[f32],
        _rows: &[u32],
        rgb: &mut [[f32; 3]],
        seg_input: Option<&mut [f32]>,
    ) {
        plain::colour(self, positions, directions, rgb, seg_input)
    }
}

/// Capability: a parametrisation that grows coarse-to-fine during stage 1 (grids).
pub trait CoarseToFine: Send + Sync {
    /// Called at the start of every stage-1 step. Returns true when the parametrisation
    /// changed (so occupancy must be rebuilt).
    fn begin_step(&mut self, step: usize, total_steps: usize) -> bool;

    /// Fraction of its final spatial detail the field currently resolves (current/final
    /// resolution); the renderer scales the number of candidate samples by it, so coarse
    /// stages are cheap.
    fn detail_fraction(&self) -> f32;

    /// Cells along the most finely divided axis of the field's final grid, where its detail is
    /// that of a grid it interpolates (`None`: not so bounded). A frozen render needs about
    /// one candidate per cell: more samples of an interpolated cell add little to a midpoint
    /// quadrature.
    fn final_cells_across(&self) -> Option<usize> {
        None
    }
}

/// Capability: regularisers the field adds to its own gradients (e.g. total variation).
pub trait Regularized: Send + Sync {
    /// Adds the regularisers' gradients to the accumulated ones; returns their value for
    /// logging.
    fn regularize(&mut self) -> f64;
}

/// The core's side of each capability: the fast path where the field offers it, the plain
/// path (the trait's required methods) where it does not.
pub mod plain {
    use super::{RadianceField, Vec3};

    /// Density, colour and segmentation input at the same samples: the field's fused pass, or
    /// [`forward_then_seg_input`].
    pub fn forward_with_seg_input(
        field: &dyn RadianceField,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        match field.frozen_pass() {
            Some(fast) => fast.forward_with_seg_input(positions, directions, density, rgb, seg_input),
            None => forward_then_seg_input(field, positions, directions, density, rgb, seg_input),
        }
    }

    /// The plain path of [`forward_with_seg_input`]: the forward pass, then the segmentation
    /// input.
    pub fn forward_then_seg_input<F: RadianceField + ?Sized>(
        field: &F,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        field.forward(positions, directions, density, rgb, false);
        field.seg_input(positions, seg_input);
    }

    /// Whether a frozen render's early termination takes a density-only pass (see
    /// [`super::FrozenPass::early_termination_pass`]; `true` without a fused pass).
    pub fn early_termination_pass(field: &dyn RadianceField) -> bool {
        field.frozen_pass().is_none_or(|fast| fast.early_termination_pass())
    }

    /// Width of the state [`density_with_state`] keeps per sample (0 without a fused pass).
    pub fn density_state_dim(field: &dyn RadianceField) -> usize {
        field.frozen_pass().map_or(0, |fast| fast.density_state_dim())
    }

    /// Density, and each sample's state when the field keeps one.
    pub fn density_with_state(field: &dyn RadianceField, positions: &[Vec3], density: &mut [f32], state: &mut [f32]) {
        match field.frozen_pass() {
            Some(fast) if fast.density_state_dim() > 0 => fast.density_with_state(positions, density, state),
            _ => field.density(positions, density),
        }
    }

    /// Colour (and segmentation input) of samples whose state [`density_with_state`] wrote;
    /// without kept state, recomputed by the field's forward pass.
    pub fn colour_from_state(
        field: &dyn RadianceField,
        positions: &[Vec3],
        directions: &[Vec3],
        state: &[f32],
        rows: &[u32],
        rgb: &mut [[f32; 3]],
        seg_input: Option<&mut [f32]>,
    ) {
        match field.frozen_pass() {
            Some(fast) if fast.density_state_dim() > 0 => {
                fast.colour_from_state(positions, directions, state, rows, rgb, seg_input)
            }
            _ => colour(field, positions, directions, rgb, seg_input),
        }
    }

    /// Colour (and segmentation input) by the field's plain forward pass.
    pub fn colour<F: RadianceField + ?Sized>(
        field: &F,
        positions: &[Vec3],
        directions: &[Vec3],
        rgb: &mut [[f32; 3]],
        seg_input: Option<&mut [f32]>,
    ) {
        let mut density = vec![0.0; positions.len()];
        field.forward(positions, directions, &mut density, rgb, false);
        if let Some(seg) = seg_input {
            field.seg_input(positions, seg);
        }
    }

    /// Hierarchical sampling, if the field asks for it.
    pub fn hierarchical(field: &dyn RadianceField) -> Option<super::Hierarchical> {
        field.hierarchical().map(|h| h.sampling())
    }

    /// Starts a stage-1 step; true when the parametrisation changed.
    pub fn begin_step(field: &mut dyn RadianceField, step: usize, total_steps: usize) -> bool {
        field.coarse_to_fine_mut().is_some_and(|c| c.begin_step(step, total_steps))
    }

    /// Fraction of its final detail the field resolves (1 for fixed parametrisations).
    pub fn detail_fraction(field: &dyn RadianceField) -> f32 {
        field.coarse_to_fine().map_or(1.0, |c| c.detail_fraction())
    }

    /// Cells along the most finely divided axis of the field's final grid (`None`: no grid).
    pub fn final_cells_across(field: &dyn RadianceField) -> Option<usize> {
        field.coarse_to_fine().and_then(|c| c.final_cells_across())
    }

    /// Applies the field's regularisers; their value (0 without any).
    pub fn regularize(field: &mut dyn RadianceField) -> f64 {
        field.regularized().map_or(0.0, |r| r.regularize())
    }
}

/// Configuration of a radiance field, chosen by `[field] kind = "..."`.
#[typetag::serde(tag = "kind")]
pub trait RadianceFieldConfig: std::fmt::Debug + Send + Sync {
    /// Validates the settings and builds an initialised field for a scene of this extent.
    fn build(&self, extent: &SceneExtent, seed: u64) -> Result<Box<dyn RadianceField>, BuildError>;

    /// An upper estimate of the memory the field will take, computed from the settings alone
    /// (nothing allocated), so that a config no machine could serve is refused before the field
    /// is built. `None` (the default): unknown, and only the core's own buffers are checked.
    fn memory_estimate(&self) -> Option<FieldMemory> {
        None
    }
}

/// What a field's memory grows with (see [`RadianceFieldConfig::memory_estimate`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldMemory {
    /// Bytes of the parameters and everything kept per parameter (gradients, optimiser moments)
    /// at the field's largest size.
    pub parameter_bytes: u64,
    /// The config key (dotted, e.g. `field.resolution`) that sets `parameter_bytes`, for the
    /// message when it is too large.
    pub parameter_key: String,
    /// Bytes the field's tape keeps per recorded sample during a training step.
    pub bytes_per_sample: u64,
}

inventory::collect!(Registration<dyn RadianceFieldConfig>);
