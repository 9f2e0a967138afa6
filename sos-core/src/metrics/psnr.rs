//! Mean squared error and PSNR in both of the reference's conventions.

use super::MetricError;

/// Mean squared error between two images (any layout, same length), accumulated in `f64`.
pub fn mse(a: &[f32], b: &[f32]) -> Result<f64, MetricError> {
    if a.len() != b.len() {
        return Err(MetricError::SizeMismatch {
            what: "MSE: rendered and ground-truth images",
            left: a.len(),
            right: b.len(),
        });
    }
    if a.is_empty() {
        return Err(MetricError::Empty { what: "MSE: images" });
    }
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    Ok(sum / a.len() as f64)
}

/// Smallest MSE a PSNR is computed from: identical images get 120 dB rather than `+∞`, which
/// JSON cannot hold (it would be written as `null`) and which would make every mean infinite.
pub const PSNR_MSE_FLOOR: f64 = 1e-12;

/// PSNR of images in `[0, 1]`: `−10·log10(mse)`, at most 120 dB ([`PSNR_MSE_FLOOR`]); NaN for a
/// NaN error.
pub fn psnr_from_mse(mse: f64) -> f64 {
    // Not `max`, which would turn a NaN error into 120 dB.
    let mse = if mse < PSNR_MSE_FLOOR { PSNR_MSE_FLOOR } else { mse };
    -10.0 * mse.log10()
}

/// The reference's in-loop `evaluate` PSNR: the PSNR of the mean of the per-image MSEs
/// (`None` for no images).
pub fn psnr_of_mean_mse(mses: &[f64]) -> Option<f64> {
    (!mses.is_empty()).then(|| psnr_from_mse(mses.iter().sum::<f64>() / mses.len() as f64))
}

/// The offline script's PSNR: the mean of the per-image PSNRs (`None` for no images).
/// Never below [`psnr_of_mean_mse`] (Jensen); an exactly reproduced image counts 120 dB.
pub fn mean_psnr(mses: &[f64]) -> Option<f64> {
    (!mses.is_empty()).then(|| mses.iter().map(|&m| psnr_from_mse(m)).sum::<f64>() / mses.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::fixture;

    #[test]
    fn reproduces_reference_fixture() {
        let fx = fixture::load();
        for (i, case) in fx.images.iter().enumerate() {
            let m = mse(&case.a.f32(), &case.b.f32()).unwrap();
            let p = psnr_from_mse(m);
            // The reference computed in f32; the f64 value differs by < 7e-7.
            assert!((p - case.psnr).abs() < 1e-6, "case {i}: {p} vs {}", case.psnr);
            assert_eq!(psnr_of_mean_mse(&[m]), Some(p));
            assert_eq!(mean_psnr(&[m]), Some(p));
        }
    }

    #[test]
    fn both_conventions_differ_as_expected() {
        let mses = [1e-2, 1e-4];
        // PSNR of the mean MSE: −10·log10(0.00505); mean PSNR: (20 + 40) / 2.
        assert!((psnr_of_mean_mse(&mses).unwrap() - 22.967_086_218_813_38).abs() < 1e-9);
        assert!((mean_psnr(&mses).unwrap() - 30.0).abs() < 1e-12);
        assert_eq!(psnr_of_mean_mse(&[]), None);
        assert_eq!(mean_psnr(&[]), None);
        assert_eq!(psnr_from_mse(0.0), 120.0);
        assert!(mse(&[0.0], &[0.0, 1.0]).is_err());
        assert!(mse(&[], &[]).is_err());
        assert_eq!(mse(&[0.0, 1.0], &[0.5, 0.0]).unwrap(), 0.625);
    }
}
