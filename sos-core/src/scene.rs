//! A loaded scene: posed views, optional ground-truth masks, the split and the scene's extent.

use serde::{Deserialize, Serialize};

use crate::camera::{dot, normalize, Camera, Vec3};
use crate::image::{GrayImage, RgbImage};

/// Largest angle (degrees) between a training camera's axis and the mean axis for which the
/// rig counts as forward-facing (all cameras look one way).
pub const PARALLEL_AXES_DEG: f32 = 15.0;

/// One posed photograph.
#[derive(Debug, Clone)]
pub struct View {
    /// File stem or generated name, used for output file names.
    pub name: String,
    /// Camera in the internal (OpenGL) convention, intrinsics matching `image`.
    pub camera: Camera,
    /// Colour in `[0, 1]`.
    pub image: RgbImage,
    /// Ground-truth foreground mask (1 = object, 0 = background), same size as `image`.
    pub mask: Option<GrayImage>,
    /// Ground-truth distance along each pixel-centre ray (unit direction, the scene's frame) to
    /// the first surface, `f32::INFINITY` where the ray meets none; same size as `image`. Only
    /// generated scenes know it.
    pub depth: Option<GrayImage>,
}

/// Where the scene's content lies, which decides how rays are sampled and how a field
/// parametrises space.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum SceneExtent {
    /// Everything lies inside an axis-aligned box (object-centric captures).
    Bounded {
        /// Box minimum corner.
        min: Vec3,
        /// Box maximum corner.
        max: Vec3,
    },
    /// A forward-facing capture in a recentred frame: the mean camera sits at the origin looking
    /// along −Z, content lies between depths `near` and `far` along −Z. Fields use normalised
    /// device coordinates of a virtual camera with this focal length and image size.
    ForwardFacing {
        /// Nearest content depth.
        near: f32,
        /// Farthest content depth (the NDC far plane is at infinity).
        far: f32,
        /// Focal length in pixels of the virtual NDC camera.
        focal: f32,
        /// Image width of the virtual NDC camera.
        width: f32,
        /// Image height of the virtual NDC camera.
        height: f32,
    },
    /// Unbounded content around a region: a sphere of `radius` at `center` holds the
    /// foreground, everything else is background (NeRF++ / mip-NeRF 360 scenes).
    Unbounded {
        /// Centre of the foreground sphere.
        center: Vec3,
        /// Radius of the foreground sphere.
        radius: f32,
    },
}

impl SceneExtent {
    /// A characteristic world length of the modelled region along one axis (the box's mean
    /// side, the forward-facing depth range, four foreground radii for unbounded scenes).
    /// Fields and the occupancy grid use it to express densities in world units.
    pub fn characteristic_length(&self) -> f32 {
        match *self {
            SceneExtent::Bounded { min, max } => ((max[0] - min[0]) + (max[1] - min[1]) + (max[2] - min[2])) / 3.0,
            SceneExtent::ForwardFacing { near, far, .. } => far - near,
            SceneExtent::Unbounded { radius, .. } => 4.0 * radius,
        }
    }
}

impl SceneExtent {
    /// Why no field could be fitted in this extent, if none could: non-finite numbers (e.g.
    /// depth bounds overflowing `f32`), an empty box, depths out of order, or a radius, focal
    /// length or image size that is not positive.
    pub fn problem(&self) -> Option<String> {
        let finite = |vs: &[f32]| vs.iter().all(|v| v.is_finite());
        match *self {
            SceneExtent::Bounded { min, max } => {
                let size = [max[0] - min[0], max[1] - min[1], max[2] - min[2]];
                if !finite(&min) || !finite(&max) || !finite(&size) {
                    Some(format!("its box {self} is not finite (or too wide for 32-bit floats)"))
                } else if (0..3).any(|a| max[a] <= min[a]) {
                    Some(format!("its box {self} is empty along an axis"))
                } else {
                    None
                }
            }
            SceneExtent::ForwardFacing { near, far, focal, width, height } => {
                if !finite(&[near, far, focal, width, height]) {
                    Some(format!("{self} is not finite (bounds too far apart for 32-bit floats?)"))
                } else if !(near > 0.0 && far > near) {
                    Some(format!("{self}: depths must satisfy 0 < near < far"))
                } else if !(focal > 0.0 && width > 0.0 && height > 0.0) {
                    Some(format!("{self}: focal length {focal} and size {width}x{height} must be positive"))
                } else {
                    None
                }
            }
            SceneExtent::Unbounded { center, radius } => {
                let usable_radius = radius.is_finite() && radius > 0.0;
                if !finite(&center) || !usable_radius {
                    Some(format!("{self}: needs a finite centre and a positive radius"))
                } else {
                    None
                }
            }
        }
    }
}

impl std::fmt::Display for SceneExtent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let v = |p: Vec3| format!("[{:.3}, {:.3}, {:.3}]", p[0], p[1], p[2]);
        match *self {
            SceneExtent::Bounded { min, max } => write!(f, "bounded box {} to {}", v(min), v(max)),
            SceneExtent::ForwardFacing { near, far, .. } => {
                write!(f, "forward-facing, content depths {near:.3} to {far:.3} (NDC)")
            }
            SceneExtent::Unbounded { center, radius } => {
                write!(f, "unbounded, foreground sphere at {} of radius {radius:.3}", v(center))
            }
        }
    }
}

/// A scene ready for training.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Human-readable name (used for output folders).
    pub name: String,
    /// All views, training and held-out.
    pub views: Vec<View>,
    /// Indices into `views` used for training.
    pub train: Vec<usize>,
    /// Indices into `views` held out for evaluation.
    pub test: Vec<usize>,
    /// Spatial extent.
    pub extent: SceneExtent,
    /// Distance from any camera below which there is no content: samples are never placed
    /// closer. Space right in front of the cameras is seen by no other training camera, so a
    /// field would otherwise fill it with fog that only novel views reveal.
    pub near: f32,
    /// A smooth novel camera path for `sos render` (may be empty).
    pub render_path: Vec<Camera>,
}

impl Scene {
    /// Checks the invariants every loader must establish; returns a description of the first
    /// violation.
    pub fn validate(&self) -> Result<(), String> {
        if self.views.is_empty() {
            return Err("scene has no views".into());
        }
        if self.train.is_empty() {
            return Err("scene has no training views".into());
        }
        if let Some(why) = self.extent.problem() {
            return Err(format!("the scene's extent: {why}; check its bounds (or set `aabb`)"));
        }
        if !(self.near.is_finite() && self.near >= 0.0) {
            return Err(format!("the scene's `near` distance {} must be a finite number of at least 0", self.near));
        }
        // In a box, no sample lies farther from a camera than the box's farthest corner: a
        // `near` beyond that for every training camera leaves every ray without a sample.
        if let SceneExtent::Bounded { min, max } = self.extent {
            let farthest = self
                .train
                .iter()
                .filter_map(|&i| self.views.get(i))
                .map(|v| {
                    let o = v.camera.origin();
                    let far = |a: usize| (o[a] - min[a]).abs().max((o[a] - max[a]).abs());
                    (far(0) * far(0) + far(1) * far(1) + far(2) * far(2)).sqrt()
                })
                .fold(0.0f32, f32::max);
            if self.near >= farthest {
                return Err(format!(
                    "the scene's `near` distance {} lies beyond every point of its box (the farthest is {farthest:.3} \
                     from a training camera), so no ray would get a sample; lower `near`",
                    self.near
                ));
            }
        }
        for &i in self.train.iter().chain(&self.test) {
            if i >= self.views.len() {
                return Err(format!("split index {i} out of range ({} views)", self.views.len()));
            }
        }
        // Masks, renders and metrics are written and reported by view name.
        let mut names = std::collections::HashSet::new();
        if let Some(v) = self.views.iter().find(|v| !names.insert(v.name.as_str())) {
            return Err(format!("two views are named {:?}; outputs are written by view name, so rename one", v.name));
        }
        for v in &self.views {
            v.camera.validate().map_err(|e| format!("view {}: {e}", v.name))?;
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            if (v.image.width, v.image.height) != (w, h) {
                return Err(format!(
                    "view {}: image is {}x{} but camera says {w}x{h}",
                    v.name, v.image.width, v.image.height
                ));
            }
            if let Some(m) = &v.mask {
                if (m.width, m.height) != (w, h) {
                    return Err(format!(
                        "view {}: mask is {}x{} but image is {w}x{h}; resize the mask",
                        v.name, m.width, m.height
                    ));
                }
            }
        }
        Ok(())
    }

    /// Why the novel camera path cannot be rendered (a camera with a non-finite pose or a
    /// degenerate lens, as a path derived from unusual poses may have); `None` when it can.
    /// Loading does not refuse such a path, since training never renders it.
    pub fn render_path_problem(&self) -> Option<String> {
        self.render_path.iter().enumerate().find_map(|(i, cam)| {
            cam.validate().err().map(|e| {
                format!(
                    "camera {i} of the scene's novel camera path: {e}; the path is derived from the views' poses, \
                     so render cameras of your own instead (`sos export --what masks --poses FILE`)"
                )
            })
        })
    }

    /// Whether every held-out view has a ground-truth mask.
    pub fn has_test_masks(&self) -> bool {
        !self.test.is_empty() && self.test.iter().all(|&i| self.views[i].mask.is_some())
    }

    /// The training cameras' mean centre and mean viewing direction (unit), when every
    /// training axis lies within [`PARALLEL_AXES_DEG`] of that direction: a forward-facing rig,
    /// whose axes do not meet. `None` for a rig whose cameras look in spread directions.
    pub fn shared_view_axis(&self) -> Option<(Vec3, Vec3)> {
        if self.train.is_empty() {
            return None;
        }
        let n = self.train.len() as f32;
        let mut origin = [0.0; 3];
        let mut axis = [0.0; 3];
        for &i in &self.train {
            let cam = &self.views[i].camera;
            let (o, f) = (cam.origin(), cam.forward());
            for k in 0..3 {
                origin[k] += o[k] / n;
                axis[k] += f[k];
            }
        }
        let direction = normalize(axis);
        let cos_max = PARALLEL_AXES_DEG.to_radians().cos();
        let parallel = direction.iter().all(|v| v.is_finite())
            && self.train.iter().all(|&i| dot(self.views[i].camera.forward(), direction) >= cos_max);
        parallel.then_some((origin, direction))
    }

    /// Point the cameras look at most: the least-squares intersection of the training cameras'
    /// viewing axes (falls back to the mean camera centre when the axes are parallel).
    pub fn focus_point(&self) -> Vec3 {
        // Minimise sum_i |(I - d_i d_i^T)(p - o_i)|^2.
        let mut a = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for &i in &self.train {
            let cam = &self.views[i].camera;
            let (o, d) = (cam.origin(), cam.forward());
            for r in 0..3 {
                for c in 0..3 {
                    let m = if r == c { 1.0 } else { 0.0 } - (d[r] * d[c]) as f64;
                    a[r][c] += m;
                    b[r] += m * o[c] as f64;
                }
            }
        }
        match solve3(a, b) {
            Some(p) => [p[0] as f32, p[1] as f32, p[2] as f32],
            None => {
                let n = self.train.len() as f32;
                let mut m = [0.0; 3];
                for &i in &self.train {
                    let o = self.views[i].camera.origin();
                    (0..3).for_each(|k| m[k] += o[k] / n);
                }
                m
            }
        }
    }
}

/// Solves a 3x3 linear system by Cramer's rule; `None` when it is (near) singular.
pub fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&a);
    let scale = a.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max).powi(3);
    if d.abs() <= 1e-9 * scale.max(1e-300) {
        return None;
    }
    let mut x = [0.0; 3];
    for k in 0..3 {
        let mut m = a;
        for r in 0..3 {
            m[r][k] = b[r];
        }
        x[k] = det(&m) / d;
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::scene::blank_scene;

    #[test]
    fn an_extent_no_field_fits_in_is_refused_by_validation() {
        assert_eq!(blank_scene(2, 4, 4).validate(), Ok(()));
        let ff = |near: f32, far: f32| SceneExtent::ForwardFacing { near, far, focal: 10.0, width: 4.0, height: 4.0 };
        for (extent, says) in [
            // LLFF bounds of 1e-30 and 1e10 scaled into f32: an infinite far plane.
            (ff(1.2, f32::INFINITY), "not finite"),
            (ff(2.0, 1.0), "0 < near < far"),
            (SceneExtent::Bounded { min: [f32::NEG_INFINITY, -1.0, -1.0], max: [1.0; 3] }, "not finite"),
            (SceneExtent::Bounded { min: [-1.0, 0.5, -1.0], max: [1.0, 0.5, 1.0] }, "empty along an axis"),
            // Finite corners whose distance overflows: every cell would be infinitely wide.
            (SceneExtent::Bounded { min: [-3e38; 3], max: [3e38; 3] }, "not finite"),
            (SceneExtent::Unbounded { center: [0.0; 3], radius: 0.0 }, "positive radius"),
            (SceneExtent::Unbounded { center: [f32::NAN, 0.0, 0.0], radius: 1.0 }, "positive radius"),
        ] {
            let mut scene = blank_scene(2, 4, 4);
            scene.extent = extent;
            let err = scene.validate().expect_err("a degenerate extent passes");
            assert!(err.contains(says) && err.contains("extent"), "{err}");
        }
        let mut scene = blank_scene(2, 4, 4);
        scene.near = f32::NAN;
        assert!(scene.validate().unwrap_err().contains("near"));
        // The cameras stand 3 and 4 from the centre of a 2-wide box: its farthest corner lies
        // sqrt(27) = 5.196 from the second.
        scene.near = 5.0;
        assert_eq!(scene.validate(), Ok(()));
        scene.near = 5.3;
        let err = scene.validate().unwrap_err();
        assert!(err.contains("`near`") && err.contains("5.196"), "{err}");
    }

    #[test]
    fn a_camera_path_with_a_broken_camera_is_named_without_refusing_the_scene() {
        let mut scene = blank_scene(2, 4, 4);
        scene.render_path = vec![scene.views[0].camera.clone(), scene.views[1].camera.clone()];
        assert_eq!(scene.render_path_problem(), None);
        scene.render_path[1].cam_to_world[0][3] = f32::NAN;
        let why = scene.render_path_problem().expect("a NaN pose passes");
        assert!(why.contains("camera 1") && why.contains("NaN") && why.contains("--poses"), "{why}");
        // Training never renders the path: the scene itself still loads.
        assert_eq!(scene.validate(), Ok(()));
    }

    #[test]
    fn only_cameras_looking_one_way_share_a_view_axis() {
        // Cameras on a line, all looking down -z: one axis, through their mean centre.
        let mut scene = blank_scene(3, 4, 4);
        for (i, view) in scene.views.iter_mut().enumerate() {
            let eye = [i as f32 - 1.0, 0.0, 3.0];
            view.camera = Camera::look_at(eye, [eye[0], 0.0, 0.0], [0.0, 1.0, 0.0], 4, 4, 100.0);
        }
        let (origin, direction) = scene.shared_view_axis().expect("parallel cameras");
        assert!(origin.iter().zip([0.0, 0.0, 3.0]).all(|(a, b)| (a - b).abs() < 1e-5), "{origin:?}");
        assert!((direction[2] + 1.0).abs() < 1e-5, "{direction:?}");
        // The same cameras turned to one point 2 in front of them: the outer two look 26.6°
        // off the mean axis, past the 15° a shared axis allows.
        for view in scene.views.iter_mut() {
            let eye = view.camera.origin();
            view.camera = Camera::look_at(eye, [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], 4, 4, 100.0);
        }
        assert_eq!(scene.shared_view_axis(), None);
        scene.train.clear();
        assert_eq!(scene.shared_view_axis(), None, "no training camera, no axis");
    }

    #[test]
    fn two_views_of_one_name_are_refused() {
        let mut scene = blank_scene(3, 4, 4);
        assert_eq!(scene.validate(), Ok(()));
        scene.views[2].name = scene.views[0].name.clone();
        let err = scene.validate().unwrap_err();
        assert!(err.contains(&format!("{:?}", scene.views[0].name)) && err.contains("rename"), "{err}");
    }
}
