//! Writer of the COLMAP layout: `images/`, `masks/` and a sparse model in `sparse/0/`.

use std::path::Path;

use sos_core::camera::{axpy, dot, Vec3};
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::Scene;

use super::{file_stems, view_bounds};
use crate::colmap::PINHOLE;
use crate::pose;
use crate::text::write_file;

/// Writes `dir/images/<stem>.png`, `dir/masks/<stem>.png` and the model
/// `dir/sparse/0/{cameras,images,points3D}.{bin|txt}` (binary when `binary`): one `PINHOLE`
/// camera per view and the stand-in points of `bound_points`, each tracked in every view it
/// projects into. Poses are stored as COLMAP's world-to-camera quaternion and translation,
/// the translation computed from the stored quaternion so the camera centre comes back
/// exactly.
pub fn write_colmap(scene: &Scene, dir: &Path, binary: bool) -> Result<(), DatasetError> {
    let stems = file_stems(scene);
    let points = bound_points(scene);
    // observed[v]: (x, y, point id) of the points view v sees; tracks[p]: (view id, index).
    let mut observed: Vec<Vec<(f64, f64, u64)>> = vec![Vec::new(); scene.views.len()];
    let mut tracks: Vec<Vec<(i32, i32)>> = vec![Vec::new(); points.len()];
    for (p, point) in points.iter().enumerate() {
        for (v, view) in scene.views.iter().enumerate() {
            let cam = &view.camera;
            let Some([x, y]) = cam.project(*point) else { continue };
            if (0.0..cam.width as f32).contains(&x) && (0.0..cam.height as f32).contains(&y) {
                tracks[p].push((v as i32 + 1, observed[v].len() as i32));
                observed[v].push((x as f64, y as f64, p as u64 + 1));
            }
        }
    }
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
        imgs_bin.extend((observed[i].len() as u64).to_le_bytes());
        for &(x, y, p) in &observed[i] {
            [x, y].iter().for_each(|c| imgs_bin.extend(c.to_le_bytes()));
            imgs_bin.extend(p.to_le_bytes());
        }
        imgs_txt += &format!("{id} {} {} {} {} {} {} {} {id} {name}\n", q[0], q[1], q[2], q[3], t[0], t[1], t[2]);
        let line: Vec<String> = observed[i].iter().map(|(x, y, p)| format!("{x} {y} {p}")).collect();
        imgs_txt += &(line.join(" ") + "\n");
    }
    let mut points_bin = (points.len() as u64).to_le_bytes().to_vec();
    let mut points_txt = String::from(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
    );
    for (p, (point, track)) in points.iter().zip(&tracks).enumerate() {
        let id = p as u64 + 1;
        points_bin.extend(id.to_le_bytes());
        point.iter().for_each(|c| points_bin.extend((*c as f64).to_le_bytes()));
        points_bin.extend([128u8; 3]);
        points_bin.extend(0f64.to_le_bytes());
        points_bin.extend((track.len() as u64).to_le_bytes());
        track.iter().for_each(|&(v, k)| {
            points_bin.extend(v.to_le_bytes());
            points_bin.extend(k.to_le_bytes());
        });
        let track: Vec<String> = track.iter().map(|(v, k)| format!("{v} {k}")).collect();
        points_txt += &format!("{id} {} {} {} 128 128 128 0 {}\n", point[0], point[1], point[2], track.join(" "));
    }
    if binary {
        write_file(&model.join("cameras.bin"), &cams_bin)?;
        write_file(&model.join("images.bin"), &imgs_bin)?;
        write_file(&model.join("points3D.bin"), &points_bin)
    } else {
        write_file(&model.join("cameras.txt"), cams_txt.as_bytes())?;
        write_file(&model.join("images.txt"), imgs_txt.as_bytes())?;
        write_file(&model.join("points3D.txt"), points_txt.as_bytes())
    }
}

/// Pixel positions (as shares of the image's sides) of the points [`bound_points`] places.
const GRID: [f32; 3] = [1.0 / 6.0, 0.5, 5.0 / 6.0];

/// Stand-ins for a reconstruction's sparse points, which a generated scene does not have:
/// for each view, points on nine pixel rays (a 3 x 3 grid) at the nearest and farthest depth
/// of its content along its viewing axis, as the scene's extent gives them (the bounds the
/// LLFF writer stores), so loaders that take depth bounds from the points find the same ones.
pub fn bound_points(scene: &Scene) -> Vec<Vec3> {
    let mut points = Vec::new();
    for view in &scene.views {
        let cam = &view.camera;
        let (o, f) = (cam.origin(), cam.forward());
        for depth in view_bounds(&scene.extent, cam) {
            for gy in GRID {
                for gx in GRID {
                    let d = cam.direction(gx * cam.width as f32, gy * cam.height as f32);
                    points.push(axpy(o, depth as f32 / dot(d, f), d));
                }
            }
        }
    }
    points
}
