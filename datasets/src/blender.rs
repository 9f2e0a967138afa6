//! Dataset kind `blender`: object-centric captures in the NeRF-synthetic ("Blender") layout.
//!
//! `transforms_train.json` and `transforms_test.json` (or `transforms_val.json`, see
//! `test_split`) each hold `camera_angle_x` (horizontal field of view, radians) and `frames`
//! with `file_path` (relative to the scene folder, with or without an image extension) and a
//! 4x4 camera-to-world `transform_matrix` in OpenGL axes. RGBA images are composited on white
//! (or black). Optional masks mirror the image paths under `masks/`: the mask of
//! `train/r_0.png` is `masks/train/r_0.<png|jpg>`; foreground = value > 0.5.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::camera::{add, cross, dot, norm, normalize, scale, sub, Camera, Vec3};
use sos_core::image::RgbImage;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use sos_core::derived::DerivedSetting;

use crate::adapter::{register_dataset, require_folder};
use crate::image_files::{find_image, find_with_stem, load_mask, stem};
use crate::text::invalid;
use crate::views::{camera_focus, check_aabb, extent_of, extent_setting};

/// Configuration of the `blender` dataset (`[scene] kind = "blender"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BlenderConfig {
    /// Scene folder (holding `transforms_*.json`), relative to the config file's folder.
    pub path: PathBuf,
    /// Composite RGBA images on white (default true) or on black.
    pub white_background: bool,
    /// Integer downscale factor of the images (default 1), box-filtered.
    pub downscale: u32,
    /// Split used for the held-out views: `"test"` (default) or `"val"`.
    pub test_split: String,
    /// Scene bounds `[min, max]`. Absent: derived from the capture. Cut-out images (most
    /// training views with a transparent background) give a cube around the point the cameras
    /// look at that holds every view's opaque silhouette; opaque images give the unbounded extent
    /// around that point that the COLMAP adapter uses, so the same capture trains alike in
    /// either layout.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aabb: Option<[Vec3; 2]>,
    /// Distance from the cameras below which nothing is sampled. Absent: 0.9 x the nearest
    /// training camera's distance to the box (given or derived from cut-out images), else 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub near: Option<f32>,
}

impl Default for BlenderConfig {
    fn default() -> Self {
        BlenderConfig {
            path: PathBuf::new(),
            white_background: true,
            downscale: 1,
            test_split: "test".into(),
            aabb: None,
            near: None,
        }
    }
}

register_dataset!(
    BlenderConfig,
    "blender",
    "NeRF-synthetic layout (transforms_{train,test}.json, RGBA on white)",
    load_blender,
    derived_blender
);

/// A pixel counts as background when its alpha is below this.
const OPAQUE_ALPHA: f32 = 0.5;
/// A view is a cut-out when at least this fraction of its pixels is background.
const CUT_OUT_FRACTION: f32 = 0.01;
/// Margin of the derived box over the silhouettes' bound.
const BOX_MARGIN: f32 = 1.2;
/// `near` as a fraction of the nearest training camera's distance to the derived box.
const NEAR_FRACTION: f32 = 0.9;

/// What the adapter chose where the config left `aabb` or `near` unset.
fn derived_blender(cfg: &BlenderConfig, _root: &Path, scene: &Scene) -> Vec<DerivedSetting> {
    let mut out = Vec::new();
    if cfg.aabb.is_none() {
        let reason = match scene.extent {
            SceneExtent::Bounded { .. } => "no `aabb`; cut-out images: a cube holding every view's silhouette",
            _ => "no `aabb`; opaque images: unbounded around the point the cameras look at",
        };
        out.push(extent_setting(scene, reason));
    }
    if cfg.near.is_none() {
        let reason = match scene.extent {
            SceneExtent::Bounded { .. } => "no `near`: 0.9 x the nearest camera's distance to the box",
            _ => "no `near`: the unbounded extent starts at the cameras",
        };
        out.push(DerivedSetting::new("scene.near", format!("{:.3}", scene.near), reason));
    }
    out
}

#[derive(Deserialize)]
struct Transforms {
    camera_angle_x: f64,
    frames: Vec<Frame>,
}

#[derive(Deserialize)]
struct Frame {
    file_path: String,
    transform_matrix: Vec<Vec<f64>>,
}

/// A frame with its image located and its pose checked.
struct FrameFile {
    image: PathBuf,
    /// `file_path` without a leading `./` and extension, for the mask lookup.
    rel: String,
    cam_to_world: [[f32; 4]; 3],
}

fn read_split(root: &Path, split: &str) -> Result<(f64, Vec<FrameFile>), DatasetError> {
    let path = root.join(format!("transforms_{split}.json"));
    let text = std::fs::read_to_string(&path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => DatasetError::Missing {
            path: path.clone(),
            hint: "a Blender-layout scene needs transforms_train.json and transforms_test.json".into(),
        },
        _ => invalid(&path, format!("cannot read: {e}")),
    })?;
    let t: Transforms =
        serde_json::from_str(&text).map_err(|e| invalid(&path, format!("malformed transforms JSON: {e}")))?;
    if !(t.camera_angle_x.is_finite() && t.camera_angle_x > 0.0 && t.camera_angle_x < std::f64::consts::PI) {
        return Err(invalid(&path, format!("camera_angle_x must be in (0, π), got {}", t.camera_angle_x)));
    }
    let frames = t
        .frames
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let m = &f.transform_matrix;
            if m.len() != 4 || m.iter().any(|r| r.len() != 4) {
                return Err(invalid(&path, format!("frame {i}: transform_matrix must be 4x4")));
            }
            if m.iter().flatten().any(|v| !v.is_finite()) {
                return Err(invalid(&path, format!("frame {i}: transform_matrix has NaN or inf")));
            }
            // A transposed (column-major) matrix keeps an orthonormal 3x3 block but carries
            // its translation in the last row, which would put every camera at the origin.
            if m[3].iter().zip([0.0, 0.0, 0.0, 1.0]).any(|(a, b)| (a - b).abs() > 1e-6) {
                return Err(invalid(
                    &path,
                    format!(
                        "frame {i}: the last row of transform_matrix is {:?}, not [0, 0, 0, 1]; \
                         write the camera-to-world matrix row by row (is it transposed?)",
                        m[3]
                    ),
                ));
            }
            let mut cam_to_world = [[0.0f32; 4]; 3];
            for r in 0..3 {
                for c in 0..4 {
                    cam_to_world[r][c] = m[r][c] as f32;
                }
            }
            // Check the rotation here, where the error can name the JSON file and frame.
            frame_camera(1, 1, t.camera_angle_x, cam_to_world)
                .validate()
                .map_err(|e| invalid(&path, format!("frame {i}: transform_matrix: {e}")))?;
            let rel = f.file_path.trim_start_matches("./").to_string();
            let image = find_image(root, &rel).ok_or_else(|| DatasetError::Missing {
                path: root.join(&rel),
                hint: format!("image of frame {i} in {} (tried .png/.jpg)", path.display()),
            })?;
            let rel = match Path::new(&rel).extension() {
                Some(_) if image == root.join(&rel) => {
                    rel[..rel.len() - image.extension().map_or(0, |e| e.len() + 1)].to_string()
                }
                _ => rel,
            };
            Ok(FrameFile { image, rel, cam_to_world })
        })
        .collect::<Result<_, _>>()?;
    Ok((t.camera_angle_x, frames))
}

/// The pinhole camera of a `width x height` frame with horizontal field of view `angle`
/// (radians), centred principal point, square pixels.
fn frame_camera(width: usize, height: usize, angle: f64, cam_to_world: [[f32; 4]; 3]) -> Camera {
    let focal = (0.5 * width as f64 / (0.5 * angle).tan()) as f32;
    Camera {
        width: width as u32,
        height: height as u32,
        fx: focal,
        fy: focal,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
        cam_to_world,
    }
}

/// Reads an image, compositing its alpha (if any) on `background`; also returns the alpha
/// channel (all ones for images without one).
fn load_composited(path: &Path, background: f32) -> Result<(RgbImage, Vec<f32>), DatasetError> {
    let img = sos_core::image::open_image(path, "image", "; re-export it as PNG or JPEG")?;
    let rgba = img.to_rgba32f();
    let (w, h) = rgba.dimensions();
    if w == 0 || h == 0 {
        return Err(invalid(path, "image has zero size"));
    }
    let data = rgba
        .pixels()
        .flat_map(|p| {
            let a = p.0[3];
            [0, 1, 2].map(|k| p.0[k] * a + background * (1.0 - a))
        })
        .collect();
    let alpha = rgba.pixels().map(|p| p.0[3]).collect();
    Ok((RgbImage { width: w as usize, height: h as usize, data }, alpha))
}

/// How a view's opaque pixels lie around the direction from its camera to `focus`.
struct Silhouette {
    /// At least [`CUT_OUT_FRACTION`] of the pixels are background.
    cut_out: bool,
    /// Largest angle (radians) between that direction and an opaque pixel's ray; `None` when
    /// no pixel is opaque.
    angle: Option<f32>,
}

fn silhouette(camera: &Camera, alpha: &[f32], focus: Vec3) -> Silhouette {
    let to_focus = normalize(sub(focus, camera.origin()));
    let width = camera.width as usize;
    let mut background = 0usize;
    let mut min_cos = f32::INFINITY;
    for (i, &a) in alpha.iter().enumerate() {
        if a < OPAQUE_ALPHA {
            background += 1;
            continue;
        }
        let (x, y) = ((i % width) as f32 + 0.5, (i / width) as f32 + 0.5);
        min_cos = min_cos.min(dot(normalize(camera.direction(x, y)), to_focus));
    }
    // A view that does not look at the focus says nothing about the object around it.
    let sees_focus = camera
        .project(focus)
        .is_some_and(|[x, y]| (0.0..camera.width as f32).contains(&x) && (0.0..camera.height as f32).contains(&y));
    Silhouette {
        cut_out: background as f32 >= CUT_OUT_FRACTION * alpha.len() as f32,
        angle: (sees_focus && min_cos.is_finite()).then(|| min_cos.clamp(-1.0, 1.0).acos()),
    }
}

/// The derived extent and `near`: where most training views are cut-outs, a cube around
/// `focus` holding every silhouette cone of a view that looks at the focus (kept clear of the
/// nearest camera); else the unbounded extent of opaque layouts.
fn derived_extent(views: &[View], train: &[usize], silhouettes: &[Silhouette], focus: Vec3) -> (SceneExtent, f32) {
    let cut_outs = train.iter().filter(|&&i| silhouettes[i].cut_out).count();
    let cut_out = 2 * cut_outs > train.len();
    // Each silhouette cone bounds the object; at the focus distance its radius is d tan θ.
    let half = train
        .iter()
        .filter_map(|&i| {
            let angle = silhouettes[i].angle?.min(1.4);
            Some(norm(sub(views[i].camera.origin(), focus)) * angle.tan())
        })
        .fold(0.0f32, f32::max);
    // The box stays inside the cameras' ring: no camera inside it (the L∞ distance).
    let clear = train
        .iter()
        .map(|&i| {
            let d = sub(views[i].camera.origin(), focus);
            d.iter().fold(0.0f32, |m, v| m.max(v.abs()))
        })
        .fold(f32::INFINITY, f32::min);
    let half = (BOX_MARGIN * half).min(NEAR_FRACTION * clear);
    if !(cut_out && half > 0.0 && half.is_finite()) {
        return (extent_of(views, train, None), 0.0);
    }
    let (min, max) = (focus.map(|v| v - half), focus.map(|v| v + half));
    (SceneExtent::Bounded { min, max }, near_of_box(views, train, min, max))
}

/// [`NEAR_FRACTION`] x the nearest training camera's distance to the box `[min, max]`.
fn near_of_box(views: &[View], train: &[usize], min: Vec3, max: Vec3) -> f32 {
    let nearest = train
        .iter()
        .map(|&i| {
            let o = views[i].camera.origin();
            let outside = [0, 1, 2].map(|k| (min[k] - o[k]).max(o[k] - max[k]).max(0.0));
            norm(outside)
        })
        .fold(f32::INFINITY, f32::min);
    if nearest.is_finite() {
        NEAR_FRACTION * nearest
    } else {
        0.0
    }
}

/// Loads a Blender-layout scene from folder `root` (the config's `path` already resolved).
pub fn load_blender(cfg: &BlenderConfig, root: &Path) -> Result<Scene, DatasetError> {
    if cfg.downscale == 0 {
        return Err(invalid(root, "config key `downscale` must be ≥ 1"));
    }
    if cfg.test_split != "test" && cfg.test_split != "val" {
        return Err(invalid(
            root,
            format!("config key `test_split` must be \"test\" or \"val\", got {:?}", cfg.test_split),
        ));
    }
    check_aabb(root, cfg.aabb)?;
    if let Some(near) = cfg.near {
        if !(near >= 0.0 && near.is_finite()) {
            return Err(invalid(root, "config key `near` must be zero or positive"));
        }
    }
    require_folder(root, "a Blender-layout scene folder with transforms_*.json")?;
    let (angle_train, train_frames) = read_split(root, "train")?;
    let (angle_test, test_frames) = read_split(root, &cfg.test_split)?;
    if train_frames.is_empty() {
        return Err(invalid(&root.join("transforms_train.json"), "no frames"));
    }
    let background = if cfg.white_background { 1.0 } else { 0.0 };
    let n_train = train_frames.len();
    let all: Vec<(f64, FrameFile)> = train_frames
        .into_iter()
        .map(|f| (angle_train, f))
        .chain(test_frames.into_iter().map(|f| (angle_test, f)))
        .collect();
    let mask_root = root.join("masks");
    // The point the training cameras look at, from their poses alone (before any image loads).
    let train_poses: Vec<Camera> =
        all[..n_train].iter().map(|(angle, f)| frame_camera(1, 1, *angle, f.cam_to_world)).collect();
    let focus = camera_focus(&train_poses.iter().collect::<Vec<_>>()).0;
    let loaded: Vec<(View, Silhouette)> = all
        .par_iter()
        .map(|(angle, f)| {
            let (mut image, alpha) = load_composited(&f.image, background)?;
            let full = frame_camera(image.width, image.height, *angle, f.cam_to_world);
            let outline = silhouette(&full, &alpha, focus);
            drop(alpha);
            let d = cfg.downscale as usize;
            // Fewest pixels a side a downscaled view may keep.
            const MIN_SIDE: usize = 8;
            if d > 1 {
                let (w, h) = (image.width / d, image.height / d);
                if w.min(h) < MIN_SIDE {
                    return Err(invalid(
                        &f.image,
                        format!(
                            "config key `downscale` = {d} leaves {w}x{h} pixels of this {}x{} image; views need at \
                             least {MIN_SIDE} a side: lower `downscale`",
                            image.width, image.height
                        ),
                    ));
                }
                image = image.resized(w, h);
            }
            let (w, h) = (image.width, image.height);
            let camera = frame_camera(w, h, *angle, f.cam_to_world);
            camera.validate().map_err(|e| invalid(&f.image, format!("pose of this frame: {e}")))?;
            let rel = Path::new(&f.rel);
            let mask_dir = mask_root.join(rel.parent().unwrap_or(Path::new("")));
            let mask = match find_with_stem(&mask_dir, stem(rel)) {
                Some(p) => Some(load_mask(&p, w, h)?),
                None => None,
            };
            Ok((View { name: f.rel.replace(['/', '\\'], "_"), camera, image, mask, depth: None }, outline))
        })
        .collect::<Result<_, DatasetError>>()?;
    let (views, silhouettes): (Vec<View>, Vec<Silhouette>) = loaded.into_iter().unzip();
    if mask_root.is_dir() && views.iter().all(|v| v.mask.is_none()) {
        return Err(invalid(
            &mask_root,
            "no mask mirrors an image path; the mask of train/r_0.png must be masks/train/r_0.png",
        ));
    }
    let name = root.file_name().and_then(|n| n.to_str()).unwrap_or("blender").to_string();
    let train: Vec<usize> = (0..n_train).collect();
    let (extent, derived_near) = match cfg.aabb {
        Some([min, max]) => (SceneExtent::Bounded { min, max }, near_of_box(&views, &train, min, max)),
        None => derived_extent(&views, &train, &silhouettes, focus),
    };
    let render_path = orbit_path_around(&views, &train, &extent);
    Ok(Scene {
        name,
        train,
        test: (n_train..views.len()).collect(),
        views,
        extent,
        near: cfg.near.unwrap_or(derived_near),
        render_path,
    })
}

/// A circle of `n` cameras around `centre` at the training cameras' mean distance and height
/// (along their mean up axis), like the 40-view circle of NeRF's Blender loader; empty when the
/// cameras sit on the axis.
pub(crate) fn orbit_path(train: &[&Camera], centre: Vec3, n: usize) -> Vec<Camera> {
    let Some(first) = train.first() else {
        return Vec::new();
    };
    let mut up = [0.0; 3];
    let (mut dist, mut height) = (0.0, 0.0);
    for c in train {
        up = add(up, c.rotate([0.0, 1.0, 0.0]));
    }
    let up = normalize(up);
    for c in train {
        let d = sub(c.origin(), centre);
        dist += norm(d) / train.len() as f32;
        height += dot(d, up) / train.len() as f32;
    }
    let d0 = sub(first.origin(), centre);
    let e1 = normalize(sub(d0, scale(up, dot(d0, up))));
    let e2 = cross(up, e1);
    let ring = (dist * dist - height * height).max(0.0).sqrt();
    if ring < 1e-3 * dist.max(1e-6) || dot(e1, e1) < 0.5 {
        return Vec::new();
    }
    (0..n)
        .map(|i| {
            let (s, c) = (std::f32::consts::TAU * i as f32 / n as f32).sin_cos();
            let around = add(scale(e1, ring * c), scale(e2, ring * s));
            let eye = add(add(centre, scale(up, height)), around);
            Camera::look_at(eye, centre, up, first.width, first.height, first.fx)
        })
        .collect()
}

/// The 40-view orbit of [`orbit_path`] around the centre of a bounded or unbounded extent
/// (empty for forward-facing extents, whose render path is the LLFF spiral).
pub(crate) fn orbit_path_around(views: &[View], train: &[usize], extent: &SceneExtent) -> Vec<Camera> {
    let centre = match *extent {
        SceneExtent::Bounded { min, max } => [0, 1, 2].map(|k| 0.5 * (min[k] + max[k])),
        SceneExtent::Unbounded { center, .. } => center,
        SceneExtent::ForwardFacing { .. } => return Vec::new(),
    };
    let cams: Vec<&Camera> = train.iter().map(|&i| &views[i].camera).collect();
    orbit_path(&cams, centre, 40)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::write_blender;
    use crate::synthetic::{generate, Rig, SyntheticConfig, OBJECT_CENTRE, OBJECT_RADIUS, ROOM_MAX, ROOM_MIN};

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("sos-blender-{}-{name}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn room_cfg(dir: &Path) -> BlenderConfig {
        BlenderConfig {
            path: dir.to_path_buf(),
            aabb: Some([ROOM_MIN, ROOM_MAX]),
            near: Some(0.0),
            ..Default::default()
        }
    }

    #[test]
    fn round_trip_of_the_synthetic_scene() {
        let scene = generate(&SyntheticConfig {
            rig: Rig::ObjectCentric,
            width: 96,
            height: 72,
            views: 12,
            ..Default::default()
        });
        let dir = temp_dir("rt");
        write_blender(&scene, &dir).unwrap();
        let loaded = load_blender(&room_cfg(&dir), &dir).unwrap();
        loaded.validate().unwrap();
        assert_eq!((loaded.train.len(), loaded.test.len()), (10, 2));
        // Views come back train first, then test.
        let order: Vec<usize> = scene.train.iter().chain(&scene.test).copied().collect();
        for (&i, l) in order.iter().zip(&loaded.views) {
            let o = &scene.views[i];
            assert_eq!(o.camera.cam_to_world, l.camera.cam_to_world, "view {}", o.name);
            assert!((o.camera.fx - l.camera.fx).abs() < 1e-3 && l.camera.cx == 48.0);
            let err = o.image.data.iter().zip(&l.image.data).map(|(p, q)| (p - q).abs()).fold(0.0, f32::max);
            assert!(err <= 0.5 / 255.0 + 1e-5, "view {}: {err}", o.name);
            assert_eq!(o.mask, l.mask, "view {}", o.name);
        }
        assert_eq!(loaded.extent, SceneExtent::Bounded { min: ROOM_MIN, max: ROOM_MAX });
        assert_eq!(loaded.render_path.len(), 40);
        for cam in &loaded.render_path {
            cam.validate().unwrap();
        }
        // The val split is written as a copy of test.
        let val = load_blender(&BlenderConfig { test_split: "val".into(), ..room_cfg(&dir) }, &dir).unwrap();
        assert_eq!(val.test.len(), 2);
        // Downscaling halves images and focal lengths; full-size masks are then an error.
        let half = load_blender(&BlenderConfig { downscale: 2, ..room_cfg(&dir) }, &dir);
        let err = half.map(|_| ()).unwrap_err().to_string();
        assert!(err.contains("masks") && err.contains("resize"), "{err}");
        std::fs::remove_dir_all(dir.join("masks")).unwrap();
        let half = load_blender(&BlenderConfig { downscale: 2, ..room_cfg(&dir) }, &dir).unwrap();
        assert_eq!((half.views[0].image.width, half.views[0].image.height), (48, 36));
        assert!((half.views[0].camera.fx - loaded.views[0].camera.fx / 2.0).abs() < 1e-3);
        std::fs::remove_dir_all(dir).ok();
    }

    fn write_minimal(dir: &Path, json: &str) {
        std::fs::write(dir.join("transforms_train.json"), json).unwrap();
        let test = r#"{"camera_angle_x": 0.7, "frames": []}"#;
        std::fs::write(dir.join("transforms_test.json"), test).unwrap();
    }

    const ONE_FRAME: &str = r#"{"camera_angle_x": 0.6911, "frames": [{"file_path": "./train/r_0",
        "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]}]}"#;

    #[test]
    fn rgba_is_composited_on_the_background() {
        let dir = temp_dir("rgba");
        std::fs::create_dir_all(dir.join("train")).unwrap();
        let mut img = image::RgbaImage::new(4, 2);
        for (x, _, p) in img.enumerate_pixels_mut() {
            *p = image::Rgba([255, 0, 0, if x < 2 { 0 } else { 255 }]);
        }
        img.save(dir.join("train/r_0.png")).unwrap();
        write_minimal(&dir, ONE_FRAME);
        let white = BlenderConfig { path: dir.clone(), ..Default::default() };
        let white = load_blender(&white, &dir).unwrap();
        let v = &white.views[0];
        assert_eq!(v.image.pixel(0, 0), [1.0, 1.0, 1.0]);
        assert_eq!(v.image.pixel(3, 1), [1.0, 0.0, 0.0]);
        assert!((v.camera.fx - 2.0 / (0.6911f32 / 2.0).tan()).abs() < 1e-4);
        let black = BlenderConfig { white_background: false, path: dir.clone(), ..Default::default() };
        let black = load_blender(&black, &dir).unwrap();
        assert_eq!(black.views[0].image.pixel(0, 0), [0.0, 0.0, 0.0]);
        assert!(black.test.is_empty() && black.views[0].mask.is_none());
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn hostile_inputs_are_errors_naming_the_file() {
        let dir = temp_dir("bad");
        std::fs::create_dir_all(dir.join("train")).unwrap();
        image::RgbImage::new(4, 2).save(dir.join("train/r_0.png")).unwrap();
        let open = || {
            let cfg = BlenderConfig { path: dir.clone(), ..Default::default() };
            load_blender(&cfg, &dir).map(|_| ()).unwrap_err().to_string()
        };
        let frame = |path: &str, matrix: &str| {
            format!(
                r#"{{"camera_angle_x": 0.7, "frames": [{{"file_path": "{path}",
                    "transform_matrix": {matrix}}}]}}"#
            )
        };
        let cases = [
            ("malformed", r#"{"camera_angle_x": 0.7, "frames": [{"file_path": }"#.to_string(), "transforms_train.json"),
            ("no frames", r#"{"camera_angle_x": 0.7}"#.to_string(), "transforms_train.json"),
            ("3x4 matrix", frame("./train/r_0", "[[1,0,0,0],[0,1,0,0],[0,0,1,4]]"), "transforms_train.json"),
            (
                "scaled rotation",
                frame("./train/r_0", "[[2,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"),
                "transforms_train.json",
            ),
            ("bad angle", r#"{"camera_angle_x": -1, "frames": []}"#.to_string(), "transforms_train.json"),
            ("missing image", frame("./train/r_9", "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]"), "r_9"),
        ];
        for (what, json, needle) in cases {
            write_minimal(&dir, &json);
            let err = open();
            assert!(err.contains(needle), "{what}: {err}");
        }
        write_minimal(&dir, ONE_FRAME);
        std::fs::create_dir_all(dir.join("masks/train")).unwrap();
        image::GrayImage::new(3, 3).save(dir.join("masks/train/r_0.png")).unwrap();
        let err = open();
        assert!(err.contains("r_0.png") && err.contains("resize"), "{err}");
        std::fs::remove_dir_all(dir.join("masks")).unwrap();
        std::fs::write(dir.join("train/r_0.png"), b"garbage").unwrap();
        let err = open();
        assert!(err.contains("r_0.png"), "{err}");
        std::fs::remove_file(dir.join("transforms_test.json")).unwrap();
        let err = open();
        assert!(err.contains("transforms_test.json") && err.contains("missing"), "{err}");
        std::fs::remove_dir_all(dir).ok();
    }

    fn small_scene(rig: Rig) -> Scene {
        generate(&SyntheticConfig { rig, width: 96, height: 72, views: 12, ..Default::default() })
    }

    #[test]
    fn opaque_images_get_the_extent_of_the_colmap_layout() {
        let scene = small_scene(Rig::Unbounded);
        let dir = temp_dir("opaque");
        write_blender(&scene, &dir).unwrap();
        let cfg = BlenderConfig { path: dir.clone(), ..Default::default() };
        let loaded = load_blender(&cfg, &dir).unwrap();
        assert_eq!(loaded.extent, extent_of(&loaded.views, &loaded.train, None));
        assert!(matches!(loaded.extent, SceneExtent::Unbounded { .. }));
        assert_eq!(loaded.near, 0.0);
        let notes = derived_blender(&cfg, &dir, &loaded);
        assert!(notes.iter().any(|d| d.key == "scene.extent" && d.reason.contains("opaque")), "{notes:?}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn cut_out_images_get_a_box_holding_the_object() {
        let scene = small_scene(Rig::ObjectCentric);
        let dir = temp_dir("cutout");
        write_blender(&scene, &dir).unwrap();
        std::fs::remove_dir_all(dir.join("masks")).unwrap();
        // Re-save every image with the object opaque and everything else transparent.
        let order: Vec<usize> = scene.train.iter().chain(&scene.test).copied().collect();
        let loaded_plain = load_blender(&BlenderConfig { path: dir.clone(), ..Default::default() }, &dir).unwrap();
        for (&i, l) in order.iter().zip(&loaded_plain.views) {
            let v = &scene.views[i];
            let mask = v.mask.as_ref().unwrap();
            let path = find_image(&dir, &l.name.replacen('_', "/", 1)).unwrap();
            let img = image::RgbaImage::from_fn(v.image.width as u32, v.image.height as u32, |x, y| {
                let [r, g, b] = v.image.pixel(x as usize, y as usize).map(|c| (c * 255.0).round() as u8);
                let a = if mask.data[y as usize * v.image.width + x as usize] > 0.5 { 255 } else { 0 };
                image::Rgba([r, g, b, a])
            });
            img.save(&path).unwrap();
        }
        let cfg = BlenderConfig { path: dir.clone(), ..Default::default() };
        let loaded = load_blender(&cfg, &dir).unwrap();
        let SceneExtent::Bounded { min, max } = loaded.extent else {
            panic!("cut-out images should give a box, got {:?}", loaded.extent)
        };
        // The object (sphere and pedestal down to the floor) lies inside, and the box is far
        // smaller than the room the cameras stand in.
        for k in 0..3 {
            let (lo, hi) = if k == 1 {
                (0.0, OBJECT_CENTRE[1] + OBJECT_RADIUS)
            } else {
                (OBJECT_CENTRE[k] - OBJECT_RADIUS, OBJECT_CENTRE[k] + OBJECT_RADIUS)
            };
            assert!(min[k] <= lo && max[k] >= hi, "axis {k}: box {min:?}..{max:?}");
        }
        let volume = |a: Vec3, b: Vec3| (0..3).map(|k| b[k] - a[k]).product::<f32>();
        assert!(volume(min, max) < 0.1 * volume(ROOM_MIN, ROOM_MAX), "box {min:?}..{max:?}");
        assert!(loaded.near > 0.0, "near {}", loaded.near);
        for &i in &loaded.train {
            let o = loaded.views[i].camera.origin();
            assert!((0..3).any(|k| o[k] < min[k] || o[k] > max[k]), "camera {i} inside the box");
        }
        let notes = derived_blender(&cfg, &dir, &loaded);
        assert!(notes.iter().any(|d| d.key == "scene.extent" && d.reason.contains("cut-out")), "{notes:?}");
        assert!(notes.iter().any(|d| d.key == "scene.near"), "{notes:?}");
        std::fs::remove_dir_all(dir).ok();
    }
}
