//! The `[field]` tables of `nerf` and `nerf++`: the shipped configs parse, the defaults are
//! written with the keys in order, and an unknown key is refused with the key named and the
//! keys of the kind listed.

use std::path::Path;

use sos_core::config::RunConfig;
use sos_plugins::nerf::NerfConfig;
use sos_plugins::nerf_pp::NerfPpConfig;

/// `nerf`'s keys, in order.
const NERF_KEYS: &str = "`hierarchical`, `coarse_samples`, `fine_samples`, `pos_frequencies`, `dir_frequencies`, \
                         `depth`, `width`, `skip`, `view_width`, `density_activation`, `lr`";
/// `nerf++`'s keys, in order.
const NERF_PP_KEYS: &str = "`hierarchical`, `coarse_samples`, `fine_samples`, `background`, `pos_frequencies`, \
                            `dir_frequencies`, `depth`, `width`, `skip`, `view_width`, `density_activation`, `lr`";

const NERF_PP: &str = include_str!("../../configs/nerf_pp_unbounded.toml");
const NERF: &str = include_str!("../../configs/nerf_synthetic_small.toml");

fn parse(text: &str) -> Result<RunConfig, String> {
    RunConfig::parse(text, Path::new("field.toml")).map_err(|e| e.to_string())
}

/// The keys of a TOML table, in order, as the error messages list them.
fn keys(table: &str) -> String {
    table.lines().map(|l| format!("`{}`", l.split(" = ").next().unwrap())).collect::<Vec<_>>().join(", ")
}

#[test]
fn shipped_configs_parse() {
    let nerf_pp = parse(NERF_PP).unwrap();
    let nerf = parse(NERF).unwrap();
    let written = |c: &RunConfig| toml::to_string(&c.field).unwrap();
    assert!(written(&nerf_pp).contains("kind = \"nerf++\""));
    assert!(written(&nerf_pp).contains("width = 128\n"), "{}", written(&nerf_pp));
    assert!(written(&nerf).contains("kind = \"nerf\""));
}

#[test]
fn defaults_are_written_with_every_key_in_order() {
    assert_eq!(keys(&toml::to_string(&NerfConfig::default()).unwrap()), NERF_KEYS);
    assert_eq!(keys(&toml::to_string(&NerfPpConfig::default()).unwrap()), NERF_PP_KEYS);
}

#[test]
fn unknown_field_keys_are_named() {
    for (text, kind, expected) in [(NERF_PP, "nerf++", NERF_PP_KEYS), (NERF, "nerf", NERF_KEYS)] {
        let table = format!("[field]\nkind = \"{kind}\"\n");
        assert!(text.contains(&table));
        let err = parse(&text.replace(&table, &format!("{table}widht = 3\n"))).unwrap_err();
        let want = format!("unknown field `widht`, expected one of {expected}");
        assert!(err.contains(&want), "{kind}: {err}");
    }
}
