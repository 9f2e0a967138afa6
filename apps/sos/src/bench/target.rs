//! Time to a usable mask: `[bench] target = { miou = 0.95, nv_ari = 0.93 }` names the quality a
//! user waits for, and the report gives each run's wall time until it had it.
//!
//! The time is read off the stage-2 learning curve: the training clock (setup, stage 1, stage 2
//! up to the first curve evaluation that meets the target) plus the run's own time to write
//! masks, which a run stopped at that point would still spend. Evaluations are off the clock,
//! as everywhere in the report. Curves sample a run at a few points, so the time is an upper
//! bound that tightens with `curve_points`. A run without curves meets the target, if at all,
//! with its final result.

use serde::{Deserialize, Serialize};

use super::record::Outcome;

/// The quality to reach; an unset metric is not required.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Target {
    /// Mean IoU over both classes.
    pub miou: Option<f64>,
    /// Mean adjusted Rand index (NV-ARI).
    pub nv_ari: Option<f64>,
}

impl Target {
    /// Checks the thresholds: each set one lies in (0, 1], and at least one is set.
    pub fn check(&self) -> Result<(), String> {
        if self.miou.is_none() && self.nv_ari.is_none() {
            return Err("sets neither `miou` nor `nv_ari`".into());
        }
        for (key, value) in [("miou", self.miou), ("nv_ari", self.nv_ari)] {
            if let Some(v) = value {
                if !(v > 0.0 && v <= 1.0) {
                    return Err(format!("`{key}` = {v} is not in (0, 1]"));
                }
            }
        }
        Ok(())
    }

    /// Whether metrics meet every set threshold (a missing metric does not).
    pub fn met_by(&self, miou: Option<f64>, nv_ari: Option<f64>) -> bool {
        let meets = |want: Option<f64>, got: Option<f64>| want.is_none_or(|w| got.is_some_and(|g| g >= w));
        meets(self.miou, miou) && meets(self.nv_ari, nv_ari)
    }

    /// The wall seconds `outcome` took to meet the target, `None` when it never did.
    pub fn time_to(&self, outcome: &Outcome) -> Option<f64> {
        let t = &outcome.timing;
        let reached = match outcome.curves.stage2.iter().find(|p| self.met_by(p.miou, p.nv_ari)) {
            Some(point) => Some(t.setup + t.stage1 + point.seconds + t.masks),
            None if outcome.curves.stage2.is_empty() => {
                self.met_by(outcome.metrics.miou, outcome.metrics.nv_ari).then_some(t.total)
            }
            None => None,
        };
        reached.filter(|s| s.is_finite())
    }

    /// `mIoU ≥ 0.95, NV-ARI ≥ 0.93`, for the report.
    pub fn describe(&self) -> String {
        let parts: Vec<String> = [("mIoU", self.miou), ("NV-ARI", self.nv_ari)]
            .iter()
            .filter_map(|(name, v)| v.map(|v| format!("{name} ≥ {v}")))
            .collect();
        parts.join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::record::{Curves, Metrics, Stage2Point, Timing};

    fn outcome(points: &[(f64, f64, f64)], final_miou: f64) -> Outcome {
        Outcome {
            metrics: Metrics { miou: Some(final_miou), nv_ari: Some(final_miou), ..Default::default() },
            timing: Timing { setup: 2.0, stage1: 100.0, stage2: 90.0, masks: 10.0, curve_eval: 30.0, total: 202.0 },
            curves: Curves {
                stage1: Vec::new(),
                stage2: points
                    .iter()
                    .enumerate()
                    .map(|(i, &(seconds, miou, nv_ari))| Stage2Point {
                        step: 10 * (i + 1),
                        seconds,
                        miou: Some(miou),
                        nv_ari: Some(nv_ari),
                    })
                    .collect(),
            },
            ..Default::default()
        }
    }

    const TARGET: Target = Target { miou: Some(0.95), nv_ari: Some(0.93) };

    #[test]
    fn the_first_curve_point_meeting_every_threshold_counts_with_the_mask_time() {
        // The second point has the mIoU but not the NV-ARI; the third has both.
        let o = outcome(&[(30.0, 0.90, 0.88), (60.0, 0.96, 0.92), (90.0, 0.97, 0.95)], 0.97);
        assert_eq!(TARGET.time_to(&o), Some(2.0 + 100.0 + 90.0 + 10.0));
        let only_miou = Target { miou: Some(0.95), nv_ari: None };
        assert_eq!(only_miou.time_to(&o), Some(2.0 + 100.0 + 60.0 + 10.0));
    }

    #[test]
    fn a_run_that_never_meets_the_target_has_no_time() {
        let o = outcome(&[(30.0, 0.90, 0.88), (90.0, 0.94, 0.95)], 0.94);
        assert_eq!(TARGET.time_to(&o), None);
    }

    #[test]
    fn without_curves_the_final_result_decides() {
        assert_eq!(TARGET.time_to(&outcome(&[], 0.96)), Some(202.0));
        assert_eq!(TARGET.time_to(&outcome(&[], 0.90)), None);
    }

    #[test]
    fn missing_metrics_do_not_meet_a_threshold() {
        assert!(!TARGET.met_by(None, Some(0.99)));
        assert!(Target { miou: None, nv_ari: Some(0.5) }.met_by(None, Some(0.6)));
    }

    #[test]
    fn thresholds_outside_the_unit_interval_or_none_at_all_are_refused() {
        assert!(TARGET.check().is_ok());
        assert!(Target::default().check().is_err());
        assert!(Target { miou: Some(1.5), nv_ari: None }.check().is_err());
        assert!(Target { miou: Some(f64::NAN), nv_ari: None }.check().is_err());
        assert_eq!(TARGET.describe(), "mIoU ≥ 0.95, NV-ARI ≥ 0.93");
    }
}
