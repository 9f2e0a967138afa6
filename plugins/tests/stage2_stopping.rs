//! Stage 2 stops once its masks settle (`segment.stop_when_stable`) and runs every step without.

mod common;

use common::tiny_session;
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
// Links every plugin (datasets, extractors, losses) so the config kinds resolve.
use sos_plugins as _;

/// Stage 2 of a tiny voxel-grid run with the given stopping settings: steps run, settled step.
fn stage_two(stop: bool, stable_change: f32, tag: &str) -> (usize, Option<usize>) {
    let mut s = tiny_session("voxel-grid", "object-centric", "", 30, tag);
    train_photometric(&mut s).unwrap();
    s.config.segment.steps = 12;
    s.config.segment.check_every = 2;
    s.config.segment.stop_when_stable = stop;
    s.config.segment.stable_change = stable_change;
    let mut seg = Segmenter::build(&s).unwrap();
    train_segmentation(&mut s, &mut seg).unwrap();
    (seg.step, seg.settled_at)
}

#[test]
fn stage_two_stops_at_the_second_calm_check_after_the_first() {
    // Any change counts as calm: checks at steps 2 (the first, nothing to compare), 4 and 6.
    assert_eq!(stage_two(true, 1.0, "stop-calm"), (6, Some(6)));
    // Switched off, every step runs.
    assert_eq!(stage_two(false, 1.0, "stop-off"), (12, None));
}
