//! Every on-disk layout of one scene: write a scene in a layout, and open it again with the
//! matching loader's default configuration. The generator's round trips, the cross-format ray
//! test, the fuzz tests and the `write_layouts` example use it.

use std::path::{Path, PathBuf};

use sos_core::camera::Vec3;
use sos_core::plugin::dataset::DatasetError;
use sos_core::scene::Scene;

use crate::blendedmvs::{load_blendedmvs, BlendedMvsConfig, Layout};
use crate::co3d::{load_co3d, Co3dConfig};
use crate::colmap::{load_colmap, ColmapConfig};
use crate::export;
use crate::tanks_temples::{load_tanks_temples, Normalize, TanksTemplesConfig};
use crate::{load_blender, load_llff, BlenderConfig, LlffConfig};

/// Category and sequence names the CO3D writer uses here.
pub const CO3D_CATEGORY: &str = "synthetic";
/// Sequence name of the written CO3D layout.
pub const CO3D_SEQUENCE: &str = "seq_000";

/// A dataset layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// LLFF `poses_bounds.npy` + `images/` (factor 1).
    Llff,
    /// Blender `transforms_{train,val,test}.json`.
    Blender,
    /// COLMAP binary model.
    ColmapBin,
    /// COLMAP text model.
    ColmapTxt,
    /// BlendedMVS original release.
    BlendedMvs,
    /// BlendedMVS in NSVF's layout.
    Nsvf,
    /// CO3Dv2 category folder.
    Co3d,
    /// Tanks and Temples in NeRF++'s layout.
    TanksTemples,
}

impl Format {
    /// Every layout.
    pub const ALL: [Format; 8] = [
        Format::Llff,
        Format::Blender,
        Format::ColmapBin,
        Format::ColmapTxt,
        Format::BlendedMvs,
        Format::Nsvf,
        Format::Co3d,
        Format::TanksTemples,
    ];

    /// Folder-friendly name.
    pub fn name(self) -> &'static str {
        match self {
            Format::Llff => "llff",
            Format::Blender => "blender",
            Format::ColmapBin => "colmap",
            Format::ColmapTxt => "colmap_txt",
            Format::BlendedMvs => "blendedmvs",
            Format::Nsvf => "blendedmvs_nsvf",
            Format::Co3d => "co3d",
            Format::TanksTemples => "tanks_temples",
        }
    }

    /// The dataset kind (`[scene] kind`) whose adapter reads the layout.
    pub fn kind(self) -> &'static str {
        match self {
            Format::Llff => "llff",
            Format::Blender => "blender",
            Format::ColmapBin | Format::ColmapTxt => "colmap",
            Format::BlendedMvs | Format::Nsvf => "blendedmvs",
            Format::Co3d => "co3d",
            Format::TanksTemples => "tanks-temples",
        }
    }

    /// Whether the layout stores the train/test split itself (the others hold out every 8th
    /// view, which matches the generator's default split).
    pub fn stores_split(self) -> bool {
        matches!(self, Format::Blender | Format::Nsvf | Format::TanksTemples)
    }

    /// Writes `scene` to `dir` in this layout.
    pub fn write(self, scene: &Scene, dir: &Path) -> Result<(), DatasetError> {
        match self {
            Format::Llff => export::write_llff(scene, dir, 1),
            Format::Blender => export::write_blender(scene, dir),
            Format::ColmapBin => export::write_colmap(scene, dir, true),
            Format::ColmapTxt => export::write_colmap(scene, dir, false),
            Format::BlendedMvs => export::write_blendedmvs(scene, dir),
            Format::Nsvf => export::write_nsvf(scene, dir),
            Format::Co3d => export::write_co3d(scene, dir, CO3D_CATEGORY, CO3D_SEQUENCE, true),
            Format::TanksTemples => export::write_tanks_temples(scene, dir),
        }
    }

    /// The folder a config's `path` must name for a layout written to `dir`.
    pub fn scene_dir(self, dir: &Path) -> PathBuf {
        match self {
            Format::Co3d => dir.join(CO3D_CATEGORY),
            _ => dir.to_path_buf(),
        }
    }

    /// Opens a layout written to `dir` with the loader's defaults, except that poses are kept
    /// in the written frame (no LLFF or forward-facing COLMAP and BlendedMVS recentring and scaling, no
    /// spherify, no NeRF++ normalisation) and, when
    /// given, `aabb` bounds the scene where the loader takes one.
    pub fn open_raw(self, dir: &Path, aabb: Option<[Vec3; 2]>) -> Result<Scene, DatasetError> {
        let root = self.scene_dir(dir);
        let path = root.clone();
        match self {
            Format::Llff => load_llff(
                &LlffConfig {
                    path,
                    factor: Some(1),
                    recenter: false,
                    bd_factor: 0.0,
                    spherify: Some(false),
                    ..Default::default()
                },
                &root,
            ),
            Format::Blender => {
                let cfg = BlenderConfig { path, aabb, near: Some(0.0), ..Default::default() };
                load_blender(&cfg, &root)
            }
            Format::ColmapBin | Format::ColmapTxt => {
                load_colmap(&ColmapConfig { path, aabb, bd_factor: 0.0, recenter: false, ..Default::default() }, &root)
            }
            Format::BlendedMvs => {
                let keep_frame = BlendedMvsConfig { bd_factor: 0.0, recenter: false, ..Default::default() };
                load_blendedmvs(&BlendedMvsConfig { path, layout: Layout::Original, aabb, ..keep_frame }, &root)
            }
            Format::Nsvf => {
                load_blendedmvs(&BlendedMvsConfig { path, layout: Layout::Nsvf, aabb, ..Default::default() }, &root)
            }
            Format::Co3d => load_co3d(&Co3dConfig { path, aabb, ..Default::default() }, &root),
            Format::TanksTemples => load_tanks_temples(
                &TanksTemplesConfig { path, normalize: Normalize::Never, ..Default::default() },
                &root,
            ),
        }
    }
}
