//! Position-embedding interpolation for inputs whose patch grid differs from the trained one,
//! as DINO's `interpolate_pos_encoding` does it: PyTorch's bicubic `interpolate` (cubic
//! convolution with `A = −0.75`, `align_corners=False`, border indices clamped) of the
//! `g × g` grid to `h × w`, called with `scale_factor = ((h + 0.1)/g, (w + 0.1)/g)`.
//!
//! PyTorch maps output index `i` to the source coordinate `(i + 0.5)/scale − 0.5` using the
//! given scale factor, not `h/g`; the `+0.1` therefore shifts the sampling positions slightly,
//! and this is reproduced here.

/// Cubic-convolution weights of the four taps around a fractional offset `t` (PyTorch's
/// `get_cubic_upsample_coefficients`).
fn cubic_weights(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let near = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let far = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    [far(t + 1.0), near(t), near(1.0 - t), far(2.0 - t)]
}

/// Taps (clamped source indices) and weights of each output index along one axis.
fn axis_taps(input: usize, output: usize, scale: f64) -> Vec<([usize; 4], [f32; 4])> {
    let inv = (1.0 / scale) as f32;
    (0..output)
        .map(|i| {
            let real = inv * (i as f32 + 0.5) - 0.5;
            let base = real.floor();
            let t = real - base;
            let base = base as isize;
            let idx = |k: isize| (base + k).clamp(0, input as isize - 1) as usize;
            ([idx(-1), idx(0), idx(1), idx(2)], cubic_weights(t))
        })
        .collect()
}

/// Resizes a `[g, g, dim]` grid (row-major, channels last) to `[h, w, dim]` the way DINO
/// does for an `h × w` patch grid. Even `h = w = g` resamples (slightly, because of the
/// `+0.1`): DINO skips the interpolation only for square inputs of the trained size, which
/// the caller decides.
pub fn interpolate_pos_grid(grid: &[f32], g: usize, dim: usize, h: usize, w: usize) -> Vec<f32> {
    assert_eq!(grid.len(), g * g * dim, "position grid is not {g}x{g}x{dim}");
    let rows = axis_taps(g, h, (h as f64 + 0.1) / g as f64);
    let cols = axis_taps(g, w, (w as f64 + 0.1) / g as f64);
    // Along the columns first, then the rows (PyTorch's order; only rounding differs).
    let mut tmp = vec![0.0f32; g * w * dim];
    for r in 0..g {
        for (c, (taps, wts)) in cols.iter().enumerate() {
            let out = &mut tmp[(r * w + c) * dim..(r * w + c + 1) * dim];
            for k in 0..4 {
                let src = &grid[(r * g + taps[k]) * dim..(r * g + taps[k] + 1) * dim];
                for (o, s) in out.iter_mut().zip(src) {
                    *o += wts[k] * s;
                }
            }
        }
    }
    let mut out = vec![0.0f32; h * w * dim];
    for (r, (taps, wts)) in rows.iter().enumerate() {
        for c in 0..w {
            let o = &mut out[(r * w + c) * dim..(r * w + c + 1) * dim];
            for k in 0..4 {
                let src = &tmp[(taps[k] * w + c) * dim..(taps[k] * w + c + 1) * dim];
                for (o, s) in o.iter_mut().zip(src) {
                    *o += wts[k] * s;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_sum_to_one_and_interpolate() {
        for t in [0.0f32, 0.25, 0.5, 0.9] {
            let w = cubic_weights(t);
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        }
        assert_eq!(cubic_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
    }

    #[test]
    fn constants_stay_constant() {
        let flat = vec![0.7f32; 14 * 14 * 3];
        for (h, w) in [(4, 4), (14, 14), (47, 63), (20, 7)] {
            let out = interpolate_pos_grid(&flat, 14, 3, h, w);
            assert_eq!(out.len(), h * w * 3);
            assert!(out.iter().all(|v| (v - 0.7).abs() < 1e-5), "{h}x{w}");
        }
    }

    /// Keys' cubic kernel as a function of distance (an independent form of the weights).
    fn kernel(x: f64) -> f64 {
        let (a, x) = (-0.75, x.abs());
        if x <= 1.0 {
            (a + 2.0) * x.powi(3) - (a + 3.0) * x * x + 1.0
        } else if x < 2.0 {
            a * x.powi(3) - 5.0 * a * x * x + 8.0 * a * x - 4.0 * a
        } else {
            0.0
        }
    }

    #[test]
    fn matches_a_direct_evaluation_with_clamped_borders() {
        let g = 14;
        let grid: Vec<f32> = (0..g * g).map(|i| ((i * 37) % 23) as f32 - 11.0).collect();
        let (h, w) = (4, 9);
        let out = interpolate_pos_grid(&grid, g, 1, h, w);
        let (sh, sw) = ((h as f64 + 0.1) / g as f64, (w as f64 + 0.1) / g as f64);
        for r in 0..h {
            for c in 0..w {
                let y = (r as f64 + 0.5) / sh - 0.5;
                let x = (c as f64 + 0.5) / sw - 0.5;
                let mut want = 0.0;
                for i in (y.floor() as i64 - 1)..=(y.floor() as i64 + 2) {
                    for j in (x.floor() as i64 - 1)..=(x.floor() as i64 + 2) {
                        let (ci, cj) = (i.clamp(0, g as i64 - 1) as usize, j.clamp(0, g as i64 - 1) as usize);
                        want += kernel(y - i as f64) * kernel(x - j as f64) * grid[ci * g + cj] as f64;
                    }
                }
                assert!((out[r * w + c] as f64 - want).abs() < 1e-4, "({r},{c}) {} vs {want}", out[r * w + c]);
            }
        }
    }
}
