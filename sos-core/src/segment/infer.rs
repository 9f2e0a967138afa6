//! Mask inference: render a view's segmentation logits with the trained head, cluster them
//! with k-means, and name the foreground cluster.
//!
//! Foreground rules (`masks.foreground`):
//! - `saliency`: the cluster with the highest mean teacher saliency. The stage-2 extractor runs
//!   on the whole rendered view; its coarse saliency grid is upsampled (nearest) to the image.
//! - `focus`: the cluster holding most of the pixels whose rendered 3D points
//!   (`origin + direction · depth`, empty rays excluded) lie nearest a focus point (the nearest
//!   [`FOCUS_VOTE_FRACTION`] of them vote). For object-centric rigs it is
//!   [`Scene::focus_point`], where the training cameras' axes meet. When the training cameras
//!   share one viewing axis ([`Scene::shared_view_axis`]: a forward-facing rig), the axes do
//!   not meet, so the focus is instead the point on the mean camera axis (through the mean
//!   camera centre) at the median rendered depth of the view's central window (sides
//!   [`CENTRAL_FRACTION`] of the image's): whatever the view is centred on.
//!
//! With more than two clusters the foreground is the single chosen cluster.
//!
//! When most of the voting pixels lie on one of the view's large planes while, on an orbit
//! rig, something stands off the planes near the focus (the focus fell on the ground between
//! the members of a group), the pixels nearest the focus off the planes vote instead
//! ([`standing_voters`]).
//!
//! `masks.keep = "connected"` (the default) then drops the regions of the foreground cluster
//! that hold none of the `focus` rule's voting pixels ([`crate::segment::cleanup`]); on orbit
//! rigs the regions that stand near the focus stay (`masks.nearby_parts`), and regions of the
//! other clusters that rise clearly off the support planes and touch the mask join it
//! (`masks.attached_parts`: a dark base clustered with its ground). A mask
//! that still covers most of the image border has its cluster split again
//! ([`crate::segment::border_split`]). Last, the pixels near the mask's outline go to the side
//! whose colours they match (`masks.colour_band`, [`crate::segment::colour_refine`]).

use crate::camera::{axpy, dot, sub, Camera, Vec3};
use crate::config::{ForegroundRule, KeepRegions, LogitSource, MaskConfig, MaskDepth};
use crate::error::{ConfigError, RunError};
use crate::image::{GrayImage, RgbImage};
use crate::kmeans::{kmeans, KMeansConfig, KMeansResult};
use crate::plugin::FeatureExtractor;
use crate::render::composite::is_hit;
use crate::render::rays::RayBatch;
use crate::render::renderer::{render_inference, ExtraChannels};
use crate::scene::Scene;
use crate::segment::border_split::{border_share, split_cluster};
use crate::segment::cleanup::{
    keep_attached_parts, keep_nearby_parts, keep_seeded_regions, DepthContinuity, NearbyParts,
};
use crate::segment::cluster_space::{cluster_view, unit_rows};
use crate::segment::colour_refine::{band_pixels, refine_by_colour};
use crate::segment::diagnostics::{evidence_image, MaskEvidence};
use crate::segment::head::SegHead;
use crate::segment::head_pass;
use crate::segment::support_plane::{PlaneCandidates, ViewPoints};
use crate::segment::surface::SurfacePoints;
use crate::train::session::Session;

/// Clearance from the support planes, in plane tolerances, beyond which a pixel of another
/// cluster may join the mask as a part holding the object up: twice the band the plane rule
/// counts as on the plane, so ground that the rule just missed does not (on the unbounded rig
/// one band let a shadow in, whose dark pixels render with noisier depth).
pub const ATTACHED_PART_CLEARANCE: f32 = 2.0;

/// Side of the central window, as a fraction of the image's sides, whose median depth places
/// the focus point of forward-facing views.
pub const CENTRAL_FRACTION: f32 = 0.2;

/// Tint of foreground pixels in overlays and how strongly it is mixed in.
const OVERLAY_TINT: [f32; 3] = [1.0, 0.1, 0.1];
const OVERLAY_ALPHA: f32 = 0.5;

/// What one view renders to: colour, depth and composited logits per pixel.
#[derive(Debug, Clone)]
pub struct RenderedLogits {
    /// Rendered colour.
    pub rgb: RgbImage,
    /// Rendered distance per pixel as `masks.depth` chooses it (by default the visible
    /// surface, [`crate::render::composite::RayColour::median_depth`]), `EMPTY_RAY_DEPTH` for
    /// empty rays; row-major.
    pub depth: Vec<f32>,
    /// Composited raw logits, `[H·W, channels]` row-major.
    pub logits: Vec<f32>,
    /// Logit channels.
    pub channels: usize,
    /// Rendered 3D point of each pixel, `None` for empty rays.
    pub points: Vec<Option<Vec3>>,
}

/// Renders the colour, depth and segmentation logits of a whole view (`masks.logits` says how
/// the logits are formed).
pub fn render_logits(session: &Session, head: &SegHead, camera: &Camera) -> RenderedLogits {
    let field = session.field.as_ref();
    let d = head.outputs();
    let rays = RayBatch::full_image(camera);
    let eval = |positions: &[Vec3]| head_pass::sample_logits(field, head, positions);
    // By default the head sees the samples stage 2 trained it on: those above the segment
    // weight threshold (the head was never evaluated below it). That is also a few samples per
    // ray instead of every candidate; the colour still composites every sample.
    let min_weight = session.config.masks.head_min_weight.unwrap_or(session.config.segment.weight_threshold);
    let extra = ExtraChannels { dim: d, min_weight, eval: &eval };
    let source = session.config.masks.logits.unwrap_or(session.config.segment.logits);
    let composited = source == LogitSource::Composited;
    let (colours, composited_logits) = render_inference(
        field,
        session.render_context(),
        &rays,
        session.frozen_render_options(),
        session.config.render.chunk,
        composited.then_some(&extra),
    );
    let mut rgb = RgbImage::new(camera.width as usize, camera.height as usize);
    let mut depth = Vec::with_capacity(colours.len());
    let mut points = Vec::with_capacity(colours.len());
    for (i, c) in colours.iter().enumerate() {
        rgb.data[i * 3..i * 3 + 3].copy_from_slice(&c.rgb);
        let d = match session.config.masks.depth {
            MaskDepth::Median => c.median_depth,
            MaskDepth::Expected => c.depth,
        };
        depth.push(d);
        points.push(is_hit(d).then(|| axpy(rays.origins[i], d, rays.directions[i])));
    }
    let logits = if composited {
        composited_logits
    } else {
        let opacities: Vec<f32> = colours.iter().map(|c| c.acc).collect();
        let surface = SurfacePoints::new(&points, &opacities);
        surface.ray_logits(&eval(surface.positions()), points.len(), d)
    };
    RenderedLogits { rgb, depth, logits, channels: d, points }
}

/// Per-row softmax of `[n, d]` values (numerically stable).
pub fn softmax_rows(values: &[f32], d: usize) -> Vec<f32> {
    let mut out = values.to_vec();
    for row in out.chunks_exact_mut(d) {
        let m = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let mut sum = 0.0;
        for v in row.iter_mut() {
            *v = (*v - m).exp();
            sum += *v;
        }
        for v in row.iter_mut() {
            *v /= sum;
        }
    }
    out
}

/// The k-means settings of `masks` (clusters and restarts) with `seed`.
pub fn kmeans_config(masks: &MaskConfig, seed: u64) -> KMeansConfig {
    KMeansConfig { k: masks.clusters, n_init: masks.restarts, seed, ..KMeansConfig::default() }
}

/// k-means of per-pixel logits (`[n, d]`), after a softmax when `masks.softmax` and scaling to
/// unit length when `masks.normalize`; the result may have fewer clusters than asked when the
/// logits take fewer distinct values.
pub fn cluster_logits(
    logits: &[f32],
    d: usize,
    masks: &MaskConfig,
    seed: u64,
) -> Result<KMeansResult, crate::kmeans::KMeansError> {
    let config = kmeans_config(masks, seed);
    let mut values = if masks.softmax { softmax_rows(logits, d) } else { logits.to_vec() };
    if masks.normalize {
        unit_rows(&mut values, d);
    }
    kmeans(&values, d, &config)
}

/// Nearest-neighbour upsampling of a `[gh, gw]` grid to `[h, w]`.
pub fn upsample_nearest(grid: &[f32], gw: usize, gh: usize, w: usize, h: usize) -> Vec<f32> {
    GrayImage { width: gw, height: gh, data: grid.to_vec() }.resized_nearest(w, h).data
}

/// Mean of `value` over each cluster's pixels; `None` for empty clusters.
fn cluster_means(labels: &[u32], k: usize, value: impl Fn(usize) -> Option<f64>) -> Vec<Option<f64>> {
    let mut sum = vec![0.0f64; k];
    let mut count = vec![0usize; k];
    for (i, &l) in labels.iter().enumerate() {
        if let Some(v) = value(i) {
            sum[l as usize] += v;
            count[l as usize] += 1;
        }
    }
    sum.iter().zip(&count).map(|(&s, &c)| (c > 0).then(|| s / c as f64)).collect()
}

/// Index of the best defined value by `better`, ties to the lower index; 0 if none is defined.
fn pick(values: &[Option<f64>], better: impl Fn(f64, f64) -> bool) -> usize {
    let mut best: Option<(usize, f64)> = None;
    for (c, v) in values.iter().enumerate() {
        if let Some(v) = *v {
            let improves = match best {
                None => true,
                Some((_, b)) => better(v, b),
            };
            if improves {
                best = Some((c, v));
            }
        }
    }
    best.map_or(0, |(c, _)| c)
}

/// The cluster (of `k`) with the highest mean saliency; `saliency` is per pixel.
pub fn foreground_by_saliency(labels: &[u32], k: usize, saliency: &[f32]) -> usize {
    pick(&cluster_means(labels, k, |i| Some(saliency[i] as f64)), |a, b| a > b)
}

/// Fraction of a view's pixels, nearest the focus point, that vote for the foreground cluster,
/// decide whether a plane is the object's own and seed the regions `keep = "connected"` keeps:
/// small, so that a thin or small object (a pole, a toy in a room's corner) still holds all of
/// them rather than the ground around it.
pub const FOCUS_VOTE_FRACTION: f64 = 0.01;

/// Indices of the pixels whose points lie nearest `focus`: the nearest
/// [`FOCUS_VOTE_FRACTION`] of the pixels with a point (at least one; none without points).
pub fn focus_voters(points: &[Option<Vec3>], focus: Vec3) -> Vec<usize> {
    let mut near: Vec<(f32, usize)> =
        points.iter().enumerate().filter_map(|(i, p)| p.map(|p| (dot(sub(p, focus), sub(p, focus)), i))).collect();
    if near.is_empty() {
        return Vec::new();
    }
    let n_votes = ((near.len() as f64 * FOCUS_VOTE_FRACTION).ceil() as usize).clamp(1, near.len());
    near.select_nth_unstable_by(n_votes - 1, |a, b| a.0.total_cmp(&b.0));
    near[..n_votes].iter().map(|&(_, i)| i).collect()
}

/// Voters for a focus that fell on a large plane: on an orbit rig whose object is a group of
/// things on the ground, the point the cameras look at lies on the ground between them, and
/// its nearest pixels are the ground's. When most `voters` lie on the view's large `planes`,
/// the pixels nearest `focus` off every plane vote instead, provided they all lie within
/// `radius` of it (something stands there); `None` keeps the voters as they are.
pub fn standing_voters(
    points: &[Option<Vec3>],
    voters: &[usize],
    planes: &PlaneCandidates,
    focus: Vec3,
    radius: f32,
) -> Option<Vec<usize>> {
    if radius <= 0.0 || voters.is_empty() {
        return None;
    }
    let on_planes = planes.any();
    if voters.iter().filter(|&&i| on_planes[i]).count() * 2 < voters.len() {
        return None;
    }
    let off: Vec<Option<Vec3>> = points.iter().zip(&on_planes).map(|(p, &on)| p.filter(|_| !on)).collect();
    let standing = focus_voters(&off, focus);
    let near = |i: &usize| {
        off[*i].is_some_and(|p| {
            let d = sub(p, focus);
            dot(d, d) <= radius * radius
        })
    };
    (!standing.is_empty() && standing.iter().all(near)).then_some(standing)
}

/// The cluster (of `k`) holding most of the [`focus_voters`]. A vote rather than a mean
/// distance: a cluster that contains the object together with far walls still wins, while one
/// that is merely close on average (the ground under the object) does not. Pixels without a
/// point (empty rays) do not vote; with no points at all, cluster 0 is returned.
pub fn foreground_by_focus(labels: &[u32], k: usize, points: &[Option<Vec3>], focus: Vec3) -> usize {
    foreground_by_votes(labels, k, &focus_voters(points, focus))
}

/// The cluster (of `k`) holding most of the `voters` (pixel indices); ties to the lower index.
fn foreground_by_votes(labels: &[u32], k: usize, voters: &[usize]) -> usize {
    let mut votes = vec![0usize; k.max(1)];
    for &i in voters {
        if let Some(v) = votes.get_mut(labels[i] as usize) {
            *v += 1;
        }
    }
    (0..votes.len()).max_by_key(|&c| (votes[c], std::cmp::Reverse(c))).unwrap_or(0)
}

/// Where the `focus` rule measures distances from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FocusTarget {
    /// A fixed point where the training cameras' axes meet.
    Point(Vec3),
    /// Forward-facing rig: a point on this axis at each view's central median depth.
    Axis {
        /// Mean training camera centre.
        origin: Vec3,
        /// Mean training viewing direction (unit).
        direction: Vec3,
    },
}

impl FocusTarget {
    /// Chooses the target for a scene (see the module documentation).
    pub fn of_scene(scene: &Scene) -> FocusTarget {
        match scene.shared_view_axis() {
            Some((origin, direction)) => FocusTarget::Axis { origin, direction },
            None => FocusTarget::Point(scene.focus_point()),
        }
    }

    /// The focus point for one rendered view (`depth` row-major `width x height`).
    pub fn point_for(&self, depth: &[f32], width: usize, height: usize) -> Option<Vec3> {
        match *self {
            FocusTarget::Point(p) => Some(p),
            FocusTarget::Axis { origin, direction } => {
                let (cw, ch) = (window(width), window(height));
                let (c0, r0) = ((width - cw) / 2, (height - ch) / 2);
                let mut central: Vec<f32> = (r0..r0 + ch)
                    .flat_map(|r| (c0..c0 + cw).map(move |c| depth[r * width + c]))
                    .filter(|&d| is_hit(d))
                    .collect();
                if central.is_empty() {
                    return None;
                }
                let mid = central.len() / 2;
                let (_, median, _) = central.select_nth_unstable_by(mid, f32::total_cmp);
                Some(axpy(origin, *median, direction))
            }
        }
    }
}

/// Distance from `p` to the nearest training camera centre (infinite with none).
fn nearest_camera_distance(scene: &Scene, p: Vec3) -> f32 {
    scene
        .train
        .iter()
        .map(|&i| {
            let d = sub(scene.views[i].camera.origin(), p);
            dot(d, d).sqrt()
        })
        .fold(f32::INFINITY, f32::min)
}

/// Pixels of the central window along a side of `n` pixels (at least one).
fn window(n: usize) -> usize {
    ((n as f32 * CENTRAL_FRACTION).round() as usize).clamp(1, n.max(1))
}

/// The segmentation of one view.
#[derive(Debug, Clone)]
pub struct ViewMask {
    /// k-means cluster of each pixel, row-major.
    pub labels: Vec<u32>,
    /// Clusters formed (at most `masks.clusters`).
    pub clusters: usize,
    /// The cluster named foreground.
    pub foreground_cluster: usize,
    /// Foreground flag of each pixel.
    pub foreground: Vec<bool>,
    /// The rendered colour.
    pub rgb: RgbImage,
    /// The rendered depth the mask was decided with (as `masks.depth` chooses it;
    /// `EMPTY_RAY_DEPTH` for empty rays), row-major; empty when not rendered here.
    pub depth: Vec<f32>,
    /// The rendered 3D point of each pixel (`None` for empty rays); empty when not rendered here.
    pub points: Vec<Option<Vec3>>,
    /// What the mask was decided from ([`crate::segment::diagnostics`]), when inferred by
    /// [`MaskInference::segment`].
    pub evidence: Option<RgbImage>,
}

impl ViewMask {
    /// Builds a mask from cluster labels and the chosen cluster.
    pub fn new(labels: Vec<u32>, clusters: usize, foreground_cluster: usize, rgb: RgbImage) -> ViewMask {
        let foreground = labels.iter().map(|&l| l as usize == foreground_cluster).collect();
        ViewMask {
            labels,
            clusters,
            foreground_cluster,
            foreground,
            rgb,
            depth: Vec::new(),
            points: Vec::new(),
            evidence: None,
        }
    }

    /// The binary mask, foreground 1 (written as 255).
    pub fn mask_image(&self) -> GrayImage {
        GrayImage {
            width: self.rgb.width,
            height: self.rgb.height,
            data: self.foreground.iter().map(|&f| if f { 1.0 } else { 0.0 }).collect(),
        }
    }

    /// The rendered depth as an image, `None` when it was not rendered here: inverse depth
    /// (near bright), stretched between the view's 2nd and 98th percentiles so that every
    /// view uses its full range whatever its scale; empty rays black.
    pub fn depth_image(&self) -> Option<GrayImage> {
        let (w, h) = (self.rgb.width, self.rgb.height);
        if self.depth.len() != w * h {
            return None;
        }
        let disparity: Vec<Option<f32>> = self.depth.iter().map(|&d| (is_hit(d) && d > 0.0).then(|| 1.0 / d)).collect();
        let mut sorted: Vec<f32> = disparity.iter().flatten().copied().collect();
        sorted.sort_by(f32::total_cmp);
        let at = |q: f32| sorted.get(((sorted.len().saturating_sub(1)) as f32 * q).round() as usize).copied();
        let (lo, hi) = (at(0.02).unwrap_or(0.0), at(0.98).unwrap_or(1.0));
        let span = (hi - lo).max(f32::EPSILON);
        let data =
            disparity.iter().map(|d| d.map_or(0.0, |d| (0.05 + 0.95 * (d - lo) / span).clamp(0.05, 1.0))).collect();
        Some(GrayImage { width: w, height: h, data })
    }

    /// The rendered colour, tinted where foreground.
    pub fn overlay(&self) -> RgbImage {
        let mut out = self.rgb.clone();
        for (px, &fg) in out.data.chunks_exact_mut(3).zip(&self.foreground) {
            if fg {
                for k in 0..3 {
                    px[k] = (1.0 - OVERLAY_ALPHA) * px[k] + OVERLAY_ALPHA * OVERLAY_TINT[k];
                }
            }
        }
        out
    }
}

/// Mask inference for a session with a trained head.
pub struct MaskInference<'a> {
    session: &'a Session,
    head: &'a SegHead,
    extractor: Option<&'a dyn FeatureExtractor>,
    focus: FocusTarget,
}

impl<'a> MaskInference<'a> {
    /// Prepares inference; `extractor` is only consulted by the `saliency` rule (and must
    /// then be given).
    pub fn new(
        session: &'a Session,
        head: &'a SegHead,
        extractor: Option<&'a dyn FeatureExtractor>,
    ) -> Result<Self, RunError> {
        if head.mlp.in_dim() != session.field.seg_input_dim() {
            return Err(RunError::Checkpoint {
                path: session.checkpoint_path(),
                message: format!(
                    "the segmentation head takes {} inputs but the field gives {}; rerun `sos segment`",
                    head.mlp.in_dim(),
                    session.field.seg_input_dim()
                ),
            });
        }
        if session.config.masks.foreground == ForegroundRule::Saliency && extractor.is_none() {
            return Err(no_saliency(session, "no feature extractor is available"));
        }
        Ok(MaskInference { session, head, extractor, focus: FocusTarget::of_scene(&session.scene) })
    }

    /// The focus target of the `focus` rule.
    pub fn focus_target(&self) -> FocusTarget {
        self.focus
    }

    /// Renders, clusters and picks the foreground of the view seen by `camera`; `name` is
    /// used in messages.
    pub fn segment(&self, camera: &Camera, name: &str) -> Result<ViewMask, RunError> {
        let r = render_logits(self.session, self.head, camera);
        let masks = &self.session.config.masks;
        let clusters = cluster_view(&r.logits, r.channels, masks, self.session.config.seed).map_err(|e| {
            RunError::Diverged(format!(
                "view {name}: cannot cluster the rendered logits ({e}); retrain stage 2 with `sos segment`"
            ))
        })?;
        let (w, h) = (r.rgb.width, r.rgb.height);
        // Nothing rendered in the centre: fall back to where the cameras look.
        let focus = self.focus.point_for(&r.depth, w, h).unwrap_or_else(|| self.session.scene.focus_point());
        let seed = self.session.config.seed;
        let view = ViewPoints { points: &r.points, origin: camera.origin(), width: w, height: h };
        let planes = masks.drop_support_planes.then(|| PlaneCandidates::find(&view, seed));
        // Only an orbit's focus is a point the object surrounds; a forward-facing one is where
        // the view's centre happens to land.
        let nearby_radius = match self.focus {
            FocusTarget::Point(centre) => masks.nearby_parts * nearest_camera_distance(&self.session.scene, centre),
            FocusTarget::Axis { .. } => 0.0,
        };
        // Computed once: the `focus` rule votes with them, the support-plane test asks whether a
        // plane holds them, and `keep = "connected"` seeds from them.
        let mut voters = focus_voters(&r.points, focus);
        if let Some(planes) = &planes {
            if let Some(standing) = standing_voters(&r.points, &voters, planes, focus, nearby_radius) {
                voters = standing;
            }
        }
        let saliency = match masks.foreground {
            ForegroundRule::Saliency => Some(self.saliency(&r.rgb, name)?),
            ForegroundRule::Focus => None,
        };
        let choose = |labels: &[u32], k: usize| match &saliency {
            Some(s) => foreground_by_saliency(labels, k, s),
            None => foreground_by_votes(labels, k, &voters),
        };
        let support = planes.as_ref().map(|planes| planes.supports(&voters));
        let continuity =
            (masks.max_depth_jump > 0.0).then_some(DepthContinuity { depth: &r.depth, max_jump: masks.max_depth_jump });
        let nearby = match self.focus {
            FocusTarget::Point(centre) if nearby_radius > 0.0 => Some(NearbyParts {
                points: &r.points,
                centre,
                radius: nearby_radius,
                min_standing_outline: masks.min_standing_outline,
            }),
            _ => None,
        };
        // Only where attached parts are looked for (orbit rigs with connected regions). Infinite
        // where no support plane was found: then no pixel is clearly off one.
        let clearance = planes
            .as_ref()
            .filter(|_| masks.attached_parts && masks.keep == KeepRegions::Connected && nearby.is_some())
            .map(|planes| planes.clearance(&view, &voters));
        // The cluster's pixels off the support planes, then (with `keep = "connected"`) only
        // its regions that hold a voter.
        let cut = |labels: &[u32], fg: usize| -> Vec<bool> {
            let mut mask: Vec<bool> = labels.iter().map(|&l| l as usize == fg).collect();
            if let Some(support) = &support {
                mask.iter_mut().zip(support).for_each(|(f, &s)| *f &= !s);
            }
            match masks.keep {
                KeepRegions::All => mask,
                KeepRegions::Connected => {
                    let kept = keep_seeded_regions(&mask, w, h, &voters, continuity);
                    let (Some(parts), Some(depth)) = (&nearby, continuity) else { return kept };
                    let kept = keep_nearby_parts(&mask, kept, w, h, parts, depth);
                    match &clearance {
                        Some(clearance) => {
                            let others: Vec<bool> = labels
                                .iter()
                                .zip(clearance)
                                .map(|(&l, &c)| l as usize != fg && c.is_finite() && c > ATTACHED_PART_CLEARANCE)
                                .collect();
                            keep_attached_parts(&others, kept, w, h, parts, depth)
                        }
                        _ => kept,
                    }
                }
            }
        };
        // Border splits cluster in the space the view's clusters were found in.
        let split_masks = MaskConfig { normalize: clusters.by_direction, ..masks.clone() };
        let (mut labels, mut k) = (clusters.result.labels, clusters.result.k);
        let mut fg = choose(&labels, k);
        let mut foreground = cut(&labels, fg);
        let mut share = border_share(&foreground, w, h);
        for _ in 0..masks.border_splits {
            if share <= masks.max_border_share as f64 {
                break;
            }
            let seed = seed.wrapping_add(k as u64);
            let Some(split) = split_cluster(&labels, k, fg, &r.logits, r.channels, &split_masks, seed) else { break };
            let split_fg = choose(&split, k + 1);
            let split_foreground = cut(&split, split_fg);
            let split_share = border_share(&split_foreground, w, h);
            // A split that does not pull the mask off the border found no object inside it.
            if split_share >= share {
                break;
            }
            (labels, k, fg, foreground, share) = (split, k + 1, split_fg, split_foreground, split_share);
        }
        if masks.keep == KeepRegions::Connected {
            let band = band_pixels(masks.colour_band, w, h);
            foreground = refine_by_colour(&r.rgb, &foreground, band, masks.colour_margin);
        }
        // A view that renders no point at all (every ray empty) shows no object; the
        // clusters of its constant logits would otherwise make all of it foreground.
        if voters.is_empty() {
            foreground.iter_mut().for_each(|f| *f = false);
        }
        let evidence = MaskEvidence {
            labels: &labels,
            foreground_cluster: fg,
            support: support.as_deref(),
            voters: &voters,
            points: &r.points,
        };
        let evidence = Some(evidence_image(&evidence, w, h));
        Ok(match masks.keep {
            KeepRegions::All => ViewMask {
                labels,
                clusters: k,
                foreground_cluster: fg,
                foreground,
                rgb: r.rgb,
                depth: r.depth,
                points: r.points,
                evidence,
            },
            // The labels become the two regions (foreground 1, background 0).
            KeepRegions::Connected => ViewMask {
                labels: foreground.iter().map(|&f| u32::from(f)).collect(),
                clusters: 2,
                foreground_cluster: 1,
                foreground,
                rgb: r.rgb,
                depth: r.depth,
                points: r.points,
                evidence,
            },
        })
    }

    /// The extractor's saliency of a rendered image (of the view `name`), upsampled to its
    /// pixels.
    fn saliency(&self, rgb: &RgbImage, name: &str) -> Result<Vec<f32>, RunError> {
        let extractor = self.extractor.ok_or_else(|| no_saliency(self.session, "no feature extractor is available"))?;
        let features = extractor
            .extract(std::slice::from_ref(rgb))
            .map_err(|source| RunError::Teacher { context: format!("the rendered view {name} (saliency)"), source })?;
        let f = features.first().ok_or_else(|| no_saliency(self.session, "the extractor returned no features"))?;
        let grid = f.saliency.as_ref().ok_or_else(|| {
            no_saliency(self.session, &format!("the extractor `{}` gives no saliency map", extractor.identity()))
        })?;
        if grid.len() != f.width * f.height || grid.is_empty() {
            return Err(no_saliency(self.session, "the extractor's saliency map does not match its grid"));
        }
        Ok(upsample_nearest(grid, f.width, f.height, rgb.width, rgb.height))
    }
}

/// Builds the stage-2 extractor from the config (the `[extractor]` table or the default
/// `cell-stats`), for the `saliency` rule outside stage 2; `None` under the `focus` rule,
/// which needs none.
pub fn saliency_extractor(session: &Session) -> Result<Option<Box<dyn FeatureExtractor>>, RunError> {
    if session.config.masks.foreground != ForegroundRule::Saliency {
        return Ok(None);
    }
    let extractor =
        crate::segment::defaults::build_extractor(session.config.extractor.as_deref(), &session.build_context())?;
    Ok(Some(extractor))
}

fn no_saliency(session: &Session, why: &str) -> RunError {
    RunError::Config(ConfigError::Invalid {
        path: session.config_source.clone(),
        key: "masks.foreground".into(),
        reason: format!(
            "`saliency` needs a teacher saliency map but {why}; set `foreground = \"focus\"` or choose an \
             extractor with saliency"
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::normalize;
    use crate::render::composite::EMPTY_RAY_DEPTH;

    #[test]
    fn the_depth_image_is_bright_near_and_black_where_rays_are_empty() {
        let mut mask = ViewMask::new(vec![0; 5], 1, 0, RgbImage::new(5, 1));
        assert!(mask.depth_image().is_none(), "no depth rendered, no image");
        mask.depth = vec![1.0, 2.0, EMPTY_RAY_DEPTH, 4.0, f32::NAN];
        let img = mask.depth_image().unwrap();
        assert_eq!((img.width, img.height), (5, 1));
        let v = &img.data;
        assert!(v[0] > v[1] && v[1] > v[3] && v[3] > 0.0, "{v:?}");
        assert_eq!((v[0], v[3]), (1.0, 0.05), "the extremes span the range");
        assert_eq!((v[2], v[4]), (0.0, 0.0), "empty and non-finite rays are black");
    }

    #[test]
    fn saliency_picks_the_more_salient_cluster() {
        // Two clusters: left half label 1, right half label 0; saliency high on the left.
        let (w, h) = (8, 4);
        let labels: Vec<u32> = (0..w * h).map(|i| u32::from(i % w < w / 2)).collect();
        let grid = [0.9, 0.1, 0.8, 0.2]; // 2x2 grid, coarse
        let saliency = upsample_nearest(&grid, 2, 2, w, h);
        assert_eq!(saliency.len(), w * h);
        assert_eq!(foreground_by_saliency(&labels, 2, &saliency), 1);
        // Swapping the saliency swaps the choice.
        let flipped: Vec<f32> = saliency.iter().map(|s| 1.0 - s).collect();
        assert_eq!(foreground_by_saliency(&labels, 2, &flipped), 0);
    }

    #[test]
    fn focus_ignores_empty_rays_and_picks_the_nearer_cluster() {
        let labels = vec![0, 0, 1, 1, 1];
        let points = vec![Some([5.0, 0.0, 0.0]), None, Some([0.1, 0.0, 0.0]), Some([0.0, 0.2, 0.0]), None];
        assert_eq!(foreground_by_focus(&labels, 2, &points, [0.0; 3]), 1);
        // A cluster of only empty rays is background.
        let points = vec![None, None, Some([9.0, 0.0, 0.0]), Some([9.0, 0.0, 0.0]), None];
        assert_eq!(foreground_by_focus(&labels, 2, &points, [0.0; 3]), 1);
    }

    #[test]
    fn focus_prefers_the_cluster_containing_the_object_over_the_ground_around_it() {
        // Cluster 1: the object (10 points at 0.5 from the focus) plus 90 far wall points.
        // Cluster 0: 100 ground points at 1.0 from the focus. The mean distance favours the
        // ground; the nearest pixels belong to the object.
        let mut labels = Vec::new();
        let mut points = Vec::new();
        for i in 0..100 {
            labels.push(1);
            points.push(Some(if i < 10 { [0.5, 0.0, 0.0] } else { [6.0, 0.0, 0.0] }));
            labels.push(0);
            points.push(Some([0.0, -1.0, 0.0]));
        }
        assert_eq!(foreground_by_focus(&labels, 2, &points, [0.0; 3]), 1);
    }

    #[test]
    fn kmeans_masks_recover_a_square_from_noisy_logits() {
        // 20x20 logits: a square of high "object" logit on a background, with small noise.
        let (w, h) = (20, 20);
        let inside = |i: usize| (5..12).contains(&(i % w)) && (6..14).contains(&(i / w));
        let mut logits = Vec::new();
        for i in 0..w * h {
            let noise = ((i * 7919) % 97) as f32 / 97.0 * 0.2 - 0.1;
            let (a, b) = if inside(i) { (-1.0, 2.0) } else { (1.5, -0.5) };
            logits.extend([a + noise, b - noise]);
        }
        // Saliency is higher on the square.
        let saliency: Vec<f32> = (0..w * h).map(|i| if inside(i) { 0.7 } else { 0.2 }).collect();
        for (softmax, normalize) in [(false, false), (true, false), (false, true)] {
            let masks = MaskConfig {
                clusters: 2,
                restarts: 3,
                softmax,
                normalize,
                foreground: ForegroundRule::Saliency,
                keep: KeepRegions::All,
                ..MaskConfig::default()
            };
            let km = cluster_logits(&logits, 2, &masks, 0).unwrap();
            assert_eq!(km.k, 2);
            let fg = foreground_by_saliency(&km.labels, km.k, &saliency);
            let mask = ViewMask::new(km.labels.clone(), km.k, fg, RgbImage::new(w, h));
            for (i, &f) in mask.foreground.iter().enumerate() {
                assert_eq!(f, inside(i), "pixel {i} (softmax {softmax})");
            }
            let img = mask.mask_image();
            assert_eq!(img.data.iter().filter(|&&v| v == 1.0).count(), 7 * 8);
            let overlay = mask.overlay();
            assert!(overlay.pixel(6, 7)[0] > 0.4 && overlay.pixel(0, 0) == [0.0; 3]);
        }
    }

    #[test]
    fn normalized_clustering_follows_direction_not_length() {
        // Object pixels point along +x with length 1; background along +y with lengths 1..20.
        // By position, lengths split the background; by direction, object and background part.
        let mut logits = Vec::new();
        for i in 0..60 {
            if i < 20 {
                logits.extend([1.0f32, 0.05 * (i % 3) as f32]);
            } else {
                logits.extend([0.05 * (i % 3) as f32, 1.0 + (i - 20) as f32 * 0.5]);
            }
        }
        let split = |normalize: bool| {
            let masks = MaskConfig { normalize, ..MaskConfig::default() };
            let labels = cluster_logits(&logits, 2, &masks, 0).unwrap().labels;
            labels.iter().skip(1).take(19).all(|&l| l == labels[0]) && labels[20..].iter().all(|&l| l != labels[0])
        };
        assert!(split(true));
        assert!(!split(false));
    }

    /// A camera at (0, 1.2, 2.5) looking at the origin over the ground y = 0, with two boxes
    /// standing side by side at x = ±0.45.
    fn group_on_the_ground(width: usize, height: usize) -> (Vec<Option<Vec3>>, Vec<bool>, Vec3) {
        let origin = [0.0f32, 1.2, 2.5];
        let forward = normalize(sub([0.0; 3], origin));
        let right = normalize(crate::camera::cross(forward, [0.0, 1.0, 0.0]));
        let up = crate::camera::cross(right, forward);
        let boxes = [-0.45f32, 0.45].map(|cx| [[cx - 0.2, 0.0, -0.2], [cx + 0.2, 0.4, 0.2]]);
        let (points, object) =
            crate::segment::support_plane::test_view::boxes_on_the_ground(origin, width, height, &boxes, |x, y| {
                let (x, y) = (x * 0.6, y * 0.45);
                normalize([0, 1, 2].map(|k| forward[k] + x * right[k] + y * up[k]))
            });
        (points, object, origin)
    }

    #[test]
    fn a_focus_on_the_ground_between_a_group_votes_with_what_stands_there() {
        let (w, h) = (96, 72);
        let (points, object, origin) = group_on_the_ground(w, h);
        let focus = [0.0; 3];
        let voters = focus_voters(&points, focus);
        assert!(voters.iter().all(|&i| !object[i]), "the nearest pixels are the ground's");
        let view = ViewPoints { points: &points, origin, width: w, height: h };
        let planes = PlaneCandidates::find(&view, 3);
        let standing = standing_voters(&points, &voters, &planes, focus, 1.0).expect("voters move off the ground");
        assert!(!standing.is_empty() && standing.iter().all(|&i| object[i]), "the boxes' pixels vote");
        // With the ground no longer holding the voters, it is a support.
        let support = planes.supports(&standing);
        let ground = (0..w * h).filter(|&i| points[i].is_some() && !object[i]).count();
        let dropped = (0..w * h).filter(|&i| support[i] && !object[i]).count();
        assert!(dropped as f64 > 0.95 * ground as f64, "{dropped} of {ground} ground pixels dropped");
        // Nothing stands within the radius: the voters stay.
        assert_eq!(standing_voters(&points, &voters, &planes, focus, 0.05), None);
        // Voters off the planes already: nothing to change.
        assert_eq!(standing_voters(&points, &standing, &planes, focus, 1.0), None);
    }

    #[test]
    fn softmax_rows_sum_to_one() {
        let s = softmax_rows(&[1000.0, 0.0, -1.0, 1.0], 2);
        assert!((s[0] - 1.0).abs() < 1e-6 && s[1] < 1e-6);
        assert!((s[2] + s[3] - 1.0).abs() < 1e-6 && s[3] > s[2]);
    }

    #[test]
    fn forward_facing_focus_uses_the_central_median_depth() {
        let target = FocusTarget::Axis { origin: [0.0, 0.0, 0.0], direction: [0.0, 0.0, -1.0] };
        // 10x10 depths: 2 everywhere, 4 in the central 2x2 window, empty in one central pixel.
        let mut depth = vec![2.0; 100];
        for r in 4..6 {
            for c in 4..6 {
                depth[r * 10 + c] = 4.0;
            }
        }
        depth[44] = EMPTY_RAY_DEPTH;
        assert_eq!(target.point_for(&depth, 10, 10), Some([0.0, 0.0, -4.0]));
        let empty = vec![EMPTY_RAY_DEPTH; 100];
        assert_eq!(target.point_for(&empty, 10, 10), None);
    }
}
