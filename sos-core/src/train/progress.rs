//! Messages printed while a progress bar may be on screen.

use indicatif::ProgressBar;

/// Prints one line above the bar, or to stderr when the bar is hidden (no terminal):
/// `ProgressBar::println` drops the line on a hidden bar, and logs must keep notices and
/// skipped-step reports.
pub fn log_line(bar: &ProgressBar, line: impl AsRef<str>) {
    if bar.is_hidden() {
        eprintln!("{}", line.as_ref());
    } else {
        bar.println(line);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hidden_bars_report_hidden() {
        // `log_line` relies on this to fall back to stderr.
        assert!(ProgressBar::hidden().is_hidden());
    }
}
