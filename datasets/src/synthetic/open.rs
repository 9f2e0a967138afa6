//! The unbounded synthetic world: the same foreground object (checkered sphere on a striped
//! pedestal) standing on an open textured ground, ringed by distant towers (8–18 m away, several
//! metres tall), under a sky that is a smooth gradient over directions (content at infinity).
//! Shading is Lambertian with one directional light, ambient light and the object's shadow.

use sos_core::camera::{axpy, dot, normalize, Vec3};

use super::geometry::{cone, cylinder, sphere, yawed_box, Hit};
use super::texture::{checker, fbm, mix, scale, stripes, Rgb};
use super::world::{shade, Sample, Trace, OBJECT_CENTRE, OBJECT_RADIUS};

/// Radius of the ground disk (beyond it rays see the sky).
pub const GROUND_RADIUS: f32 = 40.0;
/// Distance beyond which the ground's checkers fade to their mean colour (no aliasing far
/// away, where one pixel covers many squares).
const GROUND_FADE: [f32; 2] = [4.0, 10.0];
const PEDESTAL_TOP: f32 = 0.4;
const PEDESTAL_RADIUS: f32 = 0.22;
const AMBIENT: f32 = 0.45;
const DIFFUSE: f32 = 0.65;

/// A distant tower: shape, position and colours.
#[derive(Debug, Clone, Copy)]
enum Tower {
    /// Box at (x, z) with half extents and yaw.
    Box { at: [f32; 2], half: Vec3, yaw: f32, a: Rgb, b: Rgb },
    /// Vertical cylinder at (x, z).
    Cylinder { at: [f32; 2], height: f32, radius: f32, a: Rgb, b: Rgb },
    /// Cone at (x, z).
    Cone { at: [f32; 2], height: f32, radius: f32, a: Rgb, b: Rgb },
}

/// Towers at azimuths spread around the object, far outside the cameras' circle.
const TOWERS: [Tower; 6] = [
    Tower::Box { at: [9.0, -4.0], half: [1.2, 3.0, 1.2], yaw: 0.4, a: [0.25, 0.4, 0.85], b: [0.85, 0.88, 0.95] },
    Tower::Cylinder { at: [-6.0, -11.0], height: 5.0, radius: 1.5, a: [0.2, 0.65, 0.3], b: [0.85, 0.9, 0.75] },
    Tower::Cone { at: [-13.0, 3.0], height: 6.5, radius: 2.5, a: [0.65, 0.3, 0.7], b: [0.9, 0.8, 0.92] },
    Tower::Box { at: [-3.0, 14.0], half: [2.0, 2.2, 1.0], yaw: -0.3, a: [0.85, 0.3, 0.25], b: [0.95, 0.85, 0.7] },
    Tower::Cylinder { at: [12.0, 9.0], height: 7.0, radius: 1.0, a: [0.9, 0.75, 0.2], b: [0.5, 0.45, 0.4] },
    Tower::Box { at: [4.0, -17.0], half: [1.5, 4.0, 1.5], yaw: 0.9, a: [0.3, 0.7, 0.75], b: [0.2, 0.3, 0.35] },
];

#[derive(Debug, Clone, Copy, PartialEq)]
enum Surface {
    Sphere,
    Pedestal,
    Ground,
    Tower(usize),
}

/// The open world; `seed` varies the noise patterns.
#[derive(Debug, Clone)]
pub struct OpenWorld {
    seed: u32,
    light: Vec3,
}

impl OpenWorld {
    /// The world with noise patterns drawn from `seed`.
    pub fn new(seed: u64) -> Self {
        OpenWorld { seed: (seed ^ (seed >> 32)) as u32 ^ 0x0BE4, light: normalize([0.45, 1.0, 0.3]) }
    }

    fn foreground(o: Vec3, d: Vec3) -> Option<(Hit, Surface)> {
        let c = OBJECT_CENTRE;
        let s = sphere(o, d, c, OBJECT_RADIUS).map(|h| (h, Surface::Sphere));
        let p = cylinder(o, d, c[0], c[2], 0.0, PEDESTAL_TOP, PEDESTAL_RADIUS).map(|h| (h, Surface::Pedestal));
        match (s, p) {
            (Some(a), Some(b)) => Some(if a.0 .0 <= b.0 .0 { a } else { b }),
            (a, b) => a.or(b),
        }
    }

    fn tower_hit(i: usize, o: Vec3, d: Vec3) -> Option<Hit> {
        match TOWERS[i] {
            Tower::Box { at, half, yaw, .. } => yawed_box(o, d, [at[0], half[1], at[1]], half, yaw),
            Tower::Cylinder { at, height, radius, .. } => cylinder(o, d, at[0], at[1], 0.0, height, radius),
            Tower::Cone { at, height, radius, .. } => cone(o, d, at[0], at[1], 0.0, height, radius),
        }
    }

    fn nearest(&self, o: Vec3, d: Vec3) -> Option<(Hit, Surface)> {
        let mut best = Self::foreground(o, d);
        for i in 0..TOWERS.len() {
            if let Some(h) = Self::tower_hit(i, o, d) {
                if best.is_none_or(|(b, _)| h.0 < b.0) {
                    best = Some((h, Surface::Tower(i)));
                }
            }
        }
        if d[1] < -1e-6 {
            let t = -o[1] / d[1];
            let p = axpy(o, t, d);
            if t > 1e-4
                && p[0] * p[0] + p[2] * p[2] < GROUND_RADIUS * GROUND_RADIUS
                && best.is_none_or(|(b, _)| t < b.0)
            {
                best = Some(((t, [0.0, 1.0, 0.0]), Surface::Ground));
            }
        }
        best
    }

    /// Sky colour of a direction: pale at the horizon, deeper blue overhead, warmer towards
    /// the light.
    fn sky(&self, d: Vec3) -> Rgb {
        let up = d[1].max(0.0).sqrt();
        let base = mix([0.86, 0.88, 0.9], [0.35, 0.55, 0.85], up);
        let glow = dot(d, self.light).max(0.0).powi(4);
        mix(base, [1.0, 0.92, 0.75], 0.35 * glow)
    }

    fn albedo(&self, surface: Surface, p: Vec3) -> Rgb {
        let seed = self.seed;
        let noise = |size: f32, salt: u32| fbm(p, size, seed.wrapping_add(salt));
        match surface {
            Surface::Sphere => {
                let q = normalize([p[0] - OBJECT_CENTRE[0], p[1] - OBJECT_CENTRE[1], p[2] - OBJECT_CENTRE[2]]);
                let lon = q[2].atan2(q[0]) / std::f32::consts::TAU;
                let lat = q[1].clamp(-1.0, 1.0).asin() / std::f32::consts::PI;
                let c = checker(lon * 8.0, lat * 4.0 + 0.5, 1.0);
                let polar = ((q[1].abs() - 0.75) / 0.2).clamp(0.0, 1.0);
                let c = c * (1.0 - polar) + 0.3 * polar;
                scale(mix([0.95, 0.45, 0.1], [0.97, 0.93, 0.85], c), 0.9 + 0.15 * noise(0.25, 7))
            }
            Surface::Pedestal => mix([0.3, 0.3, 0.34], [0.6, 0.58, 0.55], stripes(p[1], 0.2)),
            Surface::Ground => {
                let r = (p[0] * p[0] + p[2] * p[2]).sqrt();
                let fade = ((r - GROUND_FADE[0]) / (GROUND_FADE[1] - GROUND_FADE[0])).clamp(0.0, 1.0);
                let c = checker(p[0], p[2], 1.2) * (1.0 - fade) + 0.5 * fade;
                scale(mix([0.38, 0.52, 0.3], [0.62, 0.7, 0.45], c), 0.85 + 0.3 * noise(1.5, 1))
            }
            Surface::Tower(i) => {
                let (a, b) = match TOWERS[i] {
                    Tower::Box { a, b, .. } | Tower::Cylinder { a, b, .. } | Tower::Cone { a, b, .. } => (a, b),
                };
                scale(mix(a, b, stripes(p[1], 1.5)), 0.85 + 0.3 * noise(1.0, 10 + i as u32))
            }
        }
    }
}

#[cfg(test)]
impl OpenWorld {
    /// [`Trace::trace`] without the trait in scope (tests).
    pub fn trace_at(&self, o: Vec3, d: Vec3) -> Sample {
        Trace::trace(self, o, d)
    }
}

impl Trace for OpenWorld {
    fn trace(&self, o: Vec3, d: Vec3) -> Sample {
        let Some(((t, n), surface)) = self.nearest(o, d) else {
            return Sample { rgb: self.sky(d), foreground: false, point: axpy(o, 1e4, d) };
        };
        let p = axpy(o, t, d);
        let lit = || Self::foreground(axpy(p, 1e-3, n), self.light).is_none();
        Sample {
            rgb: shade(self.albedo(surface, p), n, self.light, AMBIENT, DIFFUSE, lit),
            foreground: matches!(surface, Surface::Sphere | Surface::Pedestal),
            point: p,
        }
    }
}
