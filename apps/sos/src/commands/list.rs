//! `sos list`: every registered plugin kind per role.

use sos_core::plugin::{
    ContrastiveLossConfig, DatasetConfig, FeatureExtractorConfig, PairMinerConfig, RadianceFieldConfig,
};
use sos_core::registry::{registrations, Registration};

fn section<C: ?Sized + 'static>(role: &str, table: &str)
where
    Registration<C>: inventory::Collect,
{
    println!("{role} ([{table}] kind = ...):");
    let all = registrations::<C>();
    if all.is_empty() {
        println!("  (none registered)");
    }
    for r in all {
        println!("  {:<18} {:<22} {}", r.kind, format!("({})", r.crate_name), r.summary);
    }
}

/// `sos list`: every registered kind per role, with its crate.
pub fn run() -> anyhow::Result<()> {
    section::<dyn DatasetConfig>("datasets", "scene");
    section::<dyn RadianceFieldConfig>("radiance fields", "field");
    section::<dyn FeatureExtractorConfig>("feature extractors", "extractor");
    section::<dyn PairMinerConfig>("pair miners", "miner");
    section::<dyn ContrastiveLossConfig>("contrastive losses", "[loss]");
    Ok(())
}
