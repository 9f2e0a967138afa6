//! `sos list`: every registered plugin kind per role.

use sos_core::plugin::{
    ContrastiveLossConfig, DatasetConfig, FeatureExtractorConfig, PairMinerConfig, RadianceFieldConfig,
};
use sos_core::registry::{registrations, Registration};

fn section<C: ?Sized + 'static>(out: &mut String, role: &str, table: &str)
where
    Registration<C>: inventory::Collect,
{
    out.push_str(&format!("{role} ([{table}] kind = ...):\n"));
    let all = registrations::<C>();
    if all.is_empty() {
        out.push_str("  (none registered)\n");
    }
    for r in all {
        out.push_str(&format!("  {:<18} {:<22} {}\n", r.kind, format!("({})", r.crate_name), r.summary));
    }
}

/// `sos list`: every registered kind per role, with its crate.
pub fn run() -> anyhow::Result<()> {
    let mut out = String::new();
    section::<dyn DatasetConfig>(&mut out, "datasets", "scene");
    section::<dyn RadianceFieldConfig>(&mut out, "radiance fields", "field");
    section::<dyn FeatureExtractorConfig>(&mut out, "feature extractors", "extractor");
    section::<dyn PairMinerConfig>(&mut out, "pair miners", "miner");
    section::<dyn ContrastiveLossConfig>(&mut out, "contrastive losses", "[loss]");
    super::write_stdout(&out)
}
