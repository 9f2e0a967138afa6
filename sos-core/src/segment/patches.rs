//! Strided patches of rays for stage 2: `P x P` rays spaced `stride` pixels apart, each patch
//! from a different training view, views drawn without replacement within an epoch (as the
//! reference's shuffled data loader does).

use rand::seq::SliceRandom;
use rand::Rng;

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
    order: Vec<usize>,
    cursor: usize,
    /// Strides actually used per view (smaller than wanted for small images).
    notices: Vec<String>,
}

impl PatchSampler {
    /// A sampler of `size x size` patches with the given stride.
    pub fn new(size: u32, stride: u32) -> Self {
        PatchSampler { size, wanted_stride: stride, order: Vec::new(), cursor: 0, notices: Vec::new() }
    }

    /// Notices about reduced strides, each reported once (the caller logs them).
    pub fn take_notices(&mut self) -> Vec<String> {
        std::mem::take(&mut self.notices)
    }

    /// The stride used for an image of this size, or `None` if not even stride 1 fits.
    pub fn stride_for(&self, width: u32, height: u32) -> Option<u32> {
        PatchGrid::fitting_stride(width, height, self.size, self.wanted_stride)
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
    /// than `n`), each at a uniformly random offset that keeps it inside the image.
    pub fn next_batch(&mut self, scene: &Scene, n: usize, rng: &mut impl Rng) -> Vec<Patch> {
        let mut batch: Vec<Patch> = Vec::with_capacity(n);
        while batch.len() < n {
            if self.cursor >= self.order.len() {
                self.order = scene.train.clone();
                self.order.shuffle(rng);
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
            if stride != self.wanted_stride {
                let msg = format!(
                    "view {} ({}x{}) is smaller than {} px: patch stride {} instead of {}",
                    scene.views[view].name,
                    cam.width,
                    cam.height,
                    (self.size - 1) * self.wanted_stride + 1,
                    stride,
                    self.wanted_stride
                );
                if !self.notices.contains(&msg) {
                    self.notices.push(msg);
                }
            }
            let span = (self.size - 1) * stride + 1;
            let col0 = rng.gen_range(0..=cam.width - span);
            let row0 = rng.gen_range(0..=cam.height - span);
            batch.push(Patch { view, grid: PatchGrid { col0, row0, size: self.size, stride } });
        }
        batch
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
    use crate::camera::Camera;
    use crate::image::RgbImage;
    use crate::scene::{SceneExtent, View};
    use rand::SeedableRng;

    fn scene(n: usize, w: u32, h: u32) -> Scene {
        let views = (0..n)
            .map(|i| View {
                name: format!("v{i}"),
                camera: Camera::look_at([0.0, 0.0, 3.0 + i as f32], [0.0; 3], [0.0, 1.0, 0.0], w, h, 100.0),
                image: RgbImage::new(w as usize, h as usize),
                mask: None,
            })
            .collect();
        Scene {
            name: "t".into(),
            views,
            train: (0..n).collect(),
            test: vec![],
            extent: SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] },
            near: 0.0,
            render_path: vec![],
        }
    }

    #[test]
    fn patches_fit_come_from_distinct_views_and_cover_an_epoch() {
        let s = scene(10, 400, 300);
        let mut sampler = PatchSampler::new(64, 6);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        // 300 px is smaller than the 379 px span: the stride shrinks with a notice.
        let batch = sampler.next_batch(&s, 8, &mut rng);
        let mut views: Vec<usize> = batch.iter().map(|p| p.view).collect();
        views.sort();
        views.dedup();
        assert_eq!(views.len(), 8);
        for p in &batch {
            assert_eq!(p.grid.stride, 4);
            let (c, r) = p.grid.pixel(63, 63);
            assert!(c < 400 && r < 300);
        }
        assert_eq!(sampler.take_notices().len(), 8);
        assert_eq!(patch_rays(&s, &batch).len(), 8 * 64 * 64);
    }

    #[test]
    fn too_small_images_are_reported_not_panicked() {
        let s = scene(3, 40, 30);
        let sampler = PatchSampler::new(64, 6);
        let err = sampler.check(&s).unwrap_err();
        assert!(err.contains("40x30") && err.contains("patch_size"), "{err}");
    }
}
