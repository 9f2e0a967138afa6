//! Occupancy grid for empty-space skipping (instant-ngp / nerfacc style): a coarse grid over
//! the unit cube holding a decaying maximum of the field's density, thresholded to a bitmask.

use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::camera::Vec3;
use crate::plugin::RadianceField;
use crate::render::contraction::Contraction;

/// A `res³` occupancy grid over the unit cube.
#[derive(Debug, Clone)]
pub struct OccupancyGrid {
    res: usize,
    density: Vec<f32>,
    occupied: Vec<bool>,
    threshold: f32,
}

impl OccupancyGrid {
    /// A grid with every cell occupied (nothing is skipped until the first update).
    pub fn new(res: usize, threshold: f32) -> Self {
        let n = res * res * res;
        OccupancyGrid { res, density: vec![f32::MAX; n], occupied: vec![true; n], threshold }
    }

    /// The grid as bytes (see [`crate::plugin::state`]), for a checkpoint a run resumes from
    /// with the same skipping as if it had not stopped.
    pub fn to_bytes(&self) -> Vec<u8> {
        let header = serde_json::json!({ "res": self.res, "threshold": self.threshold });
        let occupied: Vec<f32> = self.occupied.iter().map(|&o| f32::from(u8::from(o))).collect();
        crate::plugin::state::write(&header, &[&self.density, &occupied])
    }

    /// Restores [`OccupancyGrid::to_bytes`] into a grid of the same resolution.
    pub fn load_bytes(&mut self, bytes: &[u8]) -> Result<(), crate::error::StateError> {
        use crate::error::StateError;
        const KIND: &str = "occupancy grid";
        let (header, body) = crate::plugin::state::read(KIND, bytes)?;
        if header["res"].as_u64() != Some(self.res as u64) {
            return Err(StateError::Mismatch {
                kind: KIND.into(),
                reason: format!("saved at {} cells a side, the config asks for {}", header["res"], self.res),
            });
        }
        let n = self.density.len();
        let values = crate::plugin::state::values(KIND, body, 2 * n)?;
        self.density.copy_from_slice(&values[..n]);
        self.occupied.iter_mut().zip(&values[n..]).for_each(|(o, &v)| *o = v != 0.0);
        Ok(())
    }

    /// Cells per side.
    pub fn resolution(&self) -> usize {
        self.res
    }

    /// Fraction of occupied cells.
    pub fn occupancy(&self) -> f32 {
        self.occupied.iter().filter(|&&o| o).count() as f32 / self.occupied.len() as f32
    }

    /// Whether the cell containing unit-cube point `u` may hold matter.
    #[inline]
    pub fn is_occupied(&self, u: Vec3) -> bool {
        let r = self.res as f32;
        let i = ((u[0] * r) as usize).min(self.res - 1);
        let j = ((u[1] * r) as usize).min(self.res - 1);
        let k = ((u[2] * r) as usize).min(self.res - 1);
        self.occupied[(k * self.res + j) * self.res + i]
    }

    /// Re-probes the field: each cell's value becomes `max(decay · old, σ(probe))` with one
    /// jittered probe per cell, then cells above the threshold are marked occupied. With
    /// `decay = 0` the grid is rebuilt from scratch.
    pub fn update(&mut self, field: &dyn RadianceField, contraction: &Contraction, decay: f32, rng: &mut impl Rng) {
        let res = self.res;
        let seed: u64 = rng.gen();
        // Probe positions per z-slab, in parallel; each slab has its own jitter stream.
        let slab = res * res;
        let fresh: Vec<f32> = (0..res)
            .into_par_iter()
            .flat_map_iter(|k| {
                let mut local =
                    rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ (k as u64).wrapping_mul(0x9E3779B97F4A7C15));
                let mut positions = Vec::with_capacity(slab);
                for j in 0..res {
                    for i in 0..res {
                        let u = [
                            (i as f32 + local.gen::<f32>()) / res as f32,
                            (j as f32 + local.gen::<f32>()) / res as f32,
                            (k as f32 + local.gen::<f32>()) / res as f32,
                        ];
                        positions.push(contraction.from_unit(u));
                    }
                }
                let mut sigma = vec![0.0; slab];
                field.density(&positions, &mut sigma);
                sigma.into_iter()
            })
            .collect();
        for (i, s) in fresh.into_iter().enumerate() {
            let old = if self.density[i] == f32::MAX { 0.0 } else { self.density[i] };
            self.density[i] = (decay * old).max(s);
            self.occupied[i] = self.density[i] > self.threshold;
        }
    }

    /// Marks every cell next to (sharing a face, edge or corner with) an occupied cell as
    /// occupied too. A baked grid probes each cell once, so a thin surface between two probes
    /// could be missed; one cell of margin makes skipping conservative.
    pub fn dilate(&mut self) {
        let res = self.res;
        let old = self.occupied.clone();
        let at = |i: isize, j: isize, k: isize| -> bool {
            let r = res as isize;
            (0..r).contains(&i) && (0..r).contains(&j) && (0..r).contains(&k) && old[((k * r + j) * r + i) as usize]
        };
        self.occupied.par_chunks_mut(res * res).enumerate().for_each(|(k, slab)| {
            for j in 0..res {
                for i in 0..res {
                    let (i, j, k) = (i as isize, j as isize, k as isize);
                    let mut any = false;
                    'n: for dk in -1..=1 {
                        for dj in -1..=1 {
                            for di in -1..=1 {
                                if at(i + di, j + dj, k + dk) {
                                    any = true;
                                    break 'n;
                                }
                            }
                        }
                    }
                    slab[(j * res as isize + i) as usize] = any;
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_round_trip_and_refuse_another_resolution() {
        let mut g = OccupancyGrid::new(4, 1.0);
        g.density.iter_mut().enumerate().for_each(|(i, d)| *d = i as f32 * 0.5);
        g.occupied.iter_mut().enumerate().for_each(|(i, o)| *o = i % 3 == 0);
        let mut back = OccupancyGrid::new(4, 1.0);
        back.load_bytes(&g.to_bytes()).unwrap();
        assert_eq!((back.density, back.occupied), (g.density.clone(), g.occupied.clone()));
        assert!(OccupancyGrid::new(5, 1.0).load_bytes(&g.to_bytes()).is_err());
    }

    #[test]
    fn dilation_grows_by_one_cell() {
        let mut g = OccupancyGrid::new(8, 1.0);
        g.occupied.iter_mut().for_each(|o| *o = false);
        g.occupied[(3 * 8 + 3) * 8 + 3] = true;
        g.dilate();
        assert_eq!(g.occupied.iter().filter(|&&o| o).count(), 27);
        assert!(g.is_occupied([2.5 / 8.0, 4.5 / 8.0, 3.5 / 8.0]));
        assert!(!g.is_occupied([1.5 / 8.0, 3.5 / 8.0, 3.5 / 8.0]));
        // Cells at the border do not wrap around.
        let mut g = OccupancyGrid::new(4, 1.0);
        g.occupied.iter_mut().for_each(|o| *o = false);
        g.occupied[0] = true;
        g.dilate();
        assert_eq!(g.occupied.iter().filter(|&&o| o).count(), 8);
    }
}
