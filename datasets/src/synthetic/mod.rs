//! Dataset kind `synthetic`: a procedural, analytically ray-traced room with one foreground
//! object, generated in memory (no downloads), with exact ground-truth masks; or, with
//! `world = "random"`, one of a seeded family of random worlds ([below](#random-worlds)).
//!
//! The room (7 x 3 x 7 m, textured floor, walls and ceiling) holds a checkered sphere on a
//! striped pedestal (the foreground; both parts are mask 1) and three distractors near the
//! walls (a blue box, a green striped cylinder, a purple cone). Textures are soft checkers,
//! stripes and smooth value noise; shading is Lambertian (directional light + ambient, hard
//! object shadows), so appearance is view-independent. Colour is 2x2 supersampled; the mask is
//! 1 where the pixel centre's primary ray hits the foreground object.
//!
//! Three rigs:
//! - `object-centric`: cameras on the upper hemisphere around the object, inside the room, all
//!   looking at the object centre; extent `Bounded` = the room box padded by 5 cm; render path
//!   a 25° circle around the object.
//! - `forward-facing`: parallel cameras on a jittered 0.7 x 0.4 m grid facing the object from
//!   the front of the room; everything is expressed in the frame of the LLFF average pose (the
//!   mean camera is the identity, looking along −Z); extent `ForwardFacing` with
//!   near = 0.9 x the nearest and far = 1.05 x the farthest content depth; render path the LLFF
//!   spiral;
//! - `unbounded`: no room. The same object stands on an open ground (40 m disk) ringed by
//!   distant towers (8–18 m) under a sky at infinity; cameras on a horizontal circle of radius
//!   2.3 m around the object, looking at it; extent `Unbounded` with the sphere centred on the
//!   object and 1.1 x the farthest camera distance as radius (so the cameras lie inside it, as
//!   NeRF++'s normalisation requires); render path a circle at 1.3 m.
//!
//! # Random worlds
//!
//! `world = "random"` replaces the built-in room by a world drawn entirely from `seed` (the
//! default `world = "built-in"` is the scene above, unchanged), so defaults can be measured on
//! many scenes nobody tuned for. Same seed, same bytes; another seed, another world:
//! - Foreground (mask 1 = every part): a stack or a side-by-side group of 1–4 primitives
//!   (spheres, boxes, cylinders, cones, tori) of random sizes, on a pedestal (a plinth under a
//!   group) or directly on the ground.
//! - Materials: checkers, stripes, value noise or flat colours, with grain. Hard cases on
//!   purpose: with probability 0.2 the object's colours are within 0.05 of the ground's, with
//!   probability 0.12 it wears the very texture of the floor (two times in three) or a wall.
//! - 0–5 distractors (random primitives and sizes) standing on the ground. Each is kept on the
//!   far side of a vertical plane from every camera and the object, so none is ever in the
//!   mask or between a camera and the object.
//! - Hard shadows from a directional light of random direction (35–70° high), on ground and
//!   objects.
//! - Surroundings: a room sized around the cameras (walls 0.5–2.2 m beyond them, random
//!   textures per face) for every rig but `unbounded`, which gets an open ground disk, 4–9
//!   distant towers and a sky (clear, overcast or dusk).
//! - Rigs (`rig`): `object-centric` (elevations within 5–65°), `forward-facing` (parallel
//!   cameras on a grid 12–30% x 6–16% of their distance, facing the object from 5–30° up),
//!   `unbounded` (a circle at elevations within 0–21° in the open world), `hemisphere` (the
//!   whole upper hemisphere, equal areas alike, from 3–12° up to 70–80°, as a camera straight
//!   above would have no up direction; radii vary with a ±25% share), `grazing` (1–15°), or
//!   `random` (one of the five, drawn from the seed). The horizontal field of view is drawn in
//!   45–75°, the elevation range, azimuth and aim jitter within the rig's ranges, and each
//!   camera stands where the object spans a drawn 22–50% of the view height (varied by up to
//!   ±10% per camera, ±25% for `hemisphere`), never more than 80% of the width. Render paths:
//!   a circle at the middle elevation (35° for `hemisphere`, closer for `unbounded`), the LLFF
//!   spiral for `forward-facing`.
//! - Extents as the built-in rigs state them: `Bounded` = the room box padded by 5 cm,
//!   `ForwardFacing` in the LLFF average-pose frame, `Unbounded` = a sphere about the object
//!   with 1.1 x the farthest camera distance as radius; `near` = 0.9 x the nearest content
//!   depth. Masks are exact as above.
//!
//! `world = "built-in"` supports the first three rigs only; the others are refused naming the
//! key.

mod geometry;
mod material;
mod open;
mod random;
mod render;
mod rig;
mod roots;
mod shape;
mod texture;
mod world;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sos_core::plugin::dataset::{DatasetConfig, DatasetError};
use sos_core::scene::{Scene, SceneExtent};

use crate::adapter::hold_out_split;
pub use world::{OBJECT_CENTRE, OBJECT_RADIUS, ROOM_MAX, ROOM_MIN};

/// Camera arrangement of the synthetic scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Rig {
    /// Cameras around the object, looking at it (extent `Bounded`).
    ObjectCentric,
    /// Parallel cameras on a small grid in front of the scene (extent `ForwardFacing`).
    ForwardFacing,
    /// Cameras on a circle around the object in an open world (extent `Unbounded`).
    Unbounded,
    /// Cameras over the whole upper hemisphere at varied radius (random worlds only).
    Hemisphere,
    /// A low orbit, elevations of a few degrees to 15° (random worlds only).
    Grazing,
    /// One of the five rigs, drawn from the seed (random worlds only).
    Random,
}

impl Rig {
    /// The rig's name in configurations.
    pub fn name(self) -> &'static str {
        match self {
            Rig::ObjectCentric => "object-centric",
            Rig::ForwardFacing => "forward-facing",
            Rig::Unbounded => "unbounded",
            Rig::Hemisphere => "hemisphere",
            Rig::Grazing => "grazing",
            Rig::Random => "random",
        }
    }
}

/// Which world the synthetic scene shows.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WorldKind {
    /// The hand-built room (or open world for `unbounded`) described above.
    #[default]
    BuiltIn,
    /// A world drawn entirely from the seed.
    Random,
}

impl WorldKind {
    /// Whether this is the default world (left out when configurations are written, so
    /// configurations of the built-in world read and hash as they always did).
    pub fn is_built_in(&self) -> bool {
        *self == WorldKind::BuiltIn
    }
}

/// Configuration of the `synthetic` dataset (`[scene] kind = "synthetic"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SyntheticConfig {
    /// World: `"built-in"` (default) or `"random"` (drawn from `seed`).
    #[serde(skip_serializing_if = "WorldKind::is_built_in")]
    pub world: WorldKind,
    /// Camera rig: `"object-centric"` (default), `"forward-facing"` or `"unbounded"`; random
    /// worlds also `"hemisphere"`, `"grazing"` and `"random"`.
    pub rig: Rig,
    /// Image width in pixels (default 400).
    pub width: u32,
    /// Image height in pixels (default 300).
    pub height: u32,
    /// Number of views (default 40).
    pub views: usize,
    /// Views `0, k, 2k, …` are held out for testing (default 8); 0 holds out none.
    pub hold_out_every: usize,
    /// Seed of the camera jitter and the noise textures (default 0); of the whole world for
    /// `world = "random"`.
    pub seed: u64,
    /// Number of cameras on the render path (default 60).
    pub render_path_views: usize,
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        SyntheticConfig {
            world: WorldKind::BuiltIn,
            rig: Rig::ObjectCentric,
            width: 400,
            height: 300,
            views: 40,
            hold_out_every: 8,
            seed: 0,
            render_path_views: 60,
        }
    }
}

/// Most pixels of all views together: 16 GiB of images, more than a real capture (LLFF's
/// full-size flower is 0.4 G pixels).
const MAX_SCENE_PIXELS: u64 = 1_000_000_000;

impl SyntheticConfig {
    /// Checks the values; the error names the key and the allowed range.
    pub fn check(&self) -> Result<(), String> {
        if !(8..=8192).contains(&self.width) || !(8..=8192).contains(&self.height) {
            return Err(format!("keys `width`/`height`: must be within 8..=8192, got {}x{}", self.width, self.height));
        }
        if !(2..=10_000).contains(&self.views) {
            return Err(format!("key `views`: must be within 2..=10000, got {}", self.views));
        }
        // The views are held in memory as f32 RGB with a mask: 16 bytes a pixel.
        let pixels = self.views as u64 * u64::from(self.width) * u64::from(self.height);
        if pixels > MAX_SCENE_PIXELS {
            return Err(format!(
                "keys `views`, `width`, `height`: {} views of {}x{} are {:.1} G pixels ({:.0} GiB held in memory); \
                 at most {} G pixels",
                self.views,
                self.width,
                self.height,
                pixels as f64 / 1e9,
                (pixels * 16) as f64 / (1u64 << 30) as f64,
                MAX_SCENE_PIXELS / 1_000_000_000
            ));
        }
        if self.render_path_views > 10_000 {
            return Err(format!("key `render_path_views`: must be at most 10000, got {}", self.render_path_views));
        }
        if self.hold_out_every == 1 {
            return Err("key `hold_out_every`: 1 would hold out every view; use 0 or ≥ 2".into());
        }
        if self.world == WorldKind::BuiltIn && matches!(self.rig, Rig::Hemisphere | Rig::Grazing | Rig::Random) {
            return Err(format!(
                "key `rig`: \"{}\" needs `world = \"random\"`; the built-in world has the \"object-centric\", \"forward-facing\" and \"unbounded\" rigs",
                self.rig.name()
            ));
        }
        Ok(())
    }
}

sos_core::plugin_kind! {
    kind: "synthetic",
    summary: "procedural ray-traced scene with one object and exact masks (object-centric, forward-facing or unbounded rig; seeded random worlds)",
    default: || Box::new(SyntheticConfig::default()),
    impl DatasetConfig for SyntheticConfig {
        fn open(&self, _config_dir: &Path) -> Result<Scene, DatasetError> {
            self.check().map_err(|message| DatasetError::Invalid {
                path: PathBuf::from(format!("[scene] kind = \"{}\"", Self::KIND)),
                message,
            })?;
            Ok(generate(self))
        }
    }
}

/// Generates the scene described by `cfg`.
///
/// # Panics
/// When `cfg` fails [`SyntheticConfig::check`] (`open` reports that as an error instead).
pub fn generate(cfg: &SyntheticConfig) -> Scene {
    if let Err(e) = cfg.check() {
        panic!("invalid synthetic config: {e}");
    }
    if cfg.world == WorldKind::Random {
        return random::generate(cfg);
    }
    let world = world::World::new(cfg.seed);
    let mut rng = rig::SplitMix::new(cfg.seed);
    let (w, h) = (cfg.width, cfg.height);
    let (train, test) = hold_out_split(cfg.views, cfg.hold_out_every);
    match cfg.rig {
        Rig::ObjectCentric => {
            let cams = rig::object_centric(cfg.views, w, h, &mut rng);
            let (views, near) = render::render_views(&world, cams);
            let pad = 0.05;
            let extent = SceneExtent::Bounded { min: ROOM_MIN.map(|v| v - pad), max: ROOM_MAX.map(|v| v + pad) };
            let render_path = rig::orbit_path(cfg.render_path_views, w, h);
            Scene {
                name: "synthetic-object-centric".into(),
                views,
                train,
                test,
                extent,
                // Z-depth bounds distance along any ray from below.
                near: 0.9 * near,
                render_path,
            }
        }
        Rig::Unbounded => {
            let world = open::OpenWorld::new(cfg.seed);
            let cams = rig::unbounded(cfg.views, w, h, &mut rng);
            let centre = OBJECT_CENTRE;
            let radius = 1.1 * render::farthest(&cams, centre);
            let (views, near) = render::render_views(&world, cams);
            Scene {
                name: "synthetic-unbounded".into(),
                views,
                train,
                test,
                extent: SceneExtent::Unbounded { center: centre, radius },
                near: 0.9 * near,
                render_path: rig::circle_path(cfg.render_path_views, w, h),
            }
        }
        Rig::ForwardFacing => {
            let cams = rig::forward_facing(cfg.views, w, h, &mut rng);
            let focal = rig::focal_for(w) as f64;
            render::forward_facing_scene(&world, &cams, focal, cfg, "synthetic-forward-facing".into(), train, test)
        }
        Rig::Hemisphere | Rig::Grazing | Rig::Random => unreachable!("refused by `check` for the built-in world"),
    }
}

/// A few lines for humans on what `cfg` shows (for random worlds: the drawn rig, object, hard
/// case, distractors and surroundings), without rendering it.
pub fn describe(cfg: &SyntheticConfig) -> String {
    match cfg.world {
        WorldKind::BuiltIn => format!("built-in world, {} rig", cfg.rig.name()),
        WorldKind::Random => {
            random::blueprint(cfg.seed, cfg.rig, cfg.views, cfg.width, cfg.height, cfg.render_path_views).describe()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::{self, Pose};
    use sos_core::scene::View;

    fn small(rig: Rig) -> SyntheticConfig {
        SyntheticConfig { rig, width: 160, height: 120, views: 16, ..Default::default() }
    }

    fn fg_fraction(v: &View) -> f32 {
        let m = v.mask.as_ref().unwrap();
        m.data.iter().sum::<f32>() / m.data.len() as f32
    }

    #[test]
    fn generation_is_deterministic_and_seed_dependent() {
        let a = generate(&small(Rig::ObjectCentric));
        let b = generate(&small(Rig::ObjectCentric));
        for (x, y) in a.views.iter().zip(&b.views) {
            assert_eq!(x.camera, y.camera);
            assert_eq!(x.image, y.image);
            assert_eq!(x.mask, y.mask);
        }
        let c = generate(&SyntheticConfig { seed: 7, ..small(Rig::ObjectCentric) });
        assert_ne!(a.views[1].image, c.views[1].image);
    }

    #[test]
    fn object_centric_scene_is_valid_with_centred_object() {
        let scene = generate(&small(Rig::ObjectCentric));
        scene.validate().unwrap();
        assert_eq!(scene.views.len(), 16);
        assert_eq!(scene.test, vec![0, 8]);
        assert_eq!(scene.train.len(), 14);
        assert_eq!(scene.render_path.len(), 60);
        let SceneExtent::Bounded { min, max } = scene.extent else { panic!("not bounded") };
        for v in &scene.views {
            v.camera.validate().unwrap();
            let o = v.camera.origin();
            assert!((0..3).all(|k| o[k] > min[k] && o[k] < max[k]), "camera outside room");
            // The object centre projects to the image centre, and is foreground there.
            let px = v.camera.project(OBJECT_CENTRE).unwrap();
            assert!((px[0] - 80.0).abs() < 0.01 && (px[1] - 60.0).abs() < 0.01, "{px:?}");
            let m = v.mask.as_ref().unwrap();
            assert_eq!(m.data[60 * 160 + 80], 1.0);
            assert!(v.image.data.iter().all(|c| (0.0..=1.0).contains(c)));
        }
        for &i in &scene.test {
            let f = fg_fraction(&scene.views[i]);
            assert!((0.05..=0.4).contains(&f), "view {i}: foreground fraction {f}");
        }
        for cam in &scene.render_path {
            cam.validate().unwrap();
        }
    }

    #[test]
    fn forward_facing_scene_is_recentred_and_bounded() {
        let scene = generate(&small(Rig::ForwardFacing));
        scene.validate().unwrap();
        let SceneExtent::ForwardFacing { near, far, focal, width, height } = scene.extent else {
            panic!("not forward-facing")
        };
        assert!(near > 0.5 && far > 2.0 * near && far < 20.0, "near {near} far {far}");
        assert_eq!((width, height), (160.0, 120.0));
        assert!((focal - scene.views[0].camera.fx).abs() < 1e-4);
        // The mean camera is the identity pose.
        let poses: Vec<Pose> = scene.views.iter().map(|v| pose::from_camera(&v.camera)).collect();
        let avg = pose::poses_avg(&poses);
        for (a, b) in avg.iter().flatten().zip(pose::IDENTITY.iter().flatten()) {
            assert!((a - b).abs() < 1e-5, "{avg:?}");
        }
        for &i in &scene.test {
            let f = fg_fraction(&scene.views[i]);
            assert!((0.05..=0.4).contains(&f), "view {i}: foreground fraction {f}");
        }
        // The object lies between near and far in front of every camera.
        for v in &scene.views {
            let m = v.mask.as_ref().unwrap();
            assert!(m.data.iter().any(|&x| x > 0.5));
        }
        assert_eq!(scene.render_path.len(), 60);
        for cam in &scene.render_path {
            cam.validate().unwrap();
        }
    }

    #[test]
    fn unbounded_scene_has_cameras_inside_the_sphere_and_distant_content() {
        let scene = generate(&small(Rig::Unbounded));
        scene.validate().unwrap();
        let SceneExtent::Unbounded { center, radius } = scene.extent else { panic!("not unbounded") };
        assert!((2.3..3.0).contains(&radius), "radius {radius}");
        let mut far_pixels = 0usize;
        for v in &scene.views {
            let o = v.camera.origin();
            let d: f32 = (0..3).map(|k| (o[k] - center[k]).powi(2)).sum::<f32>().sqrt();
            assert!(d < radius, "camera outside the foreground sphere");
            let px = v.camera.project(OBJECT_CENTRE).unwrap();
            assert!((px[0] - 80.0).abs() < 0.01 && (px[1] - 60.0).abs() < 0.01);
            assert_eq!(v.mask.as_ref().unwrap().data[60 * 160 + 80], 1.0);
            // Pixels beyond the sphere: the upper image half sees towers and sky.
            for row in 0..20u32 {
                for col in (0..160u32).step_by(8) {
                    let dir = v.camera.direction(col as f32 + 0.5, row as f32 + 0.5);
                    let s = open::OpenWorld::new(0).trace_at(o, dir);
                    if (0..3).map(|k| (s.point[k] - center[k]).powi(2)).sum::<f32>().sqrt() > 3.0 * radius {
                        far_pixels += 1;
                    }
                }
            }
        }
        assert!(far_pixels > 100, "only {far_pixels} probed pixels see distant content");
        for &i in &scene.test {
            let f = fg_fraction(&scene.views[i]);
            assert!((0.03..=0.4).contains(&f), "view {i}: foreground fraction {f}");
        }
    }

    #[test]
    fn config_parses_from_toml_and_rejects_typos() {
        let cfg: SyntheticConfig = toml::from_str("rig = \"forward-facing\"\nviews = 12").unwrap();
        assert_eq!(cfg.rig, Rig::ForwardFacing);
        assert_eq!(cfg.views, 12);
        assert_eq!(cfg.width, 400);
        assert!(toml::from_str::<SyntheticConfig>("veiws = 12").is_err());
        let boxed: Box<dyn DatasetConfig> = toml::from_str("kind = \"synthetic\"\nviews = 1").unwrap();
        let err = boxed.open(Path::new(".")).unwrap_err().to_string();
        assert!(err.contains("views"), "{err}");
        assert!(sos_core::registry::find::<dyn DatasetConfig>("synthetic").is_some());
        // Each size within its range, all of them together more than any machine holds.
        let huge: Box<dyn DatasetConfig> =
            toml::from_str("kind = \"synthetic\"\nviews = 10000\nwidth = 8192\nheight = 8192").unwrap();
        let err = huge.open(Path::new(".")).unwrap_err().to_string();
        assert!(err.contains("671.1 G pixels") && err.contains("`views`"), "{err}");
    }

    #[test]
    fn full_size_generation_splits_views_and_frames_the_object() {
        let scene = generate(&SyntheticConfig::default());
        assert_eq!(scene.views.len(), 40);
        assert_eq!((scene.train.len(), scene.test.len()), (35, 5));
        for &i in &scene.test {
            let f = fg_fraction(&scene.views[i]);
            assert!((0.05..=0.4).contains(&f), "view {i}: foreground fraction {f}");
        }
    }
}
