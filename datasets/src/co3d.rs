//! Dataset kind `co3d`: one sequence of a CO3Dv2 category.
//!
//! Layout: the category folder (`path`) holds `frame_annotations.jgz` and
//! `sequence_annotations.jgz` (gzip-compressed JSON lists) and one folder per sequence with
//! `images/` and `masks/`. Annotation paths (`image.path`, `mask.path`) are relative to the
//! dataset root, the category folder's parent (paths relative to the category folder itself
//! are accepted too).
//!
//! Cameras follow PyTorch3D: `X_cam = X_world · R + T` with row vectors, camera axes +X left,
//! +Y up, +Z forward; they are converted once to the core's OpenGL convention. Intrinsics are
//! in NDC: `intrinsics_format = "ndc_isotropic"` (CO3Dv2; the shorter image side spans
//! [−1, 1]) or `"ndc_norm_image_bounds"` (each side spans [−1, 1]); with `s` the half-size of
//! the spanning side(s), `f_px = s · f_ndc` and `c_px = size / 2 − s · p_ndc` per axis. Image
//! sizes are `[height, width]`.
//!
//! Masks come from each frame's `mask.path`; CO3D masks are soft and are thresholded at 0.5
//! (foreground = value > 0.5). `sequence` picks the sequence; by default the one with the
//! highest `viewpoint_quality_score` (ties and missing scores: first by name). Frames are
//! ordered by `frame_number`; views `0, k, 2k, …` (`hold_out_every`) are held out.

use std::io::Read;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sos_core::camera::Vec3;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::{Scene, View};

use crate::adapter::{hold_out_views, orbit_scene, register_dataset, require_folder};
use crate::pose::{self, Pose, M3, V3};
use crate::text::{invalid, read_bytes};
use crate::views::{
    check_aabb, checked_camera, extent_of, load_image_sized, optional_mask, unbounded_unless_aabb, Intrinsics,
};

/// Configuration of the `co3d` dataset (`[scene] kind = "co3d"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Co3dConfig {
    /// Category folder (holding `frame_annotations.jgz`), relative to the config file's folder.
    pub path: PathBuf,
    /// Sequence name; default: the best-scored sequence.
    pub sequence: Option<String>,
    /// Views `0, k, 2k, …` of the sequence are held out (default 8); 0 holds out none.
    pub hold_out_every: usize,
    /// Scene box `[min, max]` in the CO3D world frame; default: unbounded around the point the
    /// cameras look at.
    pub aabb: Option<[Vec3; 2]>,
    /// Distance from the cameras below which nothing is sampled (default 0).
    pub near: f32,
}

impl Default for Co3dConfig {
    fn default() -> Self {
        Co3dConfig { path: PathBuf::new(), sequence: None, hold_out_every: 8, aabb: None, near: 0.0 }
    }
}

register_dataset!(
    Co3dConfig,
    "co3d",
    "one CO3Dv2 sequence (frame/sequence_annotations.jgz, PyTorch3D NDC cameras, soft masks)",
    load_co3d,
    derived_co3d
);

/// The extent this adapter chose where the config gives no `aabb`.
fn derived_co3d(cfg: &Co3dConfig, _root: &Path, scene: &Scene) -> Vec<sos_core::derived::DerivedSetting> {
    unbounded_unless_aabb(cfg.aabb, scene)
}

/// `image` of a frame annotation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageAnnotation {
    /// Path relative to the dataset root.
    pub path: String,
    /// `[height, width]`.
    pub size: [u64; 2],
}

/// `mask` of a frame annotation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MaskAnnotation {
    /// Path relative to the dataset root.
    pub path: String,
    /// Sum of the soft mask (unused).
    #[serde(default)]
    pub mass: Option<f64>,
}

/// `viewpoint` of a frame annotation (PyTorch3D camera).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewpointAnnotation {
    /// Rotation, `X_cam = X_world · R + T`.
    #[serde(rename = "R")]
    pub r: M3,
    /// Translation.
    #[serde(rename = "T")]
    pub t: V3,
    /// NDC focal lengths.
    pub focal_length: [f64; 2],
    /// NDC principal point.
    pub principal_point: [f64; 2],
    /// `ndc_isotropic` or `ndc_norm_image_bounds`.
    #[serde(default = "default_format")]
    pub intrinsics_format: String,
}

fn default_format() -> String {
    "ndc_norm_image_bounds".into()
}

/// One entry of `frame_annotations.jgz` (fields this loader does not use are ignored).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameAnnotation {
    /// Sequence the frame belongs to.
    pub sequence_name: String,
    /// Frame index in the video.
    pub frame_number: i64,
    /// Image file and size.
    pub image: ImageAnnotation,
    /// Mask file, if any.
    #[serde(default)]
    pub mask: Option<MaskAnnotation>,
    /// Camera, if any.
    #[serde(default)]
    pub viewpoint: Option<ViewpointAnnotation>,
}

/// One entry of `sequence_annotations.jgz`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequenceAnnotation {
    /// Sequence name.
    pub sequence_name: String,
    /// Category.
    pub category: String,
    /// Camera-coverage score of the sequence.
    #[serde(default)]
    pub viewpoint_quality_score: Option<f64>,
}

/// Largest accepted decompressed annotation file (a gzip bomb stops here): several times
/// the largest CO3D category's frame annotations.
const MAX_JSON: u64 = 1 << 30;

/// Reads a gzip-compressed JSON file into `T`.
pub fn read_jgz<T: serde::de::DeserializeOwned>(path: &Path, hint: &str) -> Result<T, DatasetError> {
    parse_jgz(path, &read_bytes(path, hint)?)
}

/// Parses gzip-compressed JSON bytes (read from `path`, which errors name) into `T`.
pub fn parse_jgz<T: serde::de::DeserializeOwned>(path: &Path, bytes: &[u8]) -> Result<T, DatasetError> {
    parse_jgz_within(path, bytes, MAX_JSON)
}

/// [`parse_jgz`] with at most `max_json` bytes of decompressed text.
fn parse_jgz_within<T: serde::de::DeserializeOwned>(
    path: &Path,
    bytes: &[u8],
    max_json: u64,
) -> Result<T, DatasetError> {
    // Parsed as it is decompressed: no buffer of the whole text.
    let mut json = std::io::BufReader::new(flate2::read::GzDecoder::new(bytes).take(max_json));
    let parsed = serde_json::from_reader(&mut json);
    if json.get_ref().limit() == 0 {
        return Err(invalid(
            path,
            format!("decompresses to more than {max_json} bytes of JSON; not an annotation file"),
        ));
    }
    parsed.map_err(|e| {
        let what = if e.is_io() { "not a valid gzip file" } else { "malformed annotation JSON" };
        invalid(path, format!("{what} ({e}); re-download the annotations (or re-compress them with gzip)"))
    })
}

/// Writes `value` as gzip-compressed JSON.
pub fn write_jgz<T: Serialize>(path: &Path, value: &T) -> Result<(), DatasetError> {
    use std::io::Write;
    let json = serde_json::to_vec(value).map_err(|e| invalid(path, format!("cannot serialise: {e}")))?;
    let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    enc.write_all(&json)
        .and_then(|_| enc.finish())
        .map_err(|e| invalid(path, format!("cannot compress: {e}")))
        .and_then(|gz| crate::text::write_file(path, &gz))
}

/// Pixel intrinsics of a PyTorch3D NDC viewpoint for an image of `[height, width]`.
pub fn intrinsics_from_ndc(vp: &ViewpointAnnotation, size: [u64; 2]) -> Result<Intrinsics, String> {
    let (h, w) = (size[0] as f64, size[1] as f64);
    let (sx, sy) = match vp.intrinsics_format.as_str() {
        "ndc_isotropic" => {
            let s = 0.5 * h.min(w);
            (s, s)
        }
        "ndc_norm_image_bounds" => (0.5 * w, 0.5 * h),
        f => return Err(format!("unknown intrinsics_format {f:?} (ndc_isotropic or ndc_norm_image_bounds)")),
    };
    let size32 = |v: u64| u32::try_from(v).ok().filter(|&s| s > 0);
    let (Some(width), Some(height)) = (size32(size[1]), size32(size[0])) else {
        return Err(format!("image size {size:?} is zero or too large"));
    };
    Ok(Intrinsics {
        width,
        height,
        fx: sx * vp.focal_length[0],
        fy: sy * vp.focal_length[1],
        cx: 0.5 * w - sx * vp.principal_point[0],
        cy: 0.5 * h - sy * vp.principal_point[1],
    })
}

/// The NDC focal length and principal point of pixel intrinsics (inverse of
/// [`intrinsics_from_ndc`]).
pub fn ndc_from_intrinsics(k: &Intrinsics, isotropic: bool) -> ([f64; 2], [f64; 2]) {
    let (w, h) = (k.width as f64, k.height as f64);
    let (sx, sy) = if isotropic { (0.5 * w.min(h), 0.5 * w.min(h)) } else { (0.5 * w, 0.5 * h) };
    ([k.fx / sx, k.fy / sy], [(0.5 * w - k.cx) / sx, (0.5 * h - k.cy) / sy])
}

/// Pose (OpenGL axes) of a PyTorch3D camera `X_cam = X_world · R + T`: the camera axes (left,
/// up, forward) are the columns of `R`, the centre is `−(Rᵀ)⁻¹ T`. `None` when `R` is singular.
pub fn pose_from_pytorch3d(r: &M3, t: V3) -> Option<Pose> {
    let rt_inv = pose::invert3(&pose::transpose3(r))?;
    let c = pose::mul3v(&rt_inv, t);
    let mut p = [[0.0; 4]; 3];
    for k in 0..3 {
        p[k] = [-r[k][0], r[k][1], -r[k][2], -c[k]];
    }
    Some(p)
}

/// PyTorch3D `(R, T)` of a pose (inverse of [`pose_from_pytorch3d`]).
pub fn pytorch3d_from_pose(p: &Pose) -> (M3, V3) {
    let mut r = [[0.0; 3]; 3];
    for k in 0..3 {
        r[k] = [-p[k][0], p[k][1], -p[k][2]];
    }
    let c = pose::column(p, 3);
    let rc = pose::mul3v(&pose::transpose3(&r), c);
    (r, [-rc[0], -rc[1], -rc[2]])
}

/// Resolves an annotation path: relative to the dataset root (the category folder's parent),
/// else to the category folder.
fn resolve(root: &Path, rel: &str) -> PathBuf {
    let from_parent = root.parent().map(|p| p.join(rel));
    match from_parent {
        Some(p) if p.is_file() => p,
        _ if root.join(rel).is_file() => root.join(rel),
        Some(p) => p,
        None => root.join(rel),
    }
}

/// The sequence to load: the configured one, or the best-scored one with frames.
fn choose_sequence(
    cfg: &Co3dConfig,
    frames: &[FrameAnnotation],
    seqs: &[SequenceAnnotation],
    frames_path: &Path,
) -> Result<String, DatasetError> {
    let mut names: Vec<&str> = frames.iter().map(|f| f.sequence_name.as_str()).collect();
    names.sort_unstable();
    names.dedup();
    if names.is_empty() {
        return Err(invalid(frames_path, "no frame annotations; re-download the category"));
    }
    if let Some(s) = &cfg.sequence {
        if names.binary_search(&s.as_str()).is_err() {
            let some: Vec<&str> = names.iter().take(10).copied().collect();
            return Err(invalid(
                frames_path,
                format!(
                    "no frame of sequence {s:?}; set `sequence` to one of the {} sequences, e.g. {some:?}",
                    names.len()
                ),
            ));
        }
        return Ok(s.clone());
    }
    // One pass over the annotations (the first of a name counts): a lookup per sequence
    // name would scan them all for each of possibly millions of names.
    let mut scores = std::collections::HashMap::with_capacity(seqs.len());
    for s in seqs {
        scores.entry(s.sequence_name.as_str()).or_insert(s.viewpoint_quality_score);
    }
    let score = |n: &str| scores.get(n).copied().flatten().filter(|v: &f64| v.is_finite()).unwrap_or(f64::NEG_INFINITY);
    let mut best = names[0];
    for &n in &names[1..] {
        if score(n) > score(best) {
            best = n;
        }
    }
    Ok(best.to_string())
}

/// Loads one CO3Dv2 sequence from category folder `root` (the config's `path` resolved).
pub fn load_co3d(cfg: &Co3dConfig, root: &Path) -> Result<Scene, DatasetError> {
    check_aabb(root, cfg.aabb)?;
    require_folder(root, "a CO3Dv2 category folder with frame_annotations.jgz")?;
    let frames_path = root.join("frame_annotations.jgz");
    let seqs_path = root.join("sequence_annotations.jgz");
    let hint = "a CO3Dv2 category folder holds frame_annotations.jgz and sequence_annotations.jgz";
    let frames: Vec<FrameAnnotation> = read_jgz(&frames_path, hint)?;
    let seqs: Vec<SequenceAnnotation> = read_jgz(&seqs_path, hint)?;
    let sequence = choose_sequence(cfg, &frames, &seqs, &frames_path)?;
    let mut frames: Vec<&FrameAnnotation> = frames.iter().filter(|f| f.sequence_name == sequence).collect();
    frames.sort_by_key(|f| f.frame_number);
    if let Some(w) = frames.windows(2).find(|w| w[0].frame_number == w[1].frame_number) {
        return Err(invalid(
            &frames_path,
            format!("sequence {sequence}: frame_number {} appears twice", w[0].frame_number),
        ));
    }
    let views: Vec<View> = frames
        .par_iter()
        .map(|f| {
            let what = format!("sequence {sequence} frame {}", f.frame_number);
            let vp = f.viewpoint.as_ref().ok_or_else(|| {
                invalid(&frames_path, format!("{what}: no viewpoint; pick another sequence with `sequence`"))
            })?;
            let finite = vp.r.iter().flatten().chain(&vp.t).chain(&vp.focal_length).chain(&vp.principal_point);
            if finite.clone().any(|v| !v.is_finite()) {
                return Err(invalid(&frames_path, format!("{what}: viewpoint has NaN or inf")));
            }
            let k = intrinsics_from_ndc(vp, f.image.size).map_err(|m| invalid(&frames_path, format!("{what}: {m}")))?;
            let pose = pose_from_pytorch3d(&vp.r, vp.t)
                .ok_or_else(|| invalid(&frames_path, format!("{what}: rotation R is singular")))?;
            let camera = checked_camera(&frames_path, &what, &pose, &k)?;
            let img_path = resolve(root, &f.image.path);
            if !img_path.is_file() {
                return Err(DatasetError::Missing {
                    path: img_path,
                    hint: format!("the image of {what} in {}", frames_path.display()),
                });
            }
            let image = load_image_sized(&img_path, k.width, k.height, &frames_path)?;
            let mask_path = match &f.mask {
                Some(m) => {
                    let p = resolve(root, &m.path);
                    if !p.is_file() {
                        return Err(DatasetError::Missing {
                            path: p,
                            hint: format!("the mask of {what} in {}", frames_path.display()),
                        });
                    }
                    Some(p)
                }
                None => None,
            };
            let mask = optional_mask(mask_path.as_deref(), image.width, image.height)?;
            let name = Path::new(&f.image.path)
                .file_stem()
                .and_then(|s| s.to_str())
                .map(str::to_string)
                .unwrap_or_else(|| format!("frame{:06}", f.frame_number));
            Ok(View { name, camera, image, mask, depth: None })
        })
        .collect::<Result<_, DatasetError>>()?;
    let (train, test) = hold_out_views(root, views.len(), cfg.hold_out_every)?;
    let extent = extent_of(&views, &train, cfg.aabb);
    Ok(orbit_scene(sequence, views, train, test, extent, cfg.near))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn gzip(text: &[u8]) -> Vec<u8> {
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        enc.write_all(text).unwrap();
        enc.finish().unwrap()
    }

    #[test]
    fn annotations_that_decompress_past_the_limit_are_refused_without_a_buffer_of_them() {
        let path = Path::new("frame_annotations.jgz");
        let seqs = br#"[{"sequence_name": "a", "category": "c"}]"#;
        let ok: Vec<SequenceAnnotation> = parse_jgz_within(path, &gzip(seqs), 1024).unwrap();
        assert_eq!(ok[0].sequence_name, "a");
        // Whitespace compresses a thousandfold: a bomb of it stops at the limit, named.
        let mut bomb = vec![b' '; 4096];
        bomb.extend_from_slice(seqs);
        let err = parse_jgz_within::<Vec<SequenceAnnotation>>(path, &gzip(&bomb), 1024).unwrap_err().to_string();
        assert!(err.contains("more than 1024 bytes") && err.contains("frame_annotations.jgz"), "{err}");
        // Not gzip at all, and gzip of something that is not JSON.
        let err = parse_jgz_within::<Vec<SequenceAnnotation>>(path, b"plain text", 1024).unwrap_err().to_string();
        assert!(err.contains("not a valid gzip file"), "{err}");
        let err = parse_jgz_within::<Vec<SequenceAnnotation>>(path, &gzip(b"[{]"), 1024).unwrap_err().to_string();
        assert!(err.contains("malformed annotation JSON"), "{err}");
    }
}
