//! `sos bench`: every method on every scene, run time against error in one report.
//!
//! A benchmark file ([`spec`]) names scenes, methods (config overlays), sweeps and profiles.
//! [`matrix`] resolves a profile into fully specified runs, checking every key path before
//! anything runs; [`runner`] runs each in its own process (`sos bench-exec`, [`exec`]) and
//! writes a [`record`] per run (a method of another build runs that build's `sos train`,
//! [`program`]); [`report`] and [`plot`] turn the records into tables and
//! charts; [`merge`] joins the folders of sharded runs.

pub mod cli;
pub mod exec;
pub mod matrix;
pub mod merge;
pub mod overlay;
pub mod plot;
pub mod program;
pub mod record;
pub mod report;
pub mod runner;
pub mod spec;
pub mod spread;
pub mod target;
