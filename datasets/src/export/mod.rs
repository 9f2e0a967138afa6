//! Writes a [`Scene`] to disk in every layout the loaders read (LLFF, Blender, COLMAP,
//! BlendedMVS original and NSVF, CO3Dv2, Tanks and Temples / NeRF++), with masks, so generated
//! scenes can be read by other NeRF code and by this crate's loaders (the round-trip tests).

mod blendedmvs;
mod co3d;
mod colmap;
mod tanks_temples;

pub use blendedmvs::{write_blendedmvs, write_nsvf};
pub use co3d::write_co3d;
pub use colmap::write_colmap;
pub use tanks_temples::write_tanks_temples;

use std::path::Path;

use sos_core::camera::{dot, sub, Camera};
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent};

use crate::npy::write_npy;

pub(crate) fn invalid(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid { path: path.to_path_buf(), message: message.into() }
}

/// Both layouts can only express a centred principal point and square pixels.
pub(crate) fn check_simple_intrinsics(dir: &Path, cam: &Camera, name: &str) -> Result<(), DatasetError> {
    let centred = (cam.cx - cam.width as f32 / 2.0).abs() < 1e-3 && (cam.cy - cam.height as f32 / 2.0).abs() < 1e-3;
    if !centred || (cam.fx - cam.fy).abs() > 1e-3 * cam.fx {
        return Err(invalid(
            dir,
            format!("view {name}: only square pixels and a centred principal point can be exported"),
        ));
    }
    Ok(())
}

/// File stems for the views: their names when those are unique, path-safe and already in
/// sorted order (so sorting the files restores the view order), else the index prefixed.
pub(crate) fn file_stems(scene: &Scene) -> Vec<String> {
    let names: Vec<&str> = scene.views.iter().map(|v| v.name.as_str()).collect();
    let safe = names.iter().all(|n| !n.is_empty() && !n.contains(['/', '\\', '.']));
    if safe && names.windows(2).all(|w| w[0] < w[1]) {
        names.iter().map(|n| n.to_string()).collect()
    } else {
        let digits = scene.views.len().to_string().len().max(3);
        names.iter().enumerate().map(|(i, n)| format!("{i:0digits$}_{}", n.replace(['/', '\\', '.'], "_"))).collect()
    }
}

/// Depth bounds of the content seen by `cam`, derived from the scene extent.
pub(crate) fn view_bounds(extent: &SceneExtent, cam: &Camera) -> [f64; 2] {
    let (o, f) = (cam.origin(), cam.forward());
    let (lo, hi) = match *extent {
        SceneExtent::ForwardFacing { near, far, .. } => (near, far),
        SceneExtent::Bounded { min, max } => {
            let depths = (0..8).map(|k| {
                let corner = [0, 1, 2].map(|a| if k >> a & 1 == 1 { max[a] } else { min[a] });
                dot(sub(corner, o), f)
            });
            depths.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), d| (a.min(d), b.max(d)))
        }
        SceneExtent::Unbounded { center, radius } => {
            let d = dot(sub(center, o), f);
            (d - radius, d + radius)
        }
    };
    // Cameras inside the content see it from depth ~0; LLFF bounds must be positive.
    let far = hi.max(1e-3) as f64;
    [(lo as f64).max(0.02 * far), far]
}

/// Writes `dir/poses_bounds.npy`, the images as PNG in `dir/images_{factor}/` (`dir/images/`
/// when `factor` is 1) and the masks in `dir/masks/`. The stored H, W and focal are the
/// images' times `factor` (LLFF keeps full-resolution intrinsics); the depth bounds come from
/// the scene extent.
pub fn write_llff(scene: &Scene, dir: &Path, factor: u32) -> Result<(), DatasetError> {
    if factor == 0 {
        return Err(invalid(dir, "factor must be ≥ 1"));
    }
    let images = if factor == 1 { dir.join("images") } else { dir.join(format!("images_{factor}")) };
    let stems = file_stems(scene);
    let mut rows = Vec::with_capacity(scene.views.len() * 17);
    for (v, stem) in scene.views.iter().zip(&stems) {
        let cam = &v.camera;
        check_simple_intrinsics(dir, cam, &v.name)?;
        let m = &cam.cam_to_world;
        let f = factor as f64;
        let hwf = [cam.height as f64 * f, cam.width as f64 * f, cam.fx as f64 * f];
        for r in 0..3 {
            // LLFF axes (down, right, back) = (−up, right, back).
            rows.extend([-m[r][1], m[r][0], m[r][2], m[r][3]].map(|x| x as f64));
            rows.push(hwf[r]);
        }
        rows.extend(view_bounds(&scene.extent, cam));
        v.image.save_png(&images.join(format!("{stem}.png")))?;
        if let Some(mask) = &v.mask {
            mask.save_png(&dir.join("masks").join(format!("{stem}.png")))?;
        }
    }
    write_npy(&dir.join("poses_bounds.npy"), &[scene.views.len(), 17], &rows)
}

/// Writes `dir/transforms_{train,val,test}.json` (val = test), the images as PNG in
/// `dir/{train,test}/` and the masks mirrored under `dir/masks/`.
pub fn write_blender(scene: &Scene, dir: &Path) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    for (split, indices) in [("train", &scene.train), ("test", &scene.test)] {
        let mut frames = Vec::with_capacity(indices.len());
        let mut angle = None;
        for &i in indices {
            let v = &scene.views[i];
            let cam = &v.camera;
            check_simple_intrinsics(dir, cam, &v.name)?;
            let a = 2.0 * ((cam.width as f64 / 2.0) / cam.fx as f64).atan();
            if angle.is_some_and(|b: f64| (a - b).abs() > 1e-5) {
                return Err(invalid(dir, format!("view {}: the {split} views differ in field of view", v.name)));
            }
            angle = Some(a);
            let rel = format!("{split}/{}", stems[i]);
            v.image.save_png(&dir.join(format!("{rel}.png")))?;
            if let Some(mask) = &v.mask {
                mask.save_png(&dir.join("masks").join(format!("{rel}.png")))?;
            }
            let m = &cam.cam_to_world;
            let matrix: Vec<Vec<f64>> = m
                .iter()
                .map(|r| r.iter().map(|&x| x as f64).collect())
                .chain(std::iter::once(vec![0.0, 0.0, 0.0, 1.0]))
                .collect();
            frames.push(serde_json::json!({ "file_path": format!("./{rel}"), "transform_matrix": matrix }));
        }
        let json = serde_json::json!({ "camera_angle_x": angle.unwrap_or(0.8), "frames": frames });
        let text = serde_json::to_string_pretty(&json).expect("JSON values always serialise");
        let names: &[&str] = if split == "test" { &["test", "val"] } else { &["train"] };
        for name in names {
            let path = dir.join(format!("transforms_{name}.json"));
            std::fs::create_dir_all(dir).map_err(|e| invalid(dir, format!("cannot create: {e}")))?;
            std::fs::write(&path, &text).map_err(|e| invalid(&path, format!("cannot write: {e}")))?;
        }
    }
    Ok(())
}
