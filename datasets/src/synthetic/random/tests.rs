//! Tests of random worlds that need their insides: exact masks and depths, distractors that
//! never reach the mask, extents that hold the content.

use sos_core::camera::{axpy, dot, sub, Camera, Vec3};

use super::super::geometry::room_exit;
use super::super::render::render_view;
use super::super::Rig;
use super::blueprint::{draw, Blueprint, RIGS};
use super::environment::Environment;
use super::world::RandomWorld;

/// Whether the pixel-centre ray's first hit is a foreground part, found without the world's
/// tracer: every primitive tested (no culling), then the room or ground.
fn first_hit_is_foreground(world: &RandomWorld, o: Vec3, d: Vec3) -> (bool, f32) {
    let mut best = (false, f32::INFINITY);
    for p in &world.parts {
        if let Some((t, _)) = p.shape.hit(o, d) {
            if t < best.1 {
                best = (p.foreground, t);
            }
        }
    }
    let t_env = match &world.environment {
        Environment::Room { min, max, .. } => room_exit(o, d, *min, *max).0,
        // The ground is a disc: past its rim the ray meets the sky.
        Environment::Open { radius, .. } if d[1] < 0.0 => {
            let t = -o[1] / d[1];
            let p = axpy(o, t, d);
            if p[0] * p[0] + p[2] * p[2] < radius * radius {
                t
            } else {
                f32::INFINITY
            }
        }
        Environment::Open { .. } => f32::INFINITY,
    };
    if t_env < best.1 {
        (false, t_env)
    } else {
        best
    }
}

fn small(seed: u64, rig: Rig) -> Blueprint {
    draw(seed, rig, 6, 64, 48, 4)
}

fn centre_ray(cam: &Camera, col: usize, row: usize) -> (Vec3, Vec3) {
    (cam.origin(), cam.direction(col as f32 + 0.5, row as f32 + 0.5))
}

#[test]
fn masks_and_depths_follow_the_first_hit() {
    for (seed, rig) in (0..10).map(|s| (s, RIGS[s as usize % RIGS.len()])) {
        let bp = small(seed, rig);
        let mut foreground = 0;
        for cam in &bp.capture.cameras {
            let r = render_view(&bp.world, cam, cam.origin(), cam.forward());
            for row in 0..48 {
                for col in 0..64 {
                    let (o, d) = centre_ray(cam, col, row);
                    let (fg, t) = first_hit_is_foreground(&bp.world, o, d);
                    let m = r.mask.data[row * 64 + col];
                    assert_eq!(m == 1.0, fg, "seed {seed} {rig:?}: pixel ({col}, {row})");
                    // The ground-truth depth is the first hit's distance, infinite for the sky.
                    let depth = r.depth.data[row * 64 + col];
                    if t.is_finite() {
                        assert!((depth - t).abs() <= 1e-3 * t.max(1.0), "seed {seed}: depth {depth} vs hit at {t}");
                    } else {
                        assert_eq!(depth, f32::INFINITY, "seed {seed}: the sky has no depth");
                    }
                    if fg {
                        foreground += 1;
                        // The hit lies on a foreground surface.
                        let p = axpy(o, t, d);
                        let on =
                            bp.world.parts.iter().filter(|q| q.foreground).any(|q| q.shape.distance(p).abs() < 2e-3);
                        assert!(on, "seed {seed}: foreground hit off every foreground surface");
                    }
                }
            }
        }
        assert!(foreground > 0, "seed {seed}: no foreground pixel");
    }
}

#[test]
fn distractors_never_change_the_mask() {
    let mut with_distractors = 0;
    for seed in 0..16 {
        let bp = small(seed, RIGS[seed as usize % RIGS.len()]);
        if bp.distractors == 0 {
            continue;
        }
        with_distractors += 1;
        let mut bare = bp.world.clone();
        let fg = bare.parts.iter().filter(|p| p.foreground).count();
        // Keep the towers (they are part of the background, far beyond the cameras).
        bare.parts.drain(fg..fg + bp.distractors);
        for cam in &bp.capture.cameras {
            let a = render_view(&bp.world, cam, cam.origin(), cam.forward());
            let b = render_view(&bare, cam, cam.origin(), cam.forward());
            assert_eq!(a.mask, b.mask, "seed {seed}: a distractor hides part of the object");
        }
        // Nor do they touch the object.
        for d in &bp.world.parts[fg..fg + bp.distractors] {
            for p in d.shape.silhouette() {
                assert!(bp.world.parts[..fg].iter().all(|q| q.shape.distance(p) > 0.0));
            }
        }
    }
    assert!(with_distractors >= 8, "only {with_distractors} of 16 worlds have distractors");
}

#[test]
fn extents_hold_cameras_and_content() {
    for seed in 0..12 {
        for rig in RIGS {
            let bp = small(seed, rig);
            let eyes: Vec<Vec3> = bp.capture.cameras.iter().chain(&bp.capture.path).map(|c| c.origin()).collect();
            match &bp.world.environment {
                Environment::Room { min, max, .. } => {
                    assert_ne!(rig, Rig::Unbounded);
                    let inside =
                        |p: Vec3, margin: f32| (0..3).all(|k| p[k] >= min[k] + margin && p[k] <= max[k] - margin);
                    for o in &eyes {
                        // Cameras may stand low (the floor check is below), never near a wall.
                        let lifted = [o[0], o[1].max(min[1] + 0.3), o[2]];
                        assert!(inside(lifted, 0.3), "seed {seed} {rig:?}: camera {o:?} near or outside the room");
                    }
                    for p in &bp.world.parts {
                        let [lo, hi] = p.shape.aabb();
                        assert!(inside(lo, -1e-4) && inside(hi, -1e-4), "seed {seed} {rig:?}: {:?} outside", p.shape);
                    }
                }
                Environment::Open { .. } => {
                    assert_eq!(rig, Rig::Unbounded);
                    let r = bp.capture.cameras.iter().map(|c| dist(c.origin(), bp.centre)).fold(0.0, f32::max);
                    // The object lies well inside the sphere the extent states (1.1 r).
                    let fg = bp.world.parts.iter().filter(|p| p.foreground);
                    for p in fg.flat_map(|p| p.shape.silhouette()) {
                        assert!(dist(p, bp.centre) < 0.5 * r, "seed {seed}: object reaches the cameras");
                    }
                }
            }
            for cam in &bp.capture.cameras {
                assert!(cam.origin()[1] >= 0.19, "seed {seed} {rig:?}: camera under the floor");
                // The object is in front of every camera.
                assert!(dot(sub(bp.centre, cam.origin()), cam.forward()) > 0.0);
            }
        }
    }
}

fn dist(a: Vec3, b: Vec3) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt()
}

#[test]
fn rigs_keep_their_elevation_ranges() {
    for seed in 0..8 {
        for rig in [Rig::ObjectCentric, Rig::Hemisphere, Rig::Grazing] {
            let bp = draw(seed, rig, 40, 64, 48, 4);
            let el: Vec<f32> = bp
                .capture
                .cameras
                .iter()
                .map(|c| {
                    let v = sub(c.origin(), bp.centre);
                    (v[1] / dist(c.origin(), bp.centre)).asin().to_degrees()
                })
                .collect();
            let lo = el.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = el.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            // Target jitter moves the aim by a few percent of the object, hence the slack.
            match rig {
                Rig::Grazing => assert!(lo > -3.0 && hi < 18.0, "grazing {lo}..{hi}"),
                Rig::Hemisphere => assert!(lo < 20.0 && hi > 60.0 && hi < 84.0, "hemisphere {lo}..{hi}"),
                _ => assert!(lo > 2.0 && hi < 68.0, "object-centric {lo}..{hi}"),
            }
        }
    }
}

#[test]
fn hundreds_of_worlds_draw_valid_cameras() {
    for seed in 0..400 {
        let bp = draw(seed, Rig::Random, 12, 32, 24, 3);
        let d = bp.describe();
        assert!(d.lines().count() == 3, "seed {seed}: {d}");
        for cam in bp.capture.cameras.iter().chain(&bp.capture.path) {
            cam.validate().unwrap_or_else(|e| panic!("seed {seed} {:?}: {e}", bp.rig));
            assert!(cam.origin().iter().all(|v| v.is_finite() && v.abs() < 100.0), "seed {seed}");
        }
        assert!(bp.world.parts.iter().filter(|p| p.foreground).count() == bp.composition.parts.len());
    }
}
