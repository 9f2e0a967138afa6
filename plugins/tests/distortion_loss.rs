//! The distortion loss is wired into stage 1: a run with it trains to finite losses and to a
//! different field than the same run without it (same seed, same rays).

mod common;

use sos_core::train::photometric::train_photometric;
// Links every plugin so the config kinds resolve.
use sos_plugins as _;

fn trained_density(weight: f32, tag: &str) -> (f64, Vec<f32>) {
    let mut s = common::tiny_session("voxel-grid", "object-centric", "", 40, tag);
    s.config.train.distortion_weight = weight;
    let stats = train_photometric(&mut s).unwrap();
    let probes: Vec<[f32; 3]> =
        (0..64).map(|i| [0.05 * (i % 8) as f32 - 0.2, 0.5 + 0.05 * (i / 8) as f32, 0.0]).collect();
    let mut density = vec![0.0; probes.len()];
    s.field.density(&probes, &mut density);
    (stats.mse, density)
}

#[test]
fn a_run_with_the_distortion_loss_trains_another_field() {
    let (mse_off, off) = trained_density(0.0, "distortion-off");
    let (mse_on, on) = trained_density(0.05, "distortion-on");
    assert!(mse_off.is_finite() && mse_on.is_finite());
    assert!(on.iter().all(|d| d.is_finite()));
    assert_ne!(off, on, "the distortion loss changed nothing");
}
