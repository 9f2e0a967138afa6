//! What every dataset adapter does around its own parsing, kept in one place so that the
//! adapters agree: registration under the config's `kind`, the hold-out split, and the scene
//! assembled with a render path that orbits the training cameras.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::blender::orbit_path_around;
use crate::text::invalid;

/// Registers a dataset config under its `[scene] kind` tag, with a one-line summary for
/// `sos list` and its `Default` as the default configuration. Given a loader
/// `load(&config, root)`, also implements `open` as that loader on the config's `path`
/// resolved against the config file's folder, as every capture-folder adapter does.
macro_rules! register_dataset {
    ($config:ident, $kind:tt, $summary:tt, $load:path) => {
        $crate::adapter::register_dataset!($config, $kind, $summary, $load, $crate::adapter::nothing_derived);
    };
    // With `derived(&config, root, &scene)`: the settings the loader chose where the config
    // left them unset.
    ($config:ident, $kind:tt, $summary:tt, $load:path, $derived:path) => {
        sos_core::plugin_kind! {
            kind: $kind,
            summary: $summary,
            default: || Box::new(<$config>::default()),
            impl sos_core::plugin::dataset::DatasetConfig for $config {
                fn open(
                    &self,
                    config_dir: &std::path::Path,
                ) -> Result<sos_core::scene::Scene, sos_core::plugin::dataset::DatasetError> {
                    $crate::adapter::require_path(&self.path)?;
                    $load(self, &config_dir.join(&self.path))
                }

                fn derived(
                    &self,
                    config_dir: &std::path::Path,
                    scene: &sos_core::scene::Scene,
                ) -> Vec<sos_core::derived::DerivedSetting> {
                    $derived(self, &config_dir.join(&self.path), scene)
                }
            }
        }
    };
}

pub(crate) use register_dataset;

/// The `derived` of an adapter that derives nothing (every setting is in its config).
pub fn nothing_derived<C>(_config: &C, _root: &Path, _scene: &Scene) -> Vec<sos_core::derived::DerivedSetting> {
    Vec::new()
}

/// Refuses a config without `path` (an empty one would silently name the config's own
/// folder).
pub fn require_path(path: &Path) -> Result<(), DatasetError> {
    if path.as_os_str().is_empty() {
        return Err(DatasetError::Missing {
            path: "[scene] path".into(),
            hint: "the key is required: set it to the capture's folder (relative to the config file)".into(),
        });
    }
    Ok(())
}

/// Refuses a capture folder `root` that does not exist, saying what was `expected` there
/// (the hint reads "expected {expected}; check `path`").
pub fn require_folder(root: &Path, expected: &str) -> Result<(), DatasetError> {
    if root.is_dir() {
        return Ok(());
    }
    Err(DatasetError::Missing { path: root.to_path_buf(), hint: format!("expected {expected}; check `path`") })
}

/// Splits `n` views: every `hold_out_every`-th view from 0 is a test view (none when 0).
pub fn hold_out_split(n: usize, hold_out_every: usize) -> (Vec<usize>, Vec<usize>) {
    let is_test = |i: usize| hold_out_every > 0 && i.is_multiple_of(hold_out_every);
    ((0..n).filter(|&i| !is_test(i)).collect(), (0..n).filter(|&i| is_test(i)).collect())
}

/// [`hold_out_split`] of `n` loaded views, refused (naming `root`) when it leaves no training
/// view.
pub fn hold_out_views(root: &Path, n: usize, hold_out_every: usize) -> Result<(Vec<usize>, Vec<usize>), DatasetError> {
    let (train, test) = hold_out_split(n, hold_out_every);
    if train.is_empty() {
        return Err(invalid(root, "no training views left; raise `hold_out_every` or set it to 0"));
    }
    Ok((train, test))
}

/// A scene whose render path is the 40-view orbit of the training cameras around the centre
/// of `extent`.
pub fn orbit_scene(
    name: String,
    views: Vec<View>,
    train: Vec<usize>,
    test: Vec<usize>,
    extent: SceneExtent,
    near: f32,
) -> Scene {
    Scene { render_path: orbit_path_around(&views, &train, &extent), name, views, train, test, extent, near }
}
