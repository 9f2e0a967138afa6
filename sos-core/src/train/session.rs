//! A run's live state: config, scene, field and occupancy grid, with checkpointing and
//! rendering of whole views.

use std::path::{Path, PathBuf};

use rand::SeedableRng;

use crate::camera::Camera;
use crate::config::RunConfig;
use crate::derived::{derive_settings, DerivedSetting, PatchFacts};
use crate::error::RunError;
use crate::image::RgbImage;
use crate::plugin::field::plain;
use crate::plugin::{BuildContext, RadianceField};
use crate::render::contraction::Contraction;
use crate::render::memory_budget::MemoryBudget;
use crate::render::occupancy::OccupancyGrid;
use crate::render::rays::RayBatch;
use crate::render::renderer::{render_inference, RenderContext, RenderOptions};
use crate::render::sampler::MarchOptions;
use crate::scene::Scene;
use crate::train::checkpoint::{self, CheckpointMeta};

/// Decay of the occupancy grid's running maximum between updates.
const OCCUPANCY_DECAY: f32 = 0.95;

/// Everything a run works on.
pub struct Session {
    /// The parsed configuration.
    pub config: RunConfig,
    /// Folder of the config file (relative paths resolve against it).
    pub config_dir: PathBuf,
    /// The config file, or its folder for a session built from a parsed config: what errors
    /// about the config's keys name.
    pub config_source: PathBuf,
    /// `<output_dir>/<name>/`.
    pub run_dir: PathBuf,
    /// The loaded scene.
    pub scene: Scene,
    /// The radiance field.
    pub field: Box<dyn RadianceField>,
    /// The field's kind (from the config).
    pub field_kind: String,
    /// Unit-cube mapping of the scene.
    pub contraction: Contraction,
    /// Empty-space skipping grid, when enabled.
    pub occupancy: Option<OccupancyGrid>,
    /// Stage-1 steps completed.
    pub step: usize,
    /// The settings this run derived from its scene (already written into `config`).
    pub derived: Vec<DerivedSetting>,
    /// Where stage 1's random stream stood at `step` (a ChaCha8 word position), restored from
    /// a checkpoint so that a resumed run continues the stream; `None` for a fresh run.
    pub rng_position: Option<u128>,
    /// The step at which stage 1 stopped because its loss levelled off
    /// (`train.stop_when_converged`); `train.steps` then equals it, so the stage counts as
    /// complete (a resumed run does not train on).
    pub converged_at: Option<usize>,
}

/// The `kind` tag of a typetag'd config object.
pub fn kind_of<T: serde::Serialize + ?Sized>(config: &T) -> String {
    toml::Value::try_from(config)
        .ok()
        .and_then(|v| v.get("kind").and_then(|k| k.as_str().map(str::to_owned)))
        .unwrap_or_else(|| "?".into())
}

impl Session {
    /// Loads the config, the scene and builds a fresh field.
    pub fn open(config_path: &Path) -> Result<Session, RunError> {
        let config = RunConfig::load(config_path)?;
        let config_dir = config_path.parent().map(Path::to_path_buf).unwrap_or_default();
        Session::build(config, &config_dir, config_path)
    }

    /// Builds a session from an already parsed config.
    pub fn from_config(config: RunConfig, config_dir: &Path) -> Result<Session, RunError> {
        Session::build(config, config_dir, config_dir)
    }

    /// [`Session::from_config`]; `source` (the config file, or its folder) is named in errors.
    fn build(mut config: RunConfig, config_dir: &Path, source: &Path) -> Result<Session, RunError> {
        let in_config = |e| RunError::Scene { config: source.to_path_buf(), source: e };
        let scene = config.scene.open(config_dir).map_err(in_config)?;
        scene
            .validate()
            .map_err(|message| crate::plugin::dataset::DatasetError::Invalid {
                path: config_dir.to_path_buf(),
                message,
            })
            .map_err(in_config)?;
        let mut derived = derive_settings(&mut config, config_dir, &scene);
        if let Some(extractor) = config.extractor.as_ref().filter(|_| config.segment.steps > 0) {
            let patch = PatchFacts::of_run(&config.segment, &scene);
            extractor.check_for(&patch).map_err(|e| RunError::Plugin {
                config: source.to_path_buf(),
                section: "extractor",
                source: e,
            })?;
        }
        crate::train::memory_check::check(&config, source)?;
        let field = config.field.build(&scene.extent, config.seed).map_err(|source_error| RunError::Plugin {
            config: source.to_path_buf(),
            section: "field",
            source: source_error,
        })?;
        derived.extend(Session::derive_frozen_samples(&mut config, field.as_ref()));
        let field_kind = kind_of(&config.field);
        let contraction = Contraction::new(&scene.extent);
        let occupancy =
            config.train.occupancy.then(|| Session::occupancy_grid(&config, &scene, config.train.occupancy_alpha));
        let run_dir = config_dir.join(&config.output_dir).join(&config.name);
        Ok(Session {
            config,
            config_dir: config_dir.to_path_buf(),
            config_source: source.to_path_buf(),
            run_dir,
            scene,
            field,
            field_kind,
            contraction,
            occupancy,
            step: 0,
            derived,
            rng_position: None,
            converged_at: None,
        })
    }

    /// Fills `render.samples_per_ray` from the field's grid when the config leaves it unset:
    /// one candidate per cell of the finest axis, at most the training count. Training draws
    /// its samples at random inside their intervals and needs them denser; a frozen render's
    /// midpoint samples of a trilinear grid gain little beyond one per cell.
    fn derive_frozen_samples(config: &mut RunConfig, field: &dyn RadianceField) -> Option<DerivedSetting> {
        if config.render.samples_per_ray.is_some() {
            return None;
        }
        let cells = plain::final_cells_across(field)?;
        let samples = cells.clamp(2, config.train.samples_per_ray.max(2));
        config.render.samples_per_ray = Some(samples);
        Some(DerivedSetting::new(
            "render.samples_per_ray",
            samples,
            format!("one per cell along the field's finest grid axis ({cells} cells), at most train.samples_per_ray"),
        ))
    }

    /// An empty-space grid for `config`'s stage 1 on `scene` whose cells count as occupied when
    /// one candidate step through them has at least opacity `alpha` (`train.occupancy_alpha`
    /// for the run's own grid).
    pub fn occupancy_grid(config: &RunConfig, scene: &Scene, alpha: f32) -> OccupancyGrid {
        let t = &config.train;
        let step = scene.extent.characteristic_length() / t.samples_per_ray as f32;
        OccupancyGrid::new(t.occupancy_resolution, -(1.0 - alpha).ln() / step)
    }

    /// What plugins built for this run need: relative paths resolve against the config's
    /// folder.
    pub fn build_context(&self) -> BuildContext {
        BuildContext::new(&self.config_dir)
    }

    /// Claims the run's folder before any work (see [`crate::train::run_dir`]); keep the claim
    /// for as long as the run writes there.
    pub fn claim_run_dir(&self) -> Result<crate::train::run_dir::RunDirClaim, RunError> {
        crate::train::run_dir::RunDirClaim::claim(&self.run_dir, "output_dir")
    }

    /// Path of the run's checkpoint.
    pub fn checkpoint_path(&self) -> PathBuf {
        self.run_dir.join("checkpoint.bin")
    }

    /// Writes the checkpoint atomically: the field, its optimiser state and the occupancy grid,
    /// everything a run needs to resume as if it had not stopped.
    pub fn save_checkpoint(&self) -> Result<(), RunError> {
        self.save_checkpoint_with(&[])
    }

    /// Writes the checkpoint atomically with `extra` named sections after the run's own (e.g.
    /// the stage-2 `head`).
    pub fn save_checkpoint_with(&self, extra: &[(&str, &[u8])]) -> Result<(), RunError> {
        let meta = self.checkpoint_meta();
        let state = self.field.save_state();
        // The optimiser's moments (twice the field's size) matter only while the field still
        // trains: during stage 1, or in stage 2 when it trains jointly with the head.
        let field_trains = self.step < self.config.train.steps || self.config.segment.photometric_weight > 0.0;
        let optimizer = if field_trains { self.field.save_optimizer_state() } else { Vec::new() };
        let occupancy = self.occupancy.as_ref().map(OccupancyGrid::to_bytes).unwrap_or_default();
        let own = [
            ("field", state.as_slice()),
            (checkpoint::OPTIMIZER_SECTION, optimizer.as_slice()),
            (checkpoint::OCCUPANCY_SECTION, occupancy.as_slice()),
        ];
        let mut sections: Vec<(&str, &[u8])> = own.iter().copied().filter(|(_, bytes)| !bytes.is_empty()).collect();
        sections.extend(extra.iter().copied().filter(|(name, _)| !own.iter().any(|(n, _)| n == name)));
        checkpoint::save(&self.checkpoint_path(), &meta, &sections)
    }

    fn checkpoint_meta(&self) -> CheckpointMeta {
        CheckpointMeta {
            step: self.step,
            field_kind: self.field_kind.clone(),
            config: self.config.to_toml(),
            extent: Some(self.scene.extent.to_string()),
            rng_position: self.rng_position.map(|p| p.to_string()),
            converged_at: self.converged_at,
        }
    }

    /// Ends stage 1 at `step` because its loss levelled off: the stage's length becomes `step`.
    pub fn stop_converged(&mut self, step: usize) {
        self.converged_at = Some(step);
        self.config.train.steps = step;
    }

    /// Restores the field from `path` (the run's own checkpoint when `None`).
    pub fn load_checkpoint(&mut self, path: Option<&Path>) -> Result<(), RunError> {
        self.load_checkpoint_sections(path).map(|_| ())
    }

    /// Restores the field like [`Session::load_checkpoint`] and returns the checkpoint with
    /// its other sections (e.g. the stage-2 `head`) and the path it was read from.
    pub fn load_checkpoint_sections(
        &mut self,
        path: Option<&Path>,
    ) -> Result<(checkpoint::Checkpoint, PathBuf), RunError> {
        let path = path.map(Path::to_path_buf).unwrap_or_else(|| self.checkpoint_path());
        let ckpt = checkpoint::load(&path)?;
        let fail = |message: String| RunError::Checkpoint { path: path.clone(), message };
        if ckpt.meta.field_kind != self.field_kind {
            return Err(fail(format!(
                "written by a `{}` field but the config asks for `{}`",
                ckpt.meta.field_kind, self.field_kind
            )));
        }
        // A field lives in its extent's coordinates: another extent (e.g. derived anew after
        // the scene's files or the derivation rules changed) would misread every parameter.
        if let Some(extent) = ckpt.meta.extent.as_ref().filter(|e| **e != self.scene.extent.to_string()) {
            return Err(fail(format!(
                "written for the extent {extent}, but this run's scene has {}; set the scene's `aabb` (or its \
                 other keys) as that run had them, or start over without the checkpoint",
                self.scene.extent
            )));
        }
        let state = ckpt.section("field").ok_or_else(|| fail("has no field section".into()))?;
        self.field.load_state(state).map_err(|e| fail(e.to_string()))?;
        // A diverged run can have saved NaN or infinite parameters: training on from them, or
        // rendering them, would only report nonsense.
        if let Some(i) = self.field.first_non_finite_parameter() {
            return Err(fail(format!(
                "its `field` section holds a non-finite parameter (number {i}); the run that wrote it diverged: \
                 start over without the checkpoint, with a lower learning rate"
            )));
        }
        if let Some(bytes) = ckpt.section(checkpoint::OPTIMIZER_SECTION) {
            self.field.load_optimizer_state(bytes).map_err(|e| fail(format!("its optimizer section: {e}")))?;
        }
        self.step = ckpt.meta.step;
        // A stage that levelled off ended there; never beyond the configured length, whatever
        // the checkpoint says.
        if let Some(step) = ckpt.meta.converged_at {
            self.stop_converged(step.min(self.config.train.steps));
        }
        self.rng_position = match &ckpt.meta.rng_position {
            Some(p) => Some(p.parse().map_err(|_| fail(format!("its random-stream position `{p}` is not a number")))?),
            None => None,
        };
        // The grid as the run left it; rebuilt from the field when the checkpoint has none (or
        // one of another resolution).
        let restored = match (self.occupancy.as_mut(), ckpt.section(checkpoint::OCCUPANCY_SECTION)) {
            (Some(occ), Some(bytes)) => occ.load_bytes(bytes).is_ok(),
            _ => false,
        };
        if !restored {
            self.bake_occupancy();
        }
        Ok((ckpt, path))
    }

    /// Re-probes the occupancy grid (`decay = 0` rebuilds it from scratch).
    pub fn refresh_occupancy(&mut self, decay: f32) {
        if let Some(occ) = self.occupancy.as_mut() {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(self.config.seed ^ self.step as u64);
            occ.update(self.field.as_ref(), &self.contraction, decay, &mut rng);
        }
    }

    /// Rebuilds the occupancy grid from the field as it is now, with one cell of margin: the
    /// grid a frozen field (stage 2, evaluation) skips empty space with.
    pub fn bake_occupancy(&mut self) {
        self.refresh_occupancy(0.0);
        if let Some(occ) = self.occupancy.as_mut() {
            occ.dilate();
        }
    }

    /// Periodic occupancy maintenance during training.
    pub fn maintain_occupancy(&mut self) {
        let t = &self.config.train;
        if self.step >= t.occupancy_warmup && self.step.is_multiple_of(t.occupancy_every) {
            self.refresh_occupancy(OCCUPANCY_DECAY);
        }
    }

    /// Render settings for training (`stratified`) or evaluation. The candidate count follows
    /// the field's current detail, so coarse stages of a growing grid march coarsely.
    pub fn render_options(&self, stratified: bool) -> RenderOptions {
        let t = &self.config.train;
        // Frozen renders take their own count (see `derive_frozen_samples`); both shrink while
        // a grid is coarse.
        let full = if stratified {
            t.samples_per_ray
        } else {
            self.config.render.samples_per_ray.unwrap_or(t.samples_per_ray)
        };
        let steps = ((full as f32 * plain::detail_fraction(self.field.as_ref())).round() as usize).max(8);
        RenderOptions {
            proposal: true,
            march: MarchOptions { steps, stratified },
            early_stop: t.early_stop,
            min_weight: if stratified { t.weight_threshold } else { 0.0 },
            memory: MemoryBudget::from_gib(
                self.config.render.memory_gib.unwrap_or_else(|| crate::render::memory_budget::machine_default_gib().0),
            ),
        }
    }

    /// Render settings of the frozen field's renders (stage 2 and mask inference): the
    /// evaluation settings with the segment's early termination and proposal choice.
    pub fn frozen_render_options(&self) -> RenderOptions {
        let g = &self.config.segment;
        RenderOptions { early_stop: g.early_stop, proposal: g.proposal, ..self.render_options(false) }
    }

    /// The scene-level render context.
    pub fn render_context(&self) -> RenderContext<'_> {
        RenderContext {
            extent: &self.scene.extent,
            contraction: &self.contraction,
            occupancy: if self.step >= self.config.train.occupancy_warmup { self.occupancy.as_ref() } else { None },
            near: self.scene.near,
        }
    }

    /// Renders a whole view: colour and the reference-style depth `Σ w t`.
    pub fn render_view(&self, camera: &Camera) -> (RgbImage, Vec<f32>) {
        let rays = RayBatch::full_image(camera);
        let (colours, _) = render_inference(
            self.field.as_ref(),
            self.render_context(),
            &rays,
            self.render_options(false),
            self.config.render.chunk,
            None,
        );
        let mut img = RgbImage::new(camera.width as usize, camera.height as usize);
        for (i, c) in colours.iter().enumerate() {
            img.data[i * 3..i * 3 + 3].copy_from_slice(&c.rgb);
        }
        (img, colours.iter().map(|c| c.depth).collect())
    }
}
