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
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
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
pub const IDENTITY: Pose = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];

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
pub fn spiral_path(c2w: &Pose, up: V3, rads: V3, focal: f64, zrate: f64, rots: f64, n: usize) -> Vec<Pose> {
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
            let c = apply([theta.cos() * rads[0], -theta.sin() * rads[1], -(theta * zrate).sin() * rads[2], 1.0]);
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
pub(crate) fn percentile(v: &mut [f64], q: f64) -> f64 {
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

/// Poses after the reference `spherify_poses`.
#[derive(Debug, Clone, PartialEq)]
pub struct Spherified {
    /// The input poses in the new frame.
    pub poses: Vec<Pose>,
    /// The reference's render circle: `n` cameras (endpoints included, as `np.linspace`) at the
    /// cameras' mean height, looking at the origin.
    pub path: Vec<Pose>,
    /// Scale applied to translations (and to be applied to depth bounds).
    pub scale: f64,
}

/// LLFF's `spherify_poses` for 360° captures: the new origin is the point closest (least
/// squares) to every camera's viewing axis, the new +Z the mean direction from it to the
/// cameras, and the scale puts the cameras at RMS distance 1. `None` when the viewing axes are
/// (nearly) parallel, so no such point exists.
pub fn spherify(poses: &[Pose], n: usize) -> Option<Spherified> {
    if poses.is_empty() {
        return None;
    }
    let m = poses.len() as f64;
    let mut a_mean = [[0.0; 3]; 3];
    let mut b_mean = [0.0; 3];
    for p in poses {
        let (d, o) = (column(p, 2), column(p, 3));
        let mut a = [[0.0; 3]; 3];
        for r in 0..3 {
            for c in 0..3 {
                a[r][c] = if r == c { 1.0 } else { 0.0 } - d[r] * d[c];
            }
        }
        // The reference averages AᵀA and b = −A·o.
        let ata = {
            let at = transpose3(&a);
            let mut out = [[0.0; 3]; 3];
            for r in 0..3 {
                for c in 0..3 {
                    out[r][c] = (0..3).map(|k| at[r][k] * a[k][c]).sum();
                }
            }
            out
        };
        let ao = mul3v(&a, o);
        for r in 0..3 {
            b_mean[r] -= ao[r] / m;
            for c in 0..3 {
                a_mean[r][c] += ata[r][c] / m;
            }
        }
    }
    // Parallel axes leave A singular up to rounding; demand a well-conditioned system.
    let det = det3(&a_mean);
    if det.is_nan() || det.abs() <= 1e-6 {
        return None;
    }
    let inv = invert3(&a_mean)?;
    let cb = mul3v(&inv, b_mean);
    let center = [-cb[0], -cb[1], -cb[2]];
    let mut up = [0.0; 3];
    for p in poses {
        (0..3).for_each(|k| up[k] += (p[k][3] - center[k]) / m);
    }
    let vec0 = normalize(up);
    let vec1 = normalize(cross([0.1, 0.2, 0.3], vec0));
    let vec2 = normalize(cross(vec0, vec1));
    let mut c2w = [[0.0; 4]; 3];
    for r in 0..3 {
        c2w[r] = [vec1[r], vec2[r], vec0[r], center[r]];
    }
    let inv_c2w = invert_rigid(&c2w);
    let mut reset: Vec<Pose> = poses.iter().map(|p| compose(&inv_c2w, p)).collect();
    let rad = (reset.iter().map(|p| dot(column(p, 3), column(p, 3))).sum::<f64>() / m).sqrt();
    if !(rad > 0.0 && rad.is_finite()) {
        return None;
    }
    let scale = 1.0 / rad;
    for p in &mut reset {
        (0..3).for_each(|r| p[r][3] *= scale);
    }
    let zh = reset.iter().map(|p| p[2][3]).sum::<f64>() / m;
    let radcircle = (1.0 - zh * zh).max(0.0).sqrt();
    let path = (0..n)
        .map(|i| {
            let th = if n > 1 { 2.0 * std::f64::consts::PI * i as f64 / (n - 1) as f64 } else { 0.0 };
            let origin = [radcircle * th.cos(), radcircle * th.sin(), zh];
            let up = [0.0, 0.0, -1.0];
            let v2 = normalize(origin);
            let v0 = normalize(cross(v2, up));
            let v1 = normalize(cross(v2, v0));
            let mut p = [[0.0; 4]; 3];
            for r in 0..3 {
                p[r] = [v0[r], v1[r], v2[r], origin[r]];
            }
            p
        })
        .collect();
    Some(Spherified { poses: reset, path, scale })
}

/// 3x3 matrix in `f64`, rows.
pub type M3 = [[f64; 3]; 3];

/// Transpose of a 3x3 matrix.
pub fn transpose3(m: &M3) -> M3 {
    let mut t = [[0.0; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            t[r][c] = m[c][r];
        }
    }
    t
}

/// `m · v`.
pub fn mul3v(m: &M3, v: V3) -> V3 {
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
}

/// Determinant of a 3x3 matrix.
pub fn det3(m: &M3) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Inverse of a 3x3 matrix (adjugate over determinant); `None` when it is singular or not
/// finite.
pub fn invert3(m: &M3) -> Option<M3> {
    let det = det3(m);
    let scale = m.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
    if !det.is_finite() || scale == 0.0 || det.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let c = |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let adj = [
        [c(1, 2, 1, 2), -c(0, 2, 1, 2), c(0, 1, 1, 2)],
        [-c(1, 2, 0, 2), c(0, 2, 0, 2), -c(0, 1, 0, 2)],
        [c(1, 2, 0, 1), -c(0, 2, 0, 1), c(0, 1, 0, 1)],
    ];
    Some(adj.map(|row| row.map(|v| v / det)))
}

/// Why a camera-to-world rotation is unusable (`None` when it is a proper rotation to 1e-3).
pub fn rotation_problem(r: &M3) -> Option<String> {
    if r.iter().flatten().any(|v| !v.is_finite()) {
        return Some("rotation has NaN or infinite entries".into());
    }
    for a in 0..3 {
        for b in 0..3 {
            let d: f64 = (0..3).map(|k| r[k][a] * r[k][b]).sum();
            let want = if a == b { 1.0 } else { 0.0 };
            if (d - want).abs() > 1e-3 {
                return Some("rotation is not orthonormal (singular or scaled pose)".into());
            }
        }
    }
    if det3(r) < 0.0 {
        return Some("rotation is a reflection (determinant −1); flip one camera axis".into());
    }
    None
}

/// Pose (OpenGL axes) from a camera-to-world rotation whose columns are OpenCV camera axes
/// (right, down, forward) and the camera centre.
pub fn from_opencv(r_c2w: &M3, centre: V3) -> Pose {
    let mut p = [[0.0; 4]; 3];
    for r in 0..3 {
        p[r] = [r_c2w[r][0], -r_c2w[r][1], -r_c2w[r][2], centre[r]];
    }
    p
}

/// The camera-to-world rotation in OpenCV axes and the centre of a pose.
pub fn to_opencv(p: &Pose) -> (M3, V3) {
    let mut r = [[0.0; 3]; 3];
    for k in 0..3 {
        r[k] = [p[k][0], -p[k][1], -p[k][2]];
    }
    (r, column(p, 3))
}

/// Pose from an OpenCV world-to-camera transform `x_cam = R x_world + t` (COLMAP, BlendedMVS).
/// The rotation is inverted exactly (not transposed), so a pose written by
/// [`to_world_to_camera`] comes back to rounding. `None` when `R` is singular.
pub fn from_world_to_camera(r: &M3, t: V3) -> Option<Pose> {
    let r_c2w = invert3(r)?;
    let c = mul3v(&r_c2w, t);
    Some(from_opencv(&r_c2w, [-c[0], -c[1], -c[2]]))
}

/// The OpenCV world-to-camera `(R, t)` of a pose (inverse of [`from_world_to_camera`]).
pub fn to_world_to_camera(p: &Pose) -> (M3, V3) {
    let (r_c2w, c) = to_opencv(p);
    let r = transpose3(&r_c2w);
    let rc = mul3v(&r, c);
    (r, [-rc[0], -rc[1], -rc[2]])
}

/// Rotation matrix of a unit quaternion `(w, x, y, z)` (normalised first; COLMAP's order).
pub fn rotation_from_quaternion(q: [f64; 4]) -> M3 {
    let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Unit quaternion `(w, x, y, z)` with `w ≥ 0` of a rotation matrix (Shepperd's method).
pub fn quaternion_from_rotation(m: &M3) -> [f64; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = 2.0 * (tr + 1.0).sqrt();
        [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = 2.0 * (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt();
        [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    } else if m[1][1] > m[2][2] {
        let s = 2.0 * (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt();
        [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    } else {
        let s = 2.0 * (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt();
        [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
    q.map(|v| sign * v / n)
}

/// A camera with general pinhole intrinsics.
#[allow(clippy::too_many_arguments)]
pub fn to_camera_general(p: &Pose, width: u32, height: u32, fx: f64, fy: f64, cx: f64, cy: f64) -> Camera {
    Camera {
        width,
        height,
        fx: fx as f32,
        fy: fy as f32,
        cx: cx as f32,
        cy: cy as f32,
        cam_to_world: p.map(|row| row.map(|v| v as f32)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Pose, b: &Pose, tol: f64) -> bool {
        a.iter().flatten().zip(b.iter().flatten()).all(|(x, y)| (x - y).abs() < tol)
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
    fn conversions_invert_each_other() {
        let p = view_matrix([0.3, -0.2, 1.0], [0.1, 1.0, 0.0], [1.5, -2.0, 0.7]);
        let (r, t) = to_world_to_camera(&p);
        assert!(close(&from_world_to_camera(&r, t).unwrap(), &p, 1e-12));
        let q = quaternion_from_rotation(&r);
        let rq = rotation_from_quaternion(q);
        assert!(r.iter().flatten().zip(rq.iter().flatten()).all(|(a, b)| (a - b).abs() < 1e-12));
        // The OpenCV camera looks along +z: the OpenGL back axis is its negation.
        let (rc, c) = to_opencv(&p);
        assert!((0..3).all(|k| (rc[k][2] + p[k][2]).abs() < 1e-15 && c[k] == p[k][3]));
        assert!(rotation_problem(&rc).is_none());
        let mut refl = rc;
        (0..3).for_each(|k| refl[k][0] = -refl[k][0]);
        assert!(rotation_problem(&refl).unwrap().contains("reflection"));
        assert!(invert3(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]]).is_none());
        // Quaternions of the other branches of Shepperd's method.
        for m in [
            [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]],
            [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
            [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
        ] {
            let back = rotation_from_quaternion(quaternion_from_rotation(&m));
            assert!(m.iter().flatten().zip(back.iter().flatten()).all(|(a, b)| (a - b).abs() < 1e-12));
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
            assert!((px[0] - 5.0).abs() < 1e-3 && (px[1] - 5.0).abs() < 1e-3, "{px:?}");
        }
    }
}
