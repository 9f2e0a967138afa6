//! Stage 2: training the segmentation head with the collaborative contrastive loss on strided
//! patches rendered by the (frozen) field.

use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;

use crate::config::LossEntry;
use crate::error::{BuildError, RunError};
use crate::image::RgbImage;
use crate::plugin::{ContrastiveLoss, PairMiner, PatchBatch};
use crate::render::composite::{RayColor, RayGrad, EMPTY_RAY_DEPTH};
use crate::segment::defaults;
use crate::segment::frozen_render::FrozenRender;
use crate::segment::head::SegHead;
use crate::segment::head_pass::HeadSamples;
use crate::segment::patches::{patch_rays, Patch, PatchSampler};
use crate::segment::teacher::{captured_patch, Teacher};
use crate::train::observer::{TrainObserver, Unobserved};
use crate::train::progress::log_line;
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
}

fn missing(role: &str, kind: &str, table: &str) -> RunError {
    RunError::Build(BuildError::Resource {
        kind: kind.into(),
        message: format!("no `[{table}]` configured and the default `{kind}` {role} is not linked into this program"),
    })
}

impl Segmenter {
    /// Builds the head, teacher, miner and losses from the session's config.
    pub fn build(session: &Session) -> Result<Segmenter, RunError> {
        let cfg = &session.config;
        let ctx = session.build_context();
        let extractor = match &cfg.extractor {
            Some(e) => e.build(&ctx)?,
            None => defaults::extractor()
                .ok_or_else(|| missing("extractor", defaults::DEFAULT_EXTRACTOR, "extractor"))?
                .build(&ctx)?,
        };
        let miner = match &cfg.miner {
            Some(m) => m.build()?,
            None => defaults::miner().ok_or_else(|| missing("miner", defaults::DEFAULT_MINER, "miner"))?.build()?,
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
                path: session.config_dir.clone(),
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
            frozen: FrozenRender::new(session.render_options(false).memory),
        })
    }
}

/// Replaces the empty-ray depth sentinel by the largest real depth of the batch (the
/// reference's depth clip does the same for its sentinel).
pub fn fill_empty_depths(depth: &mut [f32]) {
    let limit = EMPTY_RAY_DEPTH * 0.5;
    let max_real = depth.iter().copied().filter(|&d| d < limit).fold(f32::NEG_INFINITY, f32::max);
    let fill = if max_real.is_finite() { max_real } else { 0.0 };
    for d in depth.iter_mut().filter(|d| **d >= limit) {
        *d = fill;
    }
}

/// Runs stage 2 for `segment.steps` steps.
pub fn train_segmentation(
    session: &mut Session,
    seg: &mut Segmenter,
    show_progress: bool,
) -> Result<SegStepStats, RunError> {
    train_segmentation_observed(session, seg, show_progress, &mut Unobserved)
}

/// [`train_segmentation`], calling `observer` after every step.
pub fn train_segmentation_observed(
    session: &mut Session,
    seg: &mut Segmenter,
    show_progress: bool,
    observer: &mut dyn TrainObserver,
) -> Result<SegStepStats, RunError> {
    let cfg = session.config.segment.clone();
    let joint = cfg.photometric_weight > 0.0;
    let n_patches = cfg.patches;
    let p = cfg.patch_size as usize;
    let rays_per_patch = p * p;
    let d_seg = seg.head.outputs();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(session.config.seed.wrapping_add(0x5E6 + seg.step as u64));
    let bar = if show_progress { ProgressBar::new(cfg.steps as u64) } else { ProgressBar::hidden() };
    bar.set_style(
        ProgressStyle::with_template("stage 2 {bar:30} {pos}/{len} {msg} [{elapsed_precise}<{eta_precise}]")
            .expect("valid template"),
    );
    let started = Instant::now();
    let mut last = SegStepStats::default();
    let mut bad_steps = 0;
    while seg.step < cfg.steps {
        let patches = seg.sampler.next_batch(&session.scene, n_patches);
        for notice in seg.sampler.take_notices() {
            log_line(&bar, format!("notice: {notice}"));
        }
        let timer = Instant::now();
        let rays = patch_rays(&session.scene, &patches);
        let mut r = seg.frozen.render(session, &rays, joint, true, &mut rng);

        // Head on the surviving samples, then logits composited with the field's weights.
        let n_samples = r.samples.len();
        let t_field = timer.elapsed().as_secs_f64();
        let head_samples = HeadSamples { positions: &r.samples.positions, seg_input: &r.seg_input };
        let sample_logits = seg.frozen.head_forward(session, &seg.head, head_samples);
        // Ray-major logits, as inference composites them, laid out per patch channel-first
        // for the losses.
        let ray_logits = r.composite_values(&sample_logits, d_seg, |_| true);
        let mut logits = vec![0.0f32; n_patches * d_seg * rays_per_patch];
        for (ray, l) in ray_logits.chunks_exact(d_seg).enumerate() {
            let (patch, pix) = (ray / rays_per_patch, ray % rays_per_patch);
            for (c, &v) in l.iter().enumerate() {
                logits[(patch * d_seg + c) * rays_per_patch + pix] = v;
            }
        }

        // Depth-derived points and rendered patch images.
        let mut depth: Vec<f32> = r.colors.iter().map(|c| c.depth).collect();
        fill_empty_depths(&mut depth);
        let mut points = vec![0.0f32; n_patches * 3 * rays_per_patch];
        for ray in 0..rays.len() {
            let (patch, pix) = (ray / rays_per_patch, ray % rays_per_patch);
            let (o, d) = (rays.origins[ray], rays.directions[ray]);
            for a in 0..3 {
                points[(patch * 3 + a) * rays_per_patch + pix] = o[a] + d[a] * depth[ray];
            }
        }
        let rendered = patch_images(&r.colors, p);
        let t_render = timer.elapsed().as_secs_f64();
        let features = seg.teacher.features(&session.scene, &patches, &rendered, !joint)?;
        let t_teacher = timer.elapsed().as_secs_f64();
        let cls: Vec<Vec<f32>> = features.iter().map(|f| f.cls.clone()).collect();
        let negatives = seg.miner.negatives(&cls, &mut rng);
        let batch = PatchBatch {
            n_patches,
            patch: p,
            d_seg,
            logits: &logits,
            points: &points,
            features: &features,
            negatives: &negatives,
        };
        let mut grad_logits = vec![0.0f32; logits.len()];
        let mut stats = SegStepStats { samples_per_ray: n_samples as f64 / rays.len() as f64, ..Default::default() };
        for l in &seg.losses {
            let v = l.loss.loss_and_grad(&batch, &mut rng, l.weight, &mut grad_logits);
            stats.total += l.weight as f64 * v.total;
            stats.terms.extend(v.terms);
        }
        let t_losses = timer.elapsed().as_secs_f64();
        let targets = if joint { captured_targets(session, &patches) } else { Vec::new() };
        if joint {
            let photometric = patch_mse(&r.colors, &targets);
            stats.total += cfg.photometric_weight as f64 * photometric;
            stats.terms.push(("photometric".into(), photometric));
        }
        if !stats.total.is_finite() || grad_logits.iter().any(|g| !g.is_finite()) {
            bad_steps += 1;
            log_line(
                &bar,
                format!(
                    "stage 2 step {}: non-finite loss or gradient (views {:?}), step skipped",
                    seg.step,
                    patches.iter().map(|p| p.view).collect::<Vec<_>>()
                ),
            );
            if bad_steps >= MAX_BAD_STEPS {
                return Err(RunError::Diverged(format!("{MAX_BAD_STEPS} non-finite stage-2 steps in a row")));
            }
            seg.frozen.recycle(&mut r);
            seg.step += 1;
            continue;
        }
        bad_steps = 0;

        // Back through the compositing: ∂L/∂logits_k = w_k ∂L/∂s(ray).
        let mut ray_grad_extra = vec![0.0f32; rays.len() * d_seg];
        for (ray, g) in ray_grad_extra.chunks_exact_mut(d_seg).enumerate() {
            let (patch, pix) = (ray / rays_per_patch, ray % rays_per_patch);
            for (c, g) in g.iter_mut().enumerate() {
                *g = grad_logits[(patch * d_seg + c) * rays_per_patch + pix];
            }
        }
        let grad_sample = r.composite_values_backward(&ray_grad_extra, d_seg);
        seg.frozen.head_backward(session, &mut seg.head, head_samples, &grad_sample);
        let lr_factor = cfg.final_lr_factor.powf(seg.step as f32 / cfg.steps.max(1) as f32);
        seg.head.step(lr_factor);
        if std::env::var("SOS_PROFILE").is_ok() {
            eprintln!(
                "stage 2: render {:.3} head {:.3} teacher {:.3} losses {:.3} backward {:.3}",
                t_field,
                t_render - t_field,
                t_teacher - t_render,
                t_losses - t_teacher,
                timer.elapsed().as_secs_f64() - t_losses
            );
        }

        if joint {
            // The field learns from the photometric loss and from the logits' dependence on
            // the compositing weights.
            let scale = 2.0 * cfg.photometric_weight / (rays.len() * 3) as f32;
            let grads: Vec<RayGrad> = (0..rays.len())
                .map(|ray| {
                    let mut g =
                        RayGrad { extra: &ray_grad_extra[ray * d_seg..(ray + 1) * d_seg], ..Default::default() };
                    for k in 0..3 {
                        g.rgb[k] = scale * (r.colors[ray].rgb[k] - targets[ray][k]);
                    }
                    g
                })
                .collect();
            let (g_sigma, g_rgb, _) = r.composite_backward(&sample_logits, d_seg, &grads);
            let tape = r.tape.take();
            session.field.backward(&r.samples.positions, &r.samples.directions, tape, &g_sigma, &g_rgb);
            session.field.step(lr_factor * session.config.train.final_lr_factor);
        }
        seg.frozen.recycle(&mut r);
        seg.step += 1;
        last = stats;
        observer.stage2_step(session, seg, &last)?;
        let elapsed = started.elapsed().as_secs_f64();
        bar.set_message(format!(
            "loss {:+.4}  {:.1} s/step  {:.0} head samples/ray  cache {}/{}",
            last.total,
            elapsed / seg.step.max(1) as f64,
            last.samples_per_ray,
            seg.teacher.hits,
            seg.teacher.hits + seg.teacher.misses
        ));
        bar.set_position(seg.step as u64);
        if !show_progress && (seg.step.is_multiple_of((cfg.steps / 10).max(1)) || seg.step == cfg.steps) {
            eprintln!(
                "stage 2 step {}/{}: loss {:+.5}, {:.2} s/step, {:.0} head samples/ray, {:.0} s",
                seg.step,
                cfg.steps,
                last.total,
                elapsed / seg.step.max(1) as f64,
                last.samples_per_ray,
                elapsed
            );
        }
    }
    bar.finish();
    Ok(last)
}

/// Rendered colours of `p x p` patches, patch after patch, as images.
fn patch_images(colors: &[RayColor], p: usize) -> Vec<RgbImage> {
    colors
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
    patch_images(&r.colors, session.config.segment.patch_size as usize)
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

fn patch_mse(colors: &[RayColor], targets: &[[f32; 3]]) -> f64 {
    let sum: f64 =
        colors.iter().zip(targets).map(|(c, t)| (0..3).map(|k| ((c.rgb[k] - t[k]) as f64).powi(2)).sum::<f64>()).sum();
    sum / (colors.len() * 3).max(1) as f64
}
