//! Dataset kind `llff`: forward-facing captures in the LLFF layout (Mildenhall et al., "Local
//! Light Field Fusion", 2019), loaded as the reference `load_llff.py` of NeRF / NeRF-SOS does.
//!
//! Folder layout: `poses_bounds.npy` (N x 17: a 3x5 `[R | t | (H, W, focal)]` per image in
//! LLFF's (down, right, back) axes at full resolution, then the near and far depth bounds),
//! images in `images_{factor}/` (or `images/`, downscaled in-process with a box filter when
//! that folder is missing), optional masks in `segments/` or `masks/` with the images' stems
//! (foreground = value > 0.5, same size as the loaded images; masks may cover only some views,
//! e.g. the test views, but a mask folder matching no image is an error), or in the folder the
//! `masks` key names, which may also hold them at a whole multiple of the loaded size.
//!
//! Processing, as the reference: columns reordered to (right, up, back); H, W taken from the
//! images and focal divided by the factor; translations and bounds scaled by
//! `1 / (bd_factor · min bound)`; poses recentred by the inverse of LLFF's average pose; test
//! views every `hold_out_every`-th from 0; render path the reference's 120-view spiral.
//! `spherify = true` (360° captures) applies the reference's `spherify_poses` after recentring:
//! the cameras are expressed around the point their viewing axes pass closest to, scaled to RMS
//! distance 1 from it, the extent is `Unbounded` (unit sphere) and the render path is the
//! reference's circle of cameras.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::camera::CameraConvention;
use sos_core::derived::DerivedSetting;
use sos_core::image::RgbImage;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent, View};

use crate::adapter::{hold_out_views, register_dataset, require_folder};
use crate::forward_facing::{self, FORWARD_FACING_FROM};
use crate::image_files::{find_with_stem, list_images, load_mask, load_mask_reduced, stem};
use crate::npy::read_npy;
use crate::pose::{self, Pose};
use crate::text::invalid;

/// Configuration of the `llff` dataset (`[scene] kind = "llff"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LlffConfig {
    /// Scene folder (holding `poses_bounds.npy`), relative to the config file's folder.
    pub path: PathBuf,
    /// Downscale factor: images come from `images_{factor}/` (or `images/`, downscaled).
    /// Absent: the image folder whose width is nearest [`WORKING_WIDTH`] (`images_8/` of
    /// LLFF's 4032-px captures, as the reference; see [`working_factor`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub factor: Option<u32>,
    /// Target width instead of `factor`: images come from `images_{width}x{height}/`, or from
    /// `images/` resized (height keeps the aspect ratio, rounded down). Default: unset.
    pub width: Option<u32>,
    /// Views `0, k, 2k, …` are held out for testing (default 8); 0 holds out none.
    pub hold_out_every: usize,
    /// Recentre the poses on their average pose (default true).
    pub recenter: bool,
    /// Scale so the nearest bound becomes `1 / bd_factor` (default 0.75); 0 disables scaling.
    pub bd_factor: f64,
    /// Spherical pose normalisation of 360° captures, as the reference. Absent: chosen from
    /// the cameras, on when their viewing directions spread like a capture around the scene
    /// (mean unit viewing direction shorter than [`FORWARD_FACING_FROM`]), off for forward-facing
    /// captures.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spherify: Option<bool>,
    /// Number of cameras on the spiral render path (default 120).
    pub render_path_views: usize,
    /// Folder of masks named like the images, relative to the scene folder (`path`), instead
    /// of its `segments/` or `masks/`; a mask may be a whole multiple of the loaded images'
    /// size (full-resolution masks for `images_8/`) and is then reduced by nearest neighbour.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub masks: Option<PathBuf>,
}

impl Default for LlffConfig {
    fn default() -> Self {
        LlffConfig {
            path: PathBuf::new(),
            factor: None,
            width: None,
            hold_out_every: 8,
            recenter: true,
            bd_factor: 0.75,
            spherify: None,
            render_path_views: 120,
            masks: None,
        }
    }
}

register_dataset!(
    LlffConfig,
    "llff",
    "forward-facing LLFF captures (poses_bounds.npy + images_N/), as NeRF's load_llff.py",
    load_llff,
    derived_llff
);

/// One row of `poses_bounds.npy`, validated.
struct PoseRow {
    /// Camera-to-world in OpenGL axes, unscaled.
    pose: Pose,
    /// Full-resolution height, width, focal.
    hwf: [f64; 3],
    bounds: [f64; 2],
}

fn parse_rows(path: &Path, shape: &[usize], data: &[f64]) -> Result<Vec<PoseRow>, DatasetError> {
    if shape.len() != 2 || shape[1] != 17 || shape[0] == 0 {
        return Err(invalid(
            path,
            format!("expected shape (N, 17) with N ≥ 1 (3x5 pose + near, far per image), got {shape:?}"),
        ));
    }
    data.chunks_exact(17)
        .enumerate()
        .map(|(i, row)| {
            if let Some(k) = row.iter().position(|v| !v.is_finite()) {
                return Err(invalid(path, format!("row {i} value {k} is not finite (NaN or inf)")));
            }
            // The 15 values reshape (row-major) to 3x5 [R | t | hwf], R in (down, right, back).
            let m = |r: usize, c: usize| row[5 * r + c];
            let mut llff = [[0.0f32; 3]; 3];
            for (r, out) in llff.iter_mut().enumerate() {
                *out = [m(r, 0) as f32, m(r, 1) as f32, m(r, 2) as f32];
            }
            let rot = CameraConvention::Llff.to_opengl(llff);
            let mut pose = [[0.0; 4]; 3];
            for r in 0..3 {
                pose[r] = [rot[r][0] as f64, rot[r][1] as f64, rot[r][2] as f64, m(r, 3)];
            }
            let bounds = [row[15], row[16]];
            if !(bounds[0] > 0.0 && bounds[1] >= bounds[0]) {
                return Err(invalid(path, format!("row {i}: bounds must satisfy 0 < near ≤ far, got {bounds:?}")));
            }
            Ok(PoseRow { pose, hwf: [m(0, 4), m(1, 4), m(2, 4)], bounds })
        })
        .collect()
}

/// Where the images come from and the size they must be brought to (when resized in-process).
struct ImageSource {
    dir: PathBuf,
    resize_to: Option<(usize, usize)>,
    /// Full resolution divided by the loaded resolution.
    factor: f64,
}

/// The image width an unset `factor` aims at: the reference's LLFF working size (4032 / 8).
pub const WORKING_WIDTH: f64 = 504.0;

/// The downscale factor of an unset `factor`: among the folders present the one whose width
/// is nearest [`WORKING_WIDTH`] in octaves (on a tie the finer one): an `images_N/` as it is,
/// or `images/` resized by the factor nearest that width; with no folder, the factor nearest
/// that width.
pub fn working_factor(root: &Path, full_width: f64) -> u32 {
    let usable = full_width.is_finite() && full_width > 0.0;
    // Compared in octaves: 1008 and 252 px are equally far from 504.
    let distance = |f: u32| if usable { (full_width / f as f64 / WORKING_WIDTH).log2().abs() } else { f as f64 };
    let mut present: Vec<u32> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.path().is_dir())
        .filter_map(|e| e.file_name().to_str()?.strip_prefix("images_")?.parse::<u32>().ok())
        .filter(|&f| f >= 1)
        .collect();
    // `images/` can be resized to any factor: it offers the one nearest the working width.
    if root.join("images").is_dir() {
        present.push(if usable { (full_width / WORKING_WIDTH).round().clamp(1.0, 64.0) as u32 } else { 1 });
    }
    match present.into_iter().min_by(|&a, &b| distance(a).total_cmp(&distance(b)).then(a.cmp(&b))) {
        Some(f) => f,
        None if usable => (full_width / WORKING_WIDTH).round().clamp(1.0, 64.0) as u32,
        None => 1,
    }
}

fn image_source(cfg: &LlffConfig, root: &Path, hwf: [f64; 3]) -> Result<ImageSource, DatasetError> {
    let full = root.join("images");
    let (h_full, w_full) = (hwf[0], hwf[1]);
    let (dir, w, h, factor) = match cfg.width {
        Some(0) => return Err(invalid(root, "config key `width` must be ≥ 1")),
        Some(width) => {
            if !(w_full >= 1.0 && h_full >= 1.0) {
                return Err(invalid(
                    &root.join("poses_bounds.npy"),
                    format!("image size {w_full}x{h_full} in the poses is not positive"),
                ));
            }
            // Images are only ever shrunk: a width beyond the photographs' would upsample them
            // (and a typo like 1e6 would ask for terabytes).
            if width as f64 > w_full {
                return Err(invalid(
                    root,
                    format!(
                        "config key `width` = {width} exceeds the photographs' {w_full} pixels; lower it or unset it"
                    ),
                ));
            }
            let factor = w_full / width as f64;
            let height = ((h_full / factor) as usize).max(1);
            (root.join(format!("images_{width}x{height}")), width as usize, height, factor)
        }
        None => {
            let factor = cfg.factor.unwrap_or_else(|| working_factor(root, w_full));
            if factor == 0 {
                return Err(invalid(root, "config key `factor` must be ≥ 1"));
            }
            let f = factor as f64;
            let dir = if factor == 1 { full.clone() } else { root.join(format!("images_{factor}")) };
            let (w, h) = (((w_full / f).round() as usize).max(1), ((h_full / f).round() as usize).max(1));
            if w.min(h) < 8 {
                return Err(invalid(
                    root,
                    format!("config key `factor` = {factor} leaves {w}x{h} pixels of the {w_full}x{h_full} photographs; views need at least 8 a side: lower it"),
                ));
            }
            (dir, w, h, f)
        }
    };
    if dir.is_dir() {
        return Ok(ImageSource { dir, resize_to: None, factor });
    }
    if full.is_dir() {
        return Ok(ImageSource { dir: full, resize_to: Some((w, h)), factor });
    }
    Err(DatasetError::Missing {
        path: dir,
        hint: format!("put the downscaled images there, or the full-resolution ones in {}", full.display()),
    })
}

/// Poses and bounds of an LLFF capture after the reference's processing.
#[derive(Debug, Clone, PartialEq)]
pub struct LlffGeometry {
    /// Camera-to-world poses (OpenGL axes): scaled, recentred and spherified as configured.
    pub poses: Vec<Pose>,
    /// Full-resolution (height, width, focal) of the first row.
    pub hwf: [f64; 3],
    /// Smallest near and largest far bound, in the processed frame.
    pub bounds: [f64; 2],
    /// The circle of cameras of `spherify` (its render path), when spherified.
    pub sphere_path: Option<Vec<Pose>>,
}

/// Reads `poses_bounds.npy` and processes it as the reference `load_llff_data` does: axes to
/// (right, up, back), translations and bounds scaled by `1 / (bd_factor · min near)`,
/// recentred on the average pose, then (with `spherify`) expressed around the point all
/// viewing axes pass closest to and scaled so the cameras' RMS distance to it is 1.
pub fn read_llff_geometry(cfg: &LlffConfig, npy_path: &Path) -> Result<LlffGeometry, DatasetError> {
    let arr = read_npy(npy_path)?;
    let rows = parse_rows(npy_path, &arr.shape, &arr.data)?;
    let min_bound = rows.iter().map(|r| r.bounds[0]).fold(f64::INFINITY, f64::min);
    let max_bound = rows.iter().map(|r| r.bounds[1]).fold(0.0, f64::max);
    let sc = if cfg.bd_factor > 0.0 { 1.0 / (cfg.bd_factor * min_bound) } else { 1.0 };
    let mut poses: Vec<Pose> = rows.iter().map(|r| r.pose).collect();
    for (i, p) in poses.iter().enumerate() {
        let r = [0, 1, 2].map(|k| [p[k][0], p[k][1], p[k][2]]);
        if let Some(problem) = pose::rotation_problem(&r) {
            return Err(invalid(npy_path, format!("row {i}: {problem}; fix or drop this camera")));
        }
    }
    for p in &mut poses {
        (0..3).for_each(|r| p[r][3] *= sc);
    }
    if cfg.recenter {
        poses = pose::recenter(&poses).0;
    }
    let mut bounds = [min_bound * sc, max_bound * sc];
    let mut sphere_path = None;
    // Pose column 2 is "back": its mean has the length of the viewing directions' mean.
    let backs = poses.iter().map(|p| [0, 1, 2].map(|k| p[k][2] as f32));
    if cfg.spherify.unwrap_or_else(|| forward_facing::mean_viewing_direction(backs) < FORWARD_FACING_FROM) {
        let s = pose::spherify(&poses, cfg.render_path_views).ok_or_else(|| {
            invalid(
                npy_path,
                "spherify needs cameras whose viewing axes meet (a 360° capture); these are \
                 (nearly) parallel: set `spherify = false`",
            )
        })?;
        poses = s.poses;
        bounds = bounds.map(|b| b * s.scale);
        sphere_path = Some(s.path);
    }
    Ok(LlffGeometry { poses, hwf: rows[0].hwf, bounds, sphere_path })
}

/// What the adapter chose where the config left `spherify` unset.
fn derived_llff(cfg: &LlffConfig, root: &Path, scene: &Scene) -> Vec<DerivedSetting> {
    let mut out = Vec::new();
    if cfg.factor.is_none() && cfg.width.is_none() {
        let full_width = read_npy(&root.join("poses_bounds.npy"))
            .ok()
            .and_then(|a| a.data.get(..15).map(|row| row[9]))
            .unwrap_or(f64::NAN);
        out.push(DerivedSetting::new(
            "scene.factor",
            working_factor(root, full_width),
            format!("no `factor`: of the image folders, the one nearest {WORKING_WIDTH} px wide ({full_width} px at full size)"),
        ));
    }
    if cfg.spherify.is_some() {
        return out;
    }
    let spherified = !matches!(scene.extent, SceneExtent::ForwardFacing { .. });
    let reason = if spherified {
        "no `spherify`: the cameras look in directions spread around the scene"
    } else {
        "no `spherify`: the cameras look the same way (a forward-facing capture)"
    };
    out.push(DerivedSetting::new("scene.spherify", spherified, reason));
    out.push(crate::views::extent_setting(scene, "from poses_bounds.npy's depth bounds"));
    out
}

/// Loads an LLFF scene from folder `root` (the config's `path` already resolved).
pub fn load_llff(cfg: &LlffConfig, root: &Path) -> Result<Scene, DatasetError> {
    require_folder(root, "an LLFF scene folder with poses_bounds.npy and images_N/")?;
    if !(1..=10_000).contains(&cfg.render_path_views) {
        return Err(invalid(
            root,
            format!("config key `render_path_views` must be in 1..=10000, got {}", cfg.render_path_views),
        ));
    }
    // A negative factor (a sign slip) would silently mean "no scaling", as 0 does.
    if cfg.bd_factor < 0.0 {
        return Err(invalid(
            root,
            format!("config key `bd_factor` must be 0 (no scaling) or positive, got {}", cfg.bd_factor),
        ));
    }
    let npy_path = root.join("poses_bounds.npy");
    let geo = read_llff_geometry(cfg, &npy_path)?;
    let source = image_source(cfg, root, geo.hwf)?;
    let files = list_images(&source.dir)?;
    if files.len() != geo.poses.len() {
        return Err(invalid(
            &source.dir,
            format!(
                "found {} images but {} has {} poses; the counts must match",
                files.len(),
                npy_path.display(),
                geo.poses.len()
            ),
        ));
    }
    let images: Vec<RgbImage> = files
        .par_iter()
        .map(|f| {
            let img = RgbImage::load(f)?;
            Ok(match source.resize_to {
                // Only downscaling: a size above the file's comes from a wrong H, W in the poses.
                Some((w, h)) if w > img.width || h > img.height => {
                    return Err(invalid(
                        f,
                        format!(
                            "image is {}x{}, smaller than the {w}x{h} that {} implies for this \
                             factor; put full-resolution images in images/ or fix H, W there",
                            img.width,
                            img.height,
                            npy_path.display()
                        ),
                    ))
                }
                Some((w, h)) => img.resized(w, h),
                None => img,
            })
        })
        .collect::<Result<_, DatasetError>>()?;
    let (width, height) = (images[0].width, images[0].height);
    for (img, f) in images.iter().zip(&files) {
        if (img.width, img.height) != (width, height) {
            return Err(invalid(
                f,
                format!(
                    "image is {}x{} but {} is {width}x{height}; all images must have one size",
                    img.width,
                    img.height,
                    files[0].display()
                ),
            ));
        }
    }
    // The focal length is the poses' divided by the folder's factor; images of another scale
    // (a copy put in the wrong images_N) would get a focal length off by that ratio.
    let (expect_w, expect_h) = (geo.hwf[1] / source.factor, geo.hwf[0] / source.factor);
    let off = |got: usize, want: f64| (got as f64 - want).abs() > (0.01 * want).max(1.0);
    if off(width, expect_w) || off(height, expect_h) {
        return Err(invalid(
            &files[0],
            format!(
                "image is {width}x{height}, but {} gives {}x{} full-resolution photographs, so a \
                 factor of {} means {expect_w:.0}x{expect_h:.0}; put images of that size in {} or fix H, W",
                npy_path.display(),
                geo.hwf[1],
                geo.hwf[0],
                source.factor,
                source.dir.display()
            ),
        ));
    }
    let poses = &geo.poses;
    let focal = geo.hwf[2] / source.factor;
    let (near, far) = (0.9 * geo.bounds[0], geo.bounds[1]);

    let masks = match &cfg.masks {
        Some(dir) => MaskDir::named(&root.join(dir))?,
        None => MaskDir::find(root),
    };
    let mut views = Vec::with_capacity(files.len());
    for (i, ((file, image), p)) in files.iter().zip(images).zip(poses).enumerate() {
        let camera = pose::to_camera(p, width as u32, height as u32, focal);
        camera.validate().map_err(|e| invalid(&npy_path, format!("pose of row {i} ({}): {e}", file.display())))?;
        let mask = masks.load(stem(file), width, height)?;
        views.push(View { name: stem(file).to_string(), camera, image, mask, depth: None });
    }
    masks.check_any_used(&views)?;
    let (train, test) = hold_out_views(root, views.len(), cfg.hold_out_every)?;
    let to_cam = |p: &Pose| pose::to_camera(p, width as u32, height as u32, focal);
    let name = root.file_name().and_then(|n| n.to_str()).unwrap_or("llff").to_string();
    if let Some(path) = &geo.sphere_path {
        // Spherified 360° captures: cameras around the origin at RMS distance 1.
        return Ok(Scene {
            name,
            views,
            train,
            test,
            extent: SceneExtent::Unbounded { center: [0.0; 3], radius: 1.0 },
            near: near as f32,
            render_path: path.iter().map(to_cam).collect(),
        });
    }
    let render_path =
        pose::llff_spiral(poses, geo.bounds[0], geo.bounds[1], cfg.render_path_views).iter().map(to_cam).collect();
    Ok(Scene {
        name,
        views,
        train,
        test,
        extent: SceneExtent::ForwardFacing {
            near: near as f32,
            far: far as f32,
            focal: focal as f32,
            width: width as f32,
            height: height as f32,
        },
        // The forward-facing extent's own near plane already bounds the samples.
        near: 0.0,
        render_path,
    })
}

/// The optional mask folder of a capture: `segments/` or else `masks/` in the scene folder,
/// or a folder the config names.
pub(crate) struct MaskDir {
    dir: Option<PathBuf>,
    /// Masks at a whole multiple of the images' size are reduced (a named folder only).
    reduce: bool,
}

impl MaskDir {
    /// Looks for `segments/`, then `masks/`, in `root`.
    pub(crate) fn find(root: &Path) -> Self {
        MaskDir { dir: ["segments", "masks"].iter().map(|d| root.join(d)).find(|d| d.is_dir()), reduce: false }
    }

    /// The folder the config's `masks` key names, which must exist.
    pub(crate) fn named(dir: &Path) -> Result<Self, DatasetError> {
        if !dir.is_dir() {
            return Err(DatasetError::Missing {
                path: dir.to_path_buf(),
                hint: "expected a folder of masks named like the images; check `masks` (relative to `path`)".into(),
            });
        }
        Ok(MaskDir { dir: Some(dir.to_path_buf()), reduce: true })
    }

    /// The mask of the image with stem `stem`, if the folder has one.
    pub(crate) fn load(
        &self,
        stem: &str,
        width: usize,
        height: usize,
    ) -> Result<Option<sos_core::image::GrayImage>, DatasetError> {
        match self.dir.as_ref().and_then(|d| find_with_stem(d, stem)) {
            Some(path) if self.reduce => Ok(Some(load_mask_reduced(&path, width, height)?)),
            Some(path) => Ok(Some(load_mask(&path, width, height)?)),
            None => Ok(None),
        }
    }

    /// Masks may cover only some views (e.g. the test views), but a mask folder none of whose
    /// files matches an image stem is a mistake worth reporting.
    pub(crate) fn check_any_used(&self, views: &[View]) -> Result<(), DatasetError> {
        match &self.dir {
            Some(dir) if views.iter().all(|v| v.mask.is_none()) => Err(invalid(
                dir,
                "no mask file has the stem of an image; name masks like their images \
                 (e.g. image000.png for image000.jpg)",
            )),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::write_llff;
    use crate::synthetic::{generate, Rig, SyntheticConfig};
    use sos_core::plugin::dataset::DatasetConfig;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("sos-llff-{}-{name}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn small(rig: Rig) -> Scene {
        generate(&SyntheticConfig { rig, width: 96, height: 72, views: 12, ..Default::default() })
    }

    fn cfg(path: &Path) -> LlffConfig {
        LlffConfig { path: path.to_path_buf(), ..Default::default() }
    }

    fn assert_images_match(a: &Scene, b: &Scene) {
        for (x, y) in a.views.iter().zip(&b.views) {
            assert_eq!(x.name, y.name);
            let err = x.image.data.iter().zip(&y.image.data).map(|(p, q)| (p - q).abs()).fold(0.0, f32::max);
            assert!(err <= 0.5 / 255.0 + 1e-5, "view {}: colour differs by {err}", x.name);
            assert_eq!(x.mask, y.mask, "view {}", x.name);
        }
    }

    /// Loaded poses must be one similarity transform (scale `sc`, then a rigid motion) of the
    /// written ones, and the recentred average pose must be the identity.
    fn assert_similar_poses(original: &Scene, loaded: &Scene, sc: f64) {
        let p0 = pose::from_camera(&original.views[0].camera);
        let l0 = pose::from_camera(&loaded.views[0].camera);
        // Rigid part A = L0 · S(P0)⁻¹, with S scaling the translation.
        let mut s0 = p0;
        (0..3).for_each(|r| s0[r][3] *= sc);
        let a = pose::compose(&l0, &pose::invert_rigid(&s0));
        for (o, l) in original.views.iter().zip(&loaded.views) {
            let mut s = pose::from_camera(&o.camera);
            (0..3).for_each(|r| s[r][3] *= sc);
            let want = pose::compose(&a, &s);
            let got = pose::from_camera(&l.camera);
            for (x, y) in want.iter().flatten().zip(got.iter().flatten()) {
                assert!((x - y).abs() < 1e-4, "view {}: {want:?} vs {got:?}", o.name);
            }
        }
        let loaded_poses: Vec<Pose> = loaded.views.iter().map(|v| pose::from_camera(&v.camera)).collect();
        let avg = pose::poses_avg(&loaded_poses);
        for (x, y) in avg.iter().flatten().zip(pose::IDENTITY.iter().flatten()) {
            assert!((x - y).abs() < 1e-5, "average pose {avg:?}");
        }
    }

    #[test]
    fn forward_facing_round_trip() {
        let scene = small(Rig::ForwardFacing);
        let dir = temp_dir("ff");
        write_llff(&scene, &dir, 8).unwrap();
        let loaded = load_llff(&cfg(&dir), &dir).unwrap();
        loaded.validate().unwrap();
        assert_eq!(loaded.views.len(), 12);
        assert_eq!((loaded.train.len(), loaded.test.clone()), (10, vec![0, 8]));
        assert_images_match(&scene, &loaded);
        let SceneExtent::ForwardFacing { near, far, .. } = scene.extent else { unreachable!() };
        let sc = 1.0 / (0.75 * near as f64);
        assert_similar_poses(&scene, &loaded, sc);
        // The generator's frame is already recentred, so only the scale changes.
        let (o, l) = (scene.views[3].camera.origin(), loaded.views[3].camera.origin());
        assert!((0..3).all(|k| (l[k] as f64 - sc * o[k] as f64).abs() < 1e-4), "{o:?} {l:?}");
        let SceneExtent::ForwardFacing { near: n2, far: f2, focal, width, height } = loaded.extent else {
            panic!("llff extent must be forward-facing")
        };
        assert!((n2 - 1.2).abs() < 1e-4 && (f2 as f64 - far as f64 * sc).abs() < 1e-3, "{n2} {f2}");
        assert!((focal - scene.views[0].camera.fx).abs() < 1e-3);
        assert_eq!((width, height), (96.0, 72.0));
        assert_eq!(loaded.render_path.len(), 120);
        loaded.render_path.iter().for_each(|c| c.validate().unwrap());
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn object_centric_round_trip_recentres() {
        let scene = small(Rig::ObjectCentric);
        let dir = temp_dir("oc");
        write_llff(&scene, &dir, 4).unwrap();
        let npy = read_npy(&dir.join("poses_bounds.npy")).unwrap();
        let min_bound = npy.data.chunks(17).map(|r| r[15]).fold(f64::INFINITY, f64::min);
        // Recentring and scaling alone (an object-centric capture would be spherified).
        let loaded = load_llff(&LlffConfig { factor: Some(4), spherify: Some(false), ..cfg(&dir) }, &dir).unwrap();
        loaded.validate().unwrap();
        assert_images_match(&scene, &loaded);
        assert_similar_poses(&scene, &loaded, 1.0 / (0.75 * min_bound));
        // Without recentring and scaling the poses come back unchanged.
        let raw = load_llff(
            &LlffConfig { factor: Some(4), recenter: false, bd_factor: 0.0, spherify: Some(false), ..cfg(&dir) },
            &dir,
        )
        .unwrap();
        for (a, b) in scene.views.iter().zip(&raw.views) {
            for (x, y) in a.camera.cam_to_world.iter().flatten().zip(b.camera.cam_to_world.iter().flatten()) {
                assert!((x - y).abs() < 1e-5);
            }
        }
        let err = load_llff(&LlffConfig { factor: Some(4), bd_factor: -0.75, ..cfg(&dir) }, &dir).unwrap_err();
        assert!(err.to_string().contains("`bd_factor`"), "{err}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn full_resolution_folder_is_downscaled_and_masks_must_match() {
        let scene = small(Rig::ForwardFacing);
        let dir = temp_dir("full");
        write_llff(&scene, &dir, 1).unwrap();
        // images_2 is missing: images/ is box-filtered to half size, but masks/ is full size.
        let err = load_llff(&LlffConfig { factor: Some(2), ..cfg(&dir) }, &dir).unwrap_err().to_string();
        assert!(err.contains("masks") && err.contains("resize") && err.contains("48x36"), "{err}");
        // Named by `masks`, the same full-size masks are reduced by nearest neighbour.
        std::fs::rename(dir.join("masks"), dir.join("full_masks")).unwrap();
        let named = LlffConfig { factor: Some(2), masks: Some("full_masks".into()), ..cfg(&dir) };
        let reduced = load_llff(&named, &dir).unwrap();
        let truth = scene.views[5].mask.as_ref().unwrap().resized_nearest(48, 36);
        assert_eq!(reduced.views[5].mask.as_ref().unwrap().data, truth.data);
        // A named folder that is missing, or masks of no whole multiple of the size, are errors.
        let missing = LlffConfig { masks: Some("nowhere".into()), ..named.clone() };
        let err = load_llff(&missing, &dir).unwrap_err().to_string();
        assert!(err.contains("nowhere") && err.contains("`masks`"), "{err}");
        let odd = scene.views[0].mask.as_ref().unwrap().resized_nearest(70, 50);
        odd.save_png(&dir.join("full_masks").join(format!("{}.png", reduced.views[0].name))).unwrap();
        let err = load_llff(&named, &dir).unwrap_err().to_string();
        assert!(err.contains("70x50") && err.contains("whole multiple"), "{err}");
        std::fs::remove_dir_all(dir.join("full_masks")).unwrap();
        let half = load_llff(&LlffConfig { factor: Some(2), ..cfg(&dir) }, &dir).unwrap();
        half.validate().unwrap();
        let v = &half.views[5];
        assert_eq!((v.image.width, v.image.height), (48, 36));
        assert!((v.camera.fx - scene.views[5].camera.fx / 2.0).abs() < 1e-3);
        let expect = scene.views[5].image.resized(48, 36);
        let err = expect.data.iter().zip(&v.image.data).map(|(p, q)| (p - q).abs()).fold(0.0, f32::max);
        assert!(err < 2.0 / 255.0, "{err}");
        // The `width` option picks the same size.
        let w = load_llff(&LlffConfig { width: Some(48), ..cfg(&dir) }, &dir).unwrap();
        assert_eq!((w.views[0].camera.width, w.views[0].camera.height), (48, 36));
        assert!((w.views[0].camera.fx - v.camera.fx).abs() < 1e-3);
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn hostile_inputs_are_errors_naming_the_file() {
        let scene = small(Rig::ForwardFacing);
        let dir = temp_dir("bad");
        let open = |c: &LlffConfig| load_llff(c, &dir).map(|_| ()).unwrap_err().to_string();
        write_llff(&scene, &dir, 8).unwrap();
        let npy_path = dir.join("poses_bounds.npy");
        let good = std::fs::read(&npy_path).unwrap();

        std::fs::write(&npy_path, &good[..good.len() - 100]).unwrap();
        let err = open(&cfg(&dir));
        assert!(err.contains("poses_bounds.npy") && err.contains("truncated"), "{err}");

        let mut rows = read_npy_from(&good);
        rows[3 * 17 + 5] = f64::NAN;
        crate::npy::write_npy(&npy_path, &[12, 17], &rows).unwrap();
        let err = open(&cfg(&dir));
        assert!(err.contains("poses_bounds.npy") && err.contains("row 3"), "{err}");

        let mut rows = read_npy_from(&good);
        rows[2 * 17 + 1] *= 3.0; // scales the right axis: not orthonormal
        crate::npy::write_npy(&npy_path, &[12, 17], &rows).unwrap();
        let err = open(&cfg(&dir));
        assert!(err.contains("poses_bounds.npy") && err.contains("orthonormal"), "{err}");

        let rows = read_npy_from(&good);
        crate::npy::write_npy(&npy_path, &[11, 17], &rows[..11 * 17]).unwrap();
        let err = open(&cfg(&dir));
        assert!(err.contains("images_8") && err.contains("12 images") && err.contains("11 poses"), "{err}");
        std::fs::write(&npy_path, &good).unwrap();

        let err = open(&LlffConfig { factor: Some(3), ..cfg(&dir) });
        assert!(err.contains("images_3") && err.contains("missing"), "{err}");

        // images_8's photographs put where factor 4 looks: the focal length would be halved.
        std::fs::create_dir_all(dir.join("images_4")).unwrap();
        for entry in std::fs::read_dir(dir.join("images_8")).unwrap() {
            let path = entry.unwrap().path();
            std::fs::copy(&path, dir.join("images_4").join(path.file_name().unwrap())).unwrap();
        }
        let err = open(&LlffConfig { factor: Some(4), ..cfg(&dir) });
        assert!(err.contains("images_4") && err.contains("factor of 4"), "{err}");
        std::fs::remove_dir_all(dir.join("images_4")).unwrap();

        std::fs::write(dir.join("images_8/view_004.png"), b"not a png").unwrap();
        let err = open(&cfg(&dir));
        assert!(err.contains("view_004.png"), "{err}");

        scene.views[4].image.resized(48, 36).save_png(&dir.join("images_8/view_004.png")).unwrap();
        let err = open(&cfg(&dir));
        assert!(err.contains("view_004.png") && err.contains("one size"), "{err}");

        let err = load_llff(&cfg(&dir), &dir.join("nowhere")).unwrap_err().to_string();
        assert!(err.contains("nowhere") && err.contains("missing"), "{err}");
        let err = open(&LlffConfig { spherify: Some(true), ..cfg(&dir) });
        assert!(err.contains("spherify"), "{err}");
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn an_unset_factor_picks_the_folder_nearest_the_working_width() {
        let dir = temp_dir("factor");
        // Nothing there: the factor nearest 504 px.
        assert_eq!(working_factor(&dir, 4032.0), 8);
        assert_eq!(working_factor(&dir, 200.0), 1);
        // Only full-size images: resized by that factor, not loaded at 4032 px.
        std::fs::create_dir_all(dir.join("images")).unwrap();
        assert_eq!(working_factor(&dir, 4032.0), 8);
        assert_eq!(working_factor(&dir, 640.0), 1);
        // Downscaled folders are used as they are when nearer (or as near).
        std::fs::create_dir_all(dir.join("images_4")).unwrap();
        std::fs::create_dir_all(dir.join("images_16")).unwrap();
        assert_eq!(working_factor(&dir, 4032.0), 8);
        assert_eq!(working_factor(&dir, 2016.0), 4);
        std::fs::remove_dir_all(dir.join("images")).unwrap();
        assert_eq!(working_factor(&dir, 4032.0), 4, "1008 and 252 px are an octave from 504: the finer");
        std::fs::create_dir_all(dir.join("images_12")).unwrap();
        assert_eq!(working_factor(&dir, 4032.0), 12, "336 px is nearer 504 than 1008");
        assert_eq!(working_factor(&dir, f64::NAN), 4);
        std::fs::remove_dir_all(dir).ok();
    }

    fn read_npy_from(bytes: &[u8]) -> Vec<f64> {
        crate::npy::parse_npy(bytes).unwrap().data
    }

    #[test]
    fn config_from_toml() {
        let boxed: Box<dyn DatasetConfig> = toml::from_str("kind = \"llff\"\npath = \"flower\"\nfactor = 4").unwrap();
        let err = boxed.open(Path::new("/nonexistent-root")).unwrap_err().to_string();
        assert!(err.contains("flower"), "{err}");
        assert!(toml::from_str::<LlffConfig>("factr = 4").is_err());
        assert!(sos_core::registry::find::<dyn DatasetConfig>("llff").is_some());
    }

    /// Runs only where the shared LLFF *flower* capture lies beside the repository
    /// (`../shared/data/llff_flower`, as in CI); a user's clone says it is skipped.
    #[test]
    fn real_flower_capture_when_available() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/llff_flower");
        if !root.join("poses_bounds.npy").is_file() {
            println!("skipped: the LLFF flower capture is not at {}", root.display());
            return;
        }
        let root = root.as_path();
        let scene = load_llff(&cfg(root), root).unwrap();
        scene.validate().unwrap();
        assert_eq!(scene.views.len(), 34);
        assert_eq!((scene.train.len(), scene.test.len()), (29, 5));
        assert_eq!(scene.test, vec![0, 8, 16, 24, 32]);
        let cam = &scene.views[0].camera;
        assert_eq!((cam.width, cam.height), (504, 378));
        let SceneExtent::ForwardFacing { near, far, focal, .. } = scene.extent else { unreachable!() };
        println!("flower view 0 cam_to_world (recentred): {:?}", cam.cam_to_world);
        println!("flower near {near} far {far} focal {focal}");
        assert!(near > 0.0 && far > near);
        assert!((near - 1.2).abs() < 1e-4, "near = 0.9 / 0.75 by construction, got {near}");
    }
}
