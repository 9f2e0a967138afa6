//! Camera-pose arithmetic shared by the loaders and the generator, in `f64`: the LLFF average
//! pose, recentring and the spiral render path of the reference `load_llff.py`.
//!
//! A [`Pose`] is a camera-to-world transform `[R | t]` stored as three rows, with the columns of
//! `R` being the camera's (right, up, back) axes (OpenGL convention).

use sos_core::camera::Camera;

/// Camera-to-world transform, 3 rows of `[R | t]`, OpenGL camera axes.
pub type Pose = [[f64; 4]; 3];

/// 3-vector in `f64`.
pub type V3 = [f64; 3];

/// Column `c` of a pose (0 = right, 1 = up, 2 = back, 3 = centre).
pub fn column(p: &Pose, c: usize) -> V3 {
    [p[0][c], p[1][c], p[2][c]]
}

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(v: V3) -> V3 {
    let n = dot(v, v).sqrt();
    if n > 0.0 {
        [v[0] / n, v[1] / n, v[2] / n]
    } else {
        v
    }
}

/// LLFF's `viewmatrix(z, up, pos)`: back axis `z`, right = normalize(up × z),
/// up = normalize(z × right), centre `pos`.
pub fn view_matrix(z: V3, up: V3, pos: V3) -> Pose {
    let z = normalize(z);
    let x = normalize(cross(up, z));
    let y = normalize(cross(z, x));
    let mut p = [[0.0; 4]; 3];
    for r in 0..3 {
        p[r] = [x[r], y[r], z[r], pos[r]];
    }
    p
}

/// LLFF's `poses_avg`: mean centre, normalised sum of back axes, summed up axes.
/// Returns the identity for an empty slice.
pub fn poses_avg(poses: &[Pose]) -> Pose {
    if poses.is_empty() {
        return IDENTITY;
    }
    let n = poses.len() as f64;
    let mut centre = [0.0; 3];
    let mut z = [0.0; 3];
    let mut up = [0.0; 3];
    for p in poses {
        for r in 0..3 {
            centre[r] += p[r][3] / n;
            z[r] += p[r][2];
            up[r] += p[r][1];
        }
    }
    view_matrix(z, up, centre)
}

/// The identity pose.
pub const IDENTITY: Pose = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
];

/// `a · b` as 4x4 transforms with an implicit `[0 0 0 1]` bottom row.
pub fn compose(a: &Pose, b: &Pose) -> Pose {
    let mut out = [[0.0; 4]; 3];
    for r in 0..3 {
        for c in 0..4 {
            let mut v: f64 = (0..3).map(|k| a[r][k] * b[k][c]).sum();
            if c == 3 {
                v += a[r][3];
            }
            out[r][c] = v;
        }
    }
    out
}

/// Inverse of a pose whose rotation is orthonormal (transpose rotation, rotate back the
/// translation). `poses_avg` always builds such a pose.
pub fn invert_rigid(p: &Pose) -> Pose {
    let mut out = [[0.0; 4]; 3];
    for r in 0..3 {
        for c in 0..3 {
            out[r][c] = p[c][r];
        }
        out[r][3] = -(0..3).map(|k| p[k][r] * p[k][3]).sum::<f64>();
    }
    out
}

/// LLFF's `recenter_poses`: expresses every pose in the frame of their average pose, so the
/// mean camera becomes the identity. Returns the recentred poses and the average pose used.
pub fn recenter(poses: &[Pose]) -> (Vec<Pose>, Pose) {
    let avg = poses_avg(poses);
    let inv = invert_rigid(&avg);
    (poses.iter().map(|p| compose(&inv, p)).collect(), avg)
}

/// LLFF's spiral render path (`render_path_spiral` with the settings of `load_llff_data`):
/// `n` poses over `rots` turns around `c2w`, radii `rads` along its (right, up, back) axes,
/// z oscillating at `zrate` of the angular rate, every camera looking at the point `focal`
/// in front of `c2w`, up hint `up`.
pub fn spiral_path(
    c2w: &Pose,
    up: V3,
    rads: V3,
    focal: f64,
    zrate: f64,
    rots: f64,
    n: usize,
) -> Vec<Pose> {
    let apply = |v: [f64; 4]| -> V3 {
        let mut out = [0.0; 3];
        for r in 0..3 {
            out[r] = (0..4).map(|k| c2w[r][k] * v[k]).sum();
        }
        out
    };
    let target = apply([0.0, 0.0, -focal, 1.0]);
    (0..n)
        .map(|i| {
            // np.linspace(0, 2π·rots, n + 1)[:-1]
            let theta = 2.0 * std::f64::consts::PI * rots * i as f64 / n as f64;
            let c = apply([
                theta.cos() * rads[0],
                -theta.sin() * rads[1],
                -(theta * zrate).sin() * rads[2],
                1.0,
            ]);
            let z = [c[0] - target[0], c[1] - target[1], c[2] - target[2]];
            view_matrix(z, up, c)
        })
        .collect()
}

/// The LLFF forward-facing spiral of a recentred capture: radii = 90th percentile of |t| per
/// axis (numpy's linear interpolation), focus depth `1 / (0.25 / (0.9·near) + 0.75 / (5·far))`,
/// 2 turns, zrate 0.5, up = normalised sum of the up axes.
pub fn llff_spiral(poses: &[Pose], near: f64, far: f64, n: usize) -> Vec<Pose> {
    if poses.is_empty() || n == 0 {
        return Vec::new();
    }
    let c2w = poses_avg(poses);
    let mut up = [0.0; 3];
    for p in poses {
        (0..3).for_each(|r| up[r] += p[r][1]);
    }
    let up = normalize(up);
    let (close, inf) = (0.9 * near, 5.0 * far);
    let dt = 0.75;
    let focal = 1.0 / ((1.0 - dt) / close + dt / inf);
    let mut rads = [0.0; 3];
    for (a, rad) in rads.iter_mut().enumerate() {
        let mut v: Vec<f64> = poses.iter().map(|p| p[a][3].abs()).collect();
        *rad = percentile(&mut v, 90.0);
    }
    spiral_path(&c2w, up, rads, focal, 0.5, 2.0, n)
}

/// numpy's default (linear) percentile.
fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    let pos = q / 100.0 * (v.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    v[lo] + (v[hi] - v[lo]) * (pos - lo as f64)
}

/// The camera of a pose with centred principal point and square pixels.
pub fn to_camera(p: &Pose, width: u32, height: u32, focal: f64) -> Camera {
    let cam_to_world = p.map(|row| row.map(|v| v as f32));
    Camera {
        width,
        height,
        fx: focal as f32,
        fy: focal as f32,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
        cam_to_world,
    }
}

/// The pose of a camera, widened to `f64`.
pub fn from_camera(cam: &Camera) -> Pose {
    cam.cam_to_world.map(|row| row.map(|v| v as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Pose, b: &Pose, tol: f64) -> bool {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .all(|(x, y)| (x - y).abs() < tol)
    }

    #[test]
    fn recentring_makes_the_average_pose_the_identity() {
        let poses = [
            view_matrix([0.1, 0.2, 1.0], [0.0, 1.0, 0.1], [1.0, 2.0, 3.0]),
            view_matrix([-0.1, 0.1, 1.0], [0.1, 1.0, 0.0], [1.5, 2.2, 2.9]),
            view_matrix([0.0, -0.1, 1.0], [0.0, 1.0, -0.1], [0.7, 1.8, 3.2]),
        ];
        let (rec, avg) = recenter(&poses);
        assert!(close(&poses_avg(&rec), &IDENTITY, 1e-12));
        // Undoing the recentring gives the inputs back.
        for (r, p) in rec.iter().zip(&poses) {
            assert!(close(&compose(&avg, r), p, 1e-12));
        }
    }

    #[test]
    fn spiral_looks_at_the_focus_point() {
        let path = llff_spiral(&[IDENTITY], 1.0, 10.0, 12);
        assert_eq!(path.len(), 12);
        let focal = 1.0 / (0.25 / 0.9 + 0.75 / 50.0);
        for p in &path {
            let cam = to_camera(p, 10, 10, 5.0);
            cam.validate().unwrap();
            let px = cam.project([0.0, 0.0, -focal as f32]).unwrap();
            assert!(
                (px[0] - 5.0).abs() < 1e-3 && (px[1] - 5.0).abs() < 1e-3,
                "{px:?}"
            );
        }
    }
}
