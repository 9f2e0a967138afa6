//! Camera rigs of random worlds. Each rig draws its elevations, field of view, jitter and the
//! share of the view height the object fills; each camera's distance then follows from that
//! share ([`Framing::distance`]), so the object fills 10–60% of every view whatever its size.

use sos_core::camera::{Camera, Vec3};

use super::super::rig::SplitMix;
use super::super::Rig;
use super::draw::Draw;
use super::framing::Framing;

/// Cameras never stand lower than this above the ground.
const MIN_EYE_HEIGHT: f32 = 0.2;

/// The cameras of a random world.
#[derive(Debug, Clone)]
pub struct Capture {
    /// Training and held-out cameras, in view order.
    pub cameras: Vec<Camera>,
    /// Novel-view path (empty for `forward-facing`, whose LLFF spiral needs the depth bounds).
    pub path: Vec<Camera>,
    /// One line for humans.
    pub summary: String,
}

/// Focal length for a horizontal field of view drawn in 45–75°.
pub fn draw_focal(width: u32, rng: &mut SplitMix) -> f32 {
    let fov = rng.range(45.0f32, 75.0).to_radians();
    0.5 * width as f32 / (0.5 * fov).tan()
}

/// Unit direction at `azimuth` (from +Z towards +X) and `elevation`, radians.
fn direction(azimuth: f32, elevation: f32) -> Vec3 {
    let (sa, ca) = azimuth.sin_cos();
    let (se, ce) = elevation.sin_cos();
    [ce * sa, se, ce * ca]
}

/// A camera looking at (a jittered) object centre from `azimuth`, `elevation`, at the distance
/// where the object spans `share` of the view height; raised where it would stand too low.
fn orbit_camera(framing: &Framing, azimuth: f32, elevation: f32, share: f32, target: Vec3) -> Camera {
    let mut elevation = elevation;
    let mut d = framing.distance(target, direction(azimuth, elevation), share);
    for _ in 0..3 {
        let low = target[1] + d * elevation.sin();
        if low >= MIN_EYE_HEIGHT {
            break;
        }
        elevation = ((MIN_EYE_HEIGHT + 0.02 - target[1]) / d).clamp(-1.0, 1.0).asin();
        d = framing.distance(target, direction(azimuth, elevation), share);
    }
    let dir = direction(azimuth, elevation);
    framing.camera([target[0] + d * dir[0], target[1] + d * dir[1], target[2] + d * dir[2]], target)
}

/// The object centre moved by up to `amount` along each axis.
fn jittered(c: Vec3, amount: f32, rng: &mut SplitMix) -> Vec3 {
    c.map(|v| v + amount * rng.range(-1.0, 1.0))
}

/// A circle of `n` cameras at `elevation`, the object spanning `share`.
fn circle(framing: &Framing, n: usize, elevation: f32, share: f32) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let a = std::f32::consts::TAU * i as f32 / n as f32;
            orbit_camera(framing, a, elevation, share, framing.centre)
        })
        .collect()
}

fn range_summary(name: &str, framing: &Framing, cams: &[Camera], e: [f32; 2]) -> String {
    let dist = |c: &Camera| {
        let o = c.origin();
        (0..3).map(|k| (o[k] - framing.centre[k]).powi(2)).sum::<f32>().sqrt()
    };
    let lo = cams.iter().map(dist).fold(f32::INFINITY, f32::min);
    let hi = cams.iter().map(dist).fold(0.0, f32::max);
    let fov = 2.0 * (0.5 * framing.width as f32 / framing.focal).atan().to_degrees();
    format!(
        "{name} rig, elevation {:.0}–{:.0}°, distance {lo:.2}–{hi:.2} m, horizontal fov {fov:.0}°",
        e[0].to_degrees(),
        e[1].to_degrees()
    )
}

/// Cameras of `rig` (not [`Rig::Random`]): `n` views and `path_n` path cameras.
pub fn capture(rig: Rig, n: usize, path_n: usize, framing: &Framing, rng: &mut SplitMix) -> Capture {
    let share = rng.range(0.22, 0.5);
    let target_jitter = rng.range(0.0, 0.08) * framing.radius;
    let deg = |d: f32| d.to_radians();
    let step = std::f32::consts::TAU / n as f32;
    let start = rng.angle();
    match rig {
        Rig::ObjectCentric | Rig::Grazing | Rig::Unbounded => {
            let (e, spread, name) = match rig {
                Rig::ObjectCentric => {
                    let lo = rng.range(5.0, 25.0);
                    ([deg(lo), deg((lo + rng.range(10.0, 35.0)).min(65.0))], 0.1, "object-centric")
                }
                Rig::Grazing => ([deg(rng.range(1.0, 4.0)), deg(rng.range(8.0, 15.0))], 0.08, "grazing"),
                _ => {
                    let lo = rng.range(0.0, 6.0);
                    ([deg(lo), deg(lo + rng.range(3.0, 15.0))], 0.1, "unbounded")
                }
            };
            let share = if rig == Rig::Unbounded { 0.85 * share } else { share };
            let jitter = rng.range(0.0, 0.45);
            let cameras: Vec<Camera> = (0..n)
                .map(|i| {
                    let a = start + step * (i as f32 + jitter * rng.range(-1.0, 1.0));
                    let el = rng.range(e[0], e[1]);
                    let s = share * (1.0 + spread * rng.range(-1.0, 1.0));
                    orbit_camera(framing, a, el, s, jittered(framing.centre, target_jitter, rng))
                })
                .collect();
            // Unbounded captures circle closer for their novel views, as the built-in rig does.
            let path_share = if rig == Rig::Unbounded { 1.25 * share } else { share };
            let path = circle(framing, path_n, 0.5 * (e[0] + e[1]), path_share);
            let summary = range_summary(name, framing, &cameras, e);
            Capture { cameras, path, summary }
        }
        Rig::Hemisphere => {
            // Equal areas of the hemisphere band get equal numbers of cameras (uniform in
            // sin(elevation)), azimuths on a golden-angle spiral; the share varies by ±25%, so
            // the radius does too.
            let e = [deg(rng.range(3.0, 12.0)), deg(rng.range(70.0, 80.0))];
            let (s0, s1) = (e[0].sin(), e[1].sin());
            let jitter = rng.range(0.0, 0.45);
            let cameras: Vec<Camera> = (0..n)
                .map(|i| {
                    let u = ((i as f32 + 0.5 + jitter * rng.range(-0.5, 0.5)) / n as f32).clamp(0.0, 1.0);
                    let el = (s0 + u * (s1 - s0)).asin();
                    let a = start + i as f32 * 2.399_963 + jitter * step * rng.range(-1.0, 1.0);
                    let s = (share * rng.range(0.75, 1.25)).clamp(0.12, 0.58);
                    orbit_camera(framing, a, el, s, jittered(framing.centre, target_jitter, rng))
                })
                .collect();
            let path = circle(framing, path_n, deg(35.0), share);
            let summary = range_summary("hemisphere", framing, &cameras, e);
            Capture { cameras, path, summary }
        }
        Rig::ForwardFacing => {
            let e0 = deg(rng.range(5.0, 30.0));
            let dir = direction(start, e0);
            let d0 = framing.distance(framing.centre, dir, share);
            let c = framing.centre;
            let base = framing.camera([c[0] + d0 * dir[0], c[1] + d0 * dir[1], c[2] + d0 * dir[2]], c);
            let (gw, gh) = (rng.range(0.12, 0.3) * d0, rng.range(0.06, 0.16) * d0);
            let jitter = rng.range(0.0, 0.015) * d0;
            // Parallel cameras on a grid in the base camera's image plane, row by row.
            let cols = ((n as f32 * 1.6).sqrt().ceil() as usize).max(1);
            let rows = n.div_ceil(cols);
            let frac = |k: usize, count: usize| if count > 1 { k as f32 / (count - 1) as f32 } else { 0.5 };
            let m = base.cam_to_world;
            let cameras = (0..n)
                .map(|i| {
                    let (r, col) = (i / cols, i % cols);
                    let dx = gw * (frac(col, cols) - 0.5) + jitter * rng.range(-1.0, 1.0);
                    let dy = gh * (0.5 - frac(r, rows)) + jitter * rng.range(-1.0, 1.0);
                    let mut cam = base.clone();
                    for (row, axes) in cam.cam_to_world.iter_mut().zip(&m) {
                        row[3] += dx * axes[0] + dy * axes[1];
                    }
                    cam
                })
                .collect();
            let fov = 2.0 * (0.5 * framing.width as f32 / framing.focal).atan().to_degrees();
            let summary = format!(
                "forward-facing rig, elevation {:.0}°, distance {d0:.2} m, grid {gw:.2} x {gh:.2} m, horizontal fov {fov:.0}°",
                e0.to_degrees()
            );
            Capture { cameras, path: Vec::new(), summary }
        }
        Rig::Random => unreachable!("`rig = \"random\"` is resolved before the cameras are placed"),
    }
}
