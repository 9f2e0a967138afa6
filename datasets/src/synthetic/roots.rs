//! Real roots of low-degree polynomials inside an interval, for the torus's quartic.
//!
//! Roots are isolated by the roots of the derivative (found the same way, down to a line), so
//! every sub-interval is monotone and holds at most one root; each is then polished by Newton
//! steps kept inside its bracket. Unlike the closed-form quartic this never loses a root to
//! cancellation, and it costs a few dozen polynomial evaluations.

/// Highest degree handled.
pub const MAX_DEGREE: usize = 4;

/// `c[0] + c[1] x + c[2] x² + …` by Horner's rule.
fn eval(c: &[f64], x: f64) -> f64 {
    c.iter().rev().fold(0.0, |acc, &k| acc * x + k)
}

/// Value and derivative at `x`.
fn eval_with_slope(c: &[f64], x: f64) -> (f64, f64) {
    let (mut p, mut dp) = (0.0, 0.0);
    for &k in c.iter().rev() {
        dp = dp * x + p;
        p = p * x + k;
    }
    (p, dp)
}

/// The root in `[a, b]` of a polynomial monotone there, when its values at the ends differ in
/// sign (or one is zero).
fn bracketed_root(c: &[f64], mut a: f64, mut b: f64) -> Option<f64> {
    let (fa, fb) = (eval(c, a), eval(c, b));
    if fa == 0.0 {
        return Some(a);
    }
    if fb == 0.0 {
        return Some(b);
    }
    if (fa > 0.0) == (fb > 0.0) {
        return None;
    }
    let rising = fb > 0.0;
    let mut x = 0.5 * (a + b);
    for _ in 0..64 {
        let (f, df) = eval_with_slope(c, x);
        if f == 0.0 {
            return Some(x);
        }
        if (f > 0.0) == rising {
            b = x;
        } else {
            a = x;
        }
        let newton = x - f / df;
        // Newton while it stays inside the bracket, bisection otherwise.
        let next = if df != 0.0 && newton > a && newton < b { newton } else { 0.5 * (a + b) };
        if (next - x).abs() <= 1e-13 * (1.0 + x.abs()) || b - a <= 1e-13 * (1.0 + a.abs()) {
            return Some(next);
        }
        x = next;
    }
    Some(x)
}

/// The real roots in `[lo, hi]` of the polynomial with coefficients `c` (constant first, at
/// most [`MAX_DEGREE`] + 1 of them), ascending, written to `out`; returns how many. A double
/// root (a tangency) may be missed, which for ray tracing is a grazing ray.
pub fn roots_in(c: &[f64], lo: f64, hi: f64, out: &mut [f64; MAX_DEGREE]) -> usize {
    assert!(c.len() <= MAX_DEGREE + 1, "degree above {MAX_DEGREE}");
    match c.len() {
        0 | 1 => 0,
        2 => {
            if c[1] == 0.0 {
                return 0;
            }
            let x = -c[0] / c[1];
            if (lo..=hi).contains(&x) {
                out[0] = x;
                1
            } else {
                0
            }
        }
        n => {
            let mut slope = [0.0; MAX_DEGREE];
            for i in 1..n {
                slope[i - 1] = i as f64 * c[i];
            }
            let mut turns = [0.0; MAX_DEGREE];
            let k = roots_in(&slope[..n - 1], lo, hi, &mut turns);
            let mut count = 0;
            let mut a = lo;
            for &b in turns[..k].iter().chain(std::iter::once(&hi)) {
                if let Some(x) = bracketed_root(c, a, b) {
                    // A root on a turning point is found from both sides.
                    if count == 0 || x > out[count - 1] {
                        out[count] = x;
                        count += 1;
                    }
                }
                a = b;
            }
            count
        }
    }
}

/// The smallest real root in `[lo, hi]`, as [`roots_in`].
pub fn smallest_root_in(c: &[f64], lo: f64, hi: f64) -> Option<f64> {
    let mut out = [0.0; MAX_DEGREE];
    (roots_in(c, lo, hi, &mut out) > 0).then_some(out[0])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Coefficients of `∏ (x − r)`.
    fn from_roots(roots: &[f64]) -> Vec<f64> {
        let mut c = vec![1.0];
        for &r in roots {
            let mut next = vec![0.0; c.len() + 1];
            for (i, &k) in c.iter().enumerate() {
                next[i + 1] += k;
                next[i] -= r * k;
            }
            c = next;
        }
        c
    }

    #[test]
    fn finds_every_simple_root_in_the_interval() {
        for roots in
            [vec![0.5], vec![-1.0, 2.0], vec![-3.0, 0.1, 0.2], vec![-2.0, -0.5, 1.0, 7.5], vec![0.3, 0.31, 4.0, 9.0]]
        {
            let c = from_roots(&roots);
            let mut out = [0.0; MAX_DEGREE];
            let n = roots_in(&c, -10.0, 10.0, &mut out);
            assert_eq!(n, roots.len(), "{roots:?} -> {:?}", &out[..n]);
            for (got, want) in out[..n].iter().zip(&roots) {
                assert!((got - want).abs() < 1e-9, "{roots:?}: {got} vs {want}");
            }
            // Only the roots inside the interval.
            let inside = roots.iter().filter(|r| (0.0..=5.0).contains(*r)).count();
            assert_eq!(roots_in(&c, 0.0, 5.0, &mut out), inside);
        }
    }

    #[test]
    fn no_real_roots_and_the_smallest_root() {
        // x⁴ + 1 and (x² + 1)(x − 2).
        assert_eq!(smallest_root_in(&[1.0, 0.0, 0.0, 0.0, 1.0], -5.0, 5.0), None);
        let c = [-2.0, 1.0, -2.0, 1.0];
        assert!((smallest_root_in(&c, -5.0, 5.0).unwrap() - 2.0).abs() < 1e-12);
        assert_eq!(smallest_root_in(&c, -5.0, 1.9), None);
        assert_eq!(smallest_root_in(&[3.0], -1.0, 1.0), None);
    }
}
