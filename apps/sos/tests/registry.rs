//! Every registered kind of every role, with no list to keep up to date: its registration and
//! its typetag name agree, its default config round-trips through TOML unchanged, and it
//! builds (or, for a backbone whose weights are not on this machine, says which resource is
//! missing).

use serde::{de::DeserializeOwned, Serialize};
use sos_core::error::BuildError;
use sos_core::plugin::{
    BuildContext, ContrastiveLossConfig, DatasetConfig, FeatureExtractorConfig, PairMinerConfig, RadianceFieldConfig,
};
use sos_core::registry::{registrations, Registration};
use sos_core::scene::SceneExtent;
// Links every plugin crate's registrations into this test binary.
use sos_plugins as _;

/// Round-trips each kind's default config of role `C` and returns the configs read back.
fn round_trip_all<C>(role: &str) -> Vec<(&'static str, Box<C>)>
where
    C: ?Sized + 'static,
    Registration<C>: inventory::Collect,
    Box<C>: Serialize + DeserializeOwned,
{
    let all = registrations::<C>();
    assert!(!all.is_empty(), "no {role} is registered");
    all.iter()
        .map(|reg| {
            let config = (reg.default_config)();
            let text =
                toml::to_string(&config).unwrap_or_else(|e| panic!("{role} `{}`: cannot write TOML: {e}", reg.kind));
            let table: toml::Table = toml::from_str(&text).expect("written TOML parses");
            assert_eq!(
                table.get("kind").and_then(|k| k.as_str()),
                Some(reg.kind),
                "{role} `{}`: the registration and the typetag name differ",
                reg.kind
            );
            let back: Box<C> = toml::from_str(&text).unwrap_or_else(|e| {
                panic!("{role} `{}`: its default config does not read back: {e}\n{text}", reg.kind)
            });
            let again = toml::to_string(&back).expect("config read back writes");
            assert_eq!(again, text, "{role} `{}`: the default config changes on a TOML round trip", reg.kind);
            (reg.kind, back)
        })
        .collect()
}

#[test]
fn every_field_round_trips_and_builds() {
    let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
    for (kind, config) in round_trip_all::<dyn RadianceFieldConfig>("radiance field") {
        if let Err(e) = config.build(&extent, 0) {
            panic!("radiance field `{kind}`: its default config does not build: {e}");
        }
    }
}

#[test]
fn every_loss_and_miner_round_trips_and_builds() {
    for (kind, config) in round_trip_all::<dyn ContrastiveLossConfig>("contrastive loss") {
        if let Err(e) = config.build() {
            panic!("contrastive loss `{kind}`: its default config does not build: {e}");
        }
    }
    for (kind, config) in round_trip_all::<dyn PairMinerConfig>("pair miner") {
        if let Err(e) = config.build() {
            panic!("pair miner `{kind}`: its default config does not build: {e}");
        }
    }
}

#[test]
fn every_extractor_round_trips_and_builds_or_names_its_missing_resource() {
    let ctx = BuildContext::new(std::env::temp_dir());
    let mut built = 0;
    for (kind, config) in round_trip_all::<dyn FeatureExtractorConfig>("feature extractor") {
        match config.build(&ctx) {
            Ok(_) => built += 1,
            // Pretrained weights and runtimes are not shipped; their absence must be reported
            // as such, never as a bad hyperparameter of the default config.
            Err(BuildError::Resource { kind: named, message }) => {
                assert_eq!(named, kind, "the error names another kind");
                assert!(!message.is_empty(), "feature extractor `{kind}`: empty resource message");
            }
            Err(e) => panic!("feature extractor `{kind}`: its default config is invalid: {e}"),
        }
    }
    assert!(built > 0, "no extractor builds without downloaded weights (the default teacher must)");
}

#[test]
fn every_dataset_adapter_round_trips() {
    // Adapters build from files; loading each layout is checked by the dataset tests.
    round_trip_all::<dyn DatasetConfig>("dataset adapter");
}
