//! Hostile input for every layout: missing or extra images, unreadable, corrupt or zero-size
//! images, masks of the wrong size, NaN or singular poses, malformed text, JSON, gzip and
//! binary models. Each gives a typed `DatasetError` naming the file (and the fix), never a
//! panic. The CLI prints these errors and exits with code 2.

use std::path::{Path, PathBuf};

use sos_core::plugin::dataset::{DatasetConfig, DatasetError};
use sos_core::scene::Scene;
use sos_datasets::co3d::{read_jgz, write_jgz, FrameAnnotation};
use sos_datasets::layouts::{Format, CO3D_CATEGORY, CO3D_SEQUENCE};
use sos_datasets::synthetic::{generate, Rig, SyntheticConfig};

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("sos-hostile-{}-{name}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn scene() -> Scene {
    generate(&SyntheticConfig { rig: Rig::ObjectCentric, width: 40, height: 30, views: 10, ..Default::default() })
}

/// A training view present in every layout.
const VIEW: &str = "view_003";

fn image_path(f: Format, dir: &Path, name: &str) -> PathBuf {
    match f {
        Format::Llff | Format::ColmapBin | Format::ColmapTxt => dir.join(format!("images/{name}.png")),
        Format::Blender => dir.join(format!("train/{name}.png")),
        Format::BlendedMvs => dir.join(format!("blended_images/{name}.png")),
        Format::Nsvf => dir.join(format!("rgb/0_{name}.png")),
        Format::Co3d => dir.join(format!("{CO3D_CATEGORY}/{CO3D_SEQUENCE}/images/{name}.png")),
        Format::TanksTemples => dir.join(format!("train/rgb/{name}.png")),
    }
}

fn mask_path(f: Format, dir: &Path, name: &str) -> PathBuf {
    match f {
        Format::Llff | Format::ColmapBin | Format::ColmapTxt | Format::BlendedMvs => {
            dir.join(format!("masks/{name}.png"))
        }
        Format::Blender => dir.join(format!("masks/train/{name}.png")),
        Format::Nsvf => dir.join(format!("masks/0_{name}.png")),
        Format::Co3d => dir.join(format!("{CO3D_CATEGORY}/{CO3D_SEQUENCE}/masks/{name}.png")),
        Format::TanksTemples => dir.join(format!("train/mask/{name}.png")),
    }
}

/// Writes `scene` in layout `f` to a fresh folder.
fn fresh(f: Format, s: &Scene, case: &str) -> PathBuf {
    let dir = temp_dir(&format!("{}-{case}", f.name()));
    f.write(s, &dir).unwrap();
    dir
}

/// Opens the layout; it must fail with an error whose message holds every needle.
fn expect_err(f: Format, dir: &Path, case: &str, needles: &[&str]) -> DatasetError {
    let err = match f.open_raw(dir, None) {
        Ok(_) => panic!("{f:?} {case}: loaded without error"),
        Err(e) => e,
    };
    let msg = err.to_string();
    for n in needles {
        assert!(msg.contains(n), "{f:?} {case}: error lacks {n:?}: {msg}");
    }
    err
}

/// A PNG whose header says 0 x 0 pixels (with valid CRCs).
fn zero_size_png() -> Vec<u8> {
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        png.extend((data.len() as u32).to_be_bytes());
        let mut crc = flate2::Crc::new();
        crc.update(kind);
        crc.update(data);
        png.extend(kind);
        png.extend(data);
        png.extend(crc.sum().to_be_bytes());
    };
    chunk(b"IHDR", &[0, 0, 0, 0, 0, 0, 0, 0, 8, 2, 0, 0, 0]);
    chunk(b"IEND", &[]);
    png
}

#[test]
fn broken_images_and_masks_name_the_file() {
    let s = scene();
    for f in Format::ALL {
        let img = image_path(f, Path::new(""), VIEW);
        let img_name = img.file_name().unwrap().to_str().unwrap();
        // Corrupt (unreadable) image.
        let dir = fresh(f, &s, "corrupt");
        std::fs::write(dir.join(&img), b"\x89PNG not really").unwrap();
        expect_err(f, &dir, "corrupt image", &[img_name, "decode"]);
        // Truncated image.
        let good = std::fs::read(image_path(f, &dir, "view_004")).unwrap();
        std::fs::write(dir.join(&img), &good[..good.len() / 2]).unwrap();
        expect_err(f, &dir, "truncated image", &[img_name]);
        // Zero-size image.
        std::fs::write(dir.join(&img), zero_size_png()).unwrap();
        expect_err(f, &dir, "zero-size image", &[img_name]);
        std::fs::remove_dir_all(&dir).ok();
        // Mask of the wrong size.
        let dir = fresh(f, &s, "mask");
        let mask = mask_path(f, &dir, VIEW);
        assert!(mask.is_file(), "{f:?}: {} not written", mask.display());
        image::GrayImage::new(3, 3).save(&mask).unwrap();
        let mask_name = mask.file_name().unwrap().to_str().unwrap();
        expect_err(f, &dir, "mask size", &[mask_name, "resize"]);
        std::fs::remove_dir_all(&dir).ok();
    }
}

#[test]
fn missing_and_extra_images() {
    let s = scene();
    for f in Format::ALL {
        let dir = fresh(f, &s, "missing");
        std::fs::remove_file(image_path(f, &dir, VIEW)).unwrap();
        let needles: &[&str] = match f {
            // LLFF pairs images and poses by order: the count no longer matches.
            Format::Llff => &["images", "9 images", "10 poses"],
            _ => &[VIEW],
        };
        expect_err(f, &dir, "missing image", needles);
        std::fs::remove_dir_all(&dir).ok();

        let dir = fresh(f, &s, "extra");
        let extra = match f {
            Format::Nsvf => "0_extra",
            _ => "extra",
        };
        s.views[1].image.save_png(&image_path(f, &dir, "extra")).unwrap();
        if f == Format::Nsvf {
            std::fs::rename(image_path(f, &dir, "extra"), dir.join(format!("rgb/{extra}.png"))).unwrap();
        }
        match f {
            // Layouts driven by their camera files skip images they do not list (COLMAP does not
            // register every image it is given).
            Format::Blender | Format::ColmapBin | Format::ColmapTxt | Format::Co3d => {
                let loaded = f.open_raw(&dir, None).unwrap();
                assert_eq!(loaded.views.len(), s.views.len(), "{f:?}");
            }
            Format::Llff => {
                expect_err(f, &dir, "extra image", &["11 images", "10 poses"]);
            }
            _ => {
                expect_err(f, &dir, "extra image", &[extra, "missing"]);
            }
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}

fn edit(path: &Path, f: impl FnOnce(String) -> String) {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    std::fs::write(path, f(text)).unwrap();
}

/// Replaces token `n` (whitespace-separated) of the first line of a text file that is not a
/// comment and holds at least four tokens (a matrix row or a COLMAP image line).
fn set_token(path: &Path, n: usize, value: &str) {
    edit(path, |t| {
        let mut done = false;
        t.lines()
            .map(|line| {
                if done || line.starts_with('#') || line.split_whitespace().count() < 4 {
                    return format!("{line}\n");
                }
                done = true;
                let mut toks: Vec<&str> = line.split_whitespace().collect();
                toks[n] = value;
                toks.join(" ") + "\n"
            })
            .collect()
    });
}

#[test]
fn nan_and_singular_poses() {
    let s = scene();
    // (layout, camera file, token index of the first rotation entry on its first line)
    let text_cases: [(Format, String, usize); 4] = [
        (Format::BlendedMvs, format!("cams/{VIEW}_cam.txt"), 0),
        (Format::Nsvf, format!("pose/0_{VIEW}.txt"), 0),
        (Format::TanksTemples, format!("train/pose/{VIEW}.txt"), 0),
        (Format::ColmapTxt, "sparse/0/images.txt".into(), 0),
    ];
    for (f, file, tok) in text_cases {
        let file_name = Path::new(&file).file_name().unwrap().to_str().unwrap().to_string();
        let dir = fresh(f, &s, "nan");
        // In COLMAP's images.txt token 0 is the image id, 1 to 4 the quaternion.
        let tok = if f == Format::ColmapTxt { 1 } else { tok };
        set_token(&dir.join(&file), tok, "nan");
        expect_err(f, &dir, "NaN pose", &[&file_name, "not finite"]);
        let dir2 = fresh(f, &s, "singular");
        match f {
            Format::ColmapTxt => (1..5).for_each(|k| set_token(&dir2.join(&file), k, "0")),
            _ => (0..3).for_each(|k| set_token(&dir2.join(&file), tok + k, "0")),
        }
        let needle = match f {
            Format::ColmapTxt => "zero quaternion",
            Format::BlendedMvs => "singular",
            _ => "orthonormal",
        };
        expect_err(f, &dir2, "singular pose", &[&file_name, needle]);
        std::fs::remove_dir_all(&dir).ok();
        std::fs::remove_dir_all(&dir2).ok();
    }
    // COLMAP binary: a NaN quaternion.
    let dir = fresh(Format::ColmapBin, &s, "nan");
    let p = dir.join("sparse/0/images.bin");
    let mut b = std::fs::read(&p).unwrap();
    b[12..20].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(&p, &b).unwrap();
    expect_err(Format::ColmapBin, &dir, "NaN pose", &["images.bin", "NaN"]);
    std::fs::remove_dir_all(&dir).ok();
    // CO3D: a singular R; a NaN written as Python's json does (not valid JSON).
    let dir = fresh(Format::Co3d, &s, "singular");
    let fa = dir.join(CO3D_CATEGORY).join("frame_annotations.jgz");
    let mut frames: Vec<FrameAnnotation> = read_jgz(&fa, "").unwrap();
    frames[3].viewpoint.as_mut().unwrap().r = [[0.0; 3]; 3];
    write_jgz(&fa, &frames).unwrap();
    expect_err(Format::Co3d, &dir, "singular R", &["frame_annotations.jgz", "frame 3", "singular"]);
    let text = serde_json::to_string(&frames).unwrap().replacen("\"T\":[", "\"T\":[NaN,", 1);
    let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    std::io::Write::write_all(&mut enc, text.as_bytes()).unwrap();
    std::fs::write(&fa, enc.finish().unwrap()).unwrap();
    expect_err(Format::Co3d, &dir, "NaN in JSON", &["frame_annotations.jgz", "malformed"]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn malformed_camera_files() {
    let s = scene();
    // (layout, file, replacement contents, needles)
    let cases: Vec<(Format, String, Vec<u8>, Vec<&str>)> = vec![
        (
            Format::ColmapTxt,
            "sparse/0/cameras.txt".into(),
            b"1 PINHOLE 40 30 35.0 35.0 20.0\n".to_vec(),
            vec!["cameras.txt", "4 parameters"],
        ),
        (
            Format::ColmapTxt,
            "sparse/0/cameras.txt".into(),
            b"1 PINHOLE 0 30 35.0 35.0 20.0 15.0\n".to_vec(),
            vec!["cameras.txt", "zero"],
        ),
        (Format::ColmapTxt, "sparse/0/cameras.txt".into(), b"1 WEIRD 40 30 1\n".to_vec(), vec!["cameras.txt", "WEIRD"]),
        (
            Format::ColmapTxt,
            "sparse/0/images.txt".into(),
            b"1 1 0 0 0 0 0 0 1\n\n".to_vec(),
            vec!["images.txt", "10 fields"],
        ),
        (
            Format::ColmapTxt,
            "sparse/0/images.txt".into(),
            b"# nothing registered\n".to_vec(),
            vec!["images.txt", "registers no image"],
        ),
        (
            Format::ColmapBin,
            "sparse/0/cameras.bin".into(),
            1000u64.to_le_bytes().to_vec(),
            vec!["cameras.bin", "does not fit"],
        ),
        (
            Format::BlendedMvs,
            format!("cams/{VIEW}_cam.txt"),
            b"extrinsic\n1 0 0 0\n0 1 0 0\n".to_vec(),
            vec!["view_003_cam.txt", "intrinsic"],
        ),
        (
            Format::BlendedMvs,
            format!("cams/{VIEW}_cam.txt"),
            b"intrinsic\n".to_vec(),
            vec!["view_003_cam.txt", "extrinsic"],
        ),
        (Format::Nsvf, "intrinsics.txt".into(), b"focal 35\n".to_vec(), vec!["intrinsics.txt", "\"focal\""]),
        (Format::Nsvf, "bbox.txt".into(), b"-1 -1 -1 1 1\n".to_vec(), vec!["bbox.txt", "xmin"]),
        (Format::Nsvf, "bbox.txt".into(), b"1 1 1 -1 -1 -1\n".to_vec(), vec!["bbox.txt", "below max"]),
        (
            Format::TanksTemples,
            format!("train/intrinsics/{VIEW}.txt"),
            b"35 0 20\n0 35 15\n0 0 1\n0 0 0\n".to_vec(),
            vec!["view_003.txt", "12 numbers"],
        ),
        (Format::TanksTemples, format!("train/pose/{VIEW}.txt"), b"".to_vec(), vec!["view_003.txt", "0 numbers"]),
        (
            Format::TanksTemples,
            format!("train/intrinsics/{VIEW}.txt"),
            b"1.1 0 0.5 0\n0 1.1 0.5 0\n0 0 1 0\n0 0 0 1\n".to_vec(),
            vec!["view_003.txt", "normalised"],
        ),
        (
            Format::Co3d,
            format!("{CO3D_CATEGORY}/frame_annotations.jgz"),
            b"\x1f\x8b\x08\x00 garbage".to_vec(),
            vec!["frame_annotations.jgz", "gzip"],
        ),
        (
            Format::Llff,
            "poses_bounds.npy".into(),
            b"\x93NUMPY\x01\x00\x10\x00{'descr': '<f8'}".to_vec(),
            vec!["poses_bounds.npy"],
        ),
        (
            Format::Blender,
            "transforms_train.json".into(),
            b"{\"frames\": [".to_vec(),
            vec!["transforms_train.json", "malformed"],
        ),
    ];
    for (f, file, contents, needles) in cases {
        let dir = fresh(f, &s, "malformed");
        std::fs::write(dir.join(&file), &contents).unwrap();
        expect_err(f, &dir, &format!("{file} = {:?}", String::from_utf8_lossy(&contents)), &needles);
        std::fs::remove_dir_all(&dir).ok();
    }
    // Truncating any binary or gzip file at any of a few points is an error naming it.
    for (f, file) in [
        (Format::ColmapBin, "sparse/0/cameras.bin"),
        (Format::ColmapBin, "sparse/0/images.bin"),
        (Format::Co3d, "synthetic/frame_annotations.jgz"),
        (Format::Co3d, "synthetic/sequence_annotations.jgz"),
        (Format::Llff, "poses_bounds.npy"),
    ] {
        let dir = fresh(f, &s, "truncated");
        let good = std::fs::read(dir.join(file)).unwrap();
        for cut in [0, 1, 7, good.len() / 3, good.len() - 1] {
            std::fs::write(dir.join(file), &good[..cut]).unwrap();
            let name = Path::new(file).file_name().unwrap().to_str().unwrap();
            expect_err(f, &dir, &format!("{file} cut at {cut}"), &[name]);
        }
        std::fs::remove_dir_all(&dir).ok();
    }
    // Missing annotation or model files are `Missing` errors naming them.
    let dir = fresh(Format::Co3d, &s, "missing-seq");
    std::fs::remove_file(dir.join("synthetic/sequence_annotations.jgz")).unwrap();
    let err = expect_err(Format::Co3d, &dir, "no sequence annotations", &["sequence_annotations.jgz", "missing"]);
    assert!(matches!(err, DatasetError::Missing { .. }));
    std::fs::remove_dir_all(&dir).ok();
    let dir = fresh(Format::ColmapBin, &s, "missing-images-bin");
    std::fs::remove_file(dir.join("sparse/0/images.bin")).unwrap();
    expect_err(Format::ColmapBin, &dir, "no images.bin", &["images.bin", "missing"]);
    std::fs::remove_dir_all(&dir).ok();
}

/// Pose files that parse but mean something else than they seem are refused, not loaded.
#[test]
fn transposed_mirrored_and_one_line_pose_files() {
    let s = scene();
    let edit_first_matrix = |dir: &Path, f: &dyn Fn(&mut Vec<Vec<f64>>)| {
        let path = dir.join("transforms_train.json");
        let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let m = &mut json["frames"][0]["transform_matrix"];
        let mut rows: Vec<Vec<f64>> = serde_json::from_value(m.clone()).unwrap();
        f(&mut rows);
        *m = serde_json::to_value(rows).unwrap();
        std::fs::write(&path, serde_json::to_string(&json).unwrap()).unwrap();
    };
    // Column-major: the translation lands in the last row.
    let dir = fresh(Format::Blender, &s, "transposed");
    edit_first_matrix(&dir, &|m| *m = (0..4).map(|c| (0..4).map(|r| m[r][c]).collect()).collect());
    expect_err(Format::Blender, &dir, "transposed matrix", &["transforms_train.json", "frame 0", "transposed"]);
    std::fs::remove_dir_all(&dir).ok();
    // One axis flipped: orthonormal, but every ray mirrored.
    let dir = fresh(Format::Blender, &s, "mirrored");
    edit_first_matrix(&dir, &|m| (0..3).for_each(|r| m[r][0] = -m[r][0]));
    expect_err(Format::Blender, &dir, "mirrored matrix", &["transforms_train.json", "frame 0", "reflection"]);
    std::fs::remove_dir_all(&dir).ok();
    // COLMAP's images.txt written with one line per image (no POINTS2D lines): every second
    // image would be read as the points of the one before.
    let dir = fresh(Format::ColmapTxt, &s, "one-line");
    edit(&dir.join("sparse/0/images.txt"), |t| {
        let image_line = |l: &str| l.starts_with('#') || l.split_whitespace().count() == 10;
        t.lines().filter(|l| image_line(l)).map(|l| format!("{l}\n")).collect()
    });
    expect_err(Format::ColmapTxt, &dir, "no POINTS2D lines", &["images.txt", "POINTS2D", "line 5"]);
    std::fs::remove_dir_all(&dir).ok();
}

/// The path the CLI takes: a `[scene]` table parsed into the registered kind, then opened.
#[test]
fn every_kind_opens_from_toml_and_reports_the_folder() {
    for kind in ["llff", "blender", "colmap", "blendedmvs", "co3d", "tanks-temples"] {
        let toml = format!("kind = \"{kind}\"\npath = \"no-such-scene\"");
        let cfg: Box<dyn DatasetConfig> = toml::from_str(&toml).unwrap_or_else(|e| panic!("{kind}: {e}"));
        let err = cfg.open(Path::new("/nonexistent-root")).unwrap_err();
        assert!(matches!(err, DatasetError::Missing { .. }), "{kind}: {err}");
        assert!(err.to_string().contains("no-such-scene"), "{kind}: {err}");
        assert!(sos_core::registry::find::<dyn DatasetConfig>(kind).is_some(), "{kind}");
        // Unknown keys are refused with the key's name.
        let typo = format!("kind = \"{kind}\"\npathh = \"x\"");
        let err = toml::from_str::<Box<dyn DatasetConfig>>(&typo).unwrap_err().to_string();
        assert!(err.contains("pathh"), "{kind}: {err}");
    }
}
