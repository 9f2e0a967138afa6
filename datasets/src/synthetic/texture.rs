//! Procedural textures: soft-edged checkers and stripes, and smooth value noise.
//!
//! Edges are blurred over a few centimetres and the noise has no feature smaller than about
//! 0.15 m, so a voxel grid of a few centimetres can reproduce the scene closely.

/// RGB colour in `[0, 1]`.
pub type Rgb = [f32; 3];

/// Linear blend `a + t (b − a)`.
pub fn mix(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2])]
}

/// Scales a colour (an `Rgb` is a `Vec3`, scaled as vectors are).
pub use sos_core::camera::scale;

/// A smoothed square wave in `[0, 1]` of period `period` (in the units of `x`); `softness`
/// is the edge width as a fraction of the period.
fn soft_square(x: f32, period: f32, softness: f32) -> f32 {
    let s = (std::f32::consts::TAU * x / period).sin();
    // sin crosses zero with slope 2π/period; dividing by the edge width's share keeps it ±1
    // away from the edges.
    let k = 1.0 / (std::f32::consts::TAU * softness);
    (0.5 + 0.5 * (s * k).clamp(-1.0, 1.0)).clamp(0.0, 1.0)
}

/// Soft checkers over two coordinates: 0 on one colour, 1 on the other.
pub fn checker(u: f32, v: f32, period: f32) -> f32 {
    let a = 2.0 * soft_square(u, period, 0.04) - 1.0;
    let b = 2.0 * soft_square(v, period, 0.04) - 1.0;
    0.5 + 0.5 * a * b
}

/// Soft stripes along one coordinate.
pub fn stripes(u: f32, period: f32) -> f32 {
    soft_square(u, period, 0.05)
}

fn hash(i: i32, j: i32, k: i32, seed: u32) -> f32 {
    let mut h = (i as u32).wrapping_mul(0x8da6_b343)
        ^ (j as u32).wrapping_mul(0xd816_3841)
        ^ (k as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x1656_67b1);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2c1b_3c6d);
    h ^= h >> 12;
    h = h.wrapping_mul(0x297a_2d39);
    h ^= h >> 15;
    (h >> 8) as f32 / (1u32 << 24) as f32
}

/// Value noise in `[0, 1]` with unit lattice spacing, smoothstep-interpolated (C¹).
pub fn value_noise(p: [f32; 3], seed: u32) -> f32 {
    let f = [p[0].floor(), p[1].floor(), p[2].floor()];
    let (i, j, k) = (f[0] as i32, f[1] as i32, f[2] as i32);
    let s = |t: f32| t * t * (3.0 - 2.0 * t);
    let (u, v, w) = (s(p[0] - f[0]), s(p[1] - f[1]), s(p[2] - f[2]));
    let lerp = |a: f32, b: f32, t: f32| a + t * (b - a);
    let mut x = [0.0; 4];
    for (n, (dj, dk)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
        x[n] = lerp(hash(i, j + dj, k + dk, seed), hash(i + 1, j + dj, k + dk, seed), u);
    }
    lerp(lerp(x[0], x[1], v), lerp(x[2], x[3], v), w)
}

/// Two octaves of value noise with features of about `size` and `size / 2`, in `[0, 1]`.
pub fn fbm(p: [f32; 3], size: f32, seed: u32) -> f32 {
    let q = [p[0] / size, p[1] / size, p[2] / size];
    let a = value_noise(q, seed);
    let b = value_noise([2.0 * q[0] + 17.3, 2.0 * q[1] + 5.1, 2.0 * q[2] + 9.7], seed ^ 0x9e37);
    0.65 * a + 0.35 * b
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn textures_stay_in_range_and_are_smooth() {
        let mut prev = fbm([0.0, 0.3, 0.7], 0.3, 1);
        for i in 0..2000 {
            let x = i as f32 * 0.001;
            let n = fbm([x, 0.3, 0.7], 0.3, 1);
            assert!((0.0..=1.0).contains(&n));
            // No jumps between samples 1 mm apart.
            assert!((n - prev).abs() < 0.05, "noise jumps at {x}");
            prev = n;
            let c = checker(x, 0.21, 0.5);
            assert!((0.0..=1.0).contains(&c) && (0.0..=1.0).contains(&stripes(x, 0.4)));
        }
        assert!(checker(0.125, 0.125, 0.5) > 0.99 && checker(0.375, 0.125, 0.5) < 0.01);
    }
}
