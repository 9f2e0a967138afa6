//! `cell-stats`: a weight-free feature extractor, the offline fallback for DINO.
//!
//! Each `cell`×`cell` block of pixels becomes one feature vector of colour and texture
//! statistics:
//!
//! | channels           | what                                                           |
//! |--------------------|----------------------------------------------------------------|
//! | 3                  | mean colour in an opponent space (red–green, yellow–blue, luma) |
//! | 3                  | log standard deviation of the three opponent channels          |
//! | `orientation_bins` | gradient-orientation histogram (unsigned, magnitude-weighted)  |
//! | 1                  | log mean gradient magnitude (texture energy)                   |
//! | 1                  | saliency (below), centred, times `saliency_weight`             |
//!
//! Every channel is centred and scaled with FIXED constants (typical values of natural
//! images), never with per-image statistics, so the same surface gets the same features in
//! every image and patch, and features take both signs: the cosine similarity of two cells is
//! then high for the same surface and low (possibly negative) for different ones, which is
//! what the contrastive losses and pair mining need.
//!
//! The saliency map is the colour distinctness of each cell from the cells on the image
//! border (the usual background prior), normalised to `[0, 1]`. It is also a feature channel:
//! local statistics alone put a white patch of the object next to a white wall, while DINO's
//! features carry objectness; the saliency channel is the weight-free stand-in for it, so
//! cells of a salient object correlate with each other more than with the background.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::derived::{DerivedSetting, PatchFacts};
use sos_core::error::{BuildError, ExtractError};
use sos_core::image::RgbImage;
use sos_core::plugin::{BuildContext, FeatureExtractor, FeatureExtractorConfig, FeatureMap};

const KIND: &str = CellStatsConfig::KIND;
/// Bump when the features change, so cached teacher features are recomputed.
const VERSION: u32 = 3;
/// Teacher cells across a stage-2 patch when `cell` is left to the run: an 8x8 grid was the
/// better of 8- and 4-px cells on 64-ray patches of the object-centric rig and on 32-ray
/// patches of the unbounded NeRF++ rig (benchmarks/RESULTS.md, "nerf++ teacher cells").
pub const CELLS_PER_PATCH: usize = 8;

/// Fewest cells across a stage-2 patch that a set `cell` may give: with one, every ray of a
/// patch shares one teacher feature and the appearance loss has nothing to correlate.
pub const MIN_CELLS_PER_PATCH: usize = 2;
/// Cell side outside a run (no patch to follow), the 8x8 grid of a 64-ray patch.
const DEFAULT_CELL: usize = 8;

// Fixed normalisation constants (see the module docs for why they are not per-image).
/// Scale of the chromatic opponent means (saturated colours reach about ±0.7).
const CHROMA_SCALE: f32 = 0.2;
/// Luma of mid-grey in the opponent space (`(0.5 + 0.5 + 0.5) / √3`).
const LUMA_MID: f32 = 0.866_025_4;
/// Scale of the luma mean.
const LUMA_SCALE: f32 = 0.5;
/// Standard deviation treated as "typical" (maps to 0) and the floor added before the log.
const STD_TYPICAL: f32 = 0.08;
const STD_FLOOR: f32 = 0.02;
/// Mean gradient magnitude treated as "typical" and the floor added before the log.
const ENERGY_TYPICAL: f32 = 0.04;
const ENERGY_FLOOR: f32 = 0.005;
/// Mean gradient magnitude at which the orientation histogram gets half its weight; flat
/// cells have meaningless orientations, so their histogram features fade to zero.
const ORIENTATION_HALF: f32 = 0.02;
/// Scale of the centred orientation histogram (a single-orientation cell gets norm ≈ 2).
const ORIENTATION_SCALE: f32 = 2.0;

/// Settings of the `cell-stats` extractor (`[extractor] kind = "cell-stats"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CellStatsConfig {
    /// Cell side in pixels (one feature vector per cell); at least 2. Absent: derived from
    /// the patch stage 2 shows the teacher, an [`CELLS_PER_PATCH`]-cell grid across it (8-px
    /// cells for 64-ray patches, 4-px cells for 32-ray ones), or 8 px outside a run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cell: Option<usize>,
    /// Side of the square window, centred on each cell, whose pixels make the cell's
    /// statistics; absent = the cell itself. A window larger than the cell gives a finer grid
    /// (like DINO's 14x14 on a 64x64 patch) without the noise of statistics over few pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub window: Option<usize>,
    /// Bins of the gradient-orientation histogram over `[0, π)`; 2 to 64.
    pub orientation_bins: usize,
    /// Weight of the mean-colour channels.
    pub colour_weight: f32,
    /// Weight of the colour-spread (standard deviation) channels.
    pub spread_weight: f32,
    /// Weight of the orientation-histogram channels.
    pub orientation_weight: f32,
    /// Weight of the texture-energy channel.
    pub energy_weight: f32,
    /// Weight of the saliency channel (objectness; 0 turns it off).
    pub saliency_weight: f32,
    /// How the border distance becomes the saliency channel: `"per-image"` (default) uses the
    /// min–max normalised saliency map (every patch has a most salient cell); `"fixed"`
    /// squashes it with a fixed scale (a patch of background alone has no salient cell).
    pub saliency_scale: SaliencyScale,
    /// Whose border a stage-2 patch's saliency is measured against: `"patch"`, the patch's own
    /// border, or `"view"`, the whole view the patch was cut from. Absent: derived from the
    /// rig, `"view"` when the training views all look one way (their borders show the same
    /// walls and floor, a steady background) and `"patch"` otherwise (on an orbit the view's
    /// border crosses other things, and an object part coloured like them would be salient
    /// nowhere); `"patch"` outside a run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub saliency_background: Option<SaliencyBackground>,
}

/// See [`CellStatsConfig::saliency_background`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SaliencyBackground {
    /// The patch itself: whatever differs from the patch's border stands out, so on a large
    /// object (the usual case) each patch's object cells do, and in a patch of background
    /// alone its least usual cells do.
    Patch,
    /// The view a patch was cut from: the same cell gets the same saliency in every patch and
    /// a patch of plain background has no salient cell, but an object part coloured like
    /// something on the view's border (a dark base on a dark floor) is not salient anywhere.
    View,
}

impl SaliencyBackground {
    /// The name a config gives it, quoted as TOML writes it.
    pub fn name(self) -> &'static str {
        match self {
            SaliencyBackground::Patch => "\"patch\"",
            SaliencyBackground::View => "\"view\"",
        }
    }
}

/// See [`CellStatsConfig::saliency_scale`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SaliencyScale {
    /// `d / (d + 1)`, the same for every image.
    Fixed,
    /// Min–max normalised within each image.
    PerImage,
}

impl Default for CellStatsConfig {
    fn default() -> Self {
        CellStatsConfig {
            cell: None,
            window: None,
            orientation_bins: 8,
            colour_weight: 1.0,
            spread_weight: 0.5,
            orientation_weight: 1.0,
            energy_weight: 0.5,
            // 10 rather than 5: with masks.keep = "connected", mIoU 0.969 against 0.940 on one
            // checkpoint of the object-centric scene (benchmarks/RESULTS.md).
            saliency_weight: 10.0,
            // Measured on the synthetic scene's full pipeline (benchmarks/RESULTS.md):
            // per-image mIoU 0.77 against 0.67 for fixed, same checkpoint and settings.
            saliency_scale: SaliencyScale::PerImage,
            // Derived from the rig: the view's border cost object-centric scenes 0.04-0.2 mIoU
            // and steadied the forward-facing rooms (benchmarks/RESULTS.md).
            saliency_background: None,
        }
    }
}

impl CellStatsConfig {
    /// Checks the settings (also done by [`FeatureExtractorConfig::build`]).
    pub fn validate(&self) -> Result<(), BuildError> {
        let invalid = |key: &str, reason: &str| {
            Err(BuildError::Invalid { kind: KIND.into(), key: key.into(), reason: reason.into() })
        };
        if !(2..=4096).contains(&self.cell()) {
            return invalid("cell", "must be between 2 and 4096 pixels");
        }
        if let Some(window) = self.window {
            if !(self.cell()..=4096).contains(&window) {
                return invalid("window", "must be at least `cell` and at most 4096 pixels (or absent)");
            }
        }
        if !(2..=64).contains(&self.orientation_bins) {
            return invalid("orientation_bins", "must be between 2 and 64");
        }
        let weights = [
            ("colour_weight", self.colour_weight),
            ("spread_weight", self.spread_weight),
            ("orientation_weight", self.orientation_weight),
            ("energy_weight", self.energy_weight),
            ("saliency_weight", self.saliency_weight),
        ];
        for (key, w) in weights {
            if !(w.is_finite() && w >= 0.0) {
                return invalid(key, "must be a finite number >= 0");
            }
        }
        if weights.iter().all(|&(_, w)| w == 0.0) {
            return invalid("colour_weight", "at least one weight must be positive");
        }
        Ok(())
    }

    /// The cell side: as set, or the size used outside a run.
    pub fn cell(&self) -> usize {
        self.cell.unwrap_or(DEFAULT_CELL)
    }

    /// Whose border the saliency is measured against: the set or derived one, the patch's own
    /// outside a run.
    pub fn saliency_background(&self) -> SaliencyBackground {
        self.saliency_background.unwrap_or(SaliencyBackground::Patch)
    }

    /// Number of feature channels: 3 + 3 + `orientation_bins` + 1 + 1.
    pub fn channels(&self) -> usize {
        8 + self.orientation_bins
    }
}

sos_core::plugin_kind! {
    kind: "cell-stats",
    summary: "weight-free colour and texture statistics per cell (offline fallback for DINO)",
    default: || Box::new(CellStatsConfig::default()),
    impl FeatureExtractorConfig for CellStatsConfig {
        fn build(&self, _ctx: &BuildContext) -> Result<Box<dyn FeatureExtractor>, BuildError> {
            self.validate()?;
            Ok(Box::new(CellStats { config: self.clone() }))
        }

        fn derive_for(&mut self, patch: &PatchFacts) -> Vec<DerivedSetting> {
            let mut derived = Vec::new();
            if self.cell.is_none() {
                let cell = (patch.patch_size as usize / CELLS_PER_PATCH).max(2);
                self.cell = Some(cell);
                derived.push(DerivedSetting::new(
                    "extractor.cell",
                    cell,
                    format!("{CELLS_PER_PATCH} cells across the {}-ray patch", patch.patch_size),
                ));
            }
            if self.saliency_background.is_none() {
                let (background, why) = if patch.views_look_one_way {
                    (SaliencyBackground::View, "the views look one way: their borders show the same surroundings")
                } else {
                    (SaliencyBackground::Patch, "the views look in spread directions: their borders cross other things")
                };
                self.saliency_background = Some(background);
                derived.push(DerivedSetting::new("extractor.saliency_background", background.name(), why));
            }
            derived
        }

        fn check_for(&self, patch: &PatchFacts) -> Result<(), BuildError> {
            let (cell, size) = (self.cell(), patch.patch_size as usize);
            let cells = size / cell;
            if cells < MIN_CELLS_PER_PATCH {
                let widest = size / MIN_CELLS_PER_PATCH;
                let or_cell = if widest >= 2 { format!(", or this cell at most {widest} px") } else { String::new() };
                return Err(BuildError::Invalid {
                    kind: KIND.into(),
                    key: "cell".into(),
                    reason: format!(
                        "{cell} px gives the {size}-ray patches of stage 2 {cells} cell(s) across, and the appearance \
                         loss needs at least {MIN_CELLS_PER_PATCH}: make `segment.patch_size` at least {}{or_cell}",
                        MIN_CELLS_PER_PATCH * cell
                    ),
                });
            }
            Ok(())
        }
    }
}

/// The `cell-stats` extractor; build it from a validated [`CellStatsConfig`].
#[derive(Debug, Clone)]
pub struct CellStats {
    config: CellStatsConfig,
}

impl CellStats {
    /// Builds the extractor, validating the settings.
    pub fn new(config: CellStatsConfig) -> Result<Self, BuildError> {
        config.validate()?;
        Ok(CellStats { config })
    }

    /// Features of one image. An image with no pixels (or whose buffer does not match its
    /// size) gives a 1x1 grid of zeros.
    pub fn extract_one(&self, image: &RgbImage) -> FeatureMap {
        self.extract_against(image, None)
    }

    /// Features of a patch whose saliency is measured against the whole `view` it was cut
    /// from (at the patch's pixel spacing): distinctness from the view's border, normalised
    /// with the range of the view's own cells, so every patch of a view shares one scale and a
    /// patch of plain background has no salient cell.
    pub fn extract_in_view(&self, patch: &RgbImage, view: &RgbImage) -> FeatureMap {
        match self.cells(view) {
            Some(grid) => {
                let (background, _) = Background::of(&grid, &self.config);
                self.extract_against(patch, Some(&background))
            }
            None => self.extract_one(patch),
        }
    }

    /// Saliency against `background`, or against the image's own border when `None`.
    fn extract_against(&self, image: &RgbImage, background: Option<&Background>) -> FeatureMap {
        let channels = self.config.channels();
        let Some(grid) = self.cells(image) else {
            return FeatureMap::zeros(channels, channels);
        };
        let (distance, saliency) = match background {
            Some(b) => {
                let distance = b.distances(&grid.cells, &self.config);
                let saliency = b.normalize(&distance);
                (distance, saliency)
            }
            None => {
                let (own, distance) = Background::of(&grid, &self.config);
                let saliency = own.normalize(&distance);
                (distance, saliency)
            }
        };
        let n = grid.cells.len();
        let mut data = vec![0.0; channels * n];
        let mut cls = vec![0.0; channels];
        for (i, f) in grid.cells.iter().enumerate() {
            let unit = match self.config.saliency_scale {
                SaliencyScale::Fixed => distance[i] / (distance[i] + SALIENCY_HALF),
                SaliencyScale::PerImage => saliency[i],
            };
            let salient = self.config.saliency_weight * (unit - 0.5);
            for (k, &v) in f.iter().chain([&salient]).enumerate() {
                data[k * n + i] = v;
                cls[k] += v / n as f32;
            }
        }
        FeatureMap { channels, height: grid.height, width: grid.width, data, cls, saliency: Some(saliency) }
    }

    /// The cell grid of an image (without the saliency channel); `None` for an image with no
    /// pixels or whose buffer does not match its size.
    fn cells(&self, image: &RgbImage) -> Option<CellGrid> {
        let (w, h) = (image.width, image.height);
        if w == 0 || h == 0 || image.data.len() != w * h * 3 {
            return None;
        }
        let cell = self.config.cell();
        // Floor division like a ViT's patch grid; smaller images get one cell over all of it.
        let (gh, gw) = ((h / cell).max(1), (w / cell).max(1));
        let (ch, cw) = (cell.min(h), cell.min(w));

        let window = self.config.window.unwrap_or(cell);
        let (wh, ww) = (window.min(h), window.min(w));

        let (magnitude, orientation) = gradients(image);
        let cells = (0..gh * gw)
            .into_par_iter()
            .map(|i| {
                let (r0, c0) = ((i / gw) * ch, (i % gw) * cw);
                // The window shares the cell's centre, shifted to stay inside the image.
                let r0 = (r0 + ch / 2).saturating_sub(wh / 2).min(h - wh);
                let c0 = (c0 + cw / 2).saturating_sub(ww / 2).min(w - ww);
                self.cell_features(image, &magnitude, &orientation, r0, c0, wh, ww)
            })
            .collect();
        Some(CellGrid { cells, height: gh, width: gw })
    }

    /// Feature vector of the `ch`×`cw` window whose top-left pixel is `(r0, c0)`.
    #[allow(clippy::too_many_arguments)]
    fn cell_features(
        &self,
        image: &RgbImage,
        magnitude: &[f32],
        orientation: &[f32],
        r0: usize,
        c0: usize,
        ch: usize,
        cw: usize,
    ) -> Vec<f32> {
        let cfg = &self.config;
        let bins = cfg.orientation_bins;
        let mut sum = [0.0f64; 3];
        let mut sum_sq = [0.0f64; 3];
        let mut hist = vec![0.0f64; bins];
        let mut energy = 0.0f64;
        for r in r0..r0 + ch {
            for c in c0..c0 + cw {
                let o = opponent(image.pixel(c, r));
                for k in 0..3 {
                    sum[k] += o[k] as f64;
                    sum_sq[k] += (o[k] as f64) * (o[k] as f64);
                }
                let i = r * image.width + c;
                let m = magnitude[i] as f64;
                energy += m;
                // Soft binning between the two nearest bin centres, wrapping at π.
                let pos = orientation[i] as f64 / std::f64::consts::PI * bins as f64 - 0.5;
                let lo = pos.floor();
                let frac = pos - lo;
                let b0 = (lo as isize).rem_euclid(bins as isize) as usize;
                hist[b0] += m * (1.0 - frac);
                hist[(b0 + 1) % bins] += m * frac;
            }
        }
        let count = (ch * cw) as f64;
        let mut f = Vec::with_capacity(cfg.channels());
        let mean: Vec<f32> = sum.iter().map(|s| (s / count) as f32).collect();
        f.push(cfg.colour_weight * mean[0] / CHROMA_SCALE);
        f.push(cfg.colour_weight * mean[1] / CHROMA_SCALE);
        f.push(cfg.colour_weight * (mean[2] - LUMA_MID) / LUMA_SCALE);
        for k in 0..3 {
            let var = (sum_sq[k] / count - (sum[k] / count).powi(2)).max(0.0);
            let std = var.sqrt() as f32;
            f.push(cfg.spread_weight * 0.5 * ((std + STD_FLOOR) / STD_TYPICAL).ln());
        }
        let mean_energy = (energy / count) as f32;
        let confidence = mean_energy / (mean_energy + ORIENTATION_HALF);
        let total: f64 = hist.iter().sum();
        for &v in &hist {
            let frac = if total > 0.0 { (v / total) as f32 } else { 1.0 / bins as f32 };
            let centred = frac - 1.0 / bins as f32;
            f.push(cfg.orientation_weight * ORIENTATION_SCALE * confidence * centred);
        }
        f.push(cfg.energy_weight * 0.5 * ((mean_energy + ENERGY_FLOOR) / ENERGY_TYPICAL).ln());
        f
    }
}

impl FeatureExtractor for CellStats {
    fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
        Ok(images.par_iter().map(|img| self.extract_one(img)).collect())
    }

    fn extract_in_views(&self, patches: &[RgbImage], views: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
        if views.len() != patches.len() {
            let message = format!("{} views given for {} patches", views.len(), patches.len());
            return Err(ExtractError::new(self.identity(), message));
        }
        if self.config.saliency_background() == SaliencyBackground::Patch {
            return self.extract(patches);
        }
        Ok(patches.par_iter().zip(views).map(|(p, v)| self.extract_in_view(p, v)).collect())
    }

    fn identity(&self) -> String {
        let c = &self.config;
        format!(
            "{KIND}/v{VERSION} cell={} window={:?} orientation_bins={} colour_weight={} spread_weight={} \
             orientation_weight={} energy_weight={} saliency_weight={} saliency_scale={:?} \
             saliency_background={:?}",
            c.cell(),
            c.window,
            c.orientation_bins,
            c.colour_weight,
            c.spread_weight,
            c.orientation_weight,
            c.energy_weight,
            c.saliency_weight,
            c.saliency_scale,
            c.saliency_background()
        )
    }
}

/// Opponent colour space: red–green, yellow–blue, luma (an orthonormal rotation of RGB).
#[inline]
fn opponent([r, g, b]: [f32; 3]) -> [f32; 3] {
    [(r - g) * std::f32::consts::FRAC_1_SQRT_2, (r + g - 2.0 * b) / 6.0f32.sqrt(), (r + g + b) / 3.0f32.sqrt()]
}

/// Per-pixel gradient magnitude and unsigned orientation in `[0, π)` of the mean of the
/// RGB channels (central differences, edges clamped), over the whole image so that
/// neighbouring cells see the same gradients at their shared edges.
fn gradients(image: &RgbImage) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (image.width, image.height);
    let luma: Vec<f32> = image.data.chunks_exact(3).map(|p| (p[0] + p[1] + p[2]) / 3.0).collect();
    let mut magnitude = vec![0.0; w * h];
    let mut orientation = vec![0.0; w * h];
    magnitude.par_chunks_mut(w).zip(orientation.par_chunks_mut(w)).enumerate().for_each(|(r, (mag, ori))| {
        let (up, down) = (r.saturating_sub(1), (r + 1).min(h - 1));
        for c in 0..w {
            let (left, right) = (c.saturating_sub(1), (c + 1).min(w - 1));
            let gx = (luma[r * w + right] - luma[r * w + left]) * 0.5;
            let gy = (luma[down * w + c] - luma[up * w + c]) * 0.5;
            mag[c] = (gx * gx + gy * gy).sqrt();
            let mut theta = gy.atan2(gx);
            if theta < 0.0 {
                theta += std::f32::consts::PI;
            }
            if theta >= std::f32::consts::PI {
                theta -= std::f32::consts::PI;
            }
            ori[c] = theta;
        }
    });
    (magnitude, orientation)
}

/// Distance from the border below which a cell counts as background-like: the saliency
/// feature channel is `raw / (raw + SALIENCY_HALF)`, a fixed squashing (not per image) so that
/// a patch showing only background has no "salient" cells.
const SALIENCY_HALF: f32 = 1.0;

/// The feature vectors of an image's cells (saliency channel not yet added), row-major.
struct CellGrid {
    cells: Vec<Vec<f32>>,
    height: usize,
    width: usize,
}

/// What saliency is measured against: the colour descriptors of an image's border cells (the
/// usual background prior), and the range of that image's own cells' distances from them.
struct Background {
    border: Vec<[f32; 6]>,
    range: (f32, f32),
}

impl Background {
    /// The background of an image's cells, with each cell's distance from it.
    fn of(grid: &CellGrid, cfg: &CellStatsConfig) -> (Self, Vec<f32>) {
        let (gh, gw) = (grid.height, grid.width);
        let border = (0..gh * gw)
            .filter(|&i| {
                let (r, c) = (i / gw, i % gw);
                r == 0 || c == 0 || r + 1 == gh || c + 1 == gw
            })
            .map(|i| colour_descriptor(&grid.cells[i], cfg))
            .collect();
        let mut background = Background { border, range: (0.0, 0.0) };
        let own = background.distances(&grid.cells, cfg);
        let lo = own.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = own.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        background.range = (lo, hi);
        (background, own)
    }

    /// Distinctness of each cell from the border: the mean distance of its colour features
    /// (mean and spread, fixed scales, unweighted) to the nearest eighth of the border cells.
    /// A cell that resembles some part of the border scores low; an object unlike the whole
    /// border scores high.
    fn distances(&self, cells: &[Vec<f32>], cfg: &CellStatsConfig) -> Vec<f32> {
        let m = (self.border.len() / 8).max(1);
        cells
            .par_iter()
            .map(|f| {
                let d = colour_descriptor(f, cfg);
                let mut dists: Vec<f32> = self
                    .border
                    .iter()
                    .map(|b| d.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>().sqrt())
                    .collect();
                dists.select_nth_unstable_by(m - 1, f32::total_cmp);
                dists[..m].iter().sum::<f32>() / m as f32
            })
            .collect()
    }

    /// The saliency map: distances min–max normalised with the background image's range and
    /// clamped to `[0, 1]` (all zeros when every cell of that image is alike); only the
    /// ranking within one view matters for choosing the foreground cluster.
    fn normalize(&self, raw: &[f32]) -> Vec<f32> {
        let (lo, hi) = self.range;
        if hi - lo > 1e-9 {
            raw.iter().map(|v| ((v - lo) / (hi - lo)).clamp(0.0, 1.0)).collect()
        } else {
            vec![0.0; raw.len()]
        }
    }
}

/// A cell's colour mean and spread with the user weights undone, so saliency does not depend
/// on them.
fn colour_descriptor(f: &[f32], cfg: &CellStatsConfig) -> [f32; 6] {
    let unweight = |w: f32| if w > 0.0 { 1.0 / w } else { 0.0 };
    let (cw, sw) = (unweight(cfg.colour_weight), unweight(cfg.spread_weight));
    [f[0] * cw, f[1] * cw, f[2] * cw, f[3] * sw, f[4] * sw, f[5] * sw]
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn extractor() -> CellStats {
        CellStats::new(CellStatsConfig::default()).unwrap()
    }

    fn image(w: usize, h: usize, mut f: impl FnMut(usize, usize) -> [f32; 3]) -> RgbImage {
        let mut img = RgbImage::new(w, h);
        for r in 0..h {
            for c in 0..w {
                img.set_pixel(c, r, f(c, r));
            }
        }
        img
    }

    fn cell_vec(map: &FeatureMap, r: usize, c: usize) -> Vec<f32> {
        let n = map.height * map.width;
        (0..map.channels).map(|k| map.data[k * n + r * map.width + c]).collect()
    }

    fn cosine(a: &[f32], b: &[f32]) -> f32 {
        let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
        let na: f32 = a.iter().map(|x| x * x).sum::<f32>().sqrt();
        let nb: f32 = b.iter().map(|x| x * x).sum::<f32>().sqrt();
        dot / (na * nb).max(1e-12)
    }

    #[test]
    fn shapes_follow_the_cell_grid() {
        let ex = extractor();
        let img = image(37, 21, |c, r| [c as f32 / 37.0, r as f32 / 21.0, 0.3]);
        let map = ex.extract_one(&img);
        assert_eq!((map.channels, map.height, map.width), (16, 2, 4));
        assert_eq!(map.data.len(), 16 * 8);
        assert_eq!(map.cls.len(), 16);
        assert_eq!(map.saliency.as_ref().unwrap().len(), 8);
        assert!(map.data.iter().all(|v| v.is_finite()));
        // cls is the mean over cells.
        for k in 0..16 {
            let mean = map.data[k * 8..(k + 1) * 8].iter().sum::<f32>() / 8.0;
            assert!((map.cls[k] - mean).abs() < 1e-5);
        }
        // Smaller than one cell (in one or both directions): a single row / cell.
        let tiny = ex.extract_one(&image(5, 3, |_, _| [0.2, 0.4, 0.6]));
        assert_eq!((tiny.height, tiny.width), (1, 1));
        let strip = ex.extract_one(&image(40, 3, |_, _| [0.2, 0.4, 0.6]));
        assert_eq!((strip.height, strip.width), (1, 5));
        // Degenerate input does not panic.
        let empty = ex.extract_one(&RgbImage::new(0, 0));
        assert_eq!((empty.height, empty.width, empty.data.len()), (1, 1, 16));
        let broken = RgbImage { width: 10, height: 10, data: vec![0.5; 7] };
        assert_eq!(ex.extract_one(&broken).data, vec![0.0; 16]);
        // Other settings change the channel count.
        let cfg = CellStatsConfig { cell: Some(4), orientation_bins: 12, ..Default::default() };
        let map = CellStats::new(cfg).unwrap().extract_one(&img);
        assert_eq!((map.channels, map.height, map.width), (20, 5, 9));
    }

    #[test]
    fn a_window_keeps_the_cell_grid_and_widens_the_statistics() {
        // Left half red, right half blue, boundary at x = 32.
        let img = image(64, 32, |c, _| if c < 32 { [0.9, 0.1, 0.1] } else { [0.1, 0.1, 0.9] });
        let with = |window| {
            let cfg = CellStatsConfig { cell: Some(4), window, saliency_weight: 0.0, ..Default::default() };
            CellStats::new(cfg).unwrap().extract_one(&img)
        };
        let (plain, same, wide) = (with(None), with(Some(4)), with(Some(12)));
        assert_eq!(plain, same, "a window of one cell is the cell");
        assert_eq!((wide.height, wide.width), (plain.height, plain.width));
        // Channel 0 is red–green: the cell left of the boundary (column 7) is pure red alone,
        // but its 12-px window reaches 4 px into the blue half.
        let red_green = |m: &FeatureMap, c: usize| m.data[2 * m.width + c];
        assert!((red_green(&plain, 7) - red_green(&plain, 0)).abs() < 1e-6);
        assert!(red_green(&wide, 7) < red_green(&wide, 0) - 0.1);
        // Far from the boundary and at the image edge (window shifted inside) nothing changes.
        assert!((red_green(&wide, 0) - red_green(&plain, 0)).abs() < 1e-6);
        let bad = CellStatsConfig { cell: Some(8), window: Some(4), ..Default::default() };
        assert!(CellStats::new(bad).is_err(), "a window smaller than the cell is refused");
    }

    #[test]
    fn deterministic_and_batch_independent() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let a = image(64, 48, |_, _| [rng.gen(), 0.5, 0.2]);
        let b = image(48, 64, |c, r| [((c + r) % 5) as f32 / 5.0, 0.1, 0.9]);
        let ex = extractor();
        let both = ex.extract(&[a.clone(), b.clone()]).unwrap();
        assert_eq!(both, ex.extract(&[a.clone(), b.clone()]).unwrap());
        assert_eq!(both[0], ex.extract_one(&a));
        assert_eq!(both[1], ex.extract_one(&b));
    }

    /// Mean cosine over same-region and cross-region cell pairs of a left/right split image.
    fn same_vs_cross(map: &FeatureMap) -> (f32, f32) {
        let (mut same, mut cross) = (Vec::new(), Vec::new());
        let cells: Vec<(usize, Vec<f32>)> = (0..map.height)
            .flat_map(|r| (0..map.width).map(move |c| (r, c)))
            .map(|(r, c)| ((c >= map.width / 2) as usize, cell_vec(map, r, c)))
            .collect();
        for (i, (ri, fi)) in cells.iter().enumerate() {
            for (rj, fj) in &cells[i + 1..] {
                if ri == rj { &mut same } else { &mut cross }.push(cosine(fi, fj));
            }
        }
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        (mean(&same), mean(&cross))
    }

    /// The extractor without the saliency channel (which depends on the whole image).
    fn statistics_only() -> CellStats {
        CellStats::new(CellStatsConfig { saliency_weight: 0.0, ..Default::default() }).unwrap()
    }

    #[test]
    fn same_texture_is_more_similar_than_different_texture() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let mut noise = move || rng.gen_range(-0.05f32..0.05);
        // Left: horizontal brown stripes (period 6, not aligned with the cells); right:
        // vertical grey-green stripes of period 5.
        let img = image(128, 64, |c, r| {
            let n = noise();
            if c < 64 {
                let v = if r % 6 < 3 { 0.6 } else { 0.3 };
                [v + n, v * 0.7 + n, v * 0.4 + n]
            } else {
                let v = if c % 5 < 2 { 0.7 } else { 0.4 };
                [v * 0.8 + n, v + n, v * 0.8 + n]
            }
        });
        let (same, cross) = same_vs_cross(&statistics_only().extract_one(&img));
        eprintln!("colour+texture: same {same:.3}, cross {cross:.3}");
        assert!(same > 0.9, "same-region cosine {same}");
        assert!(same - cross > 0.5, "same {same} vs cross {cross}");

        // Same colours, only the stripe orientation differs: texture alone must separate.
        let img = image(128, 64, |c, r| {
            let n = noise();
            let v = if c < 64 { (r % 6 < 3) as u8 } else { (c % 6 < 3) as u8 } as f32 * 0.6 + 0.2;
            [v + n, v + n, v + n]
        });
        let (same, cross) = same_vs_cross(&statistics_only().extract_one(&img));
        eprintln!("orientation only: same {same:.3}, cross {cross:.3}");
        assert!(same > 0.9, "same-region cosine {same}");
        assert!(same - cross > 0.3, "orientation only: same {same} vs cross {cross}");
    }

    #[test]
    fn same_surface_gets_the_same_features_in_different_images() {
        // Fixed normalisation: the rest of the image must not change a cell's features.
        let stripes = |c: usize, r: usize, other: [f32; 3]| {
            if c < 64 {
                [0.2 + 0.5 * (r % 4 < 2) as u8 as f32, 0.3, 0.25]
            } else {
                other
            }
        };
        let a = statistics_only().extract_one(&image(128, 32, |c, r| stripes(c, r, [0.9, 0.1, 0.1])));
        let b = statistics_only().extract_one(&image(128, 32, |c, r| stripes(c, r, [0.0, 0.2, 1.0])));
        // Cells 0..7 do not touch the boundary at column 64 (gradients reach one pixel).
        for r in 0..4 {
            for c in 0..7 {
                assert_eq!(cell_vec(&a, r, c), cell_vec(&b, r, c), "cell ({r}, {c})");
            }
        }
        assert_ne!(cell_vec(&a, 0, 12), cell_vec(&b, 0, 12));
        // Features take both signs (centred), so unrelated cells can have negative cosine.
        assert!(a.data.iter().any(|&v| v < 0.0) && a.data.iter().any(|&v| v > 0.0));
    }

    #[test]
    fn saliency_is_high_on_a_distinct_central_object() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        // Noisy grey-blue background, a red disc in the middle.
        let img = image(96, 80, |c, r| {
            let (dx, dy) = (c as f32 - 48.0, r as f32 - 40.0);
            let n: f32 = rng.gen_range(-0.1..0.1);
            if dx * dx + dy * dy < 20.0 * 20.0 {
                [0.85 + n * 0.5, 0.15, 0.1]
            } else {
                [0.4 + n, 0.45 + n, 0.55 + n]
            }
        });
        let map = extractor().extract_one(&img);
        let sal = map.saliency.as_ref().unwrap();
        assert!(sal.iter().all(|v| (0.0..=1.0).contains(v)));
        let (gh, gw) = (map.height, map.width);
        let at = |r: usize, c: usize| sal[r * gw + c];
        let centre = (at(4, 5) + at(4, 6) + at(5, 5) + at(5, 6)) / 4.0;
        let border: Vec<f32> = (0..gh * gw)
            .filter(|&i| i / gw == 0 || i % gw == 0 || i / gw == gh - 1 || i % gw == gw - 1)
            .map(|i| sal[i])
            .collect();
        let border_mean = border.iter().sum::<f32>() / border.len() as f32;
        eprintln!("saliency: centre {centre:.3}, border mean {border_mean:.3}");
        assert!(centre > 0.8, "centre saliency {centre}");
        assert!(border_mean < 0.2, "border saliency {border_mean}");
        // A uniform image has no salient cell.
        let flat = extractor().extract_one(&image(32, 32, |_, _| [0.5; 3]));
        assert!(flat.saliency.unwrap().iter().all(|&v| v == 0.0));
    }

    /// A 128x96 view of a floor with dark tiles (one in each corner, one inside) and a small
    /// red box.
    fn room_view() -> RgbImage {
        let tile = |c: usize, r: usize| {
            let corner = !(16..112).contains(&c) && !(16..80).contains(&r);
            corner || ((40..56).contains(&c) && (32..48).contains(&r))
        };
        image(128, 96, |c, r| {
            if (80..96).contains(&c) && (56..72).contains(&r) {
                [0.85, 0.15, 0.1]
            } else if tile(c, r) {
                [0.2, 0.2, 0.25]
            } else {
                [0.45, 0.55, 0.4]
            }
        })
    }

    fn crop(view: &RgbImage, c0: usize, r0: usize, size: usize) -> RgbImage {
        image(size, size, |c, r| view.pixel(c0 + c, r0 + r))
    }

    #[test]
    fn saliency_against_the_view_marks_the_object_not_every_patch_centre() {
        let ex = extractor();
        let view = room_view();
        // A patch around the inner tile: measured against its own border (all floor) the
        // tile stands out; measured against the view, whose border holds tiles too, it does not.
        let background = crop(&view, 32, 24, 32);
        let own = ex.extract_one(&background);
        assert_eq!(own.saliency.as_ref().unwrap().iter().copied().fold(0.0, f32::max), 1.0);
        let in_view = ex.extract_in_view(&background, &view);
        let highest = in_view.saliency.as_ref().unwrap().iter().copied().fold(0.0, f32::max);
        assert!(highest < 0.1, "background patch, view saliency up to {highest}");
        // A patch over the box: the box stands out, the floor does not.
        let over_box = crop(&view, 72, 48, 32);
        let map = ex.extract_in_view(&over_box, &view);
        let sal = map.saliency.as_ref().unwrap();
        let (box_cell, floor_cell) = (sal[map.width + 1], sal[0]);
        assert!(box_cell > 0.9 && floor_cell < 0.1, "box {box_cell}, floor {floor_cell}");
        // The whole view against itself is the plain extraction.
        assert_eq!(ex.extract_in_view(&view, &view), ex.extract_one(&view));
    }

    #[test]
    fn the_default_scores_patches_against_their_own_border_the_option_against_the_view() {
        let view = room_view();
        let patches = [crop(&view, 32, 24, 32), crop(&view, 72, 48, 32)];
        let views = [view.clone(), view.clone()];
        let by_patch = extractor();
        assert_eq!(by_patch.extract_in_views(&patches, &views).unwrap(), by_patch.extract(&patches).unwrap());
        let config = CellStatsConfig { saliency_background: Some(SaliencyBackground::View), ..Default::default() };
        let by_view = CellStats::new(config).unwrap();
        let in_views = by_view.extract_in_views(&patches, &views).unwrap();
        assert_eq!(in_views[1], by_view.extract_in_view(&patches[1], &view));
        assert_ne!(in_views[0], by_view.extract_one(&patches[0]));
        assert_ne!(by_patch.identity(), by_view.identity());
        for ex in [by_patch, by_view] {
            let err = ex.extract_in_views(&patches, &views[..1]).unwrap_err();
            assert!(err.to_string().contains("1 views given for 2 patches"), "{err}");
        }
    }

    #[test]
    fn saliency_channel_marks_the_object_and_only_the_object() {
        let scene = |disc: bool, seed: u64| {
            let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
            image(96, 80, move |c, r| {
                let (dx, dy) = (c as f32 - 48.0, r as f32 - 40.0);
                let n: f32 = rng.gen_range(-0.1..0.1);
                if disc && dx * dx + dy * dy < 20.0 * 20.0 {
                    [0.85 + n * 0.5, 0.15, 0.1]
                } else {
                    [0.4 + n, 0.45 + n, 0.55 + n]
                }
            })
        };
        let channel = |map: &FeatureMap, r: usize, c: usize| *cell_vec(map, r, c).last().unwrap();
        let fixed =
            CellStats::new(CellStatsConfig { saliency_scale: SaliencyScale::Fixed, ..Default::default() }).unwrap();
        let with = fixed.extract_one(&scene(true, 5));
        let (centre, corner) = (channel(&with, 4, 5), channel(&with, 0, 0));
        eprintln!("saliency channel: centre {centre:.3}, corner {corner:.3}");
        assert!(centre > 0.0 && corner < -1.0, "centre {centre}, corner {corner}");
        // Fixed squashing, not per-image normalisation: a view of background alone has no
        // salient cell, although its normalised saliency map still spans [0, 1].
        let without = fixed.extract_one(&scene(false, 6));
        let most = (0..with.height * with.width)
            .map(|i| channel(&without, i / without.width, i % without.width))
            .fold(f32::NEG_INFINITY, f32::max);
        assert!(most < -1.0, "most salient background cell {most}");
        assert!(without.saliency.as_ref().unwrap().contains(&1.0));
        // Per image (the default), the object's cells are the most salient of their view.
        let per_image = extractor().extract_one(&scene(true, 5));
        assert!(channel(&per_image, 4, 5) > 1.5 && channel(&per_image, 0, 0) < -1.5);
        // The weight scales the channel; 0 turns it off.
        let off = statistics_only().extract_one(&scene(true, 5));
        assert_eq!(channel(&off, 4, 5), 0.0);
    }

    #[test]
    fn toml_round_trip_and_validation() {
        let cfg: Box<dyn FeatureExtractorConfig> =
            toml::from_str("kind = \"cell-stats\"\ncell = 16\norientation_weight = 2.0\n").unwrap();
        let built = cfg.build(&BuildContext::default()).unwrap();
        assert!(built.identity().starts_with("cell-stats/v3 cell=16 "), "{}", built.identity());
        assert!(built.identity().contains("orientation_weight=2 "), "{}", built.identity());
        let text = toml::to_string(&cfg).unwrap();
        assert!(text.contains("kind = \"cell-stats\""), "{text}");
        let back: Box<dyn FeatureExtractorConfig> = toml::from_str(&text).unwrap();
        assert_eq!(back.build(&BuildContext::default()).unwrap().identity(), built.identity());
        // Defaults fill in missing keys; unknown keys are rejected with their name.
        let default: Box<dyn FeatureExtractorConfig> = toml::from_str("kind = \"cell-stats\"").unwrap();
        assert_eq!(default.build(&BuildContext::default()).unwrap().identity(), extractor().identity());
        let err = toml::from_str::<Box<dyn FeatureExtractorConfig>>("kind = \"cell-stats\"\ncells = 4").unwrap_err();
        assert!(err.to_string().contains("cells"), "{err}");
        // Out-of-range values fail at build time, naming the key.
        for (text, key) in [
            ("cell = 1", "cell"),
            ("orientation_bins = 1", "orientation_bins"),
            ("spread_weight = -1.0", "spread_weight"),
            ("saliency_weight = -2.0", "saliency_weight"),
            ("colour_weight = 0.0\nspread_weight = 0.0\norientation_weight = 0.0\nenergy_weight = 0.0\nsaliency_weight = 0.0", "colour_weight"),
        ] {
            let cfg: Box<dyn FeatureExtractorConfig> =
                toml::from_str(&format!("kind = \"cell-stats\"\n{text}")).unwrap();
            match cfg.build(&BuildContext::default()) {
                Err(BuildError::Invalid { key: k, .. }) => assert_eq!(k, key),
                other => panic!("{text}: expected Invalid, got {:?}", other.map(|e| e.identity())),
            }
        }
    }

    #[test]
    fn registered_with_a_working_default() {
        let reg = sos_core::registry::find::<dyn FeatureExtractorConfig>("cell-stats").unwrap();
        assert!(!reg.summary.is_empty());
        let ex = (reg.default_config)().build(&BuildContext::default()).unwrap();
        assert_eq!(ex.identity(), extractor().identity());
        let maps = ex.extract(&[image(16, 16, |_, _| [0.1, 0.2, 0.3])]).unwrap();
        assert_eq!((maps[0].height, maps[0].width), (2, 2));
    }
}
