//! Link-time registry of plugin kinds, one list per role.
//!
//! Each plugin file submits a [`Registration`] for its config trait object, e.g.
//! `inventory::submit! { Registration::<dyn RadianceFieldConfig>::new("voxel-grid", "…", default_fn) }`.
//! A binary that depends on a plugin crate but names nothing in it gets an empty list: write
//! `use sos_plugins as _;` in every binary and integration test.

/// One registered kind of a plugin role `C` (a config trait object type).
pub struct Registration<C: ?Sized + 'static> {
    /// The `kind = "..."` tag used in TOML.
    pub kind: &'static str,
    /// One-line description shown by `sos list`.
    pub summary: &'static str,
    /// Builds the default configuration of this kind.
    pub default_config: fn() -> Box<C>,
}

impl<C: ?Sized + 'static> Registration<C> {
    /// A registration record (used in `inventory::submit!`).
    pub const fn new(
        kind: &'static str,
        summary: &'static str,
        default_config: fn() -> Box<C>,
    ) -> Self {
        Registration { kind, summary, default_config }
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
