//! Camera rigs of the synthetic scene and their render paths, in world coordinates.

use sos_core::camera::{Camera, Vec3};

use super::world::OBJECT_CENTRE;

/// Distance of the object-centric cameras from the object centre.
pub const ORBIT_RADIUS: f32 = 2.3;
/// Horizontal field of view of every synthetic camera, in degrees.
pub const FOV_X_DEG: f32 = 60.0;

/// SplitMix64: a tiny, fixed generator so a seed gives the same scene on every platform and
/// `rand` version.
#[derive(Debug, Clone)]
pub struct SplitMix(u64);

impl SplitMix {
    /// A generator seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix(seed ^ 0x5851_f42d_4c95_7f2d)
    }

    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        (z >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }
}

/// Focal length in pixels for the rig's field of view.
pub fn focal_for(width: u32) -> f32 {
    0.5 * width as f32 / (0.5 * FOV_X_DEG.to_radians()).tan()
}

fn orbit_camera(azimuth: f32, elevation: f32, width: u32, height: u32) -> Camera {
    let c = OBJECT_CENTRE;
    let (sa, ca) = azimuth.sin_cos();
    let (se, ce) = elevation.sin_cos();
    let eye = [c[0] + ORBIT_RADIUS * ce * sa, c[1] + ORBIT_RADIUS * se, c[2] + ORBIT_RADIUS * ce * ca];
    Camera::look_at(eye, c, [0.0, 1.0, 0.0], width, height, focal_for(width))
}

/// `n` cameras around the object on the upper hemisphere: azimuths evenly spread with
/// jitter, elevations between 10° and 45°, all looking at the object centre.
pub fn object_centric(n: usize, width: u32, height: u32, rng: &mut SplitMix) -> Vec<Camera> {
    let step = std::f32::consts::TAU / n as f32;
    (0..n)
        .map(|i| {
            let azimuth = i as f32 * step + rng.range(-0.3, 0.3) * step;
            let elevation = rng.range(10.0, 45.0).to_radians();
            orbit_camera(azimuth, elevation, width, height)
        })
        .collect()
}

/// A circle of `n` cameras at 25° elevation around the object.
pub fn orbit_path(n: usize, width: u32, height: u32) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let azimuth = std::f32::consts::TAU * i as f32 / n as f32;
            orbit_camera(azimuth, 25f32.to_radians(), width, height)
        })
        .collect()
}

/// Centre of the forward-facing camera grid and the point its cameras face.
const GRID_CENTRE: Vec3 = [0.0, 1.3, 2.7];

/// `n` parallel cameras on a jittered planar grid (0.7 m x 0.4 m, in the world X–Y plane)
/// facing the object from the front of the room, row by row.
pub fn forward_facing(n: usize, width: u32, height: u32, rng: &mut SplitMix) -> Vec<Camera> {
    let cols = ((n as f32 * 1.6).sqrt().ceil() as usize).max(1);
    let rows = n.div_ceil(cols);
    let frac = |k: usize, count: usize| {
        if count > 1 {
            k as f32 / (count - 1) as f32
        } else {
            0.5
        }
    };
    let base = Camera::look_at(GRID_CENTRE, OBJECT_CENTRE, [0.0, 1.0, 0.0], width, height, focal_for(width));
    (0..n)
        .map(|i| {
            let (r, c) = (i / cols, i % cols);
            let dx = -0.35 + 0.7 * frac(c, cols) + rng.range(-0.02, 0.02);
            let dy = 0.2 - 0.4 * frac(r, rows) + rng.range(-0.02, 0.02);
            let mut cam = base.clone();
            cam.cam_to_world[0][3] += dx;
            cam.cam_to_world[1][3] += dy;
            cam
        })
        .collect()
}

/// Distance of the unbounded rig's cameras from the object centre.
pub const CIRCLE_RADIUS: f32 = 2.3;

fn circle_camera(azimuth: f32, height: f32, width: u32, height_px: u32) -> Camera {
    let c = OBJECT_CENTRE;
    let (sa, ca) = azimuth.sin_cos();
    let eye = [c[0] + CIRCLE_RADIUS * sa, height, c[2] + CIRCLE_RADIUS * ca];
    Camera::look_at(eye, c, [0.0, 1.0, 0.0], width, height_px, focal_for(width))
}

/// `n` cameras on a horizontal circle around the object (azimuths evenly spread with jitter,
/// heights 1.0–1.6 m), all looking at the object centre: most rays leave the foreground region
/// and end on distant towers, the far ground or the sky.
pub fn unbounded(n: usize, width: u32, height: u32, rng: &mut SplitMix) -> Vec<Camera> {
    let step = std::f32::consts::TAU / n as f32;
    (0..n)
        .map(|i| {
            let azimuth = i as f32 * step + rng.range(-0.3, 0.3) * step;
            circle_camera(azimuth, rng.range(1.0, 1.6), width, height)
        })
        .collect()
}

/// A circle of `n` cameras at 1.3 m around the object.
pub fn circle_path(n: usize, width: u32, height: u32) -> Vec<Camera> {
    (0..n).map(|i| circle_camera(std::f32::consts::TAU * i as f32 / n as f32, 1.3, width, height)).collect()
}
