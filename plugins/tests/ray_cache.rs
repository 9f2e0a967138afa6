//! Stage 2 with the head at the surface looks up the patch rays it rendered before: every
//! ray's result equals a fresh render of it bit for bit, whatever the memory budget, and rays
//! that recur are not rendered again.

mod common;

use std::collections::HashSet;

use common::tiny_session;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sos_core::render::memory_budget::MemoryBudget;
use sos_core::segment::frozen_render::FrozenRender;
use sos_core::segment::patches::{patch_rays, PatchSampler};
use sos_core::segment::ray_cache::patch_keys;
use sos_core::train::photometric::train_photometric;
// Links every plugin so the config kinds resolve.
use sos_plugins as _;

#[test]
fn cached_rays_equal_fresh_renders_and_recurring_rays_are_not_rendered_again() {
    let mut s = tiny_session("voxel-grid", "object-centric", "", 40, "ray-cache");
    train_photometric(&mut s).unwrap();
    let bits = |c: &sos_core::render::composite::RayColour| {
        [c.rgb[0], c.rgb[1], c.rgb[2], c.depth, c.acc, c.median_depth].map(f32::to_bits)
    };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for (budget, keeps) in [(MemoryBudget::unlimited(), true), (MemoryBudget::none(), false)] {
        // 8x8 patches at stride 2 on a 4-pixel offset grid: placements overlap and recur.
        let mut sampler = PatchSampler::new(8, 2, 4, 11);
        let mut cached = FrozenRender::new(budget);
        let (mut drawn, mut distinct) = (0, HashSet::new());
        for step in 0..12 {
            let patches = sampler.next_batch(&s.scene, 3);
            let rays = patch_rays(&s.scene, &patches);
            drawn += rays.len();
            distinct.extend(patch_keys(&patches));
            let before = cached.cached_rays();
            let (colours, timing) = cached.colours(&s, &rays, &patch_keys(&patches), &mut rng);
            let fresh = FrozenRender::new(budget).render(&s, &rays, false, false, &mut rng);
            assert_eq!(colours.len(), rays.len());
            for (i, (got, want)) in colours.iter().zip(&fresh.colours).enumerate() {
                assert_eq!(bits(got), bits(want), "step {step}, ray {i}: cached {got:?}, rendered {want:?}");
            }
            let added = cached.cached_rays() - before;
            if keeps {
                // Whatever was not held before was rendered now, and is held from now on.
                assert!(timing.candidates > 0 || added == 0, "step {step}: rays were added without a render");
            } else {
                assert_eq!(added, 0, "a zero budget holds nothing");
                assert!(timing.candidates > 0, "step {step}: without a cache every ray is rendered");
            }
        }
        if keeps {
            // One entry per distinct ray, fewer than were drawn: placements recur.
            assert_eq!(cached.cached_rays(), distinct.len());
            assert!(distinct.len() < drawn * 3 / 4, "{} distinct rays of {drawn} drawn", distinct.len());
            // Every ray of a batch already seen: nothing is rendered.
            let patches = sampler.next_batch(&s.scene, 3);
            let rays = patch_rays(&s.scene, &patches);
            let keys = patch_keys(&patches);
            cached.colours(&s, &rays, &keys, &mut rng);
            let (_, timing) = cached.colours(&s, &rays, &keys, &mut rng);
            assert_eq!(timing.candidates, 0, "a batch seen before must not be rendered again");
        }
    }
}
