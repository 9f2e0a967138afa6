//! Writers of the two BlendedMVS layouts: the original release and NSVF's.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, SceneExtent};

use super::{file_stems, invalid, view_bounds};
use crate::blendedmvs::{format_cam_txt, MvsCam};
use crate::pose;
use crate::text::{format_matrix4, write_file};
use crate::views::Intrinsics;

/// Writes the original layout: `dir/blended_images/<stem>.png`, `dir/cams/<stem>_cam.txt`
/// (world-to-camera extrinsic, K, depth range from the scene extent), `dir/cams/pair.txt`
/// (no neighbours listed) and `dir/masks/<stem>.png`.
pub fn write_blendedmvs(scene: &Scene, dir: &Path) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    let mut pair = format!("{}\n", scene.views.len());
    for (i, (v, stem)) in scene.views.iter().zip(&stems).enumerate() {
        v.image.save_png(&dir.join("blended_images").join(format!("{stem}.png")))?;
        if let Some(mask) = &v.mask {
            mask.save_png(&dir.join("masks").join(format!("{stem}.png")))?;
        }
        let (rotation, translation) = pose::to_world_to_camera(&pose::from_camera(&v.camera));
        let cam = MvsCam {
            rotation,
            translation,
            k: Intrinsics::of(&v.camera).k(),
            depth: view_bounds(&scene.extent, &v.camera),
        };
        write_file(&dir.join("cams").join(format!("{stem}_cam.txt")), format_cam_txt(&cam).as_bytes())?;
        pair += &format!("{i}\n0\n");
    }
    write_file(&dir.join("cams/pair.txt"), pair.as_bytes())
}

/// Writes NSVF's layout: `dir/rgb/{0,2}_<stem>.png` (training views `0_`, held-out `2_`; views
/// in neither split are left out), `dir/pose/…txt` (4x4 camera-to-world, OpenCV axes), one
/// `dir/intrinsics.txt` (all views must share K), `dir/bbox.txt` from the extent (a bounded
/// box, or the cube around an unbounded sphere) and masks in `dir/masks/`.
pub fn write_nsvf(scene: &Scene, dir: &Path) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    let (min, max) = match scene.extent {
        SceneExtent::Bounded { min, max } => (min, max),
        SceneExtent::Unbounded { center, radius } => (center.map(|c| c - radius), center.map(|c| c + radius)),
        SceneExtent::ForwardFacing { .. } => {
            return Err(invalid(dir, "the NSVF layout needs a bounding box; forward-facing scenes have none"))
        }
    };
    let mut k0: Option<Intrinsics> = None;
    for (prefix, indices) in [("0", &scene.train), ("2", &scene.test)] {
        for &i in indices {
            let (v, stem) = (&scene.views[i], &stems[i]);
            let k = Intrinsics::of(&v.camera);
            let same = |a: &Intrinsics| (a.fx, a.fy, a.cx, a.cy) == (k.fx, k.fy, k.cx, k.cy);
            if k0.as_ref().is_some_and(|a| !same(a)) {
                return Err(invalid(
                    dir,
                    format!("view {}: NSVF stores one intrinsics.txt; all views must share K", v.name),
                ));
            }
            k0 = Some(k);
            let file = format!("{prefix}_{stem}");
            v.image.save_png(&dir.join("rgb").join(format!("{file}.png")))?;
            if let Some(mask) = &v.mask {
                mask.save_png(&dir.join("masks").join(format!("{file}.png")))?;
            }
            let (r, c) = pose::to_opencv(&pose::from_camera(&v.camera));
            let mut m = [[0.0, 0.0, 0.0, 1.0]; 4];
            for row in 0..3 {
                m[row] = [r[row][0], r[row][1], r[row][2], c[row]];
            }
            write_file(&dir.join("pose").join(format!("{file}.txt")), format_matrix4(&m).as_bytes())?;
        }
    }
    let k = k0.ok_or_else(|| invalid(dir, "the scene has no view to write"))?;
    let km = [[k.fx, 0.0, k.cx, 0.0], [0.0, k.fy, k.cy, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
    write_file(&dir.join("intrinsics.txt"), format_matrix4(&km).as_bytes())?;
    let bbox = format!("{} {} {} {} {} {} 0.1\n", min[0], min[1], min[2], max[0], max[1], max[2]);
    write_file(&dir.join("bbox.txt"), bbox.as_bytes())
}
