//! What a caller sees of training while it runs. The library prints nothing and draws no
//! progress bar: it tells an observer the caller supplies when a stage begins and ends, what it
//! has to say (notices, warnings, skipped steps) and, after every completed step, the step's
//! figures with read access to everything trained so far (e.g. to draw a bar, print a profile
//! or evaluate held-out views for a learning curve). An observer cannot change the run: a run
//! with one trains the same field and head bit for bit as a run without.

use crate::error::RunError;
use crate::segment::train::{SegStepStats, Segmenter};
use crate::train::photometric::StepStats;
use crate::train::session::Session;

/// The two training stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Stage 1: fitting the radiance field to the photographs.
    Photometric,
    /// Stage 2: training the segmentation head.
    Segmentation,
}

impl Stage {
    /// Short name for logs ("stage 1", "stage 2").
    pub fn label(self) -> &'static str {
        match self {
            Stage::Photometric => "stage 1",
            Stage::Segmentation => "stage 2",
        }
    }
}

/// How much a message matters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Severity {
    /// Something the user may want to know (e.g. a setting the scene forced).
    Notice,
    /// Something that may spoil the result (a skipped step, content piling up at the extent).
    Warning,
}

/// Called by the trainers; every hook defaults to doing nothing.
pub trait TrainObserver {
    /// A stage starts (or resumes) at `step` of `total` steps.
    fn stage_begins(&mut self, _stage: Stage, _step: usize, _total: usize) {}

    /// A message for the user; `text` names the stage and step where that matters.
    fn message(&mut self, _severity: Severity, _text: &str) {}

    /// After stage-1 step `session.step` (already counted) has updated the field.
    fn stage1_step(&mut self, _session: &Session, _stats: &StepStats) -> Result<(), RunError> {
        Ok(())
    }

    /// After stage-2 step `seg.step` (already counted) has updated the head.
    fn stage2_step(&mut self, _session: &Session, _seg: &Segmenter, _stats: &SegStepStats) -> Result<(), RunError> {
        Ok(())
    }

    /// A stage has run all its steps.
    fn stage_ends(&mut self, _stage: Stage) {}
}

/// The observer of a run nobody watches.
pub struct Unobserved;

impl TrainObserver for Unobserved {}
