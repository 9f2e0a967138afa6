//! Dataset kind `colmap`: a COLMAP sparse reconstruction (`cameras` and `images`, binary
//! `.bin` or text `.txt`, as COLMAP writes them) with its image folder.
//!
//! Layout: `<path>/images/` (config `images`) and the model in `<path>/sparse/0/`,
//! `<path>/sparse/` or `<path>/` itself (first that holds `cameras.bin` or `cameras.txt`;
//! config `sparse` to choose). Binary files are preferred when both exist. Optional masks in
//! `<path>/masks/`: the mask of image `a/b.jpg` is `masks/a/b.png` (any image extension) or
//! COLMAP's own `masks/a/b.jpg.png`; foreground = value > 0.5.
//!
//! Poses: COLMAP stores world-to-camera `x_cam = R(q) x_world + t` (unit quaternion
//! `qw qx qy qz`) in OpenCV axes; they are inverted and converted once to the core's OpenGL
//! convention. Pixel centres are at +0.5 in both, so intrinsics carry over unchanged.
//!
//! Camera models: `SIMPLE_PINHOLE` and `PINHOLE` are read as they are. The distorted
//! perspective models (`SIMPLE_RADIAL`, `RADIAL`, `OPENCV`, `FULL_OPENCV`, `FOV`) are accepted
//! when their distortion coefficients are all zero; otherwise loading stops with an error
//! telling to undistort the images (`colmap image_undistorter` writes `PINHOLE` cameras), unless
//! `ignore_distortion = true`, which keeps only the pinhole part (rays are then slightly wrong
//! towards the image borders). Fisheye models are always refused.
//!
//! Images registered in the model are loaded, sorted by name; images in the folder that the
//! model does not register are skipped (COLMAP often fails to register a few). Views `0, k,
//! 2k, …` (`hold_out_every`) are held out. Images may be a uniformly downscaled copy of the
//! ones COLMAP saw (e.g. `images = "images_4"`): intrinsics are scaled to the image size.
//!
//! Extent, where the config gives no `aabb`: when the training cameras look one way (a
//! forward-facing capture, the test LLFF uses to choose `spherify`) and the model's
//! `points3D` gives the depths of the content the views see, the capture is processed as
//! LLFF's `imgs2poses` and `load_llff_data` would process it (depth bounds from each view's
//! points, trimmed at 0.1 % each end; scaled by `bd_factor`, recentred, NDC). Otherwise it is
//! unbounded around the point the training cameras look at.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::camera::Vec3;
use sos_core::derived::DerivedSetting;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::adapter::{hold_out_views, orbit_scene, register_dataset, require_folder};
use crate::colmap_points::{read_points, SparsePoint};
use crate::forward_facing::{
    self, check_bd_factor, depth_bounds, forward_facing_scene, forward_facing_setting, Processing, FORWARD_PATH_VIEWS,
};
use crate::image_files::find_with_stem;
use crate::pose::{self, Pose};
use crate::text::{invalid, number, read_bytes, read_text, Reader};
use crate::views::{
    check_aabb, checked_camera, extent_of, extent_setting, optional_mask, scene_name, Intrinsics, NO_AABB,
};

/// Configuration of the `colmap` dataset (`[scene] kind = "colmap"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ColmapConfig {
    /// Scene folder, relative to the config file's folder.
    pub path: PathBuf,
    /// Model folder relative to `path` (default: `sparse/0`, else `sparse`, else `path`).
    pub sparse: Option<PathBuf>,
    /// Image folder relative to `path` (default `images`).
    pub images: PathBuf,
    /// Views `0, k, 2k, …` (sorted by name) are held out for testing (default 8); 0: none.
    pub hold_out_every: usize,
    /// Use only the pinhole part of distorted perspective cameras (default false: refuse).
    pub ignore_distortion: bool,
    /// Scene box `[min, max]` in COLMAP's world frame; default: forward-facing when the
    /// cameras look one way and the model's points give depth bounds, else unbounded around
    /// the point the cameras look at.
    pub aabb: Option<[Vec3; 2]>,
    /// Distance from the cameras below which nothing is sampled (default 0; forward-facing
    /// captures start at their nearest point instead).
    pub near: f32,
    /// Treat the capture as forward-facing (NDC between the depth bounds of the model's
    /// points, as LLFF). Absent: chosen from the cameras, on when they look one way
    /// (see [`FORWARD_FACING_FROM`](crate::forward_facing::FORWARD_FACING_FROM)) and `points3D` gives depth bounds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub forward_facing: Option<bool>,
    /// Forward-facing captures: scale so the nearest bound becomes `1 / bd_factor` (default
    /// 0.75, as LLFF); 0 disables scaling.
    pub bd_factor: f64,
    /// Forward-facing captures: express the poses in the frame of their average pose (default
    /// true, as LLFF; the NDC frame needs the mean camera looking along −Z).
    pub recenter: bool,
}

impl Default for ColmapConfig {
    fn default() -> Self {
        ColmapConfig {
            path: PathBuf::new(),
            sparse: None,
            images: PathBuf::from("images"),
            hold_out_every: 8,
            ignore_distortion: false,
            aabb: None,
            near: 0.0,
            forward_facing: None,
            bd_factor: 0.75,
            recenter: true,
        }
    }
}

register_dataset!(
    ColmapConfig,
    "colmap",
    "COLMAP sparse model (cameras/images .bin or .txt) with its images/ folder",
    load_colmap,
    derived_colmap
);

/// The extent this adapter chose where the config gives no `aabb`.
fn derived_colmap(cfg: &ColmapConfig, _root: &Path, scene: &Scene) -> Vec<DerivedSetting> {
    if cfg.aabb.is_some() {
        return Vec::new();
    }
    let forward = matches!(scene.extent, SceneExtent::ForwardFacing { .. });
    let mut out = Vec::new();
    if cfg.forward_facing.is_none() {
        out.push(forward_facing_setting(scene, "the model has no points3D to bound the content's depth"));
    }
    let reason = if forward { FORWARD_EXTENT } else { NO_AABB };
    out.push(extent_setting(scene, reason));
    out
}

/// Why a forward-facing capture gets its extent.
const FORWARD_EXTENT: &str =
    "forward-facing: NDC between the depths of the points3D points the views see, scaled and recentred as LLFF";

/// COLMAP camera model: name, parameter count, whether the first parameter is a single focal
/// length, whether it is a fisheye projection.
const MODELS: [(&str, usize, bool, bool); 11] = [
    ("SIMPLE_PINHOLE", 3, true, false),
    ("PINHOLE", 4, false, false),
    ("SIMPLE_RADIAL", 4, true, false),
    ("RADIAL", 5, true, false),
    ("OPENCV", 8, false, false),
    ("OPENCV_FISHEYE", 8, false, true),
    ("FULL_OPENCV", 12, false, false),
    ("FOV", 5, false, false),
    ("SIMPLE_RADIAL_FISHEYE", 4, true, true),
    ("RADIAL_FISHEYE", 5, true, true),
    ("THIN_PRISM_FISHEYE", 12, false, true),
];

/// Model id of `PINHOLE` (what the writer uses).
pub const PINHOLE: i32 = 1;

/// One camera of `cameras.{bin,txt}`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    /// Camera id.
    pub id: i64,
    /// Index into the model table (0 = SIMPLE_PINHOLE, 1 = PINHOLE, …).
    pub model: usize,
    /// Image width.
    pub width: u64,
    /// Image height.
    pub height: u64,
    /// Model parameters.
    pub params: Vec<f64>,
}

/// One registered image of `images.{bin,txt}`.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapImage {
    /// Image id.
    pub id: i64,
    /// World-to-camera rotation quaternion `(w, x, y, z)`.
    pub qvec: [f64; 4],
    /// World-to-camera translation.
    pub tvec: [f64; 3],
    /// Camera id.
    pub camera_id: i64,
    /// File name relative to the image folder.
    pub name: String,
}

/// Parses `cameras.bin`.
pub fn parse_cameras_bin(path: &Path, bytes: &[u8]) -> Result<Vec<ColmapCamera>, DatasetError> {
    let mut r = Reader::new(path, bytes);
    // Each camera takes at least 24 bytes.
    let n = read_count(&mut r, path, bytes, "camera", 24)?;
    let mut cams = Vec::with_capacity(n as usize);
    for i in 0..n {
        let what = format!("camera {i}");
        let id = r.i32(&what)? as i64;
        let model_id = r.i32(&what)?;
        let model = model_index(path, model_id as i64, &what)?;
        let width = r.u64(&what)?;
        let height = r.u64(&what)?;
        let params = (0..MODELS[model].1).map(|_| r.f64(&what)).collect::<Result<Vec<_>, _>>()?;
        cams.push(ColmapCamera { id, model, width, height, params });
    }
    if r.remaining() != 0 {
        return Err(invalid(path, format!("{} bytes left after the last camera; re-export the model", r.remaining())));
    }
    Ok(cams)
}

/// The count of `what`s (`camera`, `image`) the binary model file `bytes` starts with, read by
/// `r`; refused when the rest of the file cannot hold that many records of at least
/// `min_bytes`.
fn read_count(r: &mut Reader, path: &Path, bytes: &[u8], what: &str, min_bytes: usize) -> Result<u64, DatasetError> {
    let n = r.u64(&format!("the {what} count"))?;
    if n > (r.remaining() / min_bytes) as u64 {
        return Err(invalid(
            path,
            format!("{what} count {n} does not fit in the file ({} bytes); re-export the model", bytes.len()),
        ));
    }
    Ok(n)
}

fn model_index(path: &Path, id: i64, what: &str) -> Result<usize, DatasetError> {
    usize::try_from(id)
        .ok()
        .filter(|&m| m < MODELS.len())
        .ok_or_else(|| invalid(path, format!("{what}: unknown camera model id {id}; re-export the model")))
}

/// The data lines of a COLMAP text file (blank and `#` lines skipped): each named by its
/// number (`line 12`) for errors, split at whitespace.
pub(crate) fn data_lines(text: &str) -> impl Iterator<Item = (String, Vec<&str>)> {
    text.lines().enumerate().filter_map(|(l, line)| {
        let line = line.trim();
        (!line.is_empty() && !line.starts_with('#'))
            .then(|| (format!("line {}", l + 1), line.split_whitespace().collect()))
    })
}

/// Parses `cameras.txt`.
pub fn parse_cameras_txt(path: &Path, text: &str) -> Result<Vec<ColmapCamera>, DatasetError> {
    let mut cams = Vec::new();
    for (what, t) in data_lines(text) {
        if t.len() < 4 {
            let line = t.join(" ");
            return Err(invalid(path, format!("{what}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {line:?}")));
        }
        let model = MODELS
            .iter()
            .position(|m| m.0 == t[1])
            .ok_or_else(|| invalid(path, format!("{what}: unknown camera model {:?}", t[1])))?;
        let int = |s: &str, name: &str| -> Result<i64, DatasetError> {
            s.parse().map_err(|_| invalid(path, format!("{what}: {name} must be an integer, got {s:?}")))
        };
        let id = int(t[0], "CAMERA_ID")?;
        let width = int(t[2], "WIDTH")?;
        let height = int(t[3], "HEIGHT")?;
        if width < 0 || height < 0 {
            return Err(invalid(path, format!("{what}: negative image size {width}x{height}")));
        }
        let params = t[4..].iter().map(|s| number(path, s, &what)).collect::<Result<Vec<_>, _>>()?;
        if params.len() != MODELS[model].1 {
            return Err(invalid(
                path,
                format!("{what}: model {} takes {} parameters, found {}", t[1], MODELS[model].1, params.len()),
            ));
        }
        cams.push(ColmapCamera { id, model, width: width as u64, height: height as u64, params });
    }
    Ok(cams)
}

/// Parses `images.bin`.
pub fn parse_images_bin(path: &Path, bytes: &[u8]) -> Result<Vec<ColmapImage>, DatasetError> {
    let mut r = Reader::new(path, bytes);
    // Each image takes at least 73 bytes.
    let n = read_count(&mut r, path, bytes, "image", 73)?;
    let mut images = Vec::with_capacity(n as usize);
    for i in 0..n {
        let what = format!("image {i}");
        let id = r.i32(&what)? as i64;
        let mut qvec = [0.0; 4];
        for q in &mut qvec {
            *q = r.f64(&what)?;
        }
        let mut tvec = [0.0; 3];
        for t in &mut tvec {
            *t = r.f64(&what)?;
        }
        let camera_id = r.i32(&what)? as i64;
        let name = r.c_string(&format!("the name of {what}"))?;
        let points = r.u64(&what)?;
        let bytes = points.checked_mul(24).filter(|&b| b <= r.remaining() as u64).ok_or_else(|| {
            invalid(path, format!("{what}: {points} 2-D points do not fit in the file; re-export the model"))
        })?;
        r.skip(bytes as usize, &what)?;
        images.push(ColmapImage { id, qvec, tvec, camera_id, name });
    }
    if r.remaining() != 0 {
        return Err(invalid(path, format!("{} bytes left after the last image; re-export the model", r.remaining())));
    }
    Ok(images)
}

/// Parses `images.txt` (an image line, then its 2-D points line, which may be empty).
pub fn parse_images_txt(path: &Path, text: &str) -> Result<Vec<ColmapImage>, DatasetError> {
    let mut images = Vec::new();
    let mut lines = text.lines().enumerate();
    while let Some((l, line)) = lines.next() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let what = format!("line {}", l + 1);
        let t: Vec<&str> = line.split_whitespace().collect();
        if t.len() != 10 {
            return Err(invalid(
                path,
                format!("{what}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 fields), got {}", t.len()),
            ));
        }
        let int = |s: &str, name: &str| -> Result<i64, DatasetError> {
            s.parse().map_err(|_| invalid(path, format!("{what}: {name} must be an integer, got {s:?}")))
        };
        let v = t[1..8].iter().map(|s| number(path, s, &what)).collect::<Result<Vec<_>, _>>()?;
        images.push(ColmapImage {
            id: int(t[0], "IMAGE_ID")?,
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
            camera_id: int(t[8], "CAMERA_ID")?,
            name: t[9].to_string(),
        });
        // The POINTS2D line follows every image line: X Y POINT3D_ID triples, possibly none.
        // A file written with one line per image would otherwise lose every second image.
        if let Some((p, points)) = lines.next() {
            let fields = points.split_whitespace().count();
            if fields % 3 != 0 {
                return Err(invalid(
                    path,
                    format!(
                        "line {}: expected the POINTS2D line of the image on {what} (X Y POINT3D_ID triples, \
                         or an empty line), got {fields} fields; images.txt holds two lines per image",
                        p + 1
                    ),
                ));
            }
        }
    }
    Ok(images)
}

/// Finds the model folder and reads cameras and images from it.
pub fn read_model(dir: &Path) -> Result<(Vec<ColmapCamera>, Vec<ColmapImage>, PathBuf), DatasetError> {
    let hint = "a COLMAP model needs cameras and images in the same format (.bin or .txt)";
    if dir.join("cameras.bin").is_file() {
        let cp = dir.join("cameras.bin");
        let ip = dir.join("images.bin");
        let cams = parse_cameras_bin(&cp, &read_bytes(&cp, hint)?)?;
        let images = parse_images_bin(&ip, &read_bytes(&ip, hint)?)?;
        Ok((cams, images, ip))
    } else {
        let cp = dir.join("cameras.txt");
        let ip = dir.join("images.txt");
        let cams = parse_cameras_txt(&cp, &read_text(&cp, hint)?)?;
        let images = parse_images_txt(&ip, &read_text(&ip, hint)?)?;
        Ok((cams, images, ip))
    }
}

/// The pinhole intrinsics of a COLMAP camera, or why it cannot be used.
fn intrinsics(cam: &ColmapCamera, ignore_distortion: bool) -> Result<Intrinsics, String> {
    let (name, _, single_f, fisheye) = MODELS[cam.model];
    if fisheye {
        return Err(format!(
            "camera {}: fisheye model {name} is not supported; undistort the images with \
             `colmap image_undistorter` (it writes PINHOLE cameras) and point `path` at its output",
            cam.id
        ));
    }
    let p = &cam.params;
    if let Some(v) = p.iter().find(|v| !v.is_finite()) {
        return Err(format!("camera {}: parameter {v} is not finite", cam.id));
    }
    let (fx, fy, cx, cy, rest) =
        if single_f { (p[0], p[0], p[1], p[2], &p[3..]) } else { (p[0], p[1], p[2], p[3], &p[4..]) };
    if rest.iter().any(|&k| k != 0.0) && !ignore_distortion {
        return Err(format!(
            "camera {}: model {name} has non-zero distortion {rest:?}; undistort the images with \
             `colmap image_undistorter` (it writes PINHOLE cameras) and point `path` at its \
             output, or set `ignore_distortion = true` to keep only the pinhole part",
            cam.id
        ));
    }
    let size = |v: u64| u32::try_from(v).ok().filter(|&s| s > 0);
    let (Some(width), Some(height)) = (size(cam.width), size(cam.height)) else {
        return Err(format!("camera {}: image size {}x{} is zero or too large", cam.id, cam.width, cam.height));
    };
    Ok(Intrinsics { width, height, fx, fy, cx, cy })
}

fn find_model_dir(cfg: &ColmapConfig, root: &Path) -> Result<PathBuf, DatasetError> {
    let has_model = |d: &Path| d.join("cameras.bin").is_file() || d.join("cameras.txt").is_file();
    if let Some(s) = &cfg.sparse {
        let d = root.join(s);
        return if has_model(&d) {
            Ok(d)
        } else {
            Err(DatasetError::Missing {
                path: d.join("cameras.bin"),
                hint: "config key `sparse` must name a folder with cameras.bin or cameras.txt".into(),
            })
        };
    }
    [root.join("sparse/0"), root.join("sparse"), root.to_path_buf()].into_iter().find(|d| has_model(d)).ok_or_else(
        || DatasetError::Missing {
            path: root.join("sparse/0/cameras.bin"),
            hint: "no COLMAP model (cameras.bin or cameras.txt) in sparse/0/, sparse/ or the scene \
                   folder; run COLMAP's mapper or set `sparse`"
                .into(),
        },
    )
}

/// The mask of image `name`: `masks/<name minus extension>.<ext>` or `masks/<name>.png`.
fn mask_path(root: &Path, name: &str) -> Option<PathBuf> {
    let masks = root.join("masks");
    let rel = Path::new(name);
    let dir = masks.join(rel.parent().unwrap_or(Path::new("")));
    let stem = rel.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    find_with_stem(&dir, stem).or_else(|| Some(masks.join(format!("{name}.png"))).filter(|p| p.is_file()))
}

/// Loads a COLMAP scene from folder `root` (the config's `path` already resolved).
pub fn load_colmap(cfg: &ColmapConfig, root: &Path) -> Result<Scene, DatasetError> {
    check_aabb(root, cfg.aabb)?;
    check_bd_factor(root, cfg.bd_factor)?;
    require_folder(root, "a COLMAP scene folder with images/ and sparse/0/")?;
    let model_dir = find_model_dir(cfg, root)?;
    let (cams, mut images, images_file) = read_model(&model_dir)?;
    let cam_file = images_file.with_file_name(if images_file.extension().is_some_and(|e| e == "bin") {
        "cameras.bin"
    } else {
        "cameras.txt"
    });
    if images.is_empty() {
        return Err(invalid(&images_file, "the model registers no image; re-run COLMAP's mapper"));
    }
    let mut by_id: HashMap<i64, Intrinsics> = HashMap::new();
    for c in &cams {
        let k = intrinsics(c, cfg.ignore_distortion).map_err(|m| invalid(&cam_file, m))?;
        if by_id.insert(c.id, k).is_some() {
            return Err(invalid(&cam_file, format!("camera id {} appears twice", c.id)));
        }
    }
    images.sort_by(|a, b| a.name.cmp(&b.name));
    if let Some(w) = images.windows(2).find(|w| w[0].name == w[1].name) {
        return Err(invalid(&images_file, format!("image {:?} is registered twice", w[0].name)));
    }
    let image_dir = root.join(&cfg.images);
    if !image_dir.is_dir() {
        return Err(DatasetError::Missing {
            path: image_dir,
            hint: "the folder of the images the model registers; set `images` if it is elsewhere".into(),
        });
    }
    let views: Vec<View> = images
        .par_iter()
        .map(|im| {
            let what = format!("image {} ({})", im.id, im.name);
            let k = by_id.get(&im.camera_id).ok_or_else(|| {
                invalid(&images_file, format!("{what}: camera id {} is not in {}", im.camera_id, cam_file.display()))
            })?;
            if im.qvec.iter().chain(&im.tvec).any(|v| !v.is_finite()) {
                return Err(invalid(&images_file, format!("{what}: pose has NaN or inf; fix or drop this image")));
            }
            let qn: f64 = im.qvec.iter().map(|v| v * v).sum::<f64>().sqrt();
            if qn.is_nan() || qn <= 1e-6 {
                return Err(invalid(&images_file, format!("{what}: zero quaternion; fix or drop this image")));
            }
            let r = pose::rotation_from_quaternion(im.qvec);
            let pose: Pose = pose::from_world_to_camera(&r, im.tvec)
                .ok_or_else(|| invalid(&images_file, format!("{what}: singular rotation")))?;
            let file = root.join(&cfg.images).join(&im.name);
            if !file.is_file() {
                return Err(DatasetError::Missing {
                    path: file,
                    hint: format!("{what} is registered in {} but its file is absent", images_file.display()),
                });
            }
            let image = sos_core::image::RgbImage::load(&file)?;
            let (w, h) = (image.width as u32, image.height as u32);
            let mut camera = checked_camera(&images_file, &what, &pose, k)?;
            if (w, h) != (k.width, k.height) {
                let (sx, sy) = (w as f64 / k.width as f64, h as f64 / k.height as f64);
                if (sx - sy).abs() > 0.02 * sx.max(sy) {
                    return Err(invalid(
                        &file,
                        format!(
                            "image is {w}x{h} but its camera in {} is {}x{}; use the images COLMAP \
                             saw or a uniformly downscaled copy",
                            cam_file.display(),
                            k.width,
                            k.height
                        ),
                    ));
                }
                camera = camera.resized(w, h);
            }
            let mask = optional_mask(mask_path(root, &im.name).as_deref(), image.width, image.height)?;
            let rel = Path::new(&im.name);
            let name = rel.with_extension("").to_string_lossy().replace(['/', '\\'], "_");
            Ok(View { name, camera, image, mask, depth: None })
        })
        .collect::<Result<_, DatasetError>>()?;
    let (train, test) = hold_out_views(root, views.len(), cfg.hold_out_every)?;
    let name = scene_name(root, "colmap");
    if forward_facing::wanted(cfg.aabb.is_some(), cfg.forward_facing, &views, &train) {
        let ids: Vec<i64> = images.iter().map(|im| im.id).collect();
        let points = read_points(&model_dir)?;
        match points.as_deref().and_then(|p| content_bounds(&views, &ids, p)) {
            Some(bounds) => {
                let how = Processing {
                    bd_factor: cfg.bd_factor,
                    recenter: cfg.recenter,
                    render_path_views: FORWARD_PATH_VIEWS,
                };
                return Ok(forward_facing_scene(name, views, train, test, bounds, how));
            }
            None if cfg.forward_facing == Some(true) => {
                return Err(invalid(
                    &model_dir.join("points3D.bin"),
                    "config key `forward_facing = true` needs the content's depth bounds: points3D.bin or \
                     points3D.txt with points in front of the cameras; add the model's points or drop the key",
                ))
            }
            None => {}
        }
    }
    let extent = extent_of(&views, &train, cfg.aabb);
    Ok(orbit_scene(name, views, train, test, extent, cfg.near))
}

/// The nearest and farthest depth over the views (`ids` their image ids) of the `points` each
/// observes (by its track; every point when no track names the view), each view's bounds
/// trimmed as [`depth_bounds`] does. `None` when no view sees a point.
fn content_bounds(views: &[View], ids: &[i64], points: &[SparsePoint]) -> Option<[f64; 2]> {
    // Each image's points, from the tracks inverted once.
    let mut observed: HashMap<i64, Vec<[f64; 3]>> = HashMap::new();
    for p in points {
        for &image in &p.images {
            observed.entry(image).or_default().push(p.xyz);
        }
    }
    let every: Vec<[f64; 3]> = points.iter().map(|p| p.xyz).collect();
    let mut bounds: Option<[f64; 2]> = None;
    for (view, id) in views.iter().zip(ids) {
        let seen = observed.get(id).filter(|s| !s.is_empty()).unwrap_or(&every).iter().copied();
        if let Some([lo, hi]) = depth_bounds(&view.camera, seen) {
            bounds = Some(match bounds {
                Some([a, b]) => [a.min(lo), b.max(hi)],
                None => [lo, hi],
            });
        }
    }
    bounds.filter(|[lo, hi]| *lo > 0.0 && hi > lo)
}
