//! The frozen 2D teacher with a feature cache: features of a patch are computed once per
//! (view, patch placement) while the field is frozen, because the rendered patch — and so its
//! features — cannot change then.

use std::collections::HashMap;
use std::time::Instant;

use crate::config::TeacherSource;
use crate::error::{ExtractError, RunError};
use crate::image::RgbImage;
use crate::plugin::{FeatureExtractor, FeatureMap};
use crate::scene::Scene;
use crate::segment::patches::Patch;

/// A teacher extractor, its input source and its cache.
pub struct Teacher {
    extractor: Box<dyn FeatureExtractor>,
    source: TeacherSource,
    cache: Option<HashMap<Patch, FeatureMap>>,
    /// Patches served from the cache.
    pub hits: usize,
    /// Patches computed by the extractor.
    pub misses: usize,
    /// Wall-clock seconds spent in the extractor.
    pub seconds: f64,
}

impl Teacher {
    /// A teacher; `cache` only takes effect while [`Teacher::features`] is told the field is
    /// frozen.
    pub fn new(extractor: Box<dyn FeatureExtractor>, source: TeacherSource, cache: bool) -> Self {
        Teacher { extractor, source, cache: cache.then(HashMap::new), hits: 0, misses: 0, seconds: 0.0 }
    }

    /// The extractor (e.g. to compute saliency of whole views).
    pub fn extractor(&self) -> &dyn FeatureExtractor {
        self.extractor.as_ref()
    }

    /// Features of each patch. `rendered[i]` is patch `i` as rendered by the field; with
    /// `teacher_source = "captured"` the photograph's pixels at the patch grid are used
    /// instead. `frozen` says whether rendered patches are reproducible (cache allowed).
    /// An extractor failure is an error naming the patches' views.
    pub fn features(
        &mut self,
        scene: &Scene,
        patches: &[Patch],
        rendered: &[RgbImage],
        frozen: bool,
    ) -> Result<Vec<FeatureMap>, RunError> {
        let cacheable = frozen || self.source == TeacherSource::Captured;
        let mut out: Vec<Option<FeatureMap>> = vec![None; patches.len()];
        if let (Some(cache), true) = (&self.cache, cacheable) {
            for (i, p) in patches.iter().enumerate() {
                out[i] = cache.get(p).cloned();
            }
        }
        let missing: Vec<usize> = (0..patches.len()).filter(|&i| out[i].is_none()).collect();
        self.hits += patches.len() - missing.len();
        self.misses += missing.len();
        if !missing.is_empty() {
            let inputs: Vec<RgbImage> = missing
                .iter()
                .map(|&i| match self.source {
                    TeacherSource::Rendered => rendered[i].clone(),
                    TeacherSource::Captured => captured_patch(scene, &patches[i]),
                })
                .collect();
            let views: Vec<RgbImage> = missing.iter().map(|&i| strided_view(scene, &patches[i])).collect();
            let started = Instant::now();
            let feats = self.extractor.extract_in_views(&inputs, &views).and_then(|f| {
                if f.len() == inputs.len() {
                    Ok(f)
                } else {
                    // A broken implementation, named by its full identity.
                    let message = format!("returned {} feature maps for {} images", f.len(), inputs.len());
                    Err(ExtractError::new(self.extractor.identity(), message))
                }
            });
            self.seconds += started.elapsed().as_secs_f64();
            let feats = feats
                .map_err(|source| RunError::Teacher { context: patch_context(scene, patches, &missing), source })?;
            for (&i, f) in missing.iter().zip(feats) {
                if let (Some(cache), true) = (self.cache.as_mut(), cacheable) {
                    cache.insert(patches[i], f.clone());
                }
                out[i] = Some(f);
            }
        }
        // Every entry is filled: from the cache or from the extractor's checked output.
        Ok(out.into_iter().flatten().collect())
    }
}

/// Which patches the teacher was given, for error messages.
fn patch_context(scene: &Scene, patches: &[Patch], which: &[usize]) -> String {
    let names: Vec<String> = which
        .iter()
        .map(|&i| {
            let p = &patches[i];
            format!("{} at ({}, {})", scene.views[p.view].name, p.grid.col0, p.grid.row0)
        })
        .collect();
    format!("stage-2 patches of views {}", names.join(", "))
}

/// The photograph's pixels at a patch's ray positions.
pub fn captured_patch(scene: &Scene, patch: &Patch) -> RgbImage {
    let n = patch.grid.size as usize;
    let img = &scene.views[patch.view].image;
    let mut out = RgbImage::new(n, n);
    for a in 0..n {
        for b in 0..n {
            let (col, row) = patch.grid.pixel(a as u32, b as u32);
            out.set_pixel(b, a, img.pixel(col as usize, row as usize));
        }
    }
    out
}

/// The photograph a patch was cut from, sampled at the patch's stride on the patch's pixel
/// lattice (the extractor's view of the patch's surroundings at the patch's scale).
pub fn strided_view(scene: &Scene, patch: &Patch) -> RgbImage {
    let img = &scene.views[patch.view].image;
    let s = patch.grid.stride.max(1) as usize;
    let (c0, r0) = (patch.grid.col0 as usize % s, patch.grid.row0 as usize % s);
    let (w, h) = (img.width.saturating_sub(c0).div_ceil(s), img.height.saturating_sub(r0).div_ceil(s));
    let mut out = RgbImage::new(w, h);
    for y in 0..h {
        for x in 0..w {
            out.set_pixel(x, y, img.pixel(c0 + x * s, r0 + y * s));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::rays::PatchGrid;
    use crate::testing::scene::blank_scene;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Counts the images it is given; fails on batches larger than `fail_above`.
    struct Counting {
        images: AtomicUsize,
        fail_above: usize,
    }

    impl FeatureExtractor for Counting {
        fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
            if images.len() > self.fail_above {
                return Err(ExtractError::new("counting", "the runtime rejected the batch"));
            }
            self.images.fetch_add(images.len(), Ordering::Relaxed);
            let map = FeatureMap { channels: 1, height: 1, width: 1, data: vec![1.0], cls: vec![1.0], saliency: None };
            Ok(vec![map; images.len()])
        }

        fn identity(&self) -> String {
            "counting/v1".into()
        }
    }

    fn teacher(fail_above: usize) -> Teacher {
        let extractor = Counting { images: AtomicUsize::new(0), fail_above };
        Teacher::new(Box::new(extractor), TeacherSource::Captured, true)
    }

    fn patch(view: usize, col0: u32) -> Patch {
        Patch { view, grid: PatchGrid { col0, row0: 0, size: 4, stride: 1 } }
    }

    #[test]
    fn repeated_placements_hit_the_cache() {
        let scene = blank_scene(3, 16, 8);
        let mut t = teacher(usize::MAX);
        let first = [patch(0, 0), patch(1, 0), patch(2, 4)];
        assert_eq!(t.features(&scene, &first, &[], true).unwrap().len(), 3);
        let again = [patch(2, 4), patch(0, 0), patch(0, 8)];
        assert_eq!(t.features(&scene, &again, &[], true).unwrap().len(), 3);
        assert_eq!((t.hits, t.misses), (2, 4));
    }

    /// Answers each patch with one cell holding the size of the view it was given.
    struct ViewSizes;

    impl FeatureExtractor for ViewSizes {
        fn extract(&self, images: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
            self.extract_in_views(images, &vec![RgbImage::new(0, 0); images.len()])
        }

        fn extract_in_views(&self, _: &[RgbImage], views: &[RgbImage]) -> Result<Vec<FeatureMap>, ExtractError> {
            let size = |v: &RgbImage| vec![v.width as f32, v.height as f32];
            let map = |v| FeatureMap { channels: 2, height: 1, width: 1, data: size(v), cls: size(v), saliency: None };
            Ok(views.iter().map(map).collect())
        }

        fn identity(&self) -> String {
            "view-sizes/v1".into()
        }
    }

    #[test]
    fn the_strided_view_holds_the_patch_on_its_lattice() {
        let mut scene = blank_scene(2, 17, 9);
        for (i, view) in scene.views.iter_mut().enumerate() {
            for r in 0..9 {
                for c in 0..17 {
                    view.image.set_pixel(c, r, [c as f32, r as f32, i as f32]);
                }
            }
        }
        let p = Patch { view: 1, grid: PatchGrid { col0: 5, row0: 2, size: 3, stride: 3 } };
        let view = strided_view(&scene, &p);
        // Columns 2, 5, ..., 14 and rows 2, 5, 8 of view 1.
        assert_eq!((view.width, view.height), (5, 3));
        assert_eq!(view.pixel(0, 0), [2.0, 2.0, 1.0]);
        assert_eq!(view.pixel(4, 2), [14.0, 8.0, 1.0]);
        let patch = captured_patch(&scene, &p);
        for a in 0..3 {
            for b in 0..3 {
                assert_eq!(patch.pixel(b, a), view.pixel(1 + b, a), "ray ({a}, {b})");
            }
        }
        // The teacher gives the extractor each patch's strided view.
        let mut t = Teacher::new(Box::new(ViewSizes), TeacherSource::Captured, false);
        let unit = Patch { view: 0, grid: PatchGrid { col0: 0, row0: 0, size: 4, stride: 1 } };
        let maps = t.features(&scene, &[p, unit], &[], true).unwrap();
        assert_eq!((maps[0].data.as_slice(), maps[1].data.as_slice()), ([5.0, 3.0].as_slice(), [17.0, 9.0].as_slice()));
    }

    #[test]
    fn an_extractor_failure_is_an_error_naming_the_views() {
        let scene = blank_scene(3, 16, 8);
        let mut t = teacher(1);
        let err = t.features(&scene, &[patch(1, 0), patch(2, 4)], &[], true).unwrap_err();
        assert!(matches!(err, RunError::Teacher { .. }), "{err:?}");
        let chain = format!("{err}: {}", std::error::Error::source(&err).unwrap());
        assert!(chain.contains("v1 at (0, 0)") && chain.contains("v2 at (4, 0)"), "{chain}");
        assert!(chain.contains("counting") && chain.contains("rejected"), "{chain}");
    }
}
