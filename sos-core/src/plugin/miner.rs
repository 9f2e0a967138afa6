//! The pair-mining role: chooses a negative partner for each patch of a batch.

use rand::RngCore;

use crate::error::BuildError;
use crate::registry::Registration;

/// Chooses, for each patch `i`, the index of its negative partner (never `i` itself when the
/// batch has more than one patch).
pub trait PairMiner: Send + Sync {
    /// `cls[i]` is patch `i`'s global descriptor. Returns one negative index per patch.
    fn negatives(&self, cls: &[Vec<f32>], rng: &mut dyn RngCore) -> Vec<usize>;
}

/// Configuration of a pair miner, chosen by `[miner] kind = "..."`.
#[typetag::serde(tag = "kind")]
pub trait PairMinerConfig: std::fmt::Debug + Send + Sync {
    /// Validates the settings and builds the miner.
    fn build(&self) -> Result<Box<dyn PairMiner>, BuildError>;
}

inventory::collect!(Registration<dyn PairMinerConfig>);
