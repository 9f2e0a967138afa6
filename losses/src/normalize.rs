//! L2 normalisation over channels (`x / max(‖x‖₂, eps)`, as `F.normalize`) and its backward.
//!
//! Buffers are channel-first: `[channels, m]` row-major, one column per point.

/// Normalises each of the `m` columns of `x` (`[channels, m]`) over its channels.
/// Returns the normalised values and the per-column denominators `max(‖x‖₂, eps)`.
///
/// # Panics
/// If `x.len() != channels * m`.
pub fn l2_normalize(x: &[f64], channels: usize, m: usize, eps: f64) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(x.len(), channels * m, "l2_normalize: buffer is not [channels, m]");
    let mut sq = vec![0.0f64; m];
    for row in x.chunks_exact(m.max(1)).take(channels) {
        for (s, v) in sq.iter_mut().zip(row) {
            *s += v * v;
        }
    }
    let denom: Vec<f64> = sq.iter().map(|s| s.sqrt().max(eps)).collect();
    let mut out = vec![0.0f64; x.len()];
    for (orow, row) in out.chunks_exact_mut(m.max(1)).zip(x.chunks_exact(m.max(1))) {
        for ((o, v), d) in orow.iter_mut().zip(row).zip(&denom) {
            *o = v / d;
        }
    }
    (out, denom)
}

/// Backward of [`l2_normalize`]: given the normalised values `xhat`, the denominators and
/// `∂L/∂x̂`, returns `∂L/∂x`. Where the norm was clamped at `eps` the denominator is a constant.
///
/// # Panics
/// If the buffers do not match `[channels, m]`.
pub fn l2_normalize_backward(
    xhat: &[f64],
    denom: &[f64],
    grad_hat: &[f64],
    channels: usize,
    m: usize,
    eps: f64,
) -> Vec<f64> {
    assert_eq!(xhat.len(), channels * m, "l2_normalize_backward: xhat is not [channels, m]");
    assert_eq!(grad_hat.len(), channels * m, "l2_normalize_backward: grad is not [channels, m]");
    assert_eq!(denom.len(), m, "l2_normalize_backward: denom is not [m]");
    // dot[j] = x̂_j · g_j over channels.
    let mut dot = vec![0.0f64; m];
    for c in 0..channels {
        let r = c * m..(c + 1) * m;
        for ((d, x), g) in dot.iter_mut().zip(&xhat[r.clone()]).zip(&grad_hat[r]) {
            *d += x * g;
        }
    }
    let mut out = vec![0.0f64; channels * m];
    for c in 0..channels {
        for j in 0..m {
            let i = c * m + j;
            // Strictly above eps the norm is differentiable: (g − x̂ (x̂·g)) / ‖x‖; otherwise
            // the clamp makes the denominator constant.
            out[i] = if denom[j] > eps { (grad_hat[i] - xhat[i] * dot[j]) / denom[j] } else { grad_hat[i] / denom[j] };
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backward_matches_finite_differences() {
        let (c, m) = (3, 4);
        let x: Vec<f64> = (0..c * m).map(|i| ((i * 37 % 11) as f64 - 5.0) * 0.3).collect();
        let w: Vec<f64> = (0..c * m).map(|i| ((i * 13 % 7) as f64 - 3.0) * 0.5).collect();
        let loss = |x: &[f64]| -> f64 {
            let (y, _) = l2_normalize(x, c, m, 1e-10);
            y.iter().zip(&w).map(|(a, b)| a * b).sum()
        };
        let (y, d) = l2_normalize(&x, c, m, 1e-10);
        let g = l2_normalize_backward(&y, &d, &w, c, m, 1e-10);
        for i in 0..c * m {
            let h = 1e-6;
            let mut xp = x.clone();
            xp[i] += h;
            let mut xm = x.clone();
            xm[i] -= h;
            let fd = (loss(&xp) - loss(&xm)) / (2.0 * h);
            assert!((fd - g[i]).abs() < 1e-7, "i={i}: fd {fd} vs analytic {}", g[i]);
        }
    }
}
