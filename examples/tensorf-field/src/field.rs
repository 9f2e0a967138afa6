//! The runtime of the `tensorf` field: the [`RadianceField`] trait over the dfdx graph of
//! [`crate::graph`].
//!
//! Threading: the parameter tensors are immutable during `&self` calls, and dfdx's CPU
//! tensors are `Send + Sync` (reference-counted data; the device's only shared state, a random
//! generator and an allocation cache, sits behind locks, and this crate uses neither), so rayon
//! workers share them. Each block of samples builds its own graph; a taped graph never leaves
//! the worker that built it.
//!
//! Determinism: dfdx's element-wise ops, gathers and reductions work row by row in a fixed
//! order. Its matrix products (gemm) choose their blocking from the matrix shapes and split the
//! work between threads without splitting a dot product, so a row's result depends on the
//! shapes alone. Every block is therefore padded to [`BLOCK`] rows, and a sample's density and
//! colour are the same whatever call or thread it came in.

use dfdx::tensor::{Cpu, TensorFromVec};
use rayon::prelude::*;
use sos_core::camera::Vec3;
use sos_core::encoding::{positional_encoding, positional_encoding_dim};
use sos_core::error::StateError;
use sos_core::plugin::{CoarseToFine, FieldTape, FrozenPass, RadianceField};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;

use crate::adam::Adam;
use crate::config::TensorfConfig;
use crate::graph::{plain, traced, vector_jacobian, Activation};
use crate::layout::{Group, Layout};
use crate::samples::{view_encoding, Corners, Matrix, LINES, PLANES};

/// Samples per dfdx graph (and the row count every matrix product sees).
pub const BLOCK: usize = 2048;
/// Blocks whose gradients are computed in parallel before they are added up (in block order,
/// so the sum does not depend on the thread count).
const GROUP: usize = 4;

/// A TensoRF vector-matrix field (see the crate docs).
pub struct TensorfField {
    config: TensorfConfig,
    contraction: Contraction,
    /// Current vertices per axis of the planes and lines.
    res: [usize; 3],
    /// Index into `upsample_at` of the next growth.
    next_growth: usize,
    layout: Layout,
    dev: Cpu,
    /// The parameter tensors, in layout order.
    tensors: Vec<Matrix>,
    /// Gradients accumulated since the last step, per tensor.
    grads: Vec<Vec<f32>>,
    adam: Adam,
    act: Activation,
}

impl TensorfField {
    /// A freshly initialised field for a scene of `extent`, its random values drawn from `seed`.
    pub fn new(config: TensorfConfig, contraction: Contraction, extent: &SceneExtent, seed: u64) -> Self {
        let res = config.resolution_at(0);
        let layout = Layout::new(&config, res);
        let dev = Cpu::default();
        let values = layout.initial_values(&config, seed);
        let tensors = layout.specs.iter().zip(values).map(|(s, v)| dev.tensor_from_vec(v, (s.rows, s.cols))).collect();
        // The final cell: density units stay put when the planes and lines grow.
        let mean_res = config.resolution.iter().sum::<usize>() as f32 / 3.0;
        let cell = extent.characteristic_length() / (mean_res - 1.0);
        // softplus(shift) = −ln(1 − alpha_init): one cell of empty space has that opacity.
        let shift = (1.0 / (1.0 - config.alpha_init) - 1.0).ln();
        TensorfField {
            grads: layout.specs.iter().map(|s| vec![0.0; s.len()]).collect(),
            adam: Adam::new(layout.specs.iter().map(|s| s.len())),
            act: Activation { shift, inv_cell: 1.0 / cell },
            config,
            contraction,
            res,
            next_growth: 0,
            layout,
            dev,
            tensors,
        }
    }

    /// Current vertices per axis of the planes and lines.
    pub fn resolution(&self) -> [usize; 3] {
        self.res
    }

    /// Replaces the parameters with `values` laid out as `layout` at resolution `res`; the
    /// optimiser restarts, as TensoRF's does after each upsampling.
    fn install(&mut self, res: [usize; 3], layout: Layout, values: Vec<Vec<f32>>) {
        self.tensors =
            layout.specs.iter().zip(values).map(|(s, v)| self.dev.tensor_from_vec(v, (s.rows, s.cols))).collect();
        self.grads = layout.specs.iter().map(|s| vec![0.0; s.len()]).collect();
        self.adam = Adam::new(layout.specs.iter().map(|s| s.len()));
        self.layout = layout;
        self.res = res;
    }

    /// Resamples the planes and lines to `res` vertices per axis.
    fn grow_to(&mut self, res: [usize; 3]) {
        let old = self.res;
        let layout = Layout::new(&self.config, res);
        let values = self
            .tensors
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let v = t.as_vec();
                let comps = self.layout.specs[i].cols;
                // Tensors 0..12: per set (density, appearance), three planes then three lines.
                match i {
                    0..12 if i % 6 < 3 => {
                        let (a, b) = PLANES[i % 6];
                        crate::resample::plane(&v, (old[a], old[b]), (res[a], res[b]), comps)
                    }
                    0..12 => {
                        let c = LINES[i % 6 - 3];
                        crate::resample::line(&v, old[c], res[c], comps)
                    }
                    _ => v,
                }
            })
            .collect();
        self.install(res, layout, values);
    }

    /// The settings this field was built from.
    pub fn config(&self) -> &TensorfConfig {
        &self.config
    }

    /// Names and shapes `[rows, cols]` of the parameter tensors, in the order of
    /// [`RadianceField::parameters`].
    pub fn tensor_shapes(&self) -> Vec<(String, [usize; 2])> {
        self.layout.specs.iter().map(|s| (s.name.clone(), [s.rows, s.cols])).collect()
    }

    /// The block's corners, padded to [`BLOCK`] rows; with the appearance tables' weights
    /// when `appearance`.
    fn corners(&self, positions: &[Vec3], appearance: bool) -> Corners {
        let widths = [self.config.density_components, self.config.appearance_components];
        let widths = if appearance { &widths[..] } else { &widths[..1] };
        Corners::new(&self.dev, &self.contraction, self.res, widths, positions, BLOCK)
    }

    fn view(&self, directions: &[Vec3]) -> Matrix {
        view_encoding(&self.dev, directions, BLOCK, self.config.view_frequencies)
    }

    /// The gradients of one block's `Σ σ·gσ + Σ c·gc`, per tensor.
    fn block_gradients(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    ) -> Vec<Vec<f32>> {
        let n = positions.len();
        let corners = self.corners(positions, true);
        let view = self.view(directions);
        // Padding rows get zero output gradients: they add nothing.
        let mut gd = vec![0.0; BLOCK];
        gd[..n].copy_from_slice(grad_density);
        let mut gc = vec![0.0; BLOCK * 3];
        gc[..n * 3].copy_from_slice(grad_rgb.as_flattened());
        let gd = self.dev.tensor_from_vec(gd, (BLOCK,));
        let gc = self.dev.tensor_from_vec(gc, (BLOCK, 3));
        let grads = vector_jacobian(traced(&self.tensors), &corners, &view, self.act, gd, gc);
        // The traced copies share their ids with the stored tensors, so dfdx files the
        // gradients under the stored ones.
        self.tensors.iter().map(|t| grads.get(t).as_vec()).collect()
    }

    /// The segmentation input rows of samples `p` from a block's density and features.
    fn write_seg_input(&self, p: &[Vec3], sigma: &[f32], feat: &[f32], out: &mut [f32]) {
        let dim = self.seg_input_dim();
        let pe = positional_encoding_dim(3, self.config.seg_frequencies);
        let features = self.config.features;
        for (i, (pi, row)) in p.iter().zip(out.chunks_exact_mut(dim)).enumerate() {
            // Scale the unit cube to [−π, π] so the octaves resolve cell-sized detail.
            let x = self.contraction.to_unit(*pi).map(|v| (2.0 * v - 1.0) * std::f32::consts::PI);
            positional_encoding(&x, self.config.seg_frequencies, &mut row[..pe]);
            row[pe] = -(-sigma[i] / self.act.inv_cell).exp_m1();
            row[pe + 1..].copy_from_slice(&feat[i * features..(i + 1) * features]);
        }
    }

    fn flatten(parts: &[Vec<f32>]) -> Vec<f32> {
        parts.concat()
    }
}

impl RadianceField for TensorfField {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        positions.par_chunks(BLOCK).zip(density.par_chunks_mut(BLOCK)).for_each(|(p, d)| {
            let corners = self.corners(p, false);
            d.copy_from_slice(&plain(&self.tensors).density(&corners, self.act).as_vec()[..p.len()]);
        });
    }

    fn forward(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        _record: bool,
    ) -> FieldTape {
        positions
            .par_chunks(BLOCK)
            .zip(directions.par_chunks(BLOCK))
            .zip(density.par_chunks_mut(BLOCK).zip(rgb.par_chunks_mut(BLOCK)))
            .for_each(|((p, dirs), (d, c))| {
                let n = p.len();
                let (sigma, _, colour) =
                    plain(&self.tensors).forward(&self.corners(p, true), &self.view(dirs), self.act);
                d.copy_from_slice(&sigma.as_vec()[..n]);
                let colour = colour.as_vec();
                for (dst, src) in c.iter_mut().zip(colour.chunks_exact(3)) {
                    *dst = [src[0], src[1], src[2]];
                }
            });
        // A dfdx tape holds closures that are neither `Send` nor `Sync`, so it cannot travel
        // in a `FieldTape`; `backward` records the same graph again.
        None
    }

    fn backward(
        &mut self,
        positions: &[Vec3],
        directions: &[Vec3],
        _tape: FieldTape,
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    ) {
        let starts: Vec<usize> = (0..positions.len()).step_by(BLOCK).collect();
        for group in starts.chunks(GROUP) {
            let parts: Vec<Vec<Vec<f32>>> = group
                .par_iter()
                .map(|&s| {
                    let e = (s + BLOCK).min(positions.len());
                    self.block_gradients(&positions[s..e], &directions[s..e], &grad_density[s..e], &grad_rgb[s..e])
                })
                .collect();
            for part in parts {
                for (acc, g) in self.grads.iter_mut().zip(part) {
                    for (a, v) in acc.iter_mut().zip(g) {
                        *a += v;
                    }
                }
            }
        }
    }

    fn step(&mut self, lr_factor: f32) {
        self.adam.begin_step();
        for (k, tensor) in self.tensors.iter_mut().enumerate() {
            let lr = lr_factor
                * match self.layout.specs[k].group {
                    Group::Grid => self.config.lr_grid,
                    Group::Network => self.config.lr_network,
                };
            let mut values = tensor.as_vec();
            self.adam.update(k, &mut values, &self.grads[k], lr);
            tensor.copy_from(&values);
            self.grads[k].fill(0.0);
        }
    }

    fn gradients_finite(&self) -> bool {
        self.grads.iter().flatten().all(|g| g.is_finite())
    }

    fn discard_gradients(&mut self) {
        for g in &mut self.grads {
            g.fill(0.0);
        }
    }

    fn seg_input_dim(&self) -> usize {
        positional_encoding_dim(3, self.config.seg_frequencies) + 1 + self.config.features
    }

    /// `[positional encoding of the contracted position, opacity of one cell, appearance
    /// features]` per sample.
    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
        let dim = self.seg_input_dim();
        positions.par_chunks(BLOCK).zip(out.par_chunks_mut(BLOCK * dim)).for_each(|(p, o)| {
            let (sigma, feat) = plain(&self.tensors).appearance(&self.corners(p, true), self.act);
            self.write_seg_input(p, &sigma.as_vec(), &feat.as_vec(), o);
        });
    }

    fn save_state(&self) -> Vec<u8> {
        crate::state::write(&self.layout, &self.tensors, self.res, self.next_growth)
    }

    fn load_state(&mut self, bytes: &[u8]) -> Result<(), StateError> {
        let loaded = crate::state::read(&self.config, bytes)?;
        self.install(loaded.resolution, loaded.layout, loaded.values);
        self.next_growth = loaded.next_growth;
        Ok(())
    }

    fn num_parameters(&self) -> usize {
        self.layout.total()
    }

    fn parameters(&self) -> Vec<f32> {
        Self::flatten(&self.tensors.iter().map(|t| t.as_vec()).collect::<Vec<_>>())
    }

    fn set_parameters(&mut self, values: &[f32]) -> Result<(), StateError> {
        if values.len() != self.layout.total() {
            return Err(StateError::Mismatch {
                kind: crate::KIND.into(),
                reason: format!("{} parameter values given for {} parameters", values.len(), self.layout.total()),
            });
        }
        let mut rest = values;
        for (tensor, spec) in self.tensors.iter_mut().zip(&self.layout.specs) {
            let (head, tail) = rest.split_at(spec.len());
            *tensor = self.dev.tensor_from_vec(head.to_vec(), (spec.rows, spec.cols));
            rest = tail;
        }
        Ok(())
    }

    fn gradients(&self) -> Vec<f32> {
        Self::flatten(&self.grads)
    }

    fn frozen_pass(&self) -> Option<&dyn FrozenPass> {
        Some(self)
    }

    fn coarse_to_fine(&self) -> Option<&dyn CoarseToFine> {
        Some(self)
    }

    fn coarse_to_fine_mut(&mut self) -> Option<&mut dyn CoarseToFine> {
        Some(self)
    }
}

/// Stage 2 renders density, colour and the segmentation input at the same samples: one graph
/// gives all three, where the plain path interpolates the planes and lines twice.
impl FrozenPass for TensorfField {
    fn forward_with_seg_input(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        let dim = self.seg_input_dim();
        positions
            .par_chunks(BLOCK)
            .zip(directions.par_chunks(BLOCK))
            .zip(density.par_chunks_mut(BLOCK).zip(rgb.par_chunks_mut(BLOCK)))
            .zip(seg_input.par_chunks_mut(BLOCK * dim))
            .for_each(|(((p, dirs), (d, c)), o)| {
                let (sigma, feat, colour) =
                    plain(&self.tensors).forward(&self.corners(p, true), &self.view(dirs), self.act);
                let sigma = sigma.as_vec();
                d.copy_from_slice(&sigma[..p.len()]);
                for (dst, src) in c.iter_mut().zip(colour.as_vec().chunks_exact(3)) {
                    *dst = [src[0], src[1], src[2]];
                }
                self.write_seg_input(p, &sigma, &feat.as_vec(), o);
            });
    }
}

impl CoarseToFine for TensorfField {
    fn begin_step(&mut self, step: usize, total_steps: usize) -> bool {
        let schedule = &self.config.upsample_at;
        if self.next_growth < schedule.len() && step as f32 >= schedule[self.next_growth] * total_steps as f32 {
            self.next_growth += 1;
            let res = self.config.resolution_at(self.next_growth);
            self.grow_to(res);
            return true;
        }
        false
    }

    fn detail_fraction(&self) -> f32 {
        self.res.iter().sum::<usize>() as f32 / self.config.resolution.iter().sum::<usize>() as f32
    }
}
