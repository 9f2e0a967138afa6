//! Geometry against a ground-truth depth map: the median relative error of a rendered depth.
//!
//! Colour can be right while the geometry is wrong (content painted onto the wrong surface,
//! fog in front of a camera); a scene that knows its depth judges the geometry directly.

use super::MetricError;
use crate::render::composite::is_hit;

/// The median over the pixels that show a surface (finite, positive `truth`) of
/// `min(|rendered − truth| / truth, 1)`: a rendered ray that meets nothing counts as a full
/// error, so the value stays in `[0, 1]` and a hole cannot look better than a wrong surface.
/// Pixels without a surface (the sky) are left out; `Ok(None)` when no pixel shows one. A
/// non-finite rendered depth is an empty ray.
pub fn median_relative_depth_error(truth: &[f32], rendered: &[f32]) -> Result<Option<f64>, MetricError> {
    if truth.len() != rendered.len() {
        return Err(MetricError::SizeMismatch {
            what: "ground-truth and rendered depth",
            left: truth.len(),
            right: rendered.len(),
        });
    }
    let mut errors: Vec<f64> = truth
        .iter()
        .zip(rendered)
        .filter(|(t, _)| t.is_finite() && **t > 0.0)
        .map(|(&t, &r)| if is_hit(r) { (((r - t).abs() / t) as f64).min(1.0) } else { 1.0 })
        .collect();
    if errors.is_empty() {
        return Ok(None);
    }
    let mid = errors.len() / 2;
    let (_, upper, _) = errors.select_nth_unstable_by(mid, f64::total_cmp);
    let upper = *upper;
    if errors.len() % 2 == 1 {
        return Ok(Some(upper));
    }
    let lower = errors[..mid].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Ok(Some(0.5 * (lower + upper)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::composite::EMPTY_RAY_DEPTH;

    #[test]
    fn the_median_of_relative_errors_over_surface_pixels() {
        // Errors 10%, 0%, 50%; the sky pixel is left out whatever renders there.
        let truth = [2.0, 4.0, 1.0, f32::INFINITY];
        let rendered = [2.2, 4.0, 1.5, 3.0];
        let e = median_relative_depth_error(&truth, &rendered).unwrap().unwrap();
        assert!((e - 0.1).abs() < 1e-6, "{e}");
        // An even count takes the mean of the middle two: 0%, 10%, 50%, 100% (an empty ray).
        let truth = [2.0, 4.0, 1.0, 5.0];
        let rendered = [2.2, 4.0, 1.5, EMPTY_RAY_DEPTH];
        let e = median_relative_depth_error(&truth, &rendered).unwrap().unwrap();
        assert!((e - 0.3).abs() < 1e-6, "{e}");
    }

    #[test]
    fn errors_are_capped_and_nan_is_an_empty_ray() {
        let e = median_relative_depth_error(&[1.0], &[50.0]).unwrap().unwrap();
        assert_eq!(e, 1.0);
        let e = median_relative_depth_error(&[1.0], &[f32::NAN]).unwrap().unwrap();
        assert_eq!(e, 1.0);
    }

    #[test]
    fn no_surface_measures_nothing_and_sizes_must_match() {
        assert_eq!(median_relative_depth_error(&[f32::INFINITY, 0.0], &[1.0, 1.0]).unwrap(), None);
        assert!(matches!(median_relative_depth_error(&[1.0], &[1.0, 2.0]), Err(MetricError::SizeMismatch { .. })));
    }
}
