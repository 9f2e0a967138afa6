//! Volume compositing along one ray, forward and backward, with log-space transmittance.
//!
//! For samples `k` with density `σ_k ≥ 0` over interval length `δ_k`:
//! `α_k = 1 − exp(−σ_k δ_k)`, `T_k = exp(−Σ_{l<k} σ_l δ_l)`, `w_k = α_k T_k`. The outputs are
//! `rgb = Σ w_k c_k`, `depth = Σ w_k t_k` (not divided by the opacity, as the reference does),
//! `acc = Σ w_k` and any number of extra channels `e = Σ w_k e_k` (segmentation logits).
//! Working in log space keeps `T` exact where the product of `(1 − α)` would underflow.

/// Depth reported for a ray whose opacity is at most [`EMPTY_RAY_ACC`] (the reference's
/// sentinel; the geometry loss clips it away).
pub const EMPTY_RAY_DEPTH: f32 = 1e10;

/// Whether a rendered depth is a real hit: finite and well below [`EMPTY_RAY_DEPTH`].
pub fn is_hit(depth: f32) -> bool {
    depth.is_finite() && depth < EMPTY_RAY_DEPTH * 0.5
}

/// Opacity at or below which a ray counts as empty.
pub const EMPTY_RAY_ACC: f32 = 1e-10;

/// The samples of one ray.
///
/// # Shapes
/// `sigma`, `delta`, `t`: `[n]`; `rgb`: `[n]`; `extra`: `[n * d_extra]`.
#[derive(Debug, Clone, Copy)]
pub struct RaySamples<'a> {
    /// Post-activation density.
    pub sigma: &'a [f32],
    /// Interval lengths in world units.
    pub delta: &'a [f32],
    /// Distance of each sample along the ray (used for depth).
    pub t: &'a [f32],
    /// Colour of each sample.
    pub rgb: &'a [[f32; 3]],
    /// Extra per-sample channels.
    pub extra: &'a [f32],
    /// Number of extra channels.
    pub d_extra: usize,
    /// Optical depth of samples dropped just before each sample (weight thresholding keeps
    /// transmittance exact); empty when nothing was dropped.
    pub skipped_tau: &'a [f32],
}

/// Composited values of one ray.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RayColour {
    /// Expected colour.
    pub rgb: [f32; 3],
    /// Expected distance `Σ w t`, or [`EMPTY_RAY_DEPTH`] for an empty ray.
    pub depth: f32,
    /// Opacity `Σ w`.
    pub acc: f32,
    /// Distance at which the accumulated opacity reaches [`MEDIAN_OPACITY`] (interpolated
    /// between the two samples it is reached between): the visible surface, which thin fog in
    /// front of it does not pull towards the camera as it does `depth`. `depth / acc` for a
    /// ray that never gets that opaque, [`EMPTY_RAY_DEPTH`] for an empty one.
    pub median_depth: f32,
}

/// Accumulated opacity at which [`RayColour::median_depth`] is read.
pub const MEDIAN_OPACITY: f32 = 0.5;

impl RayColour {
    /// The expected 3D point `Σ w_k x_k = acc · origin + depth · direction` of a ray with a
    /// unit `direction` (the ray origin for an empty ray).
    pub fn expected_point(&self, origin: [f32; 3], direction: [f32; 3]) -> [f32; 3] {
        if self.acc <= EMPTY_RAY_ACC {
            return origin;
        }
        [
            self.acc * origin[0] + self.depth * direction[0],
            self.acc * origin[1] + self.depth * direction[1],
            self.acc * origin[2] + self.depth * direction[2],
        ]
    }
}

/// Computes the weights `w` of one ray (`weights.len() == sigma.len()`); `skipped_tau` as in
/// [`RaySamples`].
pub fn weights(sigma: &[f32], delta: &[f32], skipped_tau: &[f32], weights: &mut [f32]) {
    let mut optical_depth = 0.0f32;
    for k in 0..sigma.len() {
        if !skipped_tau.is_empty() {
            optical_depth += skipped_tau[k];
        }
        let tau = sigma[k] * delta[k];
        let transmittance = (-optical_depth).exp();
        weights[k] = -(-tau).exp_m1() * transmittance;
        optical_depth += tau;
    }
}

/// Composites one ray; writes the weights into `w` and the extra channels into `extra_out`.
pub fn composite(s: &RaySamples, w: &mut [f32], extra_out: &mut [f32]) -> RayColour {
    let n = s.sigma.len();
    debug_assert!(s.delta.len() == n && s.t.len() == n && s.rgb.len() == n);
    debug_assert_eq!(s.extra.len(), n * s.d_extra);
    weights(s.sigma, s.delta, s.skipped_tau, w);
    let mut out = RayColour::default();
    let mut median = None;
    extra_out.fill(0.0);
    for k in 0..n {
        let wk = w[k];
        for c in 0..3 {
            out.rgb[c] += wk * s.rgb[k][c];
        }
        out.depth += wk * s.t[k];
        let before = out.acc;
        out.acc += wk;
        if median.is_none() && out.acc >= MEDIAN_OPACITY {
            // Linear in the opacity between the previous sample and this one: samples are
            // centimetres apart, as coarse as the planes the mask rules look for.
            median = Some(match k {
                0 => s.t[0],
                _ => s.t[k - 1] + (MEDIAN_OPACITY - before) / wk * (s.t[k] - s.t[k - 1]),
            });
        }
        for (o, e) in extra_out.iter_mut().zip(&s.extra[k * s.d_extra..(k + 1) * s.d_extra]) {
            *o += wk * e;
        }
    }
    if out.acc <= EMPTY_RAY_ACC {
        out.depth = EMPTY_RAY_DEPTH;
        out.median_depth = EMPTY_RAY_DEPTH;
    } else {
        out.median_depth = median.unwrap_or(out.depth / out.acc);
    }
    out
}

/// Upstream gradients of one ray's outputs.
#[derive(Debug, Clone, Copy, Default)]
pub struct RayGrad<'a> {
    /// `∂L/∂rgb`.
    pub rgb: [f32; 3],
    /// `∂L/∂depth` (ignored for an empty ray, whose depth is a constant sentinel).
    pub depth: f32,
    /// `∂L/∂acc`.
    pub acc: f32,
    /// `∂L/∂extra`, `[d_extra]` (empty when there are no extra channels).
    pub extra: &'a [f32],
    /// Direct gradients of per-sample losses with respect to each weight `w_k`, `[n]`
    /// (empty when there are none), e.g. DVGO's per-sample colour loss `Σ w_k‖c_k − C‖²`.
    pub weights: &'a [f32],
}

/// Backward pass of [`composite`]: writes `∂L/∂σ`, `∂L/∂rgb` and `∂L/∂extra` per sample.
/// `w` are the weights from the forward pass; `acc` its opacity.
#[allow(clippy::too_many_arguments)]
pub fn composite_backward(
    s: &RaySamples,
    w: &[f32],
    acc: f32,
    g: &RayGrad,
    grad_sigma: &mut [f32],
    grad_rgb: &mut [[f32; 3]],
    grad_extra: &mut [f32],
) {
    let n = s.sigma.len();
    let d = s.d_extra;
    let g_depth = if acc <= EMPTY_RAY_ACC { 0.0 } else { g.depth };
    // ∂L/∂w_k, and the suffix sums Σ_{j>k} w_j ∂L/∂w_j.
    let grad_w = |k: usize| {
        let c = s.rgb[k];
        let mut gw = g.rgb[0] * c[0] + g.rgb[1] * c[1] + g.rgb[2] * c[2] + g_depth * s.t[k] + g.acc;
        if d > 0 {
            gw += g.extra.iter().zip(&s.extra[k * d..(k + 1) * d]).map(|(a, b)| a * b).sum::<f32>();
        }
        if !g.weights.is_empty() {
            gw += g.weights[k];
        }
        gw
    };
    // First pass: T_{k+1} = exp(−Σ_{l≤k} σ_l δ_l), summed forwards (summing backwards from the
    // total would cancel catastrophically when a thick last interval dominates), kept in
    // `grad_sigma` as scratch.
    let mut optical_depth = 0.0f32;
    for k in 0..n {
        if !s.skipped_tau.is_empty() {
            optical_depth += s.skipped_tau[k];
        }
        optical_depth += s.sigma[k] * s.delta[k];
        grad_sigma[k] = (-optical_depth).exp();
    }
    let mut suffix = 0.0f32;
    for k in (0..n).rev() {
        let gw = grad_w(k);
        let t_next = grad_sigma[k];
        // ∂w_k/∂σ_k = δ_k T_{k+1}; ∂w_j/∂σ_k = −δ_k w_j for j > k.
        grad_sigma[k] = s.delta[k] * (t_next * gw - suffix);
        suffix += w[k] * gw;
        for c in 0..3 {
            grad_rgb[k][c] = w[k] * g.rgb[c];
        }
        for j in 0..d {
            grad_extra[k * d + j] = w[k] * g.extra[j];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::fixture::{f32_gamma, load_fixture, Array};

    struct Fixture {
        sigma: Array,
        rgb: Array,
        seg: Array,
        z: Array,
        rays_d: Array,
    }

    fn setup() -> (serde_json::Value, Fixture) {
        let v = load_fixture(include_str!("../../../fixtures/render/composite.json"));
        let f = Fixture {
            sigma: Array::from(&v["sigma"]),
            rgb: Array::from(&v["rgb"]),
            seg: Array::from(&v["seg"]),
            z: Array::from(&v["z"]),
            rays_d: Array::from(&v["rays_d"]),
        };
        (v, f)
    }

    /// Per-ray inputs: sigma, delta, t, rgb, extra.
    type RayInputs = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<[f32; 3]>, Vec<f32>);

    /// Per-ray inputs in the reference's convention: δ = Δz·|d| with a last δ of 1e10·|d|.
    fn ray_inputs(f: &Fixture, r: usize) -> RayInputs {
        let n = f.sigma.shape[1];
        let d = &f.rays_d.data[r * 3..r * 3 + 3];
        let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let z: Vec<f32> = f.z.data[r * n..(r + 1) * n].iter().map(|&v| v as f32).collect();
        let delta: Vec<f32> = (0..n)
            .map(|k| if k + 1 < n { ((z[k + 1] - z[k]) as f64 * norm) as f32 } else { (1e10 * norm) as f32 })
            .collect();
        let sigma: Vec<f32> = f.sigma.data[r * n..(r + 1) * n].iter().map(|&v| v as f32).collect();
        let rgb: Vec<[f32; 3]> = (0..n)
            .map(|k| {
                let i = (r * n + k) * 3;
                [f.rgb.data[i] as f32, f.rgb.data[i + 1] as f32, f.rgb.data[i + 2] as f32]
            })
            .collect();
        let seg: Vec<f32> = f.seg.data[r * n * 2..(r + 1) * n * 2].iter().map(|&v| v as f32).collect();
        (sigma, delta, z, rgb, seg)
    }

    fn close(a: f64, b: f64, what: &str) {
        let tol = 1e-5 * b.abs().max(1e-3);
        assert!((a - b).abs() <= tol, "{what}: got {a}, want {b}");
    }

    #[test]
    fn matches_reference_compositing_and_gradients() {
        let (v, f) = setup();
        let [n_rays, n] = [f.sigma.shape[0], f.sigma.shape[1]];
        let want = |k: &str| Array::from(&v[k]);
        let (w_ref, rgb_ref, depth_ref, acc_ref, seg_ref) =
            (want("weights"), want("rgb_map"), want("depth"), want("acc"), want("seg_map"));
        let (w_rgb, w_depth, w_acc, w_seg) = (want("w_rgb"), want("w_depth"), want("w_acc"), want("w_seg"));
        let (g_sigma_ref, g_rgb_ref, g_seg_ref) = (want("grad_sigma"), want("grad_rgb"), want("grad_seg"));
        for r in 0..n_rays {
            let (sigma, delta, z, rgb, seg) = ray_inputs(&f, r);
            let s = RaySamples {
                sigma: &sigma,
                delta: &delta,
                t: &z,
                rgb: &rgb,
                extra: &seg,
                d_extra: 2,
                skipped_tau: &[],
            };
            let mut w = vec![0.0; n];
            let mut seg_map = [0.0; 2];
            let out = composite(&s, &mut w, &mut seg_map);
            for k in 0..n {
                close(w[k] as f64, w_ref.data[r * n + k], "weight");
            }
            for c in 0..3 {
                close(out.rgb[c] as f64, rgb_ref.data[r * 3 + c], "rgb");
            }
            close(out.depth as f64, depth_ref.data[r], "depth");
            close(out.acc as f64, acc_ref.data[r], "acc");
            for c in 0..2 {
                close(seg_map[c] as f64, seg_ref.data[r * 2 + c], "seg");
            }
            let g_extra = [w_seg.data[r * 2] as f32, w_seg.data[r * 2 + 1] as f32];
            let g = RayGrad {
                rgb: [w_rgb.data[r * 3] as f32, w_rgb.data[r * 3 + 1] as f32, w_rgb.data[r * 3 + 2] as f32],
                depth: w_depth.data[r] as f32,
                acc: w_acc.data[r] as f32,
                extra: &g_extra,
                weights: &[],
            };
            let mut gs = vec![0.0; n];
            let mut grgb = vec![[0.0; 3]; n];
            let mut gseg = vec![0.0; 2 * n];
            composite_backward(&s, &w, out.acc, &g, &mut gs, &mut grgb, &mut gseg);
            // The colour gradients are the weights times the ray's colour gradient. Both sides
            // compute the weights in f32 from the transmittance, which accumulates the ray's n
            // optical depths σ_j·δ_j (total τ): a relative round-off of up to γ_n per unit of
            // optical depth and per factor on each side. Compared normwise over the ray: a
            // single entry's relative error says little where its weight is tiny.
            let depth: f64 = (0..n - 1).map(|k| sigma[k] as f64 * delta[k] as f64).sum();
            let tolerance = 2.0 * f32_gamma(n) * (1.0 + depth);
            let (mut diff, mut norm) = (0.0f64, 0.0f64);
            for k in 0..n {
                // Gradients of the 1e10-thick last interval are huge; compare relatively.
                let want = g_sigma_ref.data[r * n + k];
                let tol = 1e-5 * want.abs().max(1e-2);
                assert!((gs[k] as f64 - want).abs() <= tol, "grad sigma ray {r} sample {k}: {} vs {want}", gs[k]);
                for c in 0..3 {
                    let want = g_rgb_ref.data[(r * n + k) * 3 + c];
                    diff += (grgb[k][c] as f64 - want).powi(2);
                    norm += want * want;
                }
                for c in 0..2 {
                    close(gseg[k * 2 + c] as f64, g_seg_ref.data[(r * n + k) * 2 + c], "grad seg");
                }
            }
            let (diff, norm) = (diff.sqrt(), norm.sqrt());
            assert!(
                diff <= tolerance * norm,
                "grad rgb ray {r}: normwise relative error {:e} beyond the f32 bound {tolerance:e}",
                diff / norm
            );
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let sigma = vec![0.3f32, 1.7, 0.0, 4.0, 0.9];
        let delta = vec![0.2f32, 0.1, 0.3, 0.15, 0.25];
        let t = vec![1.0f32, 1.2, 1.3, 1.6, 1.75];
        let rgb: Vec<[f32; 3]> = (0..5).map(|k| [0.1 * k as f32, 0.5, 0.9 - 0.1 * k as f32]).collect();
        let extra: Vec<f32> = (0..10).map(|i| (i as f32 * 0.37).sin()).collect();
        let g_extra = [0.7f32, -1.3];
        let g_weights = [0.2f32, -0.1, 0.5, 0.3, -0.7];
        let g = RayGrad { rgb: [0.3, -0.2, 0.5], depth: 0.8, acc: -0.4, extra: &g_extra, weights: &g_weights };
        let loss = |sigma: &[f32], rgb: &[[f32; 3]], extra: &[f32]| -> f64 {
            let s = RaySamples { sigma, delta: &delta, t: &t, rgb, extra, d_extra: 2, skipped_tau: &[] };
            let mut w = vec![0.0; 5];
            let mut e = [0.0; 2];
            let o = composite(&s, &mut w, &mut e);
            (0..3).map(|c| (g.rgb[c] * o.rgb[c]) as f64).sum::<f64>()
                + w.iter().zip(&g_weights).map(|(a, b)| (a * b) as f64).sum::<f64>()
                + (g.depth * o.depth + g.acc * o.acc) as f64
                + (g_extra[0] * e[0] + g_extra[1] * e[1]) as f64
        };
        let s =
            RaySamples { sigma: &sigma, delta: &delta, t: &t, rgb: &rgb, extra: &extra, d_extra: 2, skipped_tau: &[] };
        let mut w = vec![0.0; 5];
        let mut e = [0.0; 2];
        let o = composite(&s, &mut w, &mut e);
        let (mut gs, mut grgb, mut ge) = (vec![0.0; 5], vec![[0.0; 3]; 5], vec![0.0; 10]);
        composite_backward(&s, &w, o.acc, &g, &mut gs, &mut grgb, &mut ge);
        let h = 1e-3f32;
        for k in 0..5 {
            let (mut p, mut m) = (sigma.clone(), sigma.clone());
            p[k] += h;
            m[k] -= h;
            let fd = (loss(&p, &rgb, &extra) - loss(&m, &rgb, &extra)) / (2.0 * h as f64);
            assert!((fd - gs[k] as f64).abs() < 2e-3, "sigma {k}: fd {fd} vs {}", gs[k]);
            let (mut p, mut m) = (rgb.clone(), rgb.clone());
            p[k][1] += h;
            m[k][1] -= h;
            let fd = (loss(&sigma, &p, &extra) - loss(&sigma, &m, &extra)) / (2.0 * h as f64);
            assert!((fd - grgb[k][1] as f64).abs() < 2e-3, "rgb {k}");
            let (mut p, mut m) = (extra.clone(), extra.clone());
            p[2 * k + 1] += h;
            m[2 * k + 1] -= h;
            let fd = (loss(&sigma, &rgb, &p) - loss(&sigma, &rgb, &m)) / (2.0 * h as f64);
            assert!((fd - ge[2 * k + 1] as f64).abs() < 2e-3, "extra {k}");
        }
    }

    #[test]
    fn the_median_depth_is_the_surface_behind_thin_fog() {
        // Thin fog at t = 1 (opacity 0.2), an opaque surface at t = 3: the expected depth is
        // pulled towards the camera, the median lies between the last fog sample and the
        // surface, where the opacity crosses one half.
        let t = [1.0, 2.0, 3.0, 4.0];
        let delta = [1.0; 4];
        let sigma = [-(0.8f32).ln(), 0.0, 50.0, 50.0];
        let rgb = [[0.5; 3]; 4];
        let s = RaySamples { sigma: &sigma, delta: &delta, t: &t, rgb: &rgb, extra: &[], d_extra: 0, skipped_tau: &[] };
        let mut w = [0.0; 4];
        let o = composite(&s, &mut w, &mut []);
        assert!((o.acc - 1.0).abs() < 1e-5);
        assert!(o.depth < 2.7, "expected depth {}", o.depth);
        // Opacity 0.2 up to t = 2, then 0.8 more at t = 3: half is reached 0.3 / 0.8 of the way.
        assert!((o.median_depth - (2.0 + 0.3 / 0.8)).abs() < 1e-4, "median depth {}", o.median_depth);
        // A ray that never gets half opaque: the normalised expected depth.
        let faint = [0.1, 0.0, 0.0, 0.0];
        let s = RaySamples { sigma: &faint, ..s };
        let o = composite(&s, &mut w, &mut []);
        assert!((o.median_depth - 1.0).abs() < 1e-5);
        // An empty ray: the sentinel.
        let s = RaySamples { sigma: &[0.0; 4], ..s };
        assert_eq!(composite(&s, &mut w, &mut []).median_depth, EMPTY_RAY_DEPTH);
    }
}
