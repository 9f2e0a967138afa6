//! Loss settings that each pass as numbers but would make stage 2 meaningless, refused when
//! the loss is built: values that do not survive the losses' `f32` arithmetic, and sample
//! counts whose pairwise correlations no machine holds.

use sos_core::plugin::ContrastiveLossConfig;
use sos_losses::{AppearanceConfig, GeometryConfig};

/// The build error's text, naming the key.
fn refused(cfg: &dyn ContrastiveLossConfig) -> String {
    match cfg.build() {
        Ok(_) => panic!("{cfg:?} builds"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn geometry_values_that_vanish_or_overflow_in_f32_are_refused() {
    assert!(GeometryConfig::default().build().is_ok());
    // 1e-50 rounds to 0 (a division by zero), 1e39 to infinity: every step's loss was skipped.
    for (key, cfg) in [
        ("epsilon", GeometryConfig { epsilon: 1e-50, ..Default::default() }),
        ("cap", GeometryConfig { cap: 1e39, ..Default::default() }),
        ("depth_clip", GeometryConfig { depth_clip: 1e300, ..Default::default() }),
        ("negative_shift", GeometryConfig { negative_shift: -1e40, ..Default::default() }),
    ] {
        let err = refused(&cfg);
        assert!(err.contains(&format!("`{key}`")) && err.contains("32-bit"), "{err}");
    }
    // Zero stays zero in f32: a weight of 0 switches its term off, as it always did.
    assert!(GeometryConfig { identity_weight: 0.0, ..Default::default() }.build().is_ok());
}

#[test]
fn appearance_sample_counts_beyond_any_machine_are_refused() {
    assert!(AppearanceConfig { samples: 64, ..Default::default() }.build().is_ok());
    // 10^6 points a side asked for terabytes; 2^32 wrapped its square to 0 points.
    for samples in [0, 65, 1_000_000, 1 << 32] {
        let err = refused(&AppearanceConfig { samples, ..Default::default() });
        assert!(err.contains("`samples`") && err.contains("1..=64"), "{samples}: {err}");
    }
}
