//! Watching for content that piles up at a bounded extent's faces during stage 1: when a box
//! cuts through the scene, whatever lies beyond it is painted onto the nearest face, where no
//! single texture agrees with every view. Rays that end on a face then keep a much larger
//! photometric error than the rest; a room whose walls the box hugs does not (its walls fit).

use crate::render::contraction::Contraction;
use crate::render::renderer::Rendered;

/// Width of the shell inside each face that counts as "at the face", as a fraction of the box.
pub const FACE_SHELL: f32 = 0.01;

/// A ray ends on a face when at least this share of its opacity lies in the shell.
const FACE_RAY_SHARE: f32 = 0.5;

/// The warning needs at least this share of the rays to end on a face ...
pub const PILEUP_RAY_FRACTION: f64 = 0.1;

/// ... with a mean squared error at least this many times the other rays'.
pub const PILEUP_ERROR_RATIO: f64 = 4.0;

/// Running counts over stage-1 batches (exponentially forgetting, so the figures describe the
/// field as it is now).
#[derive(Debug, Clone, Default)]
pub struct FaceMonitor {
    face_rays: f64,
    face_sq_error: f64,
    other_rays: f64,
    other_sq_error: f64,
}

/// What the monitor has seen.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FaceFigures {
    /// Share of the rays that end on a face.
    pub ray_fraction: f64,
    /// Their mean squared error over that of the other rays (1 when there are none).
    pub error_ratio: f64,
}

impl FaceMonitor {
    /// Counts one composited batch, with `targets` the rays' true colours. Does nothing for a
    /// contraction other than a box.
    pub fn observe(&mut self, contraction: &Contraction, r: &Rendered, targets: &[[f32; 3]]) {
        let Contraction::Box { .. } = contraction else { return };
        const FORGET: f64 = 0.95;
        for v in [&mut self.face_rays, &mut self.face_sq_error, &mut self.other_rays, &mut self.other_sq_error] {
            *v *= FORGET;
        }
        for (ray, target) in targets.iter().enumerate() {
            let colour = r.colours[ray];
            let range = r.samples.range(ray);
            let at_face: f32 = range
                .clone()
                .filter(|&k| {
                    let u = contraction.to_unit(r.samples.positions[k]);
                    u.iter().any(|c| !(FACE_SHELL..=1.0 - FACE_SHELL).contains(c))
                })
                .map(|k| r.weights[k])
                .sum();
            let sq: f64 = (0..3).map(|c| ((colour.rgb[c] - target[c]) as f64).powi(2)).sum();
            if colour.acc > 0.0 && at_face >= FACE_RAY_SHARE * colour.acc {
                self.face_rays += 1.0;
                self.face_sq_error += sq;
            } else {
                self.other_rays += 1.0;
                self.other_sq_error += sq;
            }
        }
    }

    /// The figures so far (`None` before any batch of a box extent).
    pub fn figures(&self) -> Option<FaceFigures> {
        let total = self.face_rays + self.other_rays;
        if total <= 0.0 {
            return None;
        }
        let mean = |sq: f64, n: f64| if n > 0.0 { sq / n } else { 0.0 };
        let (face, other) = (mean(self.face_sq_error, self.face_rays), mean(self.other_sq_error, self.other_rays));
        let error_ratio = if self.face_rays == 0.0 {
            1.0
        } else if other > 0.0 {
            face / other
        } else {
            f64::INFINITY
        };
        Some(FaceFigures { ray_fraction: self.face_rays / total, error_ratio })
    }
}

/// A warning when the figures show content cut off by the box.
pub fn face_pileup_warning(figures: &FaceFigures) -> Option<String> {
    (figures.ray_fraction >= PILEUP_RAY_FRACTION && figures.error_ratio >= PILEUP_ERROR_RATIO).then(|| {
        format!(
            "{:.0}% of the training rays end on a face of the extent's box with {:.1}x the squared error of the \
             others: the scene reaches beyond the box; enlarge `aabb`, or remove it to let the adapter derive the extent",
            100.0 * figures.ray_fraction,
            figures.error_ratio
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::composite::RayColour;
    use crate::render::sampler::Samples;

    /// One sample per ray at `positions[ray]` with weight 1, rendering `colours[ray]`.
    fn batch(positions: &[[f32; 3]], colours: &[[f32; 3]]) -> Rendered {
        let n = positions.len();
        let samples = Samples {
            ray_start: (0..=n as u32).collect(),
            t: vec![1.0; n],
            delta: vec![0.1; n],
            positions: positions.to_vec(),
            directions: vec![[0.0, 0.0, 1.0]; n],
            ..Default::default()
        };
        Rendered {
            samples,
            density: vec![1.0; n],
            rgb: colours.to_vec(),
            weights: vec![1.0; n],
            colours: colours.iter().map(|&rgb| RayColour { rgb, depth: 1.0, acc: 1.0, median_depth: 1.0 }).collect(),
            tape: None,
            n_candidates: n,
            coarse: None,
            seg_input: Vec::new(),
            timing: Default::default(),
        }
    }

    fn unit_box() -> Contraction {
        Contraction::Box { min: [0.0; 3], inv_size: [1.0; 3] }
    }

    #[test]
    fn badly_fitting_rays_on_the_faces_warn_and_well_fitting_walls_do_not() {
        let positions = [[0.5, 0.5, 0.999], [0.5, 0.5, 0.5], [0.4, 0.5, 0.5], [0.5, 0.001, 0.5]];
        let target = [[0.5; 3]; 4];
        let mut cut = FaceMonitor::default();
        cut.observe(&unit_box(), &batch(&positions, &[[0.9; 3], [0.51; 3], [0.49; 3], [0.1; 3]]), &target);
        let f = cut.figures().unwrap();
        assert_eq!(f.ray_fraction, 0.5);
        assert!(face_pileup_warning(&f).is_some(), "{f:?}");
        let mut walls = FaceMonitor::default();
        walls.observe(&unit_box(), &batch(&positions, &[[0.51; 3], [0.52; 3], [0.49; 3], [0.48; 3]]), &target);
        assert!(face_pileup_warning(&walls.figures().unwrap()).is_none());
    }

    #[test]
    fn only_boxes_are_watched() {
        let mut m = FaceMonitor::default();
        let sphere = Contraction::Sphere { center: [0.0; 3], radius: 1.0 };
        m.observe(&sphere, &batch(&[[0.0, 0.0, 0.999]], &[[1.0; 3]]), &[[0.0; 3]]);
        assert!(m.figures().is_none());
    }
}
