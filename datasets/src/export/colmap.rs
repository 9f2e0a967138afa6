//! Writer of the COLMAP layout: `images/`, `masks/` and a sparse model in `sparse/0/`.

use std::path::Path;

use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::Scene;

use super::file_stems;
use crate::colmap::PINHOLE;
use crate::pose;
use crate::text::write_file;

/// Writes `dir/images/<stem>.png`, `dir/masks/<stem>.png` and the model
/// `dir/sparse/0/{cameras,images,points3D}.{bin|txt}` (binary when `binary`): one `PINHOLE`
/// camera per view and an empty point cloud. Poses are stored as COLMAP's world-to-camera
/// quaternion and translation, the translation computed from the stored quaternion so the
/// camera centre comes back exactly.
pub fn write_colmap(scene: &Scene, dir: &Path, binary: bool) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    let model = dir.join("sparse/0");
    let mut cams_bin = (scene.views.len() as u64).to_le_bytes().to_vec();
    let mut imgs_bin = (scene.views.len() as u64).to_le_bytes().to_vec();
    let mut cams_txt = String::from(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
    );
    let mut imgs_txt = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    for (i, (v, stem)) in scene.views.iter().zip(&stems).enumerate() {
        let id = i as i32 + 1;
        let cam = &v.camera;
        let name = format!("{stem}.png");
        v.image.save_png(&dir.join("images").join(&name))?;
        if let Some(mask) = &v.mask {
            mask.save_png(&dir.join("masks").join(&name))?;
        }
        let params = [cam.fx, cam.fy, cam.cx, cam.cy].map(|x| x as f64);
        cams_bin.extend(id.to_le_bytes());
        cams_bin.extend(PINHOLE.to_le_bytes());
        cams_bin.extend((cam.width as u64).to_le_bytes());
        cams_bin.extend((cam.height as u64).to_le_bytes());
        params.iter().for_each(|p| cams_bin.extend(p.to_le_bytes()));
        cams_txt += &format!(
            "{id} PINHOLE {} {} {} {} {} {}\n",
            cam.width, cam.height, params[0], params[1], params[2], params[3]
        );

        let p = pose::from_camera(cam);
        let (r, _) = pose::to_world_to_camera(&p);
        let q = pose::quaternion_from_rotation(&r);
        let rq = pose::rotation_from_quaternion(q);
        let rc = pose::mul3v(&rq, pose::column(&p, 3));
        let t = [-rc[0], -rc[1], -rc[2]];
        imgs_bin.extend(id.to_le_bytes());
        q.iter().chain(&t).for_each(|x| imgs_bin.extend(x.to_le_bytes()));
        imgs_bin.extend(id.to_le_bytes());
        imgs_bin.extend(name.as_bytes());
        imgs_bin.push(0);
        imgs_bin.extend(0u64.to_le_bytes());
        imgs_txt += &format!("{id} {} {} {} {} {} {} {} {id} {name}\n\n", q[0], q[1], q[2], q[3], t[0], t[1], t[2]);
    }
    if binary {
        write_file(&model.join("cameras.bin"), &cams_bin)?;
        write_file(&model.join("images.bin"), &imgs_bin)?;
        write_file(&model.join("points3D.bin"), &0u64.to_le_bytes())
    } else {
        write_file(&model.join("cameras.txt"), cams_txt.as_bytes())?;
        write_file(&model.join("images.txt"), imgs_txt.as_bytes())?;
        write_file(&model.join("points3D.txt"), b"# 3D point list (empty)\n")
    }
}
