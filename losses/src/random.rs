//! A random pair miner: a uniformly random derangement (the reference's `--rand_neg`,
//! STEGO's `super_perm`), ignoring the descriptors.

use rand::seq::SliceRandom;
use rand::RngCore;
use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{PairMiner, PairMinerConfig};

/// Settings of [`RandomMiner`] (none).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RandomConfig {}

sos_core::plugin_kind! {
    kind: "random",
    summary: "negative = a uniformly random derangement of the batch",
    default: || Box::new(RandomConfig::default()),
    impl PairMinerConfig for RandomConfig {
        fn build(&self) -> Result<Box<dyn PairMiner>, BuildError> {
            Ok(Box::new(RandomMiner))
        }
    }
}

/// Pairs each patch with a different, uniformly random one: the negatives form a derangement
/// drawn uniformly among all derangements of the batch.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RandomMiner;

/// A uniformly random derangement of `0..n` (no fixed point). For `n ≤ 1` there is none; the
/// identity is returned.
pub fn random_derangement(n: usize, rng: &mut dyn RngCore) -> Vec<usize> {
    let mut perm: Vec<usize> = (0..n).collect();
    if n <= 1 {
        return perm;
    }
    // Rejection sampling of uniform permutations is uniform over derangements and needs
    // about e ≈ 2.72 tries on average.
    loop {
        perm.shuffle(rng);
        if perm.iter().enumerate().all(|(i, &p)| i != p) {
            return perm;
        }
    }
}

impl PairMiner for RandomMiner {
    fn negatives(&self, cls: &[Vec<f32>], rng: &mut dyn RngCore) -> Vec<usize> {
        random_derangement(cls.len(), rng)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use std::collections::HashMap;

    #[test]
    fn derangement_is_uniform_and_fixed_point_free() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut counts: HashMap<Vec<usize>, usize> = HashMap::new();
        let trials = 9000;
        for _ in 0..trials {
            let d = random_derangement(4, &mut rng);
            let mut sorted = d.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, vec![0, 1, 2, 3]);
            assert!(d.iter().enumerate().all(|(i, &p)| i != p), "{d:?}");
            *counts.entry(d).or_default() += 1;
        }
        // 4 elements have 9 derangements; each should get about 1000 draws.
        assert_eq!(counts.len(), 9);
        for (d, c) in counts {
            assert!((800..1200).contains(&c), "{d:?} drawn {c} times");
        }
    }

    #[test]
    fn trivial_sizes() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        assert!(random_derangement(0, &mut rng).is_empty());
        assert_eq!(random_derangement(1, &mut rng), vec![0]);
        assert_eq!(random_derangement(2, &mut rng), vec![1, 0]);
        let miner = RandomConfig::default().build().expect("builds");
        let neg = miner.negatives(&vec![vec![0.0f32]; 5], &mut rng);
        assert_eq!(neg.len(), 5);
    }

    #[test]
    fn config_roundtrip_and_unknown_key() {
        let cfg: Box<dyn PairMinerConfig> = Box::new(RandomConfig::default());
        let text = toml::to_string(&cfg).expect("serialise");
        let back: Box<dyn PairMinerConfig> = toml::from_str(&text).expect("parse");
        assert_eq!(format!("{back:?}"), format!("{cfg:?}"));
        assert!(toml::from_str::<Box<dyn PairMinerConfig>>("kind = \"random\"\nseed = 1\n").is_err());
        assert!(sos_core::registry::find::<dyn PairMinerConfig>("random").is_some());
    }
}
