//! The appearance contrastive loss (spec §6, §12): STEGO's correlation loss between teacher
//! features and rendered segmentation logits, sampled at random points of each patch.
//!
//! For each call, `U1` and `U2` hold `samples × samples` uniform points in `[−1,1]²` per
//! patch. With `f` the teacher features, `s` the logits and `neg` the mined negatives:
//! `L = λ_neg·helper(f@U1, f[neg]@U2, s@U1, s[neg]@U2, b_neg) + λ_id·helper(f@U1, f@U1, s@U1, s@U1, b_id)`,
//! where `@` is bilinear sampling ([`BilinearTaps`]) and `helper` is [`stego_helper`].
//! Everything is computed in f64.

use rand::{Rng, RngCore};
use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{ContrastiveLoss, ContrastiveLossConfig, FeatureMap, LossValue, PatchBatch};

use crate::normalize::{l2_normalize, l2_normalize_backward};
use crate::{validate, PatchShape};

const KIND: &str = AppearanceConfig::KIND;

/// Lower bound of the channel norm in the L2 normalisations (STEGO's `F.normalize` eps).
pub const NORM_EPS: f64 = 1e-10;

/// Settings of [`AppearanceLoss`]; defaults are the reference LLFF run's (`0.18,1,0.46,1`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AppearanceConfig {
    /// Shift `b_id` of the identity (self-correlation) term.
    pub identity_shift: f64,
    /// Weight `λ_id` of the identity term.
    pub identity_weight: f64,
    /// Shift `b_neg` of the negative term.
    pub negative_shift: f64,
    /// Weight `λ_neg` of the negative term.
    pub negative_weight: f64,
    /// Sample points per patch side (STEGO's `feature_samples`).
    pub samples: usize,
}

impl Default for AppearanceConfig {
    fn default() -> Self {
        AppearanceConfig {
            identity_shift: 0.18,
            identity_weight: 1.0,
            negative_shift: 0.46,
            negative_weight: 1.0,
            samples: 11,
        }
    }
}

/// Largest `samples` (points per patch side).
const MAX_SAMPLES: usize = 64;

sos_core::plugin_kind! {
    kind: "appearance",
    summary: "STEGO correlation loss between teacher features and logits at random sample points",
    default: || Box::new(AppearanceConfig::default()),
    impl ContrastiveLossConfig for AppearanceConfig {
        fn build(&self) -> Result<Box<dyn ContrastiveLoss>, BuildError> {
            validate::finite(KIND, "identity_shift", self.identity_shift)?;
            validate::non_negative(KIND, "identity_weight", self.identity_weight)?;
            validate::finite(KIND, "negative_shift", self.negative_shift)?;
            validate::non_negative(KIND, "negative_weight", self.negative_weight)?;
            // Each patch correlates `samples²` points with another's `samples²`: at 64 that
            // is 16 M pairs per patch pair, already far beyond the reference's 11.
            if !(1..=MAX_SAMPLES).contains(&self.samples) {
                return Err(validate::invalid(KIND, "samples", format!("must be in 1..={MAX_SAMPLES}")));
            }
            Ok(Box::new(AppearanceLoss { config: self.clone() }))
        }
    }
}

/// The appearance contrastive loss (built from a validated [`AppearanceConfig`]).
#[derive(Debug, Clone, PartialEq)]
pub struct AppearanceLoss {
    config: AppearanceConfig,
}

impl AppearanceLoss {
    /// The settings this loss was built with.
    pub fn config(&self) -> &AppearanceConfig {
        &self.config
    }
}

/// The four taps of align-corners bilinear sampling with border padding at points of a
/// `height × width` grid: for each point, `(flat index y·width + x, weight)`.
#[derive(Debug, Clone, PartialEq)]
pub struct BilinearTaps {
    /// Grid height.
    pub height: usize,
    /// Grid width.
    pub width: usize,
    /// Four `(index, weight)` taps per point.
    pub taps: Vec<[(usize, f64); 4]>,
}

impl BilinearTaps {
    /// Taps of `grid_sample(align_corners=True, padding_mode="border")` at `points`, given as
    /// `(x, y)` in `[−1,1]` (x along the width): −1 is the first pixel centre and +1 the last;
    /// coordinates outside are clamped to the border.
    ///
    /// # Panics
    /// If the grid is empty.
    pub fn new(height: usize, width: usize, points: &[[f32; 2]]) -> Self {
        assert!(height > 0 && width > 0, "BilinearTaps: empty grid");
        // As torch's grid_sampler: the source position and the weights are computed in f32
        // (this keeps gradients within f32 rounding of the reference), then widened.
        let axis = |v: f32, size: usize| -> (usize, usize, f32, f32) {
            let hi = (size - 1) as f32;
            let pos = (((v + 1.0) / 2.0) * hi).clamp(0.0, hi);
            // NaN (never produced by the samplers) falls to index 0 via the saturating cast.
            let lo = pos.floor();
            let i0 = (lo as usize).min(size - 1);
            ((i0), (i0 + 1).min(size - 1), (lo + 1.0) - pos, pos - lo)
        };
        let taps = points
            .iter()
            .map(|&[x, y]| {
                let (x0, x1, wx0, wx1) = axis(x, width);
                let (y0, y1, wy0, wy1) = axis(y, height);
                [
                    (y0 * width + x0, f64::from(wx0 * wy0)),
                    (y0 * width + x1, f64::from(wx1 * wy0)),
                    (y1 * width + x0, f64::from(wx0 * wy1)),
                    (y1 * width + x1, f64::from(wx1 * wy1)),
                ]
            })
            .collect();
        BilinearTaps { height, width, taps }
    }

    /// Number of sample points.
    pub fn len(&self) -> usize {
        self.taps.len()
    }

    /// Whether there are no sample points.
    pub fn is_empty(&self) -> bool {
        self.taps.is_empty()
    }

    /// Samples a `[channels, height, width]` grid: returns `[channels, points]`.
    ///
    /// # Panics
    /// If `grid.len() != channels · height · width`.
    pub fn sample(&self, grid: &[f32], channels: usize) -> Vec<f64> {
        let hw = self.height * self.width;
        assert_eq!(grid.len(), channels * hw, "BilinearTaps::sample: grid is not [C,h,w]");
        let mut out = Vec::with_capacity(channels * self.len());
        for plane in grid.chunks_exact(hw) {
            out.extend(self.taps.iter().map(|t| t.iter().map(|&(i, w)| w * f64::from(plane[i])).sum::<f64>()));
        }
        out
    }

    /// Backward of [`Self::sample`]: adds `scale · ∂L/∂grid` into `grad_grid`
    /// (`[channels, height, width]`) given `∂L/∂samples` (`[channels, points]`).
    ///
    /// # Panics
    /// If the buffers do not match the shapes.
    pub fn backward(&self, grad_samples: &[f64], channels: usize, scale: f64, grad_grid: &mut [f32]) {
        let hw = self.height * self.width;
        let n = self.len();
        assert_eq!(grad_grid.len(), channels * hw, "BilinearTaps::backward: grid is not [C,h,w]");
        assert_eq!(grad_samples.len(), channels * n, "BilinearTaps::backward: grad is not [C,points]");
        if n == 0 {
            return;
        }
        for (plane, g) in grad_grid.chunks_exact_mut(hw).zip(grad_samples.chunks_exact(n)) {
            // Accumulate in f64 before the single rounding to f32.
            let mut acc = vec![0.0f64; hw];
            for (t, &gv) in self.taps.iter().zip(g) {
                for &(i, w) in t {
                    acc[i] += w * gv;
                }
            }
            for (o, a) in plane.iter_mut().zip(acc) {
                if a != 0.0 {
                    *o += (scale * a) as f32;
                }
            }
        }
    }
}

/// Result of [`stego_helper`].
#[derive(Debug, Clone, PartialEq)]
pub struct HelperOutput {
    /// The loss (mean over patches and point pairs).
    pub loss: f64,
    /// `∂loss/∂sa`, `[n, c_seg, points]`.
    pub grad_sa: Vec<f64>,
    /// `∂loss/∂sb`, `[n, c_seg, points]`.
    pub grad_sb: Vec<f64>,
}

/// STEGO's `ContrastiveCorrelationLoss.helper` on sampled values, with its gradient w.r.t. the
/// sampled logits.
///
/// Inputs are per patch, channel-first: `fa`, `fb` `[n, c_feat, m]`, `sa`, `sb` `[n, c_seg, m]`
/// (`m` sample points). With `x̂ = x / max(‖x‖₂, 1e-10)` over channels:
/// - `F[n,p,q] = ⟨f̂a[n,:,p], f̂b[n,:,q]⟩`, centred without gradient:
///   `F ← F − mean_q F[n,p,:] + mean_{n,p,q} F` (global mean over the whole batch);
/// - `S[n,p,q] = ⟨ŝa[n,:,p], ŝb[n,:,q]⟩`;
/// - `loss = mean_{n,p,q} −max(S,0)·(F − shift)`.
///
/// # Panics
/// If the buffer lengths do not match `n`, `c_feat`, `c_seg` and `m`.
#[allow(clippy::too_many_arguments)]
pub fn stego_helper(
    fa: &[f64],
    fb: &[f64],
    sa: &[f64],
    sb: &[f64],
    n: usize,
    c_feat: usize,
    c_seg: usize,
    m: usize,
    shift: f64,
) -> HelperOutput {
    assert_eq!(fa.len(), n * c_feat * m, "stego_helper: fa is not [n, c_feat, m]");
    assert_eq!(fb.len(), n * c_feat * m, "stego_helper: fb is not [n, c_feat, m]");
    assert_eq!(sa.len(), n * c_seg * m, "stego_helper: sa is not [n, c_seg, m]");
    assert_eq!(sb.len(), n * c_seg * m, "stego_helper: sb is not [n, c_seg, m]");
    let mut grad_sa = vec![0.0f64; sa.len()];
    let mut grad_sb = vec![0.0f64; sb.len()];
    if n == 0 || m == 0 {
        return HelperOutput { loss: 0.0, grad_sa, grad_sb };
    }
    let mm = m * m;
    let fsz = c_feat * m;
    let ssz = c_seg * m;

    // Feature correlation per patch, then centring (no gradient flows into features anyway).
    let mut corr = vec![0.0f64; n * mm];
    for k in 0..n {
        let (a, _) = l2_normalize(&fa[k * fsz..(k + 1) * fsz], c_feat, m, NORM_EPS);
        let (b, _) = l2_normalize(&fb[k * fsz..(k + 1) * fsz], c_feat, m, NORM_EPS);
        cosine_correlation(&a, &b, c_feat, m, &mut corr[k * mm..(k + 1) * mm]);
    }
    let global_mean = corr.iter().sum::<f64>() / (n * mm) as f64;
    for row in corr.chunks_exact_mut(m) {
        let row_mean = row.iter().sum::<f64>() / m as f64;
        for v in row {
            *v += global_mean - row_mean;
        }
    }

    let total = (n * mm) as f64;
    let mut loss = 0.0f64;
    let mut s = vec![0.0f64; mm];
    for k in 0..n {
        let (a, da) = l2_normalize(&sa[k * ssz..(k + 1) * ssz], c_seg, m, NORM_EPS);
        let (b, db) = l2_normalize(&sb[k * ssz..(k + 1) * ssz], c_seg, m, NORM_EPS);
        cosine_correlation(&a, &b, c_seg, m, &mut s);
        // dS[p,q] = ∂loss/∂S[p,q]; the zero clamp passes no gradient where S < 0.
        let f = &corr[k * mm..(k + 1) * mm];
        for (sv, fv) in s.iter_mut().zip(f) {
            let centred = fv - shift;
            if *sv > 0.0 {
                loss -= *sv * centred;
                *sv = -centred / total;
            } else {
                *sv = 0.0;
            }
        }
        // ∂/∂â[c,p] = Σ_q dS[p,q] b̂[c,q];  ∂/∂b̂[c,q] = Σ_p dS[p,q] â[c,p].
        let mut ga = vec![0.0f64; ssz];
        let mut gb = vec![0.0f64; ssz];
        for c in 0..c_seg {
            let ac = &a[c * m..(c + 1) * m];
            let bc = &b[c * m..(c + 1) * m];
            let gbc = &mut gb[c * m..(c + 1) * m];
            for (p, ds_row) in s.chunks_exact(m).enumerate() {
                let mut acc = 0.0f64;
                for ((d, bv), gv) in ds_row.iter().zip(bc).zip(gbc.iter_mut()) {
                    acc += d * bv;
                    *gv += d * ac[p];
                }
                ga[c * m + p] = acc;
            }
        }
        grad_sa[k * ssz..(k + 1) * ssz].copy_from_slice(&l2_normalize_backward(&a, &da, &ga, c_seg, m, NORM_EPS));
        grad_sb[k * ssz..(k + 1) * ssz].copy_from_slice(&l2_normalize_backward(&b, &db, &gb, c_seg, m, NORM_EPS));
    }
    HelperOutput { loss: loss / total, grad_sa, grad_sb }
}

/// `out[p,q] = Σ_c a[c,p]·b[c,q]` for channel-first `[c, m]` inputs.
fn cosine_correlation(a: &[f64], b: &[f64], channels: usize, m: usize, out: &mut [f64]) {
    out.fill(0.0);
    for c in 0..channels {
        let ac = &a[c * m..(c + 1) * m];
        let bc = &b[c * m..(c + 1) * m];
        for (row, &av) in out.chunks_exact_mut(m).zip(ac) {
            for (o, &bv) in row.iter_mut().zip(bc) {
                *o += av * bv;
            }
        }
    }
}

/// One appearance term: `helper(f@A, f[partner]@B, s@A, s[partner]@B, shift)` where `@A`
/// samples patch `k` at `points_a[k·m..(k+1)·m]` and `@B` samples patch `partner[k]` at
/// `points_b[k·m..]`. Adds `grad_scale · ∂term/∂logits` into `grad_logits` (if given) and
/// returns the term.
///
/// # Panics
/// If the shapes disagree: `logits` must be `shape`, `features` hold `n_patches` maps with
/// equal channel counts, `partner` hold `n_patches` indices below `n_patches`, and both point
/// lists the same multiple `m` of `n_patches`.
#[allow(clippy::too_many_arguments)]
pub fn appearance_term(
    features: &[FeatureMap],
    logits: &[f32],
    shape: PatchShape,
    partner: &[usize],
    points_a: &[[f32; 2]],
    points_b: &[[f32; 2]],
    shift: f64,
    grad_scale: f64,
    grad_logits: Option<&mut [f32]>,
) -> f64 {
    let n = shape.n_patches;
    assert_eq!(logits.len(), shape.logits_len(), "appearance: logits are not [n, d_seg, P, P]");
    assert_eq!(features.len(), n, "appearance: need one feature map per patch");
    assert_eq!(partner.len(), n, "appearance: need one partner per patch");
    assert!(partner.iter().all(|&j| j < n), "appearance: partner index out of range");
    assert_eq!(points_a.len(), points_b.len(), "appearance: point lists differ in length");
    if n == 0 {
        return 0.0;
    }
    assert_eq!(points_a.len() % n, 0, "appearance: points are not [n, m]");
    let m = points_a.len() / n;
    let c_feat = features[0].channels;
    assert!(
        features.iter().all(|f| f.channels == c_feat && f.data.len() == f.channels * f.height * f.width),
        "appearance: feature maps must be [C,h,w] with equal C"
    );
    let d = shape.d_seg;
    let hw = shape.pixels();
    let logit_plane = |k: usize| &logits[k * d * hw..(k + 1) * d * hw];

    let mut fa = Vec::with_capacity(n * c_feat * m);
    let mut fb = Vec::with_capacity(n * c_feat * m);
    let mut sa = Vec::with_capacity(n * d * m);
    let mut sb = Vec::with_capacity(n * d * m);
    let mut taps = Vec::with_capacity(n);
    for k in 0..n {
        let j = partner[k];
        let (pa, pb) = (&points_a[k * m..(k + 1) * m], &points_b[k * m..(k + 1) * m]);
        let (fk, fj) = (&features[k], &features[j]);
        fa.extend(BilinearTaps::new(fk.height, fk.width, pa).sample(&fk.data, c_feat));
        fb.extend(BilinearTaps::new(fj.height, fj.width, pb).sample(&fj.data, c_feat));
        let ta = BilinearTaps::new(shape.patch, shape.patch, pa);
        let tb = BilinearTaps::new(shape.patch, shape.patch, pb);
        sa.extend(ta.sample(logit_plane(k), d));
        sb.extend(tb.sample(logit_plane(j), d));
        taps.push((ta, tb));
    }
    let out = stego_helper(&fa, &fb, &sa, &sb, n, c_feat, d, m, shift);
    if let Some(grad) = grad_logits {
        assert_eq!(grad.len(), logits.len(), "appearance: grad_logits is not [n, d_seg, P, P]");
        for (k, (ta, tb)) in taps.iter().enumerate() {
            let j = partner[k];
            let r = k * d * m..(k + 1) * d * m;
            ta.backward(&out.grad_sa[r.clone()], d, grad_scale, &mut grad[k * d * hw..(k + 1) * d * hw]);
            tb.backward(&out.grad_sb[r], d, grad_scale, &mut grad[j * d * hw..(j + 1) * d * hw]);
        }
    }
    out.loss
}

/// The full appearance loss with explicit sample points (`U1` = `points_1`, `U2` = `points_2`,
/// each `[n_patches, m]`): returns the unweighted terms and
/// `total = λ_neg·negative + λ_id·identity`, and adds `grad_scale · ∂total/∂logits` into
/// `grad_logits` (if given).
///
/// # Panics
/// On shape mismatches, as [`appearance_term`].
#[allow(clippy::too_many_arguments)]
pub fn appearance_loss(
    config: &AppearanceConfig,
    features: &[FeatureMap],
    logits: &[f32],
    shape: PatchShape,
    negatives: &[usize],
    points_1: &[[f32; 2]],
    points_2: &[[f32; 2]],
    grad_scale: f64,
    mut grad_logits: Option<&mut [f32]>,
) -> LossValue {
    let identity: Vec<usize> = (0..shape.n_patches).collect();
    let neg = appearance_term(
        features,
        logits,
        shape,
        negatives,
        points_1,
        points_2,
        config.negative_shift,
        grad_scale * config.negative_weight,
        grad_logits.as_deref_mut(),
    );
    let id = appearance_term(
        features,
        logits,
        shape,
        &identity,
        points_1,
        points_1,
        config.identity_shift,
        grad_scale * config.identity_weight,
        grad_logits,
    );
    LossValue {
        total: config.negative_weight * neg + config.identity_weight * id,
        terms: vec![("appearance/identity".to_string(), id), ("appearance/negative".to_string(), neg)],
    }
}

/// `count` uniform points in `[−1,1]²`.
fn uniform_points(count: usize, rng: &mut dyn RngCore) -> Vec<[f32; 2]> {
    (0..count).map(|_| [rng.gen_range(-1.0f32..=1.0), rng.gen_range(-1.0f32..=1.0)]).collect()
}

impl ContrastiveLoss for AppearanceLoss {
    /// Draws fresh `U1`, `U2` (`samples²` points per patch, in that order) and evaluates
    /// [`appearance_loss`].
    ///
    /// # Panics
    /// If the batch is inconsistent (see [`appearance_term`]) or `grad_logits` does not match
    /// `batch.logits`.
    fn loss_and_grad(
        &self,
        batch: &PatchBatch,
        rng: &mut dyn RngCore,
        grad_scale: f32,
        grad_logits: &mut [f32],
    ) -> LossValue {
        let shape = PatchShape { n_patches: batch.n_patches, d_seg: batch.d_seg, patch: batch.patch };
        let count = batch.n_patches * self.config.samples * self.config.samples;
        let u1 = uniform_points(count, rng);
        let u2 = uniform_points(count, rng);
        appearance_loss(
            &self.config,
            batch.features,
            batch.logits,
            shape,
            batch.negatives,
            &u1,
            &u2,
            f64::from(grad_scale),
            Some(grad_logits),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixtures::{assert_close, Fixture};
    use rand::SeedableRng;

    struct Case {
        features: Vec<FeatureMap>,
        logits: Vec<f32>,
        shape: PatchShape,
        neg: Vec<usize>,
        u1: Vec<[f32; 2]>,
        u2: Vec<[f32; 2]>,
    }

    fn feature_maps(shape: &[usize], data: &[f32], cls: &[Vec<f32>]) -> Vec<FeatureMap> {
        let (c, h, w) = (shape[1], shape[2], shape[3]);
        data.chunks(c * h * w)
            .zip(cls)
            .map(|(d, cl)| FeatureMap {
                channels: c,
                height: h,
                width: w,
                data: d.to_vec(),
                cls: cl.clone(),
                saliency: None,
            })
            .collect()
    }

    fn points(data: &[f32]) -> Vec<[f32; 2]> {
        data.chunks_exact(2).map(|p| [p[0], p[1]]).collect()
    }

    fn fixture_case(fx: &Fixture) -> Case {
        let (fshape, fdata) = fx.array_f32("feats");
        let (sshape, logits) = fx.array_f32("seg");
        assert_eq!(sshape[2], sshape[3]);
        let shape = PatchShape { n_patches: sshape[0], d_seg: sshape[1], patch: sshape[2] };
        Case {
            features: feature_maps(&fshape, &fdata, &fx.cls()),
            logits,
            shape,
            neg: fx.neg(),
            u1: points(&fx.array_f32("coords1").1),
            u2: points(&fx.array_f32("coords2").1),
        }
    }

    fn config_from(fx: &Fixture) -> AppearanceConfig {
        AppearanceConfig {
            identity_shift: fx.scalar("b_id"),
            negative_shift: fx.scalar("b_neg"),
            ..AppearanceConfig::default()
        }
    }

    #[test]
    fn matches_reference_fixture() {
        let fx = Fixture::appearance();
        let case = fixture_case(&fx);
        let cfg = config_from(&fx);
        let mut grad = vec![0.0f32; case.logits.len()];
        let v = appearance_loss(
            &cfg,
            &case.features,
            &case.logits,
            case.shape,
            &case.neg,
            &case.u1,
            &case.u2,
            1.0,
            Some(&mut grad),
        );
        let term = |name: &str| v.terms.iter().find(|(k, _)| k == name).map(|t| t.1).expect(name);
        assert_close("identity", &[term("appearance/identity")], &[fx.scalar("self_term")], 1e-5, 0.0);
        assert_close("negative", &[term("appearance/negative")], &[fx.scalar("neg_term")], 1e-5, 0.0);
        assert_close("total", &[v.total], &[fx.scalar("total")], 1e-5, 0.0);
        let grad: Vec<f64> = grad.iter().map(|&g| f64::from(g)).collect();
        // Both sides accumulate in f32. A logit's gradient sums, over its four bilinear
        // neighbours' sample points, the identity and the negative pair terms of every other
        // sample point of the patch, each a dot product over the feature channels.
        let reference = fx.array("grad_seg").1;
        let (samples, channels) = (case.u1.len() / case.shape.n_patches, case.features[0].channels);
        let accumulation = 4 * 2 * samples + channels;
        sos_core::testing::fixture::assert_f32_gradients("grad_seg", &grad, &reference, accumulation);
    }

    #[test]
    fn trait_impl_uses_rng_points_and_scales_gradient() {
        let fx = Fixture::appearance();
        let case = fixture_case(&fx);
        let loss = config_from(&fx).build().expect("builds");
        let points = vec![0.0f32; case.logits.len()];
        let batch = PatchBatch {
            n_patches: case.shape.n_patches,
            patch: case.shape.patch,
            d_seg: case.shape.d_seg,
            logits: &case.logits,
            points: &points,
            features: &case.features,
            negatives: &case.neg,
        };
        let mut g1 = vec![1.0f32; case.logits.len()];
        let v1 = loss.loss_and_grad(&batch, &mut rand::rngs::StdRng::seed_from_u64(3), 2.0, &mut g1);
        let mut g2 = vec![0.0f32; case.logits.len()];
        let v2 = loss.loss_and_grad(&batch, &mut rand::rngs::StdRng::seed_from_u64(3), 1.0, &mut g2);
        assert_eq!(v1, v2);
        for (a, b) in g1.iter().zip(&g2) {
            assert!((a - 1.0 - 2.0 * b).abs() <= 1e-6 * (1.0 + b.abs()), "{a} vs 1 + 2·{b}");
        }
        // Reproduce with explicit points drawn the same way.
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let count = case.shape.n_patches * 121;
        let u1 = uniform_points(count, &mut rng);
        let u2 = uniform_points(count, &mut rng);
        let cfg = config_from(&fx);
        let v3 = appearance_loss(&cfg, &case.features, &case.logits, case.shape, &case.neg, &u1, &u2, 1.0, None);
        assert_eq!(v1, v3);
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let mut g4 = vec![0.0f32; case.logits.len()];
        assert_ne!(loss.loss_and_grad(&batch, &mut rng, 1.0, &mut g4).total, v1.total);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let shape = PatchShape { n_patches: 3, d_seg: 3, patch: 5 };
        let (c, h, w) = (4, 3, 4);
        let features: Vec<FeatureMap> = (0..3)
            .map(|_| FeatureMap {
                channels: c,
                height: h,
                width: w,
                data: (0..c * h * w).map(|_| rng.gen_range(-1.0..1.0)).collect(),
                cls: vec![],
                saliency: None,
            })
            .collect();
        let logits: Vec<f32> = (0..shape.logits_len()).map(|_| rng.gen_range(-2.0..2.0)).collect();
        let neg = vec![2, 0, 0];
        let u1 = uniform_points(3 * 9, &mut rng);
        let u2 = uniform_points(3 * 9, &mut rng);
        let cfg = AppearanceConfig { identity_weight: 0.7, negative_weight: 1.3, ..Default::default() };
        let eval = |l: &[f32]| appearance_loss(&cfg, &features, l, shape, &neg, &u1, &u2, 1.0, None).total;
        let mut grad = vec![0.0f32; logits.len()];
        appearance_loss(&cfg, &features, &logits, shape, &neg, &u1, &u2, 1.0, Some(&mut grad));
        let scale = grad.iter().fold(0.0f32, |m, g| m.max(g.abs()));
        assert!(scale > 0.0);
        for i in 0..logits.len() {
            let h = 1e-3f32;
            let (mut lp, mut lm) = (logits.clone(), logits.clone());
            lp[i] += h;
            lm[i] -= h;
            let fd = (eval(&lp) - eval(&lm)) / f64::from(lp[i] - lm[i]);
            let err = (fd - f64::from(grad[i])).abs();
            assert!(err <= 1e-3 * f64::from(scale), "logit {i}: fd {fd} vs analytic {}", grad[i]);
        }
    }

    #[test]
    fn sampling_is_align_corners_with_border() {
        // 2×3 grid, values = 10·y + x.
        let grid: Vec<f32> = vec![0.0, 1.0, 2.0, 10.0, 11.0, 12.0];
        let taps = BilinearTaps::new(2, 3, &[[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0], [0.5, -1.0], [3.0, -7.0]]);
        let s = taps.sample(&grid, 1);
        assert_eq!(s, vec![0.0, 12.0, 6.0, 1.5, 2.0]);
    }

    #[test]
    fn config_roundtrip_and_validation() {
        let cfg: Box<dyn ContrastiveLossConfig> =
            Box::new(AppearanceConfig { samples: 7, negative_shift: 0.5, ..Default::default() });
        let text = toml::to_string(&cfg).expect("serialise");
        assert!(text.contains("kind = \"appearance\""), "{text}");
        let back: Box<dyn ContrastiveLossConfig> = toml::from_str(&text).expect("parse");
        assert_eq!(format!("{back:?}"), format!("{cfg:?}"));
        let partial: Box<dyn ContrastiveLossConfig> =
            toml::from_str("kind = \"appearance\"\nsamples = 5\n").expect("defaults fill in");
        assert_eq!(format!("{partial:?}"), format!("{:?}", AppearanceConfig { samples: 5, ..Default::default() }));
        assert!(toml::from_str::<Box<dyn ContrastiveLossConfig>>("kind = \"appearance\"\nsample = 5\n").is_err());
        let zero: Box<dyn ContrastiveLossConfig> =
            toml::from_str("kind = \"appearance\"\nsamples = 0\n").expect("parse");
        assert!(matches!(zero.build(), Err(BuildError::Invalid { ref key, .. }) if key == "samples"));
        let reg = sos_core::registry::find::<dyn ContrastiveLossConfig>(KIND).expect("registered");
        assert!((reg.default_config)().build().is_ok());
    }
}
