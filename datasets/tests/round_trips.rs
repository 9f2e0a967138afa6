//! Every layout round-trips the generator's scenes: poses to 1e-6, identical rays across
//! formats, images to 8-bit rounding, masks exactly, the split preserved; plus format-specific
//! options (COLMAP distortion and downscaled images, CO3D intrinsics formats and sequence
//! choice, NeRF++ normalisation, LLFF spherify) and the pinned first pose of LLFF flower.

use std::path::{Path, PathBuf};

use sos_core::render::rays::RayBatch;
use sos_core::scene::{Scene, SceneExtent};
use sos_datasets::co3d::{read_jgz, write_jgz, FrameAnnotation, SequenceAnnotation};
use sos_datasets::layouts::{Format, CO3D_CATEGORY, CO3D_SEQUENCE};
use sos_datasets::synthetic::{generate, Rig, SyntheticConfig, OBJECT_CENTRE, OBJECT_RADIUS, ROOM_MAX, ROOM_MIN};
use sos_datasets::{
    load_blendedmvs, load_co3d, load_colmap, load_llff, load_tanks_temples, BlendedMvsConfig, Co3dConfig, ColmapConfig,
    LlffConfig, TanksTemplesConfig,
};

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sos-rt-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn scene(rig: Rig) -> Scene {
    generate(&SyntheticConfig { rig, width: 64, height: 48, views: 16, ..Default::default() })
}

const ROOM: [[f32; 3]; 2] = [ROOM_MIN, ROOM_MAX];

/// Asserts `loaded` holds the views of `original` (matched by name) with poses to 1e-6,
/// intrinsics to 1e-4 px, images to 8-bit rounding, identical masks, the same rays and the
/// same held-out views.
fn assert_same_views(original: &Scene, loaded: &Scene, what: &str) {
    loaded.validate().unwrap_or_else(|e| panic!("{what}: invalid scene: {e}"));
    assert_eq!(original.views.len(), loaded.views.len(), "{what}: view count");
    for o in &original.views {
        // Blender names views by their path, e.g. `train_view_001`.
        let same =
            |l: &str| l == o.name || ["train_", "test_"].iter().any(|p| l.strip_prefix(p) == Some(o.name.as_str()));
        let l =
            loaded.views.iter().find(|l| same(&l.name)).unwrap_or_else(|| panic!("{what}: view {} not loaded", o.name));
        let (a, b) = (&o.camera, &l.camera);
        let pose_err = a
            .cam_to_world
            .iter()
            .flatten()
            .zip(b.cam_to_world.iter().flatten())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(pose_err <= 1e-6, "{what}: view {}: pose differs by {pose_err}", o.name);
        assert_eq!((a.width, a.height), (b.width, b.height), "{what}: {}", o.name);
        for (x, y) in [(a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)] {
            assert!((x - y).abs() < 1e-4, "{what}: view {}: intrinsics {a:?} vs {b:?}", o.name);
        }
        let img_err = o.image.data.iter().zip(&l.image.data).map(|(p, q)| (p - q).abs()).fold(0.0, f32::max);
        assert!(img_err <= 0.5 / 255.0 + 1e-5, "{what}: view {}: colour {img_err}", o.name);
        assert_eq!(o.mask, l.mask, "{what}: view {}: mask", o.name);
        let (ra, rb) = (RayBatch::full_image(a), RayBatch::full_image(b));
        let ray_err = ra
            .origins
            .iter()
            .chain(&ra.directions)
            .zip(rb.origins.iter().chain(&rb.directions))
            .flat_map(|(p, q)| (0..3).map(move |k| (p[k] - q[k]).abs()))
            .fold(0.0, f32::max);
        assert!(ray_err <= 1e-5, "{what}: view {}: rays differ by {ray_err}", o.name);
    }
    let names = |s: &Scene, idx: &[usize]| {
        let strip = |n: &str| n.trim_start_matches("train_").trim_start_matches("test_").to_string();
        let mut n: Vec<String> = idx.iter().map(|&i| strip(&s.views[i].name)).collect();
        n.sort();
        n
    };
    assert_eq!(names(original, &original.test), names(loaded, &loaded.test), "{what}: test split");
    assert_eq!(names(original, &original.train), names(loaded, &loaded.train), "{what}: train split");
}

#[test]
fn every_layout_round_trips_the_object_centric_rig() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("oc");
    for format in Format::ALL {
        let d = dir.join(format.name());
        format.write(&s, &d).unwrap();
        let loaded = format.open_raw(&d, Some(ROOM)).unwrap_or_else(|e| panic!("{format:?}: {e}"));
        assert_same_views(&s, &loaded, format.name());
        // Formats with no stored bounds take the configured box.
        if format != Format::Llff && format != Format::TanksTemples {
            assert_eq!(loaded.extent, SceneExtent::Bounded { min: ROOM_MIN, max: ROOM_MAX }, "{format:?}");
        }
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn forward_facing_rig_round_trips_where_the_layout_can_hold_it() {
    let s = scene(Rig::ForwardFacing);
    let dir = temp_dir("ff");
    for format in Format::ALL {
        let d = dir.join(format.name());
        if format == Format::Nsvf {
            // NSVF needs a bounding box, which forward-facing scenes do not have.
            let err = format.write(&s, &d).unwrap_err().to_string();
            assert!(err.contains("bounding box"), "{err}");
            continue;
        }
        format.write(&s, &d).unwrap();
        let loaded = format.open_raw(&d, None).unwrap_or_else(|e| panic!("{format:?}: {e}"));
        assert_same_views(&s, &loaded, format.name());
        // COLMAP's points and BlendedMVS's depth ranges carry the depth bounds: a
        // forward-facing extent holding the original's, its near bound 10 % closer as the LLFF
        // loader takes it, both a little wider where each view measures the points along its
        // own axis.
        if matches!(format, Format::ColmapBin | Format::ColmapTxt | Format::BlendedMvs) {
            let (SceneExtent::ForwardFacing { near: n0, far: f0, .. }, SceneExtent::ForwardFacing { near, far, .. }) =
                (s.extent, loaded.extent)
            else {
                panic!("{format:?}: {:?}", loaded.extent)
            };
            let holds = near <= 0.9 * n0 && far >= f0;
            let tight = near >= 0.8 * n0 && far <= 1.05 * f0;
            assert!(holds && tight, "{format:?}: {near} to {far} vs {n0} to {f0}");
        }
    }
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn default_extents_and_bounds() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("ext");
    // Without a box, COLMAP-like layouts are unbounded around the point the cameras look at:
    // the generator's object centre.
    let d = dir.join("colmap");
    Format::ColmapBin.write(&s, &d).unwrap();
    let loaded = Format::ColmapBin.open_raw(&d, None).unwrap();
    let SceneExtent::Unbounded { center, radius } = loaded.extent else { panic!("{:?}", loaded.extent) };
    let want = sos_datasets::synthetic::OBJECT_CENTRE;
    assert!((0..3).all(|k| (center[k] - want[k]).abs() < 1e-3), "{center:?}");
    assert!((radius - 1.15).abs() < 1e-3, "half the orbit radius 2.3, got {radius}");
    assert_eq!(loaded.render_path.len(), 40);
    // NSVF's bbox.txt is the extent when it bounds an object; the room box written here holds
    // the cameras, so the capture gets COLMAP's unbounded extent instead. The original
    // BlendedMVS near comes from the depth range.
    let colmap_extent = loaded.extent;
    let d = dir.join("nsvf");
    Format::Nsvf.write(&s, &d).unwrap();
    let loaded = Format::Nsvf.open_raw(&d, None).unwrap();
    match (loaded.extent, colmap_extent) {
        (SceneExtent::Unbounded { center: a, radius: ra }, SceneExtent::Unbounded { center: b, radius: rb }) => {
            assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-4) && (ra - rb).abs() < 1e-4, "{a:?} {ra} vs {b:?} {rb}")
        }
        (a, b) => panic!("NSVF {a:?}, COLMAP {b:?}"),
    }
    std::fs::write(d.join("bbox.txt"), "-1 -0.1 -1 1 1.9 1 0.01\n").unwrap();
    let loaded = Format::Nsvf.open_raw(&d, None).unwrap();
    assert_eq!(loaded.extent, SceneExtent::Bounded { min: [-1.0, -0.1, -1.0], max: [1.0, 1.9, 1.0] });
    let d = dir.join("mvs");
    Format::BlendedMvs.write(&s, &d).unwrap();
    let loaded = Format::BlendedMvs.open_raw(&d, None).unwrap();
    assert!(loaded.near > 0.0 && loaded.near < 1.0, "{}", loaded.near);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn nerfpp_normalisation_puts_cameras_in_the_unit_sphere() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("tt");
    Format::TanksTemples.write(&s, &dir).unwrap();
    let cfg = TanksTemplesConfig { path: dir.clone(), ..Default::default() };
    let loaded = load_tanks_temples(&cfg, &dir).unwrap();
    loaded.validate().unwrap();
    assert_eq!(loaded.extent, SceneExtent::Unbounded { center: [0.0; 3], radius: 1.0 });
    // The mean training camera goes to the origin, the farthest to 1 / 1.1.
    let train: Vec<[f32; 3]> = loaded.train.iter().map(|&i| loaded.views[i].camera.origin()).collect();
    let norm = |o: &[f32; 3]| o.iter().map(|x| x * x).sum::<f32>().sqrt();
    let max = train.iter().map(norm).fold(0.0, f32::max);
    assert!((max - 1.0 / 1.1).abs() < 1e-5, "{max}");
    let mean: Vec<f32> = (0..3).map(|k| train.iter().map(|o| o[k]).sum::<f32>() / train.len() as f32).collect();
    assert!(mean.iter().all(|m| m.abs() < 1e-5), "{mean:?}");
    // Rotations are untouched and translations follow one similarity transform.
    let (o0, l0) = (&s.views[s.train[0]].camera, &loaded.views[0].camera);
    let (o1, l1) = (&s.views[s.train[1]].camera, &loaded.views[1].camera);
    let d = |a: [f32; 3], b: [f32; 3]| ((0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f32>()).sqrt();
    let scale = d(l0.origin(), l1.origin()) / d(o0.origin(), o1.origin());
    assert!((scale - 1.0 / (1.1 * 2.3)).abs() < 0.02, "{scale}");
    for r in 0..3 {
        for c in 0..3 {
            assert!((o0.cam_to_world[r][c] - l0.cam_to_world[r][c]).abs() < 1e-6);
        }
    }
    // Loading the normalised capture again leaves it as it is ("auto").
    let again = temp_dir("tt2");
    Format::TanksTemples.write(&loaded, &again).unwrap();
    let twice = load_tanks_temples(&TanksTemplesConfig { path: again.clone(), ..Default::default() }, &again).unwrap();
    // (The writer prefixes the file names with the index, the views being out of name order.)
    assert_eq!(twice.views.len(), loaded.views.len());
    for (a, b) in loaded.views.iter().zip(&twice.views) {
        assert!(b.name.ends_with(&a.name), "{} {}", a.name, b.name);
        assert_eq!(a.camera, b.camera, "view {}", a.name);
    }
    std::fs::remove_dir_all(dir).ok();
    std::fs::remove_dir_all(again).ok();
}

fn edit(path: &Path, f: impl FnOnce(String) -> String) {
    let text = std::fs::read_to_string(path).unwrap();
    std::fs::write(path, f(text)).unwrap();
}

#[test]
fn colmap_distortion_and_downscaled_images() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("colmap");
    Format::ColmapTxt.write(&s, &dir).unwrap();
    let cams = dir.join("sparse/0/cameras.txt");
    let cfg = ColmapConfig { path: dir.clone(), ..Default::default() };
    // OPENCV with zero distortion is a pinhole camera: identical result.
    edit(&cams, |t| {
        t.lines()
            .map(|l| match l.starts_with('#') {
                true => format!("{l}\n"),
                false => format!("{} 0 0 0 0\n", l.replace(" PINHOLE ", " OPENCV ")),
            })
            .collect()
    });
    let loaded = load_colmap(&cfg, &dir).unwrap();
    assert_same_views(&s, &loaded, "OPENCV without distortion");
    // Non-zero distortion is refused with the fix, unless ignored.
    edit(&cams, |t| t.replacen(" 0 0 0 0\n", " 0.1 0 0 0\n", 1));
    let err = load_colmap(&cfg, &dir).unwrap_err().to_string();
    assert!(
        err.contains("cameras.txt") && err.contains("image_undistorter") && err.contains("ignore_distortion"),
        "{err}"
    );
    let ignored = load_colmap(&ColmapConfig { ignore_distortion: true, ..cfg.clone() }, &dir).unwrap();
    assert_same_views(&s, &ignored, "distortion ignored");
    // Fisheye models are always refused.
    edit(&cams, |t| t.replace(" OPENCV ", " OPENCV_FISHEYE "));
    let err = load_colmap(&ColmapConfig { ignore_distortion: true, ..cfg.clone() }, &dir).unwrap_err().to_string();
    assert!(err.contains("fisheye"), "{err}");
    // Back to PINHOLE; a half-size copy of the images scales the intrinsics; an image the model
    // does not register is skipped.
    Format::ColmapTxt.write(&s, &dir).unwrap();
    for v in &s.views {
        v.image.resized(32, 24).save_png(&dir.join(format!("half/{}.png", v.name))).unwrap();
    }
    s.views[0].image.save_png(&dir.join("images/unregistered.png")).unwrap();
    std::fs::remove_dir_all(dir.join("masks")).unwrap();
    let half = load_colmap(&ColmapConfig { images: "half".into(), ..cfg.clone() }, &dir).unwrap();
    half.validate().unwrap();
    assert_eq!(half.views.len(), s.views.len());
    let (h, o) = (&half.views[3].camera, &s.views[3].camera);
    assert!((h.fx - o.fx / 2.0).abs() < 1e-4 && (h.cx - o.cx / 2.0).abs() < 1e-4 && h.width == 32);
    let full = load_colmap(&cfg, &dir).unwrap();
    assert_eq!(full.views.len(), s.views.len());
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn co3d_intrinsics_formats_and_sequence_choice() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("co3d");
    // ndc_norm_image_bounds differs from ndc_isotropic on non-square images.
    sos_datasets::write_co3d(&s, &dir, CO3D_CATEGORY, CO3D_SEQUENCE, false).unwrap();
    let root = dir.join(CO3D_CATEGORY);
    let cfg = Co3dConfig { path: root.clone(), ..Default::default() };
    let loaded = load_co3d(&cfg, &root).unwrap();
    assert_same_views(&s, &loaded, "co3d ndc_norm_image_bounds");
    let frames_path = root.join("frame_annotations.jgz");
    let frames: Vec<FrameAnnotation> = read_jgz(&frames_path, "").unwrap();
    assert_eq!(frames[0].viewpoint.as_ref().unwrap().intrinsics_format, "ndc_norm_image_bounds");
    // A second, better-scored sequence (the same frames shifted by one metre along x) is chosen
    // by default; `sequence` picks the first again.
    let mut all = frames.clone();
    for f in &frames {
        let mut g = f.clone();
        g.sequence_name = "seq_001".into();
        let vp = g.viewpoint.as_mut().unwrap();
        // X_cam = X_world·R + T: moving the world by −x·e_x moves T by −R[0] (row 0 of R).
        for k in 0..3 {
            vp.t[k] -= vp.r[0][k];
        }
        all.push(g);
    }
    write_jgz(&frames_path, &all).unwrap();
    let seqs_path = root.join("sequence_annotations.jgz");
    let mut seqs: Vec<SequenceAnnotation> = read_jgz(&seqs_path, "").unwrap();
    seqs.push(SequenceAnnotation {
        sequence_name: "seq_001".into(),
        category: CO3D_CATEGORY.into(),
        viewpoint_quality_score: Some(5.0),
    });
    write_jgz(&seqs_path, &seqs).unwrap();
    let best = load_co3d(&cfg, &root).unwrap();
    assert_eq!(best.name, "seq_001");
    for (a, b) in s.views.iter().zip(&best.views) {
        let (oa, ob) = (a.camera.origin(), b.camera.origin());
        assert!((ob[0] - (oa[0] + 1.0)).abs() < 1e-5 && (ob[1] - oa[1]).abs() < 1e-5, "{oa:?} {ob:?}");
    }
    let first = load_co3d(&Co3dConfig { sequence: Some(CO3D_SEQUENCE.into()), ..cfg.clone() }, &root).unwrap();
    assert_same_views(&s, &first, "co3d chosen sequence");
    let err = load_co3d(&Co3dConfig { sequence: Some("nope".into()), ..cfg.clone() }, &root).unwrap_err().to_string();
    assert!(err.contains("frame_annotations.jgz") && err.contains("seq_001"), "{err}");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn co3d_soft_masks_are_thresholded_at_one_half() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("co3d-soft");
    Format::Co3d.write(&s, &dir).unwrap();
    let root = dir.join(CO3D_CATEGORY);
    // Soften mask 2: foreground 0.6, background 0.4.
    let path = root.join(CO3D_SEQUENCE).join("masks").join(format!("{}.png", s.views[2].name));
    let mut soft = s.views[2].mask.clone().unwrap();
    soft.data.iter_mut().for_each(|v| *v = 0.4 + 0.2 * *v);
    soft.save_png(&path).unwrap();
    let loaded = load_co3d(&Co3dConfig { path: root.clone(), ..Default::default() }, &root).unwrap();
    assert_eq!(loaded.views[2].mask, s.views[2].mask);
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn llff_spherify_is_chosen_from_the_camera_layout() {
    for (rig, spherified) in [(Rig::ObjectCentric, true), (Rig::ForwardFacing, false)] {
        let s = scene(rig);
        let dir = temp_dir(&format!("auto-sph-{rig:?}"));
        Format::Llff.write(&s, &dir).unwrap();
        let cfg = LlffConfig { path: dir.clone(), factor: Some(1), ..Default::default() };
        let loaded = load_llff(&cfg, &dir).unwrap();
        let forward = matches!(loaded.extent, SceneExtent::ForwardFacing { .. });
        assert_eq!(!forward, spherified, "{rig:?}: {:?}", loaded.extent);
        let notes = sos_core::plugin::DatasetConfig::derived(&cfg, Path::new(""), &loaded);
        let note = notes.iter().find(|d| d.key == "scene.spherify").expect("a spherify note");
        assert_eq!(note.value, spherified.to_string(), "{rig:?}");
        std::fs::remove_dir_all(dir).ok();
    }
}

/// A COLMAP model of a forward-facing capture is read as LLFF would read it, with depth
/// bounds from its points; without points it falls back to the unbounded extent (and says
/// why), and `forward_facing = true` then names the missing file.
#[test]
fn colmap_forward_facing_is_chosen_from_the_cameras_and_bounded_by_the_points() {
    // BlendedMVS's original layout chooses the same way, bounded by its depth ranges.
    for rig in [Rig::ObjectCentric, Rig::ForwardFacing] {
        let s = scene(rig);
        let dir = temp_dir(&format!("mvs-ff-{rig:?}"));
        Format::BlendedMvs.write(&s, &dir).unwrap();
        let cfg = BlendedMvsConfig { path: dir.clone(), ..Default::default() };
        let loaded = load_blendedmvs(&cfg, &dir).unwrap();
        loaded.validate().unwrap();
        let forward = matches!(loaded.extent, SceneExtent::ForwardFacing { .. });
        assert_eq!(forward, rig == Rig::ForwardFacing, "{rig:?}: {:?}", loaded.extent);
        let notes = sos_core::plugin::DatasetConfig::derived(&cfg, Path::new(""), &loaded);
        assert!(notes.iter().any(|d| d.key == "scene.forward_facing" && d.value == forward.to_string()), "{notes:?}");
        let off = BlendedMvsConfig { forward_facing: Some(false), ..cfg.clone() };
        assert!(matches!(load_blendedmvs(&off, &dir).unwrap().extent, SceneExtent::Unbounded { .. }));
        std::fs::remove_dir_all(dir).ok();
    }
    for (rig, forward) in [(Rig::ObjectCentric, false), (Rig::ForwardFacing, true)] {
        let s = scene(rig);
        let dir = temp_dir(&format!("colmap-ff-{rig:?}"));
        Format::ColmapBin.write(&s, &dir).unwrap();
        let cfg = ColmapConfig { path: dir.clone(), ..Default::default() };
        let loaded = load_colmap(&cfg, &dir).unwrap();
        loaded.validate().unwrap();
        assert_eq!(matches!(loaded.extent, SceneExtent::ForwardFacing { .. }), forward, "{rig:?}: {:?}", loaded.extent);
        let notes = sos_core::plugin::DatasetConfig::derived(&cfg, Path::new(""), &loaded);
        let note = notes.iter().find(|d| d.key == "scene.forward_facing").expect("a forward_facing note");
        assert_eq!(note.value, forward.to_string(), "{rig:?}");
        assert!(notes.iter().all(|d| !d.reason.contains("may hold little")), "{notes:?}");
        if forward {
            // Scaled so the nearest point is at 1 / 0.75, the extent's near 10 % closer.
            let SceneExtent::ForwardFacing { near, .. } = loaded.extent else { unreachable!() };
            assert!((near - 0.9 / 0.75).abs() < 1e-4, "{near}");
            assert_eq!(loaded.render_path.len(), 120);
            // No points: unbounded, with the reason; forced forward-facing names the file.
            std::fs::write(dir.join("sparse/0/points3D.bin"), 0u64.to_le_bytes()).unwrap();
            let bare = load_colmap(&cfg, &dir).unwrap();
            assert!(matches!(bare.extent, SceneExtent::Unbounded { .. }), "{:?}", bare.extent);
            let notes = sos_core::plugin::DatasetConfig::derived(&cfg, Path::new(""), &bare);
            assert!(notes.iter().any(|d| d.reason.contains("no points3D")), "{notes:?}");
            let extent_note = notes.iter().find(|d| d.key == "scene.extent").expect("an extent note");
            assert!(extent_note.reason.contains("may hold little"), "{extent_note:?}");
            let forced = ColmapConfig { forward_facing: Some(true), ..cfg.clone() };
            let err = load_colmap(&forced, &dir).unwrap_err().to_string();
            assert!(err.contains("points3D.bin") && err.contains("forward_facing"), "{err}");
            let err = load_colmap(&ColmapConfig { bd_factor: -0.75, ..cfg.clone() }, &dir).unwrap_err().to_string();
            assert!(err.contains("`bd_factor`"), "{err}");
        }
        std::fs::remove_dir_all(dir).ok();
    }
}

#[test]
fn llff_spherify_centres_a_360_capture() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("sph");
    Format::Llff.write(&s, &dir).unwrap();
    let cfg = LlffConfig { path: dir.clone(), factor: Some(1), spherify: Some(true), ..Default::default() };
    let loaded = load_llff(&cfg, &dir).unwrap();
    loaded.validate().unwrap();
    assert_eq!(loaded.extent, SceneExtent::Unbounded { center: [0.0; 3], radius: 1.0 });
    // Cameras at RMS distance 1 from the origin, every viewing axis through it (the generator's
    // cameras all look at the object centre).
    let n = loaded.views.len() as f32;
    let rms =
        (loaded.views.iter().map(|v| v.camera.origin().iter().map(|x| x * x).sum::<f32>()).sum::<f32>() / n).sqrt();
    assert!((rms - 1.0).abs() < 1e-5, "{rms}");
    for v in &loaded.views {
        let (o, f) = (v.camera.origin(), v.camera.forward());
        let t = -(0..3).map(|k| o[k] * f[k]).sum::<f32>();
        let closest: Vec<f32> = (0..3).map(|k| o[k] + t * f[k]).collect();
        assert!(closest.iter().all(|c| c.abs() < 1e-4), "view {}: {closest:?}", v.name);
    }
    assert_eq!(loaded.render_path.len(), 120);
    let (a, b) = (&loaded.render_path[0], &loaded.render_path[119]);
    assert!(a.cam_to_world.iter().flatten().zip(b.cam_to_world.iter().flatten()).all(|(x, y)| (x - y).abs() < 1e-5));
    assert!(loaded.near > 0.0);
    std::fs::remove_dir_all(dir).ok();
}

/// The first recentred camera of LLFF flower, from a numpy re-implementation of the reference
/// `load_llff_data` (factor 8, bd_factor 0.75, recentre; float32 as the reference) run on
/// `fixtures/llff_flower/poses_bounds.npy`.
const FLOWER_POSE_0: [[f64; 4]; 3] = [
    [0.99982196, -0.015126365, 0.011274024, -0.33761597],
    [0.01527655, 0.9997941, -0.013356328, 0.1370491],
    [-0.01106967, 0.013526176, 0.9998472, -0.078204945],
];
const FLOWER_POSE_33: [[f64; 4]; 3] = [
    [0.99793196, 0.004317099, 0.06413343, -0.28181458],
    [-0.005408767, 0.9998433, 0.016857957, -0.17196399],
    [-0.0640506, -0.017169978, 0.9977989, 0.1133771],
];

#[test]
fn llff_flower_poses_match_the_reference_loader() {
    let npy = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/llff_flower/poses_bounds.npy");
    let geo = sos_datasets::llff::read_llff_geometry(&LlffConfig::default(), &npy).unwrap();
    assert_eq!(geo.poses.len(), 34);
    for (got, want, i) in [(&geo.poses[0], &FLOWER_POSE_0, 0), (&geo.poses[33], &FLOWER_POSE_33, 33)] {
        for (g, w) in got.iter().flatten().zip(want.iter().flatten()) {
            assert!((g - w).abs() < 2e-6, "camera {i}: {got:?} vs reference {want:?}");
        }
    }
    assert!((0.9 * geo.bounds[0] - 1.2).abs() < 1e-6, "{:?}", geo.bounds);
    assert!((geo.bounds[1] - 13.140926).abs() < 1e-5, "{:?}", geo.bounds);
    assert_eq!(geo.hwf[..2], [3024.0, 4032.0]);
    assert!((geo.hwf[2] / 8.0 - 446.88232).abs() < 1e-4, "{:?}", geo.hwf);
    assert!(geo.sphere_path.is_none());
}

/// Each layout written by the `write_layouts` example opens with only `[scene] kind` and
/// `path` set, as a user's config names it.
#[test]
fn every_layout_opens_from_kind_and_path_alone() {
    let tmp = temp_dir("bare-configs");
    let s = scene(Rig::ObjectCentric);
    for f in Format::ALL {
        let dir = tmp.join(f.name());
        f.write(&s, &dir).unwrap();
        let text = format!("kind = \"{}\"\npath = \"{}\"\n", f.kind(), f.scene_dir(&dir).display());
        let table: toml::Table = toml::from_str(&text).unwrap();
        let cfg: Box<dyn sos_core::plugin::dataset::DatasetConfig> =
            table.try_into().unwrap_or_else(|e| panic!("{}: {e}", f.name()));
        let loaded = cfg.open(&tmp).unwrap_or_else(|e| panic!("{}: {e}", f.name()));
        assert_same_views_up_to_frame(&s, &loaded, f);
    }
    std::fs::remove_dir_all(tmp).ok();
}

/// Same views and split; poses compared only where the loader keeps the world frame.
fn assert_same_views_up_to_frame(original: &Scene, loaded: &Scene, f: Format) {
    match f {
        // Spherified / normalised frames: check the view count, split and extent.
        Format::Llff | Format::TanksTemples => {
            loaded.validate().unwrap();
            assert_eq!(loaded.views.len(), original.views.len(), "{f:?}");
            assert_eq!(loaded.test.len(), original.test.len(), "{f:?}");
            assert!(matches!(loaded.extent, SceneExtent::Unbounded { radius, .. } if radius == 1.0), "{f:?}");
        }
        // No bounds are set: every layout gets the unbounded extent around the
        // cameras' focus, whose foreground sphere holds the object.
        _ => {
            assert_same_views(original, loaded, f.name());
            // NSVF's bbox.txt is the room, which holds the cameras: unbounded as well.
            match (f, loaded.extent) {
                (_, SceneExtent::Unbounded { center, radius }) => {
                    let off = (0..3).map(|k| (center[k] - OBJECT_CENTRE[k]).powi(2)).sum::<f32>().sqrt();
                    assert!(off + OBJECT_RADIUS < radius, "{f:?}: centre {center:?} radius {radius}");
                }
                (_, other) => panic!("{f:?}: expected the unbounded extent, got {other:?}"),
            }
            // BlendedMVS's cams state depth ranges; the other layouts start at the cameras.
            let expect_near = matches!(f, Format::BlendedMvs);
            assert_eq!(loaded.near > 0.0, expect_near, "{f:?}: near {}", loaded.near);
        }
    }
}

/// NSVF: `1_` (validation) views are skipped when `2_` (test) views exist, and are the
/// held-out views otherwise.
#[test]
fn nsvf_split_prefixes() {
    let s = scene(Rig::ObjectCentric);
    let dir = temp_dir("nsvf-split");
    Format::Nsvf.write(&s, &dir).unwrap();
    let test_names: Vec<String> = s.test.iter().map(|&i| s.views[i].name.clone()).collect();
    let copy = |from: &str, to: &str| {
        std::fs::copy(dir.join(format!("rgb/{from}.png")), dir.join(format!("rgb/{to}.png"))).unwrap();
        std::fs::copy(dir.join(format!("pose/{from}.txt")), dir.join(format!("pose/{to}.txt"))).unwrap();
    };
    copy("0_view_003", "1_val_003");
    let loaded = Format::Nsvf.open_raw(&dir, None).unwrap();
    assert_eq!(loaded.views.len(), s.views.len());
    assert!(loaded.views.iter().all(|v| v.name != "val_003"));
    // Without test views, validation views are held out.
    for name in &test_names {
        for (sub, ext) in [("rgb", "png"), ("pose", "txt"), ("masks", "png")] {
            let from = dir.join(format!("{sub}/2_{name}.{ext}"));
            std::fs::rename(&from, dir.join(format!("{sub}/1_{name}.{ext}"))).unwrap();
        }
    }
    let loaded = Format::Nsvf.open_raw(&dir, None).unwrap();
    let mut held: Vec<&str> = loaded.test.iter().map(|&i| loaded.views[i].name.as_str()).collect();
    held.sort();
    let mut want: Vec<&str> = test_names.iter().map(|n| n.as_str()).chain(["val_003"]).collect();
    want.sort();
    assert_eq!(held, want);
    std::fs::remove_dir_all(dir).ok();
}

/// Off-centre principal points and non-square pixels survive every layout that can store them
/// (LLFF and Blender store one focal length and a centred principal point, and refuse).
#[test]
fn general_intrinsics_survive_where_the_layout_holds_them() {
    let mut s = scene(Rig::ObjectCentric);
    for v in &mut s.views {
        let c = &mut v.camera;
        c.fy = 1.1 * c.fx;
        c.cx = 0.4 * c.width as f32 + 0.25;
        c.cy = 0.55 * c.height as f32 - 0.125;
    }
    let dir = temp_dir("intr");
    for f in Format::ALL {
        let d = dir.join(f.name());
        if matches!(f, Format::Llff | Format::Blender) {
            let err = f.write(&s, &d).unwrap_err().to_string();
            assert!(err.contains("principal point"), "{f:?}: {err}");
            continue;
        }
        f.write(&s, &d).unwrap();
        let loaded = f.open_raw(&d, Some(ROOM)).unwrap_or_else(|e| panic!("{f:?}: {e}"));
        assert_same_views(&s, &loaded, f.name());
    }
    // Both CO3D intrinsics formats.
    let d = dir.join("co3d-bounds");
    sos_datasets::write_co3d(&s, &d, CO3D_CATEGORY, CO3D_SEQUENCE, false).unwrap();
    let root = d.join(CO3D_CATEGORY);
    let loaded = load_co3d(&Co3dConfig { path: root.clone(), ..Default::default() }, &root).unwrap();
    assert_same_views(&s, &loaded, "co3d ndc_norm_image_bounds");
    std::fs::remove_dir_all(dir).ok();
}

/// Hand-written cameras in each file convention, checked against where known world points
/// must appear (independent of the writers, which share the loaders' conventions).
#[test]
fn file_conventions_match_hand_written_cameras() {
    use sos_datasets::pose::{from_world_to_camera, rotation_from_quaternion, to_camera_general};
    use sos_datasets::{co3d, tanks_temples};
    // Every camera sits at world (0, 0, -5) looking along world +Z; image 100x80.
    let check = |what: &str, cam: sos_core::camera::Camera, right: [f32; 3], down: [f32; 3]| {
        let c = cam.project([0.0, 0.0, 0.0]).unwrap();
        assert!((c[0] - cam.cx).abs() < 1e-4 && (c[1] - cam.cy).abs() < 1e-4, "{what}: {c:?}");
        let r = cam.project(right).unwrap();
        assert!(r[0] > c[0] + 1.0 && (r[1] - c[1]).abs() < 1e-4, "{what}: {right:?} → {r:?}");
        let d = cam.project(down).unwrap();
        assert!(d[1] > c[1] + 1.0 && (d[0] - c[0]).abs() < 1e-4, "{what}: {down:?} → {d:?}");
    };
    // OpenCV world-to-camera (COLMAP, BlendedMVS): identity rotation, t = (0, 0, 5): camera x
    // is world +X (right), camera y world +Y (down).
    let p = from_world_to_camera(&rotation_from_quaternion([1.0, 0.0, 0.0, 0.0]), [0.0, 0.0, 5.0]).unwrap();
    check("opencv w2c", to_camera_general(&p, 100, 80, 50.0, 50.0, 50.0, 40.0), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
    // NeRF++ / NSVF camera-to-world, OpenCV axes.
    let p = tanks_temples::parse_c2w_opencv(Path::new("p.txt"), "1 0 0 0\n0 1 0 0\n0 0 1 -5\n0 0 0 1").unwrap();
    check("opencv c2w", to_camera_general(&p, 100, 80, 50.0, 50.0, 50.0, 40.0), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
    // PyTorch3D: X_cam = X_world·R + T with R = I, T = (0, 0, 5): +X left, +Y up, +Z forward,
    // so world +X appears on the left and world −Y below the centre.
    let json = r#"[{"sequence_name": "s", "frame_number": 0,
        "image": {"path": "s/images/f.jpg", "size": [80, 100]},
        "viewpoint": {"R": [[1,0,0],[0,1,0],[0,0,1]], "T": [0,0,5],
                      "focal_length": [1.25, 1.25], "principal_point": [0.1, -0.05],
                      "intrinsics_format": "ndc_isotropic"}}]"#;
    let frames: Vec<co3d::FrameAnnotation> = serde_json::from_str(json).unwrap();
    let vp = frames[0].viewpoint.as_ref().unwrap();
    let k = co3d::intrinsics_from_ndc(vp, frames[0].image.size).unwrap();
    // Isotropic: the shorter side (80 px) spans NDC [−1, 1], so s = 40 px; NDC +X is left.
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (50.0, 50.0, 50.0 - 4.0, 40.0 + 2.0));
    let p = co3d::pose_from_pytorch3d(&vp.r, vp.t).unwrap();
    check("pytorch3d", to_camera_general(&p, 100, 80, k.fx, k.fy, k.cx, k.cy), [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]);
    // A point on PyTorch3D's principal point lands on the pixel principal point: NDC
    // (px, py) = (0.1, −0.05) is left of and below the image centre.
    assert!(k.cx < 50.0 && k.cy > 40.0);
}
