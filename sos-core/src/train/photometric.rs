//! Stage 1: fitting the radiance field to the photographs with an MSE loss on random rays.

use std::time::Instant;

use rand::{Rng, SeedableRng};

use crate::error::RunError;
use crate::plugin::field::plain;
use crate::render::composite::{RayColour, RayGrad};
use crate::render::rays::RayBatch;
use crate::render::renderer::{render, RenderTiming};
use crate::train::convergence::PlateauMonitor;
use crate::train::face_pileup::{face_pileup_warning, FaceFigures, FaceMonitor};
use crate::train::observer::{Severity, Stage, TrainObserver, Unobserved};
use crate::train::session::Session;

/// Stage-1 steps between looks at where rays end on a box's faces.
const FACE_CHECK_EVERY: usize = 4;

/// Consecutive non-finite losses after which training stops.
const MAX_BAD_STEPS: usize = 20;

/// Statistics of one training step.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct StepStats {
    /// Mean squared error over the batch.
    pub mse: f64,
    /// PSNR of that error.
    pub psnr: f64,
    /// Surviving samples per ray.
    pub samples_per_ray: f64,
    /// Mean opacity of the batch's rays.
    pub opacity: f64,
    /// Rays ending on a bounded extent's faces, and how badly they fit (`None` for other
    /// extents).
    pub faces: Option<FaceFigures>,
    /// Where the step's time went.
    #[serde(skip)]
    pub timing: Stage1Timing,
}

/// Seconds spent in each phase of one stage-1 step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Stage1Timing {
    /// The render of the batch (marching, density pass, full pass).
    pub render: RenderTiming,
    /// Back through the compositing.
    pub composite_backward: f64,
    /// The field's (and its proposal network's) backward pass.
    pub field_backward: f64,
    /// The field's regulariser and the finiteness check.
    pub regularize: f64,
    /// The optimiser step.
    pub step: f64,
}

/// MSE over a batch's rays and the per-ray gradients (`scale · (c − target)` per channel), with
/// direct per-sample weight gradients from `weight_grads(ray)`.
fn ray_mse_grads<'a>(
    colours: &[RayColour],
    targets: &[[f32; 3]],
    scale: f32,
    weight_grads: impl Fn(usize) -> &'a [f32],
) -> (f64, Vec<RayGrad<'a>>) {
    let mut mse = 0.0f64;
    let grads = colours
        .iter()
        .zip(targets)
        .enumerate()
        .map(|(ray, (c, t))| {
            let mut g = RayGrad { weights: weight_grads(ray), ..Default::default() };
            for k in 0..3 {
                let e = c.rgb[k] - t[k];
                mse += (e * e) as f64;
                g.rgb[k] = scale * e;
            }
            g
        })
        .collect();
    (mse / (colours.len() * 3).max(1) as f64, grads)
}

/// Whether per-sample gradients are all finite.
fn all_finite(g_sigma: &[f32], g_rgb: &[[f32; 3]]) -> bool {
    g_sigma.iter().all(|g| g.is_finite()) && g_rgb.iter().all(|g| g.iter().all(|v| v.is_finite()))
}

/// Which rays of a batch rendered non-finite colours: a count and the first few as
/// `view:col,row`.
fn describe_bad_rays(fine: &[RayColour], coarse: Option<&[RayColour]>, pixels: &[(usize, u32, u32)]) -> String {
    let bad = |c: &RayColour| !(c.rgb.iter().all(|v| v.is_finite()) && c.acc.is_finite());
    let idx: Vec<usize> = (0..pixels.len()).filter(|&i| bad(&fine[i]) || coarse.is_some_and(|c| bad(&c[i]))).collect();
    let first: Vec<String> =
        idx.iter().take(8).map(|&i| format!("{}:{},{}", pixels[i].0, pixels[i].1, pixels[i].2)).collect();
    let views: std::collections::BTreeSet<usize> = pixels.iter().map(|p| p.0).collect();
    format!(
        "{} rays from views {:?}; {} rendered non-finite colours{}{}",
        pixels.len(),
        views.into_iter().take(16).collect::<Vec<_>>(),
        idx.len(),
        if first.is_empty() { "" } else { ", first (view:col,row): " },
        first.join(" ")
    )
}

/// Runs stage 1 from `session.step` to `train.steps`, checkpointing along the way; messages
/// are dropped (see [`train_photometric_observed`]).
pub fn train_photometric(session: &mut Session) -> Result<StepStats, RunError> {
    train_photometric_observed(session, &mut Unobserved)
}

/// [`train_photometric`], telling `observer` of the stage, its messages and every step.
pub fn train_photometric_observed(
    session: &mut Session,
    observer: &mut dyn TrainObserver,
) -> Result<StepStats, RunError> {
    let total = session.config.train.steps;
    let n_rays = session.config.train.rays_per_step;
    // One random stream for the whole stage; a resumed run continues it where the checkpoint
    // left it (a checkpoint without the position: a stream of its own from that step).
    let mut rng = match session.rng_position {
        Some(position) => {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(session.config.seed);
            rng.set_word_pos(position);
            rng
        }
        None => rand_chacha::ChaCha8Rng::seed_from_u64(session.config.seed.wrapping_add(session.step as u64)),
    };
    observer.stage_begins(Stage::Photometric, session.step, total);
    let mut last = StepStats::default();
    let mut bad_steps = 0;
    let mut faces = FaceMonitor::default();
    let mut warned_faces = false;
    let t = &session.config.train;
    let mut plateau = t.stop_when_converged.then(|| PlateauMonitor::new(t.converged_window, t.converged_gain as f64));
    while session.step < total {
        if plain::begin_step(session.field.as_mut(), session.step, total) {
            session.refresh_occupancy(0.0);
        }
        session.maintain_occupancy();

        // A batch of random rays from random training views.
        let mut rays = RayBatch::default();
        let mut targets = Vec::with_capacity(n_rays);
        let mut pixels = Vec::with_capacity(n_rays);
        for _ in 0..n_rays {
            let vi = session.scene.train[rng.gen_range(0..session.scene.train.len())];
            let v = &session.scene.views[vi];
            let (col, row) = (rng.gen_range(0..v.camera.width), rng.gen_range(0..v.camera.height));
            rays.push_pixel(&v.camera, col, row);
            targets.push(v.image.pixel(col as usize, row as usize));
            pixels.push((vi, col, row));
        }
        let options = session.render_options(true);
        let mut r = render(session.field.as_ref(), session.render_context(), &rays, options, true, &mut rng);
        r.composite();
        let mut coarse = r.coarse.take();

        let scale = 2.0 / (n_rays * 3) as f32;
        // DVGO's per-sample colour loss λ/N Σ_k w_k ‖c_k − C‖²: fog of the wrong colour is
        // penalised directly, which carves empty space much faster than the ray loss alone.
        let lambda = session.config.train.sample_colour_weight / n_rays as f32;
        let mut g_weight = vec![0.0f32; r.samples.len()];
        let mut g_rgb_direct = vec![[0.0f32; 3]; if lambda > 0.0 { r.samples.len() } else { 0 }];
        if lambda > 0.0 {
            for (ray, t) in targets.iter().enumerate() {
                for k in r.samples.range(ray) {
                    let c = r.rgb[k];
                    let d = [c[0] - t[0], c[1] - t[1], c[2] - t[2]];
                    g_weight[k] = lambda * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
                    for j in 0..3 {
                        g_rgb_direct[k][j] = lambda * 2.0 * r.weights[k] * d[j];
                    }
                }
            }
        }
        // mip-NeRF 360's distortion loss over the marched samples' normalised positions.
        let distortion = session.config.train.distortion_weight / n_rays as f32;
        if distortion > 0.0 && r.samples.s.len() == r.samples.len() {
            let width = 1.0 / options.march.steps.max(1) as f32;
            for ray in 0..r.samples.n_rays() {
                let range = r.samples.range(ray);
                crate::render::distortion::distortion(
                    &r.weights[range.clone()],
                    &r.samples.s[range.clone()],
                    width,
                    distortion,
                    &mut g_weight[range],
                );
            }
        }
        if session.step.is_multiple_of(FACE_CHECK_EVERY) {
            faces.observe(&session.contraction, &r, &targets);
        }
        let (mse, grads) = ray_mse_grads(&r.colours, &targets, scale, |ray| &g_weight[r.samples.range(ray)]);
        // The coarse (proposal) network of a hierarchical field gets its own MSE, as in NeRF.
        let (coarse_mse, coarse_grads) = match &coarse {
            Some(c) => ray_mse_grads(&c.colours, &targets, scale, |_| &[]),
            None => (0.0, Vec::new()),
        };
        let mut finite = mse.is_finite() && coarse_mse.is_finite();
        let timer = Instant::now();
        let (mut t_cb, mut t_fb) = (0.0, 0.0);
        if finite {
            let (g_sigma, mut g_rgb, _) = r.composite_backward(&[], 0, &grads);
            for (g, d) in g_rgb.iter_mut().zip(&g_rgb_direct) {
                for j in 0..3 {
                    g[j] += d[j];
                }
            }
            let coarse_g = coarse.as_ref().map(|c| c.composite_backward(&[], 0, &coarse_grads));
            finite = all_finite(&g_sigma, &g_rgb) && coarse_g.as_ref().is_none_or(|(gs, gc, _)| all_finite(gs, gc));
            t_cb = timer.elapsed().as_secs_f64();
            if finite {
                let tape = r.tape.take();
                session.field.backward(&r.samples.positions, &r.samples.directions, tape, &g_sigma, &g_rgb);
                if let (Some(c), Some((gs, gc, _))) = (coarse.as_mut(), coarse_g) {
                    let tape = c.tape.take();
                    let (p, d) = (&c.samples.positions, &c.samples.directions);
                    match session.field.hierarchical_mut().and_then(|h| h.proposal_mut()) {
                        Some(proposal) => proposal.backward(p, d, tape, &gs, &gc),
                        None => session.field.backward(p, d, tape, &gs, &gc),
                    }
                }
                t_fb = timer.elapsed().as_secs_f64();
                plain::regularize(session.field.as_mut());
                finite = session.field.gradients_finite();
            }
        }
        if !finite {
            session.field.discard_gradients();
            bad_steps += 1;
            observer.message(Severity::Warning, &format!(
                "stage 1 step {}: non-finite loss or gradient (mse {mse}, coarse mse {coarse_mse}), step skipped; batch: {}",
                session.step,
                describe_bad_rays(&r.colours, coarse.as_ref().map(|c| &c.colours[..]), &pixels)
            ));
            if bad_steps >= MAX_BAD_STEPS {
                return Err(RunError::Diverged(format!(
                    "{MAX_BAD_STEPS} stage-1 steps in a row had a non-finite loss or gradient (last at step {}); \
                     lower the field's learning rate or check the data for NaN pixels",
                    session.step
                )));
            }
            session.step += 1;
            continue;
        }
        bad_steps = 0;
        let t_reg = timer.elapsed().as_secs_f64();
        let progress = session.step as f32 / total.max(1) as f32;
        let lr_factor = session.config.train.final_lr_factor.powf(progress);
        session.field.step(lr_factor);
        let timing = Stage1Timing {
            render: r.timing,
            composite_backward: t_cb,
            field_backward: t_fb - t_cb,
            regularize: t_reg - t_fb,
            step: timer.elapsed().as_secs_f64() - t_reg,
        };
        session.step += 1;

        last = StepStats {
            mse,
            psnr: crate::metrics::psnr_from_mse(mse),
            samples_per_ray: r.samples.len() as f64 / n_rays as f64,
            opacity: r.colours.iter().map(|c| c.acc as f64).sum::<f64>() / n_rays as f64,
            faces: faces.figures(),
            timing,
        };
        // Once the field has settled, say so while the run can still be stopped.
        if !warned_faces && 2 * session.step >= total {
            if let Some(w) = last.faces.as_ref().and_then(face_pileup_warning) {
                observer.message(Severity::Warning, &format!("stage 1 step {}: {w}", session.step));
                warned_faces = true;
            }
        }
        observer.stage1_step(session, &last)?;
        if let Some(monitor) = plateau.as_mut() {
            // A growing field's loss jumps after each growth: only its final detail counts.
            let full_detail = plain::detail_fraction(session.field.as_ref()) >= 1.0;
            let window = monitor.observe(mse, full_detail);
            if let (Some(w), true) = (window, monitor.converged()) {
                observer.message(
                    Severity::Notice,
                    &format!(
                        "stage 1 converged at step {} of {total}: the training PSNR ({:.2} dB over the last {} steps) \
                     rose by less than {} dB per window twice in a row",
                        session.step,
                        w.psnr,
                        session.config.train.converged_window,
                        session.config.train.converged_gain
                    ),
                );
                session.stop_converged(session.step);
                break;
            }
        }
        let every = session.config.train.checkpoint_every;
        if every > 0 && session.step.is_multiple_of(every) && session.step < total {
            session.rng_position = Some(rng.get_word_pos());
            session.save_checkpoint()?;
        }
    }
    observer.stage_ends(Stage::Photometric);
    session.rng_position = Some(rng.get_word_pos());
    session.bake_occupancy();
    session.save_checkpoint()?;
    Ok(last)
}
