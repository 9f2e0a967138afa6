//! The runtime of the `nerf++` field: per level (coarse, fine, paired by [`CoarseFine`]) a
//! foreground and an optional background [`NerfMlp`], each point routed to one of them.

use std::any::Any;

use rand::SeedableRng;
use sos_core::camera::Vec3;
use sos_core::encoding::{positional_encoding, positional_encoding_dim};
use sos_core::nn::Adam;
use sos_core::plugin::{FieldTape, RadianceField};
use sos_core::render::contraction::Contraction;

use super::NerfPpConfig;
use crate::nerf::{CoarseFine, Level, NerfConfig, NerfMlp, NerfTape};

/// How world points map to the networks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Space {
    /// Bounded or forward-facing scene: one network on the unit-cube mapping scaled to
    /// `[−1, 1]³`, densities in world units.
    Cube(Contraction),
    /// Unbounded scene: the foreground sphere normalised to the unit sphere, and (when
    /// `background`) the inverted-sphere background beyond it.
    Sphere {
        /// Sphere centre.
        center: Vec3,
        /// Sphere radius.
        radius: f32,
        /// Whether the background network exists.
        background: bool,
    },
}

/// Where one point goes.
enum Route {
    /// Foreground network: input coordinates, density scale, contracted position.
    Fg([f32; 3], f32, [f32; 3]),
    /// Background network: `(x/r, 1/r)`, density scale, contracted position.
    Bg([f32; 4], f32, [f32; 3]),
    /// Beyond the sphere without a background: empty.
    Empty([f32; 3]),
}

impl Space {
    fn route(&self, p: Vec3) -> Route {
        match *self {
            Space::Cube(c) => {
                let u = c.to_unit(p);
                let x = u.map(|v| 2.0 * v - 1.0);
                Route::Fg(x, 1.0, x)
            }
            Space::Sphere { center, radius, background } => {
                let x = [(p[0] - center[0]) / radius, (p[1] - center[1]) / radius, (p[2] - center[2]) / radius];
                let r = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
                if r <= 1.0 {
                    return Route::Fg(x, 1.0 / radius, x);
                }
                let inv = 1.0 / r;
                let dir = x.map(|v| v * inv);
                let contracted = dir.map(|v| v * (2.0 - inv));
                if background {
                    Route::Bg([dir[0], dir[1], dir[2], inv], inv * inv / radius, contracted)
                } else {
                    Route::Empty(contracted)
                }
            }
        }
    }
}

/// Points of one batch split between the two networks.
#[derive(Default)]
struct Split {
    fg_idx: Vec<u32>,
    fg_coords: Vec<f32>,
    fg_scale: Vec<f32>,
    bg_idx: Vec<u32>,
    bg_coords: Vec<f32>,
    bg_scale: Vec<f32>,
}

/// What [`NerfPpNet::forward`] records.
struct PpTape {
    split: Split,
    fg: Option<NerfTape>,
    bg: Option<NerfTape>,
}

/// One level of the `nerf++` field: foreground and optional background network.
pub struct NerfPpNet {
    /// Foreground network (3-D input).
    pub fg: NerfMlp,
    /// Background network (4-D inverted-sphere input).
    pub bg: Option<NerfMlp>,
    fg_adam: Adam,
    bg_adam: Adam,
    space: Space,
}

fn gather<T: Copy>(v: &[T], idx: &[u32]) -> Vec<T> {
    idx.iter().map(|&i| v[i as usize]).collect()
}

/// The inverse of [`gather`]: `out[idx[j]] = values[j]`.
fn scatter<T: Copy>(values: &[T], idx: &[u32], out: &mut [T]) {
    for (&i, &v) in idx.iter().zip(values) {
        out[i as usize] = v;
    }
}

impl NerfPpNet {
    /// A freshly initialised level.
    pub fn new(config: &NerfPpConfig, space: Space, seed: u64) -> Self {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let fg = NerfMlp::new(config.shape(3), config.density_activation, &mut rng);
        let bg = matches!(space, Space::Sphere { background: true, .. })
            .then(|| NerfMlp::new(config.shape(4), config.density_activation, &mut rng));
        NerfPpNet { fg, bg, fg_adam: Adam::new(config.lr), bg_adam: Adam::new(config.lr), space }
    }

    fn split(&self, positions: &[Vec3]) -> Split {
        let mut s = Split::default();
        for (i, p) in positions.iter().enumerate() {
            match self.space.route(*p) {
                Route::Fg(x, scale, _) => {
                    s.fg_idx.push(i as u32);
                    s.fg_coords.extend_from_slice(&x);
                    s.fg_scale.push(scale);
                }
                Route::Bg(x, scale, _) => {
                    s.bg_idx.push(i as u32);
                    s.bg_coords.extend_from_slice(&x);
                    s.bg_scale.push(scale);
                }
                Route::Empty(_) => {}
            }
        }
        s
    }

    /// The networks with their points: (network, indices, coordinates, density scales).
    fn parts<'a>(&'a self, s: &'a Split) -> Vec<Part<'a>> {
        let mut parts = vec![(&self.fg, &s.fg_idx[..], &s.fg_coords[..], &s.fg_scale[..])];
        if let Some(bg) = &self.bg {
            parts.push((bg, &s.bg_idx[..], &s.bg_coords[..], &s.bg_scale[..]));
        }
        parts
    }
}

impl Level for NerfPpNet {
    fn mlps(&self) -> Vec<&NerfMlp> {
        std::iter::once(&self.fg).chain(self.bg.as_ref()).collect()
    }

    fn mlps_mut(&mut self) -> Vec<&mut NerfMlp> {
        std::iter::once(&mut self.fg).chain(self.bg.as_mut()).collect()
    }
}

/// One network of a split batch: the network, its samples' indices, their coordinates and
/// density scales.
type Part<'a> = (&'a NerfMlp, &'a [u32], &'a [f32], &'a [f32]);

/// Writes one network's density (times its sample's density scale) and colour, one per sample
/// of `idx`, into those samples' places of `density` and `rgb`.
fn scatter_density_colour(
    idx: &[u32],
    scale: &[f32],
    d: &[f32],
    c: &[[f32; 3]],
    density: &mut [f32],
    rgb: &mut [[f32; 3]],
) {
    for (j, &i) in idx.iter().enumerate() {
        density[i as usize] = d[j] * scale[j];
    }
    scatter(c, idx, rgb);
}

impl NerfPpNet {
    /// Writes the trunk part of `net`'s segmentation input rows `features` (one per sample of
    /// `idx`) into those samples' rows of `out` `[n, seg_input_dim]`.
    fn scatter_features(&self, net: &NerfMlp, idx: &[u32], features: &[f32], out: &mut [f32]) {
        let (w, dim) = (self.fg.width(), self.seg_input_dim());
        let row = net.width() + net.pe_dim();
        for (j, &i) in idx.iter().enumerate() {
            out[i as usize * dim..i as usize * dim + w].copy_from_slice(&features[j * row..j * row + w]);
        }
    }

    /// Writes the encoded contracted position after the trunk part of each row of `out`.
    fn encode_positions(&self, positions: &[Vec3], out: &mut [f32]) {
        let (w, dim) = (self.fg.width(), self.seg_input_dim());
        for (i, p) in positions.iter().enumerate() {
            let contracted = match self.space.route(*p) {
                Route::Fg(_, _, c) | Route::Bg(_, _, c) | Route::Empty(c) => c,
            };
            positional_encoding(&contracted, self.fg.pos_frequencies, &mut out[i * dim + w..(i + 1) * dim]);
        }
    }
}

impl RadianceField for NerfPpNet {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        density.fill(0.0);
        let s = self.split(positions);
        for (net, idx, coords, scale) in self.parts(&s) {
            let mut d = vec![0.0; idx.len()];
            net.density(coords, &mut d);
            for ((&i, v), k) in idx.iter().zip(d).zip(scale) {
                density[i as usize] = v * k;
            }
        }
    }

    fn forward(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
    ) -> FieldTape {
        density.fill(0.0);
        rgb.fill([0.0; 3]);
        let s = self.split(positions);
        let mut tapes = Vec::new();
        for (net, idx, coords, scale) in self.parts(&s) {
            let (mut d, mut c) = (vec![0.0; idx.len()], vec![[0.0; 3]; idx.len()]);
            tapes.push(net.forward(coords, &gather(directions, idx), &mut d, &mut c, record));
            scatter_density_colour(idx, scale, &d, &c, density, rgb);
        }
        if !record {
            return None;
        }
        let mut tapes = tapes.into_iter();
        let fg = tapes.next().flatten();
        let bg = tapes.next().flatten();
        Some(Box::new(PpTape { split: s, fg, bg }))
    }

    fn backward(
        &mut self,
        positions: &[Vec3],
        directions: &[Vec3],
        tape: FieldTape,
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    ) {
        let tape = match tape.and_then(|t| (t as Box<dyn Any>).downcast::<PpTape>().ok()) {
            Some(t) => *t,
            None => {
                let n = positions.len();
                let (mut d, mut c) = (vec![0.0; n], vec![[0.0; 3]; n]);
                let t = self.forward(positions, directions, &mut d, &mut c, true);
                *(t.expect("recording forward") as Box<dyn Any>).downcast::<PpTape>().expect("own tape")
            }
        };
        let PpTape { split, fg, bg } = tape;
        let grads = |idx: &[u32], scale: &[f32]| -> (Vec<f32>, Vec<[f32; 3]>) {
            let gd = idx.iter().zip(scale).map(|(&i, k)| grad_density[i as usize] * k).collect();
            (gd, gather(grad_rgb, idx))
        };
        if let Some(t) = fg {
            let (gd, gc) = grads(&split.fg_idx, &split.fg_scale);
            self.fg.backward(&t, &gd, &gc);
        }
        if let (Some(t), Some(net)) = (bg, self.bg.as_mut()) {
            let (gd, gc) = grads(&split.bg_idx, &split.bg_scale);
            net.backward(&t, &gd, &gc);
        }
    }

    fn step(&mut self, lr_factor: f32) {
        let mut p = self.fg.params_mut();
        self.fg_adam.step(&mut p, lr_factor);
        if let Some(bg) = self.bg.as_mut() {
            let mut p = bg.params_mut();
            self.bg_adam.step(&mut p, lr_factor);
        }
    }

    crate::nerf::network_methods!();

    fn seg_input_dim(&self) -> usize {
        self.fg.width() + positional_encoding_dim(3, self.fg.pos_frequencies)
    }

    fn seg_input(&self, positions: &[Vec3], out: &mut [f32]) {
        let s = self.split(positions);
        out.fill(0.0);
        for (net, idx, coords, _) in self.parts(&s) {
            let mut f = vec![0.0; idx.len() * (net.width() + net.pe_dim())];
            net.features(coords, &mut f);
            self.scatter_features(net, idx, &f, out);
        }
        self.encode_positions(positions, out);
    }

    fn frozen_pass(&self) -> Option<&dyn sos_core::plugin::FrozenPass> {
        Some(self)
    }
}

impl sos_core::plugin::FrozenPass for NerfPpNet {
    fn forward_with_seg_input(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        seg_input: &mut [f32],
    ) {
        density.fill(0.0);
        rgb.fill([0.0; 3]);
        seg_input.fill(0.0);
        let s = self.split(positions);
        for (net, idx, coords, scale) in self.parts(&s) {
            let (mut d, mut c) = (vec![0.0; idx.len()], vec![[0.0; 3]; idx.len()]);
            let mut f = vec![0.0; idx.len() * (net.width() + net.pe_dim())];
            net.forward_with_features(coords, &gather(directions, idx), &mut d, &mut c, &mut f);
            scatter_density_colour(idx, scale, &d, &c, density, rgb);
            self.scatter_features(net, idx, &f, seg_input);
        }
        self.encode_positions(positions, seg_input);
    }

    fn density_state_dim(&self) -> usize {
        // Both networks' trunks are `width` wide (the segmentation input relies on it too).
        self.fg.width()
    }

    fn density_with_state(&self, positions: &[Vec3], density: &mut [f32], state: &mut [f32]) {
        let w = self.fg.width();
        density.fill(0.0);
        // Points beyond the sphere without a background keep a zero trunk, as in their
        // segmentation input.
        state.fill(0.0);
        let s = self.split(positions);
        for (net, idx, coords, scale) in self.parts(&s) {
            let (mut d, mut h) = (vec![0.0; idx.len()], vec![0.0; idx.len() * w]);
            net.density_with_trunk(coords, &mut d, &mut h);
            for (j, &i) in idx.iter().enumerate() {
                density[i as usize] = d[j] * scale[j];
                state[i as usize * w..][..w].copy_from_slice(&h[j * w..][..w]);
            }
        }
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
        rgb.fill([0.0; 3]);
        let s = self.split(positions);
        for (net, idx, _, _) in self.parts(&s) {
            let mut c = vec![[0.0; 3]; idx.len()];
            net.colour_from_trunk(state, &gather(rows, idx), &[], &gather(directions, idx), &mut c, None);
            scatter(&c, idx, rgb);
        }
        if let Some(seg) = seg_input {
            let (w, dim) = (self.fg.width(), self.seg_input_dim());
            for (out, &r) in seg.chunks_exact_mut(dim).zip(rows) {
                out[..w].copy_from_slice(&state[r as usize * w..][..w]);
            }
            self.encode_positions(positions, seg);
        }
    }
}

/// The `nerf++` field: fine and coarse levels.
pub type NerfPpField = CoarseFine<NerfPpNet>;

impl CoarseFine<NerfPpNet> {
    /// Builds both levels.
    pub fn new(config: NerfPpConfig, space: Space, seed: u64) -> Self {
        CoarseFine::build(seed, NerfConfig::from(&config).sampling(), |seed| NerfPpNet::new(&config, space, seed))
    }

    /// Whether a background network exists.
    pub fn has_background(&self) -> bool {
        self.fine().bg.is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sos_core::plugin::FrozenPass;
    use sos_core::scene::SceneExtent;

    fn tiny() -> NerfPpConfig {
        NerfPpConfig {
            depth: 3,
            width: 8,
            skip: 2,
            view_width: 4,
            pos_frequencies: 2,
            dir_frequencies: 1,
            density_activation: crate::nerf::DensityActivation::Softplus,
            ..Default::default()
        }
    }

    fn sphere_space(background: bool) -> Space {
        Space::Sphere { center: [1.0, 0.0, 0.0], radius: 2.0, background }
    }

    #[test]
    fn routes_points_by_the_sphere_and_scales_density() {
        let s = sphere_space(true);
        match s.route([2.0, 0.0, 0.0]) {
            Route::Fg(x, k, c) => {
                assert_eq!(x, [0.5, 0.0, 0.0]);
                assert_eq!(c, x);
                assert!((k - 0.5).abs() < 1e-7);
            }
            _ => panic!("inside the sphere"),
        }
        match s.route([1.0, 8.0, 0.0]) {
            Route::Bg(x, k, c) => {
                // x = (0, 4, 0): r = 4.
                assert_eq!(x, [0.0, 1.0, 0.0, 0.25]);
                assert!((k - 0.0625 / 2.0).abs() < 1e-7);
                assert!((c[1] - 1.75).abs() < 1e-6, "mip-NeRF 360 contraction {c:?}");
            }
            _ => panic!("outside the sphere"),
        }
        assert!(matches!(sphere_space(false).route([1.0, 8.0, 0.0]), Route::Empty(_)));
    }

    /// The field's gradients through both networks and the density scales, against central
    /// differences of `L = Σ a·σ + Σ b·rgb` over every parameter.
    #[test]
    fn backward_matches_finite_differences() {
        let cfg = tiny();
        let positions = vec![[1.5, 0.3, -0.4], [0.2, -0.9, 0.7], [1.0, 6.0, 2.0], [-9.0, 1.0, 3.0]];
        let dirs = vec![[0.0, 0.6, 0.8], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]];
        let gd = [0.7f32, -0.4, 25.0, -30.0];
        let gc = [[0.3f32, -0.5, 0.9], [0.1, 0.2, -0.3], [-0.6, 0.4, 0.25], [0.2, 0.2, -0.1]];
        let loss = |f: &NerfPpNet| -> f64 {
            let (mut d, mut c) = (vec![0.0; 4], vec![[0.0; 3]; 4]);
            f.forward(&positions, &dirs, &mut d, &mut c, false);
            (0..4).map(|i| (gd[i] * d[i]) as f64 + (0..3).map(|k| (gc[i][k] * c[i][k]) as f64).sum::<f64>()).sum()
        };
        let mut f = NerfPpNet::new(&cfg, sphere_space(true), 5);
        let (mut d, mut c) = (vec![0.0; 4], vec![[0.0; 3]; 4]);
        let tape = f.forward(&positions, &dirs, &mut d, &mut c, true);
        assert!(d.iter().all(|&v| v > 0.0));
        f.backward(&positions, &dirs, tape, &gd, &gc);
        let mut checked = 0;
        for net in 0..2 {
            let n_params = f.mlps()[net].params().len();
            for pi in 0..n_params {
                let g = f.mlps()[net].params()[pi].grad.clone();
                for j in 0..g.len() {
                    let h = 1e-3f32;
                    let mut plus = NerfPpNet::new(&cfg, sphere_space(true), 5);
                    plus.mlps_mut()[net].params_mut()[pi].value[j] += h;
                    let mut minus = NerfPpNet::new(&cfg, sphere_space(true), 5);
                    minus.mlps_mut()[net].params_mut()[pi].value[j] -= h;
                    let fd = (loss(&plus) - loss(&minus)) / (2.0 * h as f64);
                    let an = g[j] as f64;
                    assert!(
                        (fd - an).abs() <= 3e-3 + 2e-2 * fd.abs().max(an.abs()),
                        "net {net} param {pi}[{j}]: {an} vs fd {fd}"
                    );
                    checked += usize::from(an != 0.0);
                }
            }
        }
        assert!(checked > 200, "{checked}");
    }

    #[test]
    fn bounded_scenes_get_no_background_and_state_round_trips() {
        let bounded = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let f = NerfPpField::new(tiny(), Space::Cube(Contraction::new(&bounded)), 0);
        assert!(!f.has_background());
        let unbounded = NerfPpField::new(tiny(), sphere_space(true), 1);
        assert!(unbounded.has_background());
        assert_eq!(unbounded.seg_input_dim(), 8 + 15);
        let bytes = unbounded.save_state();
        let mut other = NerfPpField::new(tiny(), sphere_space(true), 2);
        other.load_state(&bytes).unwrap();
        assert_eq!(other.save_state(), bytes);
        let mut no_bg = NerfPpField::new(tiny(), sphere_space(false), 2);
        assert!(no_bg.load_state(&bytes).is_err(), "a state with background networks needs them");
        let mut seg = vec![0.0; 2 * 23];
        unbounded.seg_input(&[[1.0, 0.0, 0.0], [30.0, 0.0, 0.0]], &mut seg);
        assert!(seg.iter().all(|v| v.is_finite()));
        // Contracted x of the far point is (2 − 1/r) ≈ 1.93 along +x.
        assert!((seg[23 + 8] - (2.0 - 2.0 / 29.0)).abs() < 1e-5);
    }

    /// One fused pass gives what `forward` and `seg_input` give, in both networks and outside.
    #[test]
    fn fused_forward_matches_the_separate_passes() {
        let f = NerfPpNet::new(&tiny(), sphere_space(false), 3);
        let g = NerfPpNet::new(&tiny(), sphere_space(true), 3);
        let positions = vec![[1.5, 0.3, -0.4], [1.0, 6.0, 2.0], [0.2, -0.9, 0.7], [-9.0, 1.0, 3.0]];
        let dirs = vec![[0.0, 0.6, 0.8], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [-0.6, 0.0, 0.8]];
        for net in [&f, &g] {
            let dim = net.seg_input_dim();
            let (mut d, mut c, mut seg) = (vec![0.0; 4], vec![[0.0; 3]; 4], vec![0.0; 4 * dim]);
            net.forward(&positions, &dirs, &mut d, &mut c, false);
            net.seg_input(&positions, &mut seg);
            let (mut d2, mut c2, mut seg2) = (vec![f32::NAN; 4], vec![[f32::NAN; 3]; 4], vec![f32::NAN; 4 * dim]);
            net.forward_with_seg_input(&positions, &dirs, &mut d2, &mut c2, &mut seg2);
            assert_eq!((d2, c2, seg2), (d, c, seg));
        }
    }

    /// Density with the trunks kept, then colour and segmentation input from chosen rows,
    /// equal the fused pass over those points (empty points beyond the sphere included).
    #[test]
    fn colour_from_the_density_pass_state_matches_the_fused_pass() {
        let f = NerfPpNet::new(&tiny(), sphere_space(false), 3);
        let g = NerfPpNet::new(&tiny(), sphere_space(true), 3);
        let positions = vec![[1.5, 0.3, -0.4], [1.0, 6.0, 2.0], [0.2, -0.9, 0.7], [-9.0, 1.0, 3.0], [2.0, 0.5, 0.1]];
        let dirs = [[0.0, 0.6, 0.8], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [-0.6, 0.0, 0.8], [0.0, 0.0, 1.0]];
        let rows: Vec<u32> = vec![4, 1, 3, 0];
        let sub_p: Vec<Vec3> = rows.iter().map(|&r| positions[r as usize]).collect();
        let sub_d: Vec<Vec3> = rows.iter().map(|&r| dirs[r as usize]).collect();
        for net in [&f, &g] {
            let (dim, w) = (net.seg_input_dim(), net.density_state_dim());
            let (mut density, mut state) = (vec![f32::NAN; 5], vec![f32::NAN; 5 * w]);
            net.density_with_state(&positions, &mut density, &mut state);
            let (mut d, mut c, mut seg) = (vec![0.0; 4], vec![[0.0; 3]; 4], vec![0.0; 4 * dim]);
            net.forward_with_seg_input(&sub_p, &sub_d, &mut d, &mut c, &mut seg);
            let (mut c2, mut seg2) = (vec![[f32::NAN; 3]; 4], vec![f32::NAN; 4 * dim]);
            net.colour_from_state(&sub_p, &sub_d, &state, &rows, &mut c2, Some(&mut seg2));
            let d2: Vec<f32> = rows.iter().map(|&r| density[r as usize]).collect();
            assert_eq!((d2, c2, seg2), (d, c, seg));
        }
    }
}
