//! Refusing a config whose sizes no machine here could serve, before anything is allocated: an
//! estimate of the largest allocations of a run (the field's parameters and optimiser state,
//! a stage-1 step's samples and the field's tape of them, a stage-2 step's samples) against the
//! machine's memory. The estimate is deliberately rough (within a small factor) and only
//! catches sizes that are wrong by orders of magnitude, such as `rays_per_step = 1e9` or a
//! 1024³ grid, which would otherwise end the process with an allocation failure.

use std::path::Path;

use crate::config::RunConfig;
use crate::error::ConfigError;
use crate::render::memory_budget::machine_memory_bytes;

/// Bytes the core keeps per candidate sample of a step: position, direction, distances,
/// density, colour, weight and their gradients, with some slack for the renderer's indices.
pub const CORE_BYTES_PER_SAMPLE: u64 = 128;

const GIB: f64 = (1u64 << 30) as f64;

/// One term of the estimate and the key that sets it.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryTerm {
    /// Dotted config key to lower when the term is too large.
    pub key: String,
    /// Estimated bytes.
    pub bytes: u64,
}

/// The terms of a run's estimate: the field's parameters, a stage-1 step, a stage-2 step.
pub fn estimate(config: &RunConfig) -> Vec<MemoryTerm> {
    let field = config.field.memory_estimate();
    let t = &config.train;
    let stage1_samples = (t.rays_per_step as u64).saturating_mul(t.samples_per_ray as u64);
    let per_sample = CORE_BYTES_PER_SAMPLE + field.as_ref().map_or(0, |f| f.bytes_per_sample);
    let mut terms =
        vec![MemoryTerm { key: "train.rays_per_step".into(), bytes: stage1_samples.saturating_mul(per_sample) }];
    if let Some(f) = field {
        terms.push(MemoryTerm { key: f.parameter_key, bytes: f.parameter_bytes });
    }
    let g = &config.segment;
    if g.steps > 0 {
        let rays = (g.patches as u64).saturating_mul((g.patch_size as u64).pow(2));
        let samples = rays.saturating_mul(t.samples_per_ray as u64);
        terms.push(MemoryTerm { key: "segment.patches".into(), bytes: samples.saturating_mul(CORE_BYTES_PER_SAMPLE) });
    }
    terms
}

/// Refuses `config` (read from `source`, named in the error) when its estimate exceeds the
/// machine's memory (where that can be read), naming the largest term's key, the estimate and
/// the machine's memory.
pub fn check(config: &RunConfig, source: &Path) -> Result<(), ConfigError> {
    let Some(machine) = machine_memory_bytes() else { return Ok(()) };
    check_against(config, source, machine)
}

/// [`check`] against `machine` bytes of memory.
pub fn check_against(config: &RunConfig, source: &Path, machine: u64) -> Result<(), ConfigError> {
    let terms = estimate(config);
    let total = terms.iter().fold(0u64, |s, t| s.saturating_add(t.bytes));
    if total <= machine {
        return Ok(());
    }
    let largest = terms.iter().max_by_key(|t| t.bytes).expect("the estimate has terms");
    Err(ConfigError::Invalid {
        path: source.to_path_buf(),
        key: largest.key.clone(),
        reason: format!(
            "the run would need about {:.1} GiB ({:.1} GiB for this setting alone) but the machine has {:.1} GiB; \
             lower it",
            total as f64 / GIB,
            largest.bytes as f64 / GIB,
            machine as f64 / GIB
        ),
    })
}
