//! A random world ready to trace: its primitives (foreground parts, distractors, towers), the
//! surroundings and the light. Shading is Lambertian with one directional light, ambient light
//! and hard shadows cast by the primitives (not by walls or ceiling, which would block the
//! light), as in the built-in world.

use sos_core::camera::{axpy, Vec3};

use super::super::geometry::{room_exit, Hit, T_MIN};
use super::super::material::Material;
use super::super::shape::{may_hit, Shape};
use super::super::texture::Rgb;
use super::super::world::{shade, Sample, Trace, SKY_DISTANCE};
use super::environment::Environment;

/// One primitive of the world.
#[derive(Debug, Clone)]
pub struct Part {
    /// Geometry.
    pub shape: Shape,
    /// Surface.
    pub material: Material,
    /// Whether it belongs to the foreground object (mask 1).
    pub foreground: bool,
    /// Bounding sphere, to skip rays that cannot hit.
    bound: (Vec3, f32),
}

impl Part {
    /// A part with its bounding sphere.
    pub fn new(shape: Shape, material: Material, foreground: bool) -> Part {
        Part { shape, material, foreground, bound: shape.bounding_sphere() }
    }
}

/// What a ray met first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    /// `parts[i]`.
    Part(usize),
    /// Room face (index as [`room_exit`]).
    Face(usize),
    /// The open ground.
    Ground,
    /// Nothing: the sky at infinity.
    Sky,
}

/// A random world.
#[derive(Debug, Clone)]
pub struct RandomWorld {
    /// Every primitive; foreground parts first.
    pub parts: Vec<Part>,
    /// Room or open world.
    pub environment: Environment,
    /// Unit direction towards the light.
    pub light: Vec3,
    /// Ambient light level.
    pub ambient: f32,
    /// Directional light level.
    pub diffuse: f32,
}

impl RandomWorld {
    /// Nearest primitive hit.
    fn nearest_part(&self, o: Vec3, d: Vec3) -> Option<(Hit, usize)> {
        let mut best: Option<(Hit, usize)> = None;
        for (i, p) in self.parts.iter().enumerate() {
            if !may_hit(o, d, p.bound) {
                continue;
            }
            if let Some(h) = p.shape.hit(o, d) {
                if best.is_none_or(|(b, _)| h.0 < b.0) {
                    best = Some((h, i));
                }
            }
        }
        best
    }

    /// Whether any primitive blocks the ray (shadow rays).
    fn blocked(&self, o: Vec3, d: Vec3) -> bool {
        self.parts.iter().any(|p| may_hit(o, d, p.bound) && p.shape.hit(o, d).is_some())
    }

    /// First surface along the unit-direction ray: distance, normal and what it is.
    pub fn first_hit(&self, o: Vec3, d: Vec3) -> (f32, Vec3, Surface) {
        let part = self.nearest_part(o, d);
        let (t_env, n_env, s_env) = match &self.environment {
            Environment::Room { min, max, .. } => {
                let (t, n, face) = room_exit(o, d, *min, *max);
                (t, n, Surface::Face(face))
            }
            Environment::Open { radius, .. } => {
                let t = if d[1] < -1e-6 { -o[1] / d[1] } else { f32::INFINITY };
                let p = axpy(o, t, d);
                if t > T_MIN && p[0] * p[0] + p[2] * p[2] < radius * radius {
                    (t, [0.0, 1.0, 0.0], Surface::Ground)
                } else {
                    (f32::INFINITY, [0.0, 1.0, 0.0], Surface::Sky)
                }
            }
        };
        match part {
            Some(((t, n), i)) if t < t_env => (t, n, Surface::Part(i)),
            _ => (t_env, n_env, s_env),
        }
    }

    /// Albedo of `surface` at `p`.
    fn albedo(&self, surface: Surface, p: Vec3) -> Rgb {
        // Flat surfaces are textured in their own plane: the solid texture's coordinate across
        // the face is pinned to the frame origin, where the patterns are mid-cell.
        let planar = |m: &Material, axis: usize| {
            let mut q = p;
            q[axis] = m.origin[axis];
            m.albedo(q)
        };
        match (surface, &self.environment) {
            (Surface::Part(i), _) => self.parts[i].material.albedo(p),
            (Surface::Face(k), Environment::Room { faces, .. }) => planar(&faces[k], k / 2),
            (Surface::Ground, Environment::Open { ground, .. }) => planar(ground, 1),
            _ => [0.0; 3],
        }
    }

    /// Whether `surface` is part of the foreground object.
    fn is_foreground(&self, surface: Surface) -> bool {
        matches!(surface, Surface::Part(i) if self.parts[i].foreground)
    }

    /// Colour of a (non-sky) surface point `p` with normal `n` and albedo `albedo`.
    fn shade(&self, p: Vec3, n: Vec3, albedo: Rgb) -> Rgb {
        let lit = || !self.blocked(axpy(p, 1e-3, n), self.light);
        shade(albedo, n, self.light, self.ambient, self.diffuse, lit)
    }

    fn sky(&self, d: Vec3) -> Rgb {
        let Environment::Open { sky, .. } = &self.environment else { unreachable!("rooms are closed") };
        sky.colour(d, self.light)
    }
}

impl Trace for RandomWorld {
    fn trace(&self, o: Vec3, d: Vec3) -> Sample {
        let (t, n, surface) = self.first_hit(o, d);
        if surface == Surface::Sky {
            return Sample { rgb: self.sky(d), foreground: false, point: axpy(o, SKY_DISTANCE, d) };
        }
        let p = axpy(o, t, d);
        Sample { rgb: self.shade(p, n, self.albedo(surface, p)), foreground: self.is_foreground(surface), point: p }
    }

    fn probe(&self, o: Vec3, d: Vec3) -> (bool, Vec3) {
        let (t, _, surface) = self.first_hit(o, d);
        if surface == Surface::Sky {
            return (false, axpy(o, SKY_DISTANCE, d));
        }
        (self.is_foreground(surface), axpy(o, t, d))
    }

    /// Geometry, light and shadow per sub-pixel ray, but the albedo once per surface the
    /// pixel sees, at the mean of its hit points: the patterns are smooth at pixel scale, and
    /// texturing is most of the shading cost.
    fn pixel(&self, o: Vec3, subs: [Vec3; 4]) -> Rgb {
        let hits = subs.map(|d| self.first_hit(o, d));
        let points: [Vec3; 4] = std::array::from_fn(|i| axpy(o, hits[i].0, subs[i]));
        let mut albedo: [Option<Rgb>; 4] = [None; 4];
        let mut acc = [0.0f32; 3];
        for i in 0..4 {
            let (_, n, surface) = hits[i];
            let rgb = if surface == Surface::Sky {
                self.sky(subs[i])
            } else {
                let a = match (0..i).find(|&j| hits[j].2 == surface) {
                    Some(j) => albedo[j].expect("set for every earlier non-sky hit"),
                    None => {
                        let (mut c, mut count) = ([0.0f32; 3], 0.0f32);
                        for j in (i..4).filter(|&j| hits[j].2 == surface) {
                            (0..3).for_each(|k| c[k] += points[j][k]);
                            count += 1.0;
                        }
                        self.albedo(surface, c.map(|v| v / count))
                    }
                };
                albedo[i] = Some(a);
                self.shade(points[i], n, a)
            };
            (0..3).for_each(|k| acc[k] += 0.25 * rgb[k]);
        }
        acc
    }
}
