//! The synthetic room: its layout, materials and shading.
//!
//! World frame: +Y up, floor at `y = 0`. A room box holds, at its centre, the foreground
//! object (a checkered sphere on a striped cylindrical pedestal; both count as foreground), and
//! near the walls three distractors of other shapes and colours (a box, a cylinder, a cone).
//! The object's reds and oranges appear nowhere else in the room: the weight-free teacher
//! (`cell-stats`) tells surfaces apart by colour and texture only, so an object painted like
//! its surroundings would need a learned teacher such as DINO.
//! Shading is Lambertian with one directional light, ambient light and hard shadows cast by
//! the objects (not by the room, which would otherwise block the light).

use sos_core::camera::{axpy, dot, normalize, Vec3};

use super::geometry::{cone, cylinder, room_exit, sphere, yawed_box, Hit};
use super::texture::{checker, fbm, mix, scale, stripes, Rgb};

/// Room box minimum corner.
pub const ROOM_MIN: Vec3 = [-3.5, 0.0, -3.5];
/// Room box maximum corner.
pub const ROOM_MAX: Vec3 = [3.5, 3.0, 3.5];
/// Centre of the foreground sphere (the point the object-centric cameras look at).
pub const OBJECT_CENTRE: Vec3 = [0.0, 0.85, 0.0];
/// Radius of the foreground sphere.
pub const OBJECT_RADIUS: f32 = 0.5;
/// Top of the pedestal (it reaches slightly into the sphere so they touch).
const PEDESTAL_TOP: f32 = 0.4;
const PEDESTAL_RADIUS: f32 = 0.22;

const AMBIENT: f32 = 0.4;
const DIFFUSE: f32 = 0.7;

/// Distractor placement: (x, z) of the box, cylinder and cone, all near the walls so they never
/// occlude the object from the object-centric cameras (which stay within 2.3 of the centre).
const BOX_AT: [f32; 2] = [1.86, -2.22];
const CYLINDER_AT: [f32; 2] = [-2.05, -2.05];
const CONE_AT: [f32; 2] = [-2.51, 1.45];

/// What a ray hit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Surface {
    Room(usize),
    Sphere,
    Pedestal,
    Box,
    Cylinder,
    Cone,
}

/// Distance at which a ray that meets no surface (the sky) reports its point: far beyond any
/// content, and read back as no surface at all by the views' ground-truth depth.
pub const SKY_DISTANCE: f32 = 1e4;

/// The shaded result of one primary ray.
#[derive(Debug, Clone, Copy)]
pub struct Sample {
    /// Shaded colour in `[0, 1]`.
    pub rgb: Rgb,
    /// Whether the ray hit the foreground object.
    pub foreground: bool,
    /// World-space hit point.
    pub point: Vec3,
}

/// Lambertian shading of a surface point of albedo `albedo` and unit normal `n` under the
/// directional light `light`: `ambient`, plus `diffuse` times the cosine where the point faces
/// the light and `lit()` finds nothing in its way; each channel at most 1.
pub fn shade(albedo: Rgb, n: Vec3, light: Vec3, ambient: f32, diffuse: f32, lit: impl FnOnce() -> bool) -> Rgb {
    let mut level = ambient;
    let lambert = dot(n, light);
    if lambert > 0.0 && lit() {
        level += diffuse * lambert;
    }
    scale(albedo, level).map(|v| v.min(1.0))
}

/// Something primary rays can be traced through (the room, the open world).
pub trait Trace {
    /// Traces a primary ray (unit direction `d`).
    fn trace(&self, o: Vec3, d: Vec3) -> Sample;

    /// Whether the ray's first hit is foreground, and where it is: [`Trace::trace`] without
    /// the shading, for masks and depth bounds.
    fn probe(&self, o: Vec3, d: Vec3) -> (bool, Vec3) {
        let s = self.trace(o, d);
        (s.foreground, s.point)
    }

    /// Colour of a pixel: the mean of the samples along its sub-pixel rays `subs`.
    fn pixel(&self, o: Vec3, subs: [Vec3; 4]) -> Rgb {
        let mut acc = [0.0f32; 3];
        for d in subs {
            let s = self.trace(o, d);
            (0..3).for_each(|k| acc[k] += 0.25 * s.rgb[k]);
        }
        acc
    }
}

impl Trace for World {
    fn trace(&self, o: Vec3, d: Vec3) -> Sample {
        World::trace(self, o, d)
    }
}

/// The procedural world; `seed` varies the noise patterns.
#[derive(Debug, Clone)]
pub struct World {
    seed: u32,
    light: Vec3,
}

impl World {
    /// The room with noise patterns drawn from `seed`.
    pub fn new(seed: u64) -> Self {
        World { seed: (seed ^ (seed >> 32)) as u32, light: normalize([0.45, 1.0, 0.3]) }
    }

    /// Nearest object hit (everything except the room), for primary and shadow rays.
    fn hit_objects(&self, o: Vec3, d: Vec3) -> Option<(Hit, Surface)> {
        let c = OBJECT_CENTRE;
        let candidates = [
            (sphere(o, d, c, OBJECT_RADIUS), Surface::Sphere),
            (cylinder(o, d, c[0], c[2], 0.0, PEDESTAL_TOP, PEDESTAL_RADIUS), Surface::Pedestal),
            (yawed_box(o, d, [BOX_AT[0], 0.35, BOX_AT[1]], [0.35, 0.35, 0.35], 0.5), Surface::Box),
            (cylinder(o, d, CYLINDER_AT[0], CYLINDER_AT[1], 0.0, 1.0, 0.3), Surface::Cylinder),
            (cone(o, d, CONE_AT[0], CONE_AT[1], 0.0, 1.2, 0.4), Surface::Cone),
        ];
        let mut best: Option<(Hit, Surface)> = None;
        for (hit, surface) in candidates {
            if let Some(h) = hit {
                if best.is_none_or(|(b, _)| h.0 < b.0) {
                    best = Some((h, surface));
                }
            }
        }
        best
    }

    /// Traces a primary ray from a point inside the room (unit direction `d`).
    pub fn trace(&self, o: Vec3, d: Vec3) -> Sample {
        let (t_room, n_room, face) = room_exit(o, d, ROOM_MIN, ROOM_MAX);
        let ((t, n), surface) = match self.hit_objects(o, d) {
            Some((h, s)) if h.0 < t_room => (h, s),
            _ => ((t_room, n_room), Surface::Room(face)),
        };
        let p = axpy(o, t, d);
        let lit = || self.hit_objects(axpy(p, 1e-3, n), self.light).is_none();
        Sample {
            rgb: shade(self.albedo(surface, p), n, self.light, AMBIENT, DIFFUSE, lit),
            foreground: matches!(surface, Surface::Sphere | Surface::Pedestal),
            point: p,
        }
    }

    /// Procedural albedo of `surface` at world point `p`.
    fn albedo(&self, surface: Surface, p: Vec3) -> Rgb {
        let seed = self.seed;
        let noise = |size: f32, salt: u32| fbm(p, size, seed.wrapping_add(salt));
        match surface {
            // Floor: warm wooden checkers.
            Surface::Room(2) => {
                let c = checker(p[0], p[2], 1.0);
                let base = mix([0.55, 0.42, 0.3], [0.82, 0.74, 0.6], c);
                scale(base, 0.8 + 0.35 * noise(0.35, 1))
            }
            // Ceiling: pale, gently mottled.
            Surface::Room(3) => scale([0.85, 0.85, 0.8], 0.85 + 0.2 * noise(0.6, 2)),
            // Left (−X) wall: terracotta checkers.
            Surface::Room(0) => {
                let c = checker(p[2], p[1], 0.8);
                scale(mix([0.45, 0.55, 0.5], [0.8, 0.82, 0.78], c), 0.85 + 0.25 * noise(0.4, 3))
            }
            // Right (+X) wall: horizontal yellow stripes.
            Surface::Room(1) => {
                let s = stripes(p[1], 0.6);
                scale(mix([0.9, 0.8, 0.35], [0.65, 0.65, 0.6], s), 0.85 + 0.25 * noise(0.4, 4))
            }
            // Back (−Z) wall: vertical blue stripes.
            Surface::Room(4) => {
                let s = stripes(p[0], 0.7);
                scale(mix([0.35, 0.5, 0.78], [0.88, 0.9, 0.92], s), 0.85 + 0.25 * noise(0.4, 5))
            }
            // Front (+Z) wall: green noise.
            Surface::Room(_) => mix([0.35, 0.6, 0.4], [0.75, 0.85, 0.55], noise(0.3, 6)),
            // Object: orange/white checkers in longitude/latitude, about 0.2 m squares.
            Surface::Sphere => {
                let q = normalize([p[0] - OBJECT_CENTRE[0], p[1] - OBJECT_CENTRE[1], p[2] - OBJECT_CENTRE[2]]);
                let lon = q[2].atan2(q[0]) / std::f32::consts::TAU; // [-0.5, 0.5]
                let lat = q[1].clamp(-1.0, 1.0).asin() / std::f32::consts::PI; // [-0.5, 0.5]
                let c = checker(lon * 8.0, lat * 4.0 + 0.5, 1.0);
                // Fade the checkers out near the poles, where they would converge into
                // detail no grid can hold.
                let polar = ((q[1].abs() - 0.75) / 0.2).clamp(0.0, 1.0);
                let c = c * (1.0 - polar) + 0.3 * polar;
                scale(mix([0.9, 0.12, 0.1], [0.95, 0.55, 0.1], c), 0.9 + 0.15 * noise(0.25, 7))
            }
            Surface::Pedestal => {
                let s = stripes(p[1], 0.2);
                mix([0.5, 0.07, 0.07], [0.85, 0.3, 0.22], s)
            }
            Surface::Box => scale([0.2, 0.35, 0.8], 0.7 + 0.5 * noise(0.3, 8)),
            Surface::Cylinder => {
                let a = (p[2] - CYLINDER_AT[1]).atan2(p[0] - CYLINDER_AT[0]);
                mix([0.2, 0.6, 0.25], [0.85, 0.9, 0.8], stripes(a, std::f32::consts::TAU / 8.0))
            }
            Surface::Cone => scale([0.6, 0.3, 0.7], 0.75 + 0.4 * noise(0.3, 9)),
        }
    }
}
