//! Drawing from the world seed: one independent [`SplitMix`] stream per aspect of the world,
//! so that adding a draw to one aspect (say, the distractors) leaves the others unchanged.

use super::super::rig::SplitMix;

/// The aspects of a random world, each with its own stream.
#[derive(Debug, Clone, Copy)]
pub enum Aspect {
    /// Which rig `rig = "random"` becomes.
    Rig,
    /// The foreground composition.
    Composition,
    /// Colours and textures.
    Materials,
    /// The room or the open world.
    Environment,
    /// Camera placement.
    Cameras,
    /// Distractors.
    Distractors,
    /// Light.
    Light,
}

/// The stream of `aspect` for world `seed`.
pub fn stream(seed: u64, aspect: Aspect) -> SplitMix {
    // Mix before seeding: SplitMix streams of nearby seeds are shifted copies of each other.
    let mut z = seed ^ (aspect as u64 + 1).wrapping_mul(0xd6e8_feb8_6659_fd93);
    z = (z ^ (z >> 32)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z ^= z >> 29;
    SplitMix::new(z)
}

/// Convenience draws on top of [`SplitMix::uniform`].
pub trait Draw {
    /// Uniform integer in `0..n` (`n > 0`).
    fn below(&mut self, n: usize) -> usize;
    /// True with probability `p`.
    fn chance(&mut self, p: f32) -> bool;
    /// Index drawn with the given (unnormalised) weights.
    fn weighted(&mut self, weights: &[f32]) -> usize;
    /// Uniform angle in `[0, 2π)`.
    fn angle(&mut self) -> f32;
    /// A `u32` seed for noise.
    fn seed32(&mut self) -> u32;
}

impl Draw for SplitMix {
    fn below(&mut self, n: usize) -> usize {
        ((self.uniform() * n as f32) as usize).min(n - 1)
    }

    fn chance(&mut self, p: f32) -> bool {
        self.uniform() < p
    }

    fn weighted(&mut self, weights: &[f32]) -> usize {
        let total: f32 = weights.iter().sum();
        let mut x = self.uniform() * total;
        for (i, &w) in weights.iter().enumerate() {
            if x < w {
                return i;
            }
            x -= w;
        }
        weights.len() - 1
    }

    fn angle(&mut self) -> f32 {
        self.range(0.0, std::f32::consts::TAU)
    }

    fn seed32(&mut self) -> u32 {
        (self.uniform() * 16_777_216.0) as u32 ^ (((self.uniform() * 256.0) as u32) << 24)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_differ_by_aspect_and_seed_and_draws_stay_in_range() {
        let first = |seed, aspect| stream(seed, aspect).uniform();
        assert_ne!(first(0, Aspect::Rig), first(0, Aspect::Composition));
        assert_ne!(first(0, Aspect::Rig), first(1, Aspect::Rig));
        assert_eq!(first(5, Aspect::Light), first(5, Aspect::Light));
        let mut rng = stream(3, Aspect::Materials);
        let mut counts = [0usize; 3];
        for _ in 0..3000 {
            assert!(rng.below(7) < 7);
            counts[rng.weighted(&[1.0, 2.0, 1.0])] += 1;
            assert!((0.0..std::f32::consts::TAU).contains(&rng.angle()));
        }
        assert!(counts[1] > counts[0] && counts[1] > counts[2], "{counts:?}");
    }
}
