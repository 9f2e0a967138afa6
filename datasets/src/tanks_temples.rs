//! Dataset kind `tanks-temples`: Tanks and Temples (or any unbounded capture) in the NeRF++
//! layout.
//!
//! Layout: `<path>/train/` and `<path>/test/` (or `validation/`, config `test_split`), each with
//! `rgb/` (images), `pose/` (one `.txt` per image with the same stem: a 4x4 camera-to-world
//! matrix, OpenCV axes: x right, y down, z forward) and `intrinsics/` (one `.txt` per image: a
//! 4x4 matrix whose top-left 3x3 is K, pixel centres at +0.5). Optional masks in `mask/` beside
//! `rgb/` (same stems; foreground = value > 0.5).
//!
//! Normalisation, as NeRF++'s `normalize_cam_dict`: the training cameras' mean centre `c` and
//! largest distance `d` to it give the sphere of radius `1.1 d` around `c`, which is mapped to
//! the unit sphere (translate by `−c`, scale by `1 / (1.1 d)`); the extent is then
//! `Unbounded` with centre 0 and radius 1 (foreground inside, background outside). With
//! `normalize = "auto"` (default) captures whose cameras all lie inside the unit sphere already
//! (NeRF++'s published data is normalised) are left as they are; `"always"` normalises anyway;
//! `"never"` keeps the world frame and uses the sphere of radius `1.1 d` around `c` as extent.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::adapter::{orbit_scene, register_dataset, require_folder};
use crate::image_files::{check_images_for, find_with_stem, list_images, stem};
use crate::pose::{self, Pose};
use crate::text::{invalid, matrix4, read_text};
use crate::views::{checked_camera, optional_mask, scene_name, Intrinsics};

/// When to map the cameras into the unit sphere.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Normalize {
    /// Only when some training camera lies outside the unit sphere.
    #[default]
    Auto,
    /// Always (NeRF++'s `normalize_cam_dict`).
    Always,
    /// Never: keep the world frame.
    Never,
}

/// Configuration of the `tanks-temples` dataset (`[scene] kind = "tanks-temples"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TanksTemplesConfig {
    /// Scene folder (holding `train/` and `test/`), relative to the config file's folder.
    pub path: PathBuf,
    /// Folder of the held-out views: `"test"` (default) or `"validation"`.
    pub test_split: String,
    /// Map the cameras into the unit sphere: `"auto"` (default), `"always"` or `"never"`.
    pub normalize: Normalize,
    /// Distance from the cameras below which nothing is sampled, in the loaded (normalised)
    /// frame (default 0).
    pub near: f32,
}

impl Default for TanksTemplesConfig {
    fn default() -> Self {
        TanksTemplesConfig { path: PathBuf::new(), test_split: "test".into(), normalize: Normalize::Auto, near: 0.0 }
    }
}

register_dataset!(
    TanksTemplesConfig,
    "tanks-temples",
    "Tanks and Temples in the NeRF++ layout (train|test/{rgb,pose,intrinsics}), unbounded",
    load_tanks_temples
);

/// K of a NeRF++ intrinsics file (4x4, or 3x3 written as 9 numbers).
pub fn parse_k(path: &Path, text: &str) -> Result<[[f64; 3]; 3], DatasetError> {
    let v = crate::text::numbers(path, text)?;
    let k = match v.len() {
        16 => [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]],
        9 => [[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]],
        n => {
            return Err(invalid(
                path,
                format!("expected a 4x4 (16 numbers) or 3x3 (9 numbers) intrinsics matrix, found {n} numbers"),
            ))
        }
    };
    if k[0][1] != 0.0 || k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
        return Err(invalid(
            path,
            "intrinsics must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew); fix the matrix",
        ));
    }
    if !(k[0][0] > 0.0 && k[1][1] > 0.0) {
        return Err(invalid(path, format!("focal lengths must be positive, got {} {}", k[0][0], k[1][1])));
    }
    Ok(k)
}

/// A camera-to-world pose file (4x4, OpenCV axes) as a pose in OpenGL axes.
pub fn parse_c2w_opencv(path: &Path, text: &str) -> Result<Pose, DatasetError> {
    let m = matrix4(path, text)?;
    if m[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(invalid(path, "the last row of the pose must be 0 0 0 1; fix the matrix"));
    }
    let r = [0, 1, 2].map(|i| [m[i][0], m[i][1], m[i][2]]);
    Ok(pose::from_opencv(&r, [m[0][3], m[1][3], m[2][3]]))
}

/// One split's files, by stem.
struct SplitFiles {
    images: Vec<PathBuf>,
    dir: PathBuf,
}

fn split_files(root: &Path, split: &str) -> Result<SplitFiles, DatasetError> {
    let dir = root.join(split);
    let rgb = dir.join("rgb");
    if !rgb.is_dir() {
        return Err(DatasetError::Missing {
            path: rgb,
            hint: format!("the NeRF++ layout needs {split}/rgb, {split}/pose and {split}/intrinsics"),
        });
    }
    let images = list_images(&rgb)?;
    if images.is_empty() {
        return Err(invalid(&rgb, "no images (.png/.jpg) in the folder"));
    }
    // Every pose and intrinsics file needs its image, and the other way round.
    for sub in ["pose", "intrinsics"] {
        let d = dir.join(sub);
        let entries = std::fs::read_dir(&d).map_err(|_| DatasetError::Missing {
            path: d.clone(),
            hint: format!("one .txt per image of {split}/rgb, with the image's stem"),
        })?;
        check_images_for(entries, &rgb)?;
    }
    Ok(SplitFiles { images, dir })
}

/// Loads the views of one split in the world frame of the files.
fn load_split(files: &SplitFiles) -> Result<Vec<View>, DatasetError> {
    files
        .images
        .par_iter()
        .map(|img_path| {
            let s = stem(img_path);
            let pose_path = files.dir.join("pose").join(format!("{s}.txt"));
            let k_path = files.dir.join("intrinsics").join(format!("{s}.txt"));
            let hint = format!("the pose and intrinsics of {} (same stem, .txt)", img_path.display());
            let pose = parse_c2w_opencv(&pose_path, &read_text(&pose_path, &hint)?)?;
            let k = parse_k(&k_path, &read_text(&k_path, &hint)?)?;
            let image = sos_core::image::RgbImage::load(img_path)?;
            let intr = Intrinsics {
                width: image.width as u32,
                height: image.height as u32,
                fx: k[0][0],
                fy: k[1][1],
                cx: k[0][2],
                cy: k[1][2],
            };
            let camera = checked_camera(&pose_path, "camera-to-world matrix", &pose, &intr)?;
            let mask_path = find_with_stem(&files.dir.join("mask"), s);
            let mask = optional_mask(mask_path.as_deref(), image.width, image.height)?;
            Ok(View { name: s.to_string(), camera, image, mask, depth: None })
        })
        .collect()
}

/// NeRF++'s sphere around the cameras: mean centre and 1.1 x the largest distance to it.
pub fn camera_sphere(views: &[View]) -> ([f64; 3], f64) {
    let n = views.len() as f64;
    let mut c = [0.0; 3];
    for v in views {
        let o = v.camera.origin();
        (0..3).for_each(|k| c[k] += o[k] as f64 / n);
    }
    let d = views
        .iter()
        .map(|v| {
            let o = v.camera.origin();
            (0..3).map(|k| (o[k] as f64 - c[k]).powi(2)).sum::<f64>().sqrt()
        })
        .fold(0.0, f64::max);
    (c, 1.1 * d)
}

/// Loads a NeRF++-layout scene from folder `root` (the config's `path` already resolved).
pub fn load_tanks_temples(cfg: &TanksTemplesConfig, root: &Path) -> Result<Scene, DatasetError> {
    if cfg.test_split != "test" && cfg.test_split != "validation" {
        return Err(invalid(
            root,
            format!("config key `test_split` must be \"test\" or \"validation\", got {:?}", cfg.test_split),
        ));
    }
    require_folder(root, "a NeRF++-layout scene folder with train/ and test/")?;
    let train_files = split_files(root, "train")?;
    let test_files = split_files(root, &cfg.test_split)?;
    let mut views = load_split(&train_files)?;
    let n_train = views.len();
    views.extend(load_split(&test_files)?);
    let (centre, radius) = camera_sphere(&views[..n_train]);
    let inside = views[..n_train].iter().all(|v| {
        let o = v.camera.origin();
        o.iter().map(|x| x * x).sum::<f32>() < 1.0
    });
    let normalise = match cfg.normalize {
        Normalize::Always => true,
        Normalize::Never => false,
        Normalize::Auto => !inside,
    };
    let extent = if normalise {
        if radius.is_nan() || radius <= 0.0 {
            return Err(invalid(
                &train_files.dir.join("pose"),
                "all training cameras sit at one point; normalisation needs distinct camera centres",
            ));
        }
        let scale = 1.0 / radius;
        for v in &mut views {
            for (k, c) in centre.iter().enumerate() {
                let t = &mut v.camera.cam_to_world[k][3];
                *t = ((*t as f64 - c) * scale) as f32;
            }
        }
        SceneExtent::Unbounded { center: [0.0; 3], radius: 1.0 }
    } else if cfg.normalize == Normalize::Auto {
        SceneExtent::Unbounded { center: [0.0; 3], radius: 1.0 }
    } else {
        SceneExtent::Unbounded { center: centre.map(|v| v as f32), radius: radius.max(1e-6) as f32 }
    };
    let train: Vec<usize> = (0..n_train).collect();
    let test: Vec<usize> = (n_train..views.len()).collect();
    Ok(orbit_scene(scene_name(root, "tanks-temples"), views, train, test, extent, cfg.near))
}
