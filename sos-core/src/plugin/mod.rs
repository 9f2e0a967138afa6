//! The plugin roles. Each role has a typetag'd, non-generic config trait (the TOML side, which
//! validates and builds) and an object-safe runtime trait (the hot path).

pub mod dataset;
pub mod extractor;
pub mod field;
pub mod loss;
pub mod miner;
pub mod state;

pub use dataset::DatasetConfig;
pub use extractor::{BuildContext, FeatureExtractor, FeatureExtractorConfig, FeatureMap};
pub use field::{
    CoarseToFine, FieldMemory, FieldTape, FrozenPass, Hierarchical, HierarchicalSampling, RadianceField,
    RadianceFieldConfig, Regularized,
};
pub use loss::{ContrastiveLoss, ContrastiveLossConfig, LossValue, PatchBatch};
pub use miner::{PairMiner, PairMinerConfig};
