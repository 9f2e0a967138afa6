//! Building checked views shared by the loaders: cameras validated where the error can name
//! the camera file, images checked against their camera, masks thresholded, and the default
//! extent of layouts that store no scene bounds.

use std::path::Path;

use sos_core::camera::{Camera, Vec3};
use sos_core::derived::DerivedSetting;
use sos_core::image::{GrayImage, RgbImage};
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{solve3, Scene, SceneExtent, View};

use crate::forward_facing::looks_one_way;
use crate::image_files::load_mask;
use crate::pose::{self, Pose};
use crate::text::invalid;

/// Pinhole intrinsics in pixels (pixel centres at +0.5).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Focal length along x.
    pub fx: f64,
    /// Focal length along y.
    pub fy: f64,
    /// Principal point x.
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
}

impl Intrinsics {
    /// The intrinsics of a camera.
    pub fn of(cam: &Camera) -> Self {
        Intrinsics {
            width: cam.width,
            height: cam.height,
            fx: cam.fx as f64,
            fy: cam.fy as f64,
            cx: cam.cx as f64,
            cy: cam.cy as f64,
        }
    }

    /// The 3x3 calibration matrix.
    pub fn k(&self) -> [[f64; 3]; 3] {
        [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
    }
}

/// The smallest focal length [`checked_camera`] accepts, as a share of the image's size: a
/// tenth, a field of view of 157°, wider than any rectilinear lens.
pub const MIN_FOCAL_SHARE: f64 = 0.1;

/// A camera from `pose` (OpenGL axes) and `k`, checked; errors name `file` and `what`
/// (e.g. "image 12") and say what to fix.
pub fn checked_camera(file: &Path, what: &str, pose: &Pose, k: &Intrinsics) -> Result<Camera, DatasetError> {
    let r = [0, 1, 2].map(|i| [pose[i][0], pose[i][1], pose[i][2]]);
    if let Some(problem) = pose::rotation_problem(&r) {
        return Err(invalid(file, format!("{what}: {problem}; fix or drop this camera")));
    }
    if (0..3).any(|i| !pose[i][3].is_finite()) {
        return Err(invalid(file, format!("{what}: camera centre is not finite; fix or drop this camera")));
    }
    if k.width == 0 || k.height == 0 {
        return Err(invalid(file, format!("{what}: zero image size {}x{}", k.width, k.height)));
    }
    // Intrinsics written in normalised units (focal ~1, principal point ~0.5) pass as a
    // pinhole of almost 180° whose axis meets the image's corner: refused, not trained on.
    let (w, h) = (k.width as f64, k.height as f64);
    if k.fx < MIN_FOCAL_SHARE * w || k.fy < MIN_FOCAL_SHARE * h {
        return Err(invalid(
            file,
            format!(
                "{what}: focal length {} x {} px is under a tenth of the {}x{} image (a field of view \
                 over 157°); are the intrinsics normalised? Give them in pixels",
                k.fx, k.fy, k.width, k.height
            ),
        ));
    }
    if !((-w..=2.0 * w).contains(&k.cx) && (-h..=2.0 * h).contains(&k.cy)) {
        return Err(invalid(
            file,
            format!(
                "{what}: principal point ({}, {}) lies far outside the {}x{} image; give it in pixels",
                k.cx, k.cy, k.width, k.height
            ),
        ));
    }
    let cam = pose::to_camera_general(pose, k.width, k.height, k.fx, k.fy, k.cx, k.cy);
    cam.validate().map_err(|e| invalid(file, format!("{what}: {e}; fix the intrinsics or the pose")))?;
    Ok(cam)
}

/// Reads an image and checks it has the size its camera file states.
pub fn load_image_sized(path: &Path, width: u32, height: u32, source: &Path) -> Result<RgbImage, DatasetError> {
    let img = RgbImage::load(path)?;
    if (img.width, img.height) != (width as usize, height as usize) {
        return Err(invalid(
            path,
            format!(
                "image is {}x{} but {} says {width}x{height}; use the original images or fix the \
                 camera size",
                img.width,
                img.height,
                source.display()
            ),
        ));
    }
    Ok(img)
}

/// The optional mask at `path` (thresholded at 0.5), checked against the image size.
pub fn optional_mask(path: Option<&Path>, width: usize, height: usize) -> Result<Option<GrayImage>, DatasetError> {
    match path {
        Some(p) => Ok(Some(load_mask(p, width, height)?)),
        None => Ok(None),
    }
}

/// The scene name: the folder's name, or `fallback`.
pub fn scene_name(root: &Path, fallback: &str) -> String {
    root.file_name().and_then(|n| n.to_str()).unwrap_or(fallback).to_string()
}

/// The extent of layouts that store no scene bounds (COLMAP, BlendedMVS, CO3D, opaque Blender
/// captures): the box `aabb` when given, else `Unbounded` around the point the training
/// cameras look at, radius half the median camera distance to it (see [`camera_focus`]).
pub fn extent_of(views: &[View], train: &[usize], aabb: Option<[Vec3; 2]>) -> SceneExtent {
    if let Some([min, max]) = aabb {
        return SceneExtent::Bounded { min, max };
    }
    let cams: Vec<&Camera> = train.iter().map(|&i| &views[i].camera).collect();
    let (center, median) = camera_focus(&cams);
    let radius = if median > 1e-6 { 0.5 * median } else { 1.0 };
    SceneExtent::Unbounded { center, radius }
}

/// The point the cameras look at (least-squares intersection of their viewing axes; their
/// mean centre when the axes are parallel) and the median camera distance to it.
pub fn camera_focus(cams: &[&Camera]) -> (Vec3, f32) {
    let mut a = [[0.0f64; 3]; 3];
    let mut b = [0.0f64; 3];
    let mut mean = [0.0f64; 3];
    for cam in cams {
        let (o, d) = (cam.origin(), cam.forward());
        for r in 0..3 {
            mean[r] += o[r] as f64 / cams.len() as f64;
            for c in 0..3 {
                let m = if r == c { 1.0 } else { 0.0 } - (d[r] * d[c]) as f64;
                a[r][c] += m;
                b[r] += m * o[c] as f64;
            }
        }
    }
    let focus = solve3(a, b).filter(|p| p.iter().all(|v| v.is_finite()));
    let center = focus.unwrap_or(mean);
    let mut dists: Vec<f64> = cams
        .iter()
        .map(|c| {
            let o = c.origin();
            (0..3).map(|k| (o[k] as f64 - center[k]).powi(2)).sum::<f64>().sqrt()
        })
        .collect();
    dists.sort_by(f64::total_cmp);
    let median = dists.get(dists.len() / 2).copied().unwrap_or(0.0);
    (center.map(|v| v as f32), median as f32)
}

/// Why layouts without stored bounds get the unbounded extent of [`extent_of`].
pub const NO_AABB: &str = "no `aabb`: unbounded around the point the training cameras look at";

/// The derived-setting line of an adapter that chose the extent itself. An unbounded extent
/// around cameras that look one way says it may be far too small: their axes meet, if at all,
/// near the cameras, and without depth bounds nothing says where the content lies.
pub fn extent_setting(scene: &Scene, reason: &str) -> DerivedSetting {
    let cams: Vec<&Camera> = scene.train.iter().map(|&i| &scene.views[i].camera).collect();
    let caution = match scene.extent {
        SceneExtent::Unbounded { .. } if looks_one_way(&cams) => {
            "; the cameras look one way and the layout gives no depth bounds, so this sphere may hold \
             little of the content: give `aabb` (or use a layout with depth bounds: LLFF, COLMAP with points3D)"
        }
        _ => "",
    };
    DerivedSetting::new("scene.extent", scene.extent, format!("{reason}{caution}"))
}

/// The derived settings of an adapter whose extent, where the config gives no `aabb`, is the
/// unbounded one of [`extent_of`].
pub fn unbounded_unless_aabb(aabb: Option<[Vec3; 2]>, scene: &Scene) -> Vec<DerivedSetting> {
    match aabb {
        Some(_) => Vec::new(),
        None => vec![extent_setting(scene, NO_AABB)],
    }
}

/// Checks a user-given box.
pub fn check_aabb(root: &Path, aabb: Option<[Vec3; 2]>) -> Result<(), DatasetError> {
    match aabb {
        Some([min, max]) if !(0..3).all(|k| min[k] < max[k] && min[k].is_finite() && max[k].is_finite()) => {
            Err(invalid(root, "config key `aabb`: min must be below max on every axis"))
        }
        _ => Ok(()),
    }
}
