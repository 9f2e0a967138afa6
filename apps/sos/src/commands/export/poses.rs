//! The `--poses` file of `sos export`: cameras of views that are not in the dataset, whose masks
//! and overlays the command renders.
//!
//! The file is one JSON object:
//!
//! ```json
//! {
//!   "width": 400,
//!   "height": 300,
//!   "focal": 346.4,
//!   "convention": "opengl",
//!   "poses": [
//!     [[1, 0, 0, 0], [0, 1, 0, 0.85], [0, 0, 1, 2.3], [0, 0, 0, 1]]
//!   ]
//! }
//! ```
//!
//! - `width`, `height`: image size in pixels, shared by every pose;
//! - `focal`: focal length in pixels (square pixels); `cx`, `cy` (optional): the principal
//!   point, the image centre when absent;
//! - `convention` (optional): the camera axes of the matrices, `"opengl"` (the default: +X
//!   right, +Y up, looking along −Z, as NeRF and Blender) or `"opencv"` (+Y down, looking
//!   along +Z, as COLMAP);
//! - `poses`: camera-to-world 4x4 matrices, row by row, in the world frame of the loaded
//!   scene (the frame `sos` trains in: for LLFF and other recentred layouts, the recentred
//!   one). The last row must be `[0, 0, 0, 1]` and the rotation orthonormal.
//!
//! Unknown keys are refused, so a misspelt key is an error rather than a silent default.

use std::path::Path;

use anyhow::{bail, Context};
use serde::Deserialize;
use sos_core::camera::{Camera, CameraConvention};

/// Axis convention of the matrices in a poses file.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Convention {
    /// +X right, +Y up, looking along −Z.
    #[default]
    OpenGl,
    /// +X right, +Y down, looking along +Z.
    OpenCv,
}

/// A poses file as written (see the module documentation).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PosesFile {
    width: u32,
    height: u32,
    focal: f32,
    #[serde(default)]
    cx: Option<f32>,
    #[serde(default)]
    cy: Option<f32>,
    #[serde(default)]
    convention: Convention,
    poses: Vec<[[f32; 4]; 4]>,
}

/// Largest image side accepted, in pixels.
const MAX_SIDE: u32 = 16_384;

/// Reads a poses file into cameras; every error names the file and, where it has one, the key.
pub fn load(path: &Path) -> anyhow::Result<Vec<Camera>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("poses file {}: cannot be read", path.display()))?;
    parse(&text).with_context(|| format!("poses file {}", path.display()))
}

/// Parses the text of a poses file into cameras.
pub fn parse(text: &str) -> anyhow::Result<Vec<Camera>> {
    let file: PosesFile = serde_json::from_str(text).context(
        "not a valid poses file (a JSON object with `width`, `height`, `focal` and `poses`, a list of \
         camera-to-world 4x4 matrices)",
    )?;
    for (key, side) in [("width", file.width), ("height", file.height)] {
        if side == 0 || side > MAX_SIDE {
            bail!("key `{key}` is {side}; it must lie in 1..={MAX_SIDE}");
        }
    }
    if !(file.focal.is_finite() && file.focal > 0.0) {
        bail!("key `focal` is {}; it must be a positive number of pixels", file.focal);
    }
    for (key, value) in [("cx", file.cx), ("cy", file.cy)] {
        if let Some(v) = value.filter(|v| !v.is_finite()) {
            bail!("key `{key}` is {v}; it must be a finite number of pixels");
        }
    }
    if file.poses.is_empty() {
        bail!("key `poses` is empty; list at least one camera-to-world matrix");
    }
    file.poses.iter().enumerate().map(|(i, m)| camera(&file, m).with_context(|| format!("key `poses[{i}]`"))).collect()
}

/// The camera of one matrix of `file`.
fn camera(file: &PosesFile, m: &[[f32; 4]; 4]) -> anyhow::Result<Camera> {
    if m.iter().flatten().any(|v| !v.is_finite()) {
        bail!("the matrix holds a number too large for 32-bit floats");
    }
    let last = m[3];
    if last.iter().zip([0.0, 0.0, 0.0, 1.0]).any(|(a, b)| (a - b).abs() > 1e-4) {
        bail!("the last row is {last:?}; a camera-to-world matrix ends in [0, 0, 0, 1]");
    }
    let rotation = [[m[0][0], m[0][1], m[0][2]], [m[1][0], m[1][1], m[1][2]], [m[2][0], m[2][1], m[2][2]]];
    let rotation = match file.convention {
        Convention::OpenGl => CameraConvention::OpenGl,
        Convention::OpenCv => CameraConvention::OpenCv,
    }
    .to_opengl(rotation);
    let mut cam_to_world = [[0.0; 4]; 3];
    for r in 0..3 {
        cam_to_world[r] = [rotation[r][0], rotation[r][1], rotation[r][2], m[r][3]];
    }
    let camera = Camera {
        width: file.width,
        height: file.height,
        fx: file.focal,
        fy: file.focal,
        cx: file.cx.unwrap_or(file.width as f32 / 2.0),
        cy: file.cy.unwrap_or(file.height as f32 / 2.0),
        cam_to_world,
    };
    camera.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(camera)
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDENTITY: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]";

    fn file(poses: &str) -> String {
        format!(r#"{{"width": 40, "height": 30, "focal": 35, "poses": [{poses}]}}"#)
    }

    #[test]
    fn reads_cameras_in_both_conventions() {
        let cams = parse(&file(IDENTITY)).unwrap();
        assert_eq!(cams.len(), 1);
        let cam = &cams[0];
        assert_eq!((cam.width, cam.height, cam.cx, cam.cy), (40, 30, 20.0, 15.0));
        assert_eq!(cam.origin(), [0.0, 0.0, 2.0]);
        assert_eq!(cam.forward(), [0.0, 0.0, -1.0]);
        // The same matrix read as OpenCV looks the other way, with +Y down.
        let opencv = file(IDENTITY).replace("\"poses\"", "\"convention\": \"opencv\", \"poses\"");
        let cam = &parse(&opencv).unwrap()[0];
        assert_eq!(cam.forward(), [0.0, 0.0, 1.0]);
        assert_eq!(cam.rotate([0.0, 1.0, 0.0]), [0.0, -1.0, 0.0]);
    }

    #[test]
    fn errors_name_the_key() {
        let cases = [
            (file("[[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,1,1]]"), "poses[0]"),
            (file(&format!("{IDENTITY}, [[2,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]]")), "poses[1]"),
            (file(""), "poses"),
            (file(IDENTITY).replace("\"focal\": 35", "\"focal\": -1"), "focal"),
            (file(IDENTITY).replace("\"width\": 40", "\"width\": 0"), "width"),
            (file(IDENTITY).replace("\"focal\"", "\"focus\""), "focus"),
            (file("[[1,0,0],[0,1,0],[0,0,1]]"), "line 1"),
            ("[1, 2]".to_owned(), "poses file"),
        ];
        for (text, key) in cases {
            let e = format!("{:#}", parse(&text).unwrap_err());
            assert!(e.contains(key), "{text}: {e}");
        }
    }
}
