//! Setting config keys by dotted path (`segment.steps`, `field.kind`, `loss.geometry.weight`)
//! on a fully resolved run config, so that every path can be checked before a run starts.
//!
//! Rules:
//! - A nested table in an overlay is the same as its dotted keys (`{ train = { steps = 5 } }`
//!   is `"train.steps" = 5`); arrays and scalars are leaves.
//! - Setting a plugin section's `kind` to another kind starts the section from that kind's
//!   defaults; the overlay's other keys of that section then apply on top.
//! - In an array of tables (`loss`), a segment is an index (`loss.0.weight`) or the `kind` of
//!   an entry (`loss.geometry.weight`).
//! - Every table on the path must exist; the last key may be new (an optional key that the
//!   default leaves out), and parsing the result (every section rejects unknown keys) decides.

use sos_core::config::RunConfig;
use sos_core::plugin::{
    ContrastiveLossConfig, DatasetConfig, FeatureExtractorConfig, PairMinerConfig, RadianceFieldConfig,
};
use sos_core::registry::{find, registrations, Registration};
use sos_core::segment::defaults;
use toml::{Table, Value};

/// Why an overlay could not be applied.
#[derive(Debug, thiserror::Error)]
pub enum OverlayError {
    /// The path names no key of the config.
    #[error("key path `{path}`: {reason}")]
    Path {
        /// The dotted path.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// The path sets a plugin kind that this program does not link: the run is skipped.
    #[error("{role} kind `{kind}` is not registered in this build (registered: {registered})")]
    Unregistered {
        /// The role (`field`, `extractor`, ...).
        role: &'static str,
        /// The kind asked for.
        kind: String,
        /// The kinds that are registered.
        registered: String,
    },
}

/// Flattens an overlay table into (dotted path, leaf value) pairs, `kind` paths first so that a
/// kind change resets its section before the section's other keys are set.
pub fn flatten(overlay: &Table) -> Vec<(String, Value)> {
    fn walk(prefix: &str, table: &Table, out: &mut Vec<(String, Value)>) {
        for (k, v) in table {
            let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
            match v {
                Value::Table(t) if !t.is_empty() => walk(&path, t, out),
                _ => out.push((path, v.clone())),
            }
        }
    }
    let mut out = Vec::new();
    walk("", overlay, &mut out);
    out.sort_by_key(|(p, _)| (!p.ends_with("kind"), p.matches('.').count()));
    out
}

/// Applies every path of `overlay` to `config` (a resolved run config as a TOML value).
pub fn apply(config: &mut Value, overlay: &Table) -> Result<(), OverlayError> {
    for (path, value) in flatten(overlay) {
        set(config, &path, value)?;
    }
    Ok(())
}

/// Sets one dotted path.
pub fn set(config: &mut Value, path: &str, value: Value) -> Result<(), OverlayError> {
    let fail = |reason: String| OverlayError::Path { path: path.to_string(), reason };
    let segments: Vec<&str> = path.split('.').collect();
    if segments.iter().any(|s| s.is_empty()) {
        return Err(fail("has an empty segment".into()));
    }
    let (last, parents) = segments.split_last().expect("split yields one segment at least");
    let mut node = config;
    let mut walked = String::new();
    for seg in parents {
        node = child(node, seg).ok_or_else(|| fail(format!("no table `{seg}` in `{}`", display(&walked))))?;
        if !walked.is_empty() {
            walked.push('.');
        }
        walked.push_str(seg);
    }
    if *last == "kind" {
        if let Some(role) = Role::of_section(&segments) {
            let kind = value.as_str().ok_or_else(|| fail("a kind must be a string".into()))?;
            let same = node.get("kind").and_then(Value::as_str) == Some(kind);
            if !same {
                let mut fresh = role.default_table(kind)?;
                // A loss entry's weight belongs to the entry, not to the loss kind.
                if let (Role::Loss, Some(w)) = (role, node.get("weight")) {
                    fresh.insert("weight".into(), w.clone());
                }
                *node = Value::Table(fresh);
            }
            return Ok(());
        }
    }
    match node {
        Value::Table(t) => {
            t.insert(last.to_string(), value);
            Ok(())
        }
        Value::Array(items) => {
            let i =
                index_in(items, last).ok_or_else(|| fail(format!("no entry `{last}` in `{}`", display(&walked))))?;
            items[i] = value;
            Ok(())
        }
        _ => Err(fail(format!("`{}` is a value, not a table", display(&walked)))),
    }
}

fn display(walked: &str) -> &str {
    if walked.is_empty() {
        "the config"
    } else {
        walked
    }
}

/// The child `seg` of a table, or an array entry by index or `kind`.
fn child<'a>(node: &'a mut Value, seg: &str) -> Option<&'a mut Value> {
    match node {
        Value::Table(t) => t.get_mut(seg),
        Value::Array(items) => {
            let i = index_in(items, seg)?;
            items.get_mut(i)
        }
        _ => None,
    }
}

fn index_in(items: &[Value], seg: &str) -> Option<usize> {
    if let Ok(i) = seg.parse::<usize>() {
        return (i < items.len()).then_some(i);
    }
    items.iter().position(|v| v.get("kind").and_then(Value::as_str) == Some(seg))
}

/// The plugin role of a section whose `kind` is being set.
#[derive(Debug, Clone, Copy)]
enum Role {
    Scene,
    Field,
    Extractor,
    Miner,
    Loss,
}

impl Role {
    fn of_section(segments: &[&str]) -> Option<Role> {
        match segments {
            ["scene", "kind"] => Some(Role::Scene),
            ["field", "kind"] => Some(Role::Field),
            ["extractor", "kind"] => Some(Role::Extractor),
            ["miner", "kind"] => Some(Role::Miner),
            ["loss", _, "kind"] => Some(Role::Loss),
            _ => None,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Role::Scene => "scene",
            Role::Field => "field",
            Role::Extractor => "extractor",
            Role::Miner => "miner",
            Role::Loss => "loss",
        }
    }

    /// The default config of `kind` in this role, as a table with its `kind`.
    fn default_table(self, kind: &str) -> Result<Table, OverlayError> {
        let value = match self {
            Role::Scene => defaults_of::<dyn DatasetConfig>(self, kind)?,
            Role::Field => defaults_of::<dyn RadianceFieldConfig>(self, kind)?,
            Role::Extractor => defaults_of::<dyn FeatureExtractorConfig>(self, kind)?,
            Role::Miner => defaults_of::<dyn PairMinerConfig>(self, kind)?,
            Role::Loss => defaults_of::<dyn ContrastiveLossConfig>(self, kind)?,
        };
        match value {
            Value::Table(t) => Ok(t),
            _ => Err(OverlayError::Path {
                path: format!("{}.kind", self.name()),
                reason: "defaults are not a table".into(),
            }),
        }
    }
}

fn defaults_of<C>(role: Role, kind: &str) -> Result<Value, OverlayError>
where
    C: ?Sized + serde::Serialize + 'static,
    Registration<C>: inventory::Collect,
{
    let Some(reg) = find::<C>(kind) else {
        let registered = registrations::<C>().iter().map(|r| r.kind).collect::<Vec<_>>().join(", ");
        return Err(OverlayError::Unregistered { role: role.name(), kind: kind.into(), registered });
    };
    let config = (reg.default_config)();
    Value::try_from(&*config).map_err(|e| OverlayError::Path {
        path: format!("{}.kind", role.name()),
        reason: format!("the defaults of `{kind}` do not serialise: {e}"),
    })
}

/// A run config with every default written out: the extractor, miner and loss terms a config
/// leaves out become the defaults the trainer would use, so that every key has a path.
pub fn resolve(mut config: RunConfig) -> RunConfig {
    if config.extractor.is_none() {
        config.extractor = defaults::extractor();
    }
    if config.miner.is_none() {
        config.miner = defaults::miner();
    }
    if config.loss.is_empty() {
        config.loss = defaults::losses();
    }
    config
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    // Link the plugins so kinds resolve.
    use sos_plugins as _;

    fn base() -> Value {
        let cfg =
            RunConfig::parse("[scene]\nkind = \"synthetic\"\n[field]\nkind = \"voxel-grid\"\n", Path::new("base.toml"))
                .unwrap();
        Value::try_from(resolve(cfg)).unwrap()
    }

    fn parse(v: &Value) -> RunConfig {
        RunConfig::parse(&toml::to_string(v).unwrap(), Path::new("x.toml")).unwrap()
    }

    #[test]
    fn nested_and_dotted_overlays_are_the_same() {
        let dotted: Table = toml::from_str("\"train.steps\" = 7").unwrap();
        let nested: Table = toml::from_str("train.steps = 7").unwrap();
        assert_eq!(flatten(&dotted), flatten(&nested));
        let mut v = base();
        apply(&mut v, &nested).unwrap();
        assert_eq!(parse(&v).train.steps, 7);
    }

    #[test]
    fn a_kind_change_starts_from_the_new_kinds_defaults() {
        let mut v = base();
        let overlay: Table = toml::from_str("field.kind = \"nerf\"\nfield.depth = 3").unwrap();
        apply(&mut v, &overlay).unwrap();
        let field = v.get("field").unwrap();
        assert_eq!(field.get("kind").unwrap().as_str(), Some("nerf"));
        assert_eq!(field.get("depth").unwrap().as_integer(), Some(3));
        assert!(field.get("resolution").is_none(), "voxel-grid keys must go");
        parse(&v);
    }

    #[test]
    fn loss_entries_are_found_by_kind_or_index() {
        let mut v = base();
        set(&mut v, "loss.geometry.weight", Value::Float(0.5)).unwrap();
        set(&mut v, "loss.0.weight", Value::Float(2.0)).unwrap();
        let cfg = parse(&v);
        let weights: Vec<(String, f32)> =
            cfg.loss.iter().map(|l| (sos_core::train::session::kind_of(&l.loss), l.weight)).collect();
        assert!(weights.contains(&("geometry".into(), 0.5)), "{weights:?}");
        assert!(weights.contains(&("appearance".into(), 2.0)), "{weights:?}");
    }

    #[test]
    fn unknown_tables_and_entries_are_errors_naming_the_path() {
        let mut v = base();
        let e = set(&mut v, "trian.steps", Value::Integer(1)).unwrap_err().to_string();
        assert!(e.contains("trian.steps") && e.contains("no table `trian`"), "{e}");
        let e = set(&mut v, "loss.nope.weight", Value::Float(1.0)).unwrap_err().to_string();
        assert!(e.contains("loss.nope.weight"), "{e}");
        // A misspelt last key is left to the parser, which rejects unknown keys.
        set(&mut v, "train.ocupancy", Value::Boolean(false)).unwrap();
        let err = RunConfig::parse(&toml::to_string(&v).unwrap(), Path::new("x.toml")).unwrap_err().to_string();
        assert!(err.contains("ocupancy"), "{err}");
    }

    #[test]
    fn an_unlinked_kind_is_reported_as_such() {
        let mut v = base();
        let e = set(&mut v, "extractor.kind", Value::String("no-such-teacher".into())).unwrap_err();
        assert!(matches!(e, OverlayError::Unregistered { role: "extractor", .. }), "{e}");
        assert!(e.to_string().contains("cell-stats"), "{e}");
    }

    #[test]
    fn resolving_writes_the_default_plugins_out() {
        let v = base();
        assert_eq!(v.get("extractor").and_then(|e| e.get("kind")).and_then(Value::as_str), Some("cell-stats"));
        assert_eq!(v.get("loss").and_then(Value::as_array).map(Vec::len), Some(2));
    }
}
