//! What stage 2 keeps of a frozen field's renders and of the head's passes, from step to step,
//! under one memory budget.

use rand::Rng;

use crate::render::composite::RayColour;
use crate::render::memory_budget::MemoryBudget;
use crate::render::rays::RayBatch;
use crate::render::renderer::{render, render_with_seg_input, FrozenBuffers, RenderTiming, Rendered};
use crate::segment::head::SegHead;
use crate::segment::head_pass::{self, HeadSamples, HeadTapes};
use crate::segment::ray_cache::{RayCache, RayKey};
use crate::train::session::Session;

/// The gigabytes a stage-2 step fills (the frozen render's state and segmentation input, the
/// head's tapes), owned in one place with the budget that bounds them. They are kept between
/// steps so their pages are faulted in once rather than every step; over budget, work is
/// recomputed and results do not change.
pub struct FrozenRender {
    budget: MemoryBudget,
    buffers: FrozenBuffers,
    tapes: HeadTapes,
    rays: RayCache,
}

impl FrozenRender {
    /// Empty buffers bounded by `budget`.
    pub fn new(budget: MemoryBudget) -> FrozenRender {
        FrozenRender {
            budget,
            buffers: FrozenBuffers::default(),
            tapes: HeadTapes::with_budget(budget.head_tapes()),
            rays: RayCache::with_budget(budget.ray_cache()),
        }
    }

    /// The budget the buffers are bounded by.
    pub fn budget(&self) -> MemoryBudget {
        self.budget
    }

    /// Renders rays as a stage-2 step does, composited. With the density frozen
    /// (`joint = false`), samples whose compositing weight is below `segment.weight_threshold`
    /// are skipped (they cannot matter), and with `keep_seg_input` the field's segmentation
    /// input at the rest is kept when it fits the budget, so the head needs no second pass of
    /// the field. Hand the result back with [`FrozenRender::recycle`] when the step is done.
    pub fn render(
        &mut self,
        session: &Session,
        rays: &RayBatch,
        joint: bool,
        keep_seg_input: bool,
        rng: &mut impl Rng,
    ) -> Rendered {
        // A jointly trained field is not frozen: it renders as stage 1 evaluates.
        let mut options = if joint { session.render_options(false) } else { session.frozen_render_options() };
        options.memory = self.budget;
        let (field, ctx) = (session.field.as_ref(), session.render_context());
        let mut r = if joint {
            render(field, ctx, rays, options, true, rng)
        } else {
            options.min_weight = session.config.segment.weight_threshold;
            let seg_budget = if keep_seg_input { self.budget.seg_input() } else { 0 };
            render_with_seg_input(field, ctx, rays, options, seg_budget, &mut self.buffers, rng)
        };
        r.composite();
        r
    }

    /// Each ray's composited render by the frozen field, `keys` saying where the rays come from:
    /// rays rendered by an earlier call are looked up, the rest rendered (and kept while the
    /// budget allows). The results equal [`FrozenRender::render`]'s colours, ray for ray: the
    /// render is not stratified, so a ray renders the same whenever it is rendered. Only for a
    /// field that no longer changes; the timing is that of the rays rendered.
    pub fn colours(
        &mut self,
        session: &Session,
        rays: &RayBatch,
        keys: &[RayKey],
        rng: &mut impl Rng,
    ) -> (Vec<RayColour>, RenderTiming) {
        let cached = self.rays.lookup(keys);
        let missing: Vec<usize> = (0..rays.len()).filter(|&i| cached[i].is_none()).collect();
        let mut colours: Vec<RayColour> = cached.into_iter().map(Option::unwrap_or_default).collect();
        if missing.is_empty() {
            return (colours, RenderTiming::default());
        }
        let misses = RayBatch {
            origins: missing.iter().map(|&i| rays.origins[i]).collect(),
            directions: missing.iter().map(|&i| rays.directions[i]).collect(),
        };
        let mut r = self.render(session, &misses, false, false, rng);
        for (&i, &c) in missing.iter().zip(&r.colours) {
            colours[i] = c;
            self.rays.insert(keys[i], c);
        }
        let timing = r.timing;
        self.recycle(&mut r);
        (colours, timing)
    }

    /// Rays held by the cache of [`FrozenRender::colours`].
    pub fn cached_rays(&self) -> usize {
        self.rays.len()
    }

    /// The head's logits at the rendered samples, keeping its tapes when they fit.
    pub fn head_forward(&mut self, session: &Session, head: &SegHead, samples: HeadSamples) -> Vec<f32> {
        head_pass::forward(session.field.as_ref(), head, samples, &mut self.tapes)
    }

    /// Accumulates the head's gradients from those of its logits at the same samples.
    pub fn head_backward(&self, session: &Session, head: &mut SegHead, samples: HeadSamples, grad_logits: &[f32]) {
        head_pass::backward(session.field.as_ref(), head, samples, grad_logits, &self.tapes)
    }

    /// Takes back a render's buffers for the next step.
    pub fn recycle(&mut self, rendered: &mut Rendered) {
        self.buffers.recycle(rendered);
    }
}
