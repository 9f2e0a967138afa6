//! Dense voxel storage with `channels` values per vertex, trilinear interpolation over the unit
//! cube (vertices at `u = i / (res − 1)`), and resampling to a finer resolution.

use serde::{Deserialize, Serialize};

/// A grid of `res[0] x res[1] x res[2]` vertices, each holding `channels` values (x fastest).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Grid {
    /// Vertices per axis.
    pub res: [usize; 3],
    /// Values per vertex.
    pub channels: usize,
    /// `[z][y][x][channel]`.
    pub data: Vec<f32>,
}

/// The 8 vertices around a point and their trilinear weights.
#[derive(Debug, Clone, Copy)]
pub struct Corners {
    /// Vertex indices (not multiplied by `channels`).
    pub index: [u32; 8],
    /// Weights summing to one.
    pub weight: [f32; 8],
}

impl Grid {
    /// A grid filled with `value`.
    pub fn new(res: [usize; 3], channels: usize, value: f32) -> Self {
        Grid { res, channels, data: vec![value; res[0] * res[1] * res[2] * channels] }
    }

    /// Number of vertices.
    pub fn n_vertices(&self) -> usize {
        self.res[0] * self.res[1] * self.res[2]
    }

    /// Corners of unit-cube point `u`, or `None` outside the cube.
    #[inline]
    pub fn corners(&self, u: [f32; 3]) -> Option<Corners> {
        let mut base = [0usize; 3];
        let mut frac = [0.0f32; 3];
        for a in 0..3 {
            if !(0.0..=1.0).contains(&u[a]) {
                return None;
            }
            let g = u[a] * (self.res[a] - 1) as f32;
            let i = (g as usize).min(self.res[a] - 2);
            base[a] = i;
            frac[a] = g - i as f32;
        }
        let (sx, sy) = (1, self.res[0]);
        let sz = self.res[0] * self.res[1];
        let i0 = base[2] * sz + base[1] * sy + base[0];
        let mut index = [0u32; 8];
        let mut weight = [0.0f32; 8];
        for c in 0..8 {
            let (dx, dy, dz) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            index[c] = (i0 + dz * sz + dy * sy + dx * sx) as u32;
            let wx = if dx == 1 { frac[0] } else { 1.0 - frac[0] };
            let wy = if dy == 1 { frac[1] } else { 1.0 - frac[1] };
            let wz = if dz == 1 { frac[2] } else { 1.0 - frac[2] };
            weight[c] = wx * wy * wz;
        }
        Some(Corners { index, weight })
    }

    /// Interpolates all channels at the corners into `out`.
    #[inline]
    pub fn gather(&self, c: &Corners, out: &mut [f32]) {
        // The channel counts of SH degrees 0–2 get a loop the compiler unrolls into vector
        // operations (the same additions in the same order, so the same values).
        match self.channels {
            4 => return self.gather_fixed::<4>(c, out),
            13 => return self.gather_fixed::<13>(c, out),
            28 => return self.gather_fixed::<28>(c, out),
            _ => {}
        }
        let ch = self.channels;
        out[..ch].fill(0.0);
        for k in 0..8 {
            let w = c.weight[k];
            let v = &self.data[c.index[k] as usize * ch..][..ch];
            for j in 0..ch {
                out[j] += w * v[j];
            }
        }
    }

    #[inline]
    fn gather_fixed<const N: usize>(&self, c: &Corners, out: &mut [f32]) {
        let mut acc = [0.0f32; N];
        for k in 0..8 {
            let w = c.weight[k];
            let v: &[f32; N] = self.data[c.index[k] as usize * N..][..N].try_into().expect("N channels");
            for j in 0..N {
                acc[j] += w * v[j];
            }
        }
        out[..N].copy_from_slice(&acc);
    }

    /// Interpolates channel 0 only.
    #[inline]
    pub fn gather_first(&self, c: &Corners) -> f32 {
        let ch = self.channels;
        (0..8).map(|k| c.weight[k] * self.data[c.index[k] as usize * ch]).sum()
    }

    /// Resamples to a new resolution by trilinear interpolation (coarse-to-fine growth).
    pub fn resampled(&self, res: [usize; 3]) -> Grid {
        let mut out = Grid::new(res, self.channels, 0.0);
        let ch = self.channels;
        let mut tmp = vec![0.0; ch];
        for z in 0..res[2] {
            for y in 0..res[1] {
                for x in 0..res[0] {
                    let u = [
                        x as f32 / (res[0] - 1) as f32,
                        y as f32 / (res[1] - 1) as f32,
                        z as f32 / (res[2] - 1) as f32,
                    ];
                    let c = self.corners(u).expect("vertex lies in the unit cube");
                    self.gather(&c, &mut tmp);
                    let i = (z * res[1] + y) * res[0] + x;
                    out.data[i * ch..(i + 1) * ch].copy_from_slice(&tmp);
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trilinear_reproduces_linear_functions_and_resampling_keeps_them() {
        let res = [5, 4, 6];
        let mut g = Grid::new(res, 2, 0.0);
        let f = |u: [f32; 3]| [1.0 + 2.0 * u[0] - u[1] + 0.5 * u[2], u[0] * 0.3];
        for z in 0..res[2] {
            for y in 0..res[1] {
                for x in 0..res[0] {
                    let u = [x as f32 / 4.0, y as f32 / 3.0, z as f32 / 5.0];
                    let i = (z * res[1] + y) * res[0] + x;
                    g.data[i * 2..i * 2 + 2].copy_from_slice(&f(u));
                }
            }
        }
        let fine = g.resampled([9, 7, 11]);
        for u in [[0.1, 0.9, 0.33], [1.0, 1.0, 1.0], [0.0, 0.5, 0.77]] {
            let mut a = [0.0; 2];
            g.gather(&g.corners(u).unwrap(), &mut a);
            let mut b = [0.0; 2];
            fine.gather(&fine.corners(u).unwrap(), &mut b);
            let want = f(u);
            for k in 0..2 {
                assert!((a[k] - want[k]).abs() < 1e-5 && (b[k] - want[k]).abs() < 1e-5);
            }
        }
        assert!(g.corners([1.01, 0.5, 0.5]).is_none());
    }

    #[test]
    fn fixed_width_gathers_equal_the_general_loop_bit_for_bit() {
        // 4, 13 and 28 channels take the fixed-width path, 5 the general one.
        for channels in [4, 13, 28, 5] {
            let mut g = Grid::new([6, 5, 7], channels, 0.0);
            let mut x = 0x2545_f491_u32;
            for v in &mut g.data {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                *v = (x as f32 / u32::MAX as f32 - 0.5) * 7.0;
            }
            for u in [[0.13, 0.71, 0.42], [0.999, 0.0, 0.5], [0.5, 0.5, 1.0]] {
                let c = g.corners(u).unwrap();
                let mut fast = vec![f32::NAN; channels];
                g.gather(&c, &mut fast);
                // The general loop: corners in order, each added into a zeroed sum.
                let mut want = vec![0.0f32; channels];
                for k in 0..8 {
                    for (j, w) in want.iter_mut().enumerate() {
                        *w += c.weight[k] * g.data[c.index[k] as usize * channels + j];
                    }
                }
                assert_eq!(
                    fast.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    want.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    "{channels} channels at {u:?}"
                );
            }
        }
    }
}
