//! The reference NeRF MLP on the core's dense layers: positional encoding, a ReLU trunk with
//! one input skip, a density head on the trunk, and a view-dependent colour branch.
//!
//! Per point, with `x` the (normalised) position and `d` the unit view direction:
//! `h = trunk(PE(x))` (ReLU after every layer, layer `skip` reads `[PE(x), h]`),
//! `σ = act(Linear(h → 1))`, `f = Linear(h → width)` (no activation),
//! `v = ReLU(Linear([f, PE(d)] → view_width))`, `rgb = sigmoid(Linear(v → 3))`.
//! Batches are processed in blocks of [`CHUNK`] rows so that every activation pass runs on
//! cache-resident data, with the GEMMs parallel inside each block.

use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::camera::Vec3;
use sos_core::encoding::{positional_encoding, positional_encoding_dim};
use sos_core::nn::activation::{sigmoid, softplus};
use sos_core::nn::{add_column_sums, Activation, Linear, MatRef, Mlp, MlpTape, Param};

/// Rows per block of the forward and backward passes.
pub const CHUNK: usize = 8192;

/// Largest density the activation returns: keeps `σ·δ` and its gradients finite however far
/// the raw output drifts.
pub const MAX_DENSITY: f32 = 1e5;

/// How the raw density output becomes a density.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DensityActivation {
    /// `max(raw, 0)` (the reference).
    Relu,
    /// `ln(1 + e^raw)`, never exactly zero, so a dead unit still receives gradient.
    Softplus,
}

impl DensityActivation {
    /// Density of a raw output: NaN maps to 0, the result is clamped to [`MAX_DENSITY`].
    #[inline]
    pub fn apply(self, raw: f32) -> f32 {
        let s = match self {
            DensityActivation::Relu => raw.max(0.0),
            DensityActivation::Softplus => softplus(raw),
        };
        // `f32::max` returns the other operand for NaN, so NaN becomes 0 here (`clamp` would
        // keep the NaN).
        #[allow(clippy::manual_clamp)]
        let clamped = s.max(0.0).min(MAX_DENSITY);
        clamped
    }

    /// `∂σ/∂raw` (0 where the clamp or the ReLU is active).
    #[inline]
    pub fn derivative(self, raw: f32) -> f32 {
        match self {
            DensityActivation::Relu => {
                if raw > 0.0 && raw < MAX_DENSITY {
                    1.0
                } else {
                    0.0
                }
            }
            DensityActivation::Softplus => {
                if raw >= MAX_DENSITY || raw.is_nan() {
                    0.0
                } else {
                    sigmoid(raw)
                }
            }
        }
    }
}

/// Sizes of a [`NerfMlp`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NerfShape {
    /// Input coordinates per point (3 for positions, 4 for NeRF++'s inverted sphere).
    pub in_dim: usize,
    /// Positional-encoding octaves of the position.
    pub pos_frequencies: usize,
    /// Positional-encoding octaves of the view direction.
    pub dir_frequencies: usize,
    /// Trunk layers.
    pub depth: usize,
    /// Trunk width.
    pub width: usize,
    /// Trunk layer that also reads the encoded input (`None`: no skip).
    pub skip: Option<usize>,
    /// Width of the view branch.
    pub view_width: usize,
}

impl NerfShape {
    /// Width of the encoded position.
    pub fn pe_dim(&self) -> usize {
        positional_encoding_dim(self.in_dim, self.pos_frequencies)
    }

    /// Width of the encoded direction.
    pub fn dir_dim(&self) -> usize {
        positional_encoding_dim(3, self.dir_frequencies)
    }
}

/// The network (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfMlp {
    /// `PE(x) → width × depth`, ReLU applied by [`NerfMlp`] after the last layer too.
    pub trunk: Mlp,
    /// `width → 1`.
    pub sigma: Linear,
    /// `width → width`.
    pub feature: Linear,
    /// `width + PE(d) → view_width`.
    pub view: Linear,
    /// `view_width → 3`.
    pub rgb: Linear,
    /// Input coordinates per point.
    pub in_dim: usize,
    /// Octaves of the position encoding.
    pub pos_frequencies: usize,
    /// Octaves of the direction encoding.
    pub dir_frequencies: usize,
    /// Density activation.
    pub density_activation: DensityActivation,
}

/// What one block of the forward pass keeps for the backward pass.
struct BlockTape {
    n: usize,
    trunk: MlpTape,
    /// `[n, width]`, after the final ReLU.
    h: Vec<f32>,
    /// `[n]` raw density.
    sigma_raw: Vec<f32>,
    /// `[n, width]`.
    feat: Vec<f32>,
    /// `[n, dir_dim]`.
    pe_d: Vec<f32>,
    /// `[n, view_width]`, after ReLU.
    hv: Vec<f32>,
    /// `[n, 3]`, after the sigmoid.
    rgb: Vec<f32>,
}

/// The tape of a whole [`NerfMlp::forward`] call.
pub struct NerfTape {
    blocks: Vec<BlockTape>,
}

/// Encodes `n` rows of `dim` coordinates into `[n, dim·(1 + 2L)]`, in parallel.
fn encode(x: &[f32], dim: usize, frequencies: usize) -> Vec<f32> {
    let width = positional_encoding_dim(dim, frequencies);
    let n = x.len() / dim;
    let mut out = vec![0.0; n * width];
    out.par_chunks_mut(1024 * width).zip(x.par_chunks(1024 * dim)).for_each(|(o, xs)| {
        for (row, xi) in o.chunks_exact_mut(width).zip(xs.chunks_exact(dim)) {
            positional_encoding(xi, frequencies, row);
        }
    });
    out
}

fn encode_dirs(dirs: &[Vec3], frequencies: usize) -> Vec<f32> {
    let flat: Vec<f32> = dirs.iter().flat_map(|d| d.iter().copied()).collect();
    encode(&flat, 3, frequencies)
}

/// Rows `[h_i, pe_i]` of the segmentation input from trunk activations `[n, w]` and encoded
/// positions `[n, pe_dim]`.
fn join_rows(h: &[f32], w: usize, pe: &[f32], pe_dim: usize, out: &mut [f32]) {
    out.par_chunks_mut(w + pe_dim).enumerate().for_each(|(i, r)| {
        r[..w].copy_from_slice(&h[i * w..(i + 1) * w]);
        r[w..].copy_from_slice(&pe[i * pe_dim..(i + 1) * pe_dim]);
    });
}

/// `Σ a_k b_k` in eight interleaved partial sums added in a fixed order (vectorises, and
/// rounds the same wherever the row sits).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = a8.remainder().iter().zip(b8.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in a8.zip(b8) {
        for k in 0..8 {
            lanes[k] += x[k] * y[k];
        }
    }
    lanes.iter().sum::<f32>() + tail
}

fn relu_in_place(x: &mut [f32]) {
    x.par_chunks_mut(1 << 14).for_each(|c| c.iter_mut().for_each(|v| *v = v.max(0.0)));
}

impl NerfMlp {
    /// A freshly initialised network (PyTorch's default `Linear` initialisation).
    pub fn new(shape: NerfShape, density_activation: DensityActivation, rng: &mut impl Rng) -> Self {
        let pe = shape.pe_dim();
        let mut dims = vec![pe];
        dims.extend(std::iter::repeat_n(shape.width, shape.depth));
        let trunk = Mlp::with_skip(&dims, shape.skip, Activation::Relu, Activation::Identity, rng);
        NerfMlp {
            trunk,
            sigma: Linear::new(shape.width, 1, rng),
            feature: Linear::new(shape.width, shape.width, rng),
            view: Linear::new(shape.width + shape.dir_dim(), shape.view_width, rng),
            rgb: Linear::new(shape.view_width, 3, rng),
            in_dim: shape.in_dim,
            pos_frequencies: shape.pos_frequencies,
            dir_frequencies: shape.dir_frequencies,
            density_activation,
        }
    }

    /// Trunk width (the width of [`NerfMlp::features`]).
    pub fn width(&self) -> usize {
        self.trunk.out_dim()
    }

    /// Width of the encoded position.
    pub fn pe_dim(&self) -> usize {
        positional_encoding_dim(self.in_dim, self.pos_frequencies)
    }

    /// Every parameter in a fixed order (checkpoints and Adam).
    pub fn params_mut(&mut self) -> Vec<&mut Param> {
        let mut p = self.trunk.params_mut();
        for l in [&mut self.sigma, &mut self.feature, &mut self.view, &mut self.rgb] {
            p.push(&mut l.weight);
            p.push(&mut l.bias);
        }
        p
    }

    /// Every parameter, read-only, in the order of [`NerfMlp::params_mut`].
    pub fn params(&self) -> Vec<&Param> {
        let mut p: Vec<&Param> = self.trunk.layers.iter().flat_map(|l| [&l.weight, &l.bias]).collect();
        for l in [&self.sigma, &self.feature, &self.view, &self.rgb] {
            p.push(&l.weight);
            p.push(&l.bias);
        }
        p
    }

    /// Number of trainable scalars.
    pub fn num_parameters(&self) -> usize {
        self.params().iter().map(|p| p.len()).sum()
    }

    /// Final trunk activations `[n, width]` of one block of encoded inputs.
    fn trunk_block(&self, pe: &[f32], n: usize) -> Vec<f32> {
        let mut h = self.trunk.infer(pe, n);
        relu_in_place(&mut h);
        h
    }

    /// Density only (the trunk and the density head), for `coords` `[n, in_dim]`.
    pub fn density(&self, coords: &[f32], out: &mut [f32]) {
        self.density_impl(coords, out, None);
    }

    /// [`NerfMlp::density`] that also writes the final trunk activations `[n, width]`, from
    /// which [`NerfMlp::colour_from_trunk`] finishes the forward pass without the trunk.
    pub fn density_with_trunk(&self, coords: &[f32], out: &mut [f32], trunk: &mut [f32]) {
        self.density_impl(coords, out, Some(trunk));
    }

    fn density_impl(&self, coords: &[f32], out: &mut [f32], mut trunk: Option<&mut [f32]>) {
        let (d, w) = (self.in_dim, self.width());
        for (block, (x, o)) in coords.chunks(CHUNK * d).zip(out.chunks_mut(CHUNK)).enumerate() {
            let n = o.len();
            let pe = encode(x, d, self.pos_frequencies);
            let h = self.trunk_block(&pe, n);
            let raw = self.raw_density(&h);
            for (o, r) in o.iter_mut().zip(&raw) {
                *o = self.density_activation.apply(*r);
            }
            if let Some(t) = trunk.as_deref_mut() {
                t[block * CHUNK * w..][..n * w].copy_from_slice(&h);
            }
        }
    }

    /// Colour of points whose final trunk activations are rows `rows[j]` of `trunk` (as
    /// [`NerfMlp::density_with_trunk`] wrote them), and with `features` their segmentation
    /// input of [`NerfMlp::features`] (which reads `coords`; pass none without it): the rest
    /// of [`NerfMlp::forward`], equal to its outputs.
    pub fn colour_from_trunk(
        &self,
        trunk: &[f32],
        rows: &[u32],
        coords: &[f32],
        dirs: &[Vec3],
        rgb: &mut [[f32; 3]],
        mut features: Option<&mut [f32]>,
    ) {
        let (d, w, pe_dim) = (self.in_dim, self.width(), self.pe_dim());
        let mut h = Vec::new();
        for (block, ((rows, dir), col)) in
            rows.chunks(CHUNK).zip(dirs.chunks(CHUNK)).zip(rgb.chunks_mut(CHUNK)).enumerate()
        {
            let n = rows.len();
            h.resize(n * w, 0.0);
            h.par_chunks_mut(w).zip(rows.par_iter()).for_each(|(out, &r)| {
                out.copy_from_slice(&trunk[r as usize * w..][..w]);
            });
            let pe_d = encode_dirs(dir, self.dir_frequencies);
            let (_, _, c) = self.view_branch(&h, &pe_d, n);
            for (i, col) in col.iter_mut().enumerate() {
                *col = [c[3 * i], c[3 * i + 1], c[3 * i + 2]];
            }
            if let Some(out) = features.as_deref_mut() {
                let row = w + pe_dim;
                let pe = encode(&coords[block * CHUNK * d..][..n * d], d, self.pos_frequencies);
                join_rows(&h, w, &pe, pe_dim, &mut out[block * CHUNK * row..][..n * row]);
            }
        }
    }

    /// The density layer on final trunk activations `h` `[n, width]`, before the activation.
    /// Each row is summed in a fixed order of its own: a one-column GEMM rounds a row
    /// differently depending on where it falls in the batch, and a frozen render's density
    /// pass and colour pass batch the same sample differently.
    fn raw_density(&self, h: &[f32]) -> Vec<f32> {
        let w = self.width();
        let (weight, bias) = (&self.sigma.weight.value, self.sigma.bias.value[0]);
        let mut out = vec![0.0; h.len() / w];
        out.par_chunks_mut(1024).zip(h.par_chunks(1024 * w)).for_each(|(out, h)| {
            for (o, row) in out.iter_mut().zip(h.chunks_exact(w)) {
                *o = bias + dot(row, weight);
            }
        });
        out
    }

    /// The view branch of one block: the feature layer, the view layer over
    /// `[feature, PE(d)]` and the colour layer, from final trunk activations `h` `[n, width]`.
    /// Returns `(feature, view activations, rgb)` for the tape.
    fn view_branch(&self, h: &[f32], pe_d: &[f32], n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let w = self.width();
        let mut feat = vec![0.0; n * w];
        self.feature.forward(h, n, &mut feat);
        let mut hv = vec![0.0; n * self.view.out_dim];
        let blocks_in = [MatRef::new(&feat, n, w), MatRef::new(pe_d, n, self.view.in_dim - w)];
        self.view.forward_blocks(&blocks_in, &mut hv, Activation::Relu);
        let mut c = vec![0.0; n * 3];
        self.rgb.forward_act(&hv, n, &mut c, Activation::Sigmoid);
        (feat, hv, c)
    }

    /// Segmentation input `[n, width + pe_dim]`: the final trunk activations followed by the
    /// encoded position (the reference's `[h, PE(x)]`).
    pub fn features(&self, coords: &[f32], out: &mut [f32]) {
        let d = self.in_dim;
        let (w, pe_dim) = (self.width(), self.pe_dim());
        let row = w + pe_dim;
        for (x, o) in coords.chunks(CHUNK * d).zip(out.chunks_mut(CHUNK * row)) {
            let n = x.len() / d;
            let pe = encode(x, d, self.pos_frequencies);
            let h = self.trunk_block(&pe, n);
            join_rows(&h, w, &pe, pe_dim, o);
        }
    }

    /// Density and colour; with `record`, a tape for [`NerfMlp::backward`].
    pub fn forward(
        &self,
        coords: &[f32],
        dirs: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
    ) -> Option<NerfTape> {
        self.forward_impl(coords, dirs, density, rgb, record, None)
    }

    /// Density, colour and the segmentation input of [`NerfMlp::features`] from one trunk
    /// pass, without a tape.
    pub fn forward_with_features(
        &self,
        coords: &[f32],
        dirs: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        features: &mut [f32],
    ) {
        self.forward_impl(coords, dirs, density, rgb, false, Some(features));
    }

    fn forward_impl(
        &self,
        coords: &[f32],
        dirs: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
        mut features: Option<&mut [f32]>,
    ) -> Option<NerfTape> {
        let d = self.in_dim;
        let (w, pe_dim) = (self.width(), self.pe_dim());
        let mut blocks = Vec::new();
        for (block, (((x, dir), dens), col)) in coords
            .chunks(CHUNK * d)
            .zip(dirs.chunks(CHUNK))
            .zip(density.chunks_mut(CHUNK))
            .zip(rgb.chunks_mut(CHUNK))
            .enumerate()
        {
            let n = dens.len();
            let pe = encode(x, d, self.pos_frequencies);
            let pe_d = encode_dirs(dir, self.dir_frequencies);
            let (mut h, trunk_tape) = if record {
                let (h, t) = self.trunk.forward(&pe, n);
                (h, Some(t))
            } else {
                (self.trunk.infer(&pe, n), None)
            };
            relu_in_place(&mut h);
            if let Some(out) = features.as_deref_mut() {
                let row = w + pe_dim;
                let out = &mut out[block * CHUNK * row..][..n * row];
                join_rows(&h, w, &pe, pe_dim, out);
            }
            let sigma_raw = self.raw_density(&h);
            let (feat, hv, c) = self.view_branch(&h, &pe_d, n);
            for i in 0..n {
                dens[i] = self.density_activation.apply(sigma_raw[i]);
                col[i] = [c[3 * i], c[3 * i + 1], c[3 * i + 2]];
            }
            if let Some(trunk) = trunk_tape {
                blocks.push(BlockTape { n, trunk, h, sigma_raw, feat, pe_d, hv, rgb: c });
            }
        }
        record.then_some(NerfTape { blocks })
    }

    /// Accumulates parameter gradients from `∂L/∂density` and `∂L/∂rgb` at the points of the
    /// forward pass that recorded `tape`.
    pub fn backward(&mut self, tape: &NerfTape, grad_density: &[f32], grad_rgb: &[[f32; 3]]) {
        let w = self.width();
        let mut start = 0;
        for b in &tape.blocks {
            let n = b.n;
            let gd = &grad_density[start..start + n];
            let gc = &grad_rgb[start..start + n];
            start += n;
            // rgb = sigmoid(raw).
            let mut g_rgb = vec![0.0f32; n * 3];
            for i in 0..n {
                for k in 0..3 {
                    let s = b.rgb[3 * i + k];
                    g_rgb[3 * i + k] = gc[i][k] * s * (1.0 - s);
                }
            }
            let mut g_hv = vec![0.0f32; n * self.rgb.in_dim];
            self.rgb.backward(&b.hv, &g_rgb, n, Some(&mut g_hv));
            // View branch: ReLU, then the block product over [feat, PE(d)].
            Activation::Relu.backward_bias(&b.hv, &mut g_hv, &mut self.view.bias.grad);
            let mut g_feat = vec![0.0f32; n * w];
            let blocks_in = [MatRef::new(&b.feat, n, w), MatRef::new(&b.pe_d, n, self.view.in_dim - w)];
            self.view.backward_blocks(
                &blocks_in,
                MatRef::new(&g_hv, n, self.view.out_dim),
                &mut [Some(&mut g_feat), None],
                false,
            );
            let mut g_h = vec![0.0f32; n * w];
            self.feature.backward(&b.h, &g_feat, n, Some(&mut g_h));
            // Density head, accumulated into ∂L/∂h.
            let g_sigma: Vec<f32> =
                (0..n).map(|i| gd[i] * self.density_activation.derivative(b.sigma_raw[i])).collect();
            add_column_sums(&g_sigma, &mut self.sigma.bias.grad);
            self.sigma.backward_blocks(
                &[MatRef::new(&b.h, n, w)],
                MatRef::new(&g_sigma, n, 1),
                &mut [Some(&mut g_h)],
                true,
            );
            // The trunk's final ReLU, then the trunk (identity output: g is the pre-activation grad).
            Activation::Relu.backward(&b.h, &mut g_h);
            self.trunk.backward(&b.trunk, &g_h, false);
        }
    }

    /// Whether every accumulated gradient is finite.
    pub fn gradients_finite(&self) -> bool {
        self.params().iter().all(|p| p.grad.iter().all(|g| g.is_finite()))
    }

    /// Zeros every accumulated gradient.
    pub fn zero_grad(&mut self) {
        self.params_mut().into_iter().for_each(Param::zero_grad);
    }

    /// GEMM multiply-adds of one forward pass over `n` points (for throughput accounting).
    pub fn forward_macs(&self, n: usize) -> usize {
        let layers = self.trunk.layers.iter().chain([&self.sigma, &self.feature, &self.view, &self.rgb]);
        layers.map(|l| n * l.in_dim * l.out_dim).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn tiny(act: DensityActivation) -> NerfMlp {
        let shape = NerfShape {
            in_dim: 3,
            pos_frequencies: 2,
            dir_frequencies: 1,
            depth: 4,
            width: 6,
            skip: Some(2),
            view_width: 5,
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut m = NerfMlp::new(shape, act, &mut rng);
        // Positive biases so that most ReLUs and the density are active.
        for p in m.params_mut() {
            if p.len() <= 6 {
                p.value.iter_mut().for_each(|v| *v = v.abs() + 0.1);
            }
        }
        m
    }

    /// L = Σ a_i σ_i + Σ b_ik rgb_ik against central differences, for every parameter.
    #[test]
    fn backward_matches_finite_differences() {
        for act in [DensityActivation::Relu, DensityActivation::Softplus] {
            let m0 = tiny(act);
            let n = 5;
            let coords: Vec<f32> = (0..n * 3).map(|i| ((i * 37 % 11) as f32 / 11.0 - 0.5) * 1.4).collect();
            let dirs: Vec<Vec3> = (0..n)
                .map(|i| {
                    let a = i as f32 * 0.9;
                    [a.cos() * 0.6, a.sin() * 0.6, 0.8]
                })
                .collect();
            let gd: Vec<f32> = (0..n).map(|i| 0.3 - 0.17 * i as f32).collect();
            let gc: Vec<[f32; 3]> = (0..n).map(|i| [0.5, -0.4 + 0.1 * i as f32, 0.2]).collect();
            let loss = |m: &NerfMlp| -> f64 {
                let mut d = vec![0.0; n];
                let mut c = vec![[0.0; 3]; n];
                m.forward(&coords, &dirs, &mut d, &mut c, false);
                (0..n).map(|i| (gd[i] * d[i]) as f64 + (0..3).map(|k| (gc[i][k] * c[i][k]) as f64).sum::<f64>()).sum()
            };
            let mut m = m0.clone();
            let mut d = vec![0.0; n];
            let mut c = vec![[0.0; 3]; n];
            let tape = m.forward(&coords, &dirs, &mut d, &mut c, true).unwrap();
            assert!(d.iter().any(|&x| x > 0.0), "some density must be active");
            m.backward(&tape, &gd, &gc);
            let grads: Vec<Vec<f32>> = m.params().iter().map(|p| p.grad.clone()).collect();
            let mut checked = 0;
            for (pi, g) in grads.iter().enumerate() {
                for j in 0..g.len() {
                    let h = 1e-3f32;
                    let mut mp = m0.clone();
                    mp.params_mut()[pi].value[j] += h;
                    let mut mm = m0.clone();
                    mm.params_mut()[pi].value[j] -= h;
                    let fd = (loss(&mp) - loss(&mm)) / (2.0 * h as f64);
                    let an = g[j] as f64;
                    assert!(
                        (fd - an).abs() <= 2e-3 + 2e-2 * fd.abs().max(an.abs()),
                        "{act:?} param {pi}[{j}]: analytic {an} vs fd {fd}"
                    );
                    if an != 0.0 {
                        checked += 1;
                    }
                }
            }
            assert!(checked > 100, "only {checked} non-zero gradients");
        }
    }

    /// A network small enough to run past one block of rows quickly: 3 trunk layers of 8 with a
    /// skip, a 4-wide view branch.
    fn small_shape() -> NerfShape {
        NerfShape {
            in_dim: 3,
            pos_frequencies: 3,
            dir_frequencies: 2,
            depth: 3,
            width: 8,
            skip: Some(2),
            view_width: 4,
        }
    }

    #[test]
    fn forward_density_and_features_agree_across_blocks() {
        let shape = small_shape();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let m = NerfMlp::new(shape, DensityActivation::Softplus, &mut rng);
        let n = CHUNK + 19;
        let coords: Vec<f32> = (0..n * 3).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let dirs: Vec<Vec3> = (0..n).map(|_| [0.0, 0.0, 1.0]).collect();
        let (mut d1, mut d2) = (vec![0.0; n], vec![0.0; n]);
        let mut c = vec![[0.0; 3]; n];
        let tape = m.forward(&coords, &dirs, &mut d1, &mut c, true).unwrap();
        assert_eq!(tape.blocks.len(), 2);
        m.density(&coords, &mut d2);
        for (a, b) in d1.iter().zip(&d2) {
            assert!((a - b).abs() <= 1e-5 * (1.0 + a.abs()));
        }
        let mut f = vec![0.0; n * (8 + shape.pe_dim())];
        m.features(&coords, &mut f);
        let row = 8 + shape.pe_dim();
        assert!((f[row * (n - 1) + 8] - coords[3 * (n - 1)]).abs() < 1e-7, "PE starts with x");
        assert!(f.iter().all(|v| v.is_finite()));
        // One fused pass gives the same density, colour and segmentation input.
        let (mut d3, mut c3, mut f3) = (vec![0.0; n], vec![[0.0; 3]; n], vec![f32::NAN; f.len()]);
        m.forward_with_features(&coords, &dirs, &mut d3, &mut c3, &mut f3);
        let (mut d4, mut c4) = (vec![0.0; n], vec![[0.0; 3]; n]);
        assert!(m.forward(&coords, &dirs, &mut d4, &mut c4, false).is_none());
        assert_eq!((d3, c3, f3), (d4, c4, f));
    }

    /// Density with the trunk kept, then colour from chosen trunk rows, equals a forward pass
    /// over those points bit for bit (rows from one batch serve another batch's order).
    #[test]
    fn colour_from_kept_trunk_rows_matches_forward() {
        let shape = small_shape();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let m = NerfMlp::new(shape, DensityActivation::Softplus, &mut rng);
        let n = 2 * CHUNK + 37;
        let coords: Vec<f32> = (0..n * 3).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let dirs: Vec<Vec3> = (0..n).map(|_| [rng.gen_range(-1.0..1.0), 0.6, 0.8]).collect();
        let mut density = vec![0.0; n];
        let mut trunk = vec![f32::NAN; n * 8];
        m.density_with_trunk(&coords, &mut density, &mut trunk);
        let mut plain = vec![0.0; n];
        m.density(&coords, &mut plain);
        assert_eq!(density, plain);
        // Every third point, last first, more than one block of them.
        let rows: Vec<u32> = (0..n as u32).rev().filter(|i| i % 3 != 1).collect();
        let k = rows.len();
        assert!(k > CHUNK);
        let sub_coords: Vec<f32> = rows.iter().flat_map(|&i| coords[3 * i as usize..][..3].to_vec()).collect();
        let sub_dirs: Vec<Vec3> = rows.iter().map(|&i| dirs[i as usize]).collect();
        let row = 8 + shape.pe_dim();
        let (mut d, mut c, mut f) = (vec![0.0; k], vec![[0.0; 3]; k], vec![0.0; k * row]);
        m.forward_with_features(&sub_coords, &sub_dirs, &mut d, &mut c, &mut f);
        let (mut c2, mut f2) = (vec![[0.0; 3]; k], vec![f32::NAN; k * row]);
        m.colour_from_trunk(&trunk, &rows, &sub_coords, &sub_dirs, &mut c2, Some(&mut f2));
        let d2: Vec<f32> = rows.iter().map(|&i| density[i as usize]).collect();
        assert_eq!((d2, &c2, f2), (d, &c, f));
        let mut c3 = vec![[0.0; 3]; k];
        m.colour_from_trunk(&trunk, &rows, &[], &sub_dirs, &mut c3, None);
        assert_eq!(c3, c);
    }

    #[test]
    fn density_activation_is_guarded() {
        for act in [DensityActivation::Relu, DensityActivation::Softplus] {
            assert_eq!(act.apply(f32::NAN), 0.0);
            assert_eq!(act.apply(f32::INFINITY), MAX_DENSITY);
            assert_eq!(act.apply(f32::NEG_INFINITY), 0.0);
            assert_eq!(act.derivative(f32::NAN), 0.0);
            assert!(act.apply(3.0) > 2.9);
        }
    }
}
