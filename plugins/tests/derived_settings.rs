//! A config that names only its scene runs: the field defaults to `voxel-grid`, and the
//! settings that depend on the scene (patch stride, teacher cells, the adapter's extent) are
//! derived from it, recorded in the session and written into its config; a set key is kept.

use std::path::Path;

use sos_core::config::RunConfig;
use sos_core::train::Session;
// Links every plugin (datasets, extractors, losses) so the config kinds resolve.
use sos_plugins as _;

fn session(text: &str) -> Session {
    let config = RunConfig::parse(text, Path::new("derived.toml")).unwrap();
    Session::from_config(config, &std::env::temp_dir()).unwrap()
}

fn derived<'a>(s: &'a Session, key: &str) -> Option<&'a str> {
    s.derived.iter().find(|d| d.key == key).map(|d| d.value.as_str())
}

#[test]
fn a_scene_alone_is_a_complete_config() {
    let s = session("[scene]\nkind = \"synthetic\"\nwidth = 200\nheight = 150\nviews = 4\n");
    assert_eq!(s.field_kind, "voxel-grid");
    // The default stride 6 would span 379 px; 2 is the widest whose 64-ray patch fits 150 px.
    assert_eq!(derived(&s, "segment.stride"), Some("2"));
    assert_eq!(s.config.segment.stride, 2);
    assert_eq!(derived(&s, "extractor.cell"), Some("8"));
    let resolved = s.config.to_toml();
    assert!(resolved.contains("kind = \"cell-stats\"") && resolved.contains("cell = 8"), "{resolved}");
    // The resolved config reads back and derives nothing more.
    let again = session(&resolved);
    assert!(again.derived.is_empty(), "{:?}", again.derived);
}

#[test]
fn teacher_cells_follow_the_patch_and_set_keys_are_kept() {
    let base = "[scene]\nkind = \"synthetic\"\nwidth = 100\nheight = 75\nviews = 4\n";
    let s = session(&format!("{base}[segment]\npatch_size = 32\nstride = 2\n"));
    assert_eq!(derived(&s, "extractor.cell"), Some("4"));
    assert_eq!(derived(&s, "segment.stride"), None, "a fitting stride is kept");
    let s = session(&format!(
        "{base}[segment]\npatch_size = 32\nstride = 2\n[extractor]\nkind = \"cell-stats\"\ncell = 6\n"
    ));
    assert_eq!(derived(&s, "extractor.cell"), None);
    assert!(s.config.to_toml().contains("cell = 6"));
}

#[test]
fn the_teacher_measures_saliency_against_the_view_only_where_the_views_look_one_way() {
    let base = "[scene]\nkind = \"synthetic\"\nwidth = 100\nheight = 75\nviews = 4\n";
    let orbit = session(base);
    assert_eq!(derived(&orbit, "extractor.saliency_background"), Some("\"patch\""));
    let forward = session(&format!("{base}rig = \"forward-facing\"\n"));
    assert_eq!(derived(&forward, "extractor.saliency_background"), Some("\"view\""));
    assert!(forward.config.to_toml().contains("saliency_background = \"view\""));
    let set = session(&format!(
        "{base}rig = \"forward-facing\"\n[extractor]\nkind = \"cell-stats\"\nsaliency_background = \"patch\"\n"
    ));
    assert_eq!(derived(&set, "extractor.saliency_background"), None, "a set key is kept");
    assert!(set.config.to_toml().contains("saliency_background = \"patch\""));
}

#[test]
fn without_stage_two_nothing_of_it_is_derived() {
    let s = session("[scene]\nkind = \"synthetic\"\nwidth = 100\nheight = 75\nviews = 4\n[segment]\nsteps = 0\n");
    // The memory budget and the frozen renders' samples serve stage-1 evaluation too; nothing
    // of stage 2 or its teacher is derived.
    let keys: Vec<&str> = s.derived.iter().map(|d| d.key.as_str()).collect();
    assert_eq!(keys, ["render.memory_gib", "render.samples_per_ray"], "{:?}", s.derived);
}

#[test]
fn frozen_renders_take_one_sample_per_grid_cell_at_most_the_training_count() {
    let base = "[scene]\nkind = \"synthetic\"\nwidth = 100\nheight = 75\nviews = 4\n";
    let grid = "[field]\nkind = \"voxel-grid\"\nresolution = [64, 96, 80]\n";
    let s = session(&format!("{base}{grid}"));
    assert_eq!(derived(&s, "render.samples_per_ray"), Some("95"), "the finest axis has 95 cells");
    assert_eq!(s.config.render.samples_per_ray, Some(95));
    let s = session(&format!("{base}{grid}[train]\nsamples_per_ray = 40\n"));
    assert_eq!(derived(&s, "render.samples_per_ray"), Some("40"), "never more than training draws");
    let s = session(&format!("{base}{grid}[render]\nsamples_per_ray = 300\n"));
    assert_eq!(derived(&s, "render.samples_per_ray"), None, "a set count is kept");
    assert_eq!(s.config.render.samples_per_ray, Some(300));
    let s = session(&format!("{base}[field]\nkind = \"nerf\"\n"));
    assert_eq!(derived(&s, "render.samples_per_ray"), None, "a network has no cells to count");
    for bad in ["0", "1", "5000"] {
        let text = format!("[scene]\nkind = \"synthetic\"\n[render]\nsamples_per_ray = {bad}\n");
        let err = sos_core::config::RunConfig::parse(&text, std::path::Path::new("bad.toml")).expect_err(bad);
        assert!(err.to_string().contains("render.samples_per_ray"), "{bad}: {err}");
    }
}

#[test]
fn a_checkpoint_refuses_a_scene_with_another_extent() {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("derived-resume");
    std::fs::remove_dir_all(&dir).ok();
    let text = |rig: &str| {
        format!(
            "name = \"resume\"\noutput_dir = \"{}\"\n[scene]\nkind = \"synthetic\"\nrig = \"{rig}\"\nwidth = 40\nheight = 30\nviews = 4\n\
             [field]\nkind = \"voxel-grid\"\nresolution = [16, 16, 16]\ninitial_resolution = [16, 16, 16]\nupsample_at = []\n",
            dir.display()
        )
    };
    let written = session(&text("object-centric"));
    written.save_checkpoint().unwrap();
    let mut same = session(&text("object-centric"));
    same.load_checkpoint(None).unwrap();
    let mut other = session(&text("unbounded"));
    let err = other.load_checkpoint(None).unwrap_err().to_string();
    assert!(err.contains("extent") && err.contains("unbounded"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_set_memory_budget_is_kept_and_a_bad_one_refused() {
    let s = session("[scene]\nkind = \"synthetic\"\nwidth = 100\nheight = 75\nviews = 4\n[render]\nmemory_gib = 2.5\n");
    assert!(s.derived.iter().all(|d| d.key != "render.memory_gib"), "{:?}", s.derived);
    assert_eq!(s.config.render.memory_gib, Some(2.5));
    for bad in ["0", "-1", "nan", "inf"] {
        let text = format!("[scene]\nkind = \"synthetic\"\n[render]\nmemory_gib = {bad}\n");
        let err = sos_core::config::RunConfig::parse(&text, std::path::Path::new("bad.toml")).expect_err(bad);
        assert!(err.to_string().contains("render.memory_gib"), "{bad}: {err}");
    }
}
