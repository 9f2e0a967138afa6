//! What `sos` shows while it trains: a progress bar per stage on a terminal, a log line every
//! tenth of a stage otherwise, the trainers' notices and warnings, and with `SOS_PROFILE` set
//! the time of every step's phases. The library prints nothing; this observer does it all.

use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use sos_core::error::RunError;
use sos_core::render::renderer::RenderTiming;
use sos_core::segment::train::{SegStepStats, Segmenter};
use sos_core::train::observer::{Severity, Stage, TrainObserver};
use sos_core::train::photometric::StepStats;
use sos_core::train::Session;

/// Environment variable that turns the per-step phase profile on.
pub const PROFILE_VAR: &str = "SOS_PROFILE";

/// Weight of the newest batch in the smoothed stage-1 PSNR shown on the bar.
const PSNR_SMOOTHING: f64 = 0.1;

/// Prints a run's progress to stderr.
pub struct Console {
    show_bars: bool,
    profile: bool,
    bar: ProgressBar,
    started: Instant,
    first_step: usize,
    total: usize,
    smoothed_psnr: Option<f64>,
}

impl Console {
    /// A console that draws bars when `show_bars` (a terminal and no `--quiet`) and otherwise
    /// logs every tenth of a stage; the profile follows [`PROFILE_VAR`].
    pub fn new(show_bars: bool) -> Console {
        Console {
            show_bars,
            profile: std::env::var_os(PROFILE_VAR).is_some(),
            bar: ProgressBar::hidden(),
            started: Instant::now(),
            first_step: 0,
            total: 0,
            smoothed_psnr: None,
        }
    }

    /// Prints one line above the bar, or to stderr when the bar is hidden (no terminal):
    /// `ProgressBar::println` drops the line on a hidden bar, and logs must keep notices and
    /// skipped-step reports.
    fn line(&self, text: &str) {
        if self.bar.is_hidden() {
            eprintln!("{text}");
        } else {
            self.bar.println(text);
        }
    }

    /// Whether `step` (of this stage) gets a log line when no bar is drawn.
    fn logs(&self, step: usize) -> bool {
        !self.show_bars && (step.is_multiple_of((self.total / 10).max(1)) || step == self.total)
    }

    /// Seconds per step since the stage (re)started.
    fn seconds_per_step(&self, step: usize) -> f64 {
        self.started.elapsed().as_secs_f64() / step.saturating_sub(self.first_step).max(1) as f64
    }
}

fn render_profile(r: &RenderTiming) -> String {
    format!(
        "render: march {:.3} density {:.3} filter {:.3} forward {:.3} (candidates {}, evaluated {}, kept {})",
        r.march, r.density, r.filter, r.forward, r.candidates, r.evaluated, r.kept
    )
}

impl TrainObserver for Console {
    fn stage_begins(&mut self, stage: Stage, step: usize, total: usize) {
        self.bar = if self.show_bars { ProgressBar::new(total as u64) } else { ProgressBar::hidden() };
        let template =
            format!("{} {{bar:30}} {{pos}}/{{len}} {{msg}} [{{elapsed_precise}}<{{eta_precise}}]", stage.label());
        if let Ok(style) = ProgressStyle::with_template(&template) {
            self.bar.set_style(style);
        }
        self.bar.set_position(step as u64);
        self.started = Instant::now();
        self.first_step = step;
        self.total = total;
        self.smoothed_psnr = None;
    }

    fn message(&mut self, severity: Severity, text: &str) {
        match severity {
            Severity::Notice => self.line(&format!("notice: {text}")),
            Severity::Warning => self.line(&format!("warning: {text}")),
        }
    }

    fn stage1_step(&mut self, session: &Session, stats: &StepStats) -> Result<(), RunError> {
        let step = session.step;
        let psnr = match self.smoothed_psnr {
            None => stats.psnr,
            Some(s) => (1.0 - PSNR_SMOOTHING) * s + PSNR_SMOOTHING * stats.psnr,
        };
        self.smoothed_psnr = Some(psnr);
        let rays_per_s = session.config.train.rays_per_step as f64 / self.seconds_per_step(step).max(1e-9);
        if self.profile {
            let t = &stats.timing;
            self.line(&render_profile(&t.render));
            self.line(&format!(
                "backward: composite {:.3} field {:.3} regularize {:.3} step {:.3}",
                t.composite_backward, t.field_backward, t.regularize, t.step
            ));
        }
        self.bar.set_message(format!(
            "loss {:.5} psnr {:.2} dB  {:.0} rays/s  {:.0} samples/ray",
            stats.mse, psnr, rays_per_s, stats.samples_per_ray
        ));
        self.bar.set_position(step as u64);
        if self.logs(step) {
            let faces = stats.faces.map_or(String::new(), |f| {
                format!(", {:.1}% of rays end on a face ({:.1}x the error)", 100.0 * f.ray_fraction, f.error_ratio)
            });
            eprintln!(
                "stage 1 step {}/{}: loss {:.5} psnr {:.2} dB, opacity {:.3}, {:.0} rays/s, {:.0} samples/ray{faces}, {:.0} s",
                step,
                self.total,
                stats.mse,
                psnr,
                stats.opacity,
                rays_per_s,
                stats.samples_per_ray,
                self.started.elapsed().as_secs_f64()
            );
        }
        Ok(())
    }

    fn stage2_step(&mut self, _session: &Session, seg: &Segmenter, stats: &SegStepStats) -> Result<(), RunError> {
        let step = seg.step;
        if self.profile {
            let t = &stats.timing;
            self.line(&render_profile(&t.render));
            self.line(&format!(
                "stage 2: render {:.3} head {:.3} teacher {:.3} losses {:.3} backward {:.3}",
                t.field, t.head, t.teacher, t.losses, t.backward
            ));
        }
        let per_step = self.seconds_per_step(step);
        self.bar.set_message(format!(
            "loss {:+.4}  {:.1} s/step  {:.1} head samples/ray  cache {}/{}",
            stats.total,
            per_step,
            stats.samples_per_ray,
            seg.teacher.hits,
            seg.teacher.hits + seg.teacher.misses
        ));
        self.bar.set_position(step as u64);
        if self.logs(step) || (!self.show_bars && stats.mask_change.is_some()) {
            let change = stats.mask_change.map(|c| format!(", masks changed {:.2}%", 100.0 * c)).unwrap_or_default();
            eprintln!(
                "stage 2 step {}/{}: loss {:+.5}, {:.2} s/step, {:.1} head samples/ray{change}, {:.0} s",
                step,
                self.total,
                stats.total,
                per_step,
                stats.samples_per_ray,
                self.started.elapsed().as_secs_f64()
            );
        }
        Ok(())
    }

    fn stage_ends(&mut self, _stage: Stage) {
        self.bar.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hidden_bars_report_hidden() {
        // `Console::line` relies on this to fall back to stderr.
        assert!(ProgressBar::hidden().is_hidden());
    }

    #[test]
    fn logs_every_tenth_of_a_stage_without_bars() {
        let mut console = Console::new(false);
        console.stage_begins(Stage::Segmentation, 0, 100);
        let logged: Vec<usize> = (1..=100).filter(|&s| console.logs(s)).collect();
        assert_eq!(logged, (1..=10).map(|i| i * 10).collect::<Vec<_>>());
        let mut with_bars = Console::new(true);
        with_bars.stage_begins(Stage::Segmentation, 0, 100);
        assert!(!(1..=100).any(|s| with_bars.logs(s)));
    }
}
