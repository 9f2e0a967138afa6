//! Writer of the NeRF++ layout used for Tanks and Temples.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::Scene;

use super::file_stems;
use crate::pose;
use crate::text::{format_matrix4, write_file};

/// Writes `dir/{train,test}/{rgb,mask}/<stem>.png`, `pose/<stem>.txt` (4x4 camera-to-world,
/// OpenCV axes) and `intrinsics/<stem>.txt` (4x4 with K top-left). Views in neither split are
/// left out.
pub fn write_tanks_temples(scene: &Scene, dir: &Path) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    for (split, indices) in [("train", &scene.train), ("test", &scene.test)] {
        let base = dir.join(split);
        for &i in indices {
            let (v, stem) = (&scene.views[i], &stems[i]);
            let cam = &v.camera;
            v.image.save_png(&base.join("rgb").join(format!("{stem}.png")))?;
            if let Some(mask) = &v.mask {
                mask.save_png(&base.join("mask").join(format!("{stem}.png")))?;
            }
            let (r, c) = pose::to_opencv(&pose::from_camera(cam));
            let mut m = [[0.0, 0.0, 0.0, 1.0]; 4];
            for k in 0..3 {
                m[k] = [r[k][0], r[k][1], r[k][2], c[k]];
            }
            write_file(&base.join("pose").join(format!("{stem}.txt")), format_matrix4(&m).as_bytes())?;
            let (fx, fy, cx, cy) = (cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64);
            let k = [[fx, 0.0, cx, 0.0], [0.0, fy, cy, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
            write_file(&base.join("intrinsics").join(format!("{stem}.txt")), format_matrix4(&k).as_bytes())?;
        }
    }
    Ok(())
}
