//! The saved state (a checkpoint's `field` section), in the layout of
//! [`sos_core::plugin::state`]: a length-prefixed JSON header with the current resolution, the
//! growths done and every tensor's name and shape, then every value as little-endian `f32`, in
//! layout order. Loading checks the header against the config first, so a state of another
//! shape is refused with the keys that differ, and a short body as truncated.

use sos_core::error::StateError;
use sos_core::plugin::state;

use crate::config::TensorfConfig;
use crate::layout::Layout;
use crate::samples::Matrix;

fn kind() -> String {
    crate::KIND.to_string()
}

/// A state read back: where the field stood and its values.
pub struct Loaded {
    /// Vertices per axis of the planes and lines.
    pub resolution: [usize; 3],
    /// Growths of the `upsample_at` schedule already done.
    pub next_growth: usize,
    /// The layout at that resolution.
    pub layout: Layout,
    /// Every tensor's values, in layout order.
    pub values: Vec<Vec<f32>>,
}

/// The state of `tensors`, laid out as `layout` says, at `resolution` after `next_growth` growths.
pub fn write(layout: &Layout, tensors: &[Matrix], resolution: [usize; 3], next_growth: usize) -> Vec<u8> {
    let shapes: Vec<(&str, usize, usize)> = layout.specs.iter().map(|s| (s.name.as_str(), s.rows, s.cols)).collect();
    let header =
        serde_json::json!({ "format": 1, "resolution": resolution, "next_growth": next_growth, "tensors": shapes });
    let values: Vec<Vec<f32>> = tensors.iter().map(|t| t.as_vec()).collect();
    let parts: Vec<&[f32]> = values.iter().map(|v| &v[..]).collect();
    state::write(&header, &parts)
}

/// A state that [`write`] made for a field of the same config.
pub fn read(config: &TensorfConfig, bytes: &[u8]) -> Result<Loaded, StateError> {
    let malformed = |reason: String| StateError::Malformed { kind: kind(), reason };
    let (header, body) = state::read(crate::KIND, bytes)?;
    let resolution: [usize; 3] =
        serde_json::from_value(header["resolution"].clone()).map_err(|e| malformed(format!("resolution: {e}")))?;
    let next_growth = header["next_growth"].as_u64().ok_or_else(|| malformed("no growth count".into()))? as usize;
    if (0..3).any(|a| !(2..=config.resolution[a]).contains(&resolution[a])) {
        return Err(StateError::Mismatch {
            kind: kind(),
            reason: format!(
                "its resolution {resolution:?} exceeds this config's {:?} (resolution changed?)",
                config.resolution
            ),
        });
    }
    let layout = Layout::new(config, resolution);
    let shapes: Vec<(String, usize, usize)> =
        serde_json::from_value(header["tensors"].clone()).map_err(|e| malformed(format!("tensor list: {e}")))?;
    let want: Vec<(String, usize, usize)> = layout.specs.iter().map(|s| (s.name.clone(), s.rows, s.cols)).collect();
    if shapes.len() != want.len() {
        return Err(malformed(format!("{} tensors where this kind writes {}", shapes.len(), want.len())));
    }
    for (got, want) in shapes.iter().zip(&want) {
        if got != want {
            return Err(StateError::Mismatch {
                kind: kind(),
                reason: format!(
                    "tensor `{}` is {}x{} in the state but {}x{} in this config \
                     (density_components, appearance_components, features, hidden or view_frequencies changed?)",
                    want.0, got.1, got.2, want.1, want.2
                ),
            });
        }
    }
    let values = state::values(crate::KIND, body, layout.total())?;
    let mut values = values.into_iter();
    let values = layout.specs.iter().map(|s| values.by_ref().take(s.len()).collect()).collect();
    Ok(Loaded { resolution, next_growth, layout, values })
}
