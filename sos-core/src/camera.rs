//! Pinhole cameras and the one place where camera conventions are converted.
//!
//! Internally every camera is stored in the OpenGL convention used by NeRF: in camera space
//! +X points right, +Y up and the camera looks along −Z. Pixel `(col, row)` has its centre at
//! `(col + 0.5, row + 0.5)`, with row 0 at the top of the image.

use serde::{Deserialize, Serialize};

/// A 3-vector.
pub type Vec3 = [f32; 3];

/// Axis conventions of camera-to-world rotations found in the wild.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CameraConvention {
    /// +X right, +Y up, looking along −Z (NeRF, Blender, nerfstudio).
    OpenGl,
    /// +X right, +Y down, looking along +Z (COLMAP, OpenCV, BlendedMVS, NeRF++).
    OpenCv,
    /// LLFF's `poses_bounds.npy` columns: (down, right, back).
    Llff,
}

impl CameraConvention {
    /// Converts a camera-to-world rotation whose columns are this convention's camera axes into
    /// the internal OpenGL convention.
    pub fn to_opengl(self, rotation: [[f32; 3]; 3]) -> [[f32; 3]; 3] {
        let col = |m: &[[f32; 3]; 3], c: usize| [m[0][c], m[1][c], m[2][c]];
        let (x, y, z) = match self {
            CameraConvention::OpenGl => (col(&rotation, 0), col(&rotation, 1), col(&rotation, 2)),
            CameraConvention::OpenCv => (col(&rotation, 0), neg(col(&rotation, 1)), neg(col(&rotation, 2))),
            // (down, right, back) -> (right, up, back) = [c1, -c0, c2], as LLFF's loader does.
            CameraConvention::Llff => (col(&rotation, 1), neg(col(&rotation, 0)), col(&rotation, 2)),
        };
        let mut out = [[0.0; 3]; 3];
        for r in 0..3 {
            out[r] = [x[r], y[r], z[r]];
        }
        out
    }
}

fn neg(v: Vec3) -> Vec3 {
    [-v[0], -v[1], -v[2]]
}

/// A pinhole camera with its pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along X in pixels.
    pub fx: f32,
    /// Focal length along Y in pixels.
    pub fy: f32,
    /// Principal point X in pixels.
    pub cx: f32,
    /// Principal point Y in pixels.
    pub cy: f32,
    /// Camera-to-world transform (rotation | translation), rows, OpenGL axes.
    pub cam_to_world: [[f32; 4]; 3],
}

impl Camera {
    /// Camera centre in world space.
    pub fn origin(&self) -> Vec3 {
        [self.cam_to_world[0][3], self.cam_to_world[1][3], self.cam_to_world[2][3]]
    }

    /// Unit world-space direction of the ray through image point `(x, y)` in pixels
    /// (pixel centres at `+0.5`).
    pub fn direction(&self, x: f32, y: f32) -> Vec3 {
        let d_cam = [(x - self.cx) / self.fx, -(y - self.cy) / self.fy, -1.0];
        normalize(self.rotate(d_cam))
    }

    /// Rotates a camera-space vector into world space.
    pub fn rotate(&self, v: Vec3) -> Vec3 {
        let m = &self.cam_to_world;
        [
            m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
            m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
            m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
        ]
    }

    /// Viewing axis (the direction the camera looks at) in world space.
    pub fn forward(&self) -> Vec3 {
        normalize(self.rotate([0.0, 0.0, -1.0]))
    }

    /// The same camera for an image scaled to `width` x `height`.
    pub fn resized(&self, width: u32, height: u32) -> Camera {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Camera {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            cam_to_world: self.cam_to_world,
        }
    }

    /// Projects a world point to pixel coordinates; `None` when it is behind the camera.
    pub fn project(&self, p: Vec3) -> Option<[f32; 2]> {
        let m = &self.cam_to_world;
        let d = [p[0] - m[0][3], p[1] - m[1][3], p[2] - m[2][3]];
        // Inverse rotation = transpose.
        let xc = m[0][0] * d[0] + m[1][0] * d[1] + m[2][0] * d[2];
        let yc = m[0][1] * d[0] + m[1][1] * d[1] + m[2][1] * d[2];
        let zc = m[0][2] * d[0] + m[1][2] * d[1] + m[2][2] * d[2];
        if zc >= -1e-6 {
            return None;
        }
        Some([self.cx + self.fx * xc / -zc, self.cy - self.fy * yc / -zc])
    }

    /// Builds a camera at `eye` looking at `target` with the given world `up` hint.
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3, width: u32, height: u32, focal: f32) -> Camera {
        let back = normalize(sub(eye, target));
        let right = normalize(cross(up, back));
        let true_up = cross(back, right);
        let mut cam_to_world = [[0.0; 4]; 3];
        for r in 0..3 {
            cam_to_world[r] = [right[r], true_up[r], back[r], eye[r]];
        }
        Camera { width, height, fx: focal, fy: focal, cx: width as f32 / 2.0, cy: height as f32 / 2.0, cam_to_world }
    }

    /// Checks that the pose is finite and the rotation a proper rotation (orthonormal, not a
    /// reflection); returns what is wrong.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!("zero image size {}x{}", self.width, self.height));
        }
        let finite = self.cam_to_world.iter().flatten().all(|v| v.is_finite())
            && [self.fx, self.fy, self.cx, self.cy].iter().all(|v| v.is_finite());
        if !finite {
            return Err("pose or intrinsics contain NaN or infinity".into());
        }
        // Below a thousandth of a pixel (a field of view of practically 180°) the ray
        // directions of the image's pixels overflow.
        if self.fx < MIN_FOCAL || self.fy < MIN_FOCAL {
            return Err(format!("focal length must be at least {MIN_FOCAL} px, got {} {}", self.fx, self.fy));
        }
        let m = &self.cam_to_world;
        for a in 0..3 {
            for b in 0..3 {
                let dot: f32 = (0..3).map(|r| m[r][a] * m[r][b]).sum();
                let want = if a == b { 1.0 } else { 0.0 };
                if (dot - want).abs() > 1e-3 {
                    return Err("rotation is not orthonormal (singular or scaled pose)".into());
                }
            }
        }
        // An orthonormal matrix with determinant −1 mirrors every ray: one axis was flipped
        // (often in a conversion between OpenCV and OpenGL axes).
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        if det < 0.0 {
            return Err("rotation is a reflection (determinant −1); flip one camera axis".into());
        }
        Ok(())
    }
}

/// Smallest focal length in pixels [`Camera::validate`] accepts.
pub const MIN_FOCAL: f32 = 1e-3;

/// Vector difference.
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Vector sum.
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// `a + s * b`.
pub fn axpy(a: Vec3, s: f32, b: Vec3) -> Vec3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}

/// Dot product.
pub fn dot(a: Vec3, b: Vec3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `s * v`.
pub fn scale(v: Vec3, s: f32) -> Vec3 {
    [v[0] * s, v[1] * s, v[2] * s]
}

/// Cross product.
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// Euclidean length.
pub fn norm(v: Vec3) -> f32 {
    dot(v, v).sqrt()
}

/// Unit vector (zero stays zero).
pub fn normalize(v: Vec3) -> Vec3 {
    let n = norm(v);
    if n > 0.0 {
        [v[0] / n, v[1] / n, v[2] / n]
    } else {
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_projects_target_to_centre() {
        let cam = Camera::look_at([0.0, -3.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 64, 48, 50.0);
        let p = cam.project([0.0, 0.0, 0.0]).unwrap();
        assert!((p[0] - 32.0).abs() < 1e-4 && (p[1] - 24.0).abs() < 1e-4);
        cam.validate().unwrap();
        // The ray through a projected point goes back through the point.
        let q = [0.3, 0.2, -0.1];
        let px = cam.project(q).unwrap();
        let d = cam.direction(px[0], px[1]);
        let to_q = normalize(sub(q, cam.origin()));
        assert!(dot(d, to_q) > 1.0 - 1e-6);
    }

    #[test]
    fn a_mirrored_pose_is_refused() {
        let mut cam = Camera::look_at([0.0, -3.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 64, 48, 50.0);
        cam.validate().unwrap();
        // Negating one axis keeps the rotation orthonormal but mirrors every ray.
        for r in 0..3 {
            cam.cam_to_world[r][2] = -cam.cam_to_world[r][2];
        }
        let err = cam.validate().unwrap_err();
        assert!(err.contains("reflection"), "{err}");
    }

    #[test]
    fn conventions_agree_on_the_viewing_axis() {
        // An OpenCV camera looking along world +Y: z_cv = +Y, y_cv = -Z (down), x_cv = +X.
        let cv = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]];
        let gl = CameraConvention::OpenCv.to_opengl(cv);
        // OpenGL looks along -z_gl, which must be world +Y.
        assert_eq!([-gl[0][2], -gl[1][2], -gl[2][2]], [0.0, 1.0, 0.0]);
        // LLFF (down, right, back) of the same camera: down = -Z, right = +X, back = -Y.
        let llff = [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]];
        assert_eq!(CameraConvention::Llff.to_opengl(llff), gl);
    }
}
