//! Maps world points into the unit cube `[0, 1]³` that grids (fields, occupancy) discretise.
//! One mapping per [`SceneExtent`], so every field and the occupancy grid agree.

use crate::camera::Vec3;
use crate::scene::SceneExtent;

/// Lateral slack of the forward-facing mapping: cameras are offset from the mean pose, so
/// content slightly outside the virtual camera's frustum is still inside the grid.
const FORWARD_FACING_MARGIN: f32 = 1.15;

/// World → unit-cube mapping.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Contraction {
    /// Affine map of an axis-aligned box.
    Box {
        /// Box minimum.
        min: Vec3,
        /// `1 / (max − min)` per axis.
        inv_size: Vec3,
    },
    /// Forward-facing: x and y are the virtual camera's normalised image coordinates, z is the
    /// disparity normalised so that depth `near` maps to 0 and `far` to 1 (NDC with a finite
    /// far plane, so no grid cells are wasted beyond the content).
    Disparity {
        /// `focal / (width / 2) / margin`.
        sx: f32,
        /// `focal / (height / 2) / margin`.
        sy: f32,
        /// `1 / near`.
        inv_near: f32,
        /// `1 / far`.
        inv_far: f32,
    },
    /// Unbounded: mip-NeRF 360's contraction of `(p − center) / radius`: points within the
    /// unit ball map linearly, the rest to the shell `2 − 1/|x|`, then into `[0, 1]³`.
    Sphere {
        /// Foreground centre.
        center: Vec3,
        /// Foreground radius.
        radius: f32,
    },
}

impl Contraction {
    /// The mapping for a scene extent.
    pub fn new(extent: &SceneExtent) -> Self {
        match *extent {
            SceneExtent::Bounded { min, max } => Contraction::Box {
                min,
                inv_size: [1.0 / (max[0] - min[0]), 1.0 / (max[1] - min[1]), 1.0 / (max[2] - min[2])],
            },
            SceneExtent::ForwardFacing { near, far, focal, width, height } => Contraction::Disparity {
                sx: focal / (width / 2.0) / FORWARD_FACING_MARGIN,
                sy: focal / (height / 2.0) / FORWARD_FACING_MARGIN,
                inv_near: 1.0 / near,
                inv_far: 1.0 / far,
            },
            SceneExtent::Unbounded { center, radius } => Contraction::Sphere { center, radius },
        }
    }

    /// Unit-cube coordinates of a world point (may fall outside `[0, 1]` for points outside the
    /// modelled region; callers treat those as empty).
    #[inline]
    pub fn to_unit(&self, p: Vec3) -> Vec3 {
        match *self {
            Contraction::Box { min, inv_size } => {
                [(p[0] - min[0]) * inv_size[0], (p[1] - min[1]) * inv_size[1], (p[2] - min[2]) * inv_size[2]]
            }
            Contraction::Disparity { sx, sy, inv_near, inv_far } => {
                let depth = -p[2];
                if depth <= 1e-6 {
                    return [-1.0, -1.0, -1.0];
                }
                let inv = 1.0 / depth;
                [0.5 + 0.5 * sx * p[0] * inv, 0.5 + 0.5 * sy * p[1] * inv, (inv_near - inv) / (inv_near - inv_far)]
            }
            Contraction::Sphere { center, radius } => {
                let x = [(p[0] - center[0]) / radius, (p[1] - center[1]) / radius, (p[2] - center[2]) / radius];
                let r = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
                let s = if r <= 1.0 { 1.0 } else { (2.0 - 1.0 / r) / r };
                [0.5 + 0.25 * s * x[0], 0.5 + 0.25 * s * x[1], 0.5 + 0.25 * s * x[2]]
            }
        }
    }

    /// Whether unit-cube coordinates lie inside the cube.
    #[inline]
    pub fn inside(u: Vec3) -> bool {
        (0.0..=1.0).contains(&u[0]) && (0.0..=1.0).contains(&u[1]) && (0.0..=1.0).contains(&u[2])
    }

    /// World point at unit-cube coordinates (inverse of [`Contraction::to_unit`]) where it
    /// exists; used to place occupancy probes.
    pub fn from_unit(&self, u: Vec3) -> Vec3 {
        match *self {
            Contraction::Box { min, inv_size } => {
                [min[0] + u[0] / inv_size[0], min[1] + u[1] / inv_size[1], min[2] + u[2] / inv_size[2]]
            }
            Contraction::Disparity { sx, sy, inv_near, inv_far } => {
                let inv = inv_near - u[2] * (inv_near - inv_far);
                let depth = 1.0 / inv;
                [(u[0] - 0.5) * 2.0 * depth / sx, (u[1] - 0.5) * 2.0 * depth / sy, -depth]
            }
            Contraction::Sphere { center, radius } => {
                let y = [(u[0] - 0.5) * 4.0, (u[1] - 0.5) * 4.0, (u[2] - 0.5) * 4.0];
                let s = (y[0] * y[0] + y[1] * y[1] + y[2] * y[2]).sqrt();
                // s ≤ 1: linear; otherwise s = 2 − 1/r.
                let r = if s <= 1.0 { s } else { 1.0 / (2.0 - s).max(1e-6) };
                let k = if s > 0.0 { r / s } else { 1.0 };
                [center[0] + radius * k * y[0], center[1] + radius * k * y[1], center[2] + radius * k * y[2]]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_for_every_extent() {
        let extents = [
            SceneExtent::Bounded { min: [-1.0, -2.0, 0.0], max: [1.0, 2.0, 3.0] },
            SceneExtent::ForwardFacing { near: 1.2, far: 8.0, focal: 400.0, width: 504.0, height: 378.0 },
            SceneExtent::Unbounded { center: [0.1, 0.0, -0.2], radius: 2.0 },
        ];
        for e in extents {
            let c = Contraction::new(&e);
            for p in [[0.2, -0.3, -2.0], [0.5, 0.1, -5.5], [-0.4, 0.3, -1.5]] {
                let u = c.to_unit(p);
                let q = c.from_unit(u);
                for k in 0..3 {
                    assert!((p[k] - q[k]).abs() < 1e-4 * (1.0 + p[k].abs()), "{e:?}: {p:?} -> {u:?} -> {q:?}");
                }
            }
        }
    }

    #[test]
    fn forward_facing_depth_range_fills_the_unit_interval() {
        let c = Contraction::new(&SceneExtent::ForwardFacing {
            near: 1.2,
            far: 8.0,
            focal: 400.0,
            width: 504.0,
            height: 378.0,
        });
        assert!(c.to_unit([0.0, 0.0, -1.2])[2].abs() < 1e-6);
        assert!((c.to_unit([0.0, 0.0, -8.0])[2] - 1.0).abs() < 1e-6);
    }
}
