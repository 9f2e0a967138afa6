//! Surfaces the object stands on or in front of: large planes in a view's rendered 3D points
//! (the ground, a wall, a table top) that the object itself does not lie in. Their pixels are
//! background whatever their appearance, which is what a shadow on the ground, a floor coloured
//! like the object or a wall texture that matches it would otherwise join the object's cluster
//! by. A plane counts as a support when
//! - at least [`MIN_PLANE_SHARE`] of the view's rendered points lie on it (within
//!   [`PLANE_TOLERANCE`] of their distance from the camera),
//! - it reaches at least two of the image's borders (a face of a box object seen in the
//!   middle of the view does not), and
//! - fewer than half of the points nearest the focus (the object's, by the `focus` rule) lie
//!   on it (a flat object facing the camera is not its own support).
//!
//! Planes are found by RANSAC with a fixed seed (the same view gives the same planes), refined
//! by a least-squares fit to their inliers; up to [`MAX_PLANES`] are tried, each on the points
//! the earlier ones left.

use rand::{Rng, SeedableRng};

use crate::camera::{cross, dot, normalize, sub, Vec3};

/// Distance from a plane, as a fraction of a point's distance from the camera, within which
/// the point lies on it: rendered depth errs in proportion to depth.
pub const PLANE_TOLERANCE: f32 = 0.01;

/// Smallest share of a view's rendered points a support plane holds.
pub const MIN_PLANE_SHARE: f64 = 0.15;

/// Share of a border's rendered pixels on the plane for the plane to reach that border.
const BORDER_SHARE: f64 = 0.25;

/// Planes tried per view.
pub const MAX_PLANES: usize = 3;

/// RANSAC draws per plane, and the points each draw is scored on.
const DRAWS: usize = 200;
const SCORED_POINTS: usize = 3000;

/// A plane `normal · p = offset` (unit normal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Unit normal.
    pub normal: Vec3,
    /// Offset along the normal.
    pub offset: f32,
}

impl Plane {
    /// The plane through three points, if they span one.
    pub fn through(a: Vec3, b: Vec3, c: Vec3) -> Option<Plane> {
        let n = cross(sub(b, a), sub(c, a));
        let len = dot(n, n).sqrt();
        (len > 1e-12 && len.is_finite()).then(|| {
            let normal = [n[0] / len, n[1] / len, n[2] / len];
            Plane { normal, offset: dot(normal, a) }
        })
    }

    /// Unsigned distance of `p` from the plane.
    pub fn distance(&self, p: Vec3) -> f32 {
        (dot(self.normal, p) - self.offset).abs()
    }
}

/// One view's rendered points as the plane search sees them.
pub struct ViewPoints<'a> {
    /// Rendered 3D point per pixel (row-major `width x height`), `None` for empty rays.
    pub points: &'a [Option<Vec3>],
    /// The camera centre.
    pub origin: Vec3,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
}

impl ViewPoints<'_> {
    fn on(&self, plane: &Plane, i: usize) -> bool {
        self.points[i].is_some_and(|p| {
            let d = sub(p, self.origin);
            plane.distance(p) <= PLANE_TOLERANCE * dot(d, d).sqrt()
        })
    }

    /// Whether the plane's pixels (`on`) reach at least two image borders.
    fn reaches_two_borders(&self, on: &[bool]) -> bool {
        let (w, h) = (self.width, self.height);
        let borders: [Vec<usize>; 4] = [
            (0..w).collect(),
            (0..w).map(|c| (h - 1) * w + c).collect(),
            (0..h).map(|r| r * w).collect(),
            (0..h).map(|r| r * w + w - 1).collect(),
        ];
        let reached = borders
            .iter()
            .filter(|border| {
                let hits: Vec<usize> = border.iter().copied().filter(|&i| self.points[i].is_some()).collect();
                !hits.is_empty() && hits.iter().filter(|&&i| on[i]).count() as f64 >= BORDER_SHARE * hits.len() as f64
            })
            .count();
        reached >= 2
    }
}

/// The large planes of one view that reach two of its borders: every plane that could be a
/// support, before asking whether the object lies in it.
#[derive(Debug, Clone)]
pub struct PlaneCandidates {
    /// Per plane, the view's pixels that lie on it (row-major).
    on: Vec<Vec<bool>>,
    /// The planes themselves, in the same order.
    planes: Vec<Plane>,
    pixels: usize,
}

impl PlaneCandidates {
    /// Finds the view's large planes (see the module documentation) with a fixed `seed`.
    pub fn find(view: &ViewPoints, seed: u64) -> PlaneCandidates {
        let n = view.points.len();
        let mut planes = PlaneCandidates { on: Vec::new(), planes: Vec::new(), pixels: n };
        if view.width == 0 || view.height == 0 {
            return planes;
        }
        let mut left: Vec<usize> = (0..n).filter(|&i| view.points[i].is_some()).collect();
        let total = left.len();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..MAX_PLANES {
            let Some(plane) = best_plane(view, &left, &mut rng) else { break };
            let on: Vec<bool> = (0..n).map(|i| view.on(&plane, i)).collect();
            let held = left.iter().filter(|&&i| on[i]).count();
            if (held as f64) < MIN_PLANE_SHARE * total as f64 {
                break;
            }
            left.retain(|&i| !on[i]);
            if view.reaches_two_borders(&on) {
                planes.on.push(on);
                planes.planes.push(plane);
            }
            if left.len() < 3 {
                break;
            }
        }
        planes
    }

    /// Pixels on any of the planes.
    pub fn any(&self) -> Vec<bool> {
        self.supports(&[])
    }

    /// Each pixel's clearance from the support planes (those [`Self::supports`] keeps for
    /// `voters`): its point's distance from the nearest of them over its distance from the
    /// camera, in units of [`PLANE_TOLERANCE`] (at most 1 on a plane); infinite for pixels
    /// without a point or with no support plane.
    pub fn clearance(&self, view: &ViewPoints, voters: &[usize]) -> Vec<f32> {
        let supports: Vec<&Plane> = self.support_indices(voters).map(|k| &self.planes[k]).collect();
        view.points
            .iter()
            .map(|p| {
                let Some(p) = p else { return f32::INFINITY };
                let d = sub(*p, view.origin);
                let range = dot(d, d).sqrt() * PLANE_TOLERANCE;
                supports.iter().map(|plane| plane.distance(*p) / range).fold(f32::INFINITY, f32::min)
            })
            .collect()
    }

    /// Pixels on the support planes: the candidates that hold fewer than half of `voters`
    /// (the pixels nearest the focus, the object's).
    pub fn supports(&self, voters: &[usize]) -> Vec<bool> {
        let mut support = vec![false; self.pixels];
        for k in self.support_indices(voters) {
            support.iter_mut().zip(&self.on[k]).for_each(|(s, &o)| *s |= o);
        }
        support
    }

    /// The planes that hold fewer than half of `voters`: the supports, by index.
    fn support_indices<'s>(&'s self, voters: &'s [usize]) -> impl Iterator<Item = usize> + 's {
        (0..self.on.len()).filter(move |&k| voters.iter().filter(|&&i| self.on[k][i]).count() * 2 < voters.len().max(1))
    }
}

/// The RANSAC plane holding most of `candidates`, refined on its inliers.
fn best_plane(view: &ViewPoints, candidates: &[usize], rng: &mut impl Rng) -> Option<Plane> {
    if candidates.len() < 3 {
        return None;
    }
    let scored: Vec<usize> = if candidates.len() <= SCORED_POINTS {
        candidates.to_vec()
    } else {
        (0..SCORED_POINTS).map(|_| candidates[rng.gen_range(0..candidates.len())]).collect()
    };
    let point = |i: usize| view.points[i].expect("candidates have points");
    let mut best: Option<(usize, Plane)> = None;
    for _ in 0..DRAWS {
        let [a, b, c] = [0; 3].map(|_| point(candidates[rng.gen_range(0..candidates.len())]));
        let Some(plane) = Plane::through(a, b, c) else { continue };
        let count = scored.iter().filter(|&&i| view.on(&plane, i)).count();
        if best.is_none_or(|(n, _)| count > n) {
            best = Some((count, plane));
        }
    }
    let (_, plane) = best?;
    let inliers: Vec<Vec3> = candidates.iter().filter(|&&i| view.on(&plane, i)).map(|&i| point(i)).collect();
    Some(fit_plane(&inliers).unwrap_or(plane))
}

/// Least-squares plane of `points`: through their centroid, normal along the covariance's
/// smallest eigenvector.
pub fn fit_plane(points: &[Vec3]) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let mut mean = [0.0f64; 3];
    for p in points {
        for k in 0..3 {
            mean[k] += p[k] as f64 / n;
        }
    }
    let mut cov = [[0.0f64; 3]; 3];
    for p in points {
        let d = [p[0] as f64 - mean[0], p[1] as f64 - mean[1], p[2] as f64 - mean[2]];
        for r in 0..3 {
            for c in 0..3 {
                cov[r][c] += d[r] * d[c] / n;
            }
        }
    }
    let normal = smallest_eigenvector(cov)?;
    let normal = normalize([normal[0] as f32, normal[1] as f32, normal[2] as f32]);
    let centroid = [mean[0] as f32, mean[1] as f32, mean[2] as f32];
    normal.iter().all(|v| v.is_finite()).then(|| Plane { normal, offset: dot(normal, centroid) })
}

/// Eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix: the eigenvalue in closed
/// form (trigonometric solution of the characteristic cubic), the vector as the largest cross
/// product of two rows of `A − λI`.
fn smallest_eigenvector(a: [[f64; 3]; 3]) -> Option<[f64; 3]> {
    let trace = a[0][0] + a[1][1] + a[2][2];
    let q = trace / 3.0;
    let p1 = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
    let p2 = (a[0][0] - q).powi(2) + (a[1][1] - q).powi(2) + (a[2][2] - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    if p <= 1e-30 {
        return None; // a multiple of the identity: no preferred direction
    }
    let b: Vec<Vec<f64>> =
        (0..3).map(|r| (0..3).map(|c| (a[r][c] - if r == c { q } else { 0.0 }) / p).collect()).collect();
    let det = b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1]) - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0])
        + b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0]);
    let phi = (det / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos();
    let rows: Vec<[f64; 3]> =
        (0..3).map(|r| [0, 1, 2].map(|c| a[r][c] - if r == c { smallest } else { 0.0 })).collect();
    let cross64 =
        |u: [f64; 3], v: [f64; 3]| [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
    let norm2 = |v: [f64; 3]| v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    [cross64(rows[0], rows[1]), cross64(rows[0], rows[2]), cross64(rows[1], rows[2])]
        .into_iter()
        .max_by(|u, v| norm2(*u).total_cmp(&norm2(*v)))
        .filter(|v| norm2(*v) > 1e-30)
}

/// Views of boxes standing on the ground plane y = 0, ray-cast exactly, for the tests of the
/// mask rules.
#[cfg(test)]
pub(crate) mod test_view {
    use crate::camera::{axpy, Vec3};

    /// Each pixel's point where its ray from `origin` first meets the ground or one of `boxes`
    /// (`[min, max]` corners), and whether that is a box; `direction(x, y)` gives the unit ray
    /// of the image coordinates `x, y ∈ (−1, 1)` (`y` up).
    pub(crate) fn boxes_on_the_ground(
        origin: Vec3,
        width: usize,
        height: usize,
        boxes: &[[Vec3; 2]],
        direction: impl Fn(f32, f32) -> Vec3,
    ) -> (Vec<Option<Vec3>>, Vec<bool>) {
        let (mut points, mut object) = (Vec::new(), Vec::new());
        for r in 0..height {
            for c in 0..width {
                let x = (c as f32 + 0.5) / width as f32 * 2.0 - 1.0;
                let y = 1.0 - (r as f32 + 0.5) / height as f32 * 2.0;
                let d = direction(x, y);
                let hit_box = boxes
                    .iter()
                    .filter_map(|[min, max]| crate::render::sampler::ray_box(origin, d, *min, *max).map(|(t, _)| t))
                    .reduce(f32::min);
                let hit_ground = (d[1] < 0.0).then(|| -origin[1] / d[1]);
                let t = match (hit_box, hit_ground) {
                    (Some(b), Some(g)) => Some(b.min(g)),
                    (b, g) => b.or(g),
                };
                object.push(hit_box.is_some() && t == hit_box);
                points.push(t.map(|t| axpy(origin, t, d)));
            }
        }
        (points, object)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera at (0, 1, 3) looking along −Z over a ground plane y = 0, with a box standing on
    /// it in the middle of the view.
    fn scene(width: usize, height: usize) -> (Vec<Option<Vec3>>, Vec<bool>) {
        let the_box = [[-0.4, 0.0, -0.4], [0.4, 0.8, 0.4]];
        test_view::boxes_on_the_ground([0.0, 1.0, 3.0], width, height, &[the_box], |x, y| {
            normalize([x, y * 0.75 - 0.3, -1.0])
        })
    }

    #[test]
    fn the_ground_is_a_support_and_the_box_standing_on_it_is_not() {
        let (w, h) = (80, 60);
        let (points, object) = scene(w, h);
        let view = ViewPoints { points: &points, origin: [0.0, 1.0, 3.0], width: w, height: h };
        let voters: Vec<usize> = (0..points.len()).filter(|&i| object[i]).take(50).collect();
        let support = PlaneCandidates::find(&view, 7).supports(&voters);
        let ground = (0..points.len()).filter(|&i| points[i].is_some() && !object[i]).count();
        let ground_found = (0..points.len()).filter(|&i| support[i] && !object[i]).count();
        assert!(ground_found as f64 > 0.95 * ground as f64, "{ground_found} of {ground} ground pixels");
        let box_lost = (0..points.len()).filter(|&i| support[i] && object[i]).count();
        let box_pixels = object.iter().filter(|&&o| o).count();
        assert!((box_lost as f64) < 0.05 * box_pixels as f64, "{box_lost} of {box_pixels} box pixels dropped");
        // Same seed, same answer.
        assert_eq!(support, PlaneCandidates::find(&view, 7).supports(&voters));
    }

    #[test]
    fn clearance_is_the_distance_from_the_support_plane_in_plane_tolerances() {
        let (w, h) = (80, 60);
        let (points, object) = scene(w, h);
        let origin = [0.0, 1.0, 3.0];
        let view = ViewPoints { points: &points, origin, width: w, height: h };
        let voters: Vec<usize> = (0..points.len()).filter(|&i| object[i]).take(50).collect();
        let planes = PlaneCandidates::find(&view, 7);
        let clearance = planes.clearance(&view, &voters);
        for i in 0..points.len() {
            let Some(p) = points[i] else {
                assert_eq!(clearance[i], f32::INFINITY, "an empty ray has no clearance");
                continue;
            };
            if object[i] {
                // The box's points stand p.y above the ground y = 0.
                let range = PLANE_TOLERANCE * dot(sub(p, origin), sub(p, origin)).sqrt();
                assert!((clearance[i] - p[1] / range).abs() < 0.05 * (p[1] / range) + 0.1, "pixel {i}");
            } else {
                assert!(clearance[i] <= 1.0, "ground pixel {i}: {}", clearance[i]);
            }
        }
        // With the ground holding the voters it is no support, and nothing has a clearance.
        let on_ground: Vec<usize> = (0..points.len()).filter(|&i| points[i].is_some() && !object[i]).take(50).collect();
        assert!(planes.clearance(&view, &on_ground).iter().all(|c| c.is_infinite()));
    }

    #[test]
    fn a_plane_holding_the_focus_is_not_a_support() {
        let (w, h) = (40, 30);
        let (points, object) = scene(w, h);
        let view = ViewPoints { points: &points, origin: [0.0, 1.0, 3.0], width: w, height: h };
        // Voters on the ground: the "object" lies in the plane, so nothing is dropped from it.
        let voters: Vec<usize> = (0..points.len()).filter(|&i| points[i].is_some() && !object[i]).take(50).collect();
        let support = PlaneCandidates::find(&view, 7).supports(&voters);
        assert!(voters.iter().all(|&i| !support[i]));
    }

    #[test]
    fn the_least_squares_fit_recovers_a_tilted_plane() {
        let normal = normalize([0.2, 1.0, -0.3]);
        let mut points = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                let (u, v) = (i as f32 * 0.1, j as f32 * 0.1);
                // Points on n·p = 0.5: solve for y.
                let y = (0.5 - normal[0] * u - normal[2] * v) / normal[1];
                points.push([u, y, v]);
            }
        }
        let plane = fit_plane(&points).unwrap();
        let agree = dot(plane.normal, normal).abs();
        assert!(agree > 0.9999, "normal {:?} vs {normal:?}", plane.normal);
        assert!(points.iter().all(|&p| plane.distance(p) < 1e-4));
    }
}
