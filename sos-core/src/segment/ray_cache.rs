//! Each patch ray's render by the frozen field, kept from step to step of stage 2.
//!
//! With the head at the surface (`segment.logits = "surface"`) and the field frozen, a stage-2
//! step needs of each ray only its composited result (colour, depth, opacity and surface depth),
//! and the render of a ray is deterministic: evaluation marching is not stratified. Patch
//! offsets lie on a coarse grid (`segment.offset_grid`) and patches are strided, so the rays of
//! a run fall on a small lattice of pixels per view and recur step after step: rendering each
//! once and looking it up afterwards gives the same results as rendering it every time, in a
//! fraction of the time.

use std::collections::HashMap;

use crate::render::composite::RayColour;
use crate::segment::patches::Patch;

/// Bytes one entry takes, the map's own overhead included (an estimate for the budget).
const ENTRY_BYTES: usize = 48;

/// Where a ray comes from: its view and pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct RayKey {
    view: u32,
    col: u32,
    row: u32,
}

/// The key of every ray of a batch of patches, in the order [`crate::segment::patches::patch_rays`]
/// places them (patch after patch, each row-major).
pub fn patch_keys(patches: &[Patch]) -> Vec<RayKey> {
    let mut keys = Vec::with_capacity(patches.iter().map(|p| (p.grid.size * p.grid.size) as usize).sum());
    for p in patches {
        for a in 0..p.grid.size {
            for b in 0..p.grid.size {
                let (col, row) = p.grid.pixel(a, b);
                keys.push(RayKey { view: p.view as u32, col, row });
            }
        }
    }
    keys
}

/// Rendered rays by where they come from, up to a memory budget: once full, new rays are
/// rendered every time they recur (slower, same results).
#[derive(Debug, Default)]
pub struct RayCache {
    entries: HashMap<RayKey, RayColour>,
    capacity: usize,
}

impl RayCache {
    /// An empty cache that holds at most `bytes` of entries.
    pub fn with_budget(bytes: usize) -> RayCache {
        RayCache { entries: HashMap::new(), capacity: bytes / ENTRY_BYTES }
    }

    /// Rays held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no ray is held.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Each key's cached render, `None` where it has none.
    pub fn lookup(&self, keys: &[RayKey]) -> Vec<Option<RayColour>> {
        keys.iter().map(|k| self.entries.get(k).copied()).collect()
    }

    /// Keeps `colour` as the render of `key` while the budget allows.
    pub fn insert(&mut self, key: RayKey, colour: RayColour) {
        if self.entries.len() < self.capacity {
            self.entries.insert(key, colour);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::rays::PatchGrid;

    fn colour(v: f32) -> RayColour {
        RayColour { rgb: [v; 3], depth: v, acc: 1.0, median_depth: v }
    }

    #[test]
    fn keys_follow_the_patch_ray_order() {
        let patches = [
            Patch { view: 2, grid: PatchGrid { col0: 10, row0: 20, size: 2, stride: 3 } },
            Patch { view: 0, grid: PatchGrid { col0: 0, row0: 0, size: 1, stride: 1 } },
        ];
        let keys = patch_keys(&patches);
        let at = |view, col, row| RayKey { view, col, row };
        assert_eq!(keys, [at(2, 10, 20), at(2, 13, 20), at(2, 10, 23), at(2, 13, 23), at(0, 0, 0)]);
    }

    #[test]
    fn lookups_find_what_was_kept_and_the_budget_bounds_it() {
        let keys: Vec<RayKey> = (0..4).map(|i| RayKey { view: 0, col: i, row: 0 }).collect();
        let mut cache = RayCache::with_budget(2 * ENTRY_BYTES);
        assert!(cache.lookup(&keys).iter().all(Option::is_none));
        for (i, &k) in keys.iter().enumerate() {
            cache.insert(k, colour(i as f32));
        }
        assert_eq!(cache.len(), 2, "the budget holds two entries");
        assert_eq!(cache.lookup(&keys), [Some(colour(0.0)), Some(colour(1.0)), None, None]);
        // Another view's pixel is another ray.
        assert_eq!(cache.lookup(&[RayKey { view: 1, col: 0, row: 0 }]), [None]);
        assert!(RayCache::with_budget(0).lookup(&keys).iter().all(Option::is_none));
    }
}
