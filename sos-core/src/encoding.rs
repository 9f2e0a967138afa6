//! Input encodings shared by fields: NeRF's positional encoding and real spherical harmonics.

/// Width of [`positional_encoding`] for `dim` inputs and `frequencies` octaves.
pub const fn positional_encoding_dim(dim: usize, frequencies: usize) -> usize {
    dim * (1 + 2 * frequencies)
}

/// NeRF's positional encoding, in the reference's order: `[x, sin(2⁰x), cos(2⁰x), …,
/// sin(2^(L−1)x), cos(2^(L−1)x)]`, where each sin and cos is applied to all of `x` at once
/// (no π factor). `out.len()` must be [`positional_encoding_dim`].
///
/// Only the first octave calls `sin_cos`; each further octave follows from the previous one by
/// the double-angle formulas. The error then grows about 2× per octave, to 4e-5 at the 10th
/// (measured by the test below), under the phase uncertainty `2^(L−1)·ulp(x)` (1e-4 for
/// |x| ≈ π) that the top octave inherits from the rounding of `x` itself. A stage-2 step
/// encodes a million samples twice, so this saves most of its `sin`/`cos` time.
pub fn positional_encoding(x: &[f32], frequencies: usize, out: &mut [f32]) {
    let d = x.len();
    assert_eq!(out.len(), positional_encoding_dim(d, frequencies), "encoding width");
    out[..d].copy_from_slice(x);
    for (k, &xk) in x.iter().enumerate() {
        let (mut s, mut c) = xk.sin_cos();
        for l in 0..frequencies {
            let base = d * (1 + 2 * l);
            out[base + k] = s;
            out[base + d + k] = c;
            (s, c) = (2.0 * s * c, (c - s) * (c + s));
        }
    }
}

/// Number of real SH coefficients up to `degree` (0..=3).
pub const fn sh_coefficients(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// Real spherical-harmonic basis up to `degree` (≤ 3) at unit direction `d`, in the order and
/// normalisation used by Plenoxels and 3D Gaussian splatting.
pub fn sh_basis(degree: usize, d: [f32; 3], out: &mut [f32]) {
    const C0: f32 = 0.282_094_8;
    const C1: f32 = 0.488_602_5;
    const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];
    const C3: [f32; 7] =
        [-0.590_043_6, 2.890_611_4, -0.457_045_8, 0.373_176_33, -0.457_045_8, 1.445_305_7, -0.590_043_6];
    let [x, y, z] = d;
    out[0] = C0;
    if degree >= 1 {
        out[1] = -C1 * y;
        out[2] = C1 * z;
        out[3] = -C1 * x;
    }
    if degree >= 2 {
        let (xx, yy, zz, xy, yz, xz) = (x * x, y * y, z * z, x * y, y * z, x * z);
        out[4] = C2[0] * xy;
        out[5] = C2[1] * yz;
        out[6] = C2[2] * (2.0 * zz - xx - yy);
        out[7] = C2[3] * xz;
        out[8] = C2[4] * (xx - yy);
        if degree >= 3 {
            out[9] = C3[0] * y * (3.0 * xx - yy);
            out[10] = C3[1] * xy * z;
            out[11] = C3[2] * y * (4.0 * zz - xx - yy);
            out[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            out[13] = C3[4] * x * (4.0 * zz - xx - yy);
            out[14] = C3[5] * z * (xx - yy);
            out[15] = C3[6] * x * (xx - 3.0 * yy);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positional_encoding_matches_reference_layout() {
        let x = [0.5f32, -1.0, 2.0];
        let mut out = vec![0.0; positional_encoding_dim(3, 2)];
        positional_encoding(&x, 2, &mut out);
        assert_eq!(out.len(), 15);
        assert_eq!(&out[..3], &x);
        assert!((out[3] - 0.5f32.sin()).abs() < 1e-7 && (out[6] - 0.5f32.cos()).abs() < 1e-7);
        assert!((out[9 + 2] - 4.0f32.sin()).abs() < 1e-6 && (out[12 + 2] - 4.0f32.cos()).abs() < 1e-6);
    }

    /// The double-angle recurrence stays within the float32 phase uncertainty of direct
    /// evaluation, up to NeRF's 10 octaves, over the range the fields feed in.
    #[test]
    fn positional_encoding_recurrence_matches_direct_evaluation() {
        let frequencies = 10;
        let mut out = vec![0.0; positional_encoding_dim(3, frequencies)];
        let mut worst = vec![0.0f64; frequencies];
        for i in 0..2000 {
            let t = i as f32 / 2000.0;
            let x = [(t - 0.5) * 2.0 * std::f32::consts::PI, (37.0 * t).sin() * 3.0, t * t - 0.3];
            positional_encoding(&x, frequencies, &mut out);
            for (l, worst) in worst.iter_mut().enumerate() {
                for (k, &xk) in x.iter().enumerate() {
                    let phase = f64::from(xk) * f64::from(1u32 << l);
                    let base = 3 * (1 + 2 * l);
                    let err_s = (f64::from(out[base + k]) - phase.sin()).abs();
                    let err_c = (f64::from(out[base + 3 + k]) - phase.cos()).abs();
                    *worst = worst.max(err_s).max(err_c);
                }
            }
        }
        for (l, &w) in worst.iter().enumerate() {
            // ~1 ulp at the first octave, doubling with every octave after it.
            let bound = 2e-7 * f64::from(1u32 << l).max(1.0) * 2.0;
            assert!(w <= bound, "octave {l}: max error {w:e} > {bound:e}");
        }
    }

    #[test]
    fn sh_basis_is_orthonormal_on_the_sphere() {
        // Monte-Carlo over a Fibonacci sphere: ∫ Y_i Y_j dΩ = δ_ij.
        let n = 20000;
        let deg = 3;
        let m = sh_coefficients(deg);
        let mut gram = vec![0.0f64; m * m];
        let mut y = vec![0.0; m];
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f32 * 2.399_963;
            sh_basis(deg, [r * phi.cos(), r * phi.sin(), z], &mut y);
            for a in 0..m {
                for b in 0..m {
                    gram[a * m + b] += (y[a] * y[b]) as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for a in 0..m {
            for b in 0..m {
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((gram[a * m + b] - want).abs() < 2e-2, "({a},{b}) = {}", gram[a * m + b]);
            }
        }
    }
}
