//! Default stage-2 plugins, looked up in the registry by kind so that the core does not depend
//! on the crates that implement them (they are absent when those crates are not linked).

use crate::config::LossEntry;
use crate::plugin::{ContrastiveLossConfig, FeatureExtractorConfig, PairMinerConfig};
use crate::registry::find;

/// The weight-free teacher, `cell-stats`.
pub const DEFAULT_EXTRACTOR: &str = "cell-stats";
/// The reference's miner, `cls-cosine`.
pub const DEFAULT_MINER: &str = "cls-cosine";
/// The reference's loss terms and weights (λ1 = 1 appearance, λ2 = 0.01 geometry).
pub const DEFAULT_LOSSES: [(&str, f32); 2] = [("appearance", 1.0), ("geometry", 0.01)];

/// Default extractor config, if its kind is registered.
pub fn extractor() -> Option<Box<dyn FeatureExtractorConfig>> {
    find::<dyn FeatureExtractorConfig>(DEFAULT_EXTRACTOR).map(|r| (r.default_config)())
}

/// Default miner config, if its kind is registered.
pub fn miner() -> Option<Box<dyn PairMinerConfig>> {
    find::<dyn PairMinerConfig>(DEFAULT_MINER).map(|r| (r.default_config)())
}

/// Default loss entries whose kinds are registered.
pub fn losses() -> Vec<LossEntry> {
    DEFAULT_LOSSES
        .iter()
        .filter_map(|(kind, weight)| {
            find::<dyn ContrastiveLossConfig>(kind).map(|r| LossEntry { weight: *weight, loss: (r.default_config)() })
        })
        .collect()
}
