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
use sos_core::camera::{Camera, Vec3};
use sos_core::image::RgbImage;
use sos_core::plugin::dataset::{DatasetConfig, DatasetError};
use sos_core::registry::Registration;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::image_files::{find_image, find_with_stem, load_mask, stem};

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
    /// Scene bounds `[min, max]` (default `[[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]]`).
    pub aabb: [Vec3; 2],
}

impl Default for BlenderConfig {
    fn default() -> Self {
        BlenderConfig {
            path: PathBuf::new(),
            white_background: true,
            downscale: 1,
            test_split: "test".into(),
            aabb: [[-1.5; 3], [1.5; 3]],
        }
    }
}

#[typetag::serde(name = "blender")]
impl DatasetConfig for BlenderConfig {
    fn open(&self, config_dir: &Path) -> Result<Scene, DatasetError> {
        load_blender(self, &config_dir.join(&self.path))
    }
}

fn default_config() -> Box<dyn DatasetConfig> {
    Box::new(BlenderConfig::default())
}

inventory::submit! {
    Registration::<dyn DatasetConfig>::new(
        "blender",
        "NeRF-synthetic layout (transforms_{train,test}.json, RGBA on white)",
        default_config,
    )
}

fn invalid(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        message: message.into(),
    }
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
            hint: "a Blender-layout scene needs transforms_train.json and transforms_test.json"
                .into(),
        },
        _ => invalid(&path, format!("cannot read: {e}")),
    })?;
    let t: Transforms = serde_json::from_str(&text)
        .map_err(|e| invalid(&path, format!("malformed transforms JSON: {e}")))?;
    if !(t.camera_angle_x.is_finite()
        && t.camera_angle_x > 0.0
        && t.camera_angle_x < std::f64::consts::PI)
    {
        return Err(invalid(
            &path,
            format!("camera_angle_x must be in (0, π), got {}", t.camera_angle_x),
        ));
    }
    let frames = t
        .frames
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let m = &f.transform_matrix;
            if m.len() != 4 || m.iter().any(|r| r.len() != 4) {
                return Err(invalid(
                    &path,
                    format!("frame {i}: transform_matrix must be 4x4"),
                ));
            }
            if m.iter().flatten().any(|v| !v.is_finite()) {
                return Err(invalid(
                    &path,
                    format!("frame {i}: transform_matrix has NaN or inf"),
                ));
            }
            let mut cam_to_world = [[0.0f32; 4]; 3];
            for r in 0..3 {
                for c in 0..4 {
                    cam_to_world[r][c] = m[r][c] as f32;
                }
            }
            // Check the rotation here, where the error can name the JSON file and frame.
            let probe = Camera {
                width: 1,
                height: 1,
                fx: 1.0,
                fy: 1.0,
                cx: 0.5,
                cy: 0.5,
                cam_to_world,
            };
            probe
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
            Ok(FrameFile {
                image,
                rel,
                cam_to_world,
            })
        })
        .collect::<Result<_, _>>()?;
    Ok((t.camera_angle_x, frames))
}

/// Reads an image, compositing its alpha (if any) on `background`.
fn load_composited(path: &Path, background: f32) -> Result<RgbImage, DatasetError> {
    let img = image::open(path).map_err(|e| {
        invalid(
            path,
            format!("cannot decode image ({e}); re-export it as PNG or JPEG"),
        )
    })?;
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
    Ok(RgbImage {
        width: w as usize,
        height: h as usize,
        data,
    })
}

/// Loads a Blender-layout scene from folder `root` (the config's `path` already resolved).
pub fn load_blender(cfg: &BlenderConfig, root: &Path) -> Result<Scene, DatasetError> {
    if cfg.downscale == 0 {
        return Err(invalid(root, "config key `downscale` must be ≥ 1"));
    }
    if cfg.test_split != "test" && cfg.test_split != "val" {
        return Err(invalid(
            root,
            format!(
                "config key `test_split` must be \"test\" or \"val\", got {:?}",
                cfg.test_split
            ),
        ));
    }
    if !(0..3).all(|k| cfg.aabb[0][k] < cfg.aabb[1][k]) {
        return Err(invalid(
            root,
            "config key `aabb`: min must be below max on every axis",
        ));
    }
    if !root.is_dir() {
        return Err(DatasetError::Missing {
            path: root.to_path_buf(),
            hint: "expected a Blender-layout scene folder with transforms_*.json; check `path`"
                .into(),
        });
    }
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
    let views: Vec<View> = all
        .par_iter()
        .map(|(angle, f)| {
            let mut image = load_composited(&f.image, background)?;
            let d = cfg.downscale as usize;
            if d > 1 {
                image = image.resized((image.width / d).max(1), (image.height / d).max(1));
            }
            let (w, h) = (image.width, image.height);
            let focal = 0.5 * w as f64 / (0.5 * angle).tan();
            let camera = Camera {
                width: w as u32,
                height: h as u32,
                fx: focal as f32,
                fy: focal as f32,
                cx: w as f32 / 2.0,
                cy: h as f32 / 2.0,
                cam_to_world: f.cam_to_world,
            };
            camera
                .validate()
                .map_err(|e| invalid(&f.image, format!("pose of this frame: {e}")))?;
            let rel = Path::new(&f.rel);
            let mask_dir = mask_root.join(rel.parent().unwrap_or(Path::new("")));
            let mask = match find_with_stem(&mask_dir, stem(rel)) {
                Some(p) => Some(load_mask(&p, w, h)?),
                None => None,
            };
            Ok(View {
                name: f.rel.replace(['/', '\\'], "_"),
                camera,
                image,
                mask,
            })
        })
        .collect::<Result<_, DatasetError>>()?;
    if mask_root.is_dir() && views.iter().all(|v| v.mask.is_none()) {
        return Err(invalid(
            &mask_root,
            "no mask mirrors an image path; the mask of train/r_0.png must be masks/train/r_0.png",
        ));
    }
    let name = root
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("blender")
        .to_string();
    Ok(Scene {
        name,
        train: (0..n_train).collect(),
        test: (n_train..views.len()).collect(),
        views,
        extent: SceneExtent::Bounded {
            min: cfg.aabb[0],
            max: cfg.aabb[1],
        },
        render_path: Vec::new(),
    })
}
