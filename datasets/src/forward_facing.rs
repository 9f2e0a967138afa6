//! Forward-facing captures in layouts that store poses but no NDC frame (COLMAP): telling them
//! from captures around a scene, depth bounds from sparse points, and the same processing LLFF's
//! `load_llff_data` applies (scale so the nearest bound is `1 / bd_factor`, recentre on the
//! average pose), so a model read here matches the LLFF layout made from it by `imgs2poses`.

use sos_core::camera::{dot, sub, Camera, Vec3};
use std::path::Path;

use sos_core::derived::DerivedSetting;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::pose::{self, Pose};
use crate::text::invalid;

/// Captures whose mean unit viewing direction is at least this long look one way (LLFF's own
/// test for choosing `spherify`): forward-facing captures keep about 1 (flower: 0.99), cameras
/// around a scene far less (0 for a full circle); 0.7 is an angular spread of about 45° around
/// the mean.
pub const FORWARD_FACING_FROM: f64 = 0.7;

/// Length of the mean of the cameras' unit viewing directions.
pub fn mean_viewing_direction(forwards: impl IntoIterator<Item = Vec3>) -> f64 {
    let mut sum = [0.0f64; 3];
    let mut n = 0usize;
    for f in forwards {
        let len = f.iter().map(|v| (*v as f64).powi(2)).sum::<f64>().sqrt().max(1e-12);
        (0..3).for_each(|k| sum[k] += f[k] as f64 / len);
        n += 1;
    }
    sum.iter().map(|s| s * s).sum::<f64>().sqrt() / n.max(1) as f64
}

/// Whether the cameras look one way (see [`FORWARD_FACING_FROM`]).
pub fn looks_one_way(cams: &[&Camera]) -> bool {
    !cams.is_empty() && mean_viewing_direction(cams.iter().map(|c| c.forward())) >= FORWARD_FACING_FROM
}

/// The derived `scene.forward_facing` of an adapter that chose it from the cameras;
/// `without_bounds` says why a capture that looks one way was not read as forward-facing.
pub fn forward_facing_setting(scene: &Scene, without_bounds: &str) -> DerivedSetting {
    let forward = matches!(scene.extent, SceneExtent::ForwardFacing { .. });
    let cams: Vec<&Camera> = scene.train.iter().map(|&i| &scene.views[i].camera).collect();
    let reason = if forward {
        "no `forward_facing`: the cameras look one way".to_string()
    } else if looks_one_way(&cams) {
        format!("no `forward_facing`: the cameras look one way, but {without_bounds}")
    } else {
        "no `forward_facing`: the cameras look in directions spread around the scene".to_string()
    };
    DerivedSetting::new("scene.forward_facing", forward, reason)
}

/// Whether an adapter reads a capture as forward-facing: never with a box (`aabb`) given or
/// `forward_facing = false`; with `forward_facing = true` always; unset, when the training
/// cameras look one way.
pub fn wanted(aabb_given: bool, forward_facing: Option<bool>, views: &[View], train: &[usize]) -> bool {
    match (aabb_given, forward_facing) {
        (true, _) | (false, Some(false)) => false,
        (false, Some(true)) => true,
        (false, None) => looks_one_way(&train.iter().map(|&i| &views[i].camera).collect::<Vec<_>>()),
    }
}

/// Share of a view's points dropped at each end of its depth range, as `imgs2poses` does
/// (its 0.1 and 99.9 percentiles), so a stray point does not set the bound.
const OUTLIER_PERCENT: f64 = 0.1;

/// The near and far depth, along `cam`'s viewing axis, of the `points` it sees: those in front
/// of it that project inside its image. `None` when it sees none.
pub fn depth_bounds(cam: &Camera, points: impl IntoIterator<Item = [f64; 3]>) -> Option<[f64; 2]> {
    let (o, f) = (cam.origin(), cam.forward());
    let mut depths: Vec<f64> = points
        .into_iter()
        .filter_map(|p| {
            let p32 = p.map(|v| v as f32);
            let depth = dot(sub(p32, o), f);
            let [u, v] = cam.project(p32)?;
            let inside = (0.0..cam.width as f32).contains(&u) && (0.0..cam.height as f32).contains(&v);
            (depth > 0.0 && inside).then_some(depth as f64)
        })
        .collect();
    if depths.is_empty() {
        return None;
    }
    let lo = pose::percentile(&mut depths, OUTLIER_PERCENT);
    let hi = pose::percentile(&mut depths, 100.0 - OUTLIER_PERCENT);
    Some([lo, hi])
}

/// Length of the render path of forward-facing captures read from layouts without one
/// (LLFF's default).
pub const FORWARD_PATH_VIEWS: usize = 120;

/// Refuses a negative `bd_factor` (a sign slip would silently mean "no scaling", as 0 does).
pub fn check_bd_factor(root: &Path, bd_factor: f64) -> Result<(), DatasetError> {
    if bd_factor >= 0.0 && bd_factor.is_finite() {
        return Ok(());
    }
    Err(invalid(root, format!("config key `bd_factor` must be 0 (no scaling) or positive, got {bd_factor}")))
}

/// How a forward-facing capture is brought into the NDC frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Processing {
    /// Scale so the nearest bound becomes `1 / bd_factor`; 0: no scaling.
    pub bd_factor: f64,
    /// Express the poses in the frame of their average pose.
    pub recenter: bool,
    /// Length of the LLFF spiral render path.
    pub render_path_views: usize,
}

/// The forward-facing scene of `views` whose content lies between depths `bounds` (the nearest
/// and farthest over the views), processed as LLFF's loader does: translations scaled by
/// `1 / (bd_factor · near)`, poses recentred, the `ForwardFacing` extent from 0.9 · near to far
/// with the first training camera's focal length and size, the LLFF spiral as render path.
/// Each camera keeps its own intrinsics.
pub fn forward_facing_scene(
    name: String,
    views: Vec<View>,
    train: Vec<usize>,
    test: Vec<usize>,
    bounds: [f64; 2],
    how: Processing,
) -> Scene {
    let sc = if how.bd_factor > 0.0 { 1.0 / (how.bd_factor * bounds[0]) } else { 1.0 };
    let mut poses: Vec<Pose> = views.iter().map(|v| pose::from_camera(&v.camera)).collect();
    for p in &mut poses {
        (0..3).for_each(|r| p[r][3] *= sc);
    }
    if how.recenter {
        poses = pose::recenter(&poses).0;
    }
    let views: Vec<View> = views
        .into_iter()
        .zip(&poses)
        .map(|(v, p)| {
            let c = &v.camera;
            let (fx, fy, cx, cy) = (c.fx as f64, c.fy as f64, c.cx as f64, c.cy as f64);
            View { camera: pose::to_camera_general(p, c.width, c.height, fx, fy, cx, cy), ..v }
        })
        .collect();
    let [near, far] = bounds.map(|b| b * sc);
    let reference = &views[train[0]].camera;
    let to_cam = |p: &Pose| {
        let c = reference;
        pose::to_camera_general(p, c.width, c.height, c.fx as f64, c.fy as f64, c.cx as f64, c.cy as f64)
    };
    let render_path = pose::llff_spiral(&poses, near, far, how.render_path_views).iter().map(to_cam).collect();
    let extent = SceneExtent::ForwardFacing {
        near: (0.9 * near) as f32,
        far: far as f32,
        focal: reference.fx,
        width: reference.width as f32,
        height: reference.height as f32,
    };
    // The forward-facing extent's own near plane already bounds the samples.
    Scene { name, views, train, test, extent, near: 0.0, render_path }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synthetic::{generate, Rig, SyntheticConfig};

    fn scene(rig: Rig) -> Scene {
        generate(&SyntheticConfig { rig, width: 64, height: 48, views: 12, ..Default::default() })
    }

    #[test]
    fn rigs_are_told_apart_by_their_viewing_directions() {
        for (rig, one_way) in [(Rig::ForwardFacing, true), (Rig::ObjectCentric, false), (Rig::Unbounded, false)] {
            let s = scene(rig);
            let cams: Vec<&Camera> = s.views.iter().map(|v| &v.camera).collect();
            assert_eq!(looks_one_way(&cams), one_way, "{rig:?}");
        }
        assert!(!looks_one_way(&[]));
    }

    #[test]
    fn depth_bounds_take_the_points_in_view() {
        let s = scene(Rig::ForwardFacing);
        let cam = &s.views[0].camera;
        let (o, f) = (cam.origin(), cam.forward());
        let at = |d: f32| [0, 1, 2].map(|k| (o[k] + d * f[k]) as f64);
        let behind = at(-5.0);
        // Far off to the side: in front of the camera, outside its image.
        let aside = [0, 1, 2].map(|k| (o[k] + 2.0 * f[k] + 50.0 * cam.cam_to_world[k][0]) as f64);
        let b = depth_bounds(cam, [at(1.0), at(3.0), at(2.0), behind, aside]).unwrap();
        assert!((b[0] - 1.0).abs() < 0.01 && (b[1] - 3.0).abs() < 0.01, "{b:?}");
        assert_eq!(depth_bounds(cam, [behind, aside]), None);
    }

    #[test]
    fn processing_puts_the_nearest_bound_at_one_over_bd_factor_and_recentres() {
        let s = scene(Rig::ForwardFacing);
        let how = Processing { bd_factor: 0.75, recenter: true, render_path_views: 10 };
        let out =
            forward_facing_scene(s.name.clone(), s.views.clone(), s.train.clone(), s.test.clone(), [2.0, 8.0], how);
        let SceneExtent::ForwardFacing { near, far, .. } = out.extent else { panic!("{:?}", out.extent) };
        assert!((near - 0.9 / 0.75).abs() < 1e-5 && (far - 4.0 / 0.75).abs() < 1e-5, "{near} {far}");
        assert_eq!(out.render_path.len(), 10);
        out.validate().unwrap();
        // Recentred: the mean camera centre is the origin, the mean axis −Z.
        let n = out.views.len() as f32;
        let mean: Vec<f32> = (0..3).map(|k| out.views.iter().map(|v| v.camera.origin()[k]).sum::<f32>() / n).collect();
        assert!(mean.iter().all(|m| m.abs() < 1e-4), "{mean:?}");
        let mean_forward = mean_viewing_direction(out.views.iter().map(|v| v.camera.forward()));
        assert!(mean_forward > 0.99);
        // Scaling keeps the views' rays' directions and the cameras' intrinsics.
        for (a, b) in s.views.iter().zip(&out.views) {
            assert_eq!((a.camera.fx, a.camera.cx, a.camera.width), (b.camera.fx, b.camera.cx, b.camera.width));
        }
    }
}
