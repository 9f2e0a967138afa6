//! Framing: how far a camera must stand for the foreground object to fill a chosen share of
//! the view height, judged from points outlining the object's silhouette.

use sos_core::camera::{Camera, Vec3};

/// Never let the object span more than this share of the view width.
const MAX_WIDTH_SHARE: f32 = 0.8;

/// The object as framed by the cameras.
#[derive(Debug, Clone)]
pub struct Framing {
    /// Points outlining the object's silhouette.
    pub outline: Vec<Vec3>,
    /// Centre of the object's bounding box.
    pub centre: Vec3,
    /// Radius of the bounding sphere about `centre`.
    pub radius: f32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Focal length in pixels (square pixels, centred principal point).
    pub focal: f32,
}

impl Framing {
    /// A camera at `eye` looking at `target`.
    pub fn camera(&self, eye: Vec3, target: Vec3) -> Camera {
        Camera::look_at(eye, target, [0.0, 1.0, 0.0], self.width, self.height, self.focal)
    }

    /// Shares of the view height and width the object spans seen from `cam` (infinite when
    /// part of it is behind the camera).
    pub fn shares(&self, cam: &Camera) -> [f32; 2] {
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for &p in &self.outline {
            let Some(px) = cam.project(p) else { return [f32::INFINITY; 2] };
            for k in 0..2 {
                lo[k] = lo[k].min(px[k]);
                hi[k] = hi[k].max(px[k]);
            }
        }
        [(hi[1] - lo[1]) / self.height as f32, (hi[0] - lo[0]) / self.width as f32]
    }

    /// The distance along unit direction `dir` from `target` at which the object spans `share`
    /// of the view height (or [`MAX_WIDTH_SHARE`] of its width, whichever is reached first).
    pub fn distance(&self, target: Vec3, dir: Vec3, share: f32) -> f32 {
        let fill = |d: f32| {
            let eye = [target[0] + d * dir[0], target[1] + d * dir[1], target[2] + d * dir[2]];
            let [v, h] = self.shares(&self.camera(eye, target));
            (v / share).max(h / MAX_WIDTH_SHARE)
        };
        // The fill shrinks with distance; bisect on a log scale between touching the bounding
        // sphere and far away.
        let (mut near, mut far) = (1.02 * self.radius + 0.05, 400.0 * self.radius + 1.0);
        for _ in 0..40 {
            let mid = (near * far).sqrt();
            if fill(mid) > 1.0 {
                near = mid;
            } else {
                far = mid;
            }
        }
        far
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::shape::Shape;
    use sos_core::camera::normalize;

    #[test]
    fn distance_gives_the_requested_share() {
        let sphere = Shape::Sphere { centre: [0.0, 0.5, 0.0], radius: 0.5 };
        let framing = Framing {
            outline: sphere.silhouette(),
            centre: [0.0, 0.5, 0.0],
            radius: 0.5,
            width: 160,
            height: 120,
            focal: 140.0,
        };
        for (dir, share) in [([0.0, 0.3, 1.0], 0.3), ([1.0, 1.0, 0.2], 0.5), ([0.2, 0.05, -1.0], 0.15)] {
            let dir = normalize(dir);
            let d = framing.distance(framing.centre, dir, share);
            let eye = [d * dir[0], 0.5 + d * dir[1], d * dir[2]];
            let [v, h] = framing.shares(&framing.camera(eye, framing.centre));
            assert!((v - share).abs() < 1e-3 && h <= MAX_WIDTH_SHARE, "{v} {h} for {share}");
            // A sphere of radius 0.5 spans 2·f·tan(asin(r/d)) pixels: within a few percent.
            let exact = 2.0 * 140.0 * (0.5f32 / d).asin().tan() / 120.0;
            assert!((v / exact - 1.0).abs() < 0.03, "{v} vs exact {exact}");
        }
    }
}
