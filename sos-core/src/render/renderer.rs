//! Rendering a batch of rays through a field: candidate samples with empty-space skipping, a
//! cheap density pass for early ray termination (and, with a frozen field, weight
//! thresholding; [`crate::render::density_pass`]), a full pass on the surviving samples, then
//! compositing and its backward. A frozen render of a field with a per-sample state (NeRF's
//! trunk) takes the surviving samples' state from the density pass, so its colour pass runs
//! only what lies after the density (NeRF's view branch).
//!
//! A field that asks for [`Hierarchical`] sampling (NeRF's coarse + fine networks) gets its
//! candidates from a proposal pass instead: stratified proposal samples (occupancy-skipped like
//! any candidates) are composited with the proposal network's density, `fine_samples` more are
//! drawn from those weights by inverse CDF, and the union is the candidate set of the field.

use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::camera::Vec3;
use crate::plugin::field::{plain, Hierarchical};
use crate::plugin::{FieldTape, RadianceField};
use crate::render::composite::{self, RayColour, RayGrad, RaySamples};
use crate::render::contraction::Contraction;
use crate::render::density_pass::{density_pass, samples_before_termination, DensityPass, KeptState};
use crate::render::memory_budget::MemoryBudget;
use crate::render::occupancy::OccupancyGrid;
use crate::render::rays::RayBatch;
use crate::render::sampler::{self, keep_ray_prefixes, MarchOptions, Samples};
use crate::scene::SceneExtent;

/// Rays per parallel marching task.
const MARCH_CHUNK: usize = 256;
/// Rays per block of an inference render (see [`render_inference`]).
const INFERENCE_BLOCK: usize = 1024;

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
    /// Hierarchical fields: place samples with the proposal (coarse) network; false: the
    /// field's own network alone on the marched candidates.
    pub proposal: bool,
    /// What a frozen render may keep between its passes (the density pass's state, the
    /// segmentation input); over it, work is recomputed and the result is the same.
    pub memory: MemoryBudget,
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
    pub colours: Vec<RayColour>,
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
    /// Where the render's time went.
    pub timing: RenderTiming,
}

/// Seconds spent in each phase of one render and the sample counts behind them, for a caller's
/// profile (the renderer itself prints nothing).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderTiming {
    /// Placing candidate samples along the rays (and the proposal pass of a hierarchical field).
    pub march: f64,
    /// The density-only pass that finds where rays terminate (0 when nothing is pruned).
    pub density: f64,
    /// Dropping the samples that pass decided to skip.
    pub filter: f64,
    /// The field's full pass over the kept samples.
    pub forward: f64,
    /// Candidates placed.
    pub candidates: usize,
    /// Candidates whose density was evaluated by the density pass.
    pub evaluated: usize,
    /// Samples kept for the full pass.
    pub kept: usize,
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
    render_impl(field, ctx, rays, options, record, 0, &mut FrozenBuffers::default(), rng)
}

/// [`render`] of a frozen field (no tape) that also keeps the field's segmentation input at
/// the surviving samples ([`Rendered::seg_input`]) when it takes at most `budget` bytes, from
/// the same pass as density and colour where the field can (stage 2 then needs no second
/// pass of, e.g., NeRF's trunk for its head). Its large buffers come from `buffers`; hand
/// the segmentation input back with [`FrozenBuffers::recycle`] for the next call.
pub fn render_with_seg_input(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    budget: usize,
    buffers: &mut FrozenBuffers,
    rng: &mut impl Rng,
) -> Rendered {
    render_impl(field, ctx, rays, options, false, budget, buffers, rng)
}

/// The large buffers of a frozen render (the field's state at the kept samples, the
/// segmentation input: gigabytes in a stage-2 step), kept from call to call. Fresh buffers
/// of that size come from the kernel page by page, zeroed, on every call, which costs
/// seconds per stage-2 step on the 2-core machine; reused ones are faulted in once.
#[derive(Default)]
pub struct FrozenBuffers {
    state: Vec<f32>,
    seg_input: Vec<f32>,
}

impl FrozenBuffers {
    /// Takes back the segmentation input of `rendered` (left empty) for the next render.
    pub fn recycle(&mut self, rendered: &mut Rendered) {
        self.seg_input = std::mem::take(&mut rendered.seg_input);
    }

    /// The segmentation-input buffer, `len` floats long (contents unspecified until written).
    /// A buffer too small is replaced (growing would copy its old contents) by one with room
    /// for `most` floats, the most later calls may ask for, reserved but not touched.
    fn take_seg_input(&mut self, len: usize, most: usize) -> Vec<f32> {
        let mut seg = std::mem::take(&mut self.seg_input);
        seg.clear();
        if seg.capacity() < len {
            seg = Vec::with_capacity(len.max(most));
        }
        seg.resize(len, 0.0);
        seg
    }
}

/// How much segmentation input a frozen render keeps: at most `budget` bytes, and (a hint
/// for its buffer) at most `most` floats in any call.
#[derive(Clone, Copy)]
struct SegLimits {
    budget: usize,
    most: usize,
}

impl SegLimits {
    /// Within `budget` bytes, for a render of `n_candidates` candidates (any of which may be
    /// kept), with room for later renders of up to twice as many.
    fn new(field: &dyn RadianceField, n_candidates: usize, budget: usize) -> Self {
        let most = (2 * n_candidates * field.seg_input_dim()).min(budget / std::mem::size_of::<f32>());
        SegLimits { budget, most }
    }

    /// The buffer for `n` samples' input, or an empty one when over budget.
    fn buffer(self, field: &dyn RadianceField, n: usize, buffers: &mut FrozenBuffers) -> Vec<f32> {
        let len = n * field.seg_input_dim();
        if len == 0 || len.saturating_mul(std::mem::size_of::<f32>()) > self.budget {
            return Vec::new();
        }
        buffers.take_seg_input(len, self.most)
    }
}

/// Density and colour of `samples`; with no tape wanted and the budget enough for their
/// segmentation input, that too.
fn evaluate(
    field: &dyn RadianceField,
    samples: &Samples,
    record: bool,
    seg: SegLimits,
    buffers: &mut FrozenBuffers,
) -> (Vec<f32>, Vec<[f32; 3]>, FieldTape, Vec<f32>) {
    let n = samples.len();
    let mut density = vec![0.0; n];
    let mut rgb = vec![[0.0; 3]; n];
    if !record {
        let mut seg = seg.buffer(field, n, buffers);
        if !seg.is_empty() {
            plain::forward_with_seg_input(
                field,
                &samples.positions,
                &samples.directions,
                &mut density,
                &mut rgb,
                &mut seg,
            );
            return (density, rgb, None, seg);
        }
    }
    let tape = field.forward(&samples.positions, &samples.directions, &mut density, &mut rgb, record);
    (density, rgb, tape, Vec::new())
}

/// What [`evaluate`] returns: density, colour, tape and segmentation input per sample.
type Evaluated = (Vec<f32>, Vec<[f32; 3]>, FieldTape, Vec<f32>);

/// The samples before each ray terminates, cut from a full pass over every candidate by the
/// density pass's rule ([`samples_before_termination`]), each ray's prefix moved down in place.
fn terminated(mut samples: Samples, out: Evaluated, early_stop: f32) -> (Samples, Evaluated) {
    let (mut density, mut rgb, tape, mut seg) = out;
    debug_assert!(tape.is_none(), "only frozen renders skip the density pass while terminating rays");
    let kept: Vec<usize> = (0..samples.n_rays())
        .map(|r| {
            let range = samples.range(r);
            samples_before_termination(&density[range.clone()], &samples.delta[range], early_stop)
        })
        .collect();
    let dim = if density.is_empty() { 0 } else { seg.len() / density.len() };
    let starts = &samples.ray_start;
    keep_ray_prefixes(&mut density, starts, &kept, 1);
    keep_ray_prefixes(&mut rgb, starts, &kept, 1);
    keep_ray_prefixes(&mut seg, starts, &kept, dim);
    samples.keep_ray_prefixes(&kept);
    (samples, (density, rgb, tape, seg))
}

/// [`evaluate`] of the kept samples of a frozen render from its density pass: their density
/// as the pass found it, and their colour (and segmentation input) from the field's state.
/// `seg` is the segmentation input's buffer (empty: none wanted).
fn finish_from_state(
    field: &dyn RadianceField,
    samples: &Samples,
    kept: &[u32],
    sigma: &[f32],
    state: &KeptState,
    mut seg: Vec<f32>,
) -> (Vec<f32>, Vec<[f32; 3]>, FieldTape, Vec<f32>) {
    let density = kept.iter().map(|&i| sigma[i as usize]).collect();
    let mut rgb = vec![[0.0; 3]; samples.len()];
    let seg_out = (!seg.is_empty()).then_some(&mut seg[..]);
    plain::colour_from_state(
        field,
        &samples.positions,
        &samples.directions,
        &state.values,
        &state.rows(kept),
        &mut rgb,
        seg_out,
    );
    (density, rgb, None, seg)
}

fn render_impl(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    record: bool,
    seg_budget: usize,
    buffers: &mut FrozenBuffers,
    rng: &mut impl Rng,
) -> Rendered {
    let timer = std::time::Instant::now();
    // A frozen render that would only terminate rays early skips the density pass where the
    // field says that pass costs more than it saves.
    let terminate = options.early_stop > 0.0 && (record || plain::early_termination_pass(field));
    let prune = terminate || options.min_weight > 0.0;
    let keeps_state = !record && plain::density_state_dim(field) > 0 && options.memory.density_state() > 0;
    let hierarchical = plain::hierarchical(field).filter(|_| options.proposal);
    if prune && !keeps_state && hierarchical.is_none() {
        let (samples, pruned) = prune_in_blocks(field, ctx, rays, options, rng);
        let seg_limits = SegLimits::new(field, pruned.candidates, seg_budget);
        let t_filter = timer.elapsed().as_secs_f64();
        let (density, rgb, tape, seg_input) = evaluate(field, &samples, record, seg_limits, buffers);
        let timing = RenderTiming { forward: timer.elapsed().as_secs_f64() - t_filter, kept: samples.len(), ..pruned };
        return Rendered::uncomposited(samples, (density, rgb, tape, seg_input), None, timing);
    }
    let (candidates, coarse) = match hierarchical {
        Some(h) => propose(field, ctx, rays, options, h, record, rng),
        None => (march_parallel(ctx, rays, options.march, rng), None),
    };
    let t_march = timer.elapsed().as_secs_f64();
    let n_candidates = candidates.len();
    let seg_limits = SegLimits::new(field, n_candidates, seg_budget);
    let (samples, (density, rgb, tape, seg_input), timing) = if !prune {
        // Nothing to decide from density alone, or nothing worth a pass of its own: skip the
        // density pass (for network fields it costs nearly as much as the full pass). Rays the
        // field would have terminated early are cut after the full pass, by the same rule.
        let out = evaluate(field, &candidates, record, seg_limits, buffers);
        let (samples, out) =
            if options.early_stop > 0.0 { terminated(candidates, out, options.early_stop) } else { (candidates, out) };
        let timing = RenderTiming {
            march: t_march,
            forward: timer.elapsed().as_secs_f64() - t_march,
            candidates: n_candidates,
            evaluated: n_candidates,
            kept: samples.len(),
            ..RenderTiming::default()
        };
        (samples, out, timing)
    } else {
        // Density-only pass to find where each ray terminates and which weights matter; a
        // frozen render also takes the field's state at the kept samples from it.
        let state_budget = if record { 0 } else { options.memory.density_state() };
        let state_buffer = std::mem::take(&mut buffers.state);
        let mut pass =
            density_pass(field, &candidates, options.early_stop, options.min_weight, state_budget, state_buffer);
        let t_density = timer.elapsed().as_secs_f64();
        let (samples, kept) = kept_samples(&candidates, &pass, options.min_weight);
        let t_filter = timer.elapsed().as_secs_f64();
        let out = match pass.state.take() {
            Some(state) => {
                let seg = seg_limits.buffer(field, samples.len(), buffers);
                let out = finish_from_state(field, &samples, &kept, &pass.sigma, &state, seg);
                buffers.state = state.values;
                out
            }
            None => evaluate(field, &samples, record, seg_limits, buffers),
        };
        let timing = RenderTiming {
            march: t_march,
            density: t_density - t_march,
            filter: t_filter - t_density,
            forward: timer.elapsed().as_secs_f64() - t_filter,
            candidates: n_candidates,
            evaluated: pass.evaluated,
            kept: samples.len(),
        };
        (samples, out, timing)
    };
    Rendered::uncomposited(samples, (density, rgb, tape, seg_input), coarse, timing)
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
    let proposal = field.hierarchical().and_then(|h| h.proposal()).unwrap_or(field);
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
            colours: Vec::new(),
            tape,
            n_candidates: n,
            coarse: None,
            seg_input: Vec::new(),
            timing: RenderTiming::default(),
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

/// Per-chunk seeds for stratified jitter; deterministic rendering draws nothing from `rng`, so
/// a caller's random stream does not depend on how (or whether) space was skipped.
fn chunk_seeds(n_chunks: usize, stratified: bool, rng: &mut impl Rng) -> Vec<u64> {
    if stratified {
        (0..n_chunks).map(|_| rng.gen()).collect()
    } else {
        vec![0; n_chunks]
    }
}

/// The samples a pruned render evaluates, found block by block: each block of
/// [`MARCH_CHUNK`] rays is marched (with the jitter stream [`march_parallel`] would give it),
/// run through the density pass and filtered on its own, blocks in parallel, so that these
/// steps' serial parts overlap. Each ray's decisions depend on that ray alone, so the samples
/// are those of the whole batch's passes. Returns them with the counts and the wall time of
/// the three steps (shared out by the time the blocks spent in each).
fn prune_in_blocks(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    rng: &mut impl Rng,
) -> (Samples, RenderTiming) {
    let timer = std::time::Instant::now();
    let n_chunks = rays.len().div_ceil(MARCH_CHUNK);
    let seeds = chunk_seeds(n_chunks, options.march.stratified, rng);
    let parts: Vec<(Samples, usize, usize, [f64; 3])> = (0..n_chunks)
        .into_par_iter()
        .map(|c| {
            let clock = std::time::Instant::now();
            let candidates = march_chunk(ctx, rays, c, options.march, seeds[c]);
            let t_march = clock.elapsed().as_secs_f64();
            let pass = density_pass(field, &candidates, options.early_stop, options.min_weight, 0, Vec::new());
            let t_density = clock.elapsed().as_secs_f64();
            let (samples, _) = kept_samples(&candidates, &pass, options.min_weight);
            let times = [t_march, t_density - t_march, clock.elapsed().as_secs_f64() - t_density];
            (samples, candidates.len(), pass.evaluated, times)
        })
        .collect();
    let wall = timer.elapsed().as_secs_f64();
    let mut busy = [0.0f64; 3];
    let (mut candidates, mut evaluated) = (0, 0);
    for (_, c, e, times) in &parts {
        candidates += c;
        evaluated += e;
        for (b, t) in busy.iter_mut().zip(times) {
            *b += t;
        }
    }
    let share = wall / busy.iter().sum::<f64>().max(f64::MIN_POSITIVE);
    let samples = concat(parts.into_iter().map(|p| p.0).collect());
    let timing = RenderTiming {
        march: busy[0] * share,
        density: busy[1] * share,
        filter: busy[2] * share,
        forward: 0.0,
        candidates,
        evaluated,
        kept: samples.len(),
    };
    (samples, timing)
}

fn march_parallel(ctx: RenderContext, rays: &RayBatch, options: MarchOptions, rng: &mut impl Rng) -> Samples {
    let n_chunks = rays.len().div_ceil(MARCH_CHUNK);
    let seeds = chunk_seeds(n_chunks, options.stratified, rng);
    let parts: Vec<Samples> =
        (0..n_chunks).into_par_iter().map(|c| march_chunk(ctx, rays, c, options, seeds[c])).collect();
    concat(parts)
}

/// Candidates of the `c`-th [`MARCH_CHUNK`] rays, jittered (when stratified) by their own
/// stream from `seed`.
fn march_chunk(ctx: RenderContext, rays: &RayBatch, c: usize, options: MarchOptions, seed: u64) -> Samples {
    let (start, end) = (c * MARCH_CHUNK, ((c + 1) * MARCH_CHUNK).min(rays.len()));
    let mut local = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    sampler::march(ctx.extent, ctx.contraction, ctx.occupancy, ctx.near, &rays.slice(start, end), options, &mut local)
}

/// The candidates a density pass kept, and their indices among the candidates; with a weight
/// threshold, each with the optical depth dropped before it.
fn kept_samples(candidates: &Samples, pass: &DensityPass, min_weight: f32) -> (Samples, Vec<u32>) {
    let (mut samples, kept) = candidates.filter(|i| pass.keep[i]);
    if min_weight > 0.0 {
        samples.skipped_tau = kept.iter().map(|&i| pass.skipped_before[i as usize]).collect();
    }
    (samples, kept)
}

/// The samples of consecutive ray blocks as one batch; `skipped_tau` is joined when the blocks
/// have it.
fn concat(parts: Vec<Samples>) -> Samples {
    let total: usize = parts.iter().map(|p| p.len()).sum();
    let mut out = Samples::with_capacity(parts.iter().map(|p| p.n_rays()).sum(), total);
    if parts.iter().any(|p| !p.skipped_tau.is_empty()) {
        out.skipped_tau.reserve(total);
    }
    for p in parts {
        let base = out.t.len() as u32;
        out.ray_start.extend(p.ray_start[1..].iter().map(|s| s + base));
        out.t.extend(p.t);
        out.delta.extend(p.delta);
        out.positions.extend(p.positions);
        out.directions.extend(p.directions);
        out.skipped_tau.extend(p.skipped_tau);
        out.s.extend(p.s);
    }
    out
}

impl Rendered {
    /// The field's values at `samples` (density, colour, tape, segmentation input), not yet
    /// composited.
    fn uncomposited(
        samples: Samples,
        (density, rgb, tape, seg_input): (Vec<f32>, Vec<[f32; 3]>, FieldTape, Vec<f32>),
        coarse: Option<Box<Rendered>>,
        timing: RenderTiming,
    ) -> Rendered {
        Rendered {
            samples,
            density,
            rgb,
            weights: Vec::new(),
            colours: Vec::new(),
            tape,
            n_candidates: timing.candidates,
            coarse,
            seg_input,
            timing,
        }
    }

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
            skipped_tau: if self.samples.skipped_tau.is_empty() { &[] } else { &self.samples.skipped_tau[range] },
        }
    }

    /// Composites every ray: fills the per-sample weights and the per-ray colours. Extra
    /// channels are composited afterwards from these weights (`Rendered::composite_extra`),
    /// or by the caller.
    pub fn composite(&mut self) {
        let n_rays = self.samples.n_rays();
        let mut weights = vec![0.0; self.samples.len()];
        let mut colours = vec![RayColour::default(); n_rays];
        for (r, color) in colours.iter_mut().enumerate() {
            let s = self.ray_samples(r, &[], 0);
            *color = composite::composite(&s, &mut weights[self.samples.range(r)], &mut []);
        }
        self.weights = weights;
        self.colours = colours;
    }

    /// `Σ_k w_k e_k` per ray over the samples with `w_k > extra.min_weight`, after
    /// [`Rendered::composite`] has computed the weights.
    fn composite_extra(&self, extra: &ExtraChannels) -> Vec<f32> {
        let selected = |k: usize| self.weights[k] > extra.min_weight;
        let positions: Vec<Vec3> =
            (0..self.samples.len()).filter(|&k| selected(k)).map(|k| self.samples.positions[k]).collect();
        let values = (extra.eval)(&positions);
        assert_eq!(values.len(), positions.len() * extra.dim, "extra channels: eval returned the wrong size");
        self.composite_values(&values, extra.dim, selected)
    }

    /// `Σ_k w_k v_k` per ray, `[n_rays, d]`: per-sample values (the segmentation logits)
    /// composited with the weights of [`Rendered::composite`], over the samples `selected`
    /// keeps; `values` holds one row per selected sample, in sample order. Stage 2 and mask
    /// inference composite their logits here, so a head sees the same sums in both.
    pub fn composite_values(&self, values: &[f32], d: usize, selected: impl Fn(usize) -> bool) -> Vec<f32> {
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

    /// Backward of [`Rendered::composite_values`] over every sample (the weights held
    /// constant): `∂L/∂v_k = w_k ∂L/∂out(ray of k)`, `[n_samples, d]`.
    pub fn composite_values_backward(&self, grad_rays: &[f32], d: usize) -> Vec<f32> {
        let mut grad = vec![0.0; self.samples.len() * d];
        for r in 0..self.samples.n_rays() {
            let g = &grad_rays[r * d..(r + 1) * d];
            for k in self.samples.range(r) {
                grad[k * d..(k + 1) * d].iter_mut().zip(g).for_each(|(o, &g)| *o = self.weights[k] * g);
            }
        }
        grad
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
                self.colours[r].acc,
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
    pub eval: &'a (dyn Fn(&[Vec3]) -> Vec<f32> + Sync),
}

/// Renders many rays in chunks without gradients (evaluation and `sos render`); returns the
/// per-ray colours and, with `extra`, its per-ray composited channels (`[n_rays, dim]`).
///
/// Each chunk of at most `chunk` rays (the memory bound) is cut into blocks of
/// 1024 rays that run the whole pipeline (march, density pass, colour pass,
/// compositing) on their own, blocks in parallel: the pipeline's serial steps (joining the
/// marched parts, filtering, the density pass's bookkeeping) then overlap, and a block's samples
/// stay in cache between its passes. Rays are independent and nothing is drawn at random, so
/// the result does not depend on the blocks.
pub fn render_inference(
    field: &dyn RadianceField,
    ctx: RenderContext,
    rays: &RayBatch,
    options: RenderOptions,
    chunk: usize,
    extra: Option<&ExtraChannels>,
) -> (Vec<RayColour>, Vec<f32>) {
    let mut colours = Vec::with_capacity(rays.len());
    let mut extras = Vec::with_capacity(rays.len() * extra.map_or(0, |e| e.dim));
    let chunk = chunk.max(1);
    let mut start = 0;
    while start < rays.len() {
        let end = (start + chunk).min(rays.len());
        let blocks: Vec<usize> = (start..end).step_by(INFERENCE_BLOCK).collect();
        let parts: Vec<(Vec<RayColour>, Vec<f32>)> = blocks
            .into_par_iter()
            .map(|first| {
                let last = (first + INFERENCE_BLOCK).min(end);
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
                let mut r = render(field, ctx, &rays.slice(first, last), options, false, &mut rng);
                r.composite();
                let channels = extra.map(|e| r.composite_extra(e)).unwrap_or_default();
                (r.colours, channels)
            })
            .collect();
        for (c, e) in parts {
            colours.extend(c);
            extras.extend(e);
        }
        start = end;
    }
    (colours, extras)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;
    use crate::camera::{Camera, Vec3};
    use crate::render::sampler::MarchOptions;

    /// Options with proposal sampling and no memory limit.
    fn unlimited(march: MarchOptions, early_stop: f32, min_weight: f32) -> RenderOptions {
        RenderOptions { proposal: true, march, early_stop, min_weight, memory: MemoryBudget::unlimited() }
    }

    /// A dense ball of radius 0.5 at the origin, coloured by position; counts density calls.
    /// `with_state`: its density pass keeps the position as state, and the colour pass reads
    /// position from there.
    struct Ball {
        evaluated: AtomicUsize,
        hierarchical: Option<Hierarchical>,
        with_state: bool,
        /// Samples whose colour came from the state.
        from_state: AtomicUsize,
        /// What [`FrozenPass::early_termination_pass`] answers.
        termination_pass: bool,
    }

    impl Ball {
        fn new(hierarchical: Option<Hierarchical>, with_state: bool) -> Self {
            Ball {
                evaluated: AtomicUsize::new(0),
                hierarchical,
                with_state,
                from_state: AtomicUsize::new(0),
                termination_pass: true,
            }
        }

        fn colour(p: Vec3) -> [f32; 3] {
            [0.5 + 0.5 * p[0], 0.5 + 0.5 * p[1], 0.5]
        }

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
                c[i] = Ball::colour(p[i]);
            }
            None
        }
        fn backward(&mut self, _: &[Vec3], _: &[Vec3], _: FieldTape, _: &[f32], _: &[[f32; 3]]) {}
        fn step(&mut self, _: f32) {}
        fn gradients_finite(&self) -> bool {
            true
        }
        fn discard_gradients(&mut self) {}
        fn hierarchical(&self) -> Option<&dyn crate::plugin::field::HierarchicalSampling> {
            self.hierarchical.is_some().then_some(self as &dyn crate::plugin::field::HierarchicalSampling)
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
        fn load_state(&mut self, _: &[u8]) -> Result<(), crate::error::StateError> {
            Ok(())
        }
        fn num_parameters(&self) -> usize {
            0
        }
        fn parameters(&self) -> Vec<f32> {
            Vec::new()
        }
        fn set_parameters(&mut self, _: &[f32]) -> Result<(), crate::error::StateError> {
            Ok(())
        }
        fn gradients(&self) -> Vec<f32> {
            Vec::new()
        }
        fn frozen_pass(&self) -> Option<&dyn crate::plugin::field::FrozenPass> {
            Some(self)
        }
    }

    /// The ball proposes its own samples.
    impl crate::plugin::field::HierarchicalSampling for Ball {
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

    impl crate::plugin::field::FrozenPass for Ball {
        fn early_termination_pass(&self) -> bool {
            self.termination_pass
        }
        fn density_state_dim(&self) -> usize {
            if self.with_state {
                3
            } else {
                0
            }
        }
        fn density_with_state(&self, positions: &[Vec3], density: &mut [f32], state: &mut [f32]) {
            self.density(positions, density);
            for (p, s) in positions.iter().zip(state.chunks_exact_mut(3)) {
                s.copy_from_slice(p);
            }
        }
        fn colour_from_state(
            &self,
            _: &[Vec3],
            _: &[Vec3],
            state: &[f32],
            rows: &[u32],
            rgb: &mut [[f32; 3]],
            seg: Option<&mut [f32]>,
        ) {
            self.from_state.fetch_add(rows.len(), Ordering::Relaxed);
            let at = |j: usize| -> Vec3 { state[3 * rows[j] as usize..][..3].try_into().unwrap() };
            for (j, c) in rgb.iter_mut().enumerate() {
                *c = Ball::colour(at(j));
            }
            if let Some(seg) = seg {
                let p: Vec<Vec3> = (0..rows.len()).map(at).collect();
                self.seg_input(&p, seg);
            }
        }
    }

    fn setup() -> (SceneExtent, Contraction, RayBatch) {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let cam = Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 16, 16, 40.0);
        (extent, Contraction::new(&extent), RayBatch::full_image(&cam))
    }

    fn colours(field: &Ball, options: RenderOptions) -> (Vec<RayColour>, usize) {
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        field.evaluated.store(0, Ordering::Relaxed);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let mut r = render(field, ctx, &rays, options, false, &mut rng);
        r.composite();
        (r.colours, field.evaluated.load(Ordering::Relaxed))
    }

    /// Extra channels composite `Σ w_k e_k` over the samples above their weight threshold only,
    /// and leave the colours as they are.
    #[test]
    fn extra_channels_composite_the_selected_samples() {
        let field = Ball::new(None, false);
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        let options = RenderOptions {
            proposal: true,
            march: MarchOptions { steps: 128, stratified: false },
            early_stop: 0.0,
            min_weight: 0.0,
            memory: MemoryBudget::unlimited(),
        };
        // Channel 0 is 1 everywhere (so it composites to the selected weight), channel 1 is z.
        let eval = |p: &[Vec3]| p.iter().flat_map(|p| [1.0, p[2]]).collect::<Vec<f32>>();
        let all = ExtraChannels { dim: 2, min_weight: 0.0, eval: &eval };
        let (colours, extra) = render_inference(&field, ctx, &rays, options, 100, Some(&all));
        let (plain, none) = render_inference(&field, ctx, &rays, options, 100, None);
        assert!(none.is_empty());
        for ((c, p), e) in colours.iter().zip(&plain).zip(extra.chunks_exact(2)) {
            assert_eq!(c.rgb, p.rgb);
            assert!((e[0] - c.acc).abs() < 1e-5, "{} vs acc {}", e[0], c.acc);
        }
        // A threshold drops the low-weight samples: less weight, never more.
        let strict = ExtraChannels { dim: 2, min_weight: 0.05, eval: &eval };
        let (_, thresholded) = render_inference(&field, ctx, &rays, options, 100, Some(&strict));
        let (mut dropped, mut hits) = (0.0f32, 0);
        for ((c, a), b) in colours.iter().zip(extra.chunks_exact(2)).zip(thresholded.chunks_exact(2)) {
            assert!(b[0] <= a[0] + 1e-6);
            if c.acc > 0.5 {
                hits += 1;
                dropped += a[0] - b[0];
            }
        }
        assert!(hits > 20 && dropped > 0.0, "{hits} hits, {dropped} weight dropped");
    }

    /// An inference render cut into chunks and parallel blocks gives each ray what one render
    /// of the whole batch gives it, bit for bit, extra channels included.
    #[test]
    fn inference_blocks_render_as_one_batch() {
        let field = Ball::new(None, false);
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let contraction = Contraction::new(&extent);
        // More rays than two blocks, the last one partial.
        let cam = Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 57, 41, 40.0);
        let rays = RayBatch::full_image(&cam);
        assert!(rays.len() > 2 * INFERENCE_BLOCK && !rays.len().is_multiple_of(INFERENCE_BLOCK));
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        let options = RenderOptions {
            proposal: true,
            march: MarchOptions { steps: 64, stratified: false },
            early_stop: 1e-4,
            min_weight: 1e-3,
            memory: MemoryBudget::unlimited(),
        };
        let eval = |p: &[Vec3]| p.iter().flat_map(|p| [1.0, p[2]]).collect::<Vec<f32>>();
        let extra = ExtraChannels { dim: 2, min_weight: 1e-3, eval: &eval };
        let mut whole = render(&field, ctx, &rays, options, false, &mut rand_chacha::ChaCha8Rng::seed_from_u64(0));
        whole.composite();
        let whole_extra = whole.composite_extra(&extra);
        let bits = |c: &[RayColour]| c.iter().flat_map(|c| c.rgb.map(f32::to_bits)).collect::<Vec<_>>();
        let float_bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let depth = |c: &[RayColour]| c.iter().map(|c| c.depth.to_bits()).collect::<Vec<_>>();
        for chunk in [rays.len(), 1500, 700] {
            let (colours, channels) = render_inference(&field, ctx, &rays, options, chunk, Some(&extra));
            assert_eq!(bits(&colours), bits(&whole.colours), "chunk {chunk}: colours differ");
            assert_eq!(depth(&colours), depth(&whole.colours), "chunk {chunk}: depths differ");
            assert_eq!(float_bits(&channels), float_bits(&whole_extra), "chunk {chunk}: extra channels differ");
        }
        assert!(whole.colours.iter().any(|c| c.acc > 0.5), "the ball is in view");
    }

    /// A frozen render keeps the segmentation input of exactly its surviving samples, and
    /// only within its budget; the samples and their values are those of a plain render.
    #[test]
    fn frozen_render_keeps_the_segmentation_input_within_its_budget() {
        let field = Ball::new(None, false);
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        let march = MarchOptions { steps: 64, stratified: false };
        for options in [unlimited(march, 1e-4, 1e-3), unlimited(march, 0.0, 0.0)] {
            let rng = || rand_chacha::ChaCha8Rng::seed_from_u64(0);
            let plain = render(&field, ctx, &rays, options, false, &mut rng());
            let kept = render_with_seg_input(
                &field,
                ctx,
                &rays,
                options,
                usize::MAX,
                &mut FrozenBuffers::default(),
                &mut rng(),
            );
            assert!(plain.seg_input.is_empty());
            assert_eq!((&kept.samples.t, &kept.density, &kept.rgb), (&plain.samples.t, &plain.density, &plain.rgb));
            let mut want = vec![0.0; kept.samples.len() * 2];
            field.seg_input(&kept.samples.positions, &mut want);
            assert!(!want.is_empty());
            assert_eq!(kept.seg_input, want);
            let over = render_with_seg_input(
                &field,
                ctx,
                &rays,
                options,
                want.len() * 4 - 1,
                &mut FrozenBuffers::default(),
                &mut rng(),
            );
            assert!(over.seg_input.is_empty(), "over its budget, nothing is kept");
            // A field that keeps its state from the density pass gives the same render.
            // Its buffers are reused from call to call, whatever they held.
            let stateful = Ball::new(None, true);
            let mut buffers = FrozenBuffers { state: vec![f32::NAN; 7], seg_input: vec![f32::NAN; 100_000] };
            for budget in [usize::MAX, 0, usize::MAX] {
                stateful.from_state.store(0, Ordering::Relaxed);
                let mut s = render_with_seg_input(&stateful, ctx, &rays, options, budget, &mut buffers, &mut rng());
                // Only a pass that prunes has a density pass to keep state from.
                let pruned = options.early_stop > 0.0;
                assert_eq!(stateful.from_state.load(Ordering::Relaxed), if pruned { s.samples.len() } else { 0 });
                let same = (&s.samples.t, &s.density, &s.rgb, &s.seg_input);
                let seg = if budget == 0 { &over.seg_input } else { &kept.seg_input };
                assert_eq!(same, (&kept.samples.t, &kept.density, &kept.rgb, seg));
                buffers.recycle(&mut s);
            }
        }
    }

    /// Pruning block by block (a field without kept state) places, keeps and evaluates the
    /// same samples as the whole batch's passes (the same field keeping its state), with
    /// stratified jitter too.
    #[test]
    fn pruning_in_blocks_keeps_what_the_whole_batch_keeps() {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let contraction = Contraction::new(&extent);
        let cam = Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 57, 41, 40.0);
        let rays = RayBatch::full_image(&cam);
        assert!(rays.len() > 4 * MARCH_CHUNK);
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        for stratified in [false, true] {
            let options = RenderOptions {
                proposal: true,
                march: MarchOptions { steps: 64, stratified },
                early_stop: 1e-4,
                min_weight: 1e-3,
                memory: MemoryBudget::unlimited(),
            };
            let rng = || rand_chacha::ChaCha8Rng::seed_from_u64(7);
            let blocks = render(&Ball::new(None, false), ctx, &rays, options, false, &mut rng());
            let stateful = Ball::new(None, true);
            let whole = render(&stateful, ctx, &rays, options, false, &mut rng());
            assert!(stateful.from_state.load(Ordering::Relaxed) > 0, "the whole batch's passes ran");
            let (a, b) = (&blocks.samples, &whole.samples);
            assert!(a.len() > 100 && !a.skipped_tau.is_empty(), "{} samples kept", a.len());
            assert_eq!((&a.ray_start, &a.t, &a.delta, &a.positions), (&b.ray_start, &b.t, &b.delta, &b.positions));
            assert_eq!((&a.skipped_tau, &a.s), (&b.skipped_tau, &b.s));
            assert_eq!((&blocks.density, &blocks.rgb), (&whole.density, &whole.rgb));
            let counts = |t: &RenderTiming| (t.candidates, t.evaluated, t.kept);
            assert_eq!(counts(&blocks.timing), counts(&whole.timing));
        }
    }

    #[test]
    fn early_termination_skips_density_work_and_keeps_colours() {
        let field = Ball::new(None, false);
        let march = MarchOptions { steps: 256, stratified: false };
        let (full, _) = colours(&field, unlimited(march, 0.0, 0.0));
        let (pruned, evaluated) = colours(&field, unlimited(march, 1e-4, 1e-4));
        let hits = full.iter().filter(|c| c.acc > 0.5).count();
        assert!(hits > 20, "the ball covers part of the image ({hits} rays)");
        for (a, b) in full.iter().zip(&pruned) {
            for k in 0..3 {
                assert!((a.rgb[k] - b.rgb[k]).abs() < 2e-3, "{a:?} vs {b:?}");
            }
            assert!((a.acc - b.acc).abs() < 2e-3);
        }
        // Rays through the ball stop inside it, skipping at least the back half of the box.
        let (_, all) = colours(&field, unlimited(march, 0.0, 1e-9));
        assert!(evaluated + 100 * hits < all, "evaluated {evaluated} of {all} densities ({hits} rays hit)");
    }

    /// A field whose density pass does not pay terminates a frozen render's rays without one,
    /// cutting them after the full pass: the same samples and colours, bit for bit, as the
    /// render whose density pass made the cut. A weight threshold, or a render for training,
    /// still takes the pass.
    #[test]
    fn early_termination_without_a_density_pass_where_the_field_says_it_does_not_pay() {
        let field = Ball { termination_pass: false, ..Ball::new(None, false) };
        let march = MarchOptions { steps: 256, stratified: false };
        let options = |early_stop, min_weight| unlimited(march, early_stop, min_weight);
        let frozen = |field: &Ball| {
            let (extent, contraction, rays) = setup();
            let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
            field.evaluated.store(0, Ordering::Relaxed);
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
            let mut r = render(field, ctx, &rays, options(1e-4, 0.0), false, &mut rng);
            r.composite();
            (r, field.evaluated.load(Ordering::Relaxed))
        };
        let (with_pass, passed) = frozen(&Ball::new(None, false));
        let (without, evaluated) = frozen(&field);
        assert!(passed > 0 && evaluated == 0, "density-only evaluations: {passed} with the pass, {evaluated} without");
        assert_eq!(without.samples.ray_start, with_pass.samples.ray_start, "the same samples per ray");
        assert_eq!(without.samples.t, with_pass.samples.t);
        let hits = without.colours.iter().filter(|c| c.acc > 0.5).count();
        let (kept, candidates) = (without.timing.kept, without.timing.candidates);
        assert!(hits > 20 && kept + 100 * hits < candidates, "{kept} of {candidates} kept, {hits} rays hit the ball");
        for (a, b) in without.colours.iter().zip(&with_pass.colours) {
            assert_eq!((a.rgb.map(f32::to_bits), a.acc.to_bits()), (b.rgb.map(f32::to_bits), b.acc.to_bits()));
        }
        let (_, thresholded) = colours(&field, options(1e-4, 1e-4));
        assert!(thresholded > 0, "a weight threshold needs the density pass");
        let (extent, contraction, rays) = setup();
        let ctx = RenderContext { extent: &extent, contraction: &contraction, occupancy: None, near: 0.0 };
        field.evaluated.store(0, Ordering::Relaxed);
        render(&field, ctx, &rays, options(1e-4, 0.0), true, &mut rand_chacha::ChaCha8Rng::seed_from_u64(0));
        assert!(field.evaluated.load(Ordering::Relaxed) > 0, "training renders keep the density pass");
    }

    #[test]
    fn hierarchical_sampling_concentrates_samples_and_matches_a_dense_render() {
        let dense = Ball::new(None, false);
        let (want, _) = colours(
            &dense,
            RenderOptions {
                proposal: true,
                march: MarchOptions { steps: 2048, stratified: false },
                early_stop: 0.0,
                min_weight: 0.0,
                memory: MemoryBudget::unlimited(),
            },
        );
        let h = Hierarchical { coarse_samples: 32, fine_samples: 64 };
        let field = Ball::new(Some(h), false);
        let (got, _) = colours(
            &field,
            RenderOptions {
                proposal: true,
                march: MarchOptions { steps: 8, stratified: false },
                early_stop: 0.0,
                min_weight: 0.0,
                memory: MemoryBudget::unlimited(),
            },
        );
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
        let options = RenderOptions {
            proposal: true,
            march: MarchOptions { steps: 8, stratified: true },
            early_stop: 0.0,
            min_weight: 0.0,
            memory: MemoryBudget::unlimited(),
        };
        let r = render(&field, ctx, &rays, options, true, &mut rng);
        let coarse = r.coarse.expect("proposal pass with record");
        assert_eq!(coarse.colours.len(), rays.len());
        let marched = (0..rays.len()).filter(|&i| !coarse.samples.range(i).is_empty()).count();
        assert_eq!(r.samples.len(), coarse.samples.len() + marched * 64);
        for ray in 0..rays.len() {
            let range = r.samples.range(ray);
            assert!(r.samples.t[range.clone()].windows(2).all(|w| w[0] <= w[1]));
            let span: f32 = r.samples.delta[range].iter().sum();
            let coarse_span: f32 = coarse.samples.delta[coarse.samples.range(ray)].iter().sum();
            assert!((span - coarse_span).abs() < 1e-3 * (1.0 + coarse_span), "intervals partition the strata");
        }
        // Without the proposal the field's own network alone marches the candidates: the
        // render of the same field without hierarchical sampling, bit for bit.
        let alone = RenderOptions {
            proposal: false,
            march: MarchOptions { steps: 64, stratified: false },
            early_stop: 1e-4,
            min_weight: 1e-3,
            memory: MemoryBudget::unlimited(),
        };
        let (fine, _) = colours(&field, alone);
        let (plain, _) = colours(&Ball::new(None, false), alone);
        for (a, b) in fine.iter().zip(&plain) {
            assert_eq!((a.rgb.map(f32::to_bits), a.acc.to_bits()), (b.rgb.map(f32::to_bits), b.acc.to_bits()));
        }
        assert!(fine.iter().any(|c| c.acc > 0.5), "rays hit the ball");
        assert!(render(&field, ctx, &rays, alone, false, &mut rng).coarse.is_none());
    }
}
