//! Surroundings of a random world: a room sized around the cameras (floor, four walls and a
//! ceiling, each with its own material), or, for the unbounded rig, an open textured ground
//! ringed by distant towers under a sky at infinity.

use sos_core::camera::{dot, Vec3};

use super::super::material::{Material, Pattern};
use super::super::rig::SplitMix;
use super::super::shape::Shape;
use super::super::texture::{mix, Rgb};
use super::draw::Draw;
use super::palette::{hsv, material, pale, Weights};

/// Room walls stand at least this far beyond the cameras and the object.
const MIN_WALL_MARGIN: f32 = 0.5;

/// A sky: a gradient from the horizon to the zenith, brighter towards the light.
#[derive(Debug, Clone, Copy)]
pub struct Sky {
    /// Colour at the horizon (and below it).
    pub horizon: Rgb,
    /// Colour straight up.
    pub zenith: Rgb,
    /// Colour of the glow around the light.
    pub glow: Rgb,
}

impl Sky {
    /// Colour of unit direction `d` with the light along `light`.
    pub fn colour(&self, d: Vec3, light: Vec3) -> Rgb {
        let base = mix(self.horizon, self.zenith, d[1].max(0.0).sqrt());
        mix(base, self.glow, 0.35 * dot(d, light).max(0.0).powi(4))
    }
}

/// The surroundings.
#[derive(Debug, Clone)]
pub enum Environment {
    /// A closed room; `faces` in [`super::super::geometry::room_exit`]'s order (−X, +X, floor,
    /// ceiling, −Z, +Z).
    Room {
        /// Minimum corner (the floor is at `min[1] = 0`).
        min: Vec3,
        /// Maximum corner.
        max: Vec3,
        /// Material of each face.
        faces: Box<[Material; 6]>,
    },
    /// An open ground disk under a sky.
    Open {
        /// Ground material (fading to its mean colour far away).
        ground: Material,
        /// Radius of the ground disk; beyond it rays see the sky.
        radius: f32,
        /// The sky.
        sky: Sky,
    },
}

impl Environment {
    /// The material the object stands on.
    pub fn ground(&self) -> &Material {
        match self {
            Environment::Room { faces, .. } => &faces[2],
            Environment::Open { ground, .. } => ground,
        }
    }

    /// Short description.
    pub fn describe(&self) -> String {
        match self {
            Environment::Room { min, max, faces } => format!(
                "room {:.1} x {:.1} x {:.1} m, {} floor, walls {}",
                max[0] - min[0],
                max[1] - min[1],
                max[2] - min[2],
                faces[2].pattern.name(),
                [0, 1, 4, 5].map(|k| faces[k].pattern.name()).join("/")
            ),
            Environment::Open { ground, radius, .. } => {
                format!("open {} ground ({radius:.0} m), sky", ground.pattern.name())
            }
        }
    }
}

/// A room holding the box `content` (cameras, novel-view path and object) with margins.
pub fn room(content: [Vec3; 2], rng: &mut SplitMix) -> Environment {
    let [lo, hi] = content;
    let mut min = [0.0; 3];
    let mut max = [0.0; 3];
    for k in [0, 2] {
        min[k] = lo[k] - rng.range(MIN_WALL_MARGIN, 2.2);
        max[k] = hi[k] + rng.range(MIN_WALL_MARGIN, 2.2);
    }
    max[1] = (hi[1] + rng.range(0.3, 1.5)).max(rng.range(2.4, 3.2));
    const FLOOR: Weights = [0.5, 1.2, 1.0, 1.0];
    const WALL: Weights = [1.0, 0.8, 1.0, 1.0];
    let floor = Material { origin: min, ..material(FLOOR, rng.range(0.4, 1.2), &[0, 2], rng) };
    // Walls keep an upright frame, so stripes run straight across them.
    let mut wall =
        |axes: &[usize]| Material { origin: min, yaw: 0.0, ..material(WALL, rng.range(0.3, 1.0), axes, rng) };
    let (x0, x1, z0, z1) = (wall(&[1, 2]), wall(&[1, 2]), wall(&[0, 1]), wall(&[0, 1]));
    let ceiling = {
        let a = pale(rng);
        let pattern = if rng.chance(0.5) { Pattern::Flat } else { Pattern::Noise { size: rng.range(0.4, 0.9) } };
        Material {
            pattern,
            a,
            b: a.map(|v| v * 0.85),
            grain: 0.1,
            grain_size: 0.5,
            origin: min,
            yaw: 0.0,
            fade: None,
            seed: rng.seed32(),
        }
    };
    Environment::Room { min, max, faces: Box::new([x0, x1, floor, ceiling, z0, z1]) }
}

/// An open world whose cameras stay within `reach` of the object (horizontally), and its
/// distant towers (shape, material).
pub fn open(reach: f32, rng: &mut SplitMix) -> (Environment, Vec<(Shape, Material)>) {
    const GROUND: Weights = [0.3, 1.2, 0.6, 1.2];
    let fade_start = (1.5 * reach).max(4.0);
    let ground =
        Material { fade: Some([fade_start, 2.5 * fade_start]), ..material(GROUND, rng.range(0.6, 1.5), &[0, 2], rng) };
    let sky = match rng.weighted(&[0.6, 0.25, 0.15]) {
        // Clear, overcast, dusk.
        0 => Sky {
            horizon: hsv(rng.range(0.5, 0.65), rng.range(0.04, 0.15), rng.range(0.85, 0.95)),
            zenith: hsv(rng.range(0.55, 0.65), rng.range(0.35, 0.6), rng.range(0.65, 0.9)),
            glow: [1.0, 0.92, 0.75],
        },
        1 => {
            let g = rng.range(0.6, 0.8);
            Sky { horizon: [g + 0.1, g + 0.1, g + 0.12], zenith: [g, g, g + 0.03], glow: [0.9, 0.9, 0.9] }
        }
        _ => Sky {
            horizon: hsv(rng.range(0.03, 0.1), rng.range(0.3, 0.5), 0.92),
            zenith: hsv(rng.range(0.6, 0.7), rng.range(0.4, 0.6), rng.range(0.45, 0.65)),
            glow: [1.0, 0.8, 0.55],
        },
    };
    let radius = rng.range(35.0, 60.0);
    // Towers on a ring well outside the cameras' circle, spread in azimuth.
    let count = 4 + rng.below(6);
    let inner = (2.5 * reach + 3.0).max(8.0);
    let start = rng.angle();
    let mut towers: Vec<(Shape, Material)> = Vec::new();
    for i in 0..count {
        for _ in 0..20 {
            let a = start + std::f32::consts::TAU * (i as f32 + rng.range(-0.3, 0.3)) / count as f32;
            let r = rng.range(inner, inner + 16.0);
            let (x, z) = (r * a.sin(), r * a.cos());
            let w = rng.range(0.8, 3.0);
            let h = rng.range(3.0, 12.0);
            let shape = match rng.below(3) {
                0 => Shape::Box {
                    centre: [x, 0.5 * h, z],
                    half: [w, 0.5 * h, w * rng.range(0.5, 1.0)],
                    yaw: rng.angle(),
                },
                1 => Shape::Cylinder { base: [x, 0.0, z], height: h, radius: w },
                _ => Shape::Cone { base: [x, 0.0, z], height: h, radius: 1.3 * w },
            };
            let clear = towers.iter().all(|(t, _)| {
                let [tx, tz] = t.axis();
                ((tx - x).powi(2) + (tz - z).powi(2)).sqrt() > t.footprint() + shape.footprint() + 1.0
            });
            if clear {
                let m = material([0.5, 0.6, 1.2, 1.0], rng.range(1.0, 3.0), &[1], rng);
                towers.push((shape, m.at(shape.centre())));
                break;
            }
        }
    }
    (Environment::Open { ground, radius, sky }, towers)
}
