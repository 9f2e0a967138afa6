//! Stage 2: training the segmentation head with the collaborative contrastive loss on strided
//! patches rendered by the (frozen) field.

use std::time::Instant;

use rand::SeedableRng;

use crate::camera::{axpy, Vec3};
use crate::config::{LogitSource, LossEntry};
use crate::error::RunError;
use crate::image::RgbImage;
use crate::plugin::{ContrastiveLoss, FeatureMap, PairMiner, PatchBatch};
use crate::render::composite::{is_hit, RayColour, RayGrad};
use crate::render::rays::RayBatch;
use crate::render::renderer::{RenderTiming, Rendered};
use crate::segment::defaults;
use crate::segment::frozen_render::FrozenRender;
use crate::segment::head::SegHead;
use crate::segment::head_pass::HeadSamples;
use crate::segment::patches::{patch_rays, Patch, PatchSampler};
use crate::segment::ray_cache::patch_keys;
use crate::segment::stability::MaskStability;
use crate::segment::surface::SurfacePoints;
use crate::segment::teacher::{captured_patch, Teacher};
use crate::train::observer::{Severity, Stage, TrainObserver, Unobserved};
use crate::train::session::{kind_of, Session};

/// Consecutive non-finite losses after which stage 2 stops.
const MAX_BAD_STEPS: usize = 20;

/// Offset of the patch sampler's seed from the run's (its own stream, so the patch sequence
/// does not depend on what else a step draws).
const PATCH_SEED: u64 = 0x9A7C;

/// A built loss term with its weight and name.
pub struct WeightedLoss {
    /// Name for logs (the loss kind).
    pub name: String,
    /// Weight in the total.
    pub weight: f32,
    /// The loss.
    pub loss: Box<dyn ContrastiveLoss>,
}

/// Everything stage 2 trains or consults.
pub struct Segmenter {
    /// The head attached to the field.
    pub head: SegHead,
    /// The frozen 2D teacher.
    pub teacher: Teacher,
    /// Negative-pair mining.
    pub miner: Box<dyn PairMiner>,
    /// Loss terms.
    pub losses: Vec<WeightedLoss>,
    /// Patch placement.
    pub sampler: PatchSampler,
    /// Stage-2 steps completed.
    pub step: usize,
    /// The step at which the masks settled and stage 2 stopped before `segment.steps`
    /// ([`crate::segment::stability`]), if it did.
    pub settled_at: Option<usize>,
    /// Buffers reused from step to step and from call to call of [`train_segmentation`].
    frozen: FrozenRender,
}

/// Loss values of one stage-2 step.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct SegStepStats {
    /// Weighted total.
    pub total: f64,
    /// Unweighted terms by name.
    pub terms: Vec<(String, f64)>,
    /// Head evaluations per ray after weight thresholding.
    pub samples_per_ray: f64,
    /// Share of probe pixels whose mask flipped since the previous stability check, on the
    /// steps that make one after the first ([`crate::segment::stability`]).
    pub mask_change: Option<f64>,
    /// Where the step's time went.
    #[serde(skip)]
    pub timing: Stage2Timing,
}

/// Seconds spent in each phase of one stage-2 step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Stage2Timing {
    /// The frozen field's render of the patches.
    pub render: RenderTiming,
    /// Rendering the patches, start to end (the render above and its compositing).
    pub field: f64,
    /// The head's forward pass and the compositing of its logits.
    pub head: f64,
    /// The teacher's features of the patches.
    pub teacher: f64,
    /// The losses and their gradients.
    pub losses: f64,
    /// Back through the compositing and the head, and the optimiser step.
    pub backward: f64,
}

impl Segmenter {
    /// Builds the head, teacher, miner and losses from the session's config.
    pub fn build(session: &Session) -> Result<Segmenter, RunError> {
        let cfg = &session.config;
        let ctx = session.build_context();
        let extractor = defaults::build_extractor(cfg.extractor.as_deref(), &ctx)?;
        let miner = match &cfg.miner {
            Some(m) => m.build()?,
            None => defaults::miner()
                .ok_or_else(|| defaults::not_linked("miner", defaults::DEFAULT_MINER, "miner"))?
                .build()?,
        };
        let default_losses;
        let entries: &[LossEntry] = if cfg.loss.is_empty() {
            default_losses = defaults::losses();
            &default_losses
        } else {
            &cfg.loss
        };
        let losses = entries
            .iter()
            .map(|e| Ok(WeightedLoss { name: kind_of(&e.loss), weight: e.weight, loss: e.loss.build()? }))
            .collect::<Result<Vec<_>, RunError>>()?;
        let seg = &cfg.segment;
        let sampler = PatchSampler::new(seg.patch_size, seg.stride, seg.offset_grid, cfg.seed.wrapping_add(PATCH_SEED));
        sampler.check(&session.scene).map_err(|message| {
            RunError::Config(crate::error::ConfigError::Invalid {
                path: session.config_source.clone(),
                key: "segment.patch_size".into(),
                reason: message,
            })
        })?;
        Ok(Segmenter {
            head: SegHead::new(&cfg.head, session.field.seg_input_dim(), seg.lr, cfg.seed),
            teacher: Teacher::new(extractor, seg.teacher_source, seg.cache_teacher),
            miner,
            losses,
            sampler,
            step: 0,
            settled_at: None,
            frozen: FrozenRender::new(session.render_options(false).memory),
        })
    }

    /// Frees the buffers stage-2 steps reuse (about a gigabyte for a 400x300 scene), for
    /// when training is over: mask inference then allocates into the memory they held
    /// instead of on top of it. A later call of [`train_segmentation`] allocates them again.
    pub fn release_step_buffers(&mut self) {
        self.frozen = FrozenRender::new(self.frozen.budget());
    }
}

/// Replaces the empty-ray depth sentinel (and any non-finite depth) by the largest real depth
/// of the batch (the reference's depth clip does the same for its sentinel).
pub fn fill_empty_depths(depth: &mut [f32]) {
    let max_real = depth.iter().copied().filter(|&d| is_hit(d)).fold(f32::NEG_INFINITY, f32::max);
    let fill = if max_real.is_finite() { max_real } else { 0.0 };
    for d in depth.iter_mut().filter(|d| !is_hit(**d)) {
        *d = fill;
    }
}

/// Runs stage 2 for `segment.steps` steps; messages are dropped (see
/// [`train_segmentation_observed`]).
pub fn train_segmentation(session: &mut Session, seg: &mut Segmenter) -> Result<SegStepStats, RunError> {
    train_segmentation_observed(session, seg, &mut Unobserved)
}

/// [`train_segmentation`], telling `observer` of the stage, its messages and every step.
pub fn train_segmentation_observed(
    session: &mut Session,
    seg: &mut Segmenter,
    observer: &mut dyn TrainObserver,
) -> Result<SegStepStats, RunError> {
    let cfg = session.config.segment.clone();
    let joint = cfg.photometric_weight > 0.0;
    if !joint {
        // The frozen field's gradients and optimiser moments would only hold memory.
        session.field.release_training_state();
    }
    let layout = PatchLayout { side: cfg.patch_size as usize };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(session.config.seed.wrapping_add(0x5E6 + seg.step as u64));
    observer.stage_begins(Stage::Segmentation, seg.step, cfg.steps);
    let mut stability = cfg.stop_when_stable.then(|| MaskStability::new(&session.scene, cfg.stable_change as f64));
    let mut last = SegStepStats::default();
    let mut bad_steps = 0;
    let first_step = seg.step;
    let mut good_steps = 0usize;
    while seg.step < cfg.steps {
        let patches = seg.sampler.next_batch(&session.scene, cfg.patches);
        for notice in seg.sampler.take_notices() {
            observer.message(Severity::Notice, &notice);
        }
        let timer = Instant::now();
        let rays = patch_rays(&session.scene, &patches);
        let mut r = match cfg.logits {
            // Only composited logits (and joint training, which needs them) use the samples:
            // they read the segmentation input at each one.
            LogitSource::Composited => {
                StepRender::Samples(Box::new(seg.frozen.render(session, &rays, joint, true, &mut rng)))
            }
            // The head at the surface needs each ray's composited render alone, and the field
            // is frozen (joint training with surface logits is refused): rays that recur are
            // looked up rather than rendered again.
            LogitSource::Surface => {
                let (colours, timing) = seg.frozen.colours(session, &rays, &patch_keys(&patches), &mut rng);
                StepRender::Rays { colours, timing }
            }
        };
        let t_field = timer.elapsed().as_secs_f64();
        let out = composite(session, seg, &r, &rays, layout);
        let t_render = timer.elapsed().as_secs_f64();
        let features = seg.teacher.features(&session.scene, &patches, &out.images, !joint)?;
        let t_teacher = timer.elapsed().as_secs_f64();
        let (mut stats, grad_logits) = losses(seg, &out, &features, layout, &mut rng);
        let head_evaluations = match (&r, &out.surface) {
            (_, Some(surface)) => surface.positions().len(),
            (StepRender::Samples(r), None) => r.samples.len(),
            (StepRender::Rays { .. }, None) => 0,
        };
        stats.samples_per_ray = head_evaluations as f64 / rays.len() as f64;
        let targets = joint.then(|| captured_targets(session, &patches));
        if let Some(targets) = &targets {
            let photometric = patch_mse(r.colours(), targets);
            stats.total += cfg.photometric_weight as f64 * photometric;
            stats.terms.push(("photometric".into(), photometric));
        }
        let t_losses = timer.elapsed().as_secs_f64();
        if !stats.total.is_finite() || grad_logits.iter().any(|g| !g.is_finite()) {
            bad_steps += 1;
            observer.message(
                Severity::Warning,
                &format!(
                    "stage 2 step {}: non-finite loss or gradient (views {:?}), step skipped",
                    seg.step,
                    patches.iter().map(|p| p.view).collect::<Vec<_>>()
                ),
            );
            if bad_steps >= MAX_BAD_STEPS {
                return Err(RunError::Diverged(format!("{MAX_BAD_STEPS} non-finite stage-2 steps in a row")));
            }
            r.recycle(&mut seg.frozen);
            seg.step += 1;
            continue;
        }
        bad_steps = 0;
        good_steps += 1;
        let ray_grad = backward(session, seg, &r, &out, layout, &grad_logits);
        let lr_factor = cfg.final_lr_factor.powf(seg.step as f32 / cfg.steps.max(1) as f32);
        seg.head.step(lr_factor);
        stats.timing = Stage2Timing {
            render: r.timing(),
            field: t_field,
            head: t_render - t_field,
            teacher: t_teacher - t_render,
            losses: t_losses - t_teacher,
            backward: timer.elapsed().as_secs_f64() - t_losses,
        };
        if let (Some(targets), StepRender::Samples(rendered)) = (&targets, &mut r) {
            let joint = JointStep { weight: cfg.photometric_weight, targets, lr_factor };
            joint.step(session, rendered, &out.sample_logits, &ray_grad);
        }
        r.recycle(&mut seg.frozen);
        seg.step += 1;
        last = stats;
        let settled = match &mut stability {
            Some(stability) if seg.step.is_multiple_of(cfg.check_every) && seg.step < cfg.steps => {
                last.mask_change = stability.check(session, &seg.head, Some(seg.teacher.extractor()), seg.step)?;
                stability.settled()
            }
            _ => false,
        };
        observer.stage2_step(session, seg, &last)?;
        if settled {
            observer.message(
                Severity::Notice,
                &format!(
                    "stage 2 step {}: the masks settled (at most {:.2}% of probe pixels flipped in each of the last \
                     {} checks), stopping before step {} (`segment.stop_when_stable = false` runs them all)",
                    seg.step,
                    100.0 * cfg.stable_change,
                    crate::segment::stability::CALM_CHECKS,
                    cfg.steps
                ),
            );
            seg.settled_at = Some(seg.step);
            break;
        }
    }
    observer.stage_ends(Stage::Segmentation);
    // Fewer bad steps in a row than the limit, yet none that trained: the head is as it began.
    if seg.step > first_step && good_steps == 0 {
        return Err(RunError::Diverged(format!(
            "none of the {} stage-2 steps had a finite loss, so the head did not train; check the `[[loss]]` \
             settings",
            seg.step - first_step
        )));
    }
    Ok(last)
}

/// Where each ray of a step sits in the losses' layout: patch after patch, channel-first
/// within a patch (`[patch, channel, pixel]`), while the renderer is ray-major
/// (`[ray, channel]`, the rays of a patch consecutive).
#[derive(Debug, Clone, Copy)]
struct PatchLayout {
    /// Rays along a patch's side.
    side: usize,
}

impl PatchLayout {
    fn rays_per_patch(self) -> usize {
        self.side * self.side
    }

    /// `[ray, d]` values to `[patch, d, pixel]`.
    fn to_patches(self, ray_major: &[f32], d: usize) -> Vec<f32> {
        let n = self.rays_per_patch();
        let mut out = vec![0.0f32; ray_major.len()];
        for (ray, v) in ray_major.chunks_exact(d).enumerate() {
            let (patch, pix) = (ray / n, ray % n);
            for (c, &v) in v.iter().enumerate() {
                out[(patch * d + c) * n + pix] = v;
            }
        }
        out
    }

    /// `[patch, d, pixel]` values to `[ray, d]`.
    fn to_rays(self, patch_major: &[f32], d: usize) -> Vec<f32> {
        let n = self.rays_per_patch();
        let mut out = vec![0.0f32; patch_major.len()];
        for (ray, v) in out.chunks_exact_mut(d).enumerate() {
            let (patch, pix) = (ray / n, ray % n);
            for (c, v) in v.iter_mut().enumerate() {
                *v = patch_major[(patch * d + c) * n + pix];
            }
        }
        out
    }
}

/// What a stage-2 step rendered of its rays.
enum StepRender {
    /// Every kept sample, composited: for composited logits, which read the samples.
    Samples(Box<Rendered>),
    /// Each ray's composited result alone (cached from step to step): for logits at the surface.
    Rays {
        /// The rays' composited values.
        colours: Vec<RayColour>,
        /// The render of the rays no earlier step had rendered.
        timing: RenderTiming,
    },
}

impl StepRender {
    fn colours(&self) -> &[RayColour] {
        match self {
            StepRender::Samples(r) => &r.colours,
            StepRender::Rays { colours, .. } => colours,
        }
    }

    fn timing(&self) -> RenderTiming {
        match self {
            StepRender::Samples(r) => r.timing,
            StepRender::Rays { timing, .. } => *timing,
        }
    }

    /// Hands a full render's buffers back for the next step.
    fn recycle(&mut self, frozen: &mut FrozenRender) {
        if let StepRender::Samples(r) = self {
            frozen.recycle(r);
        }
    }
}

/// What the losses see of a step's render.
struct Composited {
    /// The head's logits at every surviving sample, `[samples, d_seg]` (with
    /// `segment.logits = "composited"`; at the surface points otherwise).
    sample_logits: Vec<f32>,
    /// With `segment.logits = "surface"`: where the head ran, one point per ray that hit.
    surface: Option<SurfacePoints>,
    /// Composited logits in the losses' layout, `[patch, d_seg, pixel]`.
    logits: Vec<f32>,
    /// Each ray's rendered 3D point (empty rays at the batch's farthest depth),
    /// `[patch, 3, pixel]`.
    points: Vec<f32>,
    /// The rendered patches, the teacher's input with `teacher_source = "rendered"`.
    images: Vec<RgbImage>,
}

/// The head on the surviving samples, its logits composited with the field's weights (as
/// inference composites them), or once per ray at its surface (`segment.logits`), and the
/// rendered depth's points and colours.
fn composite(
    session: &Session,
    seg: &mut Segmenter,
    r: &StepRender,
    rays: &RayBatch,
    layout: PatchLayout,
) -> Composited {
    let d_seg = seg.head.outputs();
    let colours = r.colours();
    let (sample_logits, ray_logits, surface) = match r {
        StepRender::Samples(r) => {
            let head_samples = HeadSamples { positions: &r.samples.positions, seg_input: &r.seg_input };
            let sample_logits = seg.frozen.head_forward(session, &seg.head, head_samples);
            let ray_logits = r.composite_values(&sample_logits, d_seg, |_| true);
            (sample_logits, ray_logits, None)
        }
        StepRender::Rays { .. } => {
            let points: Vec<Option<Vec3>> = (0..rays.len())
                .map(|i| {
                    let t = colours[i].median_depth;
                    is_hit(t).then(|| axpy(rays.origins[i], t, rays.directions[i]))
                })
                .collect();
            let opacities: Vec<f32> = colours.iter().map(|c| c.acc).collect();
            let surface = SurfacePoints::new(&points, &opacities);
            let values = seg.frozen.head_forward(session, &seg.head, HeadSamples::at(surface.positions()));
            let ray_logits = surface.ray_logits(&values, rays.len(), d_seg);
            (values, ray_logits, Some(surface))
        }
    };
    let logits = layout.to_patches(&ray_logits, d_seg);
    let mut depth: Vec<f32> = colours.iter().map(|c| c.depth).collect();
    fill_empty_depths(&mut depth);
    let ray_points: Vec<f32> = (0..rays.len())
        .flat_map(|ray| {
            let (o, d) = (rays.origins[ray], rays.directions[ray]);
            let t = depth[ray];
            (0..3).map(move |a| o[a] + d[a] * t)
        })
        .collect();
    let points = layout.to_patches(&ray_points, 3);
    let images = patch_images(colours, layout.side);
    Composited { sample_logits, surface, logits, points, images }
}

/// Negative pairs from the teacher's global vectors, then every loss term: the weighted total,
/// the terms, and the gradient of the total with respect to the composited logits.
fn losses(
    seg: &Segmenter,
    out: &Composited,
    features: &[FeatureMap],
    layout: PatchLayout,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> (SegStepStats, Vec<f32>) {
    let cls: Vec<Vec<f32>> = features.iter().map(|f| f.cls.clone()).collect();
    let negatives = seg.miner.negatives(&cls, rng);
    let d_seg = seg.head.outputs();
    let batch = PatchBatch {
        n_patches: out.images.len(),
        patch: layout.side,
        d_seg,
        logits: &out.logits,
        points: &out.points,
        features,
        negatives: &negatives,
    };
    let mut grad_logits = vec![0.0f32; out.logits.len()];
    let mut stats = SegStepStats::default();
    for l in &seg.losses {
        let v = l.loss.loss_and_grad(&batch, rng, l.weight, &mut grad_logits);
        stats.total += l.weight as f64 * v.total;
        stats.terms.extend(v.terms);
    }
    (stats, grad_logits)
}

/// Back through the compositing (`∂L/∂logits_k = w_k ∂L/∂s(ray)`) and the head; returns the
/// gradient with respect to each ray's composited logits, `[ray, d_seg]`.
fn backward(
    session: &Session,
    seg: &mut Segmenter,
    r: &StepRender,
    out: &Composited,
    layout: PatchLayout,
    grad_logits: &[f32],
) -> Vec<f32> {
    let d_seg = seg.head.outputs();
    let ray_grad = layout.to_rays(grad_logits, d_seg);
    if let Some(surface) = &out.surface {
        let grad_point = surface.point_grads(&ray_grad, d_seg);
        seg.frozen.head_backward(session, &mut seg.head, HeadSamples::at(surface.positions()), &grad_point);
    } else if let StepRender::Samples(r) = r {
        let grad_sample = r.composite_values_backward(&ray_grad, d_seg);
        let head_samples = HeadSamples { positions: &r.samples.positions, seg_input: &r.seg_input };
        seg.frozen.head_backward(session, &mut seg.head, head_samples, &grad_sample);
    }
    ray_grad
}

/// Joint training: the field learns from the photometric loss against the photographs and
/// from the logits' dependence on the compositing weights.
struct JointStep<'a> {
    weight: f32,
    targets: &'a [[f32; 3]],
    lr_factor: f32,
}

impl JointStep<'_> {
    fn step(&self, session: &mut Session, r: &mut Rendered, sample_logits: &[f32], ray_grad: &[f32]) {
        let n_rays = r.colours.len();
        let d_seg = ray_grad.len() / n_rays.max(1);
        let scale = 2.0 * self.weight / (n_rays * 3) as f32;
        let grads: Vec<RayGrad> = (0..n_rays)
            .map(|ray| {
                let mut g = RayGrad { extra: &ray_grad[ray * d_seg..(ray + 1) * d_seg], ..Default::default() };
                for k in 0..3 {
                    g.rgb[k] = scale * (r.colours[ray].rgb[k] - self.targets[ray][k]);
                }
                g
            })
            .collect();
        let (g_sigma, g_rgb, _) = r.composite_backward(sample_logits, d_seg, &grads);
        let tape = r.tape.take();
        session.field.backward(&r.samples.positions, &r.samples.directions, tape, &g_sigma, &g_rgb);
        session.field.step(self.lr_factor * session.config.train.final_lr_factor);
    }
}

/// Rendered colours of `p x p` patches, patch after patch, as images.
fn patch_images(colours: &[RayColour], p: usize) -> Vec<RgbImage> {
    colours
        .chunks(p * p)
        .map(|patch| {
            let mut img = RgbImage::new(p, p);
            for (px, c) in img.data.chunks_exact_mut(3).zip(patch) {
                px.copy_from_slice(&c.rgb);
            }
            img
        })
        .collect()
}

/// The frozen field's rendering of each patch as a stage-2 step renders it: the teacher's
/// input with `teacher_source = "rendered"` (e.g. to fill the teacher cache ahead of steps).
pub fn render_patches(session: &Session, patches: &[Patch]) -> Vec<RgbImage> {
    let rays = patch_rays(&session.scene, patches);
    // Evaluation marching is not stratified: the generator does not change the result.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(session.config.seed);
    let r = FrozenRender::new(session.render_options(false).memory).render(session, &rays, false, false, &mut rng);
    patch_images(&r.colours, session.config.segment.patch_size as usize)
}

/// The photographs' colours at each patch ray, patch after patch.
fn captured_targets(session: &Session, patches: &[Patch]) -> Vec<[f32; 3]> {
    patches
        .iter()
        .flat_map(|patch| {
            let img = captured_patch(&session.scene, patch);
            img.data.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect::<Vec<_>>()
        })
        .collect()
}

fn patch_mse(colours: &[RayColour], targets: &[[f32; 3]]) -> f64 {
    let sum: f64 =
        colours.iter().zip(targets).map(|(c, t)| (0..3).map(|k| ((c.rgb[k] - t[k]) as f64).powi(2)).sum::<f64>()).sum();
    sum / (colours.len() * 3).max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::composite::EMPTY_RAY_DEPTH;

    #[test]
    fn patch_layout_is_patch_then_channel_then_pixel_and_inverts() {
        // Two 2x2 patches (8 rays), two channels: value = 10·ray + channel.
        let layout = PatchLayout { side: 2 };
        let rays: Vec<f32> = (0..8).flat_map(|ray| (0..2).map(move |c| (10 * ray + c) as f32)).collect();
        let patches = layout.to_patches(&rays, 2);
        // Patch 1, channel 1, pixel 2 is ray 4 + 2 = 6, channel 1.
        assert_eq!(patches[(2 + 1) * 4 + 2], 61.0);
        assert_eq!(patches[..4], [0.0, 10.0, 20.0, 30.0]);
        assert_eq!(layout.to_rays(&patches, 2), rays);
    }

    #[test]
    fn empty_depths_take_the_farthest_real_depth() {
        let mut depth = vec![1.0, EMPTY_RAY_DEPTH, 3.0];
        fill_empty_depths(&mut depth);
        assert_eq!(depth, [1.0, 3.0, 3.0]);
        let mut none = vec![EMPTY_RAY_DEPTH; 2];
        fill_empty_depths(&mut none);
        assert_eq!(none, [0.0, 0.0]);
    }
}
