//! Resampling of planes and lines to a finer resolution (TensoRF's `upsample_volume_grid`:
//! bilinear on the planes, linear on the lines, corners aligned). It changes the
//! parametrisation between steps, so no gradient flows through it: plain Rust.

/// Lower vertex and fraction of new vertex `i` of `new` vertices on a line of `old` vertices.
fn source(i: usize, old: usize, new: usize) -> (usize, f32) {
    let t = i as f32 * (old - 1) as f32 / (new - 1) as f32;
    let lo = (t.floor() as usize).min(old - 2);
    (lo, t - lo as f32)
}

/// A `[rows · cols, comps]` plane resampled from `old` to `new` `(rows, cols)` vertices.
pub fn plane(values: &[f32], old: (usize, usize), new: (usize, usize), comps: usize) -> Vec<f32> {
    let mut out = vec![0.0; new.0 * new.1 * comps];
    for i in 0..new.0 {
        let (a, fa) = source(i, old.0, new.0);
        for j in 0..new.1 {
            let (b, fb) = source(j, old.1, new.1);
            let dst = &mut out[(i * new.1 + j) * comps..(i * new.1 + j + 1) * comps];
            for (da, wa) in [(0, 1.0 - fa), (1, fa)] {
                for (db, wb) in [(0, 1.0 - fb), (1, fb)] {
                    let row = (a + da) * old.1 + b + db;
                    let src = &values[row * comps..(row + 1) * comps];
                    for (d, s) in dst.iter_mut().zip(src) {
                        *d += wa * wb * s;
                    }
                }
            }
        }
    }
    out
}

/// A `[len, comps]` line resampled from `old` to `new` vertices.
pub fn line(values: &[f32], old: usize, new: usize, comps: usize) -> Vec<f32> {
    let mut out = vec![0.0; new * comps];
    for (i, dst) in out.chunks_exact_mut(comps).enumerate() {
        let (a, fa) = source(i, old, new);
        for (da, wa) in [(0, 1.0 - fa), (1, fa)] {
            let src = &values[(a + da) * comps..(a + da + 1) * comps];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += wa * s;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_functions_are_reproduced() {
        // f(a, b) = 2a + 3b + 1 on a 3x4 plane with two components (the second negated).
        let old = (3, 4);
        let f = |u: f32, v: f32| 2.0 * u + 3.0 * v + 1.0;
        let values: Vec<f32> = (0..12)
            .flat_map(|r| {
                let (i, j) = (r / 4, r % 4);
                let x = f(i as f32 / 2.0, j as f32 / 3.0);
                [x, -x]
            })
            .collect();
        let out = plane(&values, old, (5, 7), 2);
        for i in 0..5 {
            for j in 0..7 {
                let want = f(i as f32 / 4.0, j as f32 / 6.0);
                let got = &out[(i * 7 + j) * 2..(i * 7 + j) * 2 + 2];
                assert!((got[0] - want).abs() < 1e-5 && (got[1] + want).abs() < 1e-5, "({i}, {j}): {got:?} vs {want}");
            }
        }
        assert_eq!(line(&[1.0, 3.0], 2, 3, 1), vec![1.0, 2.0, 3.0]);
    }
}
