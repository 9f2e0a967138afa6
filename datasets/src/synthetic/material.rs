//! Surface materials of random worlds: a pattern between two colours, evaluated as a solid
//! texture (so no surface needs texture coordinates), with an optional multiplicative grain.

use sos_core::camera::Vec3;

use super::texture::{fbm, mix, scale, stripes, value_noise, Rgb};

/// How the two colours of a material are laid out.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pattern {
    /// The first colour everywhere.
    Flat,
    /// Solid 3D checkers of cells `period / 2` wide.
    Checker {
        /// Period in metres (two cells).
        period: f32,
    },
    /// Stripes across one axis of the material's (yawed) frame.
    Stripes {
        /// Period in metres.
        period: f32,
        /// Axis of the material frame (0 = x, 1 = y, 2 = z) the stripes run across.
        axis: usize,
    },
    /// Blotches of smooth value noise.
    Noise {
        /// Feature size in metres.
        size: f32,
    },
}

impl Pattern {
    /// Lower-case name, for descriptions.
    pub fn name(&self) -> &'static str {
        match self {
            Pattern::Flat => "flat",
            Pattern::Checker { .. } => "checkers",
            Pattern::Stripes { .. } => "stripes",
            Pattern::Noise { .. } => "noise",
        }
    }
}

/// A material: pattern, colours, grain and the frame its solid texture is defined in.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Material {
    /// Layout of the colours.
    pub pattern: Pattern,
    /// First colour.
    pub a: Rgb,
    /// Second colour.
    pub b: Rgb,
    /// Brightness variation from value noise (0 = none, 0.3 = ±15%).
    pub grain: f32,
    /// Feature size of the grain in metres.
    pub grain_size: f32,
    /// Origin of the texture frame.
    pub origin: Vec3,
    /// Turn of the texture frame about +Y.
    pub yaw: f32,
    /// Horizontal distances from `origin` over which the pattern fades to its mean colour
    /// (far ground, where a pixel would cover many cells); `None` = never.
    pub fade: Option<[f32; 2]>,
    /// Seed of the noise.
    pub seed: u32,
}

impl Material {
    /// The same material with its frame at `origin`.
    pub fn at(self, origin: Vec3) -> Material {
        Material { origin, ..self }
    }

    /// Albedo at world point `p`.
    pub fn albedo(&self, p: Vec3) -> Rgb {
        let v = [p[0] - self.origin[0], p[1] - self.origin[1], p[2] - self.origin[2]];
        let (s, c) = self.yaw.sin_cos();
        let l = [c * v[0] - s * v[2], v[1], s * v[0] + c * v[2]];
        let t = match self.pattern {
            Pattern::Flat => 0.0,
            Pattern::Checker { period } => {
                // Shifted by a quarter period so a face through the origin sits mid-cell.
                let wave = |u: f32| 2.0 * stripes(u + 0.25 * period, period) - 1.0;
                0.5 + 0.5 * wave(l[0]) * wave(l[1]) * wave(l[2])
            }
            Pattern::Stripes { period, axis } => stripes(l[axis] + 0.25 * period, period),
            Pattern::Noise { size } => {
                let n = fbm(l, size, self.seed);
                ((n - 0.3) / 0.4).clamp(0.0, 1.0)
            }
        };
        let t = match self.fade {
            Some([start, end]) => {
                let r = (v[0] * v[0] + v[2] * v[2]).sqrt();
                let f = ((r - start) / (end - start)).clamp(0.0, 1.0);
                t * (1.0 - f) + 0.5 * f
            }
            None => t,
        };
        let colour = mix(self.a, self.b, t);
        if self.grain > 0.0 {
            // One octave: grain only modulates brightness, and noise is most of the shading cost.
            let s = 1.0 / self.grain_size;
            let g = value_noise([l[0] * s, l[1] * s, l[2] * s], self.seed ^ 0x51ed_27a3);
            scale(colour, 1.0 - 0.5 * self.grain + self.grain * g)
        } else {
            colour
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn material(pattern: Pattern) -> Material {
        Material {
            pattern,
            a: [0.1, 0.2, 0.3],
            b: [0.9, 0.8, 0.7],
            grain: 0.0,
            grain_size: 0.3,
            origin: [0.0; 3],
            yaw: 0.3,
            fade: None,
            seed: 1,
        }
    }

    #[test]
    fn patterns_use_both_colours_and_stay_between_them() {
        for pattern in
            [Pattern::Checker { period: 0.4 }, Pattern::Stripes { period: 0.3, axis: 0 }, Pattern::Noise { size: 0.25 }]
        {
            let m = material(pattern);
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for i in 0..4000 {
                // A floor through the origin: the checkers must not sit on a cell edge there.
                let p = [0.0013 * i as f32, 0.0, 0.0007 * i as f32];
                let c = m.albedo(p);
                lo = lo.min(c[0]);
                hi = hi.max(c[0]);
                assert!((0.1 - 1e-5..=0.9 + 1e-5).contains(&c[0]), "{pattern:?}: {c:?}");
            }
            assert!(lo < 0.2 && hi > 0.8, "{pattern:?} spans only {lo}..{hi}");
        }
        assert_eq!(material(Pattern::Flat).albedo([1.0, 2.0, 3.0]), [0.1, 0.2, 0.3]);
    }

    #[test]
    fn fade_reaches_the_mean_colour_far_away() {
        let m = Material { fade: Some([2.0, 4.0]), ..material(Pattern::Checker { period: 1.0 }) };
        let far = m.albedo([30.0, 0.0, 17.0]);
        assert!((far[0] - 0.5).abs() < 1e-5, "{far:?}");
    }
}
