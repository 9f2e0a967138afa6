//! `exp`, `ln(1 + x)`, softplus and the logistic function over slices, written without calls
//! or branches so that the loops vectorise (the C library's `expf` and `log1pf` are one call
//! per value). Cephes' range reductions and polynomials: within 2 ulp of the exact values over
//! the ranges the tests sweep (against f64), and deterministic (plain IEEE operations, no
//! fused multiply-add).

/// `log2(e)`.
const LOG2E: f32 = std::f32::consts::LOG2_E;
/// `ln 2` split into a part exact in few bits and the rest (Cody-Waite reduction).
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// Below this `e^x` is under the smallest normal `f32` and is returned as 0.
const EXP_MIN: f32 = -87.336_55;
/// Above this `e^x` is returned as `e^88.3` (finite; `2^n` must stay a normal exponent).
const EXP_MAX: f32 = 88.3;
/// Adding and subtracting `1.5 · 2^23` rounds an `f32` of magnitude below `2^22` to the
/// nearest integer (ties to even) without a call.
const ROUND_MAGIC: f32 = 12_582_912.0;

/// `e^x`: 0 below `EXP_MIN`, `e^EXP_MAX` above `EXP_MAX`, NaN for NaN.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let clamped = x.clamp(EXP_MIN, EXP_MAX);
    let n = (clamped * LOG2E + ROUND_MAGIC) - ROUND_MAGIC;
    let r = (clamped - n * LN2_HI) - n * LN2_LO;
    let mut p = 1.987_569_1e-4f32;
    p = p * r + 1.398_2e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 0.166_666_65;
    p = p * r + 0.5;
    let e_r = (p * (r * r) + r) + 1.0;
    let scale = f32::from_bits(((n as i32 + 127) as u32) << 23);
    if x < EXP_MIN {
        0.0
    } else {
        e_r * scale
    }
}

/// `ln(u)` for a normal, positive, finite `u`.
#[inline(always)]
fn ln_normal(u: f32) -> f32 {
    let bits = u.to_bits();
    // u = m · 2^e with m in [√½, √2).
    let mut e = ((bits >> 23) as i32 - 127) as f32;
    let mut m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let high = m > std::f32::consts::SQRT_2;
    m = if high { m * 0.5 } else { m };
    e = if high { e + 1.0 } else { e };
    let f = m - 1.0;
    let z = f * f;
    let mut p = 7.037_683_6e-2f32;
    p = p * f - 0.115_146_1;
    p = p * f + 0.116_769_98;
    p = p * f - 0.124_201_41;
    p = p * f + 0.142_493_23;
    p = p * f - 0.166_680_57;
    p = p * f + 0.200_007_15;
    p = p * f - 0.249_999_94;
    p = p * f + 0.333_333_3;
    let mut y = p * f * z;
    y += e * LN2_LO;
    y -= 0.5 * z;
    (f + y) + e * LN2_HI
}

/// `ln(1 + y)` for `y ≥ 0` (finite): `ln(u)` of the rounded `u = 1 + y`, corrected by the
/// rounding error of that sum, so tiny `y` give `y`.
#[inline(always)]
pub fn ln_1p(y: f32) -> f32 {
    let u = 1.0 + y;
    ln_normal(u) + (y - (u - 1.0)) / u
}

/// `ln(1 + e^x)`, and `x` itself above 20 (as [`super::activation::softplus`]); 0 for −∞.
#[inline(always)]
pub fn softplus(x: f32) -> f32 {
    let s = ln_1p(exp(x.min(20.0)));
    if x > 20.0 {
        x
    } else {
        s
    }
}

/// `1 / (1 + e^{−x})`.
#[inline(always)]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp(-x))
}

/// [`softplus`] of every value, in place.
pub fn softplus_in_place(xs: &mut [f32]) {
    for x in xs {
        *x = softplus(*x);
    }
}

/// [`sigmoid`] of every value, in place.
pub fn sigmoid_in_place(xs: &mut [f32]) {
    for x in xs {
        *x = sigmoid(*x);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in units in the last place between two finite `f32` of one sign.
    fn ulps(a: f32, b: f32) -> u32 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs() as u32
    }

    fn sweep(lo: f32, hi: f32, n: usize) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| lo + (hi - lo) * i as f32 / n as f32)
    }

    #[test]
    fn exp_is_within_two_ulp() {
        for x in sweep(-87.3, 88.3, 400_000) {
            let want = f64::from(x).exp() as f32;
            assert!(ulps(exp(x), want) <= 2, "exp({x}) = {} against {want}", exp(x));
        }
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-100.0), 0.0);
        assert_eq!(exp(f32::NEG_INFINITY), 0.0);
        assert!(exp(1000.0).is_finite() && exp(1000.0) > 1e38);
        assert!(exp(f32::NAN).is_nan());
    }

    #[test]
    fn ln_1p_is_within_two_ulp_from_tiny_to_huge() {
        let mut ys: Vec<f32> = (-120..120).map(|k| 2f32.powi(k) * 1.37).collect();
        ys.extend(sweep(0.0, 4.0, 100_000));
        for y in ys {
            let want = f64::from(y).ln_1p() as f32;
            assert!(ulps(ln_1p(y), want) <= 2, "ln_1p({y}) = {} against {want}", ln_1p(y));
        }
        assert_eq!(ln_1p(0.0), 0.0);
    }

    #[test]
    fn softplus_and_sigmoid_match_their_definitions() {
        for x in sweep(-80.0, 30.0, 200_000) {
            let want = if x > 20.0 { x } else { f64::from(x).exp().ln_1p() as f32 };
            assert!(ulps(softplus(x), want) <= 3, "softplus({x}) = {} against {want}", softplus(x));
            let want = (1.0 / (1.0 + (-f64::from(x)).exp())) as f32;
            assert!(ulps(sigmoid(x), want) <= 3, "sigmoid({x}) = {} against {want}", sigmoid(x));
        }
        assert_eq!(softplus(f32::NEG_INFINITY), 0.0);
        let mut xs = vec![-3.0, 0.0, 25.0];
        softplus_in_place(&mut xs);
        assert_eq!(xs, vec![softplus(-3.0), softplus(0.0), 25.0]);
        let mut xs = vec![-3.0, 0.0];
        sigmoid_in_place(&mut xs);
        assert_eq!(xs, vec![sigmoid(-3.0), 0.5]);
    }
}
