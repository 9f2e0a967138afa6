//! Random colours and materials, and the deliberate hard cases: an object whose colours are
//! close to the ground's, or one textured exactly like part of the background.

use super::super::material::{Material, Pattern};
use super::super::rig::SplitMix;
use super::super::texture::Rgb;
use super::draw::Draw;

/// Colour from hue (in turns), saturation and value.
pub fn hsv(h: f32, s: f32, v: f32) -> Rgb {
    let h = h.rem_euclid(1.0) * 6.0;
    let f = h - h.floor();
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match h as u32 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// Any colour of moderate to strong saturation.
pub fn colour(rng: &mut SplitMix) -> Rgb {
    hsv(rng.uniform(), rng.range(0.3, 0.9), rng.range(0.4, 0.95))
}

/// A pale, nearly neutral colour (ceilings, light walls).
pub fn pale(rng: &mut SplitMix) -> Rgb {
    hsv(rng.uniform(), rng.range(0.02, 0.2), rng.range(0.72, 0.95))
}

/// `c` moved by at most `spread` per channel.
pub fn near(c: Rgb, spread: f32, rng: &mut SplitMix) -> Rgb {
    c.map(|v| (v + rng.range(-spread, spread)).clamp(0.03, 0.97))
}

/// A second colour for a two-colour pattern: the same hue lighter or darker, or another colour.
fn partner(a: Rgb, rng: &mut SplitMix) -> Rgb {
    if rng.chance(0.5) {
        let k = if rng.chance(0.5) { rng.range(0.35, 0.65) } else { rng.range(1.35, 1.8) };
        a.map(|v| (v * k).clamp(0.02, 0.98))
    } else if rng.chance(0.4) {
        pale(rng)
    } else {
        colour(rng)
    }
}

/// Relative weights of the patterns [flat, checkers, stripes, noise].
pub type Weights = [f32; 4];

/// A pattern of features about `size` metres; stripes run across one of `axes`.
pub fn pattern(weights: Weights, size: f32, axes: &[usize], rng: &mut SplitMix) -> Pattern {
    let period = (size * rng.range(0.6, 1.5)).max(0.1);
    match rng.weighted(&weights) {
        0 => Pattern::Flat,
        1 => Pattern::Checker { period },
        2 => Pattern::Stripes { period, axis: axes[rng.below(axes.len())] },
        _ => Pattern::Noise { size: 0.6 * period },
    }
}

/// A material with the base colour `a`, features about `size` metres.
pub fn material_with(a: Rgb, weights: Weights, size: f32, axes: &[usize], rng: &mut SplitMix) -> Material {
    let pattern = pattern(weights, size, axes, rng);
    let b = if pattern == Pattern::Flat { a } else { partner(a, rng) };
    Material {
        pattern,
        a,
        b,
        grain: if rng.chance(0.6) { rng.range(0.05, 0.3) } else { 0.0 },
        grain_size: (size * rng.range(0.5, 1.2)).max(0.12),
        origin: [0.0; 3],
        yaw: rng.angle(),
        fade: None,
        seed: rng.seed32(),
    }
}

/// A material of any colour.
pub fn material(weights: Weights, size: f32, axes: &[usize], rng: &mut SplitMix) -> Material {
    let a = colour(rng);
    material_with(a, weights, size, axes, rng)
}

/// A hard case drawn for the foreground's colours.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HardCase {
    /// Ordinary colours.
    None,
    /// Colours within a few percent of the ground's.
    Clash,
    /// The very material of a background surface (the ground or a wall).
    Camouflage,
}

impl HardCase {
    /// Draws a case: a colour clash with probability 0.2, camouflage with 0.12.
    pub fn draw(rng: &mut SplitMix) -> HardCase {
        match rng.weighted(&[0.68, 0.2, 0.12]) {
            0 => HardCase::None,
            1 => HardCase::Clash,
            _ => HardCase::Camouflage,
        }
    }

    /// A material for one foreground part: `ground` is the material the object stands on, and
    /// `backdrop` the background surface a camouflaged object copies.
    pub fn material(self, ground: &Material, backdrop: &Material, size: f32, rng: &mut SplitMix) -> Material {
        const OBJECT: Weights = [1.0, 1.2, 1.2, 1.0];
        match self {
            HardCase::None => material(OBJECT, size, &[0, 1, 2], rng),
            HardCase::Clash => {
                let m = material_with(near(ground.a, 0.05, rng), OBJECT, size, &[0, 1, 2], rng);
                let b = if m.pattern == Pattern::Flat { m.a } else { near(ground.b, 0.06, rng) };
                Material { b, ..m }
            }
            HardCase::Camouflage => Material { fade: None, ..*backdrop },
        }
    }

    /// Lower-case name, for descriptions.
    pub fn name(self) -> &'static str {
        match self {
            HardCase::None => "none",
            HardCase::Clash => "colour clash with the ground",
            HardCase::Camouflage => "textured like the background",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::random::draw::{stream, Aspect};

    #[test]
    fn colours_are_valid_and_clashes_are_close() {
        let mut rng = stream(9, Aspect::Materials);
        assert_eq!(hsv(0.0, 1.0, 1.0), [1.0, 0.0, 0.0]);
        let ground = material([0.0, 1.0, 1.0, 1.0], 0.5, &[0, 2], &mut rng);
        for _ in 0..500 {
            for c in [colour(&mut rng), pale(&mut rng)] {
                assert!(c.iter().all(|v| (0.0..=1.0).contains(v)), "{c:?}");
            }
            let m = HardCase::Clash.material(&ground, &ground, 0.3, &mut rng);
            assert!((0..3).all(|k| (m.a[k] - ground.a[k]).abs() <= 0.05 + 1e-6), "{:?} vs {:?}", m.a, ground.a);
            let m = HardCase::Camouflage.material(&ground, &ground, 0.3, &mut rng);
            assert_eq!((m.pattern, m.a, m.b, m.seed), (ground.pattern, ground.a, ground.b, ground.seed));
        }
    }
}
