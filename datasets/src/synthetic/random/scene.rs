//! Renders a random world's views and states its extent the way the built-in rigs do: the room
//! box padded by 5 cm (`Bounded`), the LLFF average-pose frame with the content's depth range
//! (`ForwardFacing`), or a sphere about the object holding every camera (`Unbounded`); `near`
//! is 0.9 x the nearest content depth seen.

use sos_core::scene::{Scene, SceneExtent};

use super::super::render::{farthest, forward_facing_scene, render_views};
use super::super::{Rig, SyntheticConfig};
use super::blueprint::{draw, Blueprint};
use super::environment::Environment;
use crate::adapter::hold_out_split;

/// Padding of the room box in the `Bounded` extent.
const ROOM_PAD: f32 = 0.05;

/// The random world of `cfg` (`world = "random"`), rendered.
pub fn generate(cfg: &SyntheticConfig) -> Scene {
    let bp = draw(cfg.seed, cfg.rig, cfg.views, cfg.width, cfg.height, cfg.render_path_views);
    let (train, test) = hold_out_split(cfg.views, cfg.hold_out_every);
    let name = format!("synthetic-random-{}-{}", bp.rig.name(), cfg.seed);
    let Blueprint { rig, world, capture, centre, .. } = bp;
    match rig {
        Rig::ForwardFacing => {
            let focal = capture.cameras[0].fx as f64;
            forward_facing_scene(&world, &capture.cameras, focal, cfg, name, train, test)
        }
        _ => {
            let (views, near) = render_views(&world, capture.cameras.iter().cloned());
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
