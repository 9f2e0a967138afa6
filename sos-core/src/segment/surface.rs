//! Logits at each ray's visible surface (`segment.logits` and `masks.logits = "surface"`): the
//! head runs once per ray that hit something, at its surface point, and its logits are scaled
//! by the ray's opacity, the weight compositing would give them if all of it sat on that
//! surface; empty rays get zero logits. Stage 2 trains through [`SurfacePoints::point_grads`],
//! the transpose of [`SurfacePoints::ray_logits`].

use crate::camera::Vec3;

/// The rays that hit something, their surface points and their opacities.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfacePoints {
    rays: Vec<usize>,
    positions: Vec<Vec3>,
    opacities: Vec<f32>,
}

impl SurfacePoints {
    /// From each ray's surface point (`None` for an empty ray) and opacity.
    pub fn new(points: &[Option<Vec3>], opacities: &[f32]) -> SurfacePoints {
        let rays: Vec<usize> = (0..points.len()).filter(|&i| points[i].is_some()).collect();
        SurfacePoints {
            positions: rays.iter().filter_map(|&i| points[i]).collect(),
            opacities: rays.iter().map(|&i| opacities[i]).collect(),
            rays,
        }
    }

    /// Where the head runs: one point per ray that hit, in ray order.
    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }

    /// `[n_rays, d]` logits from the head's `[points, d]` `values`: each hit ray's opacity
    /// times the values at its point, zero for the other rays.
    pub fn ray_logits(&self, values: &[f32], n_rays: usize, d: usize) -> Vec<f32> {
        let mut out = vec![0.0; n_rays * d];
        for ((&ray, &opacity), value) in self.rays.iter().zip(&self.opacities).zip(values.chunks_exact(d)) {
            for (o, v) in out[ray * d..(ray + 1) * d].iter_mut().zip(value) {
                *o = opacity * v;
            }
        }
        out
    }

    /// The gradient at each point (`[points, d]`) from that of its ray's logits
    /// (`[n_rays, d]`).
    pub fn point_grads(&self, ray_grad: &[f32], d: usize) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.rays.len() * d);
        for (&ray, &opacity) in self.rays.iter().zip(&self.opacities) {
            out.extend(ray_grad[ray * d..(ray + 1) * d].iter().map(|g| opacity * g));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logits_scale_by_opacity_and_their_gradient_is_the_transpose() {
        // Rays 0 and 2 of 4 hit, with opacities 0.5 and 0.75 (products exact in f32); two
        // channels.
        let points = [Some([1.0, 0.0, 0.0]), None, Some([0.0, 2.0, 0.0]), None];
        let surface = SurfacePoints::new(&points, &[0.5, 0.1, 0.75, 0.0]);
        assert_eq!(surface.positions(), [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]);
        let values = [1.0, -2.0, 3.0, 4.0];
        let logits = surface.ray_logits(&values, 4, 2);
        assert_eq!(logits, [0.5, -1.0, 0.0, 0.0, 2.25, 3.0, 0.0, 0.0]);
        // ⟨ray_logits(v), g⟩ = ⟨v, point_grads(g)⟩ for any v and g: the backward is exact.
        let g = [0.3, -0.7, 5.0, 5.0, 1.1, 0.2, -9.0, 2.0];
        let point_grads = surface.point_grads(&g, 2);
        let forward: f32 = logits.iter().zip(&g).map(|(a, b)| a * b).sum();
        let backward: f32 = values.iter().zip(&point_grads).map(|(a, b)| a * b).sum();
        assert!((forward - backward).abs() < 1e-5, "{forward} against {backward}");
    }
}
