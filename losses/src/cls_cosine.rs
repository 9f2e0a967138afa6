//! The reference pair miner: the negative of patch `i` is the patch whose global (CLS)
//! descriptor is least cosine-similar to patch `i`'s (spec §5).

use rand::RngCore;
use serde::{Deserialize, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{PairMiner, PairMinerConfig};

use crate::validate;

const KIND: &str = ClsCosineConfig::KIND;

/// Settings of [`ClsCosineMiner`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClsCosineConfig {
    /// Lower bound of each vector norm in the cosine similarity (torch's `eps`, 1e-8).
    pub eps: f64,
}

impl Default for ClsCosineConfig {
    fn default() -> Self {
        ClsCosineConfig { eps: 1e-8 }
    }
}

sos_core::plugin_kind! {
    kind: "cls-cosine",
    summary: "negative = patch with the least cosine-similar CLS descriptor (reference mining)",
    default: || Box::new(ClsCosineConfig::default()),
    impl PairMinerConfig for ClsCosineConfig {
        fn build(&self) -> Result<Box<dyn PairMiner>, BuildError> {
            validate::positive(KIND, "eps", self.eps)?;
            Ok(Box::new(ClsCosineMiner { eps: self.eps }))
        }
    }
}

/// Picks, for each patch, the patch whose CLS vector has the smallest cosine similarity to its
/// own. Several patches may share a negative and pairs need not be mutual (as the reference).
#[derive(Debug, Clone, PartialEq)]
pub struct ClsCosineMiner {
    /// Lower bound of each vector norm.
    pub eps: f64,
}

impl Default for ClsCosineMiner {
    fn default() -> Self {
        ClsCosineMiner { eps: 1e-8 }
    }
}

/// Cosine-similarity matrix of `vectors` (`n × n`, row-major):
/// `M[i][j] = ⟨vᵢ, vⱼ⟩ / (max(‖vᵢ‖, eps) · max(‖vⱼ‖, eps))`. Computed in f64.
///
/// Vectors of different lengths are compared over their common prefix.
pub fn cosine_matrix(vectors: &[Vec<f32>], eps: f64) -> Vec<f64> {
    let n = vectors.len();
    let norms: Vec<f64> =
        vectors.iter().map(|v| v.iter().map(|&x| f64::from(x) * f64::from(x)).sum::<f64>().sqrt().max(eps)).collect();
    let mut m = vec![0.0f64; n * n];
    for i in 0..n {
        for j in 0..n {
            let dot: f64 = vectors[i].iter().zip(&vectors[j]).map(|(&a, &b)| f64::from(a) * f64::from(b)).sum();
            m[i * n + j] = dot / (norms[i] * norms[j]);
        }
    }
    m
}

/// Negative of each patch: `argmin_{j≠i} M[i][j]` of the cosine matrix (first index on ties;
/// NaN similarities are never preferred). The diagonal is excluded explicitly; with a single
/// patch, the patch itself is returned.
pub fn cls_cosine_negatives(cls: &[Vec<f32>], eps: f64) -> Vec<usize> {
    let n = cls.len();
    if n == 1 {
        return vec![0];
    }
    let m = cosine_matrix(cls, eps);
    (0..n)
        .map(|i| {
            let mut best: Option<(usize, f64)> = None;
            for j in (0..n).filter(|&j| j != i) {
                let v = m[i * n + j];
                best = match best {
                    None => Some((j, v)),
                    Some((_, b)) if v < b || (b.is_nan() && !v.is_nan()) => Some((j, v)),
                    keep => keep,
                };
            }
            best.map_or(i, |(j, _)| j)
        })
        .collect()
}

impl PairMiner for ClsCosineMiner {
    fn negatives(&self, cls: &[Vec<f32>], _rng: &mut dyn RngCore) -> Vec<usize> {
        cls_cosine_negatives(cls, self.eps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixtures::Fixture;

    #[test]
    fn matches_fixture_negatives() {
        let fx = Fixture::appearance();
        let cls = fx.cls();
        let mut rng = rand::rngs::mock::StepRng::new(0, 1);
        let miner = ClsCosineConfig::default().build().expect("default builds");
        assert_eq!(miner.negatives(&cls, &mut rng), fx.neg());
    }

    #[test]
    fn excludes_self_even_when_all_equal() {
        let cls = vec![vec![1.0, 0.0]; 3];
        assert_eq!(cls_cosine_negatives(&cls, 1e-8), vec![1, 0, 0]);
        assert_eq!(cls_cosine_negatives(&cls[..1], 1e-8), vec![0]);
        assert!(cls_cosine_negatives(&[], 1e-8).is_empty());
    }

    #[test]
    fn picks_least_similar() {
        let cls = vec![vec![1.0, 0.0], vec![0.0, 1.0], vec![-1.0, 0.1]];
        assert_eq!(cls_cosine_negatives(&cls, 1e-8), vec![2, 0, 0]);
    }

    #[test]
    fn config_roundtrip_and_validation() {
        let cfg: Box<dyn PairMinerConfig> = Box::new(ClsCosineConfig { eps: 1e-6 });
        let text = toml::to_string(&cfg).expect("serialise");
        assert!(text.contains("kind = \"cls-cosine\""), "{text}");
        let back: Box<dyn PairMinerConfig> = toml::from_str(&text).expect("parse");
        assert_eq!(format!("{back:?}"), format!("{cfg:?}"));
        let err = toml::from_str::<Box<dyn PairMinerConfig>>("kind = \"cls-cosine\"\nepz = 1.0\n");
        assert!(err.is_err(), "unknown key accepted");
        let bad: Box<dyn PairMinerConfig> = toml::from_str("kind = \"cls-cosine\"\neps = 0.0\n").expect("parse");
        assert!(matches!(bad.build(), Err(BuildError::Invalid { .. })));
        assert!(sos_core::registry::find::<dyn PairMinerConfig>(KIND).is_some());
    }
}
