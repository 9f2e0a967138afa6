//! Dataset kind `blendedmvs`: BlendedMVS scenes in either published layout.
//!
//! - `original` (the BlendedMVS release): `blended_images/<id>.jpg` (the `<id>_masked.jpg`
//!   copies are skipped) and `cams/<id>_cam.txt`, each holding `extrinsic` (4x4 world-to-camera,
//!   OpenCV axes), `intrinsic` (3x3 K, pixel centres at +0.5) and the depth range line
//!   `DEPTH_MIN DEPTH_INTERVAL [DEPTH_NUM DEPTH_MAX]` (with two values the maximum is
//!   `DEPTH_MIN + 191 · DEPTH_INTERVAL`, MVSNet's 192 planes). `cams/pair.txt` is ignored.
//!   Views `0, k, 2k, …` (`hold_out_every`) are held out.
//! - `nsvf` (NSVF's release): `rgb/<split>_<name>.png`, `pose/<split>_<name>.txt` (4x4
//!   camera-to-world, OpenCV axes), one `intrinsics.txt` (4x4 or 3x3 K, or NSVF's
//!   `f cx cy 0` first line) and `bbox.txt` (`xmin ymin zmin xmax ymax zmax [voxel]`). File-name
//!   prefix `0_` is training, `1_` validation, `2_` test; the held-out views are `2_` when there
//!   are any, else `1_`. View names drop the prefix.
//!
//! `layout = "auto"` (default) picks `original` when `cams/` exists, else `nsvf`. Optional masks
//! in `masks/` with the images' stems (foreground = value > 0.5). Extent: `bbox.txt` (NSVF), or
//! config `aabb`; else, in the original layout, forward-facing when the training cameras look
//! one way (NDC between the cameras' depth ranges, scaled and recentred as LLFF; see
//! [`crate::forward_facing`]); else unbounded around the point the cameras look at. `near`
//! defaults to 0.9 x the smallest depth bound in the original layout, 0 in the NSVF layout.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::camera::Vec3;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::adapter::{hold_out_views, orbit_scene, register_dataset, require_folder};
use crate::forward_facing::{
    self, check_bd_factor, forward_facing_scene, forward_facing_setting, Processing, FORWARD_PATH_VIEWS,
};
use crate::image_files::{check_images_for, find_with_stem, list_images, stem};
use crate::pose::{self, Pose};
use crate::tanks_temples::parse_c2w_opencv;
use crate::text::{invalid, number, read_text};
use crate::views::{check_aabb, checked_camera, extent_of, optional_mask, scene_name, Intrinsics, NO_AABB};

/// Which BlendedMVS layout to read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Layout {
    /// `original` when `cams/` exists, else `nsvf`.
    #[default]
    Auto,
    /// `blended_images/` + `cams/*_cam.txt`.
    Original,
    /// `rgb/` + `pose/` + `intrinsics.txt` + `bbox.txt`.
    Nsvf,
}

/// Configuration of the `blendedmvs` dataset (`[scene] kind = "blendedmvs"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BlendedMvsConfig {
    /// Scene folder, relative to the config file's folder.
    pub path: PathBuf,
    /// `"auto"` (default), `"original"` or `"nsvf"`.
    pub layout: Layout,
    /// Original layout: views `0, k, 2k, …` are held out (default 8); 0 holds out none.
    pub hold_out_every: usize,
    /// Scene box `[min, max]`; overrides `bbox.txt`. Default: `bbox.txt` when it bounds an
    /// object (most training cameras outside it), else unbounded around the cameras' focus.
    pub aabb: Option<[Vec3; 2]>,
    /// Distance from the cameras below which nothing is sampled (default: see the module doc).
    pub near: Option<f32>,
    /// Original layout: treat the capture as forward-facing (NDC between the cameras' depth
    /// ranges, as LLFF). Absent: on when the training cameras look one way.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub forward_facing: Option<bool>,
    /// Forward-facing captures: scale so the nearest depth becomes `1 / bd_factor` (default
    /// 0.75, as LLFF); 0 disables scaling.
    pub bd_factor: f64,
    /// Forward-facing captures: express the poses in the frame of their average pose
    /// (default true, as LLFF).
    pub recenter: bool,
}

impl Default for BlendedMvsConfig {
    fn default() -> Self {
        BlendedMvsConfig {
            path: PathBuf::new(),
            layout: Layout::Auto,
            hold_out_every: 8,
            aabb: None,
            near: None,
            forward_facing: None,
            bd_factor: 0.75,
            recenter: true,
        }
    }
}

register_dataset!(
    BlendedMvsConfig,
    "blendedmvs",
    "BlendedMVS, original (blended_images/ + cams/) or NSVF (rgb/ + pose/ + bbox.txt) layout",
    load_blendedmvs,
    derived_blendedmvs
);

/// Whether more than half of the training cameras lie inside `[min, max]`.
fn holds_most_cameras([min, max]: [Vec3; 2], views: &[View], train: &[usize]) -> bool {
    let inside = train
        .iter()
        .filter(|&&i| {
            let o = views[i].camera.origin();
            (0..3).all(|k| min[k] <= o[k] && o[k] <= max[k])
        })
        .count();
    2 * inside > train.len()
}

/// The extent this adapter chose where the config gives no `aabb`.
fn derived_blendedmvs(
    cfg: &BlendedMvsConfig,
    root: &Path,
    scene: &sos_core::scene::Scene,
) -> Vec<sos_core::derived::DerivedSetting> {
    if cfg.aabb.is_some() {
        return Vec::new();
    }
    let mut out = Vec::new();
    if cfg.forward_facing.is_none() && chosen_layout(cfg, root) == Layout::Original {
        out.push(forward_facing_setting(scene, "forward_facing = false"));
    }
    let reason = match scene.extent {
        SceneExtent::Bounded { .. } => "no `aabb`: the layout's bbox.txt",
        SceneExtent::ForwardFacing { .. } => {
            "forward-facing: NDC between the cameras' depth ranges, scaled and recentred as LLFF"
        }
        _ if root.join("bbox.txt").is_file() => {
            "no `aabb`, and bbox.txt holds the cameras (a room, not an object's box): unbounded around \
             the point the training cameras look at"
        }
        _ => NO_AABB,
    };
    out.push(crate::views::extent_setting(scene, reason));
    out
}

/// A parsed `<id>_cam.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct MvsCam {
    /// World-to-camera rotation (OpenCV axes).
    pub rotation: [[f64; 3]; 3],
    /// World-to-camera translation.
    pub translation: [f64; 3],
    /// Calibration matrix.
    pub k: [[f64; 3]; 3],
    /// Depth range `[min, max]`.
    pub depth: [f64; 2],
}

/// Parses an MVSNet-style `_cam.txt`.
pub fn parse_cam_txt(path: &Path, text: &str) -> Result<MvsCam, DatasetError> {
    let tokens: Vec<&str> = text.split_whitespace().collect();
    let expect = |i: usize, word: &str| -> Result<(), DatasetError> {
        match tokens.get(i) {
            Some(t) if t.eq_ignore_ascii_case(word) => Ok(()),
            other => Err(invalid(
                path,
                format!(
                    "expected the keyword `{word}` as token {}, found {}; the file must read \
                     `extrinsic` + 4x4, `intrinsic` + 3x3, then the depth range",
                    i + 1,
                    other.map_or("the end of the file".to_string(), |t| format!("{t:?}"))
                ),
            )),
        }
    };
    expect(0, "extrinsic")?;
    expect(17, "intrinsic")?;
    let num = |i: usize| -> Result<f64, DatasetError> {
        let t = tokens.get(i).ok_or_else(|| invalid(path, format!("truncated: token {} is missing", i + 1)))?;
        number(path, t, &format!("token {}", i + 1))
    };
    let e: Vec<f64> = (1..17).map(num).collect::<Result<_, _>>()?;
    let k: Vec<f64> = (18..27).map(num).collect::<Result<_, _>>()?;
    let depth: Vec<f64> = (27..tokens.len()).map(num).collect::<Result<_, _>>()?;
    if e[12..16] != [0.0, 0.0, 0.0, 1.0] {
        return Err(invalid(path, "the extrinsic's last row must be 0 0 0 1"));
    }
    let depth = match depth.as_slice() {
        [min, interval] => [*min, min + 191.0 * interval],
        [min, interval, n] => [*min, min + (n - 1.0) * interval],
        [min, _, _, max] => [*min, *max],
        _ => {
            return Err(invalid(
                path,
                format!(
                    "expected 2 to 4 numbers on the depth line (DEPTH_MIN DEPTH_INTERVAL \
                         [DEPTH_NUM DEPTH_MAX]), found {}",
                    depth.len()
                ),
            ))
        }
    };
    if !(depth[0] > 0.0 && depth[1] > depth[0]) {
        return Err(invalid(path, format!("depth range must satisfy 0 < min < max, got {depth:?}")));
    }
    let kk = [[k[0], k[1], k[2]], [k[3], k[4], k[5]], [k[6], k[7], k[8]]];
    if kk[0][1] != 0.0 || kk[1][0] != 0.0 || kk[2] != [0.0, 0.0, 1.0] || !(kk[0][0] > 0.0 && kk[1][1] > 0.0) {
        return Err(invalid(path, "intrinsic must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0"));
    }
    Ok(MvsCam {
        rotation: [[e[0], e[1], e[2]], [e[4], e[5], e[6]], [e[8], e[9], e[10]]],
        translation: [e[3], e[7], e[11]],
        k: kk,
        depth,
    })
}

/// Formats a `_cam.txt` (the inverse of [`parse_cam_txt`]).
pub fn format_cam_txt(cam: &MvsCam) -> String {
    let (r, t, k) = (&cam.rotation, &cam.translation, &cam.k);
    let mut s = String::from("extrinsic\n");
    for i in 0..3 {
        s += &format!("{} {} {} {}\n", r[i][0], r[i][1], r[i][2], t[i]);
    }
    s += "0 0 0 1\n\nintrinsic\n";
    for row in k {
        s += &format!("{} {} {}\n", row[0], row[1], row[2]);
    }
    let n = 192.0;
    s += &format!("\n{} {} {} {}\n", cam.depth[0], (cam.depth[1] - cam.depth[0]) / (n - 1.0), n, cam.depth[1]);
    s
}

fn chosen_layout(cfg: &BlendedMvsConfig, root: &Path) -> Layout {
    match cfg.layout {
        Layout::Auto if root.join("cams").is_dir() => Layout::Original,
        Layout::Auto => Layout::Nsvf,
        l => l,
    }
}

/// Loads a BlendedMVS scene from folder `root` (the config's `path` already resolved).
pub fn load_blendedmvs(cfg: &BlendedMvsConfig, root: &Path) -> Result<Scene, DatasetError> {
    check_aabb(root, cfg.aabb)?;
    check_bd_factor(root, cfg.bd_factor)?;
    require_folder(root, "a BlendedMVS scene folder (blended_images/ + cams/, or rgb/ + pose/)")?;
    match chosen_layout(cfg, root) {
        Layout::Nsvf if cfg.forward_facing == Some(true) => Err(invalid(
            root,
            "config key `forward_facing = true` needs depth ranges, which the NSVF layout does not store; \
             drop the key or use the original layout",
        )),
        Layout::Nsvf => load_nsvf(cfg, root),
        _ => load_original(cfg, root),
    }
}

fn masks_for(root: &Path, s: &str) -> Option<PathBuf> {
    find_with_stem(&root.join("masks"), s)
}

fn load_original(cfg: &BlendedMvsConfig, root: &Path) -> Result<Scene, DatasetError> {
    let img_dir = root.join("blended_images");
    let cam_dir = root.join("cams");
    if !img_dir.is_dir() {
        return Err(DatasetError::Missing {
            path: img_dir,
            hint: "the original BlendedMVS layout keeps its images in blended_images/".into(),
        });
    }
    let images: Vec<PathBuf> = list_images(&img_dir)?.into_iter().filter(|p| !stem(p).ends_with("_masked")).collect();
    if images.is_empty() {
        return Err(invalid(&img_dir, "no images (.jpg/.png) in the folder"));
    }
    // Every camera file needs its image.
    let entries = std::fs::read_dir(&cam_dir).map_err(|_| DatasetError::Missing {
        path: cam_dir.clone(),
        hint: "one <id>_cam.txt per image of blended_images/".into(),
    })?;
    for e in entries.flatten() {
        let p = e.path();
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if let Some(id) = name.strip_suffix("_cam.txt") {
            if find_with_stem(&img_dir, id).is_none() {
                return Err(invalid(
                    &p,
                    format!("no image {id}.jpg in {}; remove the camera file or add the image", img_dir.display()),
                ));
            }
        }
    }
    let loaded: Vec<(View, [f64; 2])> = images
        .par_iter()
        .map(|img_path| {
            let s = stem(img_path);
            let cam_path = cam_dir.join(format!("{s}_cam.txt"));
            let text = read_text(&cam_path, &format!("the camera of {}", img_path.display()))?;
            let cam = parse_cam_txt(&cam_path, &text)?;
            let pose: Pose = pose::from_world_to_camera(&cam.rotation, cam.translation)
                .ok_or_else(|| invalid(&cam_path, "extrinsic rotation is singular; fix or drop this camera"))?;
            let image = sos_core::image::RgbImage::load(img_path)?;
            let k = Intrinsics {
                width: image.width as u32,
                height: image.height as u32,
                fx: cam.k[0][0],
                fy: cam.k[1][1],
                cx: cam.k[0][2],
                cy: cam.k[1][2],
            };
            let camera = checked_camera(&cam_path, "extrinsic", &pose, &k)?;
            let mask = optional_mask(masks_for(root, s).as_deref(), image.width, image.height)?;
            Ok((View { name: s.to_string(), camera, image, mask, depth: None }, cam.depth))
        })
        .collect::<Result<_, DatasetError>>()?;
    let min_depth = loaded.iter().map(|l| l.1[0]).fold(f64::INFINITY, f64::min);
    let max_depth = loaded.iter().map(|l| l.1[1]).fold(0.0, f64::max);
    let views: Vec<View> = loaded.into_iter().map(|l| l.0).collect();
    let (train, test) = hold_out_views(root, views.len(), cfg.hold_out_every)?;
    let name = scene_name(root, "blendedmvs");
    if forward_facing::wanted(cfg.aabb.is_some(), cfg.forward_facing, &views, &train) {
        let how =
            Processing { bd_factor: cfg.bd_factor, recenter: cfg.recenter, render_path_views: FORWARD_PATH_VIEWS };
        return Ok(forward_facing_scene(name, views, train, test, [min_depth, max_depth], how));
    }
    let extent = extent_of(&views, &train, cfg.aabb);
    let near = cfg.near.unwrap_or((0.9 * min_depth) as f32);
    Ok(orbit_scene(name, views, train, test, extent, near))
}

/// NSVF's `intrinsics.txt`: 4x4 or 3x3 K, or the DeepVoxels-style `f cx cy 0` first line.
pub fn parse_nsvf_intrinsics(path: &Path, text: &str) -> Result<[f64; 4], DatasetError> {
    let v = crate::text::numbers(path, text)?;
    if v.len() == 16 || v.len() == 9 {
        let k = crate::tanks_temples::parse_k(path, text)?;
        return Ok([k[0][0], k[1][1], k[0][2], k[1][2]]);
    }
    let first: Vec<f64> = match text.lines().next() {
        Some(line) => crate::text::numbers(path, line)?,
        None => Vec::new(),
    };
    match first.as_slice() {
        [f, cx, cy, ..] if *f > 0.0 => Ok([*f, *f, *cx, *cy]),
        _ => Err(invalid(
            path,
            format!("expected a 4x4 or 3x3 intrinsics matrix, or a first line `f cx cy 0`; found {} numbers", v.len()),
        )),
    }
}

/// NSVF's `bbox.txt`: `xmin ymin zmin xmax ymax zmax [voxel_size]`.
pub fn parse_bbox(path: &Path, text: &str) -> Result<[Vec3; 2], DatasetError> {
    let v = crate::text::numbers(path, text)?;
    if v.len() != 6 && v.len() != 7 {
        return Err(invalid(
            path,
            format!("expected xmin ymin zmin xmax ymax zmax [voxel_size], found {} numbers", v.len()),
        ));
    }
    let b = [[v[0] as f32, v[1] as f32, v[2] as f32], [v[3] as f32, v[4] as f32, v[5] as f32]];
    if !(0..3).all(|k| b[0][k] < b[1][k]) {
        return Err(invalid(path, "bounding box min must be below max on every axis"));
    }
    Ok(b)
}

/// The split prefix (`0`, `1`, `2`) of an NSVF file stem and the name without it.
fn split_prefix(s: &str) -> Option<(u8, &str)> {
    let (p, rest) = s.split_once('_')?;
    match p {
        "0" | "1" | "2" => Some((p.as_bytes()[0] - b'0', rest)),
        _ => None,
    }
}

fn load_nsvf(cfg: &BlendedMvsConfig, root: &Path) -> Result<Scene, DatasetError> {
    let rgb = root.join("rgb");
    let pose_dir = root.join("pose");
    if !rgb.is_dir() {
        return Err(DatasetError::Missing {
            path: rgb,
            hint: "the NSVF layout keeps its images in rgb/ (or use the original layout with cams/)".into(),
        });
    }
    let k_path = root.join("intrinsics.txt");
    let k = parse_nsvf_intrinsics(&k_path, &read_text(&k_path, "the NSVF layout needs one intrinsics.txt")?)?;
    let bbox = match cfg.aabb {
        Some(b) => Some(b),
        None => {
            let p = root.join("bbox.txt");
            Some(parse_bbox(&p, &read_text(&p, "the NSVF layout needs bbox.txt (or set `aabb`)")?)?)
        }
    };
    let mut images = list_images(&rgb)?;
    if images.is_empty() {
        return Err(invalid(&rgb, "no images (.png/.jpg) in the folder"));
    }
    for p in &images {
        if split_prefix(stem(p)).is_none() {
            return Err(invalid(
                p,
                "NSVF file names start with the split: 0_ (train), 1_ (validation) or 2_ (test); rename it",
            ));
        }
    }
    // Train first, then the rest, each in name order.
    images.sort_by_key(|p| split_prefix(stem(p)).map(|(s, _)| s));
    if let Ok(entries) = std::fs::read_dir(&pose_dir) {
        check_images_for(entries, &rgb)?;
    }
    let has_test = images.iter().any(|p| split_prefix(stem(p)).is_some_and(|(s, _)| s == 2));
    let test_prefix = if has_test { 2 } else { 1 };
    // Validation views are not loaded when a test split exists.
    images.retain(|p| split_prefix(stem(p)).is_some_and(|(s, _)| s == 0 || s == test_prefix));
    let views: Vec<(u8, View)> = images
        .par_iter()
        .map(|img_path| {
            let s = stem(img_path);
            let (split, name) = split_prefix(s).expect("checked above");
            let pose_path = pose_dir.join(format!("{s}.txt"));
            let pose =
                parse_c2w_opencv(&pose_path, &read_text(&pose_path, &format!("the pose of {}", img_path.display()))?)?;
            let image = sos_core::image::RgbImage::load(img_path)?;
            let intr = Intrinsics {
                width: image.width as u32,
                height: image.height as u32,
                fx: k[0],
                fy: k[1],
                cx: k[2],
                cy: k[3],
            };
            let camera = checked_camera(&pose_path, "camera-to-world matrix", &pose, &intr)?;
            let mask = optional_mask(masks_for(root, s).as_deref(), image.width, image.height)?;
            Ok((split, View { name: name.to_string(), camera, image, mask, depth: None }))
        })
        .collect::<Result<_, DatasetError>>()?;
    let train: Vec<usize> = (0..views.len()).filter(|&i| views[i].0 == 0).collect();
    let test: Vec<usize> = (0..views.len()).filter(|&i| views[i].0 == test_prefix).collect();
    if train.is_empty() {
        return Err(invalid(&rgb, "no training image (prefix 0_)"));
    }
    let views: Vec<View> = views.into_iter().map(|v| v.1).collect();
    // A bbox.txt that holds the cameras bounds a room, not an object: sampled from the
    // cameras on (`near` 0) it fills with fog in front of each one, so such a capture gets the
    // unbounded extent around the cameras' focus, as layouts without bounds do.
    let bbox = match (cfg.aabb, bbox) {
        (None, Some(b)) if holds_most_cameras(b, &views, &train) => None,
        (_, b) => b,
    };
    let extent = extent_of(&views, &train, bbox);
    let near = cfg.near.unwrap_or(0.0);
    Ok(orbit_scene(scene_name(root, "blendedmvs"), views, train, test, extent, near))
}
