//! Strided patches of rays for stage 2: `P x P` rays spaced `stride` pixels apart, each patch
//! from a different training view, views drawn without replacement within an epoch (as the
//! reference's shuffled data loader does). Patch offsets lie on a coarse grid
//! (`segment.offset_grid`) so that placements recur and the teacher-feature cache can hit.
//! The sampler draws from its own seeded generator: the sequence of patches depends on the
//! seed alone, so a clone of the sampler foresees which placements a run will draw.

use std::collections::BTreeSet;

use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::render::rays::{PatchGrid, RayBatch};
use crate::scene::Scene;

/// One patch: which view and where.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Patch {
    /// Index into `scene.views`.
    pub view: usize,
    /// Pixel grid of the patch.
    pub grid: PatchGrid,
}

/// Draws batches of patches from the training views.
#[derive(Debug, Clone)]
pub struct PatchSampler {
    size: u32,
    wanted_stride: u32,
    offset_grid: u32,
    rng: ChaCha8Rng,
    order: Vec<usize>,
    cursor: usize,
    /// Notices not yet taken about reduced strides (small images).
    notices: Vec<String>,
    /// Image sizes already noticed: each is reported once per run, not once per view or step.
    noticed_sizes: BTreeSet<(u32, u32)>,
}

impl PatchSampler {
    /// A sampler of `size x size` patches with the given stride, offsets on multiples of
    /// `offset_grid` pixels (0 or 1: any pixel), drawing from a generator seeded with `seed`.
    pub fn new(size: u32, stride: u32, offset_grid: u32, seed: u64) -> Self {
        PatchSampler {
            size,
            wanted_stride: stride,
            offset_grid,
            rng: ChaCha8Rng::seed_from_u64(seed),
            order: Vec::new(),
            cursor: 0,
            notices: Vec::new(),
            noticed_sizes: BTreeSet::new(),
        }
    }

    /// Notices about reduced strides, each reported once (the caller logs them).
    pub fn take_notices(&mut self) -> Vec<String> {
        std::mem::take(&mut self.notices)
    }

    /// The stride used for an image of this size, or `None` if not even stride 1 fits.
    pub fn stride_for(&self, width: u32, height: u32) -> Option<u32> {
        PatchGrid::fitting_stride(width, height, self.size, self.wanted_stride)
    }

    /// Number of distinct patch placements in an image of this size (`None` if none fits).
    pub fn placements(&self, width: u32, height: u32) -> Option<u64> {
        let span = (self.size - 1) * self.stride_for(width, height)? + 1;
        let slots = |max: u32| offset_slots(max, self.offset_grid) as u64;
        Some(slots(width - span) * slots(height - span))
    }

    /// Checks that every training view can hold a patch; returns the message of the first
    /// that cannot.
    pub fn check(&self, scene: &Scene) -> Result<(), String> {
        for &v in &scene.train {
            let c = &scene.views[v].camera;
            if self.stride_for(c.width, c.height).is_none() {
                return Err(format!(
                    "view {} is {}x{}, smaller than a {}x{} patch; lower `segment.patch_size`",
                    scene.views[v].name, c.width, c.height, self.size, self.size
                ));
            }
        }
        Ok(())
    }

    /// `n` patches from distinct training views (repeating views only when there are fewer
    /// than `n`), each at a uniformly random grid offset that keeps it inside the image.
    pub fn next_batch(&mut self, scene: &Scene, n: usize) -> Vec<Patch> {
        let mut batch: Vec<Patch> = Vec::with_capacity(n);
        while batch.len() < n {
            if self.cursor >= self.order.len() {
                self.order = scene.train.clone();
                self.order.shuffle(&mut self.rng);
                self.cursor = 0;
            }
            let view = self.order[self.cursor];
            self.cursor += 1;
            let distinct_left = scene.train.len() >= n;
            if distinct_left && batch.iter().any(|p| p.view == view) {
                continue;
            }
            let cam = &scene.views[view].camera;
            let stride = self
                .stride_for(cam.width, cam.height)
                .expect("PatchSampler::check rejects views too small for a patch");
            if stride != self.wanted_stride && self.noticed_sizes.insert((cam.width, cam.height)) {
                self.notices.push(format!(
                    "views of {}x{} are smaller than {} px: patch stride {} instead of {}",
                    cam.width,
                    cam.height,
                    (self.size - 1) * self.wanted_stride + 1,
                    stride,
                    self.wanted_stride
                ));
            }
            let span = (self.size - 1) * stride + 1;
            let col0 = grid_offset(cam.width - span, self.offset_grid, &mut self.rng);
            let row0 = grid_offset(cam.height - span, self.offset_grid, &mut self.rng);
            batch.push(Patch { view, grid: PatchGrid { col0, row0, size: self.size, stride } });
        }
        batch
    }
}

/// Number of allowed offsets in `0..=max`: every pixel when `grid <= 1`, else the multiples of
/// `grid` below `max` and `max` itself.
fn offset_slots(max: u32, grid: u32) -> u32 {
    if grid <= 1 {
        max + 1
    } else {
        max.div_ceil(grid) + 1
    }
}

/// A uniformly drawn allowed offset in `0..=max`. The far edge `max` is a slot of its own so
/// the image's last rows and columns are still covered when `max` is not a multiple of `grid`.
fn grid_offset(max: u32, grid: u32, rng: &mut impl Rng) -> u32 {
    let slot = rng.gen_range(0..offset_slots(max, grid));
    if grid <= 1 {
        slot
    } else {
        (slot * grid).min(max)
    }
}

/// Rays of a batch of patches, patch after patch, each row-major.
pub fn patch_rays(scene: &Scene, patches: &[Patch]) -> RayBatch {
    let mut rays = RayBatch::default();
    for p in patches {
        let cam = &scene.views[p.view].camera;
        for a in 0..p.grid.size {
            for b in 0..p.grid.size {
                let (col, row) = p.grid.pixel(a, b);
                rays.push_pixel(cam, col, row);
            }
        }
    }
    rays
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::scene::blank_scene as scene;

    #[test]
    fn patches_fit_come_from_distinct_views_and_cover_an_epoch() {
        let s = scene(10, 400, 300);
        let mut sampler = PatchSampler::new(64, 6, 0, 1);
        // 300 px is smaller than the 379 px span: the stride shrinks with a notice.
        let batch = sampler.next_batch(&s, 8);
        let mut views: Vec<usize> = batch.iter().map(|p| p.view).collect();
        views.sort();
        views.dedup();
        assert_eq!(views.len(), 8);
        for p in &batch {
            assert_eq!(p.grid.stride, 4);
            let (c, r) = p.grid.pixel(63, 63);
            assert!(c < 400 && r < 300);
        }
        // One notice for the image size, however many views and steps share it.
        assert_eq!(sampler.take_notices().len(), 1);
        sampler.next_batch(&s, 8);
        assert!(sampler.take_notices().is_empty());
        assert_eq!(patch_rays(&s, &batch).len(), 8 * 64 * 64);
    }

    #[test]
    fn too_small_images_are_reported_not_panicked() {
        let s = scene(3, 40, 30);
        let sampler = PatchSampler::new(64, 6, 16, 0);
        let err = sampler.check(&s).unwrap_err();
        assert!(err.contains("40x30") && err.contains("patch_size"), "{err}");
    }

    /// Patches of `steps` batches of 4.
    fn drawn(s: &Scene, sampler: &mut PatchSampler, steps: usize) -> Vec<Patch> {
        (0..steps).flat_map(|_| sampler.next_batch(s, 4)).collect()
    }

    #[test]
    fn offsets_lie_on_the_grid_or_at_the_far_edge_and_inside_the_image() {
        let s = scene(4, 400, 300);
        let mut sampler = PatchSampler::new(64, 6, 16, 7);
        // Stride 4 (300 px is too small for 6): span 253, offsets up to 147 x 47.
        let patches = drawn(&s, &mut sampler, 500);
        let (max_col, max_row) = (400 - 253, 300 - 253);
        let mut cols = std::collections::BTreeSet::new();
        let mut rows = std::collections::BTreeSet::new();
        for p in &patches {
            assert_eq!(p.grid.stride, 4);
            assert!(p.grid.col0 % 16 == 0 || p.grid.col0 == max_col, "{:?}", p.grid);
            assert!(p.grid.row0 % 16 == 0 || p.grid.row0 == max_row, "{:?}", p.grid);
            let (c, r) = p.grid.pixel(63, 63);
            assert!(c < 400 && r < 300, "{:?}", p.grid);
            cols.insert(p.grid.col0);
            rows.insert(p.grid.row0);
        }
        // Every slot is drawn, the far edges included: 0, 16, ..., 144, 147 and 0, 16, 32, 47.
        assert_eq!(cols.len(), 11, "{cols:?}");
        assert_eq!(rows.into_iter().collect::<Vec<_>>(), vec![0, 16, 32, 47]);
        assert_eq!(sampler.placements(400, 300), Some(44));
        // Placements recur: 2000 draws over 4 x 44 placements.
        let mut distinct: Vec<Patch> = patches.clone();
        distinct.sort_by_key(|p| (p.view, p.grid.col0, p.grid.row0));
        distinct.dedup();
        assert_eq!(distinct.len(), 4 * 44);
    }

    #[test]
    fn grid_0_and_1_allow_any_pixel() {
        let s = scene(2, 100, 80);
        for grid in [0, 1] {
            let mut sampler = PatchSampler::new(16, 2, grid, 7);
            // Span 31: offsets up to 69 x 49, every one allowed.
            assert_eq!(sampler.placements(100, 80), Some(70 * 50));
            let patches = drawn(&s, &mut sampler, 2000);
            assert!(patches.iter().any(|p| p.grid.col0 % 2 == 1), "grid {grid}: only even offsets");
            assert!(patches.iter().all(|p| p.grid.col0 <= 69 && p.grid.row0 <= 49));
        }
    }

    #[test]
    fn small_images_and_coarse_grids_still_place_patches() {
        // The patch fills the image exactly: one placement, whatever the grid.
        let exact = scene(2, 64, 64);
        let mut sampler = PatchSampler::new(64, 6, 16, 7);
        assert_eq!(sampler.placements(64, 64), Some(1));
        for p in drawn(&exact, &mut sampler, 10) {
            assert_eq!((p.grid.col0, p.grid.row0, p.grid.stride), (0, 0, 1));
        }
        // A grid coarser than the offset range: the two edges only.
        let small = scene(2, 70, 66);
        let mut sampler = PatchSampler::new(64, 6, 100, 7);
        assert_eq!(sampler.placements(70, 66), Some(4));
        for p in drawn(&small, &mut sampler, 50) {
            assert!([0, 6].contains(&p.grid.col0) && [0, 2].contains(&p.grid.row0), "{:?}", p.grid);
            let (c, r) = p.grid.pixel(63, 63);
            assert!(c < 70 && r < 66);
        }
    }

    #[test]
    fn the_sequence_depends_on_the_seed_alone_and_a_clone_foresees_it() {
        let s = scene(6, 200, 150);
        let mut sampler = PatchSampler::new(32, 3, 8, 5);
        let mut foresight = sampler.clone();
        let ahead = drawn(&s, &mut foresight, 20);
        assert_eq!(drawn(&s, &mut sampler, 20), ahead);
        assert_ne!(drawn(&s, &mut PatchSampler::new(32, 3, 8, 6), 20), ahead);
    }
}
