//! The frozen 2D teacher with a feature cache: features of a patch are computed once per
//! (view, patch placement) while the field is frozen, because the rendered patch — and so its
//! features — cannot change then.

use std::collections::HashMap;

use crate::config::TeacherSource;
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
}

impl Teacher {
    /// A teacher; `cache` only takes effect while [`Teacher::features`] is told the field is
    /// frozen.
    pub fn new(extractor: Box<dyn FeatureExtractor>, source: TeacherSource, cache: bool) -> Self {
        Teacher { extractor, source, cache: cache.then(HashMap::new), hits: 0, misses: 0 }
    }

    /// The extractor (e.g. to compute saliency of whole views).
    pub fn extractor(&self) -> &dyn FeatureExtractor {
        self.extractor.as_ref()
    }

    /// Features of each patch. `rendered[i]` is patch `i` as rendered by the field; with
    /// `teacher_source = "captured"` the photograph's pixels at the patch grid are used
    /// instead. `frozen` says whether rendered patches are reproducible (cache allowed).
    pub fn features(&mut self, scene: &Scene, patches: &[Patch], rendered: &[RgbImage], frozen: bool) -> Vec<FeatureMap> {
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
            let feats = self.extractor.extract(&inputs);
            for (&i, f) in missing.iter().zip(feats) {
                if let (Some(cache), true) = (self.cache.as_mut(), cacheable) {
                    cache.insert(patches[i], f.clone());
                }
                out[i] = Some(f);
            }
        }
        out.into_iter().map(|f| f.expect("every patch has features")).collect()
    }
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
