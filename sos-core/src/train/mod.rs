//! Training: the run session, stage-1 photometric fitting, checkpoints and evaluation.

pub mod checkpoint;
pub mod convergence;
pub mod evaluate;
pub mod face_pileup;
pub mod memory_check;
pub mod observer;
pub mod photometric;
pub mod run_dir;
pub mod session;

pub use session::Session;
