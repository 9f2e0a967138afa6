//! Renders the views of a synthetic world: 2x2 supersampled colour, an exact mask and depth
//! from the pixel-centre ray and the range of content depths along a reference axis per view;
//! and the capture of a rig, the views with what the scene states about them (`near`, for
//! forward-facing rigs the extent and render path), the same for the built-in and the random
//! worlds.

use rayon::prelude::*;
use sos_core::camera::{dot, sub, Camera, Vec3};
use sos_core::image::{GrayImage, RgbImage};
use sos_core::scene::{Scene, SceneExtent, View};

use super::world::{Trace, SKY_DISTANCE};
use super::SyntheticConfig;
use crate::pose::{self, Pose};

/// Sub-pixel offsets of the 2x2 supersampling pattern.
const SUBSAMPLES: [[f32; 2]; 4] = [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]];

/// A rendered view.
#[derive(Debug, Clone)]
pub struct Rendered {
    /// Colour, the mean of 2x2 sub-pixel samples.
    pub image: RgbImage,
    /// 1 where the pixel-centre ray hits the foreground object.
    pub mask: GrayImage,
    /// Distance along the pixel-centre ray to its first surface, `f32::INFINITY` for the sky.
    pub depth: GrayImage,
    /// Min and max depth of the pixel-centre hits along `depth_axis` from `depth_origin`.
    pub depth_range: [f32; 2],
}

/// Renders `cam` (world frame). Depths are measured as `dot(hit − depth_origin, depth_axis)`.
pub fn render_view<W: Trace + Sync>(world: &W, cam: &Camera, depth_origin: Vec3, depth_axis: Vec3) -> Rendered {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut image = RgbImage::new(w, h);
    let mut mask = GrayImage { width: w, height: h, data: vec![0.0; w * h] };
    let mut distance = GrayImage { width: w, height: h, data: vec![0.0; w * h] };
    let origin = cam.origin();
    let depth_range = image
        .data
        .par_chunks_mut(w * 3)
        .zip(mask.data.par_chunks_mut(w))
        .zip(distance.data.par_chunks_mut(w))
        .enumerate()
        .map(|(row, ((rgb_row, mask_row), distance_row))| {
            let mut range = [f32::INFINITY, f32::NEG_INFINITY];
            for col in 0..w {
                let subs = SUBSAMPLES.map(|[sx, sy]| cam.direction(col as f32 + sx, row as f32 + sy));
                rgb_row[col * 3..col * 3 + 3].copy_from_slice(&world.pixel(origin, subs));
                let (foreground, point) = world.probe(origin, cam.direction(col as f32 + 0.5, row as f32 + 0.5));
                mask_row[col] = if foreground { 1.0 } else { 0.0 };
                let to_hit = sub(point, origin);
                let t = dot(to_hit, to_hit).sqrt();
                distance_row[col] = if t < 0.5 * SKY_DISTANCE { t } else { f32::INFINITY };
                let depth = dot(sub(point, depth_origin), depth_axis);
                range = [range[0].min(depth), range[1].max(depth)];
            }
            range
        })
        .reduce(|| [f32::INFINITY, f32::NEG_INFINITY], |a, b| [a[0].min(b[0]), a[1].max(b[1])]);
    Rendered { image, mask, depth: distance, depth_range }
}

/// View `i` of a generated scene, seen by `camera`.
pub fn view(i: usize, camera: Camera, r: Rendered) -> View {
    View { name: format!("view_{i:03}"), camera, image: r.image, mask: Some(r.mask), depth: Some(r.depth) }
}

/// The views of `cams`, each with depths along its own viewing axis, and the nearest depth of
/// content they see.
pub fn render_views<W: Trace + Sync>(world: &W, cams: impl IntoIterator<Item = Camera>) -> (Vec<View>, f32) {
    let mut near = f32::INFINITY;
    let views = cams
        .into_iter()
        .enumerate()
        .map(|(i, cam)| {
            let r = render_view(world, &cam, cam.origin(), cam.forward());
            near = near.min(r.depth_range[0]);
            view(i, cam, r)
        })
        .collect();
    (views, near)
}

/// The scene a forward-facing rig `cams` captures (`cfg` gives the image size and the render
/// path's length): views in the frame of the cameras' LLFF average pose, with focal length
/// `focal`; the `ForwardFacing` extent spanning the depths of content along the mean camera's
/// viewing axis, widened by 10 % towards it and 5 % away; the LLFF spiral as render path.
pub fn forward_facing_scene<W: Trace + Sync>(
    world: &W,
    cams: &[Camera],
    focal: f64,
    cfg: &SyntheticConfig,
    name: String,
    train: Vec<usize>,
    test: Vec<usize>,
) -> Scene {
    let (w, h) = (cfg.width, cfg.height);
    let poses: Vec<Pose> = cams.iter().map(pose::from_camera).collect();
    let (recentred, avg) = pose::recenter(&poses);
    // Depth along the mean camera's viewing axis (−back).
    let mean_origin = [avg[0][3] as f32, avg[1][3] as f32, avg[2][3] as f32];
    let mean_forward = [-avg[0][2] as f32, -avg[1][2] as f32, -avg[2][2] as f32];
    let mut near = f32::INFINITY;
    let mut far = 0.0f32;
    let views = cams
        .iter()
        .zip(&recentred)
        .enumerate()
        .map(|(i, (cam, p))| {
            let r = render_view(world, cam, mean_origin, mean_forward);
            near = near.min(r.depth_range[0]);
            far = far.max(r.depth_range[1]);
            view(i, pose::to_camera(p, w, h, focal), r)
        })
        .collect();
    let (near, far) = (0.9 * near, 1.05 * far);
    let extent = SceneExtent::ForwardFacing { near, far, focal: focal as f32, width: w as f32, height: h as f32 };
    let render_path = pose::llff_spiral(&recentred, near as f64, far as f64, cfg.render_path_views)
        .iter()
        .map(|p| pose::to_camera(p, w, h, focal))
        .collect();
    Scene { name, views, train, test, extent, near, render_path }
}

/// Distance from `centre` to the farthest camera centre.
pub fn farthest(cams: &[Camera], centre: Vec3) -> f32 {
    cams.iter()
        .map(|c| {
            let o = c.origin();
            (0..3).map(|k| (o[k] - centre[k]).powi(2)).sum::<f32>().sqrt()
        })
        .fold(0.0, f32::max)
}
