//! The upright primitives random worlds are built from, as one type: ray hits (from
//! [`super::geometry`]), how they rest on each other, bounds, points outlining their silhouette
//! (for framing), and for tests a signed distance.

#[cfg(test)]
use sos_core::camera::normalize;
use sos_core::camera::Vec3;

use super::geometry::{cone, cylinder, sphere, torus, yawed_box, Hit};

/// An upright primitive in world coordinates (+Y up).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Sphere.
    Sphere {
        /// Centre.
        centre: Vec3,
        /// Radius.
        radius: f32,
    },
    /// Box with half sizes `half` about `centre`, turned by `yaw` radians about +Y.
    Box {
        /// Centre.
        centre: Vec3,
        /// Half sizes along the box's own axes.
        half: Vec3,
        /// Turn about +Y.
        yaw: f32,
    },
    /// Closed cylinder standing on `base` (the centre of its bottom disk).
    Cylinder {
        /// Centre of the bottom disk.
        base: Vec3,
        /// Height.
        height: f32,
        /// Radius.
        radius: f32,
    },
    /// Cone standing on `base` (the centre of its bottom disk), apex `height` above it.
    Cone {
        /// Centre of the bottom disk.
        base: Vec3,
        /// Height of the apex above the base.
        height: f32,
        /// Base radius.
        radius: f32,
    },
    /// Torus lying flat (axis +Y): a tube of radius `minor` around a circle of radius `major`.
    Torus {
        /// Centre of the ring.
        centre: Vec3,
        /// Radius of the tube's centre circle.
        major: f32,
        /// Radius of the tube.
        minor: f32,
    },
}

/// Points on a horizontal circle.
fn circle(centre: Vec3, radius: f32, count: usize) -> impl Iterator<Item = Vec3> {
    (0..count).map(move |i| {
        let a = std::f32::consts::TAU * i as f32 / count as f32;
        [centre[0] + radius * a.cos(), centre[1], centre[2] + radius * a.sin()]
    })
}

#[cfg(test)]
/// Signed distance to the solid of revolution whose half profile (radial distance `q`, height
/// `y`) is the polygon through `profile` closed along the axis; `inside` decides the sign.
fn profile_distance(q: f32, y: f32, profile: &[[f32; 2]], inside: bool) -> f32 {
    let mut best = f32::INFINITY;
    for w in profile.windows(2) {
        let (a, b) = (w[0], w[1]);
        let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
        let s = (((q - a[0]) * ex + (y - a[1]) * ey) / (ex * ex + ey * ey)).clamp(0.0, 1.0);
        let (dx, dy) = (q - a[0] - s * ex, y - a[1] - s * ey);
        best = best.min((dx * dx + dy * dy).sqrt());
    }
    if inside {
        -best
    } else {
        best
    }
}

impl Shape {
    /// Nearest hit of the ray `o + t d` (unit `d`).
    pub fn hit(&self, o: Vec3, d: Vec3) -> Option<Hit> {
        match *self {
            Shape::Sphere { centre, radius } => sphere(o, d, centre, radius),
            Shape::Box { centre, half, yaw } => yawed_box(o, d, centre, half, yaw),
            Shape::Cylinder { base, height, radius } => {
                cylinder(o, d, base[0], base[2], base[1], base[1] + height, radius)
            }
            Shape::Cone { base, height, radius } => cone(o, d, base[0], base[2], base[1], height, radius),
            Shape::Torus { centre, major, minor } => torus(o, d, centre, major, minor),
        }
    }

    /// Horizontal position of the vertical axis.
    pub fn axis(&self) -> [f32; 2] {
        match *self {
            Shape::Sphere { centre, .. } | Shape::Box { centre, .. } | Shape::Torus { centre, .. } => {
                [centre[0], centre[2]]
            }
            Shape::Cylinder { base, .. } | Shape::Cone { base, .. } => [base[0], base[2]],
        }
    }

    /// Lowest height.
    pub fn bottom(&self) -> f32 {
        match *self {
            Shape::Sphere { centre, radius } => centre[1] - radius,
            Shape::Box { centre, half, .. } => centre[1] - half[1],
            Shape::Cylinder { base, .. } | Shape::Cone { base, .. } => base[1],
            Shape::Torus { centre, minor, .. } => centre[1] - minor,
        }
    }

    /// Highest height.
    pub fn top(&self) -> f32 {
        match *self {
            Shape::Sphere { centre, radius } => centre[1] + radius,
            Shape::Box { centre, half, .. } => centre[1] + half[1],
            Shape::Cylinder { base, height, .. } | Shape::Cone { base, height, .. } => base[1] + height,
            Shape::Torus { centre, minor, .. } => centre[1] + minor,
        }
    }

    /// Radius of the smallest vertical cylinder about [`Shape::axis`] holding the shape.
    pub fn footprint(&self) -> f32 {
        match *self {
            Shape::Sphere { radius, .. } | Shape::Cylinder { radius, .. } | Shape::Cone { radius, .. } => radius,
            Shape::Box { half, .. } => (half[0] * half[0] + half[2] * half[2]).sqrt(),
            Shape::Torus { major, minor, .. } => major + minor,
        }
    }

    /// Radius of the flat top something can stand on (0 when the top is not flat).
    pub fn support_radius(&self) -> f32 {
        match *self {
            Shape::Box { half, .. } => half[0].min(half[2]),
            Shape::Cylinder { radius, .. } => radius,
            Shape::Sphere { .. } | Shape::Cone { .. } | Shape::Torus { .. } => 0.0,
        }
    }

    /// A point inside the shape, the origin of its solid textures.
    pub fn centre(&self) -> Vec3 {
        let [x, z] = self.axis();
        [x, 0.5 * (self.bottom() + self.top()), z]
    }

    /// Axis-aligned bounding box `[min, max]`.
    pub fn aabb(&self) -> [Vec3; 2] {
        let [x, z] = self.axis();
        let (ex, ez) = match *self {
            Shape::Box { half, yaw, .. } => {
                let (s, c) = yaw.sin_cos();
                (c.abs() * half[0] + s.abs() * half[2], s.abs() * half[0] + c.abs() * half[2])
            }
            _ => (self.footprint(), self.footprint()),
        };
        [[x - ex, self.bottom(), z - ez], [x + ex, self.top(), z + ez]]
    }

    /// Bounding sphere (centre, radius), to skip rays that cannot hit.
    pub fn bounding_sphere(&self) -> (Vec3, f32) {
        let c = self.centre();
        let half_height = 0.5 * (self.top() - self.bottom());
        let r = match *self {
            Shape::Sphere { radius, .. } => radius,
            _ => (self.footprint().powi(2) + half_height * half_height).sqrt(),
        };
        (c, r * 1.0001 + 1e-5)
    }

    /// Points on the surface whose projections outline the silhouette from any viewpoint to
    /// within a few percent (the extreme points of a convex outline lie on these curves or
    /// close to them).
    pub fn silhouette(&self) -> Vec<Vec3> {
        const RING: usize = 32;
        match *self {
            Shape::Sphere { centre, radius } => {
                // A Fibonacci sphere: every direction has a point within ~0.2 rad.
                let n = 96;
                (0..n)
                    .map(|i| {
                        let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
                        let r = (1.0 - y * y).sqrt();
                        let a = i as f32 * 2.399_963;
                        [centre[0] + radius * r * a.cos(), centre[1] + radius * y, centre[2] + radius * r * a.sin()]
                    })
                    .collect()
            }
            Shape::Box { centre, half, yaw } => {
                let (s, c) = yaw.sin_cos();
                (0..8)
                    .map(|k| {
                        let l = [0, 1, 2].map(|a| if k >> a & 1 == 1 { half[a] } else { -half[a] });
                        [centre[0] + c * l[0] + s * l[2], centre[1] + l[1], centre[2] - s * l[0] + c * l[2]]
                    })
                    .collect()
            }
            Shape::Cylinder { base, height, radius } => {
                circle(base, radius, RING).chain(circle([base[0], base[1] + height, base[2]], radius, RING)).collect()
            }
            Shape::Cone { base, height, radius } => {
                circle(base, radius, RING).chain(std::iter::once([base[0], base[1] + height, base[2]])).collect()
            }
            Shape::Torus { centre, major, minor } => (0..8)
                .flat_map(|j| {
                    let a = std::f32::consts::TAU * j as f32 / 8.0;
                    let y = [centre[0], centre[1] + minor * a.sin(), centre[2]];
                    circle(y, major + minor * a.cos(), RING)
                })
                .collect(),
        }
    }

    /// Signed distance from `p` to the surface (negative inside); exact up to rounding.
    #[cfg(test)]
    pub fn distance(&self, p: Vec3) -> f32 {
        let [x, z] = self.axis();
        let q = ((p[0] - x).powi(2) + (p[2] - z).powi(2)).sqrt();
        match *self {
            Shape::Sphere { centre, radius } => {
                ((p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2) + (p[2] - centre[2]).powi(2)).sqrt() - radius
            }
            Shape::Box { centre, half, yaw } => {
                let (s, c) = yaw.sin_cos();
                let v = [p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]];
                let l = [c * v[0] - s * v[2], v[1], s * v[0] + c * v[2]];
                let e = [0, 1, 2].map(|a| l[a].abs() - half[a]);
                let outside = e.map(|v| v.max(0.0));
                (outside[0].powi(2) + outside[1].powi(2) + outside[2].powi(2)).sqrt()
                    + e[0].max(e[1]).max(e[2]).min(0.0)
            }
            Shape::Cylinder { base, height, radius } => {
                let y = p[1] - base[1];
                let inside = q <= radius && (0.0..=height).contains(&y);
                profile_distance(q, y, &[[0.0, 0.0], [radius, 0.0], [radius, height], [0.0, height]], inside)
            }
            Shape::Cone { base, height, radius } => {
                let y = p[1] - base[1];
                let inside = y >= 0.0 && q <= radius * (1.0 - y / height);
                profile_distance(q, y, &[[0.0, 0.0], [radius, 0.0], [0.0, height]], inside)
            }
            Shape::Torus { centre, major, minor } => ((q - major).powi(2) + (p[1] - centre[1]).powi(2)).sqrt() - minor,
        }
    }

    /// Outward unit normal of the distance field at `p` (central differences), for tests.
    #[cfg(test)]
    pub fn gradient(&self, p: Vec3) -> Vec3 {
        let e = 1e-3;
        normalize([0, 1, 2].map(|k| {
            let (mut a, mut b) = (p, p);
            a[k] += e;
            b[k] -= e;
            self.distance(a) - self.distance(b)
        }))
    }

    /// The shape moved by `offset`.
    pub fn moved(&self, offset: Vec3) -> Shape {
        let add = |v: Vec3| [v[0] + offset[0], v[1] + offset[1], v[2] + offset[2]];
        match *self {
            Shape::Sphere { centre, radius } => Shape::Sphere { centre: add(centre), radius },
            Shape::Box { centre, half, yaw } => Shape::Box { centre: add(centre), half, yaw },
            Shape::Cylinder { base, height, radius } => Shape::Cylinder { base: add(base), height, radius },
            Shape::Cone { base, height, radius } => Shape::Cone { base: add(base), height, radius },
            Shape::Torus { centre, major, minor } => Shape::Torus { centre: add(centre), major, minor },
        }
    }

    /// Lower-case name, for descriptions.
    pub fn name(&self) -> &'static str {
        match self {
            Shape::Sphere { .. } => "sphere",
            Shape::Box { .. } => "box",
            Shape::Cylinder { .. } => "cylinder",
            Shape::Cone { .. } => "cone",
            Shape::Torus { .. } => "torus",
        }
    }
}

/// Whether the unit-direction ray `o + t d` can meet the sphere `(c, r)` at some `t > 0`.
pub fn may_hit(o: Vec3, d: Vec3, (c, r): (Vec3, f32)) -> bool {
    let oc = [c[0] - o[0], c[1] - o[1], c[2] - o[2]];
    let along = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2];
    let dist2 = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2];
    if dist2 <= r * r {
        return true;
    }
    along > 0.0 && dist2 - along * along <= r * r
}

#[cfg(test)]
mod tests {
    use super::*;
    use sos_core::camera::dot;

    fn shapes() -> Vec<Shape> {
        vec![
            Shape::Sphere { centre: [0.1, 0.6, -0.2], radius: 0.45 },
            Shape::Box { centre: [0.0, 0.4, 0.1], half: [0.3, 0.4, 0.5], yaw: 0.7 },
            Shape::Cylinder { base: [0.2, 0.1, 0.0], height: 0.9, radius: 0.35 },
            Shape::Cone { base: [0.0, 0.0, 0.1], height: 1.1, radius: 0.5 },
            Shape::Torus { centre: [-0.1, 0.3, 0.0], major: 0.45, minor: 0.15 },
        ]
    }

    #[test]
    fn every_primitive_hits_its_surface_first_with_its_normal() {
        let mut state = 7u32;
        let mut rnd = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32
        };
        for s in shapes() {
            let (c, r) = s.bounding_sphere();
            let [lo, hi] = s.aabb();
            let mut hits = 0;
            for _ in 0..1500 {
                let a = std::f32::consts::TAU * rnd();
                let y = 2.0 * rnd() - 1.0;
                let far = [c[0] + 3.0 * a.cos(), c[1] + 3.0 * y, c[2] + 3.0 * a.sin()];
                let aim = [0, 1, 2].map(|k| lo[k] + (hi[k] - lo[k]) * (1.4 * rnd() - 0.2));
                let d = normalize([aim[0] - far[0], aim[1] - far[1], aim[2] - far[2]]);
                let at = |t: f32| [far[0] + t * d[0], far[1] + t * d[1], far[2] + t * d[2]];
                let analytic = s.hit(far, d);
                if analytic.is_some() {
                    assert!(may_hit(far, d, (c, r)), "{} escapes its bounding sphere", s.name());
                }
                // No point of the ray before the hit (sampled every millimetre) is inside.
                let clear_until = analytic.map_or(12.0, |(t, _)| t - 1e-3);
                let mut t = 0.0;
                while t < clear_until {
                    assert!(s.distance(at(t)) > -1e-4, "{}: inside at {t} before the hit {analytic:?}", s.name());
                    t += 1e-3;
                }
                if let Some((t, n)) = analytic {
                    hits += 1;
                    let p = at(t);
                    assert!(s.distance(p).abs() < 1e-3, "{}: off the surface", s.name());
                    for k in 0..3 {
                        assert!(p[k] >= lo[k] - 1e-3 && p[k] <= hi[k] + 1e-3, "{}: outside its box", s.name());
                    }
                    // Edges have no single normal; judge faces only.
                    let g = s.gradient(p);
                    let on_edge = [0, 1, 2].iter().any(|&k| {
                        let mut q = p;
                        q[k] += 4e-3;
                        dot(s.gradient(q), g) < 0.999
                    });
                    if !on_edge {
                        assert!(dot(g, n) > 0.99, "{}: normal {n:?} vs {g:?}", s.name());
                    }
                }
            }
            assert!(hits > 300, "{}: {hits} hits", s.name());
        }
    }

    #[test]
    fn bounds_and_silhouettes_hold_the_shape() {
        for s in shapes() {
            let [lo, hi] = s.aabb();
            let (c, r) = s.bounding_sphere();
            for p in s.silhouette() {
                assert!(s.distance(p).abs() < 1e-4, "{}: silhouette point off the surface", s.name());
                let d = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt();
                assert!(d <= r, "{}", s.name());
                assert!((0..3).all(|k| p[k] >= lo[k] - 1e-5 && p[k] <= hi[k] + 1e-5), "{}", s.name());
            }
            assert!(s.bottom() < s.top() && s.footprint() > 0.0);
            let moved = s.moved([1.0, 2.0, 3.0]);
            assert!((moved.bottom() - s.bottom() - 2.0).abs() < 1e-6);
            assert_eq!(moved.name(), s.name());
        }
    }
}
