//! Settings derived from the loaded scene where the config leaves them unset: the patch stride
//! from the view size, the teacher's grid from the patch, the extent and `near` from the
//! cameras (by the dataset adapters). Each is printed at the start of a run and written into
//! the run's resolved config, so a run states what it used; setting the key pins it (an
//! unbounded extent has no key: set `aabb` for a box instead).

/// Bumped whenever a derivation rule or its constants change, so that cached benchmark
/// results made under the old rules are not reused (`sos bench` hashes it with each run).
pub const DERIVATION_VERSION: u32 = 5;

use std::fmt;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::RunConfig;
use crate::render::rays::PatchGrid;
use crate::scene::Scene;
use crate::segment::defaults;

/// One setting a run chose for itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DerivedSetting {
    /// Dotted config path, e.g. `segment.stride` or `scene.extent`.
    pub key: String,
    /// The value, as it would be written in the config (or described, for the extent).
    pub value: String,
    /// What it follows from, in a few words.
    pub reason: String,
}

impl DerivedSetting {
    /// A setting with its value and reason.
    pub fn new(key: impl Into<String>, value: impl fmt::Display, reason: impl Into<String>) -> Self {
        DerivedSetting { key: key.into(), value: value.to_string(), reason: reason.into() }
    }
}

impl fmt::Display for DerivedSetting {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} = {}  ({})", self.key, self.value, self.reason)
    }
}

/// What a teacher's settings may follow from: the patches stage 2 shows it, and the views they
/// are cut from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PatchFacts {
    /// Rays per patch side (the teacher's input image is this many pixels wide).
    pub patch_size: u32,
    /// View pixels between neighbouring rays of a patch.
    pub stride: u32,
    /// Whether the training views all look one way (a forward-facing rig, see
    /// [`Scene::shared_view_axis`]): their borders then show the same walls and floor.
    pub views_look_one_way: bool,
}

impl PatchFacts {
    /// The facts of the patches a run's stage 2 cuts from `scene`'s views.
    pub fn of_run(segment: &crate::config::SegmentConfig, scene: &Scene) -> PatchFacts {
        PatchFacts {
            patch_size: segment.patch_size,
            stride: segment.stride,
            views_look_one_way: scene.shared_view_axis().is_some(),
        }
    }
}

/// Fills the settings the config leaves to the scene and returns what it chose, the
/// dataset adapter's own choices (extent, `near`) first. Deterministic: a resumed run derives the
/// same values.
pub fn derive_settings(config: &mut RunConfig, config_dir: &Path, scene: &Scene) -> Vec<DerivedSetting> {
    let mut derived = config.scene.derived(config_dir, scene);
    if config.render.memory_gib.is_none() {
        let (gib, why) = crate::render::memory_budget::machine_default_gib();
        derived.push(DerivedSetting::new("render.memory_gib", gib, why));
        config.render.memory_gib = Some(gib);
    }
    let seg = &mut config.segment;
    if seg.steps == 0 {
        return derived;
    }
    // One view size: the stride it allows is written into the config. Views of mixed sizes
    // keep the configured stride, which the sampler reduces per size, with a notice.
    let sizes: Vec<(u32, u32)> =
        scene.train.iter().map(|&i| (scene.views[i].camera.width, scene.views[i].camera.height)).collect();
    if let Some(&(width, height)) = sizes.first().filter(|first| sizes.iter().all(|s| s == *first)) {
        if let Some(stride) = PatchGrid::fitting_stride(width, height, seg.patch_size, seg.stride) {
            if stride != seg.stride {
                derived.push(DerivedSetting::new(
                    "segment.stride",
                    stride,
                    format!(
                        "the widest stride up to {} whose {}-ray patch fits the {width}x{height} views",
                        seg.stride, seg.patch_size
                    ),
                ));
                seg.stride = stride;
            }
        }
    }
    let patch = PatchFacts::of_run(seg, scene);
    if config.extractor.is_none() {
        config.extractor = defaults::extractor();
    }
    if let Some(extractor) = config.extractor.as_mut() {
        derived.extend(extractor.derive_for(&patch));
    }
    derived
}
