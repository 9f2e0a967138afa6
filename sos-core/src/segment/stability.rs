//! Stopping stage 2 once its masks stop changing, without ground truth.
//!
//! Every `segment.check_every` steps a few training views are rendered small with the current
//! head and their masks decided exactly as the run's masks are ([`MaskInference`] with its
//! `[masks]` rules). The share of probe pixels whose mask flipped since the previous check,
//! away from the masks' outlines ([`mask_change`]), measures how much the masks still move;
//! the raw clusters are not compared, since background regions may trade clusters for ever
//! without touching a mask. Once the change stays at most `segment.stable_change` over
//! [`CALM_CHECKS`] checks in a row, more steps would only move a few pixels and stage 2 stops.

use crate::camera::Camera;
use crate::error::RunError;
use crate::plugin::FeatureExtractor;
use crate::scene::Scene;
use crate::segment::head::SegHead;
use crate::segment::infer::MaskInference;
use crate::train::session::Session;

/// Training views rendered at each check, spread evenly over the training list.
pub const PROBE_VIEWS: usize = 3;

/// Longest side, in pixels, of a probe view's render (views are only ever shrunk): large
/// enough that a small object covers many probe pixels, small enough that a check costs a
/// fraction of a step.
pub const PROBE_SIDE: u32 = 96;

/// Checks in a row whose change must be within the tolerance: one calm interval can be a
/// pause before the masks move again.
pub const CALM_CHECKS: usize = 2;

/// Share of the pixels of a `width`-wide mask `a` that `b` flips, counting only pixels away
/// from `a`'s outline: an outline that shifts by a pixel between two checks is the clustering's
/// jitter, not a mask still forming. Empty masks have changed nothing.
pub fn mask_change(a: &[bool], b: &[bool], width: usize) -> f64 {
    assert_eq!(a.len(), b.len(), "mask_change: masks of different sizes");
    if a.is_empty() || width == 0 {
        return 0.0;
    }
    let outline = border_band(a, width);
    let changed = (0..a.len()).filter(|&i| !outline[i] && a[i] != b[i]).count();
    changed as f64 / a.len() as f64
}

/// Pixels of a `width`-wide mask within one pixel (8-neighbourhood) of a pixel of the other
/// value.
fn border_band(mask: &[bool], width: usize) -> Vec<bool> {
    let height = mask.len() / width;
    let mut band = vec![false; mask.len()];
    for r in 0..height {
        for c in 0..width {
            let i = r * width + c;
            let (r0, r1, c0, c1) =
                (r.saturating_sub(1), (r + 1).min(height - 1), c.saturating_sub(1), (c + 1).min(width - 1));
            band[i] = (r0..=r1).any(|rr| (c0..=c1).any(|cc| mask[rr * width + cc] != mask[i]));
        }
    }
    band
}

/// The training views a check renders, shrunk to at most [`PROBE_SIDE`] pixels a side.
pub fn probe_cameras(scene: &Scene) -> Vec<Camera> {
    let n = scene.train.len();
    let count = PROBE_VIEWS.min(n);
    (0..count)
        .map(|i| {
            let camera = &scene.views[scene.train[i * n / count]].camera;
            let scale = (PROBE_SIDE as f32 / camera.width.max(camera.height) as f32).min(1.0);
            let size = |side: u32| ((side as f32 * scale).round() as u32).max(1);
            camera.resized(size(camera.width), size(camera.height))
        })
        .collect()
}

/// What the checks have seen so far.
#[derive(Debug, Clone)]
pub struct MaskStability {
    probes: Vec<Camera>,
    tolerance: f64,
    previous: Option<Vec<Vec<bool>>>,
    calm: usize,
}

impl MaskStability {
    /// Checks on the scene's probe views, calling a change of at most `tolerance` calm.
    pub fn new(scene: &Scene, tolerance: f64) -> MaskStability {
        MaskStability { probes: probe_cameras(scene), tolerance, previous: None, calm: 0 }
    }

    /// Decides the probes' masks with `head` at stage-2 step `step` (`extractor` as
    /// [`MaskInference::new`] takes it); returns the share of probe pixels whose mask flipped
    /// since the previous check (`None` at the first).
    pub fn check(
        &mut self,
        session: &Session,
        head: &SegHead,
        extractor: Option<&dyn FeatureExtractor>,
        step: usize,
    ) -> Result<Option<f64>, RunError> {
        let inference = MaskInference::new(session, head, extractor)?;
        let masks = self
            .probes
            .iter()
            .enumerate()
            .map(|(i, camera)| Ok(inference.segment(camera, &format!("probe {i} at stage 2 step {step}"))?.foreground))
            .collect::<Result<Vec<_>, RunError>>()?;
        let change = self.previous.as_ref().map(|previous| {
            let pixels: usize = masks.iter().map(Vec::len).sum();
            let changed: f64 = previous
                .iter()
                .zip(&masks)
                .zip(&self.probes)
                .map(|((a, b), camera)| mask_change(a, b, camera.width as usize) * a.len() as f64)
                .sum();
            changed / pixels.max(1) as f64
        });
        if let Some(c) = change {
            self.record(c);
        }
        self.previous = Some(masks);
        Ok(change)
    }

    /// Counts a check's change towards [`MaskStability::settled`].
    fn record(&mut self, change: f64) {
        self.calm = if change <= self.tolerance { self.calm + 1 } else { 0 };
    }

    /// Whether the last [`CALM_CHECKS`] checks all found the masks calm.
    pub fn settled(&self) -> bool {
        self.calm >= CALM_CHECKS
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w x h` mask: the rectangle `[c0, c1) x [r0, r1)`.
    fn rectangle(w: usize, h: usize, (c0, c1): (usize, usize), (r0, r1): (usize, usize)) -> Vec<bool> {
        (0..w * h).map(|i| (c0..c1).contains(&(i % w)) && (r0..r1).contains(&(i / w))).collect()
    }

    #[test]
    fn an_outline_shifted_by_one_pixel_is_jitter_but_a_moved_region_is_change() {
        let a = rectangle(20, 10, (5, 12), (2, 8));
        assert_eq!(mask_change(&a, &a, 20), 0.0);
        assert_eq!(mask_change(&[], &[], 20), 0.0);
        assert_eq!(mask_change(&a, &rectangle(20, 10, (6, 13), (2, 8)), 20), 0.0);
        // The rectangle grows by three columns: the two beyond the outline's band changed.
        let grown = rectangle(20, 10, (5, 15), (2, 8));
        assert!((mask_change(&a, &grown, 20) - 12.0 / 200.0).abs() < 1e-12);
        // A pixel of background far from the object joins the mask.
        let mut speck = a.clone();
        speck[9 * 20 + 18] = true;
        assert!((mask_change(&a, &speck, 20) - 1.0 / 200.0).abs() < 1e-12);
        // The mask vanishes: the rectangle's inside changed.
        assert!((mask_change(&a, &[false; 200], 20) - 5.0 * 4.0 / 200.0).abs() < 1e-12);
        // Foreground and background swap: everything but the outline changed.
        let inverted: Vec<bool> = a.iter().map(|&f| !f).collect();
        let outline = border_band(&a, 20).iter().filter(|&&b| b).count();
        assert!((mask_change(&a, &inverted, 20) - (200 - outline) as f64 / 200.0).abs() < 1e-12);
    }

    #[test]
    fn settling_takes_calm_checks_in_a_row() {
        let mut stability = MaskStability::new(&crate::testing::scene::blank_scene(3, 20, 10), 0.002);
        let mut settled = Vec::new();
        for change in [0.05, 0.001, 0.01, 0.002, 0.0, 0.0] {
            stability.record(change);
            settled.push(stability.settled());
        }
        assert_eq!(settled, [false, false, false, false, true, true]);
    }

    #[test]
    fn probes_are_shrunk_training_views() {
        let scene = crate::testing::scene::blank_scene(7, 200, 150);
        let probes = probe_cameras(&scene);
        assert_eq!(probes.len(), PROBE_VIEWS);
        assert_eq!((probes[0].width, probes[0].height), (PROBE_SIDE, 72));
        for p in &probes {
            assert!(scene.train.iter().any(|&i| scene.views[i].camera.cam_to_world == p.cam_to_world));
        }
        // Views are never enlarged, and a scene with fewer views probes each of them.
        let small = probe_cameras(&crate::testing::scene::blank_scene(2, 40, 30));
        assert_eq!(small.iter().map(|p| (p.width, p.height)).collect::<Vec<_>>(), vec![(40, 30); 2]);
    }
}
