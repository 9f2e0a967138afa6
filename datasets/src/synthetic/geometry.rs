//! Analytic ray–primitive intersections. Each returns the nearest hit distance beyond
//! [`T_MIN`] along the (unit) ray direction and the outward unit normal there.

use sos_core::camera::{dot, normalize, Vec3};

use super::roots::smallest_root_in;

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
    Some((t, normalize([p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]])))
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
    let caps = nearest(disk(o, d, cx, cz, y1, radius, 1.0), disk(o, d, cx, cz, y0, radius, -1.0));
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
    let (t, axis) = if t_near > T_MIN { (t_near, axis_near) } else { (t_far, axis_far) };
    let p = lo[axis] + t * ld[axis];
    let mut n_local = [0.0; 3];
    n_local[axis] = p.signum();
    // Box frame -> world is the yaw rotation.
    let n = [c * n_local[0] + s * n_local[2], n_local[1], -s * n_local[0] + c * n_local[2]];
    Some((t, n))
}

/// Torus lying flat (axis +Y) at `centre`: a tube of radius `minor` around the horizontal circle
/// of radius `major`.
pub fn torus(o: Vec3, d: Vec3, centre: Vec3, major: f32, minor: f32) -> Option<Hit> {
    let oc = [(o[0] - centre[0]) as f64, (o[1] - centre[1]) as f64, (o[2] - centre[2]) as f64];
    let d = [d[0] as f64, d[1] as f64, d[2] as f64];
    let (big, small) = (major as f64, minor as f64);
    // Only the stretch of the ray inside the bounding sphere and the slab |y| ≤ minor can hit.
    let bound = big + small;
    let b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2];
    let disc = b * b - (oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - bound * bound);
    if disc < 0.0 {
        return None;
    }
    let (mut t_in, mut t_out) = (-b - disc.sqrt(), -b + disc.sqrt());
    if d[1].abs() > 1e-12 {
        let (ta, tb) = ((-small - oc[1]) / d[1], (small - oc[1]) / d[1]);
        t_in = t_in.max(ta.min(tb));
        t_out = t_out.min(ta.max(tb));
    } else if oc[1].abs() > small {
        return None;
    }
    if t_out <= T_MIN as f64 || t_in > t_out {
        return None;
    }
    // Solve from the entry point: the quartic's coefficients grow with the fourth power of the
    // distance, so a nearby origin keeps its roots accurate.
    let t0 = t_in.max(0.0);
    let p = [oc[0] + t0 * d[0], oc[1] + t0 * d[1], oc[2] + t0 * d[2]];
    // (|p + s d|² + R² − r²)² = 4R² ((px + s dx)² + (pz + s dz)²), with |d| = 1.
    let n = p[0] * d[0] + p[1] * d[1] + p[2] * d[2];
    let k = p[0] * p[0] + p[1] * p[1] + p[2] * p[2] + big * big - small * small;
    let a = d[0] * d[0] + d[2] * d[2];
    let bh = p[0] * d[0] + p[2] * d[2];
    let ch = p[0] * p[0] + p[2] * p[2];
    let r4 = 4.0 * big * big;
    let coefficients = [k * k - r4 * ch, 4.0 * n * k - 2.0 * r4 * bh, 4.0 * n * n + 2.0 * k - r4 * a, 4.0 * n, 1.0];
    let s = smallest_root_in(&coefficients, T_MIN as f64 - t0, t_out - t0 + 1e-9)?;
    let t = t0 + s;
    let q = [p[0] + s * d[0], p[1] + s * d[1], p[2] + s * d[2]];
    let ring = (q[0] * q[0] + q[2] * q[2]).sqrt().max(1e-12);
    let normal = [q[0] - big * q[0] / ring, q[1], q[2] - big * q[2] / ring];
    Some((t as f32, normalize(normal.map(|v| v as f32))))
}

/// Exit of a ray starting inside the axis-aligned box `[min, max]`: distance, inward normal
/// and the face index (0/1 = −X/+X wall, 2/3 = floor/ceiling, 4/5 = −Z/+Z wall).
pub fn room_exit(o: Vec3, d: Vec3, min: Vec3, max: Vec3) -> (f32, Vec3, usize) {
    let mut best = (f32::INFINITY, [0.0, 1.0, 0.0], 2);
    for a in 0..3 {
        if d[a].abs() < 1e-12 {
            continue;
        }
        let (plane, face, normal_sign) = if d[a] > 0.0 { (max[a], 2 * a + 1, -1.0) } else { (min[a], 2 * a, 1.0) };
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
        let (t, _) = yawed_box(o, d, [0.0, 0.5, 0.0], [0.5, 0.5, 0.5], std::f32::consts::FRAC_PI_4).unwrap();
        assert!((t - (5.0 - 0.5f32.sqrt())).abs() < 1e-4, "{t}");
        // Looking down onto a cylinder hits its top cap.
        let (t, n) = cylinder([0.0, 3.0, 0.0], [0.0, -1.0, 0.0], 0.0, 0.0, 0.0, 1.0, 0.5).unwrap();
        assert!((t - 2.0).abs() < 1e-5 && n[1] > 0.99);
        assert!(sphere(o, [0.0, 1.0, 0.0], [0.0, 0.5, 0.0], 1.0).is_none());
        let (t, n, face) = room_exit([0.0, 1.0, 0.0], d, [-3.0, 0.0, -3.0], [3.0, 3.0, 3.0]);
        assert!((t - 3.0).abs() < 1e-6 && face == 4 && n[2] == 1.0);
    }
    /// Signed distance to the torus of `torus_hits_match_the_surface`.
    fn torus_distance(p: Vec3) -> f32 {
        let ring = (p[0] * p[0] + p[2] * p[2]).sqrt() - 0.6;
        (ring * ring + (p[1] - 1.0) * (p[1] - 1.0)).sqrt() - 0.2
    }

    #[test]
    fn torus_hits_match_the_surface() {
        let c = [0.0, 1.0, 0.0];
        // Straight at the front of the tube, through the middle of the ring, down the hole.
        let (t, n) = torus([0.0, 1.0, 5.0], [0.0, 0.0, -1.0], c, 0.6, 0.2).unwrap();
        assert!((t - 4.2).abs() < 1e-5 && (n[2] - 1.0).abs() < 1e-5, "{t} {n:?}");
        // Along the ring's tangent the ray runs inside the tube's outer wall.
        let (t, _) = torus([0.6, 1.0, 5.0], [0.0, 0.0, -1.0], c, 0.6, 0.2).unwrap();
        assert!((t - (5.0 - 0.28f32.sqrt())).abs() < 1e-5, "{t}");
        let (t, n) = torus([-5.0, 1.0, 0.0], [1.0, 0.0, 0.0], c, 0.6, 0.2).unwrap();
        assert!((t - 4.2).abs() < 1e-5 && (n[0] + 1.0).abs() < 1e-5, "{t} {n:?}");
        assert!(torus([0.0, 5.0, 0.0], [0.0, -1.0, 0.0], c, 0.6, 0.2).is_none());
        // From inside the hole the ray meets the inner wall.
        let (t, n) = torus([0.0, 1.0, 0.0], [1.0, 0.0, 0.0], c, 0.6, 0.2).unwrap();
        assert!((t - 0.4).abs() < 1e-5 && (n[0] + 1.0).abs() < 1e-5, "{t} {n:?}");
        // Looking down onto the tube hits its top.
        let (t, n) = torus([0.6, 3.0, 0.0], [0.0, -1.0, 0.0], c, 0.6, 0.2).unwrap();
        assert!((t - 1.8).abs() < 1e-5 && n[1] > 0.999, "{t} {n:?}");
        // Many rays: the hit lies on the surface, with the surface's normal, and no point of
        // the ray before it (sampled every millimetre) is inside the tube.
        let mut state = 1u32;
        let mut rnd = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32
        };
        let mut hits = 0;
        for _ in 0..2000 {
            let o = [4.0 * rnd() - 2.0, 1.0 + 3.0 * rnd() - 1.5, 3.0 + rnd()];
            let target = [1.8 * rnd() - 0.9, 1.0 + 0.5 * rnd() - 0.25, 1.8 * rnd() - 0.9];
            let d = normalize([target[0] - o[0], target[1] - o[1], target[2] - o[2]]);
            let at = |t: f32| [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
            let hit = torus(o, d, c, 0.6, 0.2);
            let clear_until = hit.map_or(8.0, |(t, _)| t - 1e-3);
            let mut t = 0.0;
            while t < clear_until {
                assert!(torus_distance(at(t)) > -1e-4, "{o:?} {d:?}: inside at {t} before the hit {hit:?}");
                t += 1e-3;
            }
            if let Some((t, n)) = hit {
                hits += 1;
                let p = at(t);
                assert!(torus_distance(p).abs() < 1e-4);
                let e = 1e-3;
                let g = [0, 1, 2].map(|k| {
                    let mut q = p;
                    q[k] += e;
                    (torus_distance(q) - torus_distance(p)) / e
                });
                assert!(dot(normalize(g), n) > 0.99, "{n:?} vs {g:?}");
            }
        }
        assert!(hits > 500, "only {hits} of 2000 rays hit");
    }
}
