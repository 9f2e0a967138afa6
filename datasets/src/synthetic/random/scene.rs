//! Renders a random world's views and states its extent the way the built-in rigs do: the room
//! box padded by 5 cm (`Bounded`), the LLFF average-pose frame with the content's depth range
//! (`ForwardFacing`), or a sphere about the object holding every camera (`Unbounded`); `near`
//! is 0.9 x the nearest content depth seen.

use sos_core::camera::{Camera, Vec3};
use sos_core::scene::{Scene, SceneExtent, View};

use super::super::render::{render_view, Rendered};
use super::super::{Rig, SyntheticConfig};
use super::blueprint::{draw, Blueprint};
use super::environment::Environment;
use crate::adapter::hold_out_split;
use crate::pose::{self, Pose};

/// Padding of the room box in the `Bounded` extent.
const ROOM_PAD: f32 = 0.05;

fn view(i: usize, camera: Camera, r: Rendered) -> View {
    View { name: format!("view_{i:03}"), camera, image: r.image, mask: Some(r.mask) }
}

/// The random world of `cfg` (`world = "random"`), rendered.
pub fn generate(cfg: &SyntheticConfig) -> Scene {
    let bp = draw(cfg.seed, cfg.rig, cfg.views, cfg.width, cfg.height, cfg.render_path_views);
    let (train, test) = hold_out_split(cfg.views, cfg.hold_out_every);
    let name = format!("synthetic-random-{}-{}", bp.rig.name(), cfg.seed);
    let Blueprint { rig, world, capture, centre, .. } = bp;
    match rig {
        Rig::ForwardFacing => {
            let poses: Vec<Pose> = capture.cameras.iter().map(pose::from_camera).collect();
            let (recentred, avg) = pose::recenter(&poses);
            // Depth along the mean camera's viewing axis (−back).
            let mean_origin = [avg[0][3] as f32, avg[1][3] as f32, avg[2][3] as f32];
            let mean_forward = [-avg[0][2] as f32, -avg[1][2] as f32, -avg[2][2] as f32];
            let focal = capture.cameras[0].fx as f64;
            let (w, h) = (cfg.width, cfg.height);
            let mut near = f32::INFINITY;
            let mut far = 0.0f32;
            let views = capture
                .cameras
                .iter()
                .zip(&recentred)
                .enumerate()
                .map(|(i, (cam, p))| {
                    let r = render_view(&world, cam, mean_origin, mean_forward);
                    near = near.min(r.depth_range[0]);
                    far = far.max(r.depth_range[1]);
                    view(i, pose::to_camera(p, w, h, focal), r)
                })
                .collect();
            let (near, far) = (0.9 * near, 1.05 * far);
            let extent =
                SceneExtent::ForwardFacing { near, far, focal: focal as f32, width: w as f32, height: h as f32 };
            let render_path = pose::llff_spiral(&recentred, near as f64, far as f64, cfg.render_path_views)
                .iter()
                .map(|p| pose::to_camera(p, w, h, focal))
                .collect();
            Scene { name, views, train, test, extent, near, render_path }
        }
        _ => {
            let mut near = f32::INFINITY;
            let views = capture
                .cameras
                .iter()
                .enumerate()
                .map(|(i, cam)| {
                    let r = render_view(&world, cam, cam.origin(), cam.forward());
                    near = near.min(r.depth_range[0]);
                    view(i, cam.clone(), r)
                })
                .collect();
            let extent = match &world.environment {
                Environment::Room { min, max, .. } => {
                    SceneExtent::Bounded { min: min.map(|v| v - ROOM_PAD), max: max.map(|v| v + ROOM_PAD) }
                }
                Environment::Open { .. } => {
                    SceneExtent::Unbounded { center: centre, radius: 1.1 * farthest(&capture.cameras, centre) }
                }
            };
            // Z-depth bounds distance along any ray from below.
            Scene { name, views, train, test, extent, near: 0.9 * near, render_path: capture.path }
        }
    }
}

/// Distance from `centre` to the farthest camera centre.
fn farthest(cams: &[Camera], centre: Vec3) -> f32 {
    cams.iter()
        .map(|c| {
            let o = c.origin();
            (0..3).map(|k| (o[k] - centre[k]).powi(2)).sum::<f32>().sqrt()
        })
        .fold(0.0, f32::max)
}
