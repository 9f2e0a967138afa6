//! Numerical stress tests of the contrastive losses and pair miners: zero-norm and identical
//! teacher features, zero, constant, tiny and huge logits, constant and sentinel depths, zero or
//! identical \[CLS\] vectors. Totals, terms and gradients must stay finite, and the degenerate
//! cases must take the values the formulas give.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use sos_core::plugin::{ContrastiveLossConfig, FeatureMap, LossValue, PairMinerConfig, PatchBatch};
use sos_core::render::composite::EMPTY_RAY_DEPTH;
use sos_losses::geometry::{clip_depth, geometry_loss_from_depth};
use sos_losses::{AppearanceConfig, ClsCosineConfig, GeometryConfig, PatchShape, RandomConfig};

const N: usize = 3;
const D: usize = 2;
const P: usize = 6;
const M: usize = P * P;
/// Teacher grid side and channels.
const G: usize = 3;
const C: usize = 5;

fn maps(value: impl Fn(usize, usize) -> f32) -> Vec<FeatureMap> {
    (0..N)
        .map(|k| FeatureMap {
            channels: C,
            height: G,
            width: G,
            data: (0..C * G * G).map(|i| value(k, i)).collect(),
            cls: vec![1.0; 4],
            saliency: None,
        })
        .collect()
}

/// Teacher feature cases: (name, maps).
fn feature_cases() -> Vec<(&'static str, Vec<FeatureMap>)> {
    let mut rng = StdRng::seed_from_u64(1);
    let random: Vec<f32> = (0..N * C * G * G).map(|_| rng.gen_range(-1.0..1.0)).collect();
    vec![
        ("zero", maps(|_, _| 0.0)),
        ("identical", maps(|_, _| 0.8)),
        ("identical patches", maps(|_, i| (i as f32 * 0.3).sin())),
        ("tiny", maps(|k, i| 1e-38 * random[k * C * G * G + i])),
        ("huge", maps(|k, i| 1e30 * random[k * C * G * G + i])),
        ("max", maps(|k, i| if random[k * C * G * G + i] > 0.0 { f32::MAX } else { -f32::MAX })),
        ("random", maps(|k, i| random[k * C * G * G + i])),
    ]
}

/// Channel of entry `i` of a `[N, D, P, P]` buffer.
fn channel_of(i: usize) -> usize {
    (i / M) % D
}

/// Logit cases `[N, D, P, P]`: (name, logits).
fn logit_cases() -> Vec<(&'static str, Vec<f32>)> {
    let mut rng = StdRng::seed_from_u64(2);
    let random: Vec<f32> = (0..N * D * M).map(|_| rng.gen_range(-2.0..2.0)).collect();
    let len = N * D * M;
    vec![
        ("zero", vec![0.0; len]),
        ("constant", vec![0.5; len]),
        ("identical patches", (0..len).map(|i| random[i % (D * M)]).collect()),
        ("one channel zero", (0..len).map(|i| if channel_of(i) == 0 { 0.0 } else { random[i] }).collect()),
        ("subnormal", random.iter().map(|v| v * 1e-44).collect()),
        ("tiny", random.iter().map(|v| v * 1e-20).collect()),
        ("huge", random.iter().map(|v| v * 1e30).collect()),
        ("max", random.iter().map(|v| if *v > 0.0 { f32::MAX } else { -f32::MAX }).collect()),
        ("random", random),
    ]
}

/// Point cases `[N, 3, P, P]`: (name, points).
fn point_cases() -> Vec<(&'static str, Vec<f32>)> {
    let mut rng = StdRng::seed_from_u64(3);
    let len = N * 3 * M;
    vec![
        ("zero", vec![0.0; len]),
        ("one point", (0..len).map(|i| [0.3, -1.2, 2.5][(i / M) % 3]).collect()),
        ("huge spread", (0..len).map(|_| rng.gen_range(-1e30f32..1e30)).collect()),
        ("max spread", (0..len).map(|i| if i % 2 == 0 { f32::MAX } else { -f32::MAX }).collect()),
        ("random", (0..len).map(|_| rng.gen_range(-2.0f32..2.0)).collect()),
    ]
}

fn shape() -> PatchShape {
    PatchShape { n_patches: N, d_seg: D, patch: P }
}

fn assert_finite(v: &LossValue, grad: &[f32], what: &str) {
    assert!(v.total.is_finite(), "{what}: total {}", v.total);
    assert!(v.terms.iter().all(|(_, t)| t.is_finite()), "{what}: terms {:?}", v.terms);
    assert!(grad.iter().all(|g| g.is_finite()), "{what}: non-finite gradient");
}

fn evaluate(
    loss: &dyn ContrastiveLossConfig,
    features: &[FeatureMap],
    logits: &[f32],
    points: &[f32],
    negatives: &[usize],
) -> (LossValue, Vec<f32>) {
    let loss = loss.build().expect("default loss builds");
    let batch = PatchBatch { n_patches: N, patch: P, d_seg: D, logits, points, features, negatives };
    let mut grad = vec![0.0f32; logits.len()];
    let v = loss.loss_and_grad(&batch, &mut StdRng::seed_from_u64(9), 1.0, &mut grad);
    (v, grad)
}

fn term(v: &LossValue, name: &str) -> f64 {
    v.terms.iter().find(|(k, _)| k == name).map(|t| t.1).unwrap_or_else(|| panic!("no term {name}"))
}

#[test]
fn appearance_stays_finite_for_degenerate_features_and_logits() {
    let points = vec![0.0f32; N * 3 * M];
    let mut any_gradient = false;
    for (fname, features) in feature_cases() {
        for (lname, logits) in logit_cases() {
            let (v, grad) = evaluate(&AppearanceConfig::default(), &features, &logits, &points, &[1, 2, 0]);
            let what = format!("appearance, {fname} features, {lname} logits");
            assert_finite(&v, &grad, &what);
            any_gradient |= grad.iter().any(|&g| g != 0.0);
            if lname == "zero" {
                // S = 0 everywhere: the zero clamp passes neither loss nor gradient.
                assert_eq!(v.total, 0.0, "{what}");
                assert!(grad.iter().all(|&g| g == 0.0), "{what}");
            }
        }
    }
    assert!(any_gradient, "the ordinary cases have gradients");
}

#[test]
fn appearance_of_identical_or_zero_features_takes_the_formula_values() {
    let points = vec![0.0f32; N * 3 * M];
    let constant = vec![0.5f32; N * D * M];
    let cfg = AppearanceConfig::default();
    // Identical features: F = 1 after centring; constant logits: S = 1. Loss = −(1 − b).
    let (v, grad) = evaluate(&cfg, &maps(|_, _| 0.8), &constant, &points, &[1, 2, 0]);
    assert!((term(&v, "appearance/identity") + (1.0 - cfg.identity_shift)).abs() < 1e-9, "{v:?}");
    assert!((term(&v, "appearance/negative") + (1.0 - cfg.negative_shift)).abs() < 1e-9, "{v:?}");
    assert!(grad.iter().all(|g| g.abs() < 1e-6), "S = 1 is a maximum of the cosine: no gradient");
    // Zero-norm features: F = 0, so the loss is b · mean(S) = b.
    let (v, _) = evaluate(&cfg, &maps(|_, _| 0.0), &constant, &points, &[1, 2, 0]);
    assert!((term(&v, "appearance/identity") - cfg.identity_shift).abs() < 1e-9, "{v:?}");
    assert!((term(&v, "appearance/negative") - cfg.negative_shift).abs() < 1e-9, "{v:?}");
}

#[test]
fn geometry_stays_finite_for_degenerate_points_and_logits() {
    let features = maps(|_, _| 0.0);
    let mut any_gradient = false;
    for (pname, points) in point_cases() {
        for (lname, logits) in logit_cases() {
            let (v, grad) = evaluate(&GeometryConfig::default(), &features, &logits, &points, &[2, 0, 1]);
            let what = format!("geometry, {pname} points, {lname} logits");
            assert_finite(&v, &grad, &what);
            any_gradient |= grad.iter().any(|&g| g != 0.0);
            if lname == "zero" || lname == "constant" {
                // Equal normalised logits: the kernel sits at its cap, which passes no gradient.
                assert!(grad.iter().all(|&g| g == 0.0), "{what}");
            }
        }
    }
    assert!(any_gradient, "the ordinary cases have gradients");
}

#[test]
fn geometry_of_constant_depth_takes_the_formula_values() {
    let cfg = GeometryConfig::default();
    let features = maps(|_, _| 0.0);
    // One point everywhere: G = cap; constant logits: S = cap. Loss = −cap·(cap − b).
    let points: Vec<f32> = (0..N * 3 * M).map(|i| [0.3, -1.2, 2.5][(i / M) % 3]).collect();
    let (v, _) = evaluate(&cfg, &features, &vec![0.5; N * D * M], &points, &[2, 0, 1]);
    let want = |b: f64| -cfg.cap * (cfg.cap - b);
    assert!((term(&v, "geometry/identity") - want(cfg.identity_shift)).abs() < 1e-3, "{v:?}");
    assert!((term(&v, "geometry/negative") - want(cfg.negative_shift)).abs() < 1e-3, "{v:?}");
}

#[test]
fn geometry_from_sentinel_depths_is_finite() {
    let cfg = GeometryConfig::default();
    let mut rng = StdRng::seed_from_u64(5);
    let logits: Vec<f32> = (0..N * D * M).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let rays_o = vec![0.0f32; N * 3 * M];
    let rays_d: Vec<f32> = (0..N * 3 * M).map(|i| if (i / M) % 3 == 2 { -1.0 } else { 0.1 }).collect();
    let shape = shape();
    for depth in [
        vec![EMPTY_RAY_DEPTH; N * M],
        (0..N * M).map(|i| if i % 3 == 0 { EMPTY_RAY_DEPTH } else { 1.0 + i as f32 * 0.01 }).collect(),
        vec![0.0; N * M],
        vec![f32::MAX; N * M],
    ] {
        let mut grad = vec![0.0f32; logits.len()];
        let v =
            geometry_loss_from_depth(&cfg, &depth, &rays_o, &rays_d, &logits, shape, &[1, 2, 0], 1.0, Some(&mut grad));
        assert_finite(&v, &grad, &format!("depth {:?}", &depth[..3]));
    }
    // The clip: all beyond it become it; none beyond, untouched; NaN left for the caller.
    let mut d = vec![EMPTY_RAY_DEPTH; 4];
    clip_depth(&mut d, 15.0);
    assert_eq!(d, [15.0; 4]);
    let mut d = vec![1.0, 15.0, 3.0];
    clip_depth(&mut d, 15.0);
    assert_eq!(d, [1.0, 15.0, 3.0]);
    let mut d = vec![f32::NAN, 20.0, 2.0];
    clip_depth(&mut d, 15.0);
    assert!(d[0].is_nan() && d[1..] == [2.0, 2.0]);
}

#[test]
fn single_patch_and_single_pixel_batches_are_finite() {
    for (n, patch) in [(1, 1), (1, 4), (2, 1)] {
        let shape = PatchShape { n_patches: n, d_seg: D, patch };
        let m = patch * patch;
        let logits: Vec<f32> = (0..n * D * m).map(|i| (i as f32 * 0.9).cos()).collect();
        let points: Vec<f32> = (0..n * 3 * m).map(|i| (i as f32 * 0.4).sin()).collect();
        let features: Vec<FeatureMap> = (0..n)
            .map(|_| FeatureMap { channels: C, height: 1, width: 1, data: vec![0.0; C], cls: vec![], saliency: None })
            .collect();
        let negatives: Vec<usize> = (0..n).map(|k| (k + 1) % n).collect();
        let batch = PatchBatch {
            n_patches: n,
            patch,
            d_seg: D,
            logits: &logits,
            points: &points,
            features: &features,
            negatives: &negatives,
        };
        for cfg in [
            Box::new(AppearanceConfig::default()) as Box<dyn ContrastiveLossConfig>,
            Box::new(GeometryConfig::default()),
        ] {
            let mut grad = vec![0.0f32; logits.len()];
            let v = cfg.build().unwrap().loss_and_grad(&batch, &mut StdRng::seed_from_u64(0), 1.0, &mut grad);
            assert_finite(&v, &grad, &format!("{cfg:?} n={n} patch={shape:?}"));
        }
    }
}

fn mine(cfg: &dyn PairMinerConfig, cls: &[Vec<f32>]) -> Vec<usize> {
    cfg.build().expect("default miner builds").negatives(cls, &mut StdRng::seed_from_u64(4))
}

#[test]
fn miners_pair_zero_and_identical_cls_vectors_with_another_patch() {
    let cls_cases: Vec<(&str, Vec<Vec<f32>>)> = vec![
        ("zero", vec![vec![0.0; 8]; 4]),
        ("identical", vec![vec![0.25; 8]; 4]),
        ("empty", vec![Vec::new(); 4]),
        ("tiny", (0..4).map(|k| vec![1e-40 * (k as f32 + 1.0); 8]).collect()),
        ("huge", (0..4).map(|k| vec![if k % 2 == 0 { f32::MAX } else { -1e30 }; 8]).collect()),
        ("zero and not", vec![vec![0.0, 0.0], vec![1.0, 0.0], vec![-1.0, 0.0], vec![0.0, 0.0]]),
    ];
    let miners: [Box<dyn PairMinerConfig>; 2] =
        [Box::new(ClsCosineConfig::default()), Box::new(RandomConfig::default())];
    for (name, cls) in &cls_cases {
        for miner in &miners {
            let neg = mine(miner.as_ref(), cls);
            assert_eq!(neg.len(), cls.len(), "{name} {miner:?}");
            assert!(neg.iter().enumerate().all(|(i, &j)| j < cls.len() && j != i), "{name} {miner:?}: {neg:?}");
        }
    }
    let cosine = ClsCosineConfig::default();
    // Ties (zero, identical, empty vectors) go to the first other patch.
    assert_eq!(mine(&cosine, &cls_cases[0].1), [1, 0, 0, 0]);
    assert_eq!(mine(&cosine, &cls_cases[1].1), [1, 0, 0, 0]);
    assert_eq!(mine(&cosine, &cls_cases[2].1), [1, 0, 0, 0]);
    // A zero vector has cosine 0 with everything (a tie, first other patch); ±x are opposites.
    assert_eq!(mine(&cosine, &cls_cases[5].1), [1, 2, 1, 0]);
    for miner in &miners {
        assert_eq!(mine(miner.as_ref(), &[vec![0.0; 3]]), [0], "{miner:?}: one patch is its own partner");
        assert!(mine(miner.as_ref(), &[]).is_empty(), "{miner:?}");
        assert_eq!(mine(miner.as_ref(), &[vec![0.0; 3], vec![0.0; 3]]), [1, 0], "{miner:?}");
    }
}
