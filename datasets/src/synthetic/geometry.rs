//! Analytic ray–primitive intersections. Each returns the nearest hit distance beyond
//! [`T_MIN`] along the (unit) ray direction and the outward unit normal there.

use sos_core::camera::{dot, normalize, Vec3};

/// Hits closer than this are ignored, so secondary rays do not re-hit their own surface.
pub const T_MIN: f32 = 1e-4;

/// Nearest hit distance and outward normal.
pub type Hit = (f32, Vec3);

fn nearest(a: Option<Hit>, b: Option<Hit>) -> Option<Hit> {
    match (a, b) {
        (Some(x), Some(y)) => Some(if x.0 <= y.0 { x } else { y }),
        (x, None) => x,
        (None, y) => y,
    }
}

/// Sphere of `radius` at `centre`.
pub fn sphere(o: Vec3, d: Vec3, centre: Vec3, radius: f32) -> Option<Hit> {
    let oc = [o[0] - centre[0], o[1] - centre[1], o[2] - centre[2]];
    let b = dot(oc, d);
    let c = dot(oc, oc) - radius * radius;
    let disc = b * b - c;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let t = if -b - s > T_MIN { -b - s } else { -b + s };
    if t <= T_MIN {
        return None;
    }
    let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    Some((
        t,
        normalize([p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]]),
    ))
}

/// Horizontal disk at height `y` (centre `(cx, cz)`), facing `ny` (+1 up, −1 down).
fn disk(o: Vec3, d: Vec3, cx: f32, cz: f32, y: f32, radius: f32, ny: f32) -> Option<Hit> {
    if d[1].abs() < 1e-9 {
        return None;
    }
    let t = (y - o[1]) / d[1];
    if t <= T_MIN {
        return None;
    }
    let (x, z) = (o[0] + t * d[0] - cx, o[2] + t * d[2] - cz);
    (x * x + z * z <= radius * radius).then_some((t, [0.0, ny, 0.0]))
}

/// Closed vertical cylinder (axis along +Y) over `y0..y1` with centre `(cx, cz)`.
pub fn cylinder(o: Vec3, d: Vec3, cx: f32, cz: f32, y0: f32, y1: f32, radius: f32) -> Option<Hit> {
    let (ox, oz) = (o[0] - cx, o[2] - cz);
    let a = d[0] * d[0] + d[2] * d[2];
    let mut side = None;
    if a > 1e-12 {
        let b = ox * d[0] + oz * d[2];
        let c = ox * ox + oz * oz - radius * radius;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let s = disc.sqrt();
            for t in [(-b - s) / a, (-b + s) / a] {
                let y = o[1] + t * d[1];
                if t > T_MIN && y >= y0 && y <= y1 {
                    let (x, z) = (ox + t * d[0], oz + t * d[2]);
                    side = Some((t, [x / radius, 0.0, z / radius]));
                    break;
                }
            }
        }
    }
    let caps = nearest(
        disk(o, d, cx, cz, y1, radius, 1.0),
        disk(o, d, cx, cz, y0, radius, -1.0),
    );
    nearest(side, caps)
}

/// Vertical cone standing on `y0` with base `radius` and apex at `y0 + height`.
pub fn cone(o: Vec3, d: Vec3, cx: f32, cz: f32, y0: f32, height: f32, radius: f32) -> Option<Hit> {
    // Points satisfy x² + z² = (k·(apex_y − y))², k = radius / height.
    let k = radius / height;
    let apex = y0 + height;
    let (ox, oz, oy) = (o[0] - cx, o[2] - cz, apex - o[1]);
    let k2 = k * k;
    let a = d[0] * d[0] + d[2] * d[2] - k2 * d[1] * d[1];
    let b = ox * d[0] + oz * d[2] + k2 * oy * d[1];
    let c = ox * ox + oz * oz - k2 * oy * oy;
    let mut side = None;
    if a.abs() > 1e-12 {
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let s = disc.sqrt();
            let (t0, t1) = ((-b - s) / a, (-b + s) / a);
            let (t0, t1) = if t0 <= t1 { (t0, t1) } else { (t1, t0) };
            for t in [t0, t1] {
                let y = o[1] + t * d[1];
                if t > T_MIN && y >= y0 && y <= apex {
                    let (x, z) = (ox + t * d[0], oz + t * d[2]);
                    let r = (x * x + z * z).sqrt().max(1e-9);
                    side = Some((t, normalize([x / r, k, z / r])));
                    break;
                }
            }
        }
    }
    nearest(side, disk(o, d, cx, cz, y0, radius, -1.0))
}

/// Box with half sizes `half`, centred at `centre`, rotated by `yaw` radians about +Y.
pub fn yawed_box(o: Vec3, d: Vec3, centre: Vec3, half: Vec3, yaw: f32) -> Option<Hit> {
    let (s, c) = yaw.sin_cos();
    // World -> box frame is the inverse yaw rotation.
    let to_local = |v: Vec3| [c * v[0] - s * v[2], v[1], s * v[0] + c * v[2]];
    let lo = to_local([o[0] - centre[0], o[1] - centre[1], o[2] - centre[2]]);
    let ld = to_local(d);
    let (mut t_near, mut t_far) = (f32::NEG_INFINITY, f32::INFINITY);
    let (mut axis_near, mut axis_far) = (0, 0);
    for a in 0..3 {
        if ld[a].abs() < 1e-12 {
            if lo[a].abs() > half[a] {
                return None;
            }
            continue;
        }
        let (mut t0, mut t1) = ((-half[a] - lo[a]) / ld[a], (half[a] - lo[a]) / ld[a]);
        if t0 > t1 {
            std::mem::swap(&mut t0, &mut t1);
        }
        if t0 > t_near {
            t_near = t0;
            axis_near = a;
        }
        if t1 < t_far {
            t_far = t1;
            axis_far = a;
        }
    }
    if t_near > t_far || t_far <= T_MIN {
        return None;
    }
    let (t, axis) = if t_near > T_MIN {
        (t_near, axis_near)
    } else {
        (t_far, axis_far)
    };
    let p = lo[axis] + t * ld[axis];
    let mut n_local = [0.0; 3];
    n_local[axis] = p.signum();
    // Box frame -> world is the yaw rotation.
    let n = [
        c * n_local[0] + s * n_local[2],
        n_local[1],
        -s * n_local[0] + c * n_local[2],
    ];
    Some((t, n))
}

/// Exit of a ray starting inside the axis-aligned box `[min, max]`: distance, inward normal
/// and the face index (0/1 = −X/+X wall, 2/3 = floor/ceiling, 4/5 = −Z/+Z wall).
pub fn room_exit(o: Vec3, d: Vec3, min: Vec3, max: Vec3) -> (f32, Vec3, usize) {
    let mut best = (f32::INFINITY, [0.0, 1.0, 0.0], 2);
    for a in 0..3 {
        if d[a].abs() < 1e-12 {
            continue;
        }
        let (plane, face, normal_sign) = if d[a] > 0.0 {
            (max[a], 2 * a + 1, -1.0)
        } else {
            (min[a], 2 * a, 1.0)
        };
        let t = (plane - o[a]) / d[a];
        if t < best.0 {
            let mut n = [0.0; 3];
            n[a] = normal_sign;
            best = (t.max(0.0), n, face);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn primitives_hit_where_expected() {
        let o = [0.0, 0.5, 5.0];
        let d = [0.0, 0.0, -1.0];
        let (t, n) = sphere(o, d, [0.0, 0.5, 0.0], 1.0).unwrap();
        assert!((t - 4.0).abs() < 1e-5 && (n[2] - 1.0).abs() < 1e-5);
        let (t, n) = cylinder(o, d, 0.0, 0.0, 0.0, 1.0, 0.5).unwrap();
        assert!((t - 4.5).abs() < 1e-5 && (n[2] - 1.0).abs() < 1e-5);
        let (t, _) = cone(o, d, 0.0, 0.0, 0.0, 1.0, 1.0).unwrap();
        assert!((t - 4.5).abs() < 1e-5, "{t}");
        let (t, n) = yawed_box(o, d, [0.0, 0.5, 0.0], [0.5, 0.5, 0.5], 0.0).unwrap();
        assert!((t - 4.5).abs() < 1e-5 && (n[2] - 1.0).abs() < 1e-5);
        // A 45° yawed unit cube presents an edge at distance √2/2.
        let (t, _) = yawed_box(
            o,
            d,
            [0.0, 0.5, 0.0],
            [0.5, 0.5, 0.5],
            std::f32::consts::FRAC_PI_4,
        )
        .unwrap();
        assert!((t - (5.0 - 0.5f32.sqrt())).abs() < 1e-4, "{t}");
        // Looking down onto a cylinder hits its top cap.
        let (t, n) = cylinder([0.0, 3.0, 0.0], [0.0, -1.0, 0.0], 0.0, 0.0, 0.0, 1.0, 0.5).unwrap();
        assert!((t - 2.0).abs() < 1e-5 && n[1] > 0.99);
        assert!(sphere(o, [0.0, 1.0, 0.0], [0.0, 0.5, 0.0], 1.0).is_none());
        let (t, n, face) = room_exit([0.0, 1.0, 0.0], d, [-3.0, 0.0, -3.0], [3.0, 3.0, 3.0]);
        assert!((t - 3.0).abs() < 1e-6 && face == 4 && n[2] == 1.0);
    }
}
