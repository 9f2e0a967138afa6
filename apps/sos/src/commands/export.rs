//! `sos export`: what users of a finished run ask for first, from its checkpoint (field and
//! segmentation head), into `<run>/export/` or `--out`:
//! - `frames`: the scene's novel camera path rendered with the segmentation overlaid,
//!   `frames/0000.png` …;
//! - `gif`: the same frames as a looping animation, `path.gif`;
//! - `points`: the segmented object as a coloured point cloud, `points.ply`: every foreground
//!   pixel of every dataset view (training and held-out) whose ray hit something gives its
//!   rendered 3D point and colour, evenly thinned to `--max-points`;
//! - `mesh`: the object's density iso-surface, `mesh.ply` and `mesh.obj` (see [`mesh`] for the
//!   iso-level and how the object's part is chosen);
//! - `masks`: masks and overlays (`masks/`, `overlays/`) of the held-out views, or of the
//!   cameras of a `--poses` file ([`poses`] documents its format).
//!
//! `export.json` records what was written with the settings used. The views that points and
//! mesh need are segmented once each, and their held-out masks reused for `masks`.

pub mod animation;
pub mod files;
pub mod mesh;
pub mod poses;

use std::collections::BTreeSet;
use std::path::{Component, Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use sos_core::camera::{Camera, Vec3};
use sos_core::segment::evaluate::{write_view_pngs, ViewFolders};
use sos_core::segment::infer::{saliency_extractor, MaskInference, ViewMask};
use sos_core::segment::store::load_with_head;
use sos_core::train::Session;

use self::mesh::{Grid, ViewEvidence};

/// One kind of output of `sos export`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, clap::ValueEnum)]
pub enum Part {
    /// Camera-path frames with the segmentation overlaid (PNG).
    Frames,
    /// The camera-path frames as an animated GIF.
    Gif,
    /// The object's coloured point cloud (PLY).
    Points,
    /// The object's density iso-surface (PLY and OBJ).
    Mesh,
    /// Masks and overlays of the held-out views or of the `--poses` cameras (PNG).
    Masks,
}

impl Part {
    /// Every part, in the order they are written.
    pub const ALL: [Part; 5] = [Part::Frames, Part::Gif, Part::Points, Part::Mesh, Part::Masks];
}

/// The box the mesh's density grid covers.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum MeshBounds {
    /// The scene's extent (the bounded box, the unbounded foreground sphere's box, the
    /// forward-facing frustum's box).
    #[default]
    Extent,
    /// The box around the object's fused points (padded, within the extent): the same
    /// resolution spent on the object alone.
    Object,
}

/// Default cap of the point cloud.
pub const DEFAULT_MAX_POINTS: usize = 500_000;
/// Default grid nodes along the longest side of the mesh's box.
pub const DEFAULT_MESH_RESOLUTION: usize = 128;
/// Accepted grid nodes along the longest side of the mesh's box.
pub const MESH_RESOLUTIONS: std::ops::RangeInclusive<usize> = 8..=1024;

/// Settings of one export (also the `sos export` command line's options).
#[derive(Debug, Clone, clap::Args)]
pub struct ExportOptions {
    /// Checkpoint to export (default: the run's own); it must hold a segmentation head.
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// What to write, comma-separated (default: all).
    #[arg(long, value_enum, value_delimiter = ',', value_name = "WHAT")]
    pub what: Vec<Part>,
    /// JSON file of cameras (`width`, `height`, `focal`, `poses`: camera-to-world 4x4
    /// matrices) whose masks to render instead of the held-out views.
    #[arg(long, value_name = "FILE")]
    pub poses: Option<PathBuf>,
    /// Output folder (default: `<run>/export`).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Most points in the point cloud (thinned evenly over the views' pixels).
    #[arg(long, default_value_t = DEFAULT_MAX_POINTS)]
    pub max_points: usize,
    /// Density grid nodes along the longest side of the mesh's box (8 to 1024).
    #[arg(long, default_value_t = DEFAULT_MESH_RESOLUTION)]
    pub mesh_resolution: usize,
    /// The box the mesh's grid covers: the scene's extent, or the box around the object's points.
    #[arg(long, value_enum, default_value = "extent")]
    pub mesh_bounds: MeshBounds,
    /// Density of the mesh's surface, per unit of length (default: ln 2 / cell, one cell of it
    /// half opaque; see [`mesh::iso_level`]).
    #[arg(long, value_name = "SIGMA")]
    pub mesh_iso: Option<f32>,
    /// Show progress bars (set by the caller, not a flag).
    #[arg(skip)]
    pub progress: bool,
}

impl Default for ExportOptions {
    fn default() -> Self {
        ExportOptions {
            checkpoint: None,
            what: Vec::new(),
            poses: None,
            out: None,
            max_points: DEFAULT_MAX_POINTS,
            mesh_resolution: DEFAULT_MESH_RESOLUTION,
            mesh_bounds: MeshBounds::Extent,
            mesh_iso: None,
            progress: false,
        }
    }
}

/// Subfolders of the export.
const FRAMES_DIR: &str = "frames";
const MASK_FOLDERS: ViewFolders<'static> =
    ViewFolders { masks: "masks", overlays: "overlays", images: None, evidence: None, depth: None };

/// `sos export`: writes the parts `options` asks for from a run's checkpoint.
pub fn run(config: &Path, options: &ExportOptions) -> anyhow::Result<()> {
    let started = Instant::now();
    let what: BTreeSet<Part> =
        if options.what.is_empty() { Part::ALL.into_iter().collect() } else { options.what.iter().copied().collect() };
    if options.max_points == 0 {
        bail!("--max-points is 0; give the point cloud room for at least one point");
    }
    if !MESH_RESOLUTIONS.contains(&options.mesh_resolution) {
        bail!(
            "--mesh-resolution is {}; it must lie in {}..={}",
            options.mesh_resolution,
            MESH_RESOLUTIONS.start(),
            MESH_RESOLUTIONS.end()
        );
    }
    if let Some(iso) = options.mesh_iso.filter(|v| !(v.is_finite() && *v > 0.0)) {
        bail!("--mesh-iso is {iso}; it must be a positive density (per unit of length)");
    }
    let mut session = Session::open(config)?;
    let posed = options.poses.as_deref().map(poses::load).transpose()?;
    if posed.is_some() && !what.contains(&Part::Masks) {
        eprintln!("note: --poses only sets the views of `masks`, which --what leaves out");
    }
    let out = options.out.clone().unwrap_or_else(|| session.run_dir.join("export"));
    // Refuses a folder another run uses, or one that cannot be written, before any work; an
    // export elsewhere leaves the run folder alone.
    let _claim = if lexically_within(&out, &session.run_dir) { Some(session.claim_run_dir()?) } else { None };
    let (loaded, ckpt_path) = load_with_head(&mut session, options.checkpoint.as_deref())?;
    let Some(loaded) = loaded else {
        bail!(
            "checkpoint {} has no segmentation head; run `sos segment {}` to train one, then export",
            ckpt_path.display(),
            config.display()
        );
    };
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    eprintln!("exporting {} (stage 1 at step {}) to {}", ckpt_path.display(), session.step, out.display());
    let extractor = saliency_extractor(&session)?;
    let inference = MaskInference::new(&session, &loaded.head, extractor.as_deref())?;
    let exporter = Exporter { session: &session, inference: &inference, out: &out, progress: options.progress };
    let mut report = serde_json::json!({
        "checkpoint": ckpt_path,
        "stage1_steps": session.step,
        "stage2_steps": loaded.meta.steps,
    });

    if what.contains(&Part::Frames) || what.contains(&Part::Gif) {
        report["path"] = exporter.camera_path(what.contains(&Part::Frames), what.contains(&Part::Gif))?;
    }
    let fuse = what.contains(&Part::Points) || what.contains(&Part::Mesh);
    // Held-out masks come with the fused views when those are rendered anyway.
    let held_out_masks = what.contains(&Part::Masks) && posed.is_none();
    let fused = if fuse {
        let keep_points = what.contains(&Part::Points) || options.mesh_bounds == MeshBounds::Object;
        Some(exporter.fuse_views(held_out_masks, keep_points, what.contains(&Part::Mesh))?)
    } else {
        None
    };
    if what.contains(&Part::Points) {
        let fused = fused.as_ref().expect("fused for points");
        report["points"] = exporter.point_cloud(fused, options.max_points)?;
    }
    if what.contains(&Part::Mesh) {
        let fused = fused.as_ref().expect("fused for the mesh");
        report["mesh"] = exporter.mesh(fused, options)?;
    }
    if what.contains(&Part::Masks) {
        report["masks"] = match &posed {
            Some(cameras) => {
                let names: Vec<String> = (0..cameras.len()).map(|i| format!("{i:04}")).collect();
                let views: Vec<(&Camera, &str)> = cameras.iter().zip(names.iter().map(String::as_str)).collect();
                exporter.masks(&views, "poses file")?
            }
            None if fused.is_some() => held_out_record(&session),
            None => {
                let scene = &session.scene;
                let views: Vec<(&Camera, &str)> =
                    scene.test.iter().map(|&i| (&scene.views[i].camera, scene.views[i].name.as_str())).collect();
                exporter.masks(&views, "held-out views")?
            }
        };
    }
    report["seconds"] = started.elapsed().as_secs_f64().into();
    let record = out.join("export.json");
    super::write_json(&record, &report).context("writing the export record")?;
    say!("export record in {}", record.display())?;
    Ok(())
}

/// What the fused views give: the object's points with their colours, and each view's mask
/// and depth for the mesh's vote.
struct Fused {
    points: Vec<Vec3>,
    colours: Vec<[u8; 3]>,
    views: Vec<ViewEvidence>,
}

/// The session, head and output folder of one export.
struct Exporter<'a> {
    session: &'a Session,
    inference: &'a MaskInference<'a>,
    out: &'a Path,
    progress: bool,
}

impl Exporter<'_> {
    /// A bar over `len` items on a terminal, hidden otherwise.
    fn bar(&self, len: usize, what: &str) -> ProgressBar {
        if !self.progress {
            return ProgressBar::hidden();
        }
        let bar = ProgressBar::new(len as u64);
        if let Ok(style) =
            ProgressStyle::with_template("{msg:>16} [{bar:32}] {pos}/{len} {elapsed_precise} (ETA {eta})")
        {
            bar.set_style(style);
        }
        bar.set_message(what.to_owned());
        bar
    }

    /// Renders the camera path with masks overlaid, as PNG frames and/or a GIF.
    fn camera_path(&self, frames: bool, gif: bool) -> anyhow::Result<serde_json::Value> {
        let path = &self.session.scene.render_path;
        if path.is_empty() {
            eprintln!("note: the scene has no novel camera path (e.g. `render_path_views = 0`); no frames or GIF");
            return Ok(serde_json::json!({ "frames": 0 }));
        }
        if let Some(why) = self.session.scene.render_path_problem() {
            anyhow::bail!("{why}");
        }
        let gif_path = self.out.join("path.gif");
        let mut animation = match gif {
            true => Some(animation::GifWriter::create(&gif_path, path[0].width as usize, path[0].height as usize)?),
            false => None,
        };
        let bar = self.bar(path.len(), "camera path");
        for (i, cam) in path.iter().enumerate() {
            let name = format!("{i:04}");
            let overlay = self.inference.segment(cam, &name)?.overlay();
            if frames {
                overlay.save_png(&self.out.join(FRAMES_DIR).join(format!("{name}.png")))?;
            }
            if let Some(a) = animation.as_mut() {
                a.push(&overlay)?;
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        let mut record = serde_json::json!({ "frames": path.len() });
        if frames {
            say!("{} camera-path frames with masks overlaid in {}", path.len(), self.out.join(FRAMES_DIR).display())?;
            record["frames_dir"] = FRAMES_DIR.into();
        }
        if let Some(a) = animation {
            a.finish()?;
            say!("animation of the camera path in {}", gif_path.display())?;
            record["gif"] = "path.gif".into();
            record["frame_delay_ms"] = (10 * animation::FRAME_DELAY_CS).into();
        }
        Ok(record)
    }

    /// Segments every dataset view: the object's points (when
    /// `keep_points`), each view's evidence for the mesh (when `keep_views`), and the masks of
    /// the held-out views (when `held_out_masks`).
    fn fuse_views(&self, held_out_masks: bool, keep_points: bool, keep_views: bool) -> anyhow::Result<Fused> {
        let scene = &self.session.scene;
        let mut fused = Fused { points: Vec::new(), colours: Vec::new(), views: Vec::new() };
        let bar = self.bar(scene.views.len(), "views");
        for (i, view) in scene.views.iter().enumerate() {
            let mask = self.inference.segment(&view.camera, &view.name)?;
            if held_out_masks && scene.test.contains(&i) {
                write_view_pngs(&mask, self.out, MASK_FOLDERS, &view.name)?;
            }
            if keep_points {
                Self::fuse_points(&mask, &mut fused);
            }
            if keep_views {
                let ViewMask { foreground, depth, .. } = mask;
                fused.views.push(ViewEvidence { camera: view.camera.clone(), foreground, depth });
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        if held_out_masks {
            say!("masks of {} held-out views in {}", scene.test.len(), self.out.join(MASK_FOLDERS.masks).display())?;
        }
        Ok(fused)
    }

    /// Adds the point and colour of every foreground pixel of `mask` whose ray hit something,
    /// from the render the mask was decided with.
    fn fuse_points(mask: &ViewMask, into: &mut Fused) {
        for (i, point) in mask.points.iter().enumerate() {
            if let (true, Some(p)) = (mask.foreground[i], point) {
                into.points.push(*p);
                let rgb = &mask.rgb.data[i * 3..i * 3 + 3];
                into.colours.push([0, 1, 2].map(|k| (rgb[k].clamp(0.0, 1.0) * 255.0 + 0.5) as u8));
            }
        }
    }

    /// Writes the fused points, evenly thinned to `max_points`, as `points.ply`.
    fn point_cloud(&self, fused: &Fused, max_points: usize) -> anyhow::Result<serde_json::Value> {
        let keep = thin_evenly(fused.points.len(), max_points);
        let points: Vec<Vec3> = keep.iter().map(|&i| fused.points[i]).collect();
        let colours: Vec<[u8; 3]> = keep.iter().map(|&i| fused.colours[i]).collect();
        let path = self.out.join("points.ply");
        files::write_point_cloud(&path, &points, &colours)?;
        if points.is_empty() {
            eprintln!("warning: no view's mask holds a rendered surface point; the point cloud is empty");
        }
        say!(
            "point cloud of {} points (of {} foreground pixels in {} views) in {}",
            points.len(),
            fused.points.len(),
            self.session.scene.views.len(),
            path.display()
        )?;
        Ok(serde_json::json!({
            "file": "points.ply",
            "points": points.len(),
            "foreground_pixels": fused.points.len(),
            "views": self.session.scene.views.len(),
            "max_points": max_points,
        }))
    }

    /// Samples the density, labels the object's nodes and writes its iso-surface as
    /// `mesh.ply` and `mesh.obj`.
    fn mesh(&self, fused: &Fused, options: &ExportOptions) -> anyhow::Result<serde_json::Value> {
        let extent = mesh::extent_box(&self.session.scene.extent);
        let bounds = options.mesh_bounds;
        let (lo, hi) = match bounds {
            MeshBounds::Extent => extent,
            MeshBounds::Object => mesh::object_box(&fused.points, extent).unwrap_or_else(|| {
                eprintln!("note: no foreground points to bound the object; the mesh's grid covers the extent");
                extent
            }),
        };
        let grid = Grid::fit(lo, hi, options.mesh_resolution);
        let iso = options.mesh_iso.unwrap_or_else(|| mesh::iso_level(grid.cell));
        let bar = self.bar(grid.len(), "density grid");
        let density = mesh::sample_density(self.session.field.as_ref(), &grid, &|n| bar.inc(n));
        bar.finish_and_clear();
        let bar = self.bar(grid.len(), "object vote");
        let object = mesh::label_object(&grid, &density, iso, &fused.views, &|n| bar.inc(n));
        bar.finish_and_clear();
        let dense = density.iter().filter(|&&d| d >= iso).count();
        let densest = density.iter().copied().fold(0.0f32, f32::max);
        let kept = object.iter().filter(|&&o| o).count();
        let surface = mesh::extract(&grid, &density, iso, &object);
        if surface.faces.is_empty() {
            eprintln!(
                "warning: the object's mesh is empty: {dense} of {} grid nodes reach the iso-level {iso:.3} (the \
                 densest {densest:.3}), {kept} of them voted object; a soft field shows a surface on a coarser grid \
                 (--mesh-resolution) or at a lower --mesh-iso",
                grid.len()
            );
        }
        let (ply, obj) = (self.out.join("mesh.ply"), self.out.join("mesh.obj"));
        files::write_mesh_ply(&ply, &surface)?;
        files::write_mesh_obj(&obj, &surface)?;
        say!(
            "mesh of {} vertices and {} triangles (density iso-level {iso:.4} on a {}x{}x{} grid of cell {:.4}) in {} \
             and {}",
            surface.positions.len(),
            surface.faces.len(),
            grid.dims[0],
            grid.dims[1],
            grid.dims[2],
            grid.cell,
            ply.display(),
            obj.display()
        )?;
        Ok(serde_json::json!({
            "files": ["mesh.ply", "mesh.obj"],
            "vertices": surface.positions.len(),
            "faces": surface.faces.len(),
            "grid": { "min": grid.min, "max": grid.max(), "cell": grid.cell, "dims": grid.dims, "bounds": format!("{bounds:?}").to_lowercase() },
            "iso_density": iso,
            "nodes_at_iso": dense,
            "max_density": densest,
            "object_nodes": kept,
            "views": fused.views.len(),
        }))
    }

    /// Segments the given views and writes their masks and overlays.
    fn masks(&self, views: &[(&Camera, &str)], source: &str) -> anyhow::Result<serde_json::Value> {
        let bar = self.bar(views.len(), "masks");
        for (camera, name) in views {
            let mask = self.inference.segment(camera, name)?;
            write_view_pngs(&mask, self.out, MASK_FOLDERS, name)?;
            bar.inc(1);
        }
        bar.finish_and_clear();
        say!("masks of {} views ({source}) in {}", views.len(), self.out.join(MASK_FOLDERS.masks).display())?;
        Ok(serde_json::json!({
            "source": source,
            "views": views.iter().map(|(_, n)| *n).collect::<Vec<_>>(),
            "masks_dir": MASK_FOLDERS.masks,
            "overlays_dir": MASK_FOLDERS.overlays,
        }))
    }
}

/// The record of held-out masks written while fusing views.
fn held_out_record(session: &Session) -> serde_json::Value {
    let names: Vec<&str> = session.scene.test.iter().map(|&i| session.scene.views[i].name.as_str()).collect();
    serde_json::json!({
        "source": "held-out views",
        "views": names,
        "masks_dir": MASK_FOLDERS.masks,
        "overlays_dir": MASK_FOLDERS.overlays,
    })
}

/// `min(n, cap)` indices spread evenly over `0..n`, in order (all of them when `n <= cap`).
pub fn thin_evenly(n: usize, cap: usize) -> Vec<usize> {
    if n <= cap {
        return (0..n).collect();
    }
    (0..cap).map(|k| (k as u128 * n as u128 / cap as u128) as usize).collect()
}

/// Whether `path` lies inside `dir`, comparing absolute paths with `.` and `..` resolved
/// lexically (neither needs to exist).
fn lexically_within(path: &Path, dir: &Path) -> bool {
    fn normal(p: &Path) -> PathBuf {
        let absolute = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        let mut out = PathBuf::new();
        for c in absolute.components() {
            match c {
                Component::CurDir => {}
                Component::ParentDir => {
                    out.pop();
                }
                other => out.push(other),
            }
        }
        out
    }
    normal(path).starts_with(normal(dir))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thinning_is_even_and_exact() {
        assert_eq!(thin_evenly(3, 5), vec![0, 1, 2]);
        let kept = thin_evenly(1000, 10);
        assert_eq!(kept, (0..10).map(|k| k * 100).collect::<Vec<_>>());
        let kept = thin_evenly(7, 3);
        assert_eq!(kept.len(), 3);
        assert!(kept.windows(2).all(|w| w[0] < w[1]) && *kept.last().unwrap() < 7);
    }

    #[test]
    fn run_folder_containment_is_lexical() {
        assert!(lexically_within(Path::new("runs/a/export"), Path::new("runs/a")));
        assert!(lexically_within(Path::new("runs/b/../a/x"), Path::new("./runs/a")));
        assert!(!lexically_within(Path::new("runs/ab"), Path::new("runs/a")));
        assert!(!lexically_within(Path::new("/tmp/elsewhere"), Path::new("runs/a")));
    }
}
