//! Distractors: other primitives standing on the ground, never in the foreground mask and
//! never between any camera and the object.
//!
//! A distractor is accepted only when a vertical plane separates it from every camera centre
//! (novel-view path included) and from the object's bounding boxes. Every segment from a camera
//! to a point of the object lies in the convex hull of those, on the plane's other side, so no
//! view can see the object through the distractor.

use sos_core::camera::Vec3;

use super::super::rig::SplitMix;
use super::super::shape::Shape;
use super::composition::standing;
use super::draw::Draw;

/// Clearance between a distractor and the separating plane, other distractors and walls.
const CLEARANCE: f32 = 0.05;
/// Horizontal directions tried as separating-plane normals.
const DIRECTIONS: usize = 64;

/// Where distractors may stand.
#[derive(Debug, Clone, Copy)]
pub enum Region {
    /// Inside a room's floor `[min, max]` (x and z).
    Floor {
        /// Minimum corner.
        min: Vec3,
        /// Maximum corner.
        max: Vec3,
    },
    /// Within `radius` of the vertical axis through the origin.
    Disk {
        /// Radius.
        radius: f32,
    },
}

/// Whether a vertical plane keeps `shape` at least [`CLEARANCE`] away from all of `hull`.
pub fn separated(shape: &Shape, hull: &[Vec3]) -> bool {
    let [x, z] = shape.axis();
    let r = shape.footprint();
    (0..DIRECTIONS).any(|k| {
        let (s, c) = (std::f32::consts::TAU * k as f32 / DIRECTIONS as f32).sin_cos();
        let near_side = c * x + s * z - r;
        hull.iter().all(|p| c * p[0] + s * p[2] + CLEARANCE < near_side)
    })
}

/// Up to `count` distractors in `region`, clear of the hull of `hull` (camera centres and
/// object box corners) and of each other. Fewer when no place is found in a few dozen tries.
pub fn place(count: usize, region: Region, hull: &[Vec3], rng: &mut SplitMix) -> Vec<Shape> {
    let mut placed: Vec<Shape> = Vec::new();
    for _ in 0..count {
        for _ in 0..60 {
            let w = rng.range(0.08, 0.45);
            let at = match region {
                Region::Floor { min, max } => {
                    let m = w + CLEARANCE;
                    if max[0] - min[0] <= 2.0 * m || max[2] - min[2] <= 2.0 * m {
                        continue;
                    }
                    [rng.range(min[0] + m, max[0] - m), rng.range(min[2] + m, max[2] - m)]
                }
                Region::Disk { radius } => {
                    let (a, r) = (rng.angle(), radius * rng.uniform().sqrt());
                    [r * a.sin(), r * a.cos()]
                }
            };
            let shape = standing(w, at, rng);
            let inside = match region {
                // A torus or box may reach further than `w` from its axis.
                Region::Floor { min, max } => {
                    let f = shape.footprint() + CLEARANCE;
                    at[0] - f > min[0] && at[0] + f < max[0] && at[1] - f > min[2] && at[1] + f < max[2]
                }
                Region::Disk { .. } => true,
            };
            let apart = placed.iter().all(|o| {
                let [ox, oz] = o.axis();
                ((ox - at[0]).powi(2) + (oz - at[1]).powi(2)).sqrt() > o.footprint() + shape.footprint() + CLEARANCE
            });
            if inside && apart && separated(&shape, hull) {
                placed.push(shape);
                break;
            }
        }
    }
    placed
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::random::draw::{stream, Aspect};

    #[test]
    fn distractors_stay_outside_the_hull_and_apart() {
        // Cameras on a circle of radius 2 around an object at the origin.
        let mut hull: Vec<Vec3> = (0..12)
            .map(|i| {
                let a = i as f32 * 0.52;
                [2.0 * a.cos(), 1.0, 2.0 * a.sin()]
            })
            .collect();
        hull.extend([[-0.3, 0.0, -0.3], [0.3, 1.0, 0.3]]);
        let region = Region::Floor { min: [-4.0, 0.0, -4.0], max: [4.0, 3.0, 4.0] };
        let mut total = 0;
        for seed in 0..20 {
            let shapes = place(5, region, &hull, &mut stream(seed, Aspect::Distractors));
            total += shapes.len();
            for (i, s) in shapes.iter().enumerate() {
                let [x, z] = s.axis();
                // Outside the cameras' circle entirely.
                assert!((x * x + z * z).sqrt() - s.footprint() > 2.0, "{s:?}");
                assert!(x.abs() + s.footprint() < 4.0 && z.abs() + s.footprint() < 4.0);
                assert!(s.bottom().abs() < 1e-5, "{s:?} does not stand on the ground");
                for t in &shapes[..i] {
                    let [tx, tz] = t.axis();
                    assert!(((tx - x).powi(2) + (tz - z).powi(2)).sqrt() > s.footprint() + t.footprint());
                }
            }
        }
        assert!(total > 40, "only {total} distractors placed in 20 rooms");
        // No room at all: nothing is placed.
        let tight = Region::Floor { min: [-1.5, 0.0, -1.5], max: [1.5, 3.0, 1.5] };
        assert!(place(5, tight, &hull, &mut stream(0, Aspect::Distractors)).is_empty());
    }
}
