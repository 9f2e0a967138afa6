//! 2D feature extractors (teachers) for nerf-sos.
//!
//! - [`cell_stats`]: `kind = "cell-stats"`, weight-free colour and texture statistics per
//!   cell, the offline fallback for DINO.

pub mod cell_stats;

pub use cell_stats::{CellStats, CellStatsConfig, SaliencyScale};
