//! Numerical stress tests of the compositing kernel, the renderer, the empty-ray depth
//! sentinel, the metrics and k-means: extreme densities and intervals, rays that hit nothing,
//! all-empty and all-opaque fields, degenerate logits and masks. Every output and gradient
//! must stay finite and within its documented range.

use rand::SeedableRng;
use sos_core::camera::{Camera, Vec3};
use sos_core::config::MaskConfig;
use sos_core::image::RgbImage;
use sos_core::kmeans::{kmeans, KMeansConfig};
use sos_core::metrics::{
    adjusted_rand_index, binary_iou, mean_iou, mean_psnr, mse, psnr_from_mse, psnr_of_mean_mse, ssim,
    ImageQualityReport, SegmentationReport,
};
use sos_core::plugin::field::{Hierarchical, HierarchicalSampling};
use sos_core::plugin::{FieldTape, RadianceField};
use sos_core::render::composite::{
    composite, composite_backward, weights, RayColour, RayGrad, RaySamples, EMPTY_RAY_ACC, EMPTY_RAY_DEPTH,
};
use sos_core::render::contraction::Contraction;
use sos_core::render::memory_budget::MemoryBudget;
use sos_core::render::rays::RayBatch;
use sos_core::render::renderer::{render, render_inference, ExtraChannels, RenderContext, RenderOptions};
use sos_core::render::sampler::MarchOptions;
use sos_core::scene::{Scene, SceneExtent};
use sos_core::segment::infer::{cluster_logits, softmax_rows, FocusTarget};
use sos_core::segment::train::fill_empty_depths;
use sos_core::train::evaluate::ImageEval;

/// Densities from nothing to far beyond any field's range.
const SIGMAS: [f32; 9] = [0.0, 1e-30, 1e-10, 1e-3, 1.0, 1e3, 1e10, 1e30, f32::MAX];
/// Interval lengths from none to absurd (the reference's last interval is 1e10).
const DELTAS: [f32; 6] = [0.0, 1e-30, 1e-3, 1.0, 1e10, 1e30];
/// Slack of `Σ w ≤ 1` for f32 rounding.
const ACC_EPS: f32 = 1e-5;
const D_EXTRA: usize = 2;

/// One ray's inputs, owned.
struct Ray {
    sigma: Vec<f32>,
    delta: Vec<f32>,
    t: Vec<f32>,
    rgb: Vec<[f32; 3]>,
    extra: Vec<f32>,
    skipped: Vec<f32>,
}

impl Ray {
    /// Samples at `t = 1 + k/4` (a realistic range), colours and logits in ordinary ranges.
    fn new(sigma: Vec<f32>, delta: Vec<f32>) -> Ray {
        let n = sigma.len();
        assert_eq!(delta.len(), n);
        Ray {
            t: (0..n).map(|k| 1.0 + 0.25 * k as f32).collect(),
            rgb: (0..n).map(|k| [0.1 * (k % 10) as f32, 0.5, 1.0 - 0.1 * (k % 10) as f32]).collect(),
            extra: (0..n * D_EXTRA).map(|i| ((i as f32) * 0.77).sin() * 3.0).collect(),
            skipped: Vec::new(),
            sigma,
            delta,
        }
    }

    fn samples(&self) -> RaySamples<'_> {
        RaySamples {
            sigma: &self.sigma,
            delta: &self.delta,
            t: &self.t,
            rgb: &self.rgb,
            extra: &self.extra,
            d_extra: D_EXTRA,
            skipped_tau: &self.skipped,
        }
    }
}

/// Forward and backward of one ray with fixed upstream gradients.
struct Result1 {
    w: Vec<f32>,
    out: RayColour,
    extra: [f32; D_EXTRA],
    g_sigma: Vec<f32>,
    g_rgb: Vec<[f32; 3]>,
    g_extra: Vec<f32>,
}

const G_EXTRA: [f32; D_EXTRA] = [0.7, -1.3];

fn run(ray: &Ray, depth_grad: f32) -> Result1 {
    let n = ray.sigma.len();
    let s = ray.samples();
    let mut w = vec![f32::NAN; n];
    let mut extra = [f32::NAN; D_EXTRA];
    let out = composite(&s, &mut w, &mut extra);
    let g_weights: Vec<f32> = (0..n).map(|k| if k % 2 == 0 { 0.2 } else { -0.1 }).collect();
    let g = RayGrad { rgb: [1.0, -0.5, 0.25], depth: depth_grad, acc: -0.3, extra: &G_EXTRA, weights: &g_weights };
    let (mut g_sigma, mut g_rgb, mut g_extra) =
        (vec![f32::NAN; n], vec![[f32::NAN; 3]; n], vec![f32::NAN; n * D_EXTRA]);
    composite_backward(&s, &w, out.acc, &g, &mut g_sigma, &mut g_rgb, &mut g_extra);
    Result1 { w, out, extra, g_sigma, g_rgb, g_extra }
}

/// Every documented invariant of one composited ray.
fn check(ray: &Ray, r: &Result1, what: &str) {
    let all_finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    assert!(all_finite(&r.w), "{what}: weights {:?}", r.w);
    assert!(r.w.iter().all(|&w| (0.0..=1.0 + ACC_EPS).contains(&w)), "{what}: weights {:?}", r.w);
    let sum: f32 = r.w.iter().sum();
    assert!(sum <= 1.0 + ACC_EPS, "{what}: weights sum to {sum}");
    assert!((r.out.acc - sum).abs() <= 1e-6, "{what}: acc {} vs Σw {sum}", r.out.acc);
    assert!(
        all_finite(&r.out.rgb) && r.out.rgb.iter().all(|&c| (0.0..=1.0 + ACC_EPS).contains(&c)),
        "{what}: rgb {:?}",
        r.out.rgb
    );
    assert!(all_finite(&r.extra), "{what}: extra {:?}", r.extra);
    // |Σ w e| ≤ max|e| · Σ w.
    let e_max = ray.extra.iter().fold(0.0f32, |m, e| m.max(e.abs()));
    assert!(r.extra.iter().all(|e| e.abs() <= e_max * (sum + ACC_EPS)), "{what}: extra {:?}", r.extra);
    if r.out.acc <= EMPTY_RAY_ACC {
        assert_eq!(r.out.depth, EMPTY_RAY_DEPTH, "{what}: an empty ray reports the sentinel");
    } else {
        // Σ w t lies within [acc·t_min, acc·t_max].
        let (lo, hi) = (ray.t[0], *ray.t.last().unwrap());
        let d = r.out.depth;
        assert!(
            d.is_finite() && d >= r.out.acc * lo * (1.0 - 1e-5) && d <= r.out.acc * hi * (1.0 + 1e-5),
            "{what}: depth {d}"
        );
    }
    assert!(all_finite(&r.g_sigma), "{what}: ∂σ {:?}", r.g_sigma);
    assert!(r.g_rgb.iter().flatten().all(|g| g.is_finite()), "{what}: ∂rgb {:?}", r.g_rgb);
    assert!(all_finite(&r.g_extra), "{what}: ∂extra {:?}", r.g_extra);
    // ∂L/∂e_k = w_k ∂L/∂e exactly.
    for (k, (w, g)) in r.w.iter().zip(r.g_extra.chunks_exact(D_EXTRA)).enumerate() {
        let want: Vec<f32> = G_EXTRA.iter().map(|e| w * e).collect();
        assert_eq!(g, want, "{what}: ∂extra of sample {k}");
    }
}

#[test]
fn every_density_and_interval_composites_to_finite_values() {
    for &sigma in &SIGMAS {
        for &delta in &DELTAS {
            for n in [1, 2, 7] {
                let ray = Ray::new(vec![sigma; n], vec![delta; n]);
                check(&ray, &run(&ray, 0.8), &format!("σ={sigma:e} δ={delta:e} n={n}"));
            }
        }
    }
}

#[test]
fn mixed_extremes_along_one_ray_stay_finite() {
    // Every ordered pair of extreme samples, then all of them in one ray, forwards and back.
    let pairs: Vec<(f32, f32)> = SIGMAS.iter().flat_map(|&s| DELTAS.iter().map(move |&d| (s, d))).collect();
    for a in &pairs {
        for b in &pairs {
            let ray = Ray::new(vec![a.0, b.0, 1.0], vec![a.1, b.1, 0.5]);
            check(&ray, &run(&ray, -1.5), &format!("{a:?} then {b:?}"));
        }
    }
    let (sigma, delta): (Vec<f32>, Vec<f32>) = pairs.iter().copied().unzip();
    let ray = Ray::new(sigma.clone(), delta.clone());
    check(&ray, &run(&ray, 0.3), "all pairs");
    let ray = Ray::new(sigma.into_iter().rev().collect(), delta.into_iter().rev().collect());
    check(&ray, &run(&ray, 0.3), "all pairs reversed");
}

#[test]
fn skipped_optical_depth_of_any_size_stays_finite() {
    for &tau in &[0.0f32, 1e-30, 1.0, 1e30, f32::INFINITY] {
        let mut ray = Ray::new(vec![1.0; 4], vec![0.5; 4]);
        ray.skipped = vec![0.0, tau, 0.0, tau];
        let r = run(&ray, 1.0);
        check(&ray, &r, &format!("skipped τ={tau:e}"));
        if tau >= 1e30 {
            assert_eq!(r.w[1..], [0.0; 3], "nothing is visible behind an opaque skipped interval");
        }
    }
}

#[test]
fn an_opaque_first_sample_takes_all_the_weight() {
    for (sigma, delta) in [(1e30, 1.0), (f32::MAX, 1e30), (1e10, 1e10)] {
        let ray = Ray::new(vec![sigma, 1.0, 1e30, 0.0], vec![delta, 1.0, 1.0, 1.0]);
        let r = run(&ray, 0.5);
        check(&ray, &r, "opaque");
        assert_eq!(r.w, [1.0, 0.0, 0.0, 0.0]);
        assert_eq!((r.out.rgb, r.out.depth, r.out.acc), (ray.rgb[0], ray.t[0], 1.0));
        assert_eq!(r.g_rgb[0], [1.0, -0.5, 0.25], "the visible sample gets the whole colour gradient");
        assert!(r.g_rgb[1..].iter().flatten().all(|&g| g == 0.0));
        // Behind an opaque sample nothing can change the output.
        assert!(r.g_sigma[1..].iter().all(|&g| g == 0.0), "{:?}", r.g_sigma);
    }
}

#[test]
fn an_empty_ray_reports_the_sentinel_and_ignores_its_depth_gradient() {
    for (sigma, delta) in [(0.0, 1.0), (1e-30, 1e-30), (1.0, 0.0), (0.0, 1e30), (1e-30, 1e10)] {
        let ray = Ray::new(vec![sigma; 5], vec![delta; 5]);
        let a = run(&ray, 0.0);
        check(&ray, &a, "empty");
        assert!(a.out.acc <= EMPTY_RAY_ACC, "σ={sigma:e} δ={delta:e}: acc {}", a.out.acc);
        assert_eq!(a.out.depth, EMPTY_RAY_DEPTH);
        // The sentinel is a constant: a depth gradient changes nothing.
        let b = run(&ray, 1e6);
        assert_eq!(a.g_sigma, b.g_sigma);
        // Its expected point is the ray origin, not origin + 1e10 · direction.
        assert_eq!(a.out.expected_point([1.0, 2.0, 3.0], [0.0, 0.0, -1.0]), [1.0, 2.0, 3.0]);
    }
    // Just above the threshold the depth is real (Σ w t, tiny), not the sentinel.
    let ray = Ray::new(vec![1e-6; 2], vec![1e-3; 2]);
    let r = run(&ray, 1.0);
    assert!(r.out.acc > EMPTY_RAY_ACC && r.out.depth < 1e-6 && r.out.depth > 0.0, "{:?}", r.out);
    let p = r.out.expected_point([0.0; 3], [1.0, 0.0, 0.0]);
    assert!(p.iter().all(|v| v.is_finite()) && p[0] == r.out.depth);
}

#[test]
fn a_ray_with_no_samples_is_empty() {
    let ray = Ray::new(Vec::new(), Vec::new());
    let r = run(&ray, 1.0);
    assert_eq!(r.out, RayColour { rgb: [0.0; 3], depth: EMPTY_RAY_DEPTH, acc: 0.0, median_depth: EMPTY_RAY_DEPTH });
    assert_eq!(r.extra, [0.0; D_EXTRA]);
    assert!(r.g_sigma.is_empty() && r.g_rgb.is_empty() && r.g_extra.is_empty());
    let mut w: [f32; 0] = [];
    weights(&[], &[], &[], &mut w);
}

/// A field of constant density and colour, optionally hierarchical.
struct Constant {
    sigma: f32,
    hierarchical: Option<Hierarchical>,
}

impl RadianceField for Constant {
    fn density(&self, positions: &[Vec3], density: &mut [f32]) {
        density[..positions.len()].fill(self.sigma);
    }
    fn forward(&self, p: &[Vec3], _: &[Vec3], d: &mut [f32], c: &mut [[f32; 3]], _: bool) -> FieldTape {
        d[..p.len()].fill(self.sigma);
        c[..p.len()].fill([0.2, 0.6, 0.9]);
        None
    }
    fn backward(&mut self, _: &[Vec3], _: &[Vec3], _: FieldTape, _: &[f32], _: &[[f32; 3]]) {}
    fn step(&mut self, _: f32) {}
    fn gradients_finite(&self) -> bool {
        true
    }
    fn discard_gradients(&mut self) {}
    fn hierarchical(&self) -> Option<&dyn HierarchicalSampling> {
        self.hierarchical.is_some().then_some(self as &dyn HierarchicalSampling)
    }
    fn seg_input_dim(&self) -> usize {
        1
    }
    fn seg_input(&self, p: &[Vec3], out: &mut [f32]) {
        for (o, p) in out.iter_mut().zip(p) {
            *o = p[0];
        }
    }
    fn save_state(&self) -> Vec<u8> {
        Vec::new()
    }
    fn load_state(&mut self, _: &[u8]) -> Result<(), sos_core::error::StateError> {
        Ok(())
    }
    fn num_parameters(&self) -> usize {
        0
    }
    fn parameters(&self) -> Vec<f32> {
        Vec::new()
    }
    fn set_parameters(&mut self, _: &[f32]) -> Result<(), sos_core::error::StateError> {
        Ok(())
    }
    fn gradients(&self) -> Vec<f32> {
        Vec::new()
    }
}

/// The field proposes its own samples (no separate proposal network).
impl HierarchicalSampling for Constant {
    fn sampling(&self) -> Hierarchical {
        self.hierarchical.expect("handed out only when set")
    }
    fn proposal(&self) -> Option<&dyn RadianceField> {
        None
    }
    fn proposal_mut(&mut self) -> Option<&mut dyn RadianceField> {
        None
    }
}

/// A 12x12 view of the unit box from 3 m with a wide field of view: the corner rays miss it.
fn view_rays() -> (SceneExtent, Contraction, RayBatch) {
    let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
    let cam = Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 12, 12, 4.0);
    (extent, Contraction::new(&extent), RayBatch::full_image(&cam))
}

#[test]
fn rendering_empty_opaque_and_extreme_fields_stays_finite() {
    let (extent, contraction, rays) = view_rays();
    let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
    let march = MarchOptions { steps: 32, stratified: true };
    let hier = Some(Hierarchical { coarse_samples: 8, fine_samples: 8 });
    for sigma in [0.0, 1e-30, 1.0, 1e30, f32::MAX] {
        for hierarchical in [None, hier] {
            for (early_stop, min_weight) in [(0.0, 0.0), (1e-4, 1e-4)] {
                let what = format!("σ={sigma:e} hierarchical={} prune={early_stop}", hierarchical.is_some());
                let field = Constant { sigma, hierarchical };
                let options =
                    RenderOptions { proposal: true, march, early_stop, min_weight, memory: MemoryBudget::unlimited() };
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
                let mut r = render(&field, ctx, &rays, options, true, &mut rng);
                r.composite();
                let mut missed = 0;
                for (i, c) in r.colours.iter().enumerate() {
                    assert!(
                        c.rgb.iter().all(|v| v.is_finite()) && c.acc.is_finite() && c.depth.is_finite(),
                        "{what}: {c:?}"
                    );
                    assert!((0.0..=1.0 + ACC_EPS).contains(&c.acc), "{what}: acc {}", c.acc);
                    if r.samples.range(i).is_empty() {
                        missed += 1;
                        assert_eq!((c.acc, c.depth), (0.0, EMPTY_RAY_DEPTH), "{what}: a ray that hits nothing");
                    } else if sigma >= 1e30 {
                        assert_eq!(c.acc, 1.0, "{what}: an opaque field stops every ray that enters it");
                        assert!(c.depth >= 2.0 - 1e-3 && c.depth < 6.0, "{what}: depth {}", c.depth);
                    } else if sigma == 0.0 {
                        assert_eq!((c.acc, c.depth), (0.0, EMPTY_RAY_DEPTH), "{what}");
                    }
                }
                assert!(missed >= 4, "{what}: the corner rays miss the box ({missed})");
                let extra = vec![1.5f32; r.samples.len()];
                let grads: Vec<RayGrad> = (0..rays.len())
                    .map(|_| RayGrad { rgb: [1.0, -1.0, 0.5], depth: 0.1, acc: 0.2, extra: &[0.4], weights: &[] })
                    .collect();
                let (gs, grgb, gex) = r.composite_backward(&extra, 1, &grads);
                assert!(gs.iter().chain(grgb.iter().flatten()).chain(&gex).all(|g| g.is_finite()), "{what}: gradients");
            }
        }
        // Inference with the segmentation channels composited alongside.
        let field = Constant { sigma, hierarchical: None };
        let eval = |p: &[Vec3]| p.iter().flat_map(|p| [p[0], -p[1]]).collect::<Vec<f32>>();
        let channels = ExtraChannels { dim: 2, min_weight: 1e-3, eval: &eval };
        let options = RenderOptions {
            proposal: true,
            march: MarchOptions { steps: 32, stratified: false },
            early_stop: 1e-4,
            min_weight: 0.0,
            memory: MemoryBudget::unlimited(),
        };
        let (colours, logits) = render_inference(&field, ctx, &rays, options, 50, Some(&channels));
        assert_eq!((colours.len(), logits.len()), (rays.len(), 2 * rays.len()));
        assert!(logits.iter().all(|v| v.is_finite() && v.abs() <= 1.0 + 1e-4), "σ={sigma:e}: logits");
    }
}

#[test]
fn empty_depths_are_filled_for_any_batch() {
    // Mixed: the sentinel becomes the largest real depth.
    let mut d = vec![2.0, EMPTY_RAY_DEPTH, 3.5, EMPTY_RAY_DEPTH, 0.0];
    fill_empty_depths(&mut d);
    assert_eq!(d, [2.0, 3.5, 3.5, 3.5, 0.0]);
    // All empty: a finite constant, never the sentinel.
    let mut d = vec![EMPTY_RAY_DEPTH; 6];
    fill_empty_depths(&mut d);
    assert!(d.iter().all(|&v| v.is_finite() && v < EMPTY_RAY_DEPTH * 0.5), "{d:?}");
    assert!(d.windows(2).all(|w| w[0] == w[1]));
    // No empty ray: untouched, bit for bit.
    let before = vec![1e-20, 0.5, 7.25, 4e9, 1e3];
    let mut d = before.clone();
    fill_empty_depths(&mut d);
    assert_eq!(d, before);
    let mut none: Vec<f32> = Vec::new();
    fill_empty_depths(&mut none);
    assert!(none.is_empty());
}

#[test]
fn psnr_of_identical_images_has_a_finite_floor() {
    let p = psnr_from_mse(0.0);
    assert!(p.is_finite() && p >= 100.0, "{p}");
    // The floor does not touch ordinary errors, and an exact view does not make the means inf.
    assert!((psnr_from_mse(1e-2) - 20.0).abs() < 1e-12);
    assert!(psnr_from_mse(1e-13) <= p && psnr_from_mse(1e-11) > 100.0);
    assert!(mean_psnr(&[0.0, 1e-2]).unwrap().is_finite());
    assert!(psnr_of_mean_mse(&[0.0, 0.0]).unwrap().is_finite());
    assert!(psnr_from_mse(f64::NAN).is_nan(), "a NaN error is not hidden");
    let black = RgbImage::new(7, 5);
    let mut report = ImageQualityReport::new();
    report.add_view("black", &black, &black).unwrap();
    let v = &report.views()[0];
    assert_eq!((v.mse, v.ssim), (0.0, 1.0));
    assert!(v.psnr.is_finite());
    assert!(report.mean_psnr().unwrap().is_finite() && report.psnr_of_mean_mse().unwrap().is_finite());
    let json = serde_json::to_value(&report).unwrap();
    assert!(json["views"][0]["psnr"].is_f64() && json["mean_psnr"].is_f64(), "{json}");
    let eval = ImageEval::from_report(&report, 35, 0.1);
    assert!(eval.psnr.is_finite() && eval.psnr_mean_per_view.is_finite() && eval.ssim == 1.0);
}

#[test]
fn ssim_and_mse_of_flat_images_are_finite() {
    let flat = |v: f32| RgbImage { width: 9, height: 4, data: vec![v; 9 * 4 * 3] };
    for (a, b) in [(0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.5, 0.5)] {
        let s = ssim(&flat(a), &flat(b)).unwrap();
        assert!(s.is_finite() && (-1.0..=1.0).contains(&s), "{a} vs {b}: {s}");
        if a == b {
            assert!((s - 1.0).abs() < 1e-12);
        }
        assert_eq!(mse(&flat(a).data, &flat(b).data).unwrap(), f64::from((a - b) * (a - b)));
    }
    let one = RgbImage::new(1, 1);
    assert!(ssim(&one, &one).unwrap().is_finite());
}

#[test]
fn segmentation_metrics_of_one_class_masks_are_defined_or_none() {
    let all = |v: bool, n: usize| vec![v; n];
    for n in [1, 2, 50] {
        for (gt, pred) in [(false, false), (true, true), (false, true), (true, false)] {
            let (g, p) = (all(gt, n), all(pred, n));
            let iou = binary_iou(&g, &p).unwrap();
            for v in [iou.bg, iou.fg, iou.miou()].into_iter().flatten() {
                assert!(v.is_finite() && (0.0..=1.0).contains(&v), "n={n} {gt}/{pred}: {iou:?}");
            }
            let want = if gt == pred { Some(1.0) } else { Some(0.0) };
            assert_eq!(iou.miou(), want, "n={n} {gt}/{pred}: {iou:?}");
            // One class in both masks: ARI is 1 (the same partition).
            assert_eq!(adjusted_rand_index(&g, &p).unwrap(), 1.0);
        }
        // One class in the truth, two in the prediction: ARI 0, not NaN.
        if n > 1 {
            let split: Vec<bool> = (0..n).map(|i| i % 2 == 0).collect();
            assert_eq!(adjusted_rand_index(&all(false, n), &split).unwrap(), 0.0);
            assert_eq!(adjusted_rand_index(&split, &all(true, n)).unwrap(), 0.0);
        }
    }
    let mut report = SegmentationReport::new();
    report.add_view("bg", &[false; 4], &[false; 4]).unwrap();
    report.add_view("fg-missed", &[true; 4], &[false; 4]).unwrap();
    let json = serde_json::to_value(&report).unwrap();
    for key in ["mean_ari", "iou_bg", "iou_fg", "miou"] {
        assert!(json[key].as_f64().is_some_and(f64::is_finite), "{key}: {json}");
    }
    assert!(json["views"][0]["iou_fg"].is_null(), "absent from both masks: None, not NaN");
    assert_eq!(mean_iou(&[]).miou, None);
}

fn mask_config(softmax: bool, normalize: bool) -> MaskConfig {
    MaskConfig { softmax, normalize, ..MaskConfig::default() }
}

#[test]
fn kmeans_of_identical_zero_and_single_logits_is_well_defined() {
    for data in [vec![0.0f32; 2 * 40], vec![0.37f32; 2 * 40], vec![-3.0, 5.0]] {
        let n = data.len() / 2;
        let r = kmeans(&data, 2, &KMeansConfig::default()).unwrap();
        assert_eq!((r.k, r.inertia), (1, 0.0), "one distinct point, one cluster");
        assert_eq!(r.labels, vec![0; n]);
        assert_eq!(r.centroid(0), &data[..2]);
        for (softmax, normalize) in [(false, false), (true, false), (false, true), (true, true)] {
            let r = cluster_logits(&data, 2, &mask_config(softmax, normalize), 0).unwrap();
            assert_eq!((r.k, r.labels.len()), (1, n));
            assert!(r.centroids.iter().all(|c| c.is_finite()) && r.inertia == 0.0);
        }
    }
    // A single pixel with one channel.
    let r = kmeans(&[2.5], 1, &KMeansConfig { k: 2, ..Default::default() }).unwrap();
    assert_eq!((r.k, r.labels.as_slice(), r.inertia), (1, &[0u32][..], 0.0));
}

#[test]
fn kmeans_separates_huge_logits() {
    // Two blobs around ±1e30: squared distances overflow f32.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let (mut data, mut truth) = (Vec::new(), Vec::new());
    for i in 0..200 {
        let side = if i % 2 == 0 { 1.0f32 } else { -1.0 };
        for _ in 0..2 {
            data.push(side * 1e30 * (1.0 + rand::Rng::gen_range(&mut rng, -0.05f32..0.05)));
        }
        truth.push(i % 2);
    }
    let r = kmeans(&data, 2, &KMeansConfig::default()).unwrap();
    assert_eq!(r.k, 2);
    assert_eq!(adjusted_rand_index(&truth, &r.labels).unwrap(), 1.0);
    assert!(r.centroids.iter().all(|c| c.is_finite() && (c.abs() - 1e30).abs() < 0.05e30), "{:?}", r.centroids);
    assert!(r.inertia.is_finite() && r.inertia > 0.0, "{}", r.inertia);
    // The largest finite values too.
    let r = kmeans(&[f32::MAX, -f32::MAX, f32::MAX, -f32::MAX], 1, &KMeansConfig::default()).unwrap();
    assert_eq!((r.k, r.inertia), (2, 0.0));
    assert_eq!(adjusted_rand_index(&[0, 1, 0, 1], &r.labels).unwrap(), 1.0);
    assert!(r.centroids.contains(&f32::MAX) && r.centroids.contains(&-f32::MAX));
}

#[test]
fn softmax_and_normalisation_of_extreme_logits_stay_finite() {
    let rows = [0.0f32, 0.0, 1e30, -1e30, f32::MAX, -f32::MAX, 1e-45, 0.0, 1e20, 1e20, -1e25, 3e25];
    let s = softmax_rows(&rows, 2);
    assert!(s.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)), "{s:?}");
    for row in s.chunks_exact(2) {
        assert!((row[0] + row[1] - 1.0).abs() < 1e-6, "{row:?}");
    }
    assert_eq!(&s[..4], &[0.5, 0.5, 1.0, 0.0]);
    // Unit-length logits: every non-zero row ends on the unit circle, however large.
    let r = cluster_logits(&rows, 2, &mask_config(false, true), 0).unwrap();
    assert!(r.centroids.iter().all(|c| c.is_finite()));
    for c in 0..r.k {
        let v = r.centroid(c);
        let norm = (v[0] * v[0] + v[1] * v[1]).sqrt();
        assert!(norm <= 1.0 + 1e-5, "centroid {v:?}");
    }
    // The rows themselves, clustered one by one, are unit vectors, or shorter below the norm
    // floor of 1e-10 (as `F.normalize`).
    for (i, row) in rows.chunks_exact(2).enumerate() {
        let r = cluster_logits(row, 2, &mask_config(false, true), 0).unwrap();
        let v = r.centroid(0);
        let norm = (f64::from(v[0]).powi(2) + f64::from(v[1]).powi(2)).sqrt();
        let true_norm = (f64::from(row[0]).powi(2) + f64::from(row[1]).powi(2)).sqrt();
        let ok = if true_norm >= 1e-9 { (norm - 1.0).abs() < 1e-5 } else { norm <= 1.0 };
        assert!(ok, "row {i} {row:?} normalised to {v:?}");
    }
}

/// Collinear cameras, all on the z axis looking down −z: no axes meet.
fn collinear_scene() -> Scene {
    sos_core::testing::scene::blank_scene(5, 16, 12)
}

#[test]
fn collinear_cameras_have_a_finite_focus() {
    let scene = collinear_scene();
    let p = scene.focus_point();
    assert!(p.iter().all(|v| v.is_finite()), "{p:?}");
    match FocusTarget::of_scene(&scene) {
        FocusTarget::Axis { origin, direction } => {
            assert!(origin.iter().chain(&direction).all(|v| v.is_finite()));
            assert!((direction[2] + 1.0).abs() < 1e-5, "{direction:?}");
            // No hit in the central window: no focus rather than a NaN one.
            let target = FocusTarget::Axis { origin, direction };
            assert_eq!(target.point_for(&vec![EMPTY_RAY_DEPTH; 16 * 12], 16, 12), None);
            let q = target.point_for(&vec![2.0; 16 * 12], 16, 12).unwrap();
            assert!(q.iter().all(|v| v.is_finite()));
        }
        other => panic!("parallel axes are a forward-facing rig, got {other:?}"),
    }
    // Opposite cameras on one line: the mean axis vanishes; still a finite point.
    let mut scene = collinear_scene();
    scene.views[1].camera = Camera::look_at([0.0, 0.0, -4.0], [0.0; 3], [0.0, 1.0, 0.0], 16, 12, 100.0);
    scene.train = vec![0, 1];
    let p = match FocusTarget::of_scene(&scene) {
        FocusTarget::Point(p) => p,
        FocusTarget::Axis { origin, direction } => panic!("not parallel: {origin:?} {direction:?}"),
    };
    assert!(p.iter().all(|v| v.is_finite()), "{p:?}");
}
