//! The root configuration of a run, read from TOML. Plugin sections are chosen by their
//! `kind`; every section rejects unknown keys, so a typo is an error naming the key.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::ConfigError;
use crate::plugin::{
    ContrastiveLossConfig, DatasetConfig, FeatureExtractorConfig, PairMinerConfig, RadianceFieldConfig,
};

/// Everything a run needs.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunConfig {
    /// Name of the run; outputs go to `<output_dir>/<name>/`.
    #[serde(default = "default_name")]
    pub name: String,
    /// Folder for run outputs, relative to the config file.
    #[serde(default = "default_output_dir")]
    pub output_dir: PathBuf,
    /// Seed of every random choice (sampling, initialisation, k-means).
    #[serde(default)]
    pub seed: u64,
    /// The scene: `kind` = a registered dataset adapter.
    pub scene: Box<dyn DatasetConfig>,
    /// The radiance field: `kind` = a registered field (default `voxel-grid`).
    #[serde(default = "crate::segment::defaults::field")]
    pub field: Box<dyn RadianceFieldConfig>,
    /// Stage 1: photometric training.
    #[serde(default)]
    pub train: TrainConfig,
    /// Rendering of held-out views and camera paths.
    #[serde(default)]
    pub render: RenderConfig,
    /// Stage 2: training the segmentation head.
    #[serde(default)]
    pub segment: SegmentConfig,
    /// The segmentation head attached to the field.
    #[serde(default)]
    pub head: HeadConfig,
    /// The 2D teacher (`kind` = a registered extractor; default `cell-stats`).
    #[serde(default)]
    pub extractor: Option<Box<dyn FeatureExtractorConfig>>,
    /// Negative-pair mining (`kind` = a registered miner; default `cls-cosine`).
    #[serde(default)]
    pub miner: Option<Box<dyn PairMinerConfig>>,
    /// Contrastive loss terms, each with its weight (default: appearance 1.0, geometry 0.01).
    #[serde(default)]
    pub loss: Vec<LossEntry>,
    /// Mask inference: clustering and the foreground rule.
    #[serde(default)]
    pub masks: MaskConfig,
}

/// One `[[loss]]` entry: a contrastive loss and the weight the trainer gives it.
#[derive(Debug, Serialize, Deserialize)]
pub struct LossEntry {
    /// Weight of this term in the total loss (the trainer is the only place that weights).
    pub weight: f32,
    /// The loss (`kind` and its own settings).
    #[serde(flatten)]
    pub loss: Box<dyn ContrastiveLossConfig>,
}

/// Where the teacher's input images come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TeacherSource {
    /// The field's rendered colour of the patch (the reference's choice).
    Rendered,
    /// The captured photograph at the patch's pixels.
    Captured,
}

/// Stage-2 settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentConfig {
    /// Optimisation steps of the head (0 skips stage 2).
    pub steps: usize,
    /// Patches per step, each from a different training view.
    pub patches: usize,
    /// Rays per patch side.
    pub patch_size: u32,
    /// Pixels between neighbouring rays of a patch (reduced, with a notice, for small images).
    pub stride: u32,
    /// Pixels between the allowed patch offsets: a patch's top-left corner lies on multiples
    /// of this (or at the far edge), so placements recur and the teacher-feature cache hits.
    /// 0 or 1 = any pixel (the reference's random crops).
    pub offset_grid: u32,
    /// Adam learning rate of the head.
    pub lr: f32,
    /// Learning-rate factor at the last step (exponential decay).
    pub final_lr_factor: f32,
    /// Evaluate the head only at samples whose compositing weight exceeds this (the density
    /// is frozen in stage 2, so skipped samples contribute at most this much); 0 disables.
    pub weight_threshold: f32,
    /// Frozen renders (stage 2 and mask inference) stop a ray once its transmittance falls
    /// below this, whatever `train.early_stop` says (a reference stage 1 marches every ray to
    /// its end; a frozen field's colour then changes by at most this much); 0 disables.
    pub early_stop: f32,
    /// Frozen renders of a hierarchical (coarse + fine) field place their samples with its
    /// proposal network, as stage 1 does. Off by default: the fine network alone marches the
    /// occupancy-skipped candidates, several times fewer network evaluations for masks of the
    /// same quality (`benchmarks/RESULTS.md`, reference NeRF stage 2). Other fields ignore it.
    pub proposal: bool,
    /// Teacher input: rendered patches or captured photographs.
    pub teacher_source: TeacherSource,
    /// Reuse teacher features of identical patches while the field is frozen.
    pub cache_teacher: bool,
    /// Weight of the photometric loss on the patch rays; above 0 the field is trained jointly
    /// with the head (an ablation; the paper freezes it).
    pub photometric_weight: f32,
    /// Stop before `steps` once the masks settle: every `check_every` steps the masks of a few
    /// training views are decided at a small size, and when at most `stable_change` of their
    /// pixels flipped (away from the outlines) at two checks in a row, stage 2 ends
    /// ([`crate::segment::stability`]). Needs no ground truth. Off by default: the masks
    /// settle before their outlines are refined (the main job settles at about a third of its
    /// steps, 0.01 mIoU short of the full run).
    pub stop_when_stable: bool,
    /// Largest share of probe pixels whose mask may flip between two checks for the masks to
    /// count as settled.
    pub stable_change: f32,
    /// Steps between two stability checks.
    pub check_every: usize,
    /// Where the head is trained: once per ray at its visible surface (the median depth's
    /// point) times the ray's opacity (the default), or over every sample above
    /// `weight_threshold`, its logits composited with the colour's weights (the paper's).
    /// Joint training (`photometric_weight > 0`) needs composited logits: the surface logits
    /// give the field no gradient.
    pub logits: LogitSource,
}

impl Default for SegmentConfig {
    fn default() -> Self {
        SegmentConfig {
            steps: 100,
            patches: 8,
            patch_size: 64,
            stride: 6,
            // 44 placements per 400x300 view with 64 rays at stride 4, 65 per 504x378 one.
            offset_grid: 16,
            lr: 1e-3,
            final_lr_factor: 0.3,
            weight_threshold: 1e-3,
            early_stop: 1e-4,
            proposal: false,
            teacher_source: TeacherSource::Rendered,
            cache_teacher: true,
            photometric_weight: 0.0,
            stop_when_stable: false,
            stable_change: 0.002,
            check_every: 10,
            // The head once per ray at its visible surface rather than over every sample
            // above the threshold: stage 2 1.9x faster and views twice as fast on the main
            // job, mIoU within 0.01 of composited logits on every quick-profile scene
            // (benchmarks/RESULTS.md, "Head logits at the surface").
            logits: LogitSource::Surface,
        }
    }
}

/// The segmentation head: an MLP from the field's per-sample segmentation input to logits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HeadConfig {
    /// Hidden layer widths (the reference: `[128]`; the paper's four layers: `[256, 256, 128]`).
    pub hidden: Vec<usize>,
    /// Logit channels (the reference: 2).
    pub outputs: usize,
}

impl Default for HeadConfig {
    fn default() -> Self {
        HeadConfig { hidden: vec![128], outputs: 2 }
    }
}

/// How the foreground cluster is chosen among the k-means clusters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ForegroundRule {
    /// The cluster with the higher mean teacher saliency (DINO's \[CLS\] attention, as the
    /// reference does, or the weight-free extractor's colour distinctness).
    Saliency,
    /// The cluster whose rendered 3D points lie nearer the point the training cameras look at.
    Focus,
}

/// Mask inference settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskConfig {
    /// Number of k-means clusters (the reference: 2).
    pub clusters: usize,
    /// k-means restarts (k-means++ initialisation each).
    pub restarts: usize,
    /// Apply a softmax to the logits before clustering (the reference run does not).
    pub softmax: bool,
    /// Scale each pixel's logits to unit length before clustering. The contrastive losses
    /// compare logits by direction only (cosine, or the kernel on normalised logits), so their
    /// length carries no trained meaning; the reference clusters raw logits (`false`).
    pub normalize: bool,
    /// With raw logits (`normalize` and `softmax` off): cluster each view's logits by
    /// direction instead where the raw clusters cut across the directions, explaining less
    /// than half of what clustering the directions explains of their variance
    /// ([`crate::segment::cluster_space`]).
    pub direction_check: bool,
    /// Rule that names the foreground cluster.
    pub foreground: ForegroundRule,
    /// Which regions of the foreground cluster make the mask (see [`KeepRegions`]).
    pub keep: KeepRegions,
    /// With `keep = "connected"`: the largest relative step of rendered depth between
    /// neighbouring pixels of one region, so that background touching the object's silhouette
    /// in the image is not connected to it; 0 = image connectivity alone.
    pub max_depth_jump: f32,
    /// Return the pixels on large planes the object stands on or in front of (the ground, a
    /// wall: [`crate::segment::support_plane`]) to the background before regions are kept.
    pub drop_support_planes: bool,
    /// Times the foreground cluster may be split again when the mask covers more than
    /// `max_border_share` of the image border ([`crate::segment::border_split`]); 0 = never.
    pub border_splits: usize,
    /// Largest share of the image border's pixels a mask may cover before its cluster is split
    /// again (objects rarely run along most of the frame's edge; ground, walls and sky do).
    pub max_border_share: f32,
    /// Orbit rigs: regions of the foreground cluster that hold no focus voter are kept too
    /// when they come within this fraction of the nearest training camera's distance from the
    /// focus and stand in front of what surrounds them
    /// ([`crate::segment::cleanup::keep_nearby_parts`]): the other members of a group of
    /// objects. 0 = keep only the voters' regions.
    pub nearby_parts: f32,
    /// Share of a nearby region's outline at which the rendered depth must step back (by more
    /// than `max_depth_jump`) for the region to count as standing: a patch of ground does not.
    pub min_standing_outline: f32,
    /// Orbit rigs, where a support plane was found: regions of the other clusters that lie
    /// clearly off the support planes, touch the mask and come within `nearby_parts` of the
    /// focus join it ([`crate::segment::cleanup::keep_attached_parts`]): a dark base that
    /// clustered with the ground it stands on.
    pub attached_parts: bool,
    /// With `keep = "connected"`: the pixels within this fraction of the view's diagonal of
    /// the mask's outline go to the side (mask or background) whose colour histogram explains
    /// the rendered colours around them better ([`crate::segment::colour_refine`]): an outline that
    /// strayed onto a differently coloured neighbour comes back, stripes of the object's
    /// colours that the clusters left out join. 0 = off.
    pub colour_band: f32,
    /// Log-likelihood ratio of its colours (averaged over its 3x3 neighbourhood), mask against
    /// background, that a pixel in the `colour_band` needs to be in the mask (0: the likelier side wins; higher keeps colours
    /// the two sides share out of the mask).
    pub colour_margin: f32,
    /// Which rendered distance places a pixel's 3D point for the mask rules (focus votes,
    /// support planes, depth continuity).
    pub depth: MaskDepth,
    /// Compositing weight at or below which a sample's logits are left out of a rendered view;
    /// unset: `segment.weight_threshold`, the samples the head was trained on. A higher value
    /// evaluates the head only near the surface: fewer samples per ray, so faster views.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub head_min_weight: Option<f32>,
    /// Where a rendered view's logits come from; unset: as stage 2 trained the head
    /// (`segment.logits`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub logits: Option<LogitSource>,
}

/// How per-pixel logits are formed from the head: in stage 2 (`segment.logits`) and in a
/// rendered view (`masks.logits`, [`crate::segment::infer::render_logits`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LogitSource {
    /// The head over every sample above `head_min_weight`, composited with the colour's
    /// weights: what stage 2 trains (the paper's).
    Composited,
    /// The head once per ray, at the point `depth` places the pixel at, times the ray's
    /// opacity: the composited sum when the weight sits on one surface, for one head
    /// evaluation per ray instead of dozens.
    Surface,
}

/// The rendered distance the mask rules place pixels at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskDepth {
    /// Where the ray's opacity reaches one half: the visible surface, which semi-transparent
    /// fog in front of it does not move.
    Median,
    /// The compositing weights' expected distance `Σ w t` (the reference's depth map), which
    /// fog and partly opaque rays pull towards the camera.
    Expected,
}

/// Which connected regions of the foreground cluster are kept in the mask.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KeepRegions {
    /// Every pixel of the cluster (the reference).
    All,
    /// Only the 4-connected regions holding a pixel that the `focus` rule counts as the
    /// object's (nearest the focus point); NV-ARI then scores these two regions.
    Connected,
}

impl Default for MaskConfig {
    fn default() -> Self {
        MaskConfig {
            clusters: 2,
            restarts: 10,
            softmax: false,
            normalize: false,
            // Random worlds whose raw clusters split a view by logit length (a room's middle
            // from its corners, near ground from far): worlds 08 and 06 0.309 -> 0.732 and
            // 0.500 -> 0.576 mIoU from the same heads; no other benchmark scene moves by more
            // than 0.005 (RESULTS.md, "Clustering by direction").
            direction_check: true,
            foreground: ForegroundRule::Focus,
            keep: KeepRegions::Connected,
            // 5% rather than 10%: floaters just above the object and strands of wall that touch
            // its silhouette are cut off (mIoU +0.015 on the object-centric rig and its Blender
            // copy, +0.009 forward-facing, -0.008 on the 100x75 NeRF++ rig; RESULTS.md, "Mask
            // cleanup").
            max_depth_jump: 0.05,
            drop_support_planes: true,
            border_splits: 2,
            // An object running along one whole long side of a 4:3 frame covers 0.29 of its
            // border; a mask along more than that has background in it.
            max_border_share: 0.3,
            // Distractors stand outside the cameras' path, the object's parts well inside it.
            nearby_parts: 0.25,
            // A part standing on the ground steps back along its top and sides, not its base.
            min_standing_outline: 0.45,
            // A dark pedestal clusters with its ground: unbounded rig and its Blender and
            // COLMAP copies +0.018 to +0.034 mIoU, no scene of the quick, timed, bare or
            // random-world profiles lower (masks from the same heads; RESULTS.md, "Mask
            // cleanup").
            attached_parts: true,
            // From the masks of 23 default benchmark runs (bare rigs and layouts, the timed
            // rigs, flower, the twelve random worlds), evidence averaged over 3x3 pixels: a
            // band of 1.5% of the diagonal lifts the random worlds' mean mIoU 0.825 -> 0.846 and
            // the others' 0.955 -> 0.975, two scenes lower by more than 0.005 (at most 0.010);
            // 2.5% gains a little more with six lower (benchmarks/RESULTS.md, "Colour at the
            // mask's outline").
            colour_band: 0.015,
            colour_margin: 0.5,
            depth: MaskDepth::Median,
            head_min_weight: None,
            logits: None,
        }
    }
}

fn default_name() -> String {
    "run".into()
}

fn default_output_dir() -> PathBuf {
    PathBuf::from("runs")
}

/// Stage-1 (photometric) training settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimisation steps.
    pub steps: usize,
    /// Random rays per step (drawn from all training views). 2048 by default: on the random
    /// worlds it gives the masks of 4096 at about two thirds of the stage-1 time (the
    /// `stage1-rays` sweep; `benchmarks/RESULTS.md`).
    pub rays_per_step: usize,
    /// Learning-rate factor at the last step (exponential decay from 1).
    pub final_lr_factor: f32,
    /// Candidate samples per ray across the scene extent (before skipping).
    pub samples_per_ray: usize,
    /// Stop marching a ray once its transmittance is below this; 0 disables.
    pub early_stop: f32,
    /// Weight of the per-sample colour loss `Σ_k w_k ‖c_k − C‖²` (DVGO's `rgbper`), which
    /// clears semi-transparent fog quickly; 0 disables. `sample_color_weight` is accepted too.
    #[serde(alias = "sample_color_weight")]
    pub sample_colour_weight: f32,
    /// Weight of mip-NeRF 360's distortion loss over the marched samples
    /// (`crate::render::distortion`), which favours weight gathered in one thin interval over
    /// spread-out fog; 0 disables. Off by default: on a box that holds the cameras but cuts
    /// the scene it did not lift the held-out PSNR (see the face-pile-up warning instead).
    pub distortion_weight: f32,
    /// Skip colour and gradients of samples whose compositing weight (from a density-only
    /// pass) is at most this (DVGO's fast colour threshold); 0 keeps every sample.
    pub weight_threshold: f32,
    /// Use the occupancy grid to skip empty space.
    pub occupancy: bool,
    /// Occupancy cells per side.
    pub occupancy_resolution: usize,
    /// Re-probe the occupancy grid every this many steps.
    pub occupancy_every: usize,
    /// Opacity over one candidate interval below which a cell counts as empty.
    pub occupancy_alpha: f32,
    /// Steps before empty-space skipping starts.
    pub occupancy_warmup: usize,
    /// Write a checkpoint every this many steps (and at the end); 0 = only at the end.
    pub checkpoint_every: usize,
    /// Stop before `steps` once the training loss levels off: when the PSNR of the mean loss
    /// over each `converged_window` steps rose by less than `converged_gain` dB, two windows
    /// in a row, after the field reached its full detail ([`crate::train::convergence`]).
    /// Needs no held-out views. Off by default: the learning rate decays over `steps`, so a
    /// run stopped early ends at a higher rate than a run of its length would.
    pub stop_when_converged: bool,
    /// Smallest rise (dB) of the windowed training PSNR that still counts as progress.
    pub converged_gain: f32,
    /// Steps per window of the convergence test.
    pub converged_window: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            steps: 3000,
            rays_per_step: 2048,
            final_lr_factor: 0.1,
            samples_per_ray: 256,
            early_stop: 1e-4,
            sample_colour_weight: 0.1,
            distortion_weight: 0.0,
            weight_threshold: 1e-4,
            occupancy: true,
            occupancy_resolution: 128,
            occupancy_every: 8,
            occupancy_alpha: 1e-3,
            occupancy_warmup: 64,
            checkpoint_every: 1000,
            stop_when_converged: false,
            converged_gain: 0.05,
            converged_window: 100,
        }
    }
}

/// Rendering settings for evaluation, `sos render` and camera paths.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderConfig {
    /// Rays rendered at once.
    pub chunk: usize,
    /// Write every held-out view's renders when training ends (colour; after stage 2 also
    /// masks and overlays). The metrics are measured either way.
    pub test_views: bool,
    /// Render the scene's novel camera path when training ends (`sos train`, `sos segment`):
    /// colour frames, and after stage 2 their masks and overlays, as `sos render` does.
    pub camera_path: bool,
    /// GiB that frozen renders and the segmentation head may keep between passes (see
    /// [`MemoryBudget`](crate::render::memory_budget::MemoryBudget)); a smaller budget costs time,
    /// not results. Unset: derived from the machine's memory.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub memory_gib: Option<f64>,
    /// Candidate samples per ray across the extent in frozen renders (views, masks, stage 2),
    /// scaled down while a grid is coarse as in training. Unset: one per cell along the
    /// field's finest grid axis, at most `train.samples_per_ray` (fields without a grid:
    /// `train.samples_per_ray`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub samples_per_ray: Option<usize>,
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig { chunk: 16384, test_views: true, camera_path: false, memory_gib: None, samples_per_ray: None }
    }
}

/// Upper bounds of the counts that drive loops and allocations: far above any useful setting,
/// low enough that a typo (`1e9`) is refused at once instead of hanging the run or failing
/// to allocate.
pub const MAX_STEPS: usize = 10_000_000;
/// Largest `segment.stride`: a 256-ray patch at this stride spans a million pixels.
pub const MAX_STRIDE: u32 = 4096;
/// Upper bound of `train.rays_per_step` (a step's buffers grow with rays x samples).
pub const MAX_RAYS_PER_STEP: usize = 1 << 20;
/// Upper bound of `train.samples_per_ray`.
pub const MAX_SAMPLES_PER_RAY: usize = 4096;
/// Upper bound of `segment.patches` per step.
pub const MAX_PATCHES: usize = 1024;
/// Upper bound of `masks.restarts` (each restart is a full k-means of every pixel).
pub const MAX_RESTARTS: usize = 1000;
/// Upper bound of the head's layer widths.
pub const MAX_HEAD_WIDTH: usize = 4096;
/// Upper bound of the head's hidden layers.
pub const MAX_HEAD_LAYERS: usize = 32;
/// Upper bound of `render.chunk` (rays rendered together).
pub const MAX_CHUNK: usize = 1 << 22;

/// The dotted key and value of the first NaN or infinite float in `table` (arrays index as
/// `key[i]`), searched in key order.
fn first_non_finite(table: &toml::Table, prefix: &str) -> Option<(String, f64)> {
    fn walk(value: &toml::Value, key: String) -> Option<(String, f64)> {
        match value {
            toml::Value::Float(f) if !f.is_finite() => Some((key, *f)),
            toml::Value::Table(t) => first_non_finite(t, &key),
            toml::Value::Array(items) => items.iter().enumerate().find_map(|(i, v)| walk(v, format!("{key}[{i}]"))),
            _ => None,
        }
    }
    table.iter().find_map(|(k, v)| walk(v, if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") }))
}

impl RunConfig {
    /// Reads and validates a config file.
    pub fn load(path: &Path) -> Result<RunConfig, ConfigError> {
        let text =
            std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_path_buf(), source })?;
        RunConfig::parse(&text, path)
    }

    /// Parses config text; `path` is only used in messages.
    pub fn parse(text: &str, path: &Path) -> Result<RunConfig, ConfigError> {
        let parse_error = |e: toml::de::Error| ConfigError::Parse { path: path.to_path_buf(), message: e.to_string() };
        let table: toml::Table = toml::from_str(text).map_err(parse_error)?;
        // Every number of every section and plugin table is a size, a weight, a distance or a
        // rate: none means anything as NaN or infinity, and each would train nonsense quietly.
        if let Some((key, value)) = first_non_finite(&table, "") {
            return Err(ConfigError::Invalid {
                path: path.to_path_buf(),
                key,
                reason: format!("must be a finite number, not {value}"),
            });
        }
        let cfg: RunConfig = toml::from_str(text).map_err(parse_error)?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Checks ranges the types cannot express.
    pub fn validate(&self, path: &Path) -> Result<(), ConfigError> {
        let invalid = |key: &str, reason: &str| ConfigError::Invalid {
            path: path.to_path_buf(),
            key: key.into(),
            reason: reason.into(),
        };
        let t = &self.train;
        if !(1..=MAX_RAYS_PER_STEP).contains(&t.rays_per_step) {
            return Err(invalid("train.rays_per_step", &format!("must be in 1..={MAX_RAYS_PER_STEP}")));
        }
        if !(2..=MAX_SAMPLES_PER_RAY).contains(&t.samples_per_ray) {
            return Err(invalid("train.samples_per_ray", &format!("must be in 2..={MAX_SAMPLES_PER_RAY}")));
        }
        if t.steps > MAX_STEPS {
            return Err(invalid("train.steps", &format!("must be at most {MAX_STEPS}")));
        }
        if !(t.final_lr_factor > 0.0 && t.final_lr_factor <= 1.0) {
            return Err(invalid("train.final_lr_factor", "must be in (0, 1]"));
        }
        if !(0.0..1.0).contains(&t.early_stop) {
            return Err(invalid("train.early_stop", "must be in [0, 1)"));
        }
        if !(t.sample_colour_weight >= 0.0 && t.sample_colour_weight.is_finite()) {
            return Err(invalid("train.sample_colour_weight", "must be zero or positive"));
        }
        if !(t.distortion_weight >= 0.0 && t.distortion_weight.is_finite()) {
            return Err(invalid("train.distortion_weight", "must be zero or positive"));
        }
        if !(0.0..1.0).contains(&t.weight_threshold) {
            return Err(invalid("train.weight_threshold", "must be in [0, 1)"));
        }
        if t.occupancy && !(8..=512).contains(&t.occupancy_resolution) {
            return Err(invalid("train.occupancy_resolution", "must be in 8..=512"));
        }
        if t.occupancy_every == 0 {
            return Err(invalid("train.occupancy_every", "must be at least 1"));
        }
        if !(t.occupancy_alpha >= 0.0 && t.occupancy_alpha < 1.0) {
            return Err(invalid("train.occupancy_alpha", "must be in [0, 1)"));
        }
        if !t.converged_gain.is_finite() {
            return Err(invalid("train.converged_gain", "must be a finite number of dB"));
        }
        if t.stop_when_converged && t.converged_window == 0 {
            return Err(invalid("train.converged_window", "must be at least 1 with `stop_when_converged = true`"));
        }
        let g = &self.segment;
        if g.steps > MAX_STEPS {
            return Err(invalid("segment.steps", &format!("must be at most {MAX_STEPS}")));
        }
        // Mask inference of a checkpoint's head reads it too, whatever `steps` says.
        if !(0.0..1.0).contains(&g.weight_threshold) {
            return Err(invalid("segment.weight_threshold", "must be in [0, 1)"));
        }
        if !(0.0..1.0).contains(&g.early_stop) {
            return Err(invalid("segment.early_stop", "must be in [0, 1)"));
        }
        if g.steps > 0 {
            // A patch's negatives are the other patches of its step: one alone has none.
            if !(2..=MAX_PATCHES).contains(&g.patches) {
                return Err(invalid("segment.patches", &format!("must be in 2..={MAX_PATCHES}")));
            }
            if !(2..=256).contains(&g.patch_size) {
                return Err(invalid("segment.patch_size", "must be in 2..=256"));
            }
            // Wider than any view: a patch of 256 rays at this stride spans a million pixels.
            if !(1..=MAX_STRIDE).contains(&g.stride) {
                return Err(invalid("segment.stride", &format!("must be in 1..={MAX_STRIDE}")));
            }
            if !(g.lr > 0.0 && g.lr.is_finite()) {
                return Err(invalid("segment.lr", "must be a positive number"));
            }
            if !(g.final_lr_factor > 0.0 && g.final_lr_factor <= 1.0) {
                return Err(invalid("segment.final_lr_factor", "must be in (0, 1]"));
            }
            if !(g.photometric_weight >= 0.0 && g.photometric_weight.is_finite()) {
                return Err(invalid("segment.photometric_weight", "must be zero or positive"));
            }
            if g.photometric_weight > 0.0 && g.logits == LogitSource::Surface {
                return Err(invalid(
                    "segment.logits",
                    "joint training (`photometric_weight` above 0) needs `logits = \"composited\"`; `surface` \
                     trains a frozen field's head only",
                ));
            }
            if !(0.0..=1.0).contains(&g.stable_change) {
                return Err(invalid("segment.stable_change", "must be a share in [0, 1]"));
            }
            if g.stop_when_stable && g.check_every == 0 {
                return Err(invalid("segment.check_every", "must be at least 1 with `stop_when_stable = true`"));
            }
        }
        if self.head.hidden.contains(&0) {
            return Err(invalid("head.hidden", "every width must be at least 1"));
        }
        // The losses normalise each sample's logits over the channels: one channel normalises
        // to a constant, whose gradient is zero, and the head would never learn.
        if self.head.outputs < 2 {
            return Err(invalid("head.outputs", "must be at least 2"));
        }
        if self.head.outputs > MAX_HEAD_WIDTH {
            return Err(invalid("head.outputs", &format!("must be at most {MAX_HEAD_WIDTH}")));
        }
        if self.head.hidden.iter().any(|&w| w > MAX_HEAD_WIDTH) {
            return Err(invalid("head.hidden", &format!("every width must be at most {MAX_HEAD_WIDTH}")));
        }
        if self.head.hidden.len() > MAX_HEAD_LAYERS {
            return Err(invalid("head.hidden", &format!("at most {MAX_HEAD_LAYERS} hidden layers")));
        }
        if !(2..=16).contains(&self.masks.clusters) {
            return Err(invalid("masks.clusters", "must be in 2..=16"));
        }
        if !(1..=MAX_RESTARTS).contains(&self.masks.restarts) {
            return Err(invalid("masks.restarts", &format!("must be in 1..={MAX_RESTARTS}")));
        }
        if !(self.masks.max_depth_jump >= 0.0 && self.masks.max_depth_jump.is_finite()) {
            return Err(invalid("masks.max_depth_jump", "must be zero (off) or positive, e.g. 0.1"));
        }
        if self.masks.border_splits > 8 {
            return Err(invalid("masks.border_splits", "must be at most 8"));
        }
        if !(self.masks.max_border_share > 0.0 && self.masks.max_border_share <= 1.0) {
            return Err(invalid("masks.max_border_share", "must be in (0, 1], e.g. 0.3"));
        }
        if !(self.masks.nearby_parts >= 0.0 && self.masks.nearby_parts <= 1.0) {
            return Err(invalid("masks.nearby_parts", "must be in [0, 1] (0 = off), e.g. 0.25"));
        }
        if !(self.masks.min_standing_outline >= 0.0 && self.masks.min_standing_outline <= 1.0) {
            return Err(invalid("masks.min_standing_outline", "must be in [0, 1], e.g. 0.45"));
        }
        if !(0.0..=1.0).contains(&self.masks.colour_band) {
            return Err(invalid("masks.colour_band", "must be in [0, 1] (0 = off), e.g. 0.015"));
        }
        if !self.masks.colour_margin.is_finite() {
            return Err(invalid("masks.colour_margin", "must be a finite number, e.g. 1"));
        }
        if self.masks.head_min_weight.is_some_and(|w| !(0.0..1.0).contains(&w)) {
            return Err(invalid("masks.head_min_weight", "must be in [0, 1), e.g. 0.01"));
        }
        for (i, l) in self.loss.iter().enumerate() {
            if !(l.weight >= 0.0 && l.weight.is_finite()) {
                return Err(invalid(&format!("loss[{i}].weight"), "must be zero or positive"));
            }
        }
        // No `[[loss]]` means the default losses; a list whose every weight is 0 trains nothing.
        let trains_head = self.segment.steps > 0 && self.segment.photometric_weight == 0.0;
        if trains_head && !self.loss.is_empty() && !self.loss.iter().any(|l| l.weight > 0.0) {
            return Err(invalid(
                "loss",
                "stage 2 needs a loss with a positive `weight` (every `[[loss]]` weight is 0); set one, \
                 or `segment.steps = 0` to skip stage 2",
            ));
        }
        if self.render.memory_gib.is_some_and(|g| !(g.is_finite() && g > 0.0 && g <= 1e6)) {
            return Err(invalid("render.memory_gib", "must be a positive number of GiB"));
        }
        if self.render.samples_per_ray.is_some_and(|n| !(2..=MAX_SAMPLES_PER_RAY).contains(&n)) {
            return Err(invalid("render.samples_per_ray", &format!("must be in 2..={MAX_SAMPLES_PER_RAY}")));
        }
        if !(1..=MAX_CHUNK).contains(&self.render.chunk) {
            return Err(invalid("render.chunk", &format!("must be in 1..={MAX_CHUNK}")));
        }
        // `.` and `..` would put the run's files into `output_dir` itself or its parent.
        if self.name.is_empty() || self.name.contains(['/', '\\']) || self.name == "." || self.name == ".." {
            return Err(invalid("name", "must be a non-empty file name without slashes, not `.` or `..`"));
        }
        Ok(())
    }

    /// Serialises back to TOML (what `sos init` writes and what checkpoints record).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("a run config always serialises")
    }
}
