//! The foreground object of a random world: 1–4 primitives stacked on each other or standing
//! side by side, on a pedestal (a plinth under a group) or on the ground. Every part rests on
//! what is below it (spheres sink slightly into narrow tops, a sphere on a torus sits in its
//! ring), so the composite is one connected object; all of its parts are mask 1.

use sos_core::camera::Vec3;

use super::super::rig::SplitMix;
use super::super::shape::Shape;
use super::draw::Draw;

/// How the primitives are put together.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arrangement {
    /// Each primitive stands on the one before.
    Stack,
    /// Primitives (or short stacks) side by side on a common base.
    Group,
}

/// The foreground composite, centred on the vertical axis through the world origin.
#[derive(Debug, Clone)]
pub struct Composition {
    /// Every part; the pedestal, when there is one, first.
    pub parts: Vec<Shape>,
    /// Whether `parts[0]` is a pedestal (or a group's plinth).
    pub pedestal: bool,
    /// Stack or group.
    pub arrangement: Arrangement,
}

/// The primitive kinds, in the order of the weight tables below.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Sphere,
    Box,
    Cylinder,
    Cone,
    Torus,
}

const KINDS: [Kind; 5] = [Kind::Sphere, Kind::Box, Kind::Cylinder, Kind::Cone, Kind::Torus];

/// What a new part stands on.
#[derive(Debug, Clone, Copy)]
struct Support {
    /// Height of the top.
    y: f32,
    /// Radius of its flat top (infinite for the ground or a plinth).
    radius: f32,
    /// A torus's ring instead of a flat top: (centre height, major, minor).
    ring: Option<(f32, f32, f32)>,
}

const GROUND: Support = Support { y: 0.0, radius: f32::INFINITY, ring: None };

/// Spheres sink this far into a narrower support (or a ring), so no hairline gap shows
/// between the parts.
const SINK: f32 = 0.006;

/// A part of kind `kind` and horizontal radius about `w`, standing on `on` at `(x, z)`.
fn place(kind: Kind, w: f32, on: Support, [x, z]: [f32; 2], rng: &mut SplitMix) -> Shape {
    match kind {
        Kind::Sphere => {
            let y = match on.ring {
                // Resting on the tube: |centre − tube centre circle| = w + minor.
                Some((cy, major, minor)) => cy + ((w + minor).powi(2) - major * major).max(0.0).sqrt(),
                None if on.radius >= w => on.y + w,
                None => on.y + (w * w - on.radius * on.radius).sqrt(),
            };
            let sink = if on.radius.is_finite() { SINK } else { 0.0 };
            Shape::Sphere { centre: [x, y - sink, z], radius: w }
        }
        Kind::Box => {
            let half = [w * rng.range(0.55, 0.85), 0.5 * w * rng.range(0.8, 2.0), w * rng.range(0.55, 0.85)];
            Shape::Box { centre: [x, on.y + half[1], z], half, yaw: rng.angle() }
        }
        Kind::Cylinder => Shape::Cylinder { base: [x, on.y, z], height: w * rng.range(0.5, 2.2), radius: w },
        Kind::Cone => Shape::Cone { base: [x, on.y, z], height: w * rng.range(1.2, 2.8), radius: w },
        Kind::Torus => {
            let mut minor = w * rng.range(0.22, 0.4);
            // The hole must be narrower than the top it rests on, or the ring would drop over it.
            if on.radius.is_finite() {
                minor = minor.max(0.5 * (w - on.radius + 0.02)).min(0.48 * w);
            }
            let major = w - minor;
            let lift =
                if on.radius >= major { minor } else { (minor * minor - (major - on.radius).powi(2)).max(0.0).sqrt() };
            Shape::Torus { centre: [x, on.y + lift, z], major, minor }
        }
    }
}

/// What stands on top of `s` can rest on.
fn support_of(s: &Shape) -> Support {
    match *s {
        Shape::Torus { centre, major, minor } => {
            Support { y: s.top(), radius: 0.0, ring: Some((centre[1], major, minor)) }
        }
        _ => Support { y: s.top(), radius: s.support_radius(), ring: None },
    }
}

/// A stack of `count` parts at `(x, z)` on `on`, the first of horizontal radius `w`. Only flat
/// tops carry more parts; a torus only carries a sphere, which ends the stack.
fn stack(count: usize, mut w: f32, mut on: Support, at: [f32; 2], rng: &mut SplitMix) -> Vec<Shape> {
    let mut parts: Vec<Shape> = Vec::new();
    for i in 0..count {
        let last = i + 1 == count;
        let kind = match parts.last() {
            Some(Shape::Torus { .. }) => Kind::Sphere,
            _ if last => KINDS[rng.weighted(&[1.3, 1.0, 1.0, 1.0, 0.8])],
            _ if i + 2 == count => KINDS[rng.weighted(&[0.0, 1.0, 1.0, 0.0, 0.6])],
            _ => KINDS[rng.weighted(&[0.0, 1.0, 1.0, 0.0, 0.0])],
        };
        if let Some((_, major, minor)) = on.ring {
            // A sphere in a ring must be wider than the hole, and not much wider than the ring.
            w = w.min(major + minor).max(major - minor + 0.04);
        }
        let part = place(kind, w, on, at, rng);
        on = support_of(&part);
        parts.push(part);
        if matches!(kind, Kind::Sphere | Kind::Cone) || on.y > 2.0 {
            break;
        }
        w = (w * rng.range(0.55, 1.1)).clamp(0.08, 0.42);
    }
    parts
}

/// A single primitive of any kind and horizontal radius about `w` on the ground at `(x, z)`.
pub fn standing(w: f32, at: [f32; 2], rng: &mut SplitMix) -> Shape {
    let kind = KINDS[rng.below(KINDS.len())];
    place(kind, w, GROUND, at, rng)
}

/// The widest horizontal reach of `parts` from `(x, z)`.
fn reach(parts: &[Shape], [x, z]: [f32; 2]) -> f32 {
    parts
        .iter()
        .map(|s| {
            let [sx, sz] = s.axis();
            ((sx - x).powi(2) + (sz - z).powi(2)).sqrt() + s.footprint()
        })
        .fold(0.0, f32::max)
}

/// Draws the foreground composite.
pub fn compose(rng: &mut SplitMix) -> Composition {
    let count = 1 + rng.weighted(&[0.2, 0.3, 0.3, 0.2]);
    let pedestal = rng.chance(0.45);
    if count >= 2 && rng.chance(0.45) {
        group(count, pedestal, rng)
    } else {
        let w = rng.range(0.12, 0.38);
        let mut parts = Vec::new();
        let mut on = GROUND;
        if pedestal {
            // Narrow stands under spheres (as a ball on a column), wider ones under the rest;
            // tori need a top wider than their hole, which `place` keeps.
            let r = w * rng.range(0.35, 1.1);
            let height = rng.range(0.15, 0.7);
            let p = if rng.chance(0.6) {
                Shape::Cylinder { base: [0.0; 3], height, radius: r }
            } else {
                let half = [r, 0.5 * height, r];
                Shape::Box { centre: [0.0, 0.5 * height, 0.0], half, yaw: rng.angle() }
            };
            on = support_of(&p);
            parts.push(p);
        }
        parts.extend(stack(count, w, on, [0.0, 0.0], rng));
        Composition { parts, pedestal, arrangement: Arrangement::Stack }
    }
}

/// `count` primitives side by side around the origin, on a plinth when `pedestal`.
fn group(count: usize, pedestal: bool, rng: &mut SplitMix) -> Composition {
    // With three or more primitives, one member may be a stack of two.
    let members = if count >= 3 && rng.chance(0.35) { count - 1 } else { count };
    let plinth_height = if pedestal { rng.range(0.08, 0.35) } else { 0.0 };
    let on = Support { y: plinth_height, ..GROUND };
    let mut built: Vec<Vec<Shape>> = (0..members)
        .map(|i| {
            let parts = if i == 0 && members < count { 2 } else { 1 };
            stack(parts, rng.range(0.09, 0.26), on, [0.0, 0.0], rng)
        })
        .collect();
    let widths: Vec<f32> = built.iter().map(|m| reach(m, [0.0, 0.0])).collect();
    let gap = rng.range(0.0, 0.1);
    let turn = rng.angle();
    let positions: Vec<[f32; 2]> = if members == 2 {
        let (s, c) = turn.sin_cos();
        let (a, b) = (widths[0] + 0.5 * gap, widths[1] + 0.5 * gap);
        vec![[-a * c, -a * s], [b * c, b * s]]
    } else {
        // On a circle wide enough that neighbours (even jittered) keep `gap` between them.
        let chord = 2.0 * (std::f32::consts::PI / members as f32).sin();
        let radius =
            (0..members).map(|i| (widths[i] + widths[(i + 1) % members] + gap) / chord).fold(0.0, f32::max) * 1.15;
        (0..members)
            .map(|i| {
                let a = turn + std::f32::consts::TAU * i as f32 / members as f32 + rng.range(-0.12, 0.12);
                [radius * a.cos(), radius * a.sin()]
            })
            .collect()
    };
    for (m, p) in built.iter_mut().zip(&positions) {
        for s in m.iter_mut() {
            *s = s.moved([p[0], 0.0, p[1]]);
        }
    }
    let mut parts: Vec<Shape> = Vec::new();
    if pedestal {
        let all: Vec<Shape> = built.iter().flatten().copied().collect();
        let r = reach(&all, [0.0, 0.0]) + rng.range(0.04, 0.15);
        parts.push(if rng.chance(0.5) {
            Shape::Cylinder { base: [0.0; 3], height: plinth_height, radius: r }
        } else {
            // A square plinth holding the circle of radius r.
            Shape::Box { centre: [0.0, 0.5 * plinth_height, 0.0], half: [r, 0.5 * plinth_height, r], yaw: rng.angle() }
        });
    }
    parts.extend(built.into_iter().flatten());
    Composition { parts, pedestal, arrangement: Arrangement::Group }
}

impl Composition {
    /// Bounding box of all parts.
    pub fn aabb(&self) -> [Vec3; 2] {
        let mut b = [[f32::INFINITY; 3], [f32::NEG_INFINITY; 3]];
        for s in &self.parts {
            let [lo, hi] = s.aabb();
            for k in 0..3 {
                b[0][k] = b[0][k].min(lo[k]);
                b[1][k] = b[1][k].max(hi[k]);
            }
        }
        b
    }

    /// Points outlining the composite's silhouette from any viewpoint.
    pub fn silhouette(&self) -> Vec<Vec3> {
        self.parts.iter().flat_map(Shape::silhouette).collect()
    }

    /// Number of primitives, the pedestal not counted.
    pub fn primitives(&self) -> usize {
        self.parts.len() - usize::from(self.pedestal)
    }

    /// One line for humans: arrangement, primitives, base.
    pub fn describe(&self) -> String {
        let names: Vec<&str> = self.parts[usize::from(self.pedestal)..].iter().map(Shape::name).collect();
        let (what, base) = match self.arrangement {
            Arrangement::Stack => ("stack", "pedestal"),
            Arrangement::Group => ("group", "plinth"),
        };
        let on = if self.pedestal { format!("on a {base}") } else { "on the ground".into() };
        format!("{what} of {} ({}) {on}", self.primitives(), names.join(", "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::random::draw::{stream, Aspect};

    /// Whether some point of a 1 cm grid lies within 1.2 cm of both surfaces.
    fn touching(a: &Shape, b: &Shape) -> bool {
        let ([alo, ahi], [blo, bhi]) = (a.aabb(), b.aabb());
        let lo = [0, 1, 2].map(|k| alo[k].max(blo[k]) - 0.02);
        let hi = [0, 1, 2].map(|k| ahi[k].min(bhi[k]) + 0.02);
        let steps = [0, 1, 2].map(|k| ((hi[k] - lo[k]) / 0.01).ceil().max(0.0) as usize);
        (0..=steps[0]).any(|i| {
            (0..=steps[1]).any(|j| {
                (0..=steps[2]).any(|k| {
                    let p = [lo[0] + 0.01 * i as f32, lo[1] + 0.01 * j as f32, lo[2] + 0.01 * k as f32];
                    a.distance(p) < 0.012 && b.distance(p) < 0.012
                })
            })
        })
    }

    #[test]
    fn compositions_rest_on_the_ground_and_hold_together() {
        let mut kinds = std::collections::BTreeSet::new();
        let (mut stacks, mut groups, mut pedestals) = (0, 0, 0);
        for seed in 0..300 {
            let c = compose(&mut stream(seed, Aspect::Composition));
            assert!((1..=4).contains(&c.primitives()), "seed {seed}: {}", c.describe());
            let [lo, hi] = c.aabb();
            assert!(lo[1].abs() < 1e-6, "seed {seed}: the object floats or sinks ({})", lo[1]);
            assert!(hi[1] < 2.8 && hi[0] - lo[0] < 2.5, "seed {seed}: {lo:?} {hi:?}");
            // Connected: every part touches (or slightly overlaps) an earlier part or the ground.
            for (i, s) in c.parts.iter().enumerate() {
                let grounded = s.bottom().abs() < 1e-5;
                let touches = c.parts[..i].iter().any(|t| touching(s, t));
                assert!(grounded || touches, "seed {seed}: part {i} ({}) floats in {}", s.name(), c.describe());
            }
            kinds.extend(c.parts.iter().map(Shape::name));
            match c.arrangement {
                Arrangement::Stack => stacks += 1,
                Arrangement::Group => groups += 1,
            }
            pedestals += usize::from(c.pedestal);
        }
        assert_eq!(kinds.len(), 5, "{kinds:?}");
        assert!(stacks > 60 && groups > 60 && pedestals > 60, "{stacks} {groups} {pedestals}");
    }
}
