//! Structural similarity with the reference's Gaussian window (`utils/ssim.py`).

use rayon::prelude::*;

use super::MetricError;
use crate::image::RgbImage;

/// Window side in pixels.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the Gaussian window.
pub const SSIM_SIGMA: f64 = 1.5;
/// Stabiliser of the luminance term, `(0.01·L)²` with dynamic range `L = 1`.
pub const SSIM_C1: f64 = 0.01 * 0.01;
/// Stabiliser of the contrast-structure term, `(0.03·L)²`.
pub const SSIM_C2: f64 = 0.03 * 0.03;

const HALF: usize = SSIM_WINDOW / 2;

/// SSIM of two RGB images of the same size (values in `[0, 1]`): 11x11 Gaussian window
/// (σ = 1.5), zero-padded "same" convolution per channel, mean of the SSIM map over all
/// pixels and channels.
pub fn ssim(a: &RgbImage, b: &RgbImage) -> Result<f64, MetricError> {
    check_sizes(a.data.len(), b.data.len(), a.width * a.height * 3)?;
    if (a.width, a.height) != (b.width, b.height) {
        return Err(MetricError::SizeMismatch { what: "SSIM: image widths", left: a.width, right: b.width });
    }
    let sum: f64 = (0..3)
        .map(|c| {
            let pa = Plane { data: &a.data, offset: c, stride: 3 };
            let pb = Plane { data: &b.data, offset: c, stride: 3 };
            ssim_sum(pa, pb, a.height, a.width)
        })
        .sum();
    Ok(sum / (3 * a.width * a.height) as f64)
}

/// SSIM of two channel-first images `[channels, height, width]` (the reference's CHW
/// tensors), same definition as [`ssim`].
pub fn ssim_planar(a: &[f32], b: &[f32], channels: usize, height: usize, width: usize) -> Result<f64, MetricError> {
    check_sizes(a.len(), b.len(), channels * height * width)?;
    let plane = height * width;
    let sum: f64 = (0..channels)
        .map(|c| {
            let pa = Plane { data: a, offset: c * plane, stride: 1 };
            let pb = Plane { data: b, offset: c * plane, stride: 1 };
            ssim_sum(pa, pb, height, width)
        })
        .sum();
    Ok(sum / (channels * plane) as f64)
}

fn check_sizes(a: usize, b: usize, expected: usize) -> Result<(), MetricError> {
    if a != b {
        return Err(MetricError::SizeMismatch { what: "SSIM: the two images", left: a, right: b });
    }
    if a != expected {
        return Err(MetricError::SizeMismatch {
            what: "SSIM: buffer length and channels x height x width",
            left: a,
            right: expected,
        });
    }
    if a == 0 {
        return Err(MetricError::Empty { what: "SSIM: images" });
    }
    Ok(())
}

/// One channel of an image, pixel `i` at `data[offset + i * stride]`.
#[derive(Clone, Copy)]
struct Plane<'a> {
    data: &'a [f32],
    offset: usize,
    stride: usize,
}

impl Plane<'_> {
    #[inline]
    fn at(&self, i: usize) -> f64 {
        self.data[self.offset + i * self.stride] as f64
    }
}

/// Normalised 1D Gaussian; the 2D window is its outer product, so the 2D convolution is a
/// horizontal pass followed by a vertical one (22 instead of 121 taps per pixel).
fn gaussian() -> [f64; SSIM_WINDOW] {
    let mut g = [0.0; SSIM_WINDOW];
    for (i, v) in g.iter_mut().enumerate() {
        let x = i as f64 - HALF as f64;
        *v = (-x * x / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let total: f64 = g.iter().sum();
    g.map(|v| v / total)
}

/// Sum of the SSIM map of one channel.
fn ssim_sum(a: Plane, b: Plane, height: usize, width: usize) -> f64 {
    let g = gaussian();
    // Horizontal pass of the five moment images (x, y, x², y², xy), interleaved per pixel.
    let mut horiz = vec![[0.0f64; 5]; height * width];
    horiz.par_chunks_mut(width).enumerate().for_each(|(r, row)| {
        let base = r * width;
        for (c, out) in row.iter_mut().enumerate() {
            let lo = c.saturating_sub(HALF);
            let hi = (c + HALF).min(width - 1);
            let mut acc = [0.0; 5];
            for cc in lo..=hi {
                let w = g[cc + HALF - c];
                let (x, y) = (a.at(base + cc), b.at(base + cc));
                acc[0] += w * x;
                acc[1] += w * y;
                acc[2] += w * x * x;
                acc[3] += w * y * y;
                acc[4] += w * x * y;
            }
            *out = acc;
        }
    });
    // Vertical pass and the SSIM formula, one row per task; rows summed in order so the
    // result does not depend on the thread count.
    let row_sums: Vec<f64> = (0..height)
        .into_par_iter()
        .map(|r| {
            let lo = r.saturating_sub(HALF);
            let hi = (r + HALF).min(height - 1);
            let mut sum = 0.0;
            for c in 0..width {
                let mut m = [0.0; 5];
                for rr in lo..=hi {
                    let w = g[rr + HALF - r];
                    let h = &horiz[rr * width + c];
                    for k in 0..5 {
                        m[k] += w * h[k];
                    }
                }
                let (mu1, mu2) = (m[0], m[1]);
                let s11 = m[2] - mu1 * mu1;
                let s22 = m[3] - mu2 * mu2;
                let s12 = m[4] - mu1 * mu2;
                sum += ((2.0 * mu1 * mu2 + SSIM_C1) * (2.0 * s12 + SSIM_C2))
                    / ((mu1 * mu1 + mu2 * mu2 + SSIM_C1) * (s11 + s22 + SSIM_C2));
            }
            sum
        })
        .collect();
    row_sums.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::fixture;

    /// Direct 2D zero-padded convolution, the reference's definition, for cross-checking.
    fn ssim_direct(a: &[f32], b: &[f32], h: usize, w: usize) -> f64 {
        let g = gaussian();
        let at = |d: &[f32], r: isize, c: isize| {
            if r < 0 || c < 0 || r >= h as isize || c >= w as isize {
                0.0
            } else {
                d[r as usize * w + c as usize] as f64
            }
        };
        let mut sum = 0.0;
        for r in 0..h as isize {
            for c in 0..w as isize {
                let mut m = [0.0; 5];
                for i in 0..SSIM_WINDOW as isize {
                    for j in 0..SSIM_WINDOW as isize {
                        let wgt = g[i as usize] * g[j as usize];
                        let (x, y) = (at(a, r + i - 5, c + j - 5), at(b, r + i - 5, c + j - 5));
                        m[0] += wgt * x;
                        m[1] += wgt * y;
                        m[2] += wgt * x * x;
                        m[3] += wgt * y * y;
                        m[4] += wgt * x * y;
                    }
                }
                let (s11, s22, s12) = (m[2] - m[0] * m[0], m[3] - m[1] * m[1], m[4] - m[0] * m[1]);
                sum += ((2.0 * m[0] * m[1] + SSIM_C1) * (2.0 * s12 + SSIM_C2))
                    / ((m[0] * m[0] + m[1] * m[1] + SSIM_C1) * (s11 + s22 + SSIM_C2));
            }
        }
        sum / (h * w) as f64
    }

    #[test]
    fn reproduces_reference_fixture() {
        let fx = fixture::load();
        for (i, case) in fx.images.iter().enumerate() {
            let [n, c, h, w] = case.a.shape[..] else { panic!("NCHW expected") };
            assert_eq!(n, 1);
            let v = ssim_planar(&case.a.f32(), &case.b.f32(), c, h, w).unwrap();
            assert!((v - case.ssim).abs() < 1e-6, "case {i}: {v} vs {}", case.ssim);
        }
    }

    #[test]
    fn interleaved_equals_planar_and_direct_convolution() {
        let fx = fixture::load();
        let case = &fx.images[0];
        let (h, w) = (case.a.shape[2], case.a.shape[3]);
        let (a, b) = (case.a.f32(), case.b.f32());
        let to_rgb = |p: &[f32]| {
            let mut img = RgbImage::new(w, h);
            for ch in 0..3 {
                for i in 0..h * w {
                    img.data[i * 3 + ch] = p[ch * h * w + i];
                }
            }
            img
        };
        let planar = ssim_planar(&a, &b, 3, h, w).unwrap();
        let rgb = ssim(&to_rgb(&a), &to_rgb(&b)).unwrap();
        assert!((planar - rgb).abs() < 1e-12);
        let direct: f64 =
            (0..3).map(|c| ssim_direct(&a[c * h * w..][..h * w], &b[c * h * w..][..h * w], h, w)).sum::<f64>() / 3.0;
        assert!((planar - direct).abs() < 1e-12, "{planar} vs {direct}");
    }

    #[test]
    fn identical_images_score_one_and_sizes_are_checked() {
        let mut img = RgbImage::new(13, 7);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = ((i * 37) % 101) as f32 / 100.0;
        }
        assert!((ssim(&img, &img).unwrap() - 1.0).abs() < 1e-12);
        let mut other = img.clone();
        other.data.iter_mut().for_each(|v| *v = 1.0 - *v);
        assert!(ssim(&img, &other).unwrap() < 0.5);
        assert!(ssim(&img, &RgbImage::new(7, 13)).is_err());
        assert!(ssim(&img, &RgbImage::new(13, 6)).is_err());
        assert!(ssim_planar(&[0.0; 6], &[0.0; 6], 1, 2, 2).is_err());
        assert!(ssim(&RgbImage::new(0, 0), &RgbImage::new(0, 0)).is_err());
    }
}
