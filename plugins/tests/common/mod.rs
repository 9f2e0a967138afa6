//! A tiny two-stage run on the built-in synthetic scene (40x30 views, a few steps of each
//! stage), shared by the integration tests.

use std::path::Path;

use sos_core::config::{LogitSource, RunConfig};
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;

/// A session of `field` on the `rig` camera rig with the extra `[field]` lines `field_keys`,
/// training stage 1 for `steps` steps; its run folder, unique to `tag`, lies in Cargo's scratch
/// folder for integration tests (`target/tmp`) and is emptied first, so reruns reuse it.
///
/// A voxel grid whose keys name no resolution gets [`TINY_GRID`]: the default 160³ grid is far
/// finer than 40×30 views resolve, and each of its checkpoints would take 213 MB of disk.
pub fn tiny_session(field: &str, rig: &str, field_keys: &str, steps: usize, tag: &str) -> Session {
    let field_keys = if field == "voxel-grid" && !field_keys.contains("resolution") {
        format!("{TINY_GRID}\n{field_keys}")
    } else {
        field_keys.to_string()
    };
    let text = format!(
        r#"
name = "tiny"
output_dir = "runs"
[scene]
kind = "synthetic"
rig = "{rig}"
width = 40
height = 30
views = 6
[field]
kind = "{field}"
{field_keys}
[train]
steps = {steps}
rays_per_step = 512
samples_per_ray = 48
occupancy = false
checkpoint_every = 0
[segment]
steps = 3
patches = 2
patch_size = 8
stride = 2
"#
    );
    let config = RunConfig::parse(&text, Path::new("tiny.toml")).unwrap();
    let dir = scratch_dir(&format!("tiny-{field}-{tag}"));
    Session::from_config(config, &dir).unwrap()
}

/// The grid of a tiny voxel-grid session: about one vertex per pixel across the 40×30 views,
/// grown coarse-to-fine on the default schedule.
pub const TINY_GRID: &str = "resolution = [48, 48, 48]\ninitial_resolution = [16, 16, 16]";

/// An empty folder `name` in Cargo's scratch folder for integration tests (`target/tmp`).
pub fn scratch_dir(name: &str) -> std::path::PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(name);
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A tiny voxel-grid session on the object-centric rig, trained through stage 1 (40 steps) and
/// stage 2 with `logits`; its run folder is unique to `tag`.
#[allow(dead_code)] // Not every test file trains both stages.
pub fn two_stage_session(tag: &str, logits: LogitSource) -> (Session, Segmenter) {
    let mut s = tiny_session("voxel-grid", "object-centric", "", 40, tag);
    s.config.segment.logits = logits;
    train_photometric(&mut s).unwrap();
    let mut seg = Segmenter::build(&s).unwrap();
    train_segmentation(&mut s, &mut seg).unwrap();
    (s, seg)
}
