//! Rendering a batch of rays through a field: candidate samples with empty-space skipping, a
//! cheap density pass for early ray termination (and, with a frozen field, weight
//! thresholding), a full pass on the surviving samples, then compositing and its backward.
//!
//! A field that asks for [`Hierarchical`] sampling (NeRF's coarse + fine networks) gets its
//! candidates from a proposal pass instead: stratified proposal samples (occupancy-skipped like
//! any candidates) are composited with the proposal network's density, `fine_samples` more are
//! drawn from those weights by inverse CDF, and the union is the candidate set of the field.

use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::camera::Vec3;
use crate::plugin::field::Hierarchical;
use crate::plugin::{FieldTape, RadianceField};
use crate::render::composite::{self, RayColor, RayGrad, RaySamples};
use crate::render::contraction::Contraction;
use crate::render::occupancy::OccupancyGrid;
use crate::render::rays::RayBatch;
use crate::render::sampler::{self, MarchOptions, Samples};
use crate::scene::SceneExtent;

/// Rays per parallel marching task.
const MARCH_CHUNK: usize = 256;

/// How to render.
#[derive(Debug, Clone, Copy)]
pub struct RenderOptions {
    /// Candidate placement.
    pub march: MarchOptions,
    /// Stop a ray once its transmittance falls below this (early ray termination); 0 disables.
    pub early_stop: f32,
    /// Drop samples whose compositing weight is at most this (only sound when the density is
    /// frozen, e.g. in stage 2); 0 keeps every sample before termination.
    pub min_weight: f32,
}

/// The scene-level context a renderer needs.
#[derive(Debug, Clone, Copy)]
pub struct RenderContext<'a> {
    /// Scene extent (sets the candidate spacing).
    pub extent: &'a SceneExtent,
    /// Unit-cube mapping (shared with the occupancy grid).
    pub contraction: &'a Contraction,
    /// Empty-space skipping, if enabled.
    pub occupancy: Option<&'a OccupancyGrid>,
    /// No samples closer than this to the ray origin.
    pub near: f32,
}

/// Samples that survived skipping, with the field's values at them.
pub struct Rendered {
    /// Surviving samples.
    pub samples: Samples,
    /// Density at each sample.
    pub density: Vec<f32>,
    /// Colour at each sample.
    pub rgb: Vec<[f32; 3]>,
    /// Compositing weight of each sample (filled by [`Rendered::composite`]).
    pub weights: Vec<f32>,
    /// Per-ray results (filled by [`Rendered::composite`]).
    pub colors: Vec<RayColor>,
    /// The field's tape for its backward pass.
    pub tape: FieldTape,
    /// Candidates placed before the density pass (for statistics).
    pub n_candidates: usize,
    /// The proposal pass of a [`Hierarchical`] field, composited (weights and colours filled),
    /// with its own tape; present only when rendering with `record` (training), so that the
    /// proposal network gets its own photometric loss as in NeRF.
    pub coarse: Option<Box<Rendered>>,
    /// The field's segmentation input at each sample, `[n, seg_input_dim]`, when rendered by
    /// [`render_with_seg_input`] within its budget; empty otherwise.
    pub seg_input: Vec<f32>,
}

/// Marches, prunes and evaluates the field. Call [`Rendered::composite`] next.
pub fn render(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    record: bool,
    rng: &mut impl Rng,
) -> Rendered {
    render_impl(field, ctx, rays, options, record, 0, rng)
}

/// [`render`] of a frozen field (no tape) that also keeps the field's segmentation input at
/// the surviving samples ([`Rendered::seg_input`]) when it takes at most `budget` bytes, from
/// the same pass as density and colour where the field can (stage 2 then needs no second
/// pass of, e.g., NeRF's trunk for its head).
pub fn render_with_seg_input(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    budget: usize,
    rng: &mut impl Rng,
) -> Rendered {
    render_impl(field, ctx, rays, options, false, budget, rng)
}

/// Density and colour of `samples`; with `seg_budget` bytes enough for their segmentation
/// input (and no tape wanted), that too.
fn evaluate(
    field: &dyn RadianceField,
    samples: &Samples,
    record: bool,
    seg_budget: usize,
) -> (Vec<f32>, Vec<[f32; 3]>, FieldTape, Vec<f32>) {
    let n = samples.len();
    let mut density = vec![0.0; n];
    let mut rgb = vec![[0.0; 3]; n];
    let seg_len = n * field.seg_input_dim();
    if !record && seg_len > 0 && seg_len.saturating_mul(std::mem::size_of::<f32>()) <= seg_budget {
        let mut seg = vec![0.0; seg_len];
        field.forward_with_seg_input(&samples.positions, &samples.directions, &mut density, &mut rgb, &mut seg);
        return (density, rgb, None, seg);
    }
    let tape = field.forward(&samples.positions, &samples.directions, &mut density, &mut rgb, record);
    (density, rgb, tape, Vec::new())
}

fn render_impl(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    record: bool,
    seg_budget: usize,
    rng: &mut impl Rng,
) -> Rendered {
    let timer = std::time::Instant::now();
    let (candidates, coarse) = match field.hierarchical() {
        Some(h) => propose(field, ctx, rays, options, h, record, rng),
        None => (march_parallel(ctx, rays, options.march, rng), None),
    };
    let t_march = timer.elapsed().as_secs_f64();
    let n_candidates = candidates.len();
    let prune = options.early_stop > 0.0 || options.min_weight > 0.0;
    if !prune {
        // Nothing to decide from density alone: skip the density pass (for network fields it
        // costs nearly as much as the full pass).
        let (density, rgb, tape, seg_input) = evaluate(field, &candidates, record, seg_budget);
        if std::env::var("SOS_PROFILE").is_ok() {
            eprintln!(
                "render: march {:.3} forward {:.3} (samples {})",
                t_march,
                timer.elapsed().as_secs_f64() - t_march,
                n_candidates
            );
        }
        return Rendered {
            samples: candidates,
            density,
            rgb,
            weights: Vec::new(),
            colors: Vec::new(),
            tape,
            n_candidates,
            coarse,
            seg_input,
        };
    }

    // Density-only pass to find where each ray terminates and which weights matter.
    let sigma = density_pass(field, &candidates, options.early_stop);
    // For each candidate: kept or not, and the optical depth of dropped candidates since the
    // previous kept one (so the kept samples' transmittance stays exact).
    let mut keep = vec![false; candidates.len()];
    let mut skipped_before = vec![0.0f32; candidates.len()];
    // The same criterion as the density pass, in optical depth, so the scan never reads a
    // candidate the pass did not evaluate.
    let stop_at = if options.early_stop > 0.0 { -options.early_stop.ln() } else { f32::INFINITY };
    for r in 0..candidates.n_rays() {
        let mut optical = 0.0f32;
        let mut skipped = 0.0f32;
        for i in candidates.range(r) {
            if optical > stop_at {
                break;
            }
            let transmittance = (-optical).exp();
            let tau = sigma[i] * candidates.delta[i];
            let w = -(-tau).exp_m1() * transmittance;
            keep[i] = options.min_weight <= 0.0 || w > options.min_weight;
            if keep[i] {
                skipped_before[i] = skipped;
                skipped = 0.0;
            } else {
                skipped += tau;
            }
            optical += tau;
        }
    }
    let t_density = timer.elapsed().as_secs_f64();
    let (mut samples, kept) = candidates.filter(|i| keep[i]);
    if options.min_weight > 0.0 {
        samples.skipped_tau = kept.iter().map(|&i| skipped_before[i as usize]).collect();
    }
    let t_filter = timer.elapsed().as_secs_f64();

    let (density, rgb, tape, seg_input) = evaluate(field, &samples, record, seg_budget);
    if std::env::var("SOS_PROFILE").is_ok() {
        eprintln!(
            "render: march {:.3} density {:.3} filter {:.3} forward {:.3} (candidates {}, kept {})",
            t_march,
            t_density - t_march,
            t_filter - t_density,
            timer.elapsed().as_secs_f64() - t_filter,
            n_candidates,
            samples.len()
        );
    }
    Rendered { samples, density, rgb, weights: Vec::new(), colors: Vec::new(), tape, n_candidates, coarse, seg_input }
}

/// The proposal pass of a [`Hierarchical`] field: returns the fine candidates (proposal and
/// importance samples merged, each with the interval it stands for) and, when `record`, the
/// composited proposal pass.
fn propose(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    h: Hierarchical,
    record: bool,
    rng: &mut impl Rng,
) -> (Samples, Option<Box<Rendered>>) {
    let proposal = field.coarse().unwrap_or(field);
    // Strata midpoints, then (training) one uniform draw inside each stratum.
    let march = MarchOptions { steps: h.coarse_samples.max(1), stratified: false };
    let mut coarse = march_parallel(ctx, rays, march, rng);
    let starts: Vec<f32> = coarse.t.iter().zip(&coarse.delta).map(|(t, d)| t - 0.5 * d).collect();
    if options.march.stratified {
        for r in 0..coarse.n_rays() {
            let (o, d) = (rays.origins[r], rays.directions[r]);
            for i in coarse.range(r) {
                let t = starts[i] + rng.gen::<f32>() * coarse.delta[i];
                coarse.t[i] = t;
                coarse.positions[i] = crate::camera::axpy(o, t, d);
            }
        }
    }
    let n = coarse.len();
    let mut density = vec![0.0; n];
    let mut rendered = None;
    let weights = if record {
        let mut rgb = vec![[0.0; 3]; n];
        let tape = proposal.forward(&coarse.positions, &coarse.directions, &mut density, &mut rgb, true);
        let mut r = Rendered {
            samples: coarse.clone(),
            density,
            rgb,
            weights: Vec::new(),
            colors: Vec::new(),
            tape,
            n_candidates: n,
            coarse: None,
            seg_input: Vec::new(),
        };
        r.composite();
        let w = r.weights.clone();
        rendered = Some(Box::new(r));
        w
    } else {
        proposal.density(&coarse.positions, &mut density);
        let mut w = vec![0.0; n];
        for r in 0..coarse.n_rays() {
            let range = coarse.range(r);
            composite::weights(&density[range.clone()], &coarse.delta[range.clone()], &[], &mut w[range]);
        }
        w
    };
    // Importance samples per chunk of rays, in parallel, each chunk with its own stream.
    let n_rays = coarse.n_rays();
    let n_chunks = n_rays.div_ceil(MARCH_CHUNK);
    let stratified = options.march.stratified;
    let seeds = chunk_seeds(n_chunks, stratified, rng);
    let parts: Vec<Samples> = (0..n_chunks)
        .into_par_iter()
        .map(|c| {
            let mut local = rand_chacha::ChaCha8Rng::seed_from_u64(seeds[c]);
            let mut out = Samples { ray_start: vec![0], ..Default::default() };
            let (mut ts, mut deltas) = (Vec::new(), Vec::new());
            for r in c * MARCH_CHUNK..((c + 1) * MARCH_CHUNK).min(n_rays) {
                let range = coarse.range(r);
                let ends: Vec<f32> = range.clone().map(|i| starts[i] + coarse.delta[i]).collect();
                let fine = sampler::sample_bins(
                    &starts[range.clone()],
                    &ends,
                    &weights[range.clone()],
                    h.fine_samples,
                    if stratified { Some(&mut local) } else { None },
                );
                sampler::merge_intervals(&starts[range.clone()], &ends, &coarse.t[range], &fine, &mut ts, &mut deltas);
                let (o, d) = (rays.origins[r], rays.directions[r]);
                for (&t, &delta) in ts.iter().zip(&deltas) {
                    out.t.push(t);
                    out.delta.push(delta);
                    out.positions.push(crate::camera::axpy(o, t, d));
                    out.directions.push(d);
                }
                out.ray_start.push(out.t.len() as u32);
            }
            out
        })
        .collect();
    (concat(parts), rendered)
}

/// Densities of the candidates, evaluated in waves: every live ray evaluates its next few
/// candidates, then rays whose transmittance fell below `early_stop` stop, so candidates
/// behind a ray's termination point are never evaluated (for network fields the density pass
/// dominates a frozen-field render). Entries past a ray's termination are left at 0 and must
/// not be read (the caller's scan stops at the same point). With `early_stop = 0` every
/// candidate is evaluated in one batch.
fn density_pass(field: &dyn RadianceField, candidates: &Samples, early_stop: f32) -> Vec<f32> {
    let n = candidates.len();
    let mut sigma = vec![0.0; n];
    if early_stop <= 0.0 {
        field.density(&candidates.positions, &mut sigma);
        return sigma;
    }
    let n_rays = candidates.n_rays();
    let mut cursor: Vec<usize> = (0..n_rays).map(|r| candidates.ray_start[r] as usize).collect();
    let mut optical = vec![0.0f32; n_rays];
    let mut live: Vec<usize> = (0..n_rays).filter(|&r| !candidates.range(r).is_empty()).collect();
    // Optical depth at which the transmittance reaches `early_stop`.
    let stop_at = -early_stop.ln();
    let mut wave = FIRST_WAVE;
    let mut idx = Vec::new();
    let mut positions = Vec::new();
    while !live.is_empty() {
        idx.clear();
        for &r in &live {
            let end = (cursor[r] + wave).min(candidates.ray_start[r + 1] as usize);
            idx.extend(cursor[r] as u32..end as u32);
        }
        positions.clear();
        positions.extend(idx.iter().map(|&i| candidates.positions[i as usize]));
        let mut values = vec![0.0; idx.len()];
        field.density(&positions, &mut values);
        for (&i, v) in idx.iter().zip(values) {
            sigma[i as usize] = v;
        }
        live.retain(|&r| {
            let end = (cursor[r] + wave).min(candidates.ray_start[r + 1] as usize);
            for i in cursor[r]..end {
                optical[r] += sigma[i] * candidates.delta[i];
            }
            cursor[r] = end;
            end < candidates.ray_start[r + 1] as usize && optical[r] <= stop_at
        });
        wave = (wave * 2).min(MAX_WAVE);
    }
    sigma
}

/// Candidates per live ray in the first wave of [`density_pass`], doubled each wave up to
/// [`MAX_WAVE`].
const FIRST_WAVE: usize = 8;
/// Largest wave of [`density_pass`].
const MAX_WAVE: usize = 128;

/// Per-chunk seeds for stratified jitter; deterministic rendering draws nothing from `rng`, so
/// a caller's random stream does not depend on how (or whether) space was skipped.
fn chunk_seeds(n_chunks: usize, stratified: bool, rng: &mut impl Rng) -> Vec<u64> {
    if stratified {
        (0..n_chunks).map(|_| rng.gen()).collect()
    } else {
        vec![0; n_chunks]
    }
}

fn march_parallel(ctx: RenderContext, rays: &RayBatch, options: MarchOptions, rng: &mut impl Rng) -> Samples {
    let n_chunks = rays.len().div_ceil(MARCH_CHUNK);
    let seeds = chunk_seeds(n_chunks, options.stratified, rng);
    let parts: Vec<Samples> = (0..n_chunks)
        .into_par_iter()
        .map(|c| {
            let (start, end) = (c * MARCH_CHUNK, ((c + 1) * MARCH_CHUNK).min(rays.len()));
            let mut local = rand_chacha::ChaCha8Rng::seed_from_u64(seeds[c]);
            sampler::march(ctx.extent, ctx.contraction, ctx.occupancy, ctx.near, &rays.slice(start, end), options, &mut local)
        })
        .collect();
    concat(parts)
}

fn concat(parts: Vec<Samples>) -> Samples {
    let total: usize = parts.iter().map(|p| p.len()).sum();
    let mut out = Samples {
        ray_start: vec![0],
        t: Vec::with_capacity(total),
        delta: Vec::with_capacity(total),
        positions: Vec::with_capacity(total),
        directions: Vec::with_capacity(total),
        skipped_tau: Vec::new(),
    };
    for p in parts {
        let base = out.t.len() as u32;
        out.ray_start.extend(p.ray_start[1..].iter().map(|s| s + base));
        out.t.extend(p.t);
        out.delta.extend(p.delta);
        out.positions.extend(p.positions);
        out.directions.extend(p.directions);
    }
    out
}

impl Rendered {
    /// The samples of ray `r` as the compositing kernel sees them.
    fn ray_samples<'a>(&'a self, r: usize, extra: &'a [f32], d_extra: usize) -> RaySamples<'a> {
        let range = self.samples.range(r);
        RaySamples {
            sigma: &self.density[range.clone()],
            delta: &self.samples.delta[range.clone()],
            t: &self.samples.t[range.clone()],
            rgb: &self.rgb[range.clone()],
            extra: &extra[range.start * d_extra..range.end * d_extra],
            d_extra,
            skipped_tau: if self.samples.skipped_tau.is_empty() {
                &[]
            } else {
                &self.samples.skipped_tau[range]
            },
        }
    }

    /// Composites every ray: fills the per-sample weights and the per-ray colours. Extra
    /// channels are composited afterwards from these weights ([`Rendered::composite_extra`]),
    /// or by the caller.
    pub fn composite(&mut self) {
        let n_rays = self.samples.n_rays();
        let mut weights = vec![0.0; self.samples.len()];
        let mut colors = vec![RayColor::default(); n_rays];
        for (r, color) in colors.iter_mut().enumerate() {
            let s = self.ray_samples(r, &[], 0);
            *color = composite::composite(&s, &mut weights[self.samples.range(r)], &mut []);
        }
        self.weights = weights;
        self.colors = colors;
    }

    /// `Σ_k w_k e_k` per ray over the samples with `w_k > extra.min_weight`, after
    /// [`Rendered::composite`] has computed the weights.
    fn composite_extra(&self, extra: &ExtraChannels) -> Vec<f32> {
        let d = extra.dim;
        let selected = |k: usize| self.weights[k] > extra.min_weight;
        let positions: Vec<Vec3> =
            (0..self.samples.len()).filter(|&k| selected(k)).map(|k| self.samples.positions[k]).collect();
        let values = (extra.eval)(&positions);
        assert_eq!(values.len(), positions.len() * d, "extra channels: eval returned the wrong size");
        let mut out = vec![0.0; self.samples.n_rays() * d];
        let mut next = values.chunks_exact(d);
        for (r, out) in out.chunks_exact_mut(d).enumerate() {
            for k in self.samples.range(r).filter(|&k| selected(k)) {
                let v = next.next().expect("one value row per selected sample");
                out.iter_mut().zip(v).for_each(|(o, e)| *o += self.weights[k] * e);
            }
        }
        out
    }

    /// Backward of [`Rendered::composite`]: given per-ray output gradients, returns
    /// `(∂L/∂σ, ∂L/∂rgb, ∂L/∂extra)` per sample.
    pub fn composite_backward(
        &self,
        extra: &[f32],
        d_extra: usize,
        grads: &[RayGrad],
    ) -> (Vec<f32>, Vec<[f32; 3]>, Vec<f32>) {
        let n = self.samples.len();
        let mut g_sigma = vec![0.0; n];
        let mut g_rgb = vec![[0.0; 3]; n];
        let mut g_extra = vec![0.0; n * d_extra];
        for (r, g) in grads.iter().enumerate() {
            let range = self.samples.range(r);
            let s = self.ray_samples(r, extra, d_extra);
            composite::composite_backward(
                &s,
                &self.weights[range.clone()],
                self.colors[r].acc,
                g,
                &mut g_sigma[range.clone()],
                &mut g_rgb[range.clone()],
                &mut g_extra[range.start * d_extra..range.end * d_extra],
            );
        }
        (g_sigma, g_rgb, g_extra)
    }
}

/// Per-sample channels composited alongside the colour at inference (the segmentation logits).
pub struct ExtraChannels<'a> {
    /// Channels per sample.
    pub dim: usize,
    /// Only samples whose compositing weight exceeds this are evaluated and composited; stage 2
    /// trains the head on exactly those, and it skips the many near-empty samples of a ray.
    pub min_weight: f32,
    /// `[n, dim]` values at the given sample positions.
    pub eval: &'a dyn Fn(&[Vec3]) -> Vec<f32>,
}

/// Renders many rays in chunks without gradients (evaluation and `sos render`); returns the
/// per-ray colours and, with `extra`, its per-ray composited channels (`[n_rays, dim]`).
pub fn render_inference(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    chunk: usize,
    extra: Option<&ExtraChannels>,
) -> (Vec<RayColor>, Vec<f32>) {
    let mut colors = Vec::with_capacity(rays.len());
    let mut extras = Vec::with_capacity(rays.len() * extra.map_or(0, |e| e.dim));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut start = 0;
    while start < rays.len() {
        let end = (start + chunk).min(rays.len());
        let mut r = render(field, ctx, &rays.slice(start, end), options, false, &mut rng);
        r.composite();
        if let Some(extra) = extra {
            extras.extend(r.composite_extra(extra));
        }
        colors.extend(r.colors);
        start = end;
    }
    (colors, extras)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;
    use crate::camera::{Camera, Vec3};
    use crate::render::sampler::MarchOptions;

    /// A dense ball of radius 0.5 at the origin, coloured by position; counts density calls.
    struct Ball {
        evaluated: AtomicUsize,
        hierarchical: Option<Hierarchical>,
    }

    impl Ball {
        fn sigma(p: Vec3) -> f32 {
            let r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
            if r2 < 0.25 {
                40.0
            } else {
                0.0
            }
        }
    }

    impl RadianceField for Ball {
        fn density(&self, positions: &[Vec3], density: &mut [f32]) {
            self.evaluated.fetch_add(positions.len(), Ordering::Relaxed);
            for (p, d) in positions.iter().zip(density) {
                *d = Ball::sigma(*p);
            }
        }
        fn forward(&self, p: &[Vec3], _: &[Vec3], d: &mut [f32], c: &mut [[f32; 3]], _: bool) -> FieldTape {
            for i in 0..p.len() {
                d[i] = Ball::sigma(p[i]);
                c[i] = [0.5 + 0.5 * p[i][0], 0.5 + 0.5 * p[i][1], 0.5];
            }
            None
        }
        fn backward(&mut self, _: &[Vec3], _: &[Vec3], _: FieldTape, _: &[f32], _: &[[f32; 3]]) {}
        fn step(&mut self, _: f32) {}
        fn hierarchical(&self) -> Option<Hierarchical> {
            self.hierarchical
        }
        fn seg_input_dim(&self) -> usize {
            2
        }
        fn seg_input(&self, p: &[Vec3], out: &mut [f32]) {
            for (p, row) in p.iter().zip(out.chunks_exact_mut(2)) {
                row.copy_from_slice(&[p[0], p[1] * p[2]]);
            }
        }
        fn save_state(&self) -> Vec<u8> {
            Vec::new()
        }
        fn load_state(&mut self, _: &[u8]) -> Result<(), String> {
            Ok(())
        }
        fn num_parameters(&self) -> usize {
            0
        }
    }

    fn setup() -> (SceneExtent, Contraction, RayBatch) {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let cam = Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 16, 16, 40.0);
        (extent, Contraction::new(&extent), RayBatch::full_image(&cam))
    }

    fn colors(field: &Ball, options: RenderOptions) -> (Vec<RayColor>, usize) {
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        field.evaluated.store(0, Ordering::Relaxed);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let mut r = render(field, ctx, &rays, options, false, &mut rng);
        r.composite();
        (r.colors, field.evaluated.load(Ordering::Relaxed))
    }

    /// Extra channels composite `Σ w_k e_k` over the samples above their weight threshold only,
    /// and leave the colours as they are.
    #[test]
    fn extra_channels_composite_the_selected_samples() {
        let field = Ball { evaluated: AtomicUsize::new(0), hierarchical: None };
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        let options = RenderOptions { march: MarchOptions { steps: 128, stratified: false }, early_stop: 0.0, min_weight: 0.0 };
        // Channel 0 is 1 everywhere (so it composites to the selected weight), channel 1 is z.
        let eval = |p: &[Vec3]| p.iter().flat_map(|p| [1.0, p[2]]).collect::<Vec<f32>>();
        let all = ExtraChannels { dim: 2, min_weight: 0.0, eval: &eval };
        let (colors, extra) = render_inference(&field, ctx, &rays, options, 100, Some(&all));
        let (plain, none) = render_inference(&field, ctx, &rays, options, 100, None);
        assert!(none.is_empty());
        for ((c, p), e) in colors.iter().zip(&plain).zip(extra.chunks_exact(2)) {
            assert_eq!(c.rgb, p.rgb);
            assert!((e[0] - c.acc).abs() < 1e-5, "{} vs acc {}", e[0], c.acc);
        }
        // A threshold drops the low-weight samples: less weight, never more.
        let strict = ExtraChannels { dim: 2, min_weight: 0.05, eval: &eval };
        let (_, thresholded) = render_inference(&field, ctx, &rays, options, 100, Some(&strict));
        let (mut dropped, mut hits) = (0.0f32, 0);
        for ((c, a), b) in colors.iter().zip(extra.chunks_exact(2)).zip(thresholded.chunks_exact(2)) {
            assert!(b[0] <= a[0] + 1e-6);
            if c.acc > 0.5 {
                hits += 1;
                dropped += a[0] - b[0];
            }
        }
        assert!(hits > 20 && dropped > 0.0, "{hits} hits, {dropped} weight dropped");
    }

    /// A frozen render keeps the segmentation input of exactly its surviving samples, and
    /// only within its budget; the samples and their values are those of a plain render.
    #[test]
    fn frozen_render_keeps_the_segmentation_input_within_its_budget() {
        let field = Ball { evaluated: AtomicUsize::new(0), hierarchical: None };
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        let march = MarchOptions { steps: 64, stratified: false };
        for options in [
            RenderOptions { march, early_stop: 1e-4, min_weight: 1e-3 },
            RenderOptions { march, early_stop: 0.0, min_weight: 0.0 },
        ] {
            let rng = || rand_chacha::ChaCha8Rng::seed_from_u64(0);
            let plain = render(&field, ctx, &rays, options, false, &mut rng());
            let kept = render_with_seg_input(&field, ctx, &rays, options, usize::MAX, &mut rng());
            assert!(plain.seg_input.is_empty());
            assert_eq!((&kept.samples.t, &kept.density, &kept.rgb), (&plain.samples.t, &plain.density, &plain.rgb));
            let mut want = vec![0.0; kept.samples.len() * 2];
            field.seg_input(&kept.samples.positions, &mut want);
            assert!(!want.is_empty());
            assert_eq!(kept.seg_input, want);
            let over = render_with_seg_input(&field, ctx, &rays, options, want.len() * 4 - 1, &mut rng());
            assert!(over.seg_input.is_empty(), "over its budget, nothing is kept");
        }
    }

    #[test]
    fn early_termination_skips_density_work_and_keeps_colours() {
        let field = Ball { evaluated: AtomicUsize::new(0), hierarchical: None };
        let march = MarchOptions { steps: 256, stratified: false };
        let (full, _) = colors(&field, RenderOptions { march, early_stop: 0.0, min_weight: 0.0 });
        let (pruned, evaluated) = colors(&field, RenderOptions { march, early_stop: 1e-4, min_weight: 1e-4 });
        let hits = full.iter().filter(|c| c.acc > 0.5).count();
        assert!(hits > 20, "the ball covers part of the image ({hits} rays)");
        for (a, b) in full.iter().zip(&pruned) {
            for k in 0..3 {
                assert!((a.rgb[k] - b.rgb[k]).abs() < 2e-3, "{a:?} vs {b:?}");
            }
            assert!((a.acc - b.acc).abs() < 2e-3);
        }
        // Rays through the ball stop inside it, skipping at least the back half of the box.
        let (_, all) = colors(&field, RenderOptions { march, early_stop: 0.0, min_weight: 1e-9 });
        assert!(evaluated + 100 * hits < all, "evaluated {evaluated} of {all} densities ({hits} rays hit)");
    }

    #[test]
    fn hierarchical_sampling_concentrates_samples_and_matches_a_dense_render() {
        let dense = Ball { evaluated: AtomicUsize::new(0), hierarchical: None };
        let (want, _) = colors(&dense, RenderOptions { march: MarchOptions { steps: 2048, stratified: false }, early_stop: 0.0, min_weight: 0.0 });
        let h = Hierarchical { coarse_samples: 32, fine_samples: 64 };
        let field = Ball { evaluated: AtomicUsize::new(0), hierarchical: Some(h) };
        let (got, _) = colors(&field, RenderOptions { march: MarchOptions { steps: 8, stratified: false }, early_stop: 0.0, min_weight: 0.0 });
        let mut worst = 0.0f32;
        for (a, b) in want.iter().zip(&got) {
            worst = worst.max((a.acc - b.acc).abs());
            for k in 0..3 {
                worst = worst.max((a.rgb[k] - b.rgb[k]).abs());
            }
        }
        assert!(worst < 0.03, "hierarchical render differs by {worst}");
        // With record, the proposal pass comes back composited, samples inside the box.
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let options = RenderOptions { march: MarchOptions { steps: 8, stratified: true }, early_stop: 0.0, min_weight: 0.0 };
        let r = render(&field, ctx, &rays, options, true, &mut rng);
        let coarse = r.coarse.expect("proposal pass with record");
        assert_eq!(coarse.colors.len(), rays.len());
        let marched = (0..rays.len()).filter(|&i| !coarse.samples.range(i).is_empty()).count();
        assert_eq!(r.samples.len(), coarse.samples.len() + marched * 64);
        for ray in 0..rays.len() {
            let range = r.samples.range(ray);
            assert!(r.samples.t[range.clone()].windows(2).all(|w| w[0] <= w[1]));
            let span: f32 = r.samples.delta[range].iter().sum();
            let coarse_span: f32 = coarse.samples.delta[coarse.samples.range(ray)].iter().sum();
            assert!((span - coarse_span).abs() < 1e-3 * (1.0 + coarse_span), "intervals partition the strata");
        }
    }
}
