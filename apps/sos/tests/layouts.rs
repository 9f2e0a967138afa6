//! Every dataset layout end to end: the built-in synthetic scene is written in each layout the
//! adapters read, and opened as a user would, with only `[scene] kind` and `path` set. Each
//! adapter may move, turn and scale the capture into its own frame (LLFF recentres and
//! spherifies, NeRF++ normalises), so the test compares what no such change alters: which
//! photograph each view holds, the split, the intrinsics, the angles between the cameras'
//! axes and the cameras' distances relative to each other. Then `sos train` runs both stages
//! on every layout for a few steps and must finish with finite metrics.

mod common;

use common::{sos, temp_dir, text};
use sos_core::camera::{dot, sub, Camera};
use sos_core::config::RunConfig;
use sos_core::scene::Scene;
use sos_core::train::Session;
use sos_datasets::layouts::Format;
use sos_datasets::synthetic::{generate, SyntheticConfig};
// Links every plugin crate's registrations (dataset kinds, fields) into this test binary.
use sos_plugins as _;

/// The scene: small enough that a run takes seconds; every 8th view held out, the split the
/// layouts without one of their own apply.
const WIDTH: u32 = 64;
const HEIGHT: u32 = 48;
const VIEWS: usize = 16;

/// Largest pixel difference: the layouts store 8-bit images (half a step of rounding).
const PIXEL_TOLERANCE: f32 = 0.5 / 255.0 + 1e-6;

/// Largest error of a relative camera distance or of an axis angle (radians). Poses pass
/// through text and f32 files and the adapters' f64 normalisations: about 1e-6 relative each;
/// a misread axis or convention is off by a large fraction of a radian.
const GEOMETRY_TOLERANCE: f32 = 1e-3;

/// Index of the generator's view whose photograph `image` is (within 8-bit rounding).
fn same_photograph(original: &Scene, image: &sos_core::image::RgbImage) -> Option<usize> {
    original.views.iter().position(|v| {
        v.image.width == image.width
            && v.image.height == image.height
            && v.image.data.iter().zip(&image.data).all(|(a, b)| (a - b).abs() <= PIXEL_TOLERANCE)
    })
}

fn right(c: &Camera) -> [f32; 3] {
    c.rotate([1.0, 0.0, 0.0])
}

fn distance(a: &Camera, b: &Camera) -> f32 {
    let d = sub(a.origin(), b.origin());
    dot(d, d).sqrt()
}

/// Checks the layout's scene against the generator's; returns what differs.
fn compare(format: Format, original: &Scene, loaded: &Scene) -> Vec<String> {
    let name = format.name();
    let mut problems = Vec::new();
    if loaded.views.len() != original.views.len() {
        return vec![format!("{name}: {} views, the generator wrote {}", loaded.views.len(), original.views.len())];
    }
    let Some(map) = loaded.views.iter().map(|v| same_photograph(original, &v.image)).collect::<Option<Vec<usize>>>()
    else {
        return vec![format!("{name}: a view's photograph is none of the generator's")];
    };
    let mut test: Vec<usize> = loaded.test.iter().map(|&i| map[i]).collect();
    test.sort_unstable();
    if test != original.test {
        problems.push(format!("{name}: held-out views {test:?}, the generator's {:?}", original.test));
    }
    let scale = |scene: &Scene, index: &dyn Fn(usize) -> usize| {
        let n = scene.views.len();
        let sum: f32 = (0..n)
            .flat_map(|i| (0..n).map(move |j| (i, j)))
            .map(|(i, j)| distance(&scene.views[index(i)].camera, &scene.views[index(j)].camera))
            .sum();
        sum / (n * n) as f32
    };
    // Loaded view i holds the generator's view map[i]; compare in the generator's order.
    let inverse: Vec<usize> = (0..map.len()).map(|g| map.iter().position(|&m| m == g).unwrap_or(0)).collect();
    let (s0, s1) = (scale(original, &|i| i), scale(loaded, &|i| inverse[i]));
    for g in 0..original.views.len() {
        let (a, b) = (&original.views[g].camera, &loaded.views[inverse[g]].camera);
        let intrinsics = [(a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)];
        if intrinsics.iter().any(|(x, y)| (x - y).abs() > GEOMETRY_TOLERANCE * x.abs().max(1.0)) {
            problems.push(format!("{name}: view {g} intrinsics {intrinsics:?}"));
        }
        for h in 0..g {
            let (c, d) = (&original.views[h].camera, &loaded.views[inverse[h]].camera);
            let forward = (
                dot(a.forward(), c.forward()).clamp(-1.0, 1.0).acos(),
                dot(b.forward(), d.forward()).clamp(-1.0, 1.0).acos(),
            );
            let side =
                (dot(right(a), right(c)).clamp(-1.0, 1.0).acos(), dot(right(b), right(d)).clamp(-1.0, 1.0).acos());
            let spacing = (distance(a, c) / s0, distance(b, d) / s1);
            for (what, (x, y)) in [("axis angle", forward), ("side angle", side), ("relative distance", spacing)] {
                if (x - y).abs() > GEOMETRY_TOLERANCE {
                    problems.push(format!("{name}: views {h} and {g}: {what} {y}, the generator's {x}"));
                }
            }
        }
    }
    problems
}

#[test]
fn every_layout_reads_back_the_generators_scene_and_trains() {
    let dir = temp_dir("sos-layouts", "every_layout");
    let scene = generate(&SyntheticConfig { width: WIDTH, height: HEIGHT, views: VIEWS, ..SyntheticConfig::default() });
    assert_eq!(scene.test, [0, 8], "the generator holds out every 8th view");
    let mut problems = Vec::new();
    for format in Format::ALL {
        let layout_dir = dir.join("layouts").join(format.name());
        format.write(&scene, &layout_dir).unwrap_or_else(|e| panic!("{}: {e}", format.name()));
        let config = format!(
            "name = \"{name}\"\noutput_dir = \"runs\"\n[scene]\nkind = \"{kind}\"\npath = \"{path}\"\n\
             [field]\nkind = \"voxel-grid\"\nresolution = [24, 24, 24]\ninitial_resolution = [16, 16, 16]\n\
             [train]\nsteps = 30\nrays_per_step = 512\ncheckpoint_every = 0\n\
             [segment]\nsteps = 2\npatches = 2\npatch_size = 16\nstride = 2\n",
            name = format.name(),
            kind = format.kind(),
            path = format.scene_dir(&layout_dir).display()
        );
        let file = dir.join(format!("{}.toml", format.name()));
        std::fs::write(&file, &config).unwrap();
        let session = Session::from_config(RunConfig::load(&file).unwrap(), &dir)
            .unwrap_or_else(|e| panic!("{}: the layout does not open: {e}", format.name()));
        problems.extend(compare(format, &scene, &session.scene));

        let out = sos(&["train", "--quiet", &file.display().to_string()], &dir);
        let stderr = text(&out.stderr);
        assert!(out.status.success(), "{}: `sos train` failed:\n{stderr}", format.name());
        let metrics = dir.join("runs").join(format.name()).join("metrics.json");
        let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&metrics).unwrap()).unwrap();
        let test = &json["stage2"]["test"];
        for value in [&test["image"]["psnr_of_mean_mse"], &test["segmentation"]["miou"]] {
            assert!(value.as_f64().is_some_and(f64::is_finite), "{}: a metric is not finite: {value}", format.name());
        }
    }
    assert!(problems.is_empty(), "layouts that do not read back the generator's scene:\n{}", problems.join("\n"));
    std::fs::remove_dir_all(dir).ok();
}
