//! When stage 1 stops paying, told from the training loss alone (no held-out views needed).
//!
//! Each window of `converged_window` steps gives the PSNR of its mean photometric MSE (the
//! mean, not one batch's value: a batch's loss swings by far more than the late gains). Once
//! that PSNR rises by less than `converged_gain` dB from one window to the next,
//! [`CALM_WINDOWS`] windows in a row, the field has stopped improving on its own rays and
//! stage 1 may end. Windows count only once the field has its full detail: a growing grid's
//! loss jumps after each growth, and a plateau before the last one says nothing about the end.

use crate::metrics::psnr_from_mse;

/// Windows in a row whose gain must stay under the threshold.
pub const CALM_WINDOWS: usize = 2;

/// What one finished window measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowGain {
    /// PSNR of the window's mean training MSE, dB.
    pub psnr: f64,
    /// Rise over the previous counted window, dB (`None` for the first one).
    pub gain: Option<f64>,
}

/// Watches the training loss for its plateau (see the module docs).
#[derive(Debug, Clone)]
pub struct PlateauMonitor {
    window: usize,
    min_gain_db: f64,
    sum: f64,
    count: usize,
    previous: Option<f64>,
    calm: usize,
}

impl PlateauMonitor {
    /// A monitor over windows of `window` steps (at least 1) that calls a rise below
    /// `min_gain_db` a plateau.
    pub fn new(window: usize, min_gain_db: f64) -> Self {
        PlateauMonitor { window: window.max(1), min_gain_db, sum: 0.0, count: 0, previous: None, calm: 0 }
    }

    /// Adds one step's training MSE. `counts` is false while the field still grows: the test
    /// then starts over. Returns the window's figures when this step finished one.
    pub fn observe(&mut self, mse: f64, counts: bool) -> Option<WindowGain> {
        if !counts || !mse.is_finite() {
            *self = PlateauMonitor::new(self.window, self.min_gain_db);
            return None;
        }
        self.sum += mse;
        self.count += 1;
        if self.count < self.window {
            return None;
        }
        let psnr = psnr_from_mse(self.sum / self.count as f64);
        let gain = self.previous.map(|p| psnr - p);
        self.calm = match gain {
            Some(g) if g < self.min_gain_db => self.calm + 1,
            _ => 0,
        };
        self.previous = Some(psnr);
        self.sum = 0.0;
        self.count = 0;
        Some(WindowGain { psnr, gain })
    }

    /// Whether the last [`CALM_WINDOWS`] windows each gained less than the threshold.
    pub fn converged(&self) -> bool {
        self.calm >= CALM_WINDOWS
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// MSE whose PSNR is `db`.
    fn mse_at(db: f64) -> f64 {
        10f64.powf(-db / 10.0)
    }

    /// Feeds whole windows at the given PSNRs; returns the window after which it converged.
    fn run(monitor: &mut PlateauMonitor, window: usize, psnrs: &[f64]) -> Option<usize> {
        for (w, &db) in psnrs.iter().enumerate() {
            for _ in 0..window {
                monitor.observe(mse_at(db), true);
            }
            if monitor.converged() {
                return Some(w);
            }
        }
        None
    }

    #[test]
    fn converges_after_two_calm_windows_in_a_row() {
        let mut m = PlateauMonitor::new(10, 0.05);
        // Gains 1, 0.5, 0.02 (calm), 0.3 (not), 0.01, 0.04: the second calm pair ends it.
        assert_eq!(run(&mut m, 10, &[20.0, 21.0, 21.5, 21.52, 21.82, 21.83, 21.87, 25.0]), Some(6));
    }

    #[test]
    fn steady_gains_never_converge() {
        let mut m = PlateauMonitor::new(5, 0.05);
        let psnrs: Vec<f64> = (0..40).map(|w| 20.0 + 0.1 * w as f64).collect();
        assert_eq!(run(&mut m, 5, &psnrs), None);
    }

    #[test]
    fn a_window_reports_the_psnr_of_its_mean_loss() {
        let mut m = PlateauMonitor::new(2, 0.05);
        assert_eq!(m.observe(0.01, true), None);
        let w = m.observe(0.03, true).expect("the window is full");
        assert!((w.psnr - psnr_from_mse(0.02)).abs() < 1e-12);
        assert_eq!(w.gain, None);
        m.observe(0.02, true);
        let w = m.observe(0.02, true).expect("the window is full");
        assert!(w.gain.expect("a second window has a gain").abs() < 1e-12);
    }

    #[test]
    fn growth_or_a_bad_step_starts_the_test_over() {
        let mut m = PlateauMonitor::new(4, 0.05);
        assert_eq!(run(&mut m, 4, &[30.0, 30.0]), None);
        // A third flat window would converge; a growth in between resets the count.
        m.observe(mse_at(30.0), false);
        assert_eq!(run(&mut m, 4, &[30.0, 30.0]), None);
        assert_eq!(run(&mut m, 4, &[30.0]), Some(0));
        let mut m = PlateauMonitor::new(4, 0.05);
        assert_eq!(run(&mut m, 4, &[30.0, 30.0]), None);
        m.observe(f64::NAN, true);
        assert!(!m.converged());
    }
}
