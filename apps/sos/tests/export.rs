//! End-to-end test of `sos export`: a tiny two-stage run on the synthetic room is exported, and
//! every file is parsed back (PLY with an independent reader, OBJ, GIF, PNG) and checked
//! against the scene it was trained on; plus the errors that must exit 2 naming their file.

use std::collections::HashMap;
use std::path::Path;

use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Property};
use sos_core::camera::{Camera, Vec3};
use sos_core::scene::{Scene, SceneExtent};
use sos_datasets::synthetic::{OBJECT_CENTRE, OBJECT_RADIUS};
use sos_datasets::{generate, SyntheticConfig};
// Link the plugin registrations so configs with plugin kinds parse in this test binary.
use sos_plugins as _;

mod common;

use common::{sos, text};

const WIDTH: u32 = 80;
const HEIGHT: u32 = 60;
const VIEWS: usize = 10;
const HOLD_OUT_EVERY: usize = 5;
const PATH_VIEWS: usize = 4;

/// The tiny run: 80x60, 10 views, a 48³ grid (the room's 7 m in 15 cm voxels: the object's
/// metre spans a few of them), `train_steps` + `seg_steps` steps.
fn config(name: &str, train_steps: usize, seg_steps: usize) -> String {
    format!(
        r#"name = "{name}"
seed = 3

[scene]
kind = "synthetic"
width = {WIDTH}
height = {HEIGHT}
views = {VIEWS}
hold_out_every = {HOLD_OUT_EVERY}
render_path_views = {PATH_VIEWS}

[field]
kind = "voxel-grid"
resolution = [48, 48, 48]
initial_resolution = [24, 24, 24]

[train]
steps = {train_steps}
rays_per_step = 1024
checkpoint_every = 0

[render]
chunk = 4096

[segment]
steps = {seg_steps}
patches = 4
patch_size = 16
stride = 2
"#
    )
}

/// The scene the config trains on, generated here independently of the run.
fn scene() -> Scene {
    generate(&SyntheticConfig {
        width: WIDTH,
        height: HEIGHT,
        views: VIEWS,
        hold_out_every: HOLD_OUT_EVERY,
        render_path_views: PATH_VIEWS,
        ..Default::default()
    })
}

fn bounds(scene: &Scene) -> (Vec3, Vec3) {
    match scene.extent {
        SceneExtent::Bounded { min, max } => (min, max),
        other => panic!("the object-centric room has a bounded extent, not {other}"),
    }
}

fn inside(p: Vec3, (min, max): (Vec3, Vec3)) -> bool {
    (0..3).all(|k| p[k] >= min[k] - 1e-4 && p[k] <= max[k] + 1e-4)
}

fn distance(a: Vec3, b: Vec3) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>().sqrt()
}

fn centroid(points: &[Vec3]) -> Vec3 {
    let n = points.len() as f64;
    [0, 1, 2].map(|k| (points.iter().map(|p| p[k] as f64).sum::<f64>() / n) as f32)
}

/// A PLY file read back with ply-rs-bw: its header's element counts and its elements.
struct Ply {
    counts: HashMap<String, usize>,
    elements: HashMap<String, Vec<DefaultElement>>,
}

fn read_ply(path: &Path) -> Ply {
    let mut file = std::fs::File::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let ply = Parser::<DefaultElement>::new().read_ply(&mut file).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let counts = ply.header.elements.iter().map(|(name, e)| (name.clone(), e.count)).collect();
    let elements = ply.payload.into_iter().collect();
    Ply { counts, elements }
}

fn float(e: &DefaultElement, key: &str) -> f32 {
    match e.get(key) {
        Some(Property::Float(v)) => *v,
        other => panic!("property {key} is {other:?}, not a float"),
    }
}

fn byte(e: &DefaultElement, key: &str) -> u8 {
    match e.get(key) {
        Some(Property::UChar(v)) => *v,
        other => panic!("property {key} is {other:?}, not a uchar"),
    }
}

fn position(e: &DefaultElement) -> Vec3 {
    [float(e, "x"), float(e, "y"), float(e, "z")]
}

/// `rows` of a camera-to-world matrix as the poses file holds them (4x4).
fn matrix(camera: &Camera) -> Vec<Vec<f32>> {
    let mut rows: Vec<Vec<f32>> = camera.cam_to_world.iter().map(|r| r.to_vec()).collect();
    rows.push(vec![0.0, 0.0, 0.0, 1.0]);
    rows
}

fn png_size(path: &Path) -> (u32, u32) {
    let img = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    (img.width(), img.height())
}

#[test]
fn export_writes_every_part_and_each_parses_back_consistently() {
    let dir = common::temp_dir("sos-export", "all");
    std::fs::write(dir.join("tiny.toml"), config("tiny", 250, 10)).unwrap();
    let out = sos(&["train", "tiny.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}\n{}", text(&out.stdout), text(&out.stderr));

    // Three cameras the dataset does not have, at another image size: around the object, higher
    // up than the training orbit.
    let (pw, ph, focal) = (48u32, 36u32, 40.0f32);
    let cameras: Vec<Camera> = [0.3f32, 2.4, 4.5]
        .iter()
        .map(|&a| {
            let c = OBJECT_CENTRE;
            let eye = [c[0] + 2.0 * a.sin(), c[1] + 1.4, c[2] + 2.0 * a.cos()];
            Camera::look_at(eye, c, [0.0, 1.0, 0.0], pw, ph, focal)
        })
        .collect();
    let poses = serde_json::json!({
        "width": pw,
        "height": ph,
        "focal": focal,
        "poses": cameras.iter().map(matrix).collect::<Vec<_>>(),
    });
    std::fs::write(dir.join("poses.json"), serde_json::to_string_pretty(&poses).unwrap()).unwrap();

    let started = std::time::Instant::now();
    let out = sos(&["export", "tiny.toml", "--poses", "poses.json", "--mesh-resolution", "64"], &dir);
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", text(&out.stderr));
    assert!(started.elapsed().as_secs() < 60, "export took {:?}", started.elapsed());
    let export = dir.join("runs/tiny/export");
    let scene = scene();
    let extent = bounds(&scene);
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(export.join("export.json")).unwrap()).unwrap();

    // Frames and GIF: one per camera-path view, at the path's size.
    assert_eq!(scene.render_path.len(), PATH_VIEWS);
    for i in 0..PATH_VIEWS {
        assert_eq!(png_size(&export.join(format!("frames/{i:04}.png"))), (WIDTH, HEIGHT));
    }
    assert!(!export.join(format!("frames/{PATH_VIEWS:04}.png")).exists());
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut gif = options.read_info(std::fs::File::open(export.join("path.gif")).unwrap()).unwrap();
    assert_eq!((gif.width(), gif.height()), (WIDTH as u16, HEIGHT as u16));
    let mut frames = 0;
    while let Some(frame) = gif.read_next_frame().unwrap() {
        assert_eq!((frame.width, frame.height), (WIDTH as u16, HEIGHT as u16));
        frames += 1;
    }
    assert_eq!(frames, PATH_VIEWS);

    // Point cloud: as many vertices as the header says, all in the room, around the object,
    // coloured like it (orange and red checkers: far more red than blue).
    let ply = read_ply(&export.join("points.ply"));
    let vertices = &ply.elements["vertex"];
    assert!(!vertices.is_empty(), "empty point cloud");
    assert_eq!(vertices.len(), ply.counts["vertex"]);
    assert_eq!(vertices.len() as u64, record["points"]["points"].as_u64().unwrap());
    let points: Vec<Vec3> = vertices.iter().map(position).collect();
    for p in &points {
        assert!(inside(*p, extent), "point {p:?} outside the extent {extent:?}");
    }
    let c = centroid(&points);
    assert!(
        distance(c, OBJECT_CENTRE) < 1.2 * OBJECT_RADIUS,
        "the point cloud's centroid {c:?} is {} from the object's centre {OBJECT_CENTRE:?}",
        distance(c, OBJECT_CENTRE)
    );
    let near = points.iter().filter(|p| distance(**p, OBJECT_CENTRE) < 2.0 * OBJECT_RADIUS).count();
    assert!(near * 3 >= points.len() * 2, "only {near} of {} points lie near the object", points.len());
    let mean = |key: &str| vertices.iter().map(|v| byte(v, key) as f64).sum::<f64>() / vertices.len() as f64;
    let (red, blue) = (mean("red"), mean("blue"));
    assert!(red > blue + 30.0, "mean colour red {red:.0}, blue {blue:.0}: not the object's");

    // Mesh: PLY and OBJ agree; faces index real vertices; the surface lies in the room, around
    // the object.
    let mesh = read_ply(&export.join("mesh.ply"));
    let (mv, mf) = (&mesh.elements["vertex"], &mesh.elements["face"]);
    assert!(!mv.is_empty() && !mf.is_empty(), "empty mesh: {}", record["mesh"]);
    assert_eq!((mv.len(), mf.len()), (mesh.counts["vertex"], mesh.counts["face"]));
    let positions: Vec<Vec3> = mv.iter().map(position).collect();
    for p in &positions {
        assert!(inside(*p, extent), "mesh vertex {p:?} outside the extent {extent:?}");
    }
    for f in mf {
        let Some(Property::ListInt(ix)) = f.get("vertex_indices") else { panic!("face without indices: {f:?}") };
        assert_eq!(ix.len(), 3);
        assert!(ix.iter().all(|&i| i >= 0 && (i as usize) < mv.len()), "face {ix:?} of {} vertices", mv.len());
    }
    let c = centroid(&positions);
    assert!(
        distance(c, OBJECT_CENTRE) < 1.5 * OBJECT_RADIUS,
        "the mesh's centroid {c:?} is {} from the object's centre",
        distance(c, OBJECT_CENTRE)
    );
    let obj = std::fs::read_to_string(export.join("mesh.obj")).unwrap();
    let count = |prefix: &str| obj.lines().filter(|l| l.starts_with(prefix)).count();
    assert_eq!((count("v "), count("vn "), count("f ")), (mv.len(), mv.len(), mf.len()));
    let first: Vec<f32> =
        obj.lines().find(|l| l.starts_with("v ")).unwrap()[2..].split(' ').map(|v| v.parse().unwrap()).collect();
    assert_eq!(first, positions[0].to_vec(), "OBJ and PLY list different first vertices");
    for l in obj.lines().filter(|l| l.starts_with("f ")) {
        for corner in l[2..].split(' ') {
            let i: usize = corner.split("//").next().unwrap().parse().unwrap();
            assert!((1..=mv.len()).contains(&i), "OBJ face {l}");
        }
    }

    // Masks of the poses file's cameras, at their size.
    for i in 0..cameras.len() {
        for sub in ["masks", "overlays"] {
            assert_eq!(png_size(&export.join(format!("{sub}/{i:04}.png"))), (pw, ph), "{sub}/{i:04}.png");
        }
    }
    assert_eq!(record["masks"]["source"], "poses file");

    // Without a poses file, the held-out views' masks; into a folder outside the run.
    let out = sos(&["export", "tiny.toml", "--what", "masks", "--out", "held-out"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    for &i in &scene.test {
        let name = format!("{}.png", scene.views[i].name);
        assert_eq!(png_size(&dir.join("held-out/masks").join(&name)), (WIDTH, HEIGHT), "{name}");
    }
    assert!(!dir.join("held-out/points.ply").exists(), "--what masks wrote a point cloud");

    // `sos render --export gif` renders, then exports the GIF alone.
    std::fs::remove_file(export.join("path.gif")).unwrap();
    let out = sos(&["render", "tiny.toml", "--export", "gif"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(dir.join("runs/tiny/path/0000.png").is_file() && export.join("path.gif").is_file());
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(export.join("export.json")).unwrap()).unwrap();
    assert_eq!(record["path"]["frames"], PATH_VIEWS);
    assert!(record.get("points").is_none() && record["path"].get("frames_dir").is_none(), "{record}");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_malformed_poses_file_exits_2_naming_it() {
    let dir = common::temp_dir("sos-export", "poses");
    std::fs::write(dir.join("tiny.toml"), config("poses", 1, 0)).unwrap();
    let cases: [(&str, &str, &str); 4] = [
        ("broken.json", r#"{"width": 40, "height": 30, "focal": 35, "poses": [[[1, 0"#, "broken.json"),
        (
            "scaled.json",
            r#"{"width": 40, "height": 30, "focal": 35, "poses": [[[2,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]]}"#,
            "poses[0]",
        ),
        ("misspelt.json", r#"{"width": 40, "height": 30, "focul": 35, "poses": []}"#, "focul"),
        // A subnormal focal length: every pixel's ray direction would overflow to NaN.
        (
            "subnormal.json",
            r#"{"width": 4, "height": 3, "focal": 1e-45, "poses": [[[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]]}"#,
            "focal length",
        ),
    ];
    for (file, body, key) in cases {
        std::fs::write(dir.join(file), body).unwrap();
        let out = sos(&["export", "tiny.toml", "--poses", file], &dir);
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{file}: {stderr}");
        assert!(stderr.contains(file) && stderr.contains(key), "{file}: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
    // A missing checkpoint names it and what to do.
    std::fs::write(
        dir.join("good.json"),
        r#"{"width": 4, "height": 3, "focal": 3, "poses": [[[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]]}"#,
    )
    .unwrap();
    let out = sos(&["export", "tiny.toml", "--poses", "good.json", "--checkpoint", "nowhere.bin"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("nowhere.bin") && stderr.contains("sos train"), "{stderr}");
    assert!(!dir.join("runs/poses/export").exists(), "an export that failed left a folder");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_camera_that_sees_nothing_gets_an_empty_mask() {
    let dir = common::temp_dir("sos-export", "empty-view");
    std::fs::write(dir.join("tiny.toml"), config("empty", 2, 2)).unwrap();
    let out = sos(&["train", "tiny.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    // Outside the room, looking away from it: every ray misses the scene's extent.
    std::fs::write(
        dir.join("away.json"),
        r#"{"width": 24, "height": 24, "focal": 20, "poses": [[[-1,0,0,0],[0,1,0,1.5],[0,0,-1,60],[0,0,0,1]]]}"#,
    )
    .unwrap();
    let out = sos(&["export", "tiny.toml", "--what", "masks", "--poses", "away.json"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let mask = image::open(dir.join("runs/empty/export/masks/0000.png")).unwrap().to_luma8();
    assert_eq!(mask.dimensions(), (24, 24));
    assert!(mask.pixels().all(|p| p.0[0] == 0), "a view of nothing was given foreground");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn a_checkpoint_without_a_head_says_to_run_segment() {
    let dir = common::temp_dir("sos-export", "nohead");
    std::fs::write(dir.join("s1.toml"), config("nohead", 2, 0)).unwrap();
    let out = sos(&["train", "s1.toml", "--quiet"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let out = sos(&["export", "s1.toml"], &dir);
    let stderr = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("checkpoint.bin") && stderr.contains("no segmentation head") && stderr.contains("sos segment"),
        "{stderr}"
    );
    assert!(!dir.join("runs/nohead/export").exists());
    // The bad numbers of the flags are named too.
    let out = sos(&["export", "s1.toml", "--mesh-resolution", "4"], &dir);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("--mesh-resolution"), "{}", text(&out.stderr));
    std::fs::remove_dir_all(dir).ok();
}
