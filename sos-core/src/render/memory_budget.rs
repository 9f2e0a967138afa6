//! One memory budget for what frozen renders and the segmentation head keep between passes.
//!
//! Three buffers trade memory for speed, and each falls back to recomputation when it would
//! not fit, so the budget changes run time, never results:
//! - the density pass's per-sample state (NeRF's trunk activations), so the colour pass does not
//!   run the density network again;
//! - the field's segmentation input at the kept samples, so the head needs no field pass;
//! - the head's forward tapes, so its backward pass does not run it again.
//!
//! Stage 2 with the head at the surface keeps no segmentation input; its cache of rendered
//! patch rays takes that share instead.
//!
//! The split follows what a stage-2 step of the reference-sized NeRF fills when nothing is
//! recomputed (state and input about equal) and leaves the tapes room for the worst case, a
//! copy of the input beside their bfloat16 hidden layer when the input was not kept (up to
//! half as much again): 2 : 2 : 3.

use serde::{Deserialize, Serialize};

/// Bytes per GiB.
const GIB: f64 = (1u64 << 30) as f64;

/// Share of the machine's memory the budget takes when `render.memory_gib` is unset: the rest
/// holds the field, the scene, the teacher cache and the allocator's slack.
pub const MACHINE_SHARE: f64 = 0.6;

/// The memory frozen renders and the head may keep, in bytes, split among their buffers.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MemoryBudget {
    total: usize,
}

impl MemoryBudget {
    /// A budget of `gib` GiB.
    pub fn from_gib(gib: f64) -> MemoryBudget {
        MemoryBudget { total: (gib.max(0.0) * GIB) as usize }
    }

    /// No memory at all: every buffer is recomputed (for tests of the fallbacks).
    pub fn none() -> MemoryBudget {
        MemoryBudget { total: 0 }
    }

    /// Everything kept, however large (for tests of the fast paths).
    pub fn unlimited() -> MemoryBudget {
        MemoryBudget { total: usize::MAX }
    }

    /// Bytes for the density pass's kept per-sample state.
    pub fn density_state(&self) -> usize {
        self.total / 7 * 2
    }

    /// Bytes for the segmentation input a frozen render keeps.
    pub fn seg_input(&self) -> usize {
        self.total / 7 * 2
    }

    /// Bytes for stage 2's cache of rendered patch rays: the segmentation input's share, which
    /// a stage 2 that caches rays (the head at the surface) does not keep.
    pub fn ray_cache(&self) -> usize {
        self.seg_input()
    }

    /// Bytes for the head's forward tapes.
    pub fn head_tapes(&self) -> usize {
        self.total / 7 * 3
    }
}

/// The default budget in GiB: [`MACHINE_SHARE`] of the machine's memory, or of 8 GiB where the
/// machine's cannot be read.
pub fn machine_default_gib() -> (f64, String) {
    match machine_memory_bytes() {
        Some(bytes) => {
            let gib = bytes as f64 / GIB;
            (
                (MACHINE_SHARE * gib * 10.0).floor() / 10.0,
                format!("{:.0}% of the machine's {gib:.1} GiB", MACHINE_SHARE * 100.0),
            )
        }
        None => (
            MACHINE_SHARE * 8.0,
            format!("{:.0}% of 8 GiB (the machine's memory could not be read)", MACHINE_SHARE * 100.0),
        ),
    }
}

/// Total memory of the machine (Linux: `MemTotal` of `/proc/meminfo`).
pub fn machine_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_add_up_to_at_most_the_budget() {
        let b = MemoryBudget::from_gib(14.0);
        assert!(b.density_state() + b.seg_input() + b.head_tapes() <= b.total);
        assert_eq!(b.density_state(), b.seg_input());
        assert!(b.head_tapes() > b.seg_input());
        assert_eq!(MemoryBudget::none().head_tapes(), 0);
    }

    #[test]
    fn the_machine_default_is_a_share_of_a_positive_memory() {
        let (gib, why) = machine_default_gib();
        assert!(gib > 0.0 && gib.is_finite(), "{gib} ({why})");
    }
}
