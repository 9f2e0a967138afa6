//! Branch-free `exp`, `erf` and GELU for the ViT's softmax and MLP, written so that loops over
//! slices vectorise (the standard library's `exp` is a scalar call).
//!
//! - `exp`: `2^n · e^r` with `n = round(x / ln 2)`, `r` reduced with a two-part `ln 2`, and a
//!   degree-6 Taylor polynomial for `e^r` on `|r| ≤ ln 2 / 2` (relative error about 2e-7).
//! - `erf`: Abramowitz & Stegun 7.1.26, `1 − t·P(t)·e^(−x²)` with `t = 1/(1 + p|x|)`
//!   (absolute error 1.5e-7 in exact arithmetic, below 1e-6 in `f32`).
//! - GELU: the exact (erf) form `x/2 · (1 + erf(x/√2))`, as PyTorch's `nn.GELU()`.

const LN2_HI: f32 = 0.693_145_75;
const LN2_LO: f32 = 1.428_606_8e-6;
const LOG2E: f32 = std::f32::consts::LOG2_E;
/// 1.5·2²³: adding and subtracting it rounds an `f32` of magnitude below 2²² to the nearest
/// integer with plain additions (which vectorise on any x86-64, unlike `round`).
const ROUNDER: f32 = 12_582_912.0;

/// `e^x` for `f32`; inputs below −87 give about 1.6e-38 instead of denormals or 0, inputs
/// above 88 are clamped (no infinities).
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    // Compare-and-select clamps and integer bit arithmetic keep the loop vectorisable.
    let x = if x < -87.0 { -87.0 } else { x };
    let x = if x > 88.0 { 88.0 } else { x };
    let shifted = x * LOG2E + ROUNDER;
    let n = shifted - ROUNDER;
    // The low mantissa bits of `shifted` hold n (two's complement): 2^n's exponent field.
    let n_bits = shifted.to_bits().wrapping_sub(ROUNDER.to_bits());
    let scale = f32::from_bits(n_bits.wrapping_add(127) << 23);
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    p * scale
}

/// The error function.
#[inline(always)]
pub fn erf(x: f32) -> f32 {
    const P: f32 = 0.327_591_1;
    const A: [f32; 5] = [0.254_829_6, -0.284_496_74, 1.421_413_7, -1.453_152_1, 1.061_405_4];
    let a = x.abs();
    let t = 1.0 / (1.0 + P * a);
    let poly = t * (A[0] + t * (A[1] + t * (A[2] + t * (A[3] + t * A[4]))));
    let y = 1.0 - poly * exp(-a * a);
    y.copysign(x)
}

/// Exact GELU, `x/2 · (1 + erf(x/√2))`.
#[inline(always)]
pub fn gelu(x: f32) -> f32 {
    0.5 * x * (1.0 + erf(x * std::f32::consts::FRAC_1_SQRT_2))
}

/// Sum of a slice with eight independent accumulators (vectorises; the order differs from a
/// sequential sum only by rounding).
#[inline]
pub fn sum(values: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = values.chunks_exact(8);
    let rest: f32 = chunks.remainder().iter().sum();
    for c in chunks {
        for k in 0..8 {
            acc[k] += c[k];
        }
    }
    acc.iter().sum::<f32>() + rest
}

/// Maximum of a slice (NaN-free input), with eight independent accumulators.
#[inline]
pub fn max(values: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; 8];
    let chunks = values.chunks_exact(8);
    let rest = chunks.remainder().iter().copied().fold(f32::NEG_INFINITY, f32::max);
    for c in chunks {
        for k in 0..8 {
            acc[k] = if c[k] > acc[k] { c[k] } else { acc[k] };
        }
    }
    acc.iter().copied().fold(rest, f32::max)
}

/// In-place softmax of one row (max-subtracted).
pub fn softmax_row(row: &mut [f32]) {
    let m = max(row);
    for v in row.iter_mut() {
        *v = exp(*v - m);
    }
    let inv = 1.0 / sum(row);
    for v in row.iter_mut() {
        *v *= inv;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// erf in f64: Maclaurin series below 3 (no cancellation there), asymptotic erfc above.
    fn erf_ref(x: f64) -> f64 {
        let a = x.abs();
        if a >= 3.0 {
            let z = 1.0 / (2.0 * a * a);
            let series = 1.0 - z + 3.0 * z * z - 15.0 * z.powi(3) + 105.0 * z.powi(4) - 945.0 * z.powi(5);
            let erfc = (-a * a).exp() / (a * std::f64::consts::PI.sqrt()) * series;
            return (1.0 - erfc).copysign(x);
        }
        let (mut term, mut sum) = (x, x);
        for n in 1..200 {
            term *= -x * x / n as f64;
            let add = term / (2 * n + 1) as f64;
            sum += add;
            if add.abs() < 1e-17 {
                break;
            }
        }
        sum * 2.0 / std::f64::consts::PI.sqrt()
    }

    #[test]
    fn exp_is_accurate_over_the_softmax_range() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            let x = -87.0 + 175.0 * i as f64 / 200_000.0;
            let got = exp(x as f32) as f64;
            let want = (x as f32 as f64).exp();
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 5e-7, "exp relative error {worst}");
        assert_eq!(exp(0.0), 1.0);
        assert!(exp(-1000.0) > 0.0 && exp(-1000.0) < 1e-37);
        assert!(exp(1000.0).is_finite());
    }

    #[test]
    fn erf_and_gelu_are_accurate() {
        let mut worst = 0.0f64;
        for i in 0..=40_000 {
            let x = -6.0 + 12.0 * i as f64 / 40_000.0;
            worst = worst.max((erf(x as f32) as f64 - erf_ref(x as f32 as f64)).abs());
        }
        assert!(worst < 1e-6, "erf absolute error {worst}");
        assert!(erf(0.0).abs() < 1e-6 && erf(-1e-3) < 0.0);
        for x in [-3.0f64, -0.5, 0.0, 0.7, 2.0, 9.0] {
            let want = 0.5 * x * (1.0 + erf_ref(x / std::f64::consts::SQRT_2));
            assert!((gelu(x as f32) as f64 - want).abs() < 2e-6, "gelu({x})");
        }
    }

    #[test]
    fn sums_and_maxima() {
        let v: Vec<f32> = (0..37).map(|i| ((i * 13) % 29) as f32 - 9.0).collect();
        assert_eq!(sum(&v), v.iter().sum::<f32>());
        assert_eq!(max(&v), 19.0);
        assert_eq!(max(&v[..3]), v[..3].iter().copied().fold(f32::MIN, f32::max));
        assert_eq!(sum(&[]), 0.0);
    }

    #[test]
    fn softmax_sums_to_one_and_keeps_order() {
        let mut row = vec![1.0, 3.0, -2.0, 3.0, 100.0, -100.0];
        softmax_row(&mut row);
        assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert!(row[4] > 0.999 && row[5] >= 0.0);
        assert_eq!(row[1], row[3]);
    }
}
