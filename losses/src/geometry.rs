//! The geometry contrastive loss (spec §7, §14.17): STEGO's correlation loss with the
//! inverse-L1 kernel `K(a,b) = min(1 / (Σ_c |a_c − b_c| + ε), cap)` on 3D points (`G`) and on
//! L2-normalised logits (`S`), over ALL `P²×P²` pixel pairs of two patches:
//! `L = λ_neg·helper(X, X[neg], s, s[neg], b_neg) + λ_id·helper(X, X, s, s, b_id)` with
//! `helper = mean −max(S,0)·(G_c − b)` and `G_c` the pointwise-centred `G` (no gradient).
//!
//! The `P⁴` volumes are never stored: a first pass accumulates the row means and the global
//! mean of `G`; a second pass recomputes `G` and `S` tile by tile and accumulates the loss and
//! its gradient. Both passes run in f32 with SIMD-friendly lane accumulators flushed to f64
//! every tile, in parallel over rows. The identity term pairs a patch with itself, so `G` and
//! `S` are symmetric there: its pass 2 visits each unordered pair once, carrying both orders'
//! shares of the loss and gradient.
//!
//! The all-pairs sum costs `P⁴` kernel evaluations per patch pair, most of a stage-2 step on a
//! CPU. With `samples = s` (below `P`), each patch draws `s²` of its pixels at random per step
//! and the loss is the same mean over the pairs of those pixels: an estimate of the full loss
//! whose gradient reaches the drawn pixels only, as the appearance loss samples its points
//! (STEGO's `feature_samples`). `samples = 0` (or `≥ P`) sums over every pair, as the reference.

use rand::RngCore;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{ContrastiveLoss, ContrastiveLossConfig, LossValue, PatchBatch};

use crate::normalize::{l2_normalize, l2_normalize_backward};
use crate::{validate, PatchShape};

const KIND: &str = GeometryConfig::KIND;

/// Lower bound of the channel norm when normalising the logits (`F.normalize` eps).
pub const NORM_EPS: f64 = 1e-10;

/// SIMD lanes of the inner loops.
const LANES: usize = 8;
/// Columns per tile; lane accumulators are flushed to f64 after each tile.
const TILE: usize = 512;
/// Rows per parallel task.
const ROWS: usize = 16;

/// Most parallel tasks the rows of one patch pair are split into.
const MAX_TASKS: usize = 16;

/// Pixels per patch side that each step's pairs are drawn from by default: 32² of a 64×64
/// patch's pixels give a sixteenth of the all-pairs work.
pub const DEFAULT_SAMPLES: usize = 32;

/// Settings of [`GeometryLoss`]; the shifts, weights and kernel are the reference LLFF run's
/// (`0.5,1,3,1`); `samples` departs from it (see the module documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GeometryConfig {
    /// Shift `b_id` of the identity (self-correlation) term.
    pub identity_shift: f64,
    /// Weight `λ_id` of the identity term.
    pub identity_weight: f64,
    /// Shift `b_neg` of the negative term.
    pub negative_shift: f64,
    /// Weight `λ_neg` of the negative term.
    pub negative_weight: f64,
    /// `ε` added to the L1 distance before inverting.
    pub epsilon: f64,
    /// Upper bound of the kernel.
    pub cap: f64,
    /// Depth clip applied by the renderer before forming points (see [`clip_depth`]); the
    /// loss itself receives points.
    pub depth_clip: f64,
    /// Pixels per patch side drawn for each step's pairs (`samples²` per patch); 0, or at
    /// least the patch side, pairs every pixel as the reference does.
    pub samples: usize,
}

impl Default for GeometryConfig {
    fn default() -> Self {
        GeometryConfig {
            identity_shift: 0.5,
            identity_weight: 1.0,
            negative_shift: 3.0,
            negative_weight: 1.0,
            epsilon: 0.05,
            cap: 15.0,
            depth_clip: 15.0,
            samples: DEFAULT_SAMPLES,
        }
    }
}

impl GeometryConfig {
    /// The kernel settings.
    pub fn kernel(&self) -> InverseL1Kernel {
        InverseL1Kernel { epsilon: self.epsilon as f32, cap: self.cap as f32 }
    }
}

sos_core::plugin_kind! {
    kind: "geometry",
    summary: "inverse-L1 correlation loss between rendered 3D points and logits over the pairs of pixels drawn from each patch each step (or of all its pixels)",
    default: || Box::new(GeometryConfig::default()),
    impl ContrastiveLossConfig for GeometryConfig {
        fn build(&self) -> Result<Box<dyn ContrastiveLoss>, BuildError> {
            validate::finite(KIND, "identity_shift", self.identity_shift)?;
            validate::non_negative(KIND, "identity_weight", self.identity_weight)?;
            validate::finite(KIND, "negative_shift", self.negative_shift)?;
            validate::non_negative(KIND, "negative_weight", self.negative_weight)?;
            validate::positive(KIND, "epsilon", self.epsilon)?;
            validate::positive(KIND, "cap", self.cap)?;
            validate::positive(KIND, "depth_clip", self.depth_clip)?;
            Ok(Box::new(GeometryLoss { config: self.clone() }))
        }
    }
}

/// The geometry contrastive loss (built from a validated [`GeometryConfig`]).
///
/// [`ContrastiveLoss::loss_and_grad`] treats `batch.points` as final points: the renderer is
/// expected to have clipped the depth with [`clip_depth`] (at `depth_clip`) before forming
/// them, as the reference does.
#[derive(Debug, Clone, PartialEq)]
pub struct GeometryLoss {
    config: GeometryConfig,
}

impl GeometryLoss {
    /// The settings this loss was built with.
    pub fn config(&self) -> &GeometryConfig {
        &self.config
    }
}

/// The kernel `K(a,b) = min(1 / (Σ_c |a_c − b_c| + ε), cap)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InverseL1Kernel {
    /// `ε` added to the L1 distance.
    pub epsilon: f32,
    /// Upper bound.
    pub cap: f32,
}

impl InverseL1Kernel {
    /// The kernel value given the L1 distance.
    #[inline(always)]
    pub fn of_distance(&self, l1: f32) -> f32 {
        let t = 1.0 / (l1 + self.epsilon);
        if t < self.cap {
            t
        } else {
            self.cap
        }
    }
}

/// The reference depth clip, in place over the whole batch: every value `> clip` becomes the
/// largest value `< clip` (this also catches the 1e10 empty-ray sentinel). Values equal to
/// `clip` are kept. If no value is below `clip` (the reference would fail), the clipped values
/// become `clip`. NaNs are left alone.
pub fn clip_depth(depth: &mut [f32], clip: f32) {
    let below = depth.iter().copied().filter(|&d| d < clip).fold(f32::NEG_INFINITY, f32::max);
    let fill = if below.is_finite() { below } else { clip };
    for d in depth.iter_mut().filter(|d| **d > clip) {
        *d = fill;
    }
}

/// Points `rays_o + rays_d · depth` (the directions are not normalised).
///
/// Layouts: `depth` `[n, 1, P, P]`, `rays_o` and `rays_d` `[n, 3, P, P]`; returns `[n, 3, P, P]`.
///
/// # Panics
/// If the buffers do not match `n_patches` and `pixels` (= `P²`).
pub fn points_from_depth(depth: &[f32], rays_o: &[f32], rays_d: &[f32], n_patches: usize, pixels: usize) -> Vec<f32> {
    assert_eq!(depth.len(), n_patches * pixels, "points_from_depth: depth is not [n,1,P,P]");
    assert_eq!(rays_o.len(), 3 * n_patches * pixels, "points_from_depth: rays_o is not [n,3,P,P]");
    assert_eq!(rays_d.len(), 3 * n_patches * pixels, "points_from_depth: rays_d is not [n,3,P,P]");
    let mut out = Vec::with_capacity(rays_o.len());
    for k in 0..n_patches {
        let dk = &depth[k * pixels..(k + 1) * pixels];
        for c in 0..3 {
            let r = (k * 3 + c) * pixels..(k * 3 + c + 1) * pixels;
            out.extend(rays_o[r.clone()].iter().zip(&rays_d[r]).zip(dk).map(|((o, d), t)| o + d * t));
        }
    }
    out
}

/// Largest logit channel count supported (channels are zero-padded to a compiled width).
pub const MAX_D_SEG: usize = 64;

/// Inputs of pass 2 shared by all rows of one patch pair, with `D` logit channels (zero
/// channels pad the real ones: they add nothing to the L1 distance and get no gradient).
struct PairView<'a, const D: usize> {
    pa: [&'a [f32]; 3],
    pb: [&'a [f32]; 3],
    /// Normalised logits of patch a / b, `D` slices of `m`.
    sa: [&'a [f32]; D],
    sb: [&'a [f32]; D],
    kernel: InverseL1Kernel,
}

/// Pass 1 for `W` consecutive columns at `q0`: adds `G[p, q0..q0+W]` into `acc`.
#[inline(always)]
fn g_block<const W: usize>(a: [f32; 3], pb: [&[f32]; 3], q0: usize, k: InverseL1Kernel, acc: &mut [f32; LANES]) {
    let (bx, by, bz) = (&pb[0][q0..q0 + W], &pb[1][q0..q0 + W], &pb[2][q0..q0 + W]);
    for j in 0..W {
        acc[j] += k.of_distance((a[0] - bx[j]).abs() + (a[1] - by[j]).abs() + (a[2] - bz[j]).abs());
    }
}

/// `Σ_q G[p,q]` of one row.
fn g_row_sum(a: [f32; 3], pb: [&[f32]; 3], k: InverseL1Kernel) -> f64 {
    let m = pb[0].len();
    let mut total = 0.0f64;
    for t0 in (0..m).step_by(TILE) {
        let t1 = (t0 + TILE).min(m);
        let mut acc = [0.0f32; LANES];
        let mut q = t0;
        while q + LANES <= t1 {
            g_block::<LANES>(a, pb, q, k, &mut acc);
            q += LANES;
        }
        while q < t1 {
            g_block::<1>(a, pb, q, k, &mut acc);
            q += 1;
        }
        total += acc.iter().map(|&v| f64::from(v)).sum::<f64>();
    }
    total
}

/// Lane accumulators of one row over one tile in pass 2.
struct RowAcc<const D: usize> {
    loss: [f32; LANES],
    ga: [[f32; LANES]; D],
}

/// Pass 2 for `W` consecutive columns at `q0` of row `p`: accumulates `S·(G_c − b)` into
/// `acc.loss`, and `∂/∂L1 · sign` (before the `1/M` factor) into `acc.ga` and `gb` (`[D, m]`).
///
/// `SYMMETRIC` (a patch against itself, `q > p`): the pair stands for `(p, q)` and `(q, p)`,
/// whose centred kernels differ only in their row shift, so the weight is
/// `2G + shift[p] + shift[q]` (`shift` = `row_shift`).
// Lane loops index fixed-width arrays on purpose: that is the shape LLVM vectorises.
#[allow(clippy::needless_range_loop, clippy::too_many_arguments)]
#[inline(always)]
fn pair_block<const W: usize, const D: usize, const SYMMETRIC: bool>(
    v: &PairView<D>,
    a: ([f32; 3], [f32; D]),
    row_shift: f32,
    shift: &[f32],
    q0: usize,
    acc: &mut RowAcc<D>,
    gb: &mut [f32],
) {
    let k = v.kernel;
    let m = v.pb[0].len();
    let (pa, sa) = a;
    let (bx, by, bz) = (&v.pb[0][q0..q0 + W], &v.pb[1][q0..q0 + W], &v.pb[2][q0..q0 + W]);
    let mut l1 = [0.0f32; LANES];
    for c in 0..D {
        let b = &v.sb[c][q0..q0 + W];
        for j in 0..W {
            l1[j] += (sa[c] - b[j]).abs();
        }
    }
    let mut coef = [0.0f32; LANES];
    let col_shift = if SYMMETRIC { &shift[q0..q0 + W] } else { &[] };
    for j in 0..W {
        let g = k.of_distance((pa[0] - bx[j]).abs() + (pa[1] - by[j]).abs() + (pa[2] - bz[j]).abs());
        let centred = if SYMMETRIC { (g + row_shift) + (g + col_shift[j]) } else { g + row_shift };
        let t = 1.0 / (l1[j] + k.epsilon);
        // S > 0 always (the zero clamp is a no-op); the cap passes no gradient.
        let s = if t < k.cap { t } else { k.cap };
        acc.loss[j] += s * centred;
        // ∂(S·Gc)/∂L1 = −t²·Gc below the cap; the loss carries a minus sign, so +t²·Gc.
        coef[j] = if t <= k.cap { centred * t * t } else { 0.0 };
    }
    for c in 0..D {
        let b = &v.sb[c][q0..q0 + W];
        // Signs first into a local array: keeps the loop free of stores that could alias.
        let mut sg = [0.0f32; LANES];
        for j in 0..W {
            let diff = sa[c] - b[j];
            sg[j] = (if diff > 0.0 { coef[j] } else { 0.0 }) - (if diff < 0.0 { coef[j] } else { 0.0 });
        }
        for j in 0..W {
            acc.ga[c][j] += sg[j];
        }
        let gbc = &mut gb[c * m + q0..c * m + q0 + W];
        for j in 0..W {
            gbc[j] -= sg[j];
        }
    }
}

/// Accumulated result of pass 2 over some rows of one patch pair.
struct PairAcc {
    /// `Σ S·(G_c − b)`.
    loss: f64,
    /// Gradient w.r.t. `ŝa` (`[D, m]`), before the `1/M` factor.
    ga: Vec<f64>,
    /// Gradient w.r.t. `ŝb` (`[D, m]`), before the `1/M` factor.
    gb: Vec<f64>,
}

impl PairAcc {
    fn new(d: usize, m: usize) -> Self {
        PairAcc { loss: 0.0, ga: vec![0.0; d * m], gb: vec![0.0; d * m] }
    }

    fn merge(mut self, other: PairAcc) -> PairAcc {
        self.loss += other.loss;
        for (a, b) in self.ga.iter_mut().zip(&other.ga) {
            *a += b;
        }
        for (a, b) in self.gb.iter_mut().zip(&other.gb) {
            *a += b;
        }
        self
    }
}

/// Pass 2 over rows `rows` of one patch pair; `row_shift[p] = mean(G) − b − mean_q G[p,:]`.
/// `SYMMETRIC` (a patch against itself) visits only the columns right of the diagonal (see
/// [`pair_block`]); the diagonal is left to the caller.
fn pair_rows<const D: usize, const SYMMETRIC: bool>(
    v: &PairView<D>,
    rows: std::ops::Range<usize>,
    row_shift: &[f32],
    out: &mut PairAcc,
) {
    let m = v.pb[0].len();
    let mut gb = vec![0.0f32; D * m];
    for p in rows {
        let a = ([v.pa[0][p], v.pa[1][p], v.pa[2][p]], std::array::from_fn(|c| v.sa[c][p]));
        let (mut loss, mut ga) = (0.0f64, [0.0f64; D]);
        let first = if SYMMETRIC { p + 1 } else { 0 };
        for t0 in (first..m).step_by(TILE) {
            let t1 = (t0 + TILE).min(m);
            let mut acc = RowAcc { loss: [0.0; LANES], ga: [[0.0; LANES]; D] };
            let mut q = t0;
            while q + LANES <= t1 {
                pair_block::<LANES, D, SYMMETRIC>(v, a, row_shift[p], row_shift, q, &mut acc, &mut gb);
                q += LANES;
            }
            while q < t1 {
                pair_block::<1, D, SYMMETRIC>(v, a, row_shift[p], row_shift, q, &mut acc, &mut gb);
                q += 1;
            }
            loss += acc.loss.iter().map(|&x| f64::from(x)).sum::<f64>();
            for (g, lanes) in ga.iter_mut().zip(&acc.ga) {
                *g += lanes.iter().map(|&x| f64::from(x)).sum::<f64>();
            }
        }
        out.loss += loss;
        for (c, g) in ga.into_iter().enumerate() {
            out.ga[c * m + p] += g;
        }
    }
    for (o, g) in out.gb.iter_mut().zip(gb) {
        *o += f64::from(g);
    }
}

/// Pass 2 of all patch pairs with `D ≥ d` (zero-padded) channels. Returns `Σ S·(G_c − b)` and
/// adds the gradient w.r.t. the normalised logits (before `1/M`) into `grad_hat` (`[n, d, m]`).
#[allow(clippy::too_many_arguments)]
fn pass2<const D: usize>(
    points: &[f32],
    shat: &[f32],
    d: usize,
    m: usize,
    partner: &[usize],
    row_sums: &[Vec<f64>],
    shift: f64,
    global_mean: f64,
    kernel: InverseL1Kernel,
    grad_hat: &mut [f64],
) -> f64 {
    let zeros = vec![0.0f32; m];
    let pts = |k: usize| -> [&[f32]; 3] { std::array::from_fn(|c| &points[(k * 3 + c) * m..(k * 3 + c + 1) * m]) };
    let sl = |k: usize| -> [&[f32]; D] {
        std::array::from_fn(|c| if c < d { &shat[(k * d + c) * m..(k * d + c + 1) * m] } else { &zeros[..] })
    };
    let mut loss = 0.0f64;
    for (k, sums) in row_sums.iter().enumerate() {
        let j = partner[k];
        let view = PairView::<D> { pa: pts(k), pb: pts(j), sa: sl(k), sb: sl(j), kernel };
        let row_shift: Vec<f32> = sums.iter().map(|&s| (global_mean - shift - s / m as f64) as f32).collect();
        let symmetric = j == k;
        // A fixed split of the rows into tasks, merged in order: the same sums every run.
        let task_rows = ROWS.max(m.div_ceil(MAX_TASKS));
        let acc = (0..m.div_ceil(task_rows))
            .into_par_iter()
            .map(|task| {
                let mut acc = PairAcc::new(D, m);
                let rows = task * task_rows..((task + 1) * task_rows).min(m);
                for start in rows.clone().step_by(ROWS) {
                    let block = start..(start + ROWS).min(rows.end);
                    if symmetric {
                        pair_rows::<D, true>(&view, block, &row_shift, &mut acc);
                    } else {
                        pair_rows::<D, false>(&view, block, &row_shift, &mut acc);
                    }
                }
                acc
            })
            .collect::<Vec<_>>()
            .into_iter()
            .fold(PairAcc::new(D, m), PairAcc::merge);
        loss += acc.loss;
        if symmetric {
            // The diagonal: zero distances, so both kernels are K(0), and no gradient (no sign).
            let k0 = kernel.of_distance(0.0);
            loss += row_shift.iter().map(|&r| f64::from(k0 * (k0 + r))).sum::<f64>();
        }
        // Only the first d (real) channels carry gradient.
        for (g, a) in grad_hat[k * d * m..(k + 1) * d * m].iter_mut().zip(&acc.ga) {
            *g += a;
        }
        for (g, b) in grad_hat[j * d * m..(j + 1) * d * m].iter_mut().zip(&acc.gb) {
            *g += b;
        }
    }
    loss
}

/// One geometry term `helper(X, X[partner], s, s[partner], shift)` over all pixel pairs, where
/// `X` are the points. Adds `grad_scale · ∂term/∂logits` into `grad_logits` (if given) and
/// returns the term.
///
/// Layouts: `points` `[n, 3, P, P]`, `logits` `[n, d_seg, P, P]` (as `shape`).
///
/// # Panics
/// If the buffers do not match `shape`, a partner index is out of range, or
/// `d_seg > MAX_D_SEG`.
#[allow(clippy::too_many_arguments)]
pub fn geometry_term(
    points: &[f32],
    logits: &[f32],
    shape: PatchShape,
    partner: &[usize],
    shift: f32,
    kernel: InverseL1Kernel,
    grad_scale: f32,
    grad_logits: Option<&mut [f32]>,
) -> f64 {
    let (n, d, m) = (shape.n_patches, shape.d_seg, shape.pixels());
    assert_eq!(points.len(), n * 3 * m, "geometry: points are not [n, 3, P, P]");
    assert_eq!(logits.len(), shape.logits_len(), "geometry: logits are not [n, d_seg, P, P]");
    assert_eq!(partner.len(), n, "geometry: need one partner per patch");
    assert!(partner.iter().all(|&j| j < n), "geometry: partner index out of range");
    assert!(d <= MAX_D_SEG, "geometry: at most {MAX_D_SEG} logit channels are supported");
    if n == 0 || m == 0 {
        return 0.0;
    }
    let pts = |k: usize| -> [&[f32]; 3] {
        let base = k * 3 * m;
        [&points[base..base + m], &points[base + m..base + 2 * m], &points[base + 2 * m..base + 3 * m]]
    };

    // Normalised logits (f64 for the backward, f32 for the kernel).
    let mut shat = Vec::with_capacity(n);
    let mut shat32 = Vec::with_capacity(logits.len());
    for k in 0..n {
        let x: Vec<f64> = logits[k * d * m..(k + 1) * d * m].iter().map(|&v| f64::from(v)).collect();
        let (y, den) = l2_normalize(&x, d, m, NORM_EPS);
        shat32.extend(y.iter().map(|&v| v as f32));
        shat.push((y, den));
    }

    // Pass 1: row sums of G and the global mean over the whole batch.
    let row_sums: Vec<Vec<f64>> = (0..n)
        .map(|k| {
            let (pa, pb) = (pts(k), pts(partner[k]));
            (0..m)
                .into_par_iter()
                .with_min_len(ROWS)
                .map(|p| g_row_sum([pa[0][p], pa[1][p], pa[2][p]], pb, kernel))
                .collect()
        })
        .collect();
    let total = n as f64 * m as f64 * m as f64;
    let global_mean = row_sums.iter().flatten().sum::<f64>() / total;

    // Pass 2: loss and gradient w.r.t. the normalised logits, compiled for a few channel
    // counts (padded with zero channels up to the next one).
    let mut grad_hat = vec![0.0f64; logits.len()];
    let args = (points, &shat32[..], d, m, partner, &row_sums[..], f64::from(shift), global_mean, kernel);
    macro_rules! run {
        ($dd:literal) => {
            pass2::<$dd>(args.0, args.1, args.2, args.3, args.4, args.5, args.6, args.7, args.8, &mut grad_hat)
        };
    }
    let loss = match d {
        1 => run!(1),
        2 => run!(2),
        3 => run!(3),
        4 => run!(4),
        5..=8 => run!(8),
        9..=16 => run!(16),
        17..=32 => run!(32),
        _ => run!(64),
    };

    if let Some(grad) = grad_logits {
        assert_eq!(grad.len(), logits.len(), "geometry: grad_logits is not [n, d_seg, P, P]");
        let scale = f64::from(grad_scale) / total;
        for (k, (y, den)) in shat.iter().enumerate() {
            let r = k * d * m..(k + 1) * d * m;
            let gx = l2_normalize_backward(y, den, &grad_hat[r.clone()], d, m, NORM_EPS);
            for (o, g) in grad[r].iter_mut().zip(gx) {
                *o += (scale * g) as f32;
            }
        }
    }
    -loss / total
}

/// The full geometry loss on points (`[n, 3, P, P]`): returns the unweighted terms and
/// `total = λ_neg·negative + λ_id·identity`, and adds `grad_scale · ∂total/∂logits` into
/// `grad_logits` (if given). The points are used as given (no depth clip).
///
/// # Panics
/// On shape mismatches, as [`geometry_term`].
pub fn geometry_loss(
    config: &GeometryConfig,
    points: &[f32],
    logits: &[f32],
    shape: PatchShape,
    negatives: &[usize],
    grad_scale: f32,
    mut grad_logits: Option<&mut [f32]>,
) -> LossValue {
    let identity: Vec<usize> = (0..shape.n_patches).collect();
    let kernel = config.kernel();
    let neg = geometry_term(
        points,
        logits,
        shape,
        negatives,
        config.negative_shift as f32,
        kernel,
        grad_scale * config.negative_weight as f32,
        grad_logits.as_deref_mut(),
    );
    let id = geometry_term(
        points,
        logits,
        shape,
        &identity,
        config.identity_shift as f32,
        kernel,
        grad_scale * config.identity_weight as f32,
        grad_logits,
    );
    LossValue {
        total: config.negative_weight * neg + config.identity_weight * id,
        terms: vec![("geometry/identity".to_string(), id), ("geometry/negative".to_string(), neg)],
    }
}

/// The reference pipeline from depth: clips a copy of `depth` (`[n, 1, P, P]`) with
/// [`clip_depth`] at `config.depth_clip`, forms points with [`points_from_depth`] and
/// evaluates [`geometry_loss`].
///
/// # Panics
/// On shape mismatches.
#[allow(clippy::too_many_arguments)]
pub fn geometry_loss_from_depth(
    config: &GeometryConfig,
    depth: &[f32],
    rays_o: &[f32],
    rays_d: &[f32],
    logits: &[f32],
    shape: PatchShape,
    negatives: &[usize],
    grad_scale: f32,
    grad_logits: Option<&mut [f32]>,
) -> LossValue {
    let mut depth = depth.to_vec();
    clip_depth(&mut depth, config.depth_clip as f32);
    let points = points_from_depth(&depth, rays_o, rays_d, shape.n_patches, shape.pixels());
    geometry_loss(config, &points, logits, shape, negatives, grad_scale, grad_logits)
}

impl ContrastiveLoss for GeometryLoss {
    /// Evaluates [`geometry_loss`] on `batch.points` (already depth-clipped by the renderer),
    /// over every pixel pair or, with `samples` below the patch side, over the pairs of
    /// `samples²` pixels per patch drawn from `rng` (nothing is drawn otherwise).
    ///
    /// # Panics
    /// If the batch is inconsistent (see [`geometry_term`]) or `grad_logits` does not match
    /// `batch.logits`.
    fn loss_and_grad(
        &self,
        batch: &PatchBatch,
        rng: &mut dyn RngCore,
        grad_scale: f32,
        grad_logits: &mut [f32],
    ) -> LossValue {
        let shape = PatchShape { n_patches: batch.n_patches, d_seg: batch.d_seg, patch: batch.patch };
        let side = self.config.samples;
        if side == 0 || side >= batch.patch {
            return geometry_loss(
                &self.config,
                batch.points,
                batch.logits,
                shape,
                batch.negatives,
                grad_scale,
                Some(grad_logits),
            );
        }
        let drawn = PixelSample::draw(shape, side, rng);
        let (points, logits) = drawn.gather(batch.points, batch.logits);
        let mut grad = vec![0.0f32; logits.len()];
        let value =
            geometry_loss(&self.config, &points, &logits, drawn.shape, batch.negatives, grad_scale, Some(&mut grad));
        drawn.scatter_add(&grad, grad_logits);
        value
    }
}

/// `side²` distinct pixels of each patch, drawn uniformly, as a smaller batch of `side × side`
/// "patches" (the loss uses only the pixels' pairs, never their layout).
///
/// Each pair of distinct pixels is then drawn with the same probability, so the logits'
/// expected gradient is the all-pairs gradient (to a factor 1 − 1/side²). The loss value is
/// the drawn pairs' mean, in which the pixels' pairs with themselves (no gradient; the kernel's
/// cap) weigh 1/side² rather than 1/P²: it is comparable between runs with the same `samples`.
struct PixelSample {
    /// Layout of the gathered batch.
    shape: PatchShape,
    /// The full batch's layout.
    full: PatchShape,
    /// Drawn pixel indices, `side²` per patch, ascending within a patch.
    pixels: Vec<usize>,
}

impl PixelSample {
    fn draw(full: PatchShape, side: usize, rng: &mut dyn RngCore) -> Self {
        let (m, count) = (full.pixels(), side * side);
        let mut pixels = Vec::with_capacity(full.n_patches * count);
        let mut order: Vec<usize> = (0..m).collect();
        for _ in 0..full.n_patches {
            // A partial Fisher-Yates shuffle: the first `count` entries are a uniform draw.
            for i in 0..count {
                let j = i + (rng.next_u64() % (m - i) as u64) as usize;
                order.swap(i, j);
            }
            let start = pixels.len();
            pixels.extend_from_slice(&order[..count]);
            pixels[start..].sort_unstable();
        }
        PixelSample { shape: PatchShape { patch: side, ..full }, full, pixels }
    }

    fn count(&self) -> usize {
        self.shape.pixels()
    }

    /// The drawn pixels' points (`[n, 3, count]`) and logits (`[n, d, count]`).
    fn gather(&self, points: &[f32], logits: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let (m, c) = (self.full.pixels(), self.count());
        let pick = |src: &[f32], channels: usize| -> Vec<f32> {
            let mut out = Vec::with_capacity(self.full.n_patches * channels * c);
            for (k, drawn) in self.pixels.chunks(c).enumerate() {
                for ch in 0..channels {
                    let row = &src[(k * channels + ch) * m..(k * channels + ch + 1) * m];
                    out.extend(drawn.iter().map(|&p| row[p]));
                }
            }
            out
        };
        (pick(points, 3), pick(logits, self.full.d_seg))
    }

    /// Adds the gathered batch's logit gradient into the full batch's at the drawn pixels.
    fn scatter_add(&self, grad: &[f32], full_grad: &mut [f32]) {
        let (m, c, d) = (self.full.pixels(), self.count(), self.full.d_seg);
        for (k, drawn) in self.pixels.chunks(c).enumerate() {
            for ch in 0..d {
                let src = &grad[(k * d + ch) * c..(k * d + ch + 1) * c];
                let dst = &mut full_grad[(k * d + ch) * m..(k * d + ch + 1) * m];
                for (&p, &g) in drawn.iter().zip(src) {
                    dst[p] += g;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixtures::{assert_close, Fixture};
    use rand::{Rng, SeedableRng};

    /// Straightforward f64 version with the full `[n, m, m]` matrices.
    fn naive_term(
        points: &[f64],
        logits: &[f64],
        shape: PatchShape,
        partner: &[usize],
        shift: f64,
        eps: f64,
        cap: f64,
    ) -> f64 {
        let (n, d, m) = (shape.n_patches, shape.d_seg, shape.pixels());
        let kern = |l1: f64| (1.0 / (l1 + eps)).min(cap);
        let mut shat = Vec::new();
        for k in 0..n {
            shat.extend(l2_normalize(&logits[k * d * m..(k + 1) * d * m], d, m, NORM_EPS).0);
        }
        let pt = |k: usize, c: usize, p: usize| points[(k * 3 + c) * m + p];
        let sv = |k: usize, c: usize, p: usize| shat[(k * d + c) * m + p];
        let mut g = vec![0.0f64; n * m * m];
        for k in 0..n {
            for p in 0..m {
                for q in 0..m {
                    let l1: f64 = (0..3).map(|c| (pt(k, c, p) - pt(partner[k], c, q)).abs()).sum();
                    g[(k * m + p) * m + q] = kern(l1);
                }
            }
        }
        let gm = g.iter().sum::<f64>() / g.len() as f64;
        let mut loss = 0.0;
        for k in 0..n {
            for p in 0..m {
                let row = &g[(k * m + p) * m..(k * m + p + 1) * m];
                let rm = row.iter().sum::<f64>() / m as f64;
                for (q, gv) in row.iter().enumerate() {
                    let l1: f64 = (0..d).map(|c| (sv(k, c, p) - sv(partner[k], c, q)).abs()).sum();
                    let s = kern(l1).max(0.0);
                    loss -= s * (gv - rm + gm - shift);
                }
            }
        }
        loss / g.len() as f64
    }

    struct Case {
        points: Vec<f32>,
        logits: Vec<f32>,
        shape: PatchShape,
        neg: Vec<usize>,
    }

    fn random_case(seed: u64, n: usize, d: usize, patch: usize) -> Case {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let shape = PatchShape { n_patches: n, d_seg: d, patch };
        // Points on a smooth-ish surface with noise, so both capped and uncapped pairs occur.
        let m = shape.pixels();
        let mut points = Vec::with_capacity(n * 3 * m);
        for _ in 0..n {
            let z0: f32 = rng.gen_range(1.0..4.0);
            for c in 0..3 {
                for p in 0..m {
                    let (y, x) = ((p / patch) as f32 / patch as f32, (p % patch) as f32 / patch as f32);
                    let base = [x, y, z0 + 0.3 * x * y][c];
                    points.push(base + rng.gen_range(-0.01..0.01));
                }
            }
        }
        let logits = (0..shape.logits_len()).map(|_| rng.gen_range(-2.0..2.0)).collect();
        let neg = crate::random::random_derangement(n, &mut rng);
        Case { points, logits, shape, neg }
    }

    fn widen(x: &[f32]) -> Vec<f64> {
        x.iter().map(|&v| f64::from(v)).collect()
    }

    #[test]
    fn matches_reference_fixture() {
        let fx = Fixture::geometry();
        let (sshape, logits) = fx.array_f32("seg");
        let shape = PatchShape { n_patches: sshape[0], d_seg: sshape[1], patch: sshape[2] };
        let cfg = GeometryConfig {
            identity_shift: fx.scalar("b_id"),
            negative_shift: fx.scalar("b_neg"),
            epsilon: fx.scalar("eps"),
            cap: fx.scalar("cap"),
            depth_clip: fx.scalar("depth_clip"),
            ..GeometryConfig::default()
        };
        let mut grad = vec![0.0f32; logits.len()];
        let v = geometry_loss_from_depth(
            &cfg,
            &fx.array_f32("depth").1,
            &fx.array_f32("rays_o").1,
            &fx.array_f32("rays_d").1,
            &logits,
            shape,
            &fx.neg(),
            1.0,
            Some(&mut grad),
        );
        let term = |name: &str| v.terms.iter().find(|(k, _)| k == name).map(|t| t.1).expect(name);
        assert_close("identity", &[term("geometry/identity")], &[fx.scalar("self_term")], 1e-5, 0.0);
        assert_close("negative", &[term("geometry/negative")], &[fx.scalar("neg_term")], 1e-5, 0.0);
        // The total is a difference of two nearly equal terms: compare it relative to them.
        let scale = fx.scalar("neg_term").abs();
        assert!((v.total - fx.scalar("total")).abs() <= 1e-5 * scale, "total {} vs {}", v.total, fx.scalar("total"));
        let reference = fx.array("grad_seg").1;
        let grad = widen(&grad);
        // Both sides accumulate in f32: a logit's gradient sums the identity and the negative
        // pair terms of every pixel of the patch.
        let accumulation = 2 * shape.patch * shape.patch;
        sos_core::testing::fixture::assert_f32_gradients("grad_seg", &grad, &reference, accumulation);
    }

    #[test]
    fn tiled_equals_naive() {
        let case = random_case(5, 3, 2, 8);
        let k = InverseL1Kernel { epsilon: 0.05, cap: 15.0 };
        let (pts, lg) = (widen(&case.points), widen(&case.logits));
        let identity: Vec<usize> = (0..3).collect();
        for (partner, shift) in [(&case.neg, 3.0f32), (&identity, 0.5)] {
            let tiled = geometry_term(&case.points, &case.logits, case.shape, partner, shift, k, 1.0, None);
            let naive = naive_term(&pts, &lg, case.shape, partner, f64::from(shift), 0.05, 15.0);
            assert!((tiled - naive).abs() <= 1e-6 * naive.abs().max(1.0), "tiled {tiled} vs naive {naive}");
        }
        // Zero-padded channel counts (5 → 8).
        let case = random_case(7, 2, 5, 6);
        let (pts, lg) = (widen(&case.points), widen(&case.logits));
        let tiled = geometry_term(&case.points, &case.logits, case.shape, &case.neg, 2.0, k, 1.0, None);
        let naive = naive_term(&pts, &lg, case.shape, &case.neg, 2.0, 0.05, 15.0);
        assert!((tiled - naive).abs() <= 1e-6 * naive.abs().max(1.0), "tiled {tiled} vs naive {naive}");
        // A size that is not a multiple of the lanes or the tile, with more channels.
        let case = random_case(6, 2, 3, 27);
        let (pts, lg) = (widen(&case.points), widen(&case.logits));
        let tiled = geometry_term(&case.points, &case.logits, case.shape, &case.neg, 1.0, k, 1.0, None);
        let naive = naive_term(&pts, &lg, case.shape, &case.neg, 1.0, 0.05, 15.0);
        assert!((tiled - naive).abs() <= 1e-6 * naive.abs().max(1.0), "tiled {tiled} vs naive {naive}");
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let case = random_case(9, 3, 2, 5);
        let cfg = GeometryConfig { identity_weight: 0.8, negative_weight: 1.2, ..Default::default() };
        let pts = widen(&case.points);
        let identity: Vec<usize> = (0..3).collect();
        let eval = |lg: &[f64]| {
            cfg.negative_weight * naive_term(&pts, lg, case.shape, &case.neg, cfg.negative_shift, cfg.epsilon, cfg.cap)
                + cfg.identity_weight
                    * naive_term(&pts, lg, case.shape, &identity, cfg.identity_shift, cfg.epsilon, cfg.cap)
        };
        let mut grad = vec![0.5f32; case.logits.len()];
        geometry_loss(&cfg, &case.points, &case.logits, case.shape, &case.neg, 2.0, Some(&mut grad));
        let lg = widen(&case.logits);
        let scale = grad.iter().fold(0.0f32, |m, g| m.max((g - 0.5).abs()));
        assert!(scale > 0.0);
        for i in 0..lg.len() {
            let h = 1e-6;
            let (mut lp, mut lm) = (lg.clone(), lg.clone());
            lp[i] += h;
            lm[i] -= h;
            let fd = 2.0 * (eval(&lp) - eval(&lm)) / (2.0 * h);
            let an = f64::from(grad[i]) - 0.5;
            assert!((fd - an).abs() <= 1e-4 * f64::from(scale), "logit {i}: fd {fd} vs analytic {an}");
        }
    }

    #[test]
    fn trait_impl_uses_points_as_given() {
        let case = random_case(2, 4, 2, 6);
        let loss = GeometryConfig::default().build().expect("builds");
        let batch = PatchBatch {
            n_patches: 4,
            patch: 6,
            d_seg: 2,
            logits: &case.logits,
            points: &case.points,
            features: &[],
            negatives: &case.neg,
        };
        let mut g1 = vec![0.0f32; case.logits.len()];
        let v1 = loss.loss_and_grad(&batch, &mut rand::rngs::StdRng::seed_from_u64(0), 1.0, &mut g1);
        let (v2, g2) = all_pairs(&case);
        assert_eq!(v1, v2);
        assert_eq!(g1, g2);
        assert_eq!(v1.terms.len(), 2);
    }

    /// The default loss over every pixel pair, with its logit gradient.
    fn all_pairs(case: &Case) -> (LossValue, Vec<f32>) {
        let mut grad = vec![0.0f32; case.logits.len()];
        let value = geometry_loss(
            &GeometryConfig::default(),
            &case.points,
            &case.logits,
            case.shape,
            &case.neg,
            1.0,
            Some(&mut grad),
        );
        (value, grad)
    }

    /// The sampled loss of one draw, with the pixels it drew (drawn again from the same seed).
    fn sampled(case: &Case, side: usize, seed: u64) -> (LossValue, Vec<f32>, PixelSample) {
        let cfg = GeometryConfig { samples: side, ..Default::default() };
        let batch = PatchBatch {
            n_patches: case.shape.n_patches,
            patch: case.shape.patch,
            d_seg: case.shape.d_seg,
            logits: &case.logits,
            points: &case.points,
            features: &[],
            negatives: &case.neg,
        };
        let mut grad = vec![0.0f32; case.logits.len()];
        let value = cfg.build().expect("builds").loss_and_grad(
            &batch,
            &mut rand::rngs::StdRng::seed_from_u64(seed),
            1.0,
            &mut grad,
        );
        let drawn = PixelSample::draw(case.shape, side, &mut rand::rngs::StdRng::seed_from_u64(seed));
        (value, grad, drawn)
    }

    #[test]
    fn sampled_pixels_are_the_loss_of_the_drawn_pixels_and_only_they_get_gradient() {
        let case = random_case(5, 4, 2, 12);
        let (value, grad, drawn) = sampled(&case, 5, 9);
        let m = case.shape.pixels();
        for patch in drawn.pixels.chunks(25) {
            assert!(patch.windows(2).all(|w| w[0] < w[1]), "pixels drawn twice: {patch:?}");
            assert!(patch.iter().all(|&p| p < m));
        }
        let (points, logits) = drawn.gather(&case.points, &case.logits);
        let mut small_grad = vec![0.0f32; logits.len()];
        let expected = geometry_loss(
            &GeometryConfig::default(),
            &points,
            &logits,
            drawn.shape,
            &case.neg,
            1.0,
            Some(&mut small_grad),
        );
        assert_eq!(value, expected);
        let mut full = vec![0.0f32; case.logits.len()];
        drawn.scatter_add(&small_grad, &mut full);
        assert_eq!(grad, full);
        let touched = grad.iter().filter(|g| **g != 0.0).count();
        assert!(touched > 0 && touched <= 4 * 2 * 25, "{touched} logits got a gradient");
    }

    #[test]
    fn sampled_pixels_estimate_the_all_pairs_gradient() {
        let case = random_case(6, 4, 2, 12);
        let full = all_pairs(&case).1;
        let (side, draws) = (6, 2000);
        let (mut sum, mut sum_sq) = (vec![0.0f64; full.len()], vec![0.0f64; full.len()]);
        for seed in 0..draws {
            for (i, g) in sampled(&case, side, seed).1.into_iter().enumerate() {
                sum[i] += f64::from(g);
                sum_sq[i] += f64::from(g) * f64::from(g);
            }
        }
        let n = draws as f64;
        let (mut error, mut spread, mut norm) = (0.0f64, 0.0f64, 0.0f64);
        for i in 0..full.len() {
            let mean = sum[i] / n;
            error += (mean - f64::from(full[i])).powi(2);
            spread += (sum_sq[i] / n - mean * mean) / (n - 1.0);
            norm += f64::from(full[i]).powi(2);
        }
        // A pair of distinct pixels is drawn with probability s²(s²−1)/(m(m−1)) and weighs
        // 1/s² against 1/m²: the expected gradient is (1 − 1/s²)/(1 − 1/m) of the full one,
        // plus the drawn pixels' own means in the centring, also of order 1/s².
        let bias = 2.0 / (side * side) as f64 * norm.sqrt();
        assert!(
            error.sqrt() <= 4.0 * spread.sqrt() + bias,
            "mean gradient off by {} (norm {}, standard error {}, bias bound {bias})",
            error.sqrt(),
            norm.sqrt(),
            spread.sqrt()
        );
    }

    #[test]
    fn depth_clip_replaces_values_above() {
        let mut d = vec![1.0, 20.0, 14.5, 1e10, 15.0, 3.0];
        clip_depth(&mut d, 15.0);
        assert_eq!(d, vec![1.0, 14.5, 14.5, 14.5, 15.0, 3.0]);
        let mut all_far = vec![16.0, 1e10];
        clip_depth(&mut all_far, 15.0);
        assert_eq!(all_far, vec![15.0, 15.0]);
        let p = points_from_depth(&[2.0], &[1.0, 2.0, 3.0], &[0.5, -1.0, 0.0], 1, 1);
        assert_eq!(p, vec![2.0, 0.0, 3.0]);
    }

    #[test]
    fn config_roundtrip_and_validation() {
        let cfg: Box<dyn ContrastiveLossConfig> =
            Box::new(GeometryConfig { negative_shift: 1.0, cap: 10.0, ..Default::default() });
        let text = toml::to_string(&cfg).expect("serialise");
        assert!(text.contains("kind = \"geometry\""), "{text}");
        let back: Box<dyn ContrastiveLossConfig> = toml::from_str(&text).expect("parse");
        assert_eq!(format!("{back:?}"), format!("{cfg:?}"));
        assert!(toml::from_str::<Box<dyn ContrastiveLossConfig>>("kind = \"geometry\"\neps = 0.1\n").is_err());
        for bad in ["epsilon = 0.0", "cap = -1.0", "depth_clip = 0.0", "identity_weight = -1.0"] {
            let c: Box<dyn ContrastiveLossConfig> =
                toml::from_str(&format!("kind = \"geometry\"\n{bad}\n")).expect("parse");
            assert!(matches!(c.build(), Err(BuildError::Invalid { .. })), "{bad} accepted");
        }
        let reg = sos_core::registry::find::<dyn ContrastiveLossConfig>(KIND).expect("registered");
        assert!((reg.default_config)().build().is_ok());
    }
}
