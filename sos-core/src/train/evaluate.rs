//! Evaluation of held-out views: renders them, writes PNGs and image-quality metrics.

use std::time::Instant;

use serde::Serialize;

use crate::error::RunError;
use crate::metrics::{psnr_from_mse, ImageQualityReport};
use crate::train::session::Session;

/// Quality of one held-out view.
#[derive(Debug, Clone, Serialize)]
pub struct ViewQuality {
    /// View name.
    pub view: String,
    /// PSNR in dB.
    pub psnr: f64,
    /// Mean squared error.
    pub mse: f64,
    /// Structural similarity (11x11 Gaussian window, as the reference).
    pub ssim: f64,
}

/// Image-quality summary over the held-out views.
#[derive(Debug, Clone, Serialize)]
pub struct ImageEval {
    /// PSNR of the mean MSE over views (the reference's in-loop value).
    pub psnr: f64,
    /// Mean of per-view PSNR (the reference's offline value).
    pub psnr_mean_per_view: f64,
    /// Mean SSIM over views.
    pub ssim: f64,
    /// Per-view values.
    pub views: Vec<ViewQuality>,
    /// Rays rendered per second while rendering the views.
    pub render_rays_per_second: f64,
}

/// Held-out PSNR this many dB below the last training batch's is reported as overfitting. A
/// field that fits its training views honestly generalises within a few dB (4 dB on the main
/// job at 1000 steps); one that paints content missing from its extent as fog in front of each
/// training camera fits those rays (30 dB) and fails every other view (17 dB).
pub const OVERFIT_GAP_DB: f64 = 8.0;

/// A warning when held-out views are far worse than the training rays, with what to try.
pub fn overfitting_warning(train_psnr: f64, test_psnr: f64) -> Option<String> {
    (train_psnr.is_finite() && test_psnr.is_finite() && train_psnr - test_psnr > OVERFIT_GAP_DB).then(|| {
        format!(
            "held-out PSNR {test_psnr:.1} dB is {:.1} dB below the training rays' {train_psnr:.1} dB: the field \
             explains its training views with content other views do not confirm (typically fog in front of \
             the cameras when the scene reaches beyond its extent): check `resolved.toml`'s extent, drop a \
             too small `aabb` for the unbounded extent, or raise `near`",
            train_psnr - test_psnr
        )
    })
}

#[cfg(test)]
mod overfitting_tests {
    use super::*;

    #[test]
    fn only_a_large_finite_gap_warns() {
        assert!(overfitting_warning(30.0, 17.0).unwrap().contains("13.0 dB below"));
        assert!(overfitting_warning(31.0, 27.5).is_none());
        assert!(overfitting_warning(f64::NAN, 10.0).is_none());
        assert!(overfitting_warning(40.0, f64::NAN).is_none());
    }
}

/// Renders every held-out view into `<run>/test/` and returns the metrics.
pub fn evaluate_views(session: &Session, write_images: bool) -> Result<ImageEval, RunError> {
    let mut views = Vec::new();
    let mut rays = 0usize;
    let started = Instant::now();
    for &i in &session.scene.test {
        let v = &session.scene.views[i];
        let (img, _) = session.render_view(&v.camera);
        rays += img.width * img.height;
        let mse = crate::metrics::mse(&img.data, &v.image.data)
            .map_err(|e| crate::error::IoError::file(&session.run_dir, format!("MSE of view {}: {e}", v.name)))?;
        if write_images {
            img.save_png(&session.run_dir.join("test").join(format!("{}.png", v.name)))?;
        }
        let ssim = crate::metrics::ssim(&img, &v.image)
            .map_err(|e| crate::error::IoError::file(&session.run_dir, format!("SSIM of view {}: {e}", v.name)))?;
        // Floored at 120 dB for an exact view; a NaN render stays NaN, never a perfect score.
        views.push(ViewQuality { view: v.name.clone(), psnr: psnr_from_mse(mse), mse, ssim });
    }
    let elapsed = started.elapsed().as_secs_f64().max(1e-9);
    // No held-out view measures nothing: NaN (written as null), never an empty mean's 120 dB.
    let mean = |value: fn(&ViewQuality) -> f64| {
        if views.is_empty() {
            f64::NAN
        } else {
            views.iter().map(value).sum::<f64>() / views.len() as f64
        }
    };
    Ok(ImageEval {
        psnr: psnr_from_mse(mean(|v| v.mse)),
        psnr_mean_per_view: mean(|v| v.psnr),
        ssim: mean(|v| v.ssim),
        views,
        render_rays_per_second: rays as f64 / elapsed,
    })
}

impl ImageEval {
    /// The same summary from a report another pass already measured (mask inference renders
    /// and measures the held-out colour too); `seconds` is that pass's time for `rays` rays.
    pub fn from_report(report: &ImageQualityReport, rays: usize, seconds: f64) -> ImageEval {
        let views: Vec<ViewQuality> = report
            .views()
            .iter()
            .map(|v| ViewQuality { view: v.name.clone(), psnr: v.psnr, mse: v.mse, ssim: v.ssim })
            .collect();
        ImageEval {
            psnr: report.psnr_of_mean_mse().unwrap_or(f64::NAN),
            psnr_mean_per_view: report.mean_psnr().unwrap_or(f64::NAN),
            ssim: report.mean_ssim().unwrap_or(f64::NAN),
            views,
            render_rays_per_second: rays as f64 / seconds.max(1e-9),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::psnr_from_mse;

    /// A summary taken from another pass's report carries its per-view values and both PSNR
    /// conventions unchanged.
    #[test]
    fn summary_from_a_report_keeps_its_values() {
        let mut report = ImageQualityReport::new();
        report.push("a", 1e-3, 0.9);
        report.push("b", 4e-3, 0.8);
        let eval = ImageEval::from_report(&report, 1000, 0.5);
        assert_eq!(eval.views.iter().map(|v| v.view.as_str()).collect::<Vec<_>>(), ["a", "b"]);
        assert!((eval.views[1].psnr - psnr_from_mse(4e-3)).abs() < 1e-9);
        assert!((eval.psnr - psnr_from_mse(2.5e-3)).abs() < 1e-9, "{}", eval.psnr);
        assert!((eval.psnr_mean_per_view - (psnr_from_mse(1e-3) + psnr_from_mse(4e-3)) / 2.0).abs() < 1e-9);
        assert!((eval.ssim - 0.85).abs() < 1e-12);
        assert!((eval.render_rays_per_second - 2000.0).abs() < 1e-6);
    }
}
