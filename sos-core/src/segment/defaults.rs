//! Default stage-2 plugins, looked up in the registry by kind so that the core does not depend
//! on the crates that implement them (they are absent when those crates are not linked).

use serde::{Deserialize, Serialize};

use crate::config::LossEntry;
use crate::error::BuildError;
use crate::plugin::{
    BuildContext, ContrastiveLossConfig, FeatureExtractor, FeatureExtractorConfig, PairMinerConfig, RadianceField,
    RadianceFieldConfig,
};
use crate::registry::find;
use crate::scene::SceneExtent;

/// The field of a config without `[field]`: the fast voxel grid.
pub const DEFAULT_FIELD: &str = "voxel-grid";

/// The weight-free teacher, `cell-stats`.
pub const DEFAULT_EXTRACTOR: &str = "cell-stats";
/// The reference's miner, `cls-cosine`.
pub const DEFAULT_MINER: &str = "cls-cosine";
/// The reference's loss terms and weights (λ1 = 1 appearance, λ2 = 0.01 geometry).
pub const DEFAULT_LOSSES: [(&str, f32); 2] = [("appearance", 1.0), ("geometry", 0.01)];

/// Default field config: [`DEFAULT_FIELD`]'s defaults, or, when that kind is not linked into
/// the program, a placeholder whose `build` says so.
pub fn field() -> Box<dyn RadianceFieldConfig> {
    match find::<dyn RadianceFieldConfig>(DEFAULT_FIELD) {
        Some(r) => (r.default_config)(),
        None => Box::new(UnlinkedDefaultField {}),
    }
}

/// Stands in for the default field in a program that does not link it.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnlinkedDefaultField {}

#[typetag::serde(name = "unlinked-default-field")]
impl RadianceFieldConfig for UnlinkedDefaultField {
    fn build(&self, _extent: &SceneExtent, _seed: u64) -> Result<Box<dyn RadianceField>, BuildError> {
        Err(BuildError::Resource {
            kind: DEFAULT_FIELD.into(),
            message: format!(
                "no `[field]` configured and the default `{DEFAULT_FIELD}` field is not linked into this program"
            ),
        })
    }
}

/// Default extractor config, if its kind is registered.
pub fn extractor() -> Option<Box<dyn FeatureExtractorConfig>> {
    find::<dyn FeatureExtractorConfig>(DEFAULT_EXTRACTOR).map(|r| (r.default_config)())
}

/// The stage-2 teacher of a run: its `[extractor]` table, or [`DEFAULT_EXTRACTOR`]'s defaults;
/// an error when neither is configured nor linked.
pub fn build_extractor(
    configured: Option<&dyn FeatureExtractorConfig>,
    ctx: &BuildContext,
) -> Result<Box<dyn FeatureExtractor>, BuildError> {
    match configured {
        Some(e) => e.build(ctx),
        None => extractor().ok_or_else(|| not_linked("extractor", DEFAULT_EXTRACTOR, "extractor"))?.build(ctx),
    }
}

/// The error for a stage-2 role with no table and no linked default.
pub fn not_linked(role: &str, kind: &str, table: &str) -> BuildError {
    BuildError::Resource {
        kind: kind.into(),
        message: format!("no `[{table}]` configured and the default `{kind}` {role} is not linked into this program"),
    }
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
