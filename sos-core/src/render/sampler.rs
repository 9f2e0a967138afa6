//! Placing samples along rays: stratified candidates over the scene extent, skipping empty
//! space with the occupancy grid, and inverse-CDF importance sampling.

use rand::Rng;

use crate::camera::{axpy, Vec3};
use crate::render::contraction::Contraction;
use crate::render::occupancy::OccupancyGrid;
use crate::render::rays::RayBatch;
use crate::scene::SceneExtent;

/// Samples of many rays, packed ray after ray.
///
/// # Shapes
/// `ray_start`: `[n_rays + 1]` (samples of ray `r` are `ray_start[r]..ray_start[r + 1]`);
/// every other field `[n_samples]`.
#[derive(Debug, Clone, Default)]
pub struct Samples {
    /// Offsets of each ray's samples.
    pub ray_start: Vec<u32>,
    /// Distance of the sample along its (unit-direction) ray.
    pub t: Vec<f32>,
    /// Length of the interval the sample stands for.
    pub delta: Vec<f32>,
    /// World position.
    pub positions: Vec<Vec3>,
    /// Unit view direction (the ray's).
    pub directions: Vec<Vec3>,
    /// Optical depth of dropped samples just before each sample (see
    /// [`crate::render::composite::RaySamples::skipped_tau`]); empty when none were dropped.
    pub skipped_tau: Vec<f32>,
    /// Normalised position of each sample along its ray, the candidate spacing's parameter in
    /// `[0, 1]` (uniform in distance, disparity or contracted distance by the extent), with
    /// candidate intervals `1 / steps` wide; empty when the samples were not marched (e.g.
    /// importance samples).
    pub s: Vec<f32>,
}

impl Samples {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.t.len()
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// Number of rays.
    pub fn n_rays(&self) -> usize {
        self.ray_start.len().saturating_sub(1)
    }

    /// Sample index range of ray `r`.
    pub fn range(&self, r: usize) -> std::ops::Range<usize> {
        self.ray_start[r] as usize..self.ray_start[r + 1] as usize
    }

    /// No samples yet (one ray offset, 0), with room for `n` samples of `n_rays` rays: vectors
    /// filled up to that never grow (and copy), and only the pages written are committed.
    /// `skipped_tau` gets no room (most batches have none).
    pub fn with_capacity(n_rays: usize, n: usize) -> Samples {
        let mut ray_start = Vec::with_capacity(n_rays + 1);
        ray_start.push(0);
        Samples {
            ray_start,
            t: Vec::with_capacity(n),
            delta: Vec::with_capacity(n),
            positions: Vec::with_capacity(n),
            directions: Vec::with_capacity(n),
            skipped_tau: Vec::new(),
            s: Vec::with_capacity(n),
        }
    }

    /// Keeps the samples for which `keep(index)` is true.
    pub fn filter(&self, mut keep: impl FnMut(usize) -> bool) -> (Samples, Vec<u32>) {
        let mut out = Samples::with_capacity(self.n_rays(), self.len());
        let mut kept = Vec::with_capacity(self.len());
        for r in 0..self.n_rays() {
            for i in self.range(r) {
                if keep(i) {
                    out.t.push(self.t[i]);
                    out.delta.push(self.delta[i]);
                    out.positions.push(self.positions[i]);
                    out.directions.push(self.directions[i]);
                    if !self.s.is_empty() {
                        out.s.push(self.s[i]);
                    }
                    kept.push(i as u32);
                }
            }
            out.ray_start.push(out.t.len() as u32);
        }
        (out, kept)
    }

    /// Keeps the first `kept[r]` samples of each ray `r`, in place (see [`keep_ray_prefixes`]).
    pub fn keep_ray_prefixes(&mut self, kept: &[usize]) {
        let starts = std::mem::take(&mut self.ray_start);
        keep_ray_prefixes(&mut self.t, &starts, kept, 1);
        keep_ray_prefixes(&mut self.delta, &starts, kept, 1);
        keep_ray_prefixes(&mut self.positions, &starts, kept, 1);
        keep_ray_prefixes(&mut self.directions, &starts, kept, 1);
        for optional in [&mut self.s, &mut self.skipped_tau] {
            if !optional.is_empty() {
                keep_ray_prefixes(optional, &starts, kept, 1);
            }
        }
        self.ray_start = std::iter::once(0)
            .chain(kept.iter().scan(0u32, |end, &n| {
                *end += n as u32;
                Some(*end)
            }))
            .collect();
    }
}

/// Keeps the first `kept[r]` samples of each ray `r` in `values` (`width` values a sample, the
/// rays starting at `ray_start`, the first at 0), moved down in place.
pub fn keep_ray_prefixes<T: Copy>(values: &mut Vec<T>, ray_start: &[u32], kept: &[usize], width: usize) {
    let mut end = 0;
    for (&start, &n) in ray_start.iter().zip(kept) {
        let start = start as usize * width;
        values.copy_within(start..start + n * width, end);
        end += n * width;
    }
    values.truncate(end);
}

/// How candidates are spread along each ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Spacing {
    /// Uniform in distance between the ray's entry and exit of a box.
    Linear,
    /// Uniform in disparity (inverse depth along −Z) between `near` and `far`.
    Disparity {
        /// Nearest depth.
        near: f32,
        /// Farthest depth.
        far: f32,
    },
    /// Uniform in distance inside the foreground sphere, then uniform in disparity out to
    /// `far_factor` radii.
    SphereThenDisparity {
        /// Sphere centre.
        center: Vec3,
        /// Sphere radius.
        radius: f32,
    },
}

/// Per-ray quantities the spacing functions need.
struct RayCtx {
    origin: Vec3,
    direction: Vec3,
    t0: f32,
    t1: f32,
    inv_near: f32,
    inv_far: f32,
    split: f32,
}

/// Candidate sampling settings.
#[derive(Debug, Clone, Copy)]
pub struct MarchOptions {
    /// Number of candidate intervals per ray across the whole extent.
    pub steps: usize,
    /// Jitter each sample uniformly inside its interval (training) instead of its midpoint.
    pub stratified: bool,
}

/// The candidate spacing suited to a scene extent.
pub fn spacing_for(extent: &SceneExtent) -> Spacing {
    match *extent {
        SceneExtent::Bounded { .. } => Spacing::Linear,
        SceneExtent::ForwardFacing { near, far, .. } => Spacing::Disparity { near, far },
        SceneExtent::Unbounded { center, radius } => Spacing::SphereThenDisparity { center, radius },
    }
}

fn ray_context(extent: &SceneExtent, origin: Vec3, direction: Vec3) -> Option<RayCtx> {
    let mut ctx = RayCtx { origin, direction, t0: 0.0, t1: 0.0, inv_near: 0.0, inv_far: 0.0, split: 0.0 };
    match *extent {
        SceneExtent::Bounded { min, max } => {
            let (t0, t1) = ray_box(origin, direction, min, max)?;
            ctx.t0 = t0.max(1e-4);
            ctx.t1 = t1;
            (ctx.t1 > ctx.t0).then_some(ctx)
        }
        SceneExtent::ForwardFacing { near, far, .. } => {
            if direction[2] >= -1e-6 {
                return None;
            }
            ctx.inv_near = 1.0 / near;
            ctx.inv_far = 1.0 / far;
            Some(ctx)
        }
        SceneExtent::Unbounded { center, radius } => {
            // Exit of the foreground sphere; cameras may be inside or outside it.
            let oc = [origin[0] - center[0], origin[1] - center[1], origin[2] - center[2]];
            let b = oc[0] * direction[0] + oc[1] * direction[1] + oc[2] * direction[2];
            let c = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - radius * radius;
            let disc = b * b - c;
            let t_exit = if disc > 0.0 { -b + disc.sqrt() } else { radius };
            ctx.t0 = if c > 0.0 && disc > 0.0 { (-b - disc.sqrt()).max(1e-3) } else { 1e-3 };
            ctx.split = t_exit.max(ctx.t0 + 1e-3);
            ctx.inv_near = 1.0 / ctx.split;
            ctx.inv_far = 1.0 / (ctx.split + 1000.0 * radius);
            Some(ctx)
        }
    }
}

fn t_linear(c: &RayCtx, s: f32) -> f32 {
    c.t0 + s * (c.t1 - c.t0)
}

fn t_disparity(c: &RayCtx, s: f32) -> f32 {
    let depth = 1.0 / (c.inv_near - s * (c.inv_near - c.inv_far));
    // The point at camera-space depth `depth` along −Z: o_z + t d_z = −depth.
    ((-depth - c.origin[2]) / c.direction[2]).max(0.0)
}

fn t_sphere(c: &RayCtx, s: f32) -> f32 {
    if s <= 0.5 {
        c.t0 + 2.0 * s * (c.split - c.t0)
    } else {
        1.0 / (c.inv_near - (2.0 * s - 1.0) * (c.inv_near - c.inv_far))
    }
}

/// Entry and exit distances of a ray through a box.
pub fn ray_box(origin: Vec3, direction: Vec3, min: Vec3, max: Vec3) -> Option<(f32, f32)> {
    let mut t0 = f32::NEG_INFINITY;
    let mut t1 = f32::INFINITY;
    for k in 0..3 {
        let inv = 1.0 / direction[k];
        let (a, b) = ((min[k] - origin[k]) * inv, (max[k] - origin[k]) * inv);
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t1 > t0.max(0.0)).then_some((t0.max(0.0), t1))
}

/// Places candidate samples on every ray, dropping those in cells the occupancy grid marks
/// empty (all kept when `occupancy` is `None`).
pub fn march(
    extent: &SceneExtent,
    contraction: &Contraction,
    occupancy: Option<&OccupancyGrid>,
    near: f32,
    rays: &RayBatch,
    options: MarchOptions,
    rng: &mut impl Rng,
) -> Samples {
    // Maps the normalised position s ∈ [0, 1] along a ray to a distance.
    let t_of: fn(&RayCtx, f32) -> f32 = match spacing_for(extent) {
        Spacing::Linear => t_linear,
        Spacing::Disparity { .. } => t_disparity,
        Spacing::SphereThenDisparity { .. } => t_sphere,
    };
    let steps = options.steps.max(1);
    // Room for every candidate.
    let mut out = Samples::with_capacity(rays.len(), rays.len() * steps);
    let inv_steps = 1.0 / steps as f32;
    for r in 0..rays.len() {
        let (o, d) = (rays.origins[r], rays.directions[r]);
        if let Some(ctx) = ray_context(extent, o, d) {
            let mut t_prev = t_of(&ctx, 0.0);
            for i in 0..steps {
                let t_next = t_of(&ctx, (i + 1) as f32 * inv_steps);
                let xi = if options.stratified { rng.gen::<f32>() } else { 0.5 };
                let t = t_prev + xi * (t_next - t_prev);
                let delta = t_next - t_prev;
                t_prev = t_next;
                if delta <= 0.0 || t < near {
                    continue;
                }
                let p = axpy(o, t, d);
                let u = contraction.to_unit(p);
                if !Contraction::inside(u) {
                    continue;
                }
                if let Some(occ) = occupancy {
                    if !occ.is_occupied(u) {
                        continue;
                    }
                }
                out.t.push(t);
                out.delta.push(delta);
                out.positions.push(p);
                out.directions.push(d);
                out.s.push((i as f32 + xi) * inv_steps);
            }
        }
        out.ray_start.push(out.t.len() as u32);
    }
    out
}

/// Inverse-CDF sampling of `n` distances from a piecewise-constant density over bins with
/// edges `edges[0..=m]` and weights `weights[0..m]` (NeRF's `sample_pdf`). `uniform` draws
/// the quantiles at random (training) instead of evenly spaced; a padding of `1e-5` per bin
/// keeps empty rays well defined. Returns sorted distances.
pub fn sample_pdf(edges: &[f32], weights: &[f32], n: usize, uniform: Option<&mut dyn rand::RngCore>) -> Vec<f32> {
    let m = weights.len();
    assert_eq!(edges.len(), m + 1, "sample_pdf needs one more edge than weights");
    let w: Vec<f32> = weights.iter().map(|w| w.max(0.0) + 1e-5).collect();
    let total: f32 = w.iter().sum();
    let mut cdf = Vec::with_capacity(m + 1);
    cdf.push(0.0f32);
    let mut acc = 0.0;
    for wk in &w {
        acc += wk / total;
        cdf.push(acc.min(1.0));
    }
    let mut quantiles: Vec<f32> = match uniform {
        Some(rng) => (0..n).map(|_| (rng.next_u32() >> 8) as f32 / (1u32 << 24) as f32).collect(),
        None => (0..n).map(|i| if n > 1 { i as f32 / (n - 1) as f32 } else { 0.5 }).collect(),
    };
    quantiles.sort_by(|a, b| a.total_cmp(b));
    quantiles
        .iter()
        .map(|&u| {
            // First bin whose upper CDF exceeds u.
            let k = cdf[1..].partition_point(|&c| c < u).min(m - 1);
            let span = cdf[k + 1] - cdf[k];
            let f = if span < 1e-5 { 0.0 } else { (u - cdf[k]) / span };
            edges[k] + f.clamp(0.0, 1.0) * (edges[k + 1] - edges[k])
        })
        .collect()
}

/// Inverse-CDF sampling of `n` distances from a piecewise-constant density over possibly
/// disjoint, sorted bins `[starts[k], ends[k]]` with weights `weights[k]` (the bins a
/// hierarchical proposal pass kept after empty-space skipping). Like [`sample_pdf`], a padding
/// of `1e-5` per bin keeps empty rays well defined, `uniform` draws the quantiles at random
/// (training) instead of evenly spaced, and the result is sorted. No bins, no samples.
pub fn sample_bins<R: Rng>(
    starts: &[f32],
    ends: &[f32],
    weights: &[f32],
    n: usize,
    uniform: Option<&mut R>,
) -> Vec<f32> {
    let m = weights.len();
    debug_assert!(starts.len() == m && ends.len() == m);
    if m == 0 || n == 0 {
        return Vec::new();
    }
    let mut cdf = Vec::with_capacity(m + 1);
    cdf.push(0.0f64);
    let mut acc = 0.0f64;
    for w in weights {
        // Non-finite weights (a diverging proposal) count as empty rather than poisoning the CDF.
        let w = if w.is_finite() { w.max(0.0) } else { 0.0 };
        acc += w as f64 + 1e-5;
        cdf.push(acc);
    }
    let mut quantiles: Vec<f64> = match uniform {
        Some(rng) => (0..n).map(|_| rng.gen::<f64>() * acc).collect(),
        None => (0..n).map(|i| if n > 1 { i as f64 / (n - 1) as f64 * acc } else { 0.5 * acc }).collect(),
    };
    quantiles.sort_by(|a, b| a.total_cmp(b));
    quantiles
        .iter()
        .map(|&u| {
            let k = cdf[1..].partition_point(|&c| c < u).min(m - 1);
            let span = cdf[k + 1] - cdf[k];
            let f = if span > 0.0 { ((u - cdf[k]) / span).clamp(0.0, 1.0) as f32 } else { 0.5 };
            starts[k] + f * (ends[k] - starts[k])
        })
        .collect()
}

/// Merges the proposal samples `coarse_t` (one per bin `[starts[k], ends[k]]`) with the
/// importance samples `fine_t` (all inside those bins) into sorted distances `t` and the length
/// `delta` of the interval each stands for: maximal runs of touching bins form segments, and
/// each segment is partitioned at the midpoints between consecutive samples (the first
/// interval starts at the segment's start, the last ends at its end). Gaps between segments
/// (space the occupancy grid skipped) belong to no interval, so a sample before a gap never
/// absorbs its length.
pub fn merge_intervals(
    starts: &[f32],
    ends: &[f32],
    coarse_t: &[f32],
    fine_t: &[f32],
    t: &mut Vec<f32>,
    delta: &mut Vec<f32>,
) {
    t.clear();
    delta.clear();
    t.extend_from_slice(coarse_t);
    t.extend_from_slice(fine_t);
    t.sort_by(|a, b| a.total_cmp(b));
    delta.resize(t.len(), 0.0);
    let m = starts.len();
    let mut i = 0; // next sample
    let mut k = 0; // next bin
    while k < m {
        // Segment [a, b] = bins k..j that touch.
        let a = starts[k];
        let mut b = ends[k];
        let mut j = k + 1;
        while j < m && starts[j] <= b + 1e-4 * (ends[j] - starts[j]).max(1e-6) {
            b = b.max(ends[j]);
            j += 1;
        }
        // Samples of this segment: everything up to b (samples before a cannot exist, but clamp).
        let first = i;
        while i < t.len() && (t[i] <= b || j >= m) {
            i += 1;
        }
        let seg = first..i;
        for s in seg.clone() {
            let lo = if s == seg.start { a } else { 0.5 * (t[s - 1] + t[s]) };
            let hi = if s + 1 == seg.end { b } else { 0.5 * (t[s] + t[s + 1]) };
            delta[s] = (hi - lo).max(0.0);
        }
        k = j;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use rand::SeedableRng;

    #[test]
    fn merged_intervals_partition_the_segments_and_skip_gaps() {
        // Two touching bins [0, 1], [1, 2], a gap, then [5, 6].
        let starts = [0.0f32, 1.0, 5.0];
        let ends = [1.0f32, 2.0, 6.0];
        let coarse = [0.5f32, 1.5, 5.5];
        let fine = [0.25f32, 1.9, 5.75];
        let (mut t, mut d) = (Vec::new(), Vec::new());
        merge_intervals(&starts, &ends, &coarse, &fine, &mut t, &mut d);
        assert_eq!(t, vec![0.25, 0.5, 1.5, 1.9, 5.5, 5.75]);
        // Segment [0, 2]: boundaries 0, 0.375, 1.0, 1.7, 2.
        let want = [0.375f32, 0.625, 0.7, 0.3, 0.625, 0.375];
        for (a, b) in d.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{d:?}");
        }
        let covered: f32 = d.iter().sum();
        assert!((covered - 3.0).abs() < 1e-5, "covers the bins, not the gap: {covered}");
    }

    #[test]
    fn bin_sampling_follows_weights_and_stays_in_bins() {
        let starts = [0.0f32, 4.0, 9.0];
        let ends = [1.0f32, 5.0, 10.0];
        let weights = [0.0f32, 1.0, 3.0];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let t = sample_bins(&starts, &ends, &weights, 4000, Some(&mut rng));
        assert!(t.windows(2).all(|w| w[0] <= w[1]));
        assert!(t.iter().all(|&x| (0.0..=1.0).contains(&x) || (4.0..=5.0).contains(&x) || (9.0..=10.0).contains(&x)));
        let (b, c) = (t.iter().filter(|&&x| (4.0..=5.0).contains(&x)).count(), t.iter().filter(|&&x| x >= 9.0).count());
        assert!((c as f32 / b as f32 - 3.0).abs() < 0.3, "{b} {c}");
        let even = sample_bins::<rand_chacha::ChaCha8Rng>(&starts, &ends, &weights, 8, None);
        assert_eq!(even.len(), 8);
        assert!(sample_bins::<rand_chacha::ChaCha8Rng>(&[], &[], &[], 8, None).is_empty());
    }

    #[test]
    fn importance_samples_follow_the_weights() {
        let edges: Vec<f32> = (0..=10).map(|i| i as f32).collect();
        let mut weights = vec![0.0; 10];
        weights[3] = 1.0;
        weights[7] = 3.0;
        let t = sample_pdf(&edges, &weights, 400, None);
        let in3 = t.iter().filter(|&&x| (3.0..4.0).contains(&x)).count();
        let in7 = t.iter().filter(|&&x| (7.0..8.0).contains(&x)).count();
        assert!(t.windows(2).all(|w| w[0] <= w[1]));
        assert!((in7 as f32 / in3 as f32 - 3.0).abs() < 0.3, "{in3} {in7}");
        assert!(in3 + in7 > 390);
    }

    #[test]
    fn candidates_cover_the_box_and_respect_intervals() {
        let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
        let cam = Camera::look_at([0.0, 0.0, 3.0], [0.0; 3], [0.0, 1.0, 0.0], 8, 8, 8.0);
        let rays = RayBatch::full_image(&cam);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let s = march(
            &extent,
            &Contraction::new(&extent),
            None,
            0.0,
            &rays,
            MarchOptions { steps: 64, stratified: true },
            &mut rng,
        );
        assert_eq!(s.n_rays(), 64);
        for r in 0..s.n_rays() {
            let range = s.range(r);
            let span: f32 = s.delta[range.clone()].iter().sum();
            // Central rays cross the full cube depth of 2.
            if r == 27 {
                assert!((span - 2.0).abs() < 0.1, "span {span}");
            }
            assert!(s.t[range].windows(2).all(|w| w[0] < w[1]));
        }
    }

    #[test]
    fn disparity_spacing_spans_near_to_far() {
        let extent = SceneExtent::ForwardFacing { near: 1.0, far: 10.0, focal: 10.0, width: 8.0, height: 8.0 };
        let rays = RayBatch { origins: vec![[0.0; 3]], directions: vec![[0.0, 0.0, -1.0]] };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let s = march(
            &extent,
            &Contraction::new(&extent),
            None,
            0.0,
            &rays,
            MarchOptions { steps: 32, stratified: false },
            &mut rng,
        );
        assert_eq!(s.len(), 32);
        let span: f32 = s.delta.iter().sum();
        assert!((span - 9.0).abs() < 1e-3, "{span}");
        assert!(s.delta[31] > s.delta[0] * 10.0, "far intervals are longer");
    }
}
