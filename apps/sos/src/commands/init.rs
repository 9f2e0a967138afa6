//! `sos init`: a complete default configuration.

use std::path::Path;

use anyhow::{bail, Context};
use sos_core::config::{HeadConfig, MaskConfig, RenderConfig, RunConfig, SegmentConfig, TrainConfig};
use sos_core::plugin::{DatasetConfig, RadianceFieldConfig};
use sos_core::registry::{find, registrations};
use sos_core::segment::defaults;

fn kinds<C: ?Sized + 'static>() -> String
where
    sos_core::registry::Registration<C>: inventory::Collect,
{
    registrations::<C>().iter().map(|r| r.kind).collect::<Vec<_>>().join(", ")
}

/// `sos init`: writes a complete default configuration.
pub fn run(path: Option<&Path>, scene: &str, field: &str) -> anyhow::Result<()> {
    let Some(scene_reg) = find::<dyn DatasetConfig>(scene) else {
        bail!("unknown scene kind `{scene}`; registered: {}", kinds::<dyn DatasetConfig>());
    };
    let Some(field_reg) = find::<dyn RadianceFieldConfig>(field) else {
        bail!("unknown field kind `{field}`; registered: {}", kinds::<dyn RadianceFieldConfig>());
    };
    let config = RunConfig {
        name: "run".into(),
        output_dir: "runs".into(),
        seed: 0,
        scene: (scene_reg.default_config)(),
        field: (field_reg.default_config)(),
        train: TrainConfig::default(),
        render: RenderConfig::default(),
        segment: SegmentConfig::default(),
        head: HeadConfig::default(),
        extractor: defaults::extractor(),
        miner: defaults::miner(),
        loss: defaults::losses(),
        masks: MaskConfig::default(),
    };
    let text = format!("# nerf-sos run configuration (written by `sos init`)\n{}", config.to_toml());
    match path {
        Some(p) => {
            if p.exists() {
                bail!("{} already exists; choose another path or delete it", p.display());
            }
            std::fs::write(p, &text).with_context(|| format!("writing {}", p.display()))?;
            eprintln!("wrote {}", p.display());
        }
        None => super::write_stdout(&text)?,
    }
    Ok(())
}
