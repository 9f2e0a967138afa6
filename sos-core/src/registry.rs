//! Link-time registry of plugin kinds, one list per role.
//!
//! Each plugin file declares its kind with [`plugin_kind!`](crate::plugin_kind), which writes the
//! typetag impl of its config and submits a [`Registration`] for its config trait object under
//! the same name.
//! A binary that depends on a plugin crate but names nothing in it gets an empty list: write
//! `use sos_plugins as _;` in every binary and integration test.

/// One registered kind of a plugin role `C` (a config trait object type).
pub struct Registration<C: ?Sized + 'static> {
    /// The `kind = "..."` tag used in TOML.
    pub kind: &'static str,
    /// One-line description shown by `sos list`.
    pub summary: &'static str,
    /// The crate that declared the kind (`sos list` shows it, so a user can tell a plugin
    /// crate's kinds from the built-in ones).
    pub crate_name: &'static str,
    /// Builds the default configuration of this kind.
    pub default_config: fn() -> Box<C>,
}

impl<C: ?Sized + 'static> Registration<C> {
    /// A registration record (submitted by [`plugin_kind!`](crate::plugin_kind)).
    pub const fn new(
        kind: &'static str,
        summary: &'static str,
        crate_name: &'static str,
        default_config: fn() -> Box<C>,
    ) -> Self {
        Registration { kind, summary, crate_name, default_config }
    }
}

/// All registrations of role `C`, sorted by kind.
pub fn registrations<C: ?Sized + 'static>() -> Vec<&'static Registration<C>>
where
    Registration<C>: inventory::Collect,
{
    let mut all: Vec<_> = inventory::iter::<Registration<C>>.into_iter().collect();
    all.sort_by_key(|r| r.kind);
    all
}

/// The registration of `kind` in role `C`, if any.
pub fn find<C: ?Sized + 'static>(kind: &str) -> Option<&'static Registration<C>>
where
    Registration<C>: inventory::Collect,
{
    inventory::iter::<Registration<C>>.into_iter().find(|r| r.kind == kind)
}

/// Declares a plugin kind once: its `kind = "..."` name goes to typetag (which reads it from
/// TOML) and to the [`Registration`] (which `sos list` and the default lookups read), so the
/// two cannot disagree; the config type also gets `KIND`, the same name as a constant.
///
/// ```
/// use rand::RngCore;
/// use serde::{Deserialize, Serialize};
/// use sos_core::error::BuildError;
/// use sos_core::plugin::{PairMiner, PairMinerConfig};
///
/// /// Pairs each patch with the next one.
/// struct NextMiner;
///
/// impl PairMiner for NextMiner {
///     fn negatives(&self, cls: &[Vec<f32>], _rng: &mut dyn RngCore) -> Vec<usize> {
///         (0..cls.len()).map(|i| (i + 1) % cls.len()).collect()
///     }
/// }
///
/// #[derive(Debug, Default, Serialize, Deserialize)]
/// pub struct NextConfig {}
///
/// sos_core::plugin_kind! {
///     kind: "next",
///     summary: "negative = the next patch of the batch",
///     default: || Box::new(NextConfig::default()),
///     impl PairMinerConfig for NextConfig {
///         fn build(&self) -> Result<Box<dyn PairMiner>, BuildError> {
///             Ok(Box::new(NextMiner))
///         }
///     }
/// }
///
/// fn main() {
///     assert_eq!(NextConfig::KIND, "next");
///     // The declaring crate is recorded (here the doctest's own crate).
///     assert!(!sos_core::registry::find::<dyn PairMinerConfig>("next").unwrap().crate_name.is_empty());
///     let registered = sos_core::registry::find::<dyn PairMinerConfig>("next").expect("registered");
///     let config: Box<dyn PairMinerConfig> = toml::from_str("kind = \"next\"").expect("typetag reads the kind");
///     assert_eq!(toml::to_string(&config).unwrap(), toml::to_string(&(registered.default_config)()).unwrap());
/// }
/// ```
/// The calling crate depends on `typetag` (its expansion names it); `inventory` is reached
/// through sos-core.
#[macro_export]
macro_rules! plugin_kind {
    (
        kind: $kind:literal,
        summary: $summary:literal,
        default: $default:expr,
        impl $($role:ident)::+ for $config:ty { $($body:tt)* }
    ) => {
        impl $config {
            /// The `kind = "..."` name of this plugin in TOML.
            pub const KIND: &'static str = $kind;
        }

        #[typetag::serde(name = $kind)]
        impl $($role)::+ for $config {
            $($body)*
        }

        $crate::inventory::submit! {
            $crate::registry::Registration::<dyn $($role)::+>::new($kind, $summary, env!("CARGO_PKG_NAME"), $default)
        }
    };
}
