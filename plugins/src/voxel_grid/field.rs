//! The runtime of the `voxel-grid` field.

use rayon::prelude::*;
use sos_core::camera::Vec3;
use sos_core::encoding::{positional_encoding, positional_encoding_dim, sh_basis, sh_coefficients};
use sos_core::nn::activation::{sigmoid, softplus};
use sos_core::nn::vector_math;
use sos_core::plugin::{state, CoarseToFine, FieldTape, FrozenPass, RadianceField, Regularized};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;

use super::grid::{Corners, Grid};
use super::sparse_adam::SparseAdam;
use super::VoxelGridConfig;

/// Samples per parallel task.
const CHUNK: usize = 4096;
/// Segmentation input beyond the positional encoding: voxel opacity and base colour.
const SEG_EXTRA: usize = 4;

/// A density + SH-colour voxel grid (see the module docs).
pub struct VoxelGridField {
    config: VoxelGridConfig,
    contraction: Contraction,
    grid: Grid,
    /// Present only while the field trains (made by the first backward pass or a restored
    /// optimiser state): three times the grid's memory that a frozen field does not need.
    training: Option<Training>,
    /// Softplus shift so that an empty grid has opacity `alpha_init` per voxel.
    shift: f32,
    /// World length of one voxel (converts per-voxel optical depth to world density).
    voxel_length: f32,
    n_sh: usize,
    /// Index into the upsampling schedule of the next growth.
    next_growth: usize,
}

impl VoxelGridField {
    /// An empty field (uniform low density, grey colour) at the initial resolution.
    pub fn new(config: VoxelGridConfig, contraction: Contraction, extent: &SceneExtent) -> Self {
        let n_sh = sh_coefficients(config.sh_degree);
        let channels = 1 + 3 * n_sh;
        let res = config.initial_resolution;
        let grid = Grid::new(res, channels, 0.0);
        let shift = (1.0 / (1.0 - config.alpha_init) - 1.0).ln();
        let voxel_length =
            extent.characteristic_length() / (config.resolution.iter().sum::<usize>() as f32 / 3.0 - 1.0);
        VoxelGridField { training: None, grid, config, contraction, shift, voxel_length, n_sh, next_growth: 0 }
    }

    /// Current vertices per axis.
    pub fn resolution(&self) -> [usize; 3] {
        self.grid.res
    }

    fn corners(&self, p: Vec3) -> Option<Corners> {
        self.grid.corners(self.contraction.to_unit(p))
    }

    /// Density and colour of one chunk of samples, and with `tape` their corners and the
    /// sigmoid of their raw density.
    fn forward_chunk(
        &self,
        p: &[Vec3],
        dirs: &[Vec3],
        d: &mut [f32],
        c: &mut [[f32; 3]],
        mut tape: Option<(&mut [Option<Corners>], &mut [f32])>,
    ) {
        let n_sh = self.n_sh;
        let mut feat = vec![0.0; self.grid.channels];
        let mut basis = vec![0.0; n_sh];
        // Pre-activations first, then each activation over the whole chunk, vectorised.
        // Outside the grid the density's pre-activation is −∞ (softplus 0); the colour is
        // zeroed after its sigmoid.
        let mut outside = Vec::new();
        for i in 0..p.len() {
            let corners = self.corners(p[i]);
            match corners {
                Some(corners) => {
                    self.grid.gather(&corners, &mut feat);
                    d[i] = feat[0] + self.shift;
                    sh_basis(self.config.sh_degree, dirs[i], &mut basis);
                    for k in 0..3 {
                        let coef = &feat[1 + k * n_sh..1 + (k + 1) * n_sh];
                        c[i][k] = coef.iter().zip(&basis).map(|(a, b)| a * b).sum();
                    }
                }
                None => {
                    d[i] = f32::NEG_INFINITY;
                    outside.push(i);
                }
            }
            if let Some((kept, _)) = tape.as_mut() {
                kept[i] = corners;
            }
        }
        if let Some((_, sigmoids)) = tape.as_mut() {
            sigmoids.copy_from_slice(d);
            vector_math::sigmoid_in_place(sigmoids);
        }
        self.activate_density(d);
        vector_math::sigmoid_in_place(c.as_flattened_mut());
        for i in outside {
            c[i] = [0.0; 3];
        }
    }

    /// Raw density plus the shift, in place, to density: `softplus(x) / voxel_length` (0 for
    /// −∞, a sample outside the grid).
    fn activate_density(&self, d: &mut [f32]) {
        vector_math::softplus_in_place(d);
        for v in d {
            *v /= self.voxel_length;
        }
    }

    fn grow_to(&mut self, res: [usize; 3]) {
        self.grid = self.grid.resampled(res);
        // The moments of the old vertices mean nothing for the new ones: training starts
        // afresh (made again by the next backward pass).
        self.training = None;
    }

    fn scheduled_resolution(&self, stage: usize) -> [usize; 3] {
        let n = self.config.upsample_at.len();
        let f = stage as f32 / n.max(1) as f32;
        let mut res = [0; 3];
        for a in 0..3 {
            let (lo, hi) = (self.config.initial_resolution[a] as f32, self.config.resolution[a] as f32);
            res[a] = (lo * (hi / lo).powf(f)).round() as usize;
        }
        res
    }
}

impl RadianceField for VoxelGridField {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        positions.par_chunks(CHUNK).zip(density.par_chunks_mut(CHUNK)).for_each(|(p, d)| {
            for (pi, di) in p.iter().zip(d.iter_mut()) {
                *di = match self.corners(*pi) {
                    Some(c) => self.grid.gather_first(&c) + self.shift,
                    None => f32::NEG_INFINITY,
                };
            }
            self.activate_density(d);
        });
    }

    fn forward(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
    ) -> FieldTape {
        let chunks = positions
            .par_chunks(CHUNK)
            .zip(directions.par_chunks(CHUNK))
            .zip(density.par_chunks_mut(CHUNK).zip(rgb.par_chunks_mut(CHUNK)));
        if !record {
            chunks.for_each(|((p, dirs), (d, c))| self.forward_chunk(p, dirs, d, c, None));
            return None;
        }
        let mut tape = Tape::new(positions.len());
        chunks.zip(tape.corners.par_chunks_mut(CHUNK).zip(tape.density_sigmoid.par_chunks_mut(CHUNK))).for_each(
            |(((p, dirs), (d, c)), (corners, sigmoids))| self.forward_chunk(p, dirs, d, c, Some((corners, sigmoids))),
        );
        tape.colour.copy_from_slice(rgb);
        Some(Box::new(tape))
    }

    fn backward(
        &mut self,
        positions: &[Vec3],
        directions: &[Vec3],
        tape: FieldTape,
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    ) {
        let ch = self.grid.channels;
        let n_sh = self.n_sh;
        let n = positions.len();
        // Pass 1, parallel over samples: the gradient of the interpolated channels, from what
        // the training forward pass kept (without its tape, or with another field's, that pass
        // runs again).
        let tape = tape.and_then(|t| t.downcast::<Tape>().ok()).filter(|t| t.corners.len() == n);
        let Tape { corners, density_sigmoid, colour } = match tape {
            Some(t) => *t,
            None => {
                let (mut d, mut c) = (vec![0.0; n], vec![[0.0; 3]; n]);
                let tape = self.forward(positions, directions, &mut d, &mut c, true);
                *tape.and_then(|t| t.downcast::<Tape>().ok()).expect("a recording forward pass returns its tape")
            }
        };
        let mut g = vec![0.0f32; n * ch];
        let bounds: Vec<f32> = corners
            .par_chunks(CHUNK)
            .zip(g.par_chunks_mut(CHUNK * ch))
            .enumerate()
            .map(|(chunk, (corners, g))| {
                let mut basis = vec![0.0; n_sh];
                // The largest |value| of the chunk, infinite for a NaN (see `Training::bound`).
                let mut bound = 0.0f32;
                for (j, c) in corners.iter().enumerate() {
                    let i = chunk * CHUNK + j;
                    if c.is_none() {
                        continue;
                    }
                    sh_basis(self.config.sh_degree, directions[i], &mut basis);
                    let gi = &mut g[j * ch..(j + 1) * ch];
                    // d softplus(x)/dx = sigmoid(x).
                    gi[0] = grad_density[i] * density_sigmoid[i] / self.voxel_length;
                    for k in 0..3 {
                        let s = colour[i][k];
                        let gx = grad_rgb[i][k] * s * (1.0 - s);
                        for l in 0..n_sh {
                            gi[1 + k * n_sh + l] = gx * basis[l];
                        }
                    }
                    bound = gi.iter().fold(bound, |b, v| b.max(if v.is_nan() { f32::INFINITY } else { v.abs() }));
                }
                bound
            })
            .collect();
        // Pass 2, parallel over vertex ranges: each task owns a slab of vertices and scatters
        // only the corners that fall in it, so no two tasks write the same gradient.
        let n_vertices = self.grid.n_vertices();
        let n_tasks = rayon::current_num_threads().max(1) * 2;
        let per_task = n_vertices.div_ceil(n_tasks);
        let training = Training::of(&mut self.training, &self.grid);
        let new_touched: Vec<Vec<u32>> = training
            .grads
            .par_chunks_mut(per_task * ch)
            .zip(training.touched_flag.par_chunks_mut(per_task))
            .enumerate()
            .map(|(task, (grads, flags))| {
                let lo = (task * per_task) as u32;
                let hi = lo + flags.len() as u32;
                let mut touched = Vec::new();
                for (i, c) in corners.iter().enumerate() {
                    let Some(c) = c else { continue };
                    // Corner indices grow with k, so a quick range test skips most samples.
                    if c.index[7] < lo || c.index[0] >= hi {
                        continue;
                    }
                    let gi = &g[i * ch..(i + 1) * ch];
                    for k in 0..8 {
                        let v = c.index[k];
                        if v < lo || v >= hi {
                            continue;
                        }
                        let local = (v - lo) as usize;
                        if !flags[local] {
                            flags[local] = true;
                            touched.push(v);
                        }
                        let w = c.weight[k];
                        let dst = &mut grads[local * ch..(local + 1) * ch];
                        for j in 0..ch {
                            dst[j] += w * gi[j];
                        }
                    }
                }
                touched
            })
            .collect();
        for t in new_touched {
            training.touched.extend(t);
        }
        // Each vertex sums at most 8 weighted (weight ≤ 1) values per sample.
        let bound = bounds.iter().fold(0.0f32, |b, &v| b.max(v));
        training.bound += 8.0 * n as f32 * bound;
    }

    fn step(&mut self, lr_factor: f32) {
        let ch = self.grid.channels;
        let mut lr = vec![self.config.lr_colour * lr_factor; ch];
        lr[0] = self.config.lr_density * lr_factor;
        let t = Training::of(&mut self.training, &self.grid);
        t.adam.step(&mut self.grid.data, &mut t.grads, &mut t.touched_flag, ch, &lr);
        t.touched.clear();
        t.bound = 0.0;
    }

    fn gradients_finite(&self) -> bool {
        let ch = self.grid.channels;
        self.training.as_ref().is_none_or(|t| {
            // Below the bound no sum can have overflowed: nothing to scan.
            t.bound < f32::MAX / 2.0
                || t.touched
                    .iter()
                    .all(|&v| t.grads[v as usize * ch..(v as usize + 1) * ch].iter().all(|g| g.is_finite()))
        })
    }

    fn discard_gradients(&mut self) {
        let ch = self.grid.channels;
        if let Some(t) = &mut self.training {
            for &v in &t.touched {
                let v = v as usize;
                t.grads[v * ch..(v + 1) * ch].fill(0.0);
                t.touched_flag[v] = false;
            }
            t.touched.clear();
            t.bound = 0.0;
        }
    }

    fn release_training_state(&mut self) {
        self.training = None;
    }

    fn seg_input_dim(&self) -> usize {
        positional_encoding_dim(3, self.config.seg_frequencies) + SEG_EXTRA
    }

    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
        let dim = self.seg_input_dim();
        let pe = dim - SEG_EXTRA;
        let ch = self.grid.channels;
        let c0 = 0.282_094_8f32;
        positions.par_chunks(CHUNK).zip(out.par_chunks_mut(CHUNK * dim)).for_each(|(p, o)| {
            let mut feat = vec![0.0; ch];
            for (i, pi) in p.iter().enumerate() {
                let row = &mut o[i * dim..(i + 1) * dim];
                let u = self.contraction.to_unit(*pi);
                // Scale the unit cube to [−π, π] so the octaves resolve voxel-sized detail.
                let x = u.map(|v| (2.0 * v - 1.0) * std::f32::consts::PI);
                positional_encoding(&x, self.config.seg_frequencies, &mut row[..pe]);
                match self.grid.corners(u) {
                    Some(c) => {
                        self.grid.gather(&c, &mut feat);
                        row[pe] = -(-softplus(feat[0] + self.shift)).exp_m1();
                        for k in 0..3 {
                            row[pe + 1 + k] = sigmoid(c0 * feat[1 + k * self.n_sh]);
                        }
                    }
                    None => row[pe..].fill(0.0),
                }
            }
        });
    }

    fn save_state(&self) -> Vec<u8> {
        let header = serde_json::json!({
            "res": self.grid.res,
            "channels": self.grid.channels,
            "next_growth": self.next_growth,
        });
        state::write(&header, &[&self.grid.data])
    }

    fn save_optimizer_state(&self) -> Vec<u8> {
        // Untrained since it was made or grown: the moments are zero, as a fresh state's are.
        match &self.training {
            Some(t) => t.adam.to_bytes(),
            None => Training::fresh_adam(&self.grid).to_bytes(),
        }
    }

    fn load_optimizer_state(&mut self, bytes: &[u8]) -> Result<(), sos_core::error::StateError> {
        Training::of(&mut self.training, &self.grid).adam.load_bytes("voxel-grid", bytes)
    }

    fn load_state(&mut self, bytes: &[u8]) -> Result<(), sos_core::error::StateError> {
        use sos_core::error::StateError;
        let kind = "voxel-grid";
        let malformed = |reason: String| StateError::Malformed { kind: kind.into(), reason };
        let (header, body) = state::read(kind, bytes)?;
        let res: [usize; 3] =
            serde_json::from_value(header["res"].clone()).map_err(|e| malformed(format!("resolution: {e}")))?;
        let channels =
            header["channels"].as_u64().ok_or_else(|| malformed("the header has no channel count".into()))? as usize;
        if channels != self.grid.channels {
            return Err(StateError::Mismatch {
                kind: kind.into(),
                reason: format!(
                    "it has {channels} channels per vertex but the config implies {} (sh_degree changed?)",
                    self.grid.channels
                ),
            });
        }
        if res.iter().any(|r| !super::RESOLUTION_RANGE.contains(r)) {
            return Err(malformed(format!("resolution {res:?}: each entry must be in {:?}", super::RESOLUTION_RANGE)));
        }
        let values = state::values(kind, body, res[0] * res[1] * res[2] * channels)?;
        self.grow_to(res);
        self.grid.data.copy_from_slice(&values);
        self.next_growth = header["next_growth"].as_u64().unwrap_or(0) as usize;
        Ok(())
    }

    fn num_parameters(&self) -> usize {
        self.grid.data.len()
    }

    fn parameters(&self) -> Vec<f32> {
        self.grid.data.clone()
    }

    fn first_non_finite_parameter(&self) -> Option<usize> {
        self.grid.data.iter().position(|v| !v.is_finite())
    }

    fn set_parameters(&mut self, values: &[f32]) -> Result<(), sos_core::error::StateError> {
        if values.len() != self.grid.data.len() {
            return Err(sos_core::error::StateError::Mismatch {
                kind: "voxel-grid".into(),
                reason: format!("{} parameter values given for {} grid values", values.len(), self.grid.data.len()),
            });
        }
        self.grid.data.copy_from_slice(values);
        Ok(())
    }

    fn gradients(&self) -> Vec<f32> {
        self.training.as_ref().map_or_else(|| vec![0.0; self.grid.data.len()], |t| t.grads.clone())
    }

    fn coarse_to_fine(&self) -> Option<&dyn CoarseToFine> {
        Some(self)
    }

    fn frozen_pass(&self) -> Option<&dyn FrozenPass> {
        Some(self)
    }

    fn coarse_to_fine_mut(&mut self) -> Option<&mut dyn CoarseToFine> {
        Some(self)
    }

    fn regularized(&mut self) -> Option<&mut dyn Regularized> {
        // Without weights there is nothing to add; the trainer then skips the pass.
        if self.config.tv_density == 0.0 && self.config.tv_colour == 0.0 {
            None
        } else {
            Some(self)
        }
    }
}

/// Gradients, the optimiser's moments and the vertices touched since the last step.
struct Training {
    grads: Vec<f32>,
    adam: SparseAdam,
    touched: Vec<u32>,
    touched_flag: Vec<bool>,
    /// An upper bound of every |gradient| accumulated since the last step (infinite or NaN
    /// when a term was): while it stays far below `f32::MAX`, every gradient is finite.
    bound: f32,
}

/// What a training forward pass keeps for the backward pass, per sample, so that it need not
/// interpolate the grid again: the corners and the activations' values.
struct Tape {
    corners: Vec<Option<Corners>>,
    /// `sigmoid(raw + shift)`, the slope of the density's softplus (0 outside the grid).
    density_sigmoid: Vec<f32>,
    /// The colour, the sigmoid of each channel's SH sum.
    colour: Vec<[f32; 3]>,
}

impl Tape {
    fn new(n: usize) -> Tape {
        Tape { corners: vec![None; n], density_sigmoid: vec![0.0; n], colour: vec![[0.0; 3]; n] }
    }
}

impl Training {
    /// The field's training state, made (zero) for `grid` when there is none.
    fn of<'a>(training: &'a mut Option<Training>, grid: &Grid) -> &'a mut Training {
        training.get_or_insert_with(|| Training {
            grads: vec![0.0; grid.data.len()],
            adam: Training::fresh_adam(grid),
            touched: Vec::new(),
            touched_flag: vec![false; grid.n_vertices()],
            bound: 0.0,
        })
    }

    fn fresh_adam(grid: &Grid) -> SparseAdam {
        SparseAdam::new(grid.data.len(), 0.9, 0.99)
    }

    fn touch(&mut self, vertex: u32) {
        if !self.touched_flag[vertex as usize] {
            self.touched_flag[vertex as usize] = true;
            self.touched.push(vertex);
        }
    }
}

impl CoarseToFine for VoxelGridField {
    fn begin_step(&mut self, step: usize, total_steps: usize) -> bool {
        let schedule = &self.config.upsample_at;
        if self.next_growth < schedule.len() && step as f32 >= schedule[self.next_growth] * total_steps as f32 {
            self.next_growth += 1;
            let res = self.scheduled_resolution(self.next_growth);
            self.grow_to(res);
            return true;
        }
        false
    }

    fn detail_fraction(&self) -> f32 {
        let now: usize = self.grid.res.iter().sum();
        let full: usize = self.config.resolution.iter().sum();
        now as f32 / full as f32
    }

    fn final_cells_across(&self) -> Option<usize> {
        self.config.resolution.iter().max().map(|&vertices| vertices.saturating_sub(1).max(1))
    }
}

/// The plain passes, but early termination in a frozen render without a density pass: the
/// density interpolates the same eight corners as the colour, so a density-only pass costs
/// about as much as the full one, while the samples behind each ray's opaque point are few
/// (the occupancy grid has already dropped empty space).
impl FrozenPass for VoxelGridField {
    fn early_termination_pass(&self) -> bool {
        false
    }
}

impl Regularized for VoxelGridField {
    fn regularize(&mut self) -> f64 {
        // Total variation between each touched vertex and its +x, +y, +z neighbours:
        // λ Σ (v_n − v)², gradient ±2λ(v_n − v). Neighbours become touched too.
        let (tv_d, tv_c) = (self.config.tv_density, self.config.tv_colour);
        if tv_d == 0.0 && tv_c == 0.0 {
            return 0.0;
        }
        let ch = self.grid.channels;
        let [rx, ry, rz] = self.grid.res;
        let strides = [1usize, rx, rx * ry];
        let mut value = 0.0f64;
        let t = Training::of(&mut self.training, &self.grid);
        let base: Vec<u32> = t.touched.clone();
        for v in base {
            let v = v as usize;
            let (x, y, z) = (v % rx, (v / rx) % ry, v / (rx * ry));
            let coord = [x, y, z];
            for a in 0..3 {
                if coord[a] + 1 >= [rx, ry, rz][a] {
                    continue;
                }
                let n = v + strides[a];
                t.touch(n as u32);
                for j in 0..ch {
                    let lambda = if j == 0 { tv_d } else { tv_c };
                    let d = self.grid.data[n * ch + j] - self.grid.data[v * ch + j];
                    value += (lambda * d * d) as f64;
                    t.grads[n * ch + j] += 2.0 * lambda * d;
                    t.grads[v * ch + j] -= 2.0 * lambda * d;
                    t.bound += 2.0 * (2.0 * lambda * d).abs();
                }
            }
        }
        value
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field() -> VoxelGridField {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let cfg = VoxelGridConfig {
            initial_resolution: [6, 5, 7],
            resolution: [12, 10, 14],
            upsample_at: vec![0.1, 0.5],
            sh_degree: 2,
            ..Default::default()
        };
        let mut f = VoxelGridField::new(cfg, Contraction::new(&extent), &extent);
        for (i, v) in f.grid.data.iter_mut().enumerate() {
            *v = ((i * 7919) % 1000) as f32 / 500.0 - 1.0;
        }
        f
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut f = field();
        let positions = vec![[0.1, -0.3, 0.5], [-0.7, 0.2, 0.05], [0.33, 0.61, -0.9]];
        let directions = vec![[0.0, 0.6, 0.8], [1.0, 0.0, 0.0], [0.48, -0.6, 0.64]];
        let gd = [0.7f32, -0.2, 0.4];
        let gc = [[0.3f32, -0.5, 0.9], [0.1, 0.2, -0.3], [-0.6, 0.4, 0.25]];
        let loss = |f: &VoxelGridField| -> f64 {
            let mut d = vec![0.0; 3];
            let mut c = vec![[0.0; 3]; 3];
            f.forward(&positions, &directions, &mut d, &mut c, false);
            (0..3).map(|i| (gd[i] * d[i] + (0..3).map(|k| gc[i][k] * c[i][k]).sum::<f32>()) as f64).sum()
        };
        f.backward(&positions, &directions, None, &gd, &gc);
        let grads = f.gradients();
        let mut checked = 0;
        for i in 0..f.grid.data.len() {
            if grads[i] == 0.0 {
                continue;
            }
            let h = 1e-2;
            let orig = f.grid.data[i];
            f.grid.data[i] = orig + h;
            let lp = loss(&f);
            f.grid.data[i] = orig - h;
            let lm = loss(&f);
            f.grid.data[i] = orig;
            let fd = (lp - lm) / (2.0 * h as f64);
            assert!((fd - grads[i] as f64).abs() < 1e-3 * (1.0 + fd.abs()), "param {i}: fd {fd} vs {}", grads[i]);
            checked += 1;
        }
        assert!(checked > 50, "only {checked} parameters had gradients");
    }

    #[test]
    fn the_forward_tape_gives_the_gradients_found_without_it() {
        let positions = vec![[0.1, -0.3, 0.5], [-0.7, 0.2, 0.05], [3.0, 0.0, 0.0], [0.33, 0.61, -0.9]];
        let directions = vec![[0.0, 0.6, 0.8], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.48, -0.6, 0.64]];
        let gd = [0.7f32, -0.2, 0.5, 0.4];
        let gc = [[0.3f32, -0.5, 0.9], [0.1, 0.2, -0.3], [1.0, 1.0, 1.0], [-0.6, 0.4, 0.25]];
        let (mut taped, mut fresh) = (field(), field());
        let (mut d, mut c) = (vec![0.0; 4], vec![[0.0; 3]; 4]);
        let tape = taped.forward(&positions, &directions, &mut d, &mut c, true);
        assert!(tape.is_some(), "a recording pass keeps a tape");
        taped.backward(&positions, &directions, tape, &gd, &gc);
        fresh.backward(&positions, &directions, None, &gd, &gc);
        let bits = |f: &VoxelGridField| f.gradients().iter().map(|g| g.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&taped), bits(&fresh));
        assert!(taped.gradients().iter().any(|&g| g != 0.0));
        // A tape for other samples is not used.
        let mut other = field();
        let tape = other.forward(&positions[..2], &directions[..2], &mut d[..2], &mut c[..2], true);
        other.backward(&positions, &directions, tape, &gd, &gc);
        assert_eq!(bits(&other), bits(&fresh));
    }

    #[test]
    fn gradients_that_overflow_when_summed_are_detected() {
        // Every sample at one point: each colour gradient is finite, their sum is not.
        let mut f = field();
        let positions = vec![[0.1, -0.3, 0.5]; 200];
        let directions = vec![[0.0, 0.6, 0.8]; 200];
        f.backward(&positions, &directions, None, &[0.0; 200], &[[3e38, 0.0, 0.0]; 200]);
        assert!(f.gradients().iter().any(|g| g.is_infinite()));
        assert!(!f.gradients_finite());
        // A NaN among finite values is not lost either.
        let mut f = field();
        f.backward(&positions[..3], &directions[..3], None, &[f32::NAN, 0.5, 0.5], &[[0.1, 0.2, 0.3]; 3]);
        assert!(!f.gradients_finite());
        // Ordinary gradients are finite.
        let mut f = field();
        f.backward(&positions[..3], &directions[..3], None, &[0.5; 3], &[[0.1, 0.2, 0.3]; 3]);
        assert!(f.gradients_finite());
    }

    #[test]
    fn non_finite_gradients_are_detected_and_discarded() {
        let mut f = field();
        let positions = vec![[0.1, -0.3, 0.5]];
        let directions = vec![[0.0, 0.6, 0.8]];
        f.backward(&positions, &directions, None, &[f32::NAN], &[[0.1, 0.2, 0.3]]);
        assert!(!f.gradients_finite());
        let before = f.grid.data.clone();
        f.discard_gradients();
        assert!(f.gradients_finite());
        f.step(1.0);
        assert_eq!(f.grid.data, before, "a discarded step changes nothing");
        assert!(f.gradients().iter().all(|&g| g == 0.0));
    }

    #[test]
    fn a_frozen_field_holds_no_training_state_and_trains_afresh_after_release() {
        let positions = vec![[0.1, -0.3, 0.5], [-0.7, 0.2, 0.05]];
        let directions = vec![[0.0, 0.6, 0.8], [1.0, 0.0, 0.0]];
        let (gd, gc) = ([0.7f32, -0.2], [[0.3f32, -0.5, 0.9], [0.1, 0.2, -0.3]]);
        let mut f = field();
        assert!(f.training.is_none(), "a new field has nothing to train yet");
        f.backward(&positions, &directions, None, &gd, &gc);
        f.step(1.0);
        assert!(f.training.is_some());
        f.release_training_state();
        assert!(f.training.is_none());
        assert!(f.gradients_finite() && f.gradients().iter().all(|&g| g == 0.0));
        // Training after the release matches a field that never trained, from the same values.
        let mut fresh = field();
        fresh.grid.data.clone_from(&f.grid.data);
        for g in [&mut f, &mut fresh] {
            g.backward(&positions, &directions, None, &gd, &gc);
            g.step(1.0);
        }
        assert_eq!(f.grid.data, fresh.grid.data);
        // An untrained field's optimiser state is a fresh one, and it loads back.
        let mut frozen = field();
        let bytes = frozen.save_optimizer_state();
        frozen.load_optimizer_state(&bytes).unwrap();
        assert_eq!(frozen.save_optimizer_state(), bytes);
    }

    #[test]
    fn state_round_trips_and_growth_follows_the_schedule() {
        let mut f = field();
        assert!(!f.begin_step(0, 100));
        assert!(f.begin_step(10, 100));
        assert!(f.resolution()[0] > 6);
        let bytes = f.save_state();
        let mut g = field();
        g.load_state(&bytes).unwrap();
        assert_eq!(g.grid.data, f.grid.data);
        assert!(matches!(g.load_state(&bytes[..bytes.len() - 3]), Err(sos_core::error::StateError::Truncated { .. })));
    }

    #[test]
    fn a_state_with_an_impossible_resolution_is_refused_not_indexed() {
        let mut f = field();
        let channels = f.grid.channels;
        // 2^32 per axis wraps to a count of 0 in the product; 1 and 0 leave no cell to interpolate.
        for res in [[1u64, 1, 1], [0, 0, 0], [1 << 32, 1 << 32, 1], [2000, 2, 2]] {
            let header = serde_json::json!({ "res": res, "channels": channels, "next_growth": 0 });
            let bytes = state::write(&header, &[&[]]);
            let err = f.load_state(&bytes).expect_err("an impossible resolution loads");
            assert!(
                matches!(err, sos_core::error::StateError::Malformed { .. }),
                "{res:?} gave {err:?}, not a malformed-state error"
            );
        }
        assert_eq!(f.resolution(), field().resolution(), "a refused state leaves the grid as it was");
    }
}
