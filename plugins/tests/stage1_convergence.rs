//! Stage 1 stops once its training loss levels off (`train.stop_when_converged`), the stop
//! survives a checkpoint, and without the switch every step runs.

mod common;

use common::tiny_session;
use sos_core::plugin::field::plain;
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;
// Links every plugin so the config kinds resolve.
use sos_plugins as _;

const STEPS: usize = 60;
const WINDOW: usize = 5;

/// A tiny voxel-grid stage 1 with the convergence test on (`gain` dB per window) or off.
fn stage_one(stop: bool, gain: f32, tag: &str) -> Session {
    let mut s = tiny_session("voxel-grid", "object-centric", "", STEPS, tag);
    s.config.train.stop_when_converged = stop;
    s.config.train.converged_window = WINDOW;
    s.config.train.converged_gain = gain;
    train_photometric(&mut s).unwrap();
    s
}

#[test]
fn stage_one_stops_three_windows_after_full_detail_and_stays_stopped() {
    // Any rise counts as calm: the first window after the grid's last growth has nothing to
    // compare with, the next two are calm.
    let s = stage_one(true, 1e3, "converge-calm");
    let stopped = s.converged_at.expect("stage 1 converged");
    assert_eq!(stopped, s.step);
    assert!(stopped < STEPS, "stopped at {stopped} of {STEPS}");
    assert_eq!(s.config.train.steps, stopped, "the stage's length becomes the stop");
    assert_eq!(plain::detail_fraction(s.field.as_ref()), 1.0);
    // Every growth happens before half the steps: the stop is three windows after the last.
    let last_growth = STEPS / 2;
    assert!((last_growth + 3 * WINDOW..=last_growth + 3 * WINDOW + 1).contains(&stopped), "stopped at {stopped}");

    // A resumed run finds stage 1 complete, although its config asks for more steps.
    s.save_checkpoint().unwrap();
    let run_dir = s.run_dir.clone();
    let mut resumed = tiny_session("voxel-grid", "object-centric", "", STEPS, "converge-resumed");
    resumed.run_dir = run_dir;
    resumed.config.train.stop_when_converged = true;
    resumed.load_checkpoint(None).unwrap();
    assert_eq!((resumed.step, resumed.converged_at, resumed.config.train.steps), (stopped, Some(stopped), stopped));
    train_photometric(&mut resumed).unwrap();
    assert_eq!(resumed.step, stopped, "a converged stage 1 trains no further");
}

#[test]
fn a_checkpoint_cannot_stretch_stage_one_beyond_the_configured_steps() {
    // A checkpoint is input: one that claims its stage levelled off at step 10^15 would
    // otherwise set the stage's length to that and train for ever.
    let mut s = stage_one(false, 1e3, "converge-claim");
    s.converged_at = Some(1_000_000_000_000_000);
    s.save_checkpoint().unwrap();
    let mut resumed = tiny_session("voxel-grid", "object-centric", "", STEPS, "converge-claim-resumed");
    resumed.run_dir = s.run_dir.clone();
    resumed.load_checkpoint(None).unwrap();
    assert_eq!(resumed.config.train.steps, STEPS);
    train_photometric(&mut resumed).unwrap();
    assert_eq!(resumed.step, STEPS);
}

#[test]
fn stage_one_runs_every_step_without_the_switch_or_while_it_improves() {
    let off = stage_one(false, 1e3, "converge-off");
    assert_eq!((off.step, off.converged_at), (STEPS, None));
    // No window can rise by a kilodecibel: never converged.
    let improving = stage_one(true, -1e3, "converge-never");
    assert_eq!((improving.step, improving.converged_at), (STEPS, None));
}
