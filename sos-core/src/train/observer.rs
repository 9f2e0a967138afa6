//! What a caller sees of training while it runs: a hook called after every completed step of
//! either stage, with read access to everything trained so far (e.g. to evaluate held-out
//! views for a learning curve). An observer cannot change the run: a run with one trains the
//! same field and head bit for bit as a run without.

use crate::error::RunError;
use crate::segment::train::{SegStepStats, Segmenter};
use crate::train::photometric::StepStats;
use crate::train::session::Session;

/// Called between training steps; both hooks default to doing nothing.
pub trait TrainObserver {
    /// After stage-1 step `session.step` (already counted) has updated the field.
    fn stage1_step(&mut self, _session: &Session, _stats: &StepStats) -> Result<(), RunError> {
        Ok(())
    }

    /// After stage-2 step `seg.step` (already counted) has updated the head.
    fn stage2_step(&mut self, _session: &Session, _seg: &Segmenter, _stats: &SegStepStats) -> Result<(), RunError> {
        Ok(())
    }
}

/// The observer of a run nobody watches.
pub struct Unobserved;

impl TrainObserver for Unobserved {}
