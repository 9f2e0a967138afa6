//! One benchmark run in its own process (`sos bench-exec`): both stages as `sos train` runs
//! them, with learning curves sampled between steps, then the outcome as JSON. A process per
//! run gives each its own peak-memory figure, and a crash of one run ends only that run.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use sos_core::error::RunError;
use sos_core::segment::evaluate::{evaluate_masks, MaskEval};
use sos_core::segment::infer::MaskInference;
use sos_core::segment::store::{save_with_head, HeadMeta};
use sos_core::segment::train::{train_segmentation_observed, SegStepStats, Segmenter};
use sos_core::train::evaluate::{evaluate_views, overfitting_warning};
use sos_core::train::face_pileup::face_pileup_warning;
use sos_core::train::observer::{Severity, Stage, TrainObserver};

use crate::console::Console;
use sos_core::train::photometric::{train_photometric_observed, StepStats};
use sos_core::train::Session;

use super::record::{
    cpu_seconds, cpu_ticks, peak_rss_mib, stolen_between, Curves, Metrics, Outcome, RunRecord, Stage1Point,
    Stage1Summary, Stage2Point, Timing, ViewTime,
};

/// Arguments of `sos bench-exec`.
#[derive(Debug, clap::Args)]
pub struct ExecArgs {
    /// The resolved run config.
    pub config: PathBuf,
    /// Folder the config's relative paths resolve against.
    #[arg(long)]
    pub config_dir: PathBuf,
    /// Where to write the outcome (JSON).
    #[arg(long)]
    pub outcome: PathBuf,
    /// Learning-curve samples per stage.
    #[arg(long, default_value_t = 0)]
    pub curve_points: usize,
    /// Skip stage 1: load this checkpoint of an earlier run with the same stage-1 settings
    /// (a field stage 2 left frozen) and count that run's stage-1 time, curve and notes.
    #[arg(long, requires = "stage1_record")]
    pub stage1_checkpoint: Option<PathBuf>,
    /// The record (`runs/<id>.json`) of the run `--stage1-checkpoint` comes from.
    #[arg(long, requires = "stage1_checkpoint")]
    pub stage1_record: Option<PathBuf>,
    /// Size of the view whose time with its mask is measured (default: the scene's own).
    #[arg(long, num_args = 2, value_names = ["WIDTH", "HEIGHT"])]
    pub view_size: Option<Vec<u32>>,
}

/// Stage 1 as a run ran it or took it from an earlier run.
struct Stage1Result {
    summary: Stage1Summary,
    /// Taken from an earlier run: its time, curve (final point included) and memory are that
    /// run's, not this process's.
    shared: bool,
    /// Peak resident memory of the run a shared stage 1 ran in.
    source_peak_mib: Option<f64>,
}

/// Runs one benchmark run and writes its outcome.
pub fn run(args: &ExecArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    let ticks = cpu_ticks();
    let text = std::fs::read_to_string(&args.config).with_context(|| format!("reading {}", args.config.display()))?;
    let config = sos_core::config::RunConfig::parse(&text, &args.config)?;
    let mut session = Session::from_config(config, &args.config_dir)?;
    crate::commands::announce_resolved(&session)?;
    let segmenter = if session.config.segment.steps > 0 { Some(Segmenter::build(&session)?) } else { None };
    let _claim = session.claim_run_dir()?;
    let mut timing = Timing { setup: started.elapsed().as_secs_f64(), ..Default::default() };
    let mut curves = CurveRecorder::new(args.curve_points, &session, segmenter.is_some());

    let shared = match (&args.stage1_checkpoint, &args.stage1_record) {
        (Some(checkpoint), Some(record)) => Some((checkpoint, RunRecord::load(record)?)),
        _ => None,
    };
    let stage1 = match shared {
        Some((checkpoint, source)) => {
            let loaded = Instant::now();
            session.load_checkpoint_sections(Some(checkpoint))?;
            timing.setup += loaded.elapsed().as_secs_f64();
            let o = source.outcome.as_ref().context("the shared stage 1's run has no outcome")?;
            let mut summary = o.stage1.clone().context("the shared stage 1's run kept no stage-1 summary")?;
            timing.stage1 = o.timing.stage1;
            curves.curves.stage1 = o.curves.stage1.clone();
            curves.stage1_steps = summary.steps;
            summary.notes.push(format!(
                "stage 1 shared with `{}` (the same stage-1 settings): its stage-1 time and curve are that run's",
                source.key.id
            ));
            Stage1Result { summary, shared: true, source_peak_mib: o.peak_rss_mib }
        }
        None => {
            let stage1 = Instant::now();
            curves.begin_stage();
            let stats = train_photometric_observed(&mut session, &mut curves)?;
            timing.stage1 = stage1.elapsed().as_secs_f64() - curves.stage1_eval;
            curves.stage1_steps = session.step;
            let mut notes = Vec::new();
            if let Some(step) = session.converged_at {
                notes.push(format!("stage 1 stopped at step {step}: its training loss levelled off"));
            }
            notes.extend(stats.faces.as_ref().and_then(face_pileup_warning));
            let train_psnr = stats.psnr.is_finite().then_some(stats.psnr);
            let summary = Stage1Summary { notes, train_psnr, steps: session.step };
            Stage1Result { summary, shared: false, source_peak_mib: None }
        }
    };
    let mut notes = stage1.summary.notes.clone();
    let mut view = None;
    // The view's timing is a measurement, like the curves: kept off the run's time.
    let mut view_measurement = 0.0;
    let mut stage2_steps = None;
    let metrics = match segmenter {
        None => {
            let t = Instant::now();
            let eval = evaluate_views(&session, session.config.render.test_views)?;
            timing.masks = t.elapsed().as_secs_f64();
            Metrics {
                psnr: finite(eval.psnr, "PSNR", &mut notes),
                ssim: finite(eval.ssim, "SSIM", &mut notes),
                ..Default::default()
            }
        }
        Some(mut seg) => {
            let stage2 = Instant::now();
            curves.begin_stage();
            train_segmentation_observed(&mut session, &mut seg, &mut curves)?;
            seg.release_step_buffers();
            timing.stage2 = stage2.elapsed().as_secs_f64() - curves.stage2_eval;
            curves.stage2_steps = seg.step;
            if let Some(step) = seg.settled_at {
                notes.push(format!(
                    "stage 2 stopped at step {step} of {}: the masks settled",
                    session.config.segment.steps
                ));
            }
            save_with_head(&session, &seg.head, HeadMeta { steps: seg.step })
                .context("saving the segmentation head")?;
            let t = Instant::now();
            let inference = MaskInference::new(&session, &seg.head, Some(seg.teacher.extractor()))?;
            let eval = evaluate_masks(&session, &inference, true)?;
            timing.masks = t.elapsed().as_secs_f64();
            stage2_steps = Some(seg.step);
            let t = Instant::now();
            // The held-out masks are the run's result; a timing that fails is only a note.
            match time_view(&session, &inference, args.view_size.as_deref()) {
                Ok(v) => view = v,
                Err(e) => notes.push(format!("the timed view with its mask failed: {e:#}")),
            }
            view_measurement = t.elapsed().as_secs_f64();
            mask_metrics(&eval, &mut notes)
        }
    };
    let train_psnr = stage1.summary.train_psnr.unwrap_or(f64::NAN);
    if let Some(w) = metrics.psnr.and_then(|p| overfitting_warning(train_psnr, p)) {
        notes.push(w);
    }
    curves.finish(&metrics, timing.stage1, timing.stage2, stage1.shared);
    if session.scene.test.is_empty() {
        notes.push("the scene holds out no views: no held-out metrics".into());
    }
    timing.curve_eval = curves.stage1_eval + curves.stage2_eval;
    let measured = timing.curve_eval + view_measurement;
    timing.total = started.elapsed().as_secs_f64() - measured;
    if stage1.shared {
        // The shared stage 1 ran in another process: its time counts as if it ran here.
        timing.total += timing.stage1;
    }
    let outcome = Outcome {
        metrics,
        timing,
        // A shared stage 1 ran in another process: its peak memory counts, and the CPU time of
        // this process alone over a wall time that includes that stage would mean nothing.
        peak_rss_mib: match (peak_rss_mib(), stage1.source_peak_mib) {
            (Some(own), Some(source)) => Some(own.max(source)),
            (own, source) => own.or(source),
        },
        cpu_seconds: if stage1.shared { None } else { cpu_seconds() },
        cpu_stolen: ticks.zip(cpu_ticks()).and_then(|(a, b)| stolen_between(a, b)),
        curves: curves.curves,
        notes,
        derived: session.derived.clone(),
        stage1: (!stage1.shared).then_some(stage1.summary),
        stage2_steps,
        view,
    };
    crate::commands::write_json(&args.outcome, &outcome)
}

/// The time of one view with its mask at `size` (the camera's own without one): the first
/// held-out camera, else the first training one; `None` for a scene without views.
fn time_view(session: &Session, inference: &MaskInference, size: Option<&[u32]>) -> anyhow::Result<Option<ViewTime>> {
    let scene = &session.scene;
    let Some(&index) = scene.test.first().or(scene.train.first()) else { return Ok(None) };
    let view = &scene.views[index];
    let camera = match size {
        Some(&[width, height]) => view.camera.resized(width, height),
        _ => view.camera.clone(),
    };
    let mut seconds = Vec::with_capacity(ViewTime::REPEATS);
    for _ in 0..ViewTime::REPEATS {
        let t = Instant::now();
        inference.segment(&camera, &view.name)?;
        seconds.push(t.elapsed().as_secs_f64());
    }
    seconds.sort_by(f64::total_cmp);
    Ok(Some(ViewTime { width: camera.width, height: camera.height, seconds: seconds[seconds.len() / 2] }))
}

/// `Some(v)` for a finite value; otherwise a note and `None`, so that no report shows NaN.
fn finite(v: f64, name: &str, notes: &mut Vec<String>) -> Option<f64> {
    if v.is_finite() {
        Some(v)
    } else {
        notes.push(format!("{name} was not finite ({v})"));
        None
    }
}

fn finite_opt(v: Option<f64>, name: &str, notes: &mut Vec<String>) -> Option<f64> {
    v.and_then(|v| finite(v, name, notes))
}

/// The held-out metrics of a mask pass.
fn mask_metrics(eval: &MaskEval, notes: &mut Vec<String>) -> Metrics {
    let iou = eval.segmentation.iou();
    Metrics {
        psnr: finite_opt(eval.image.psnr_of_mean_mse(), "PSNR", notes),
        ssim: finite_opt(eval.image.mean_ssim(), "SSIM", notes),
        nv_ari: finite_opt(eval.segmentation.mean_ari(), "NV-ARI", notes),
        iou_fg: finite_opt(iou.iou_fg, "IoU FG", notes),
        iou_bg: finite_opt(iou.iou_bg, "IoU BG", notes),
        miou: finite_opt(iou.miou, "mIoU", notes),
        depth_error: finite_opt(eval.depth_error, "depth error", notes),
        object_depth_error: finite_opt(eval.object_depth_error, "object depth error", notes),
    }
}

/// Samples held-out quality at evenly spaced steps of each stage and keeps its own
/// evaluation time apart from the training clock. The last point of each curve is the run's
/// final evaluation, so it costs nothing extra.
struct CurveRecorder {
    points: usize,
    stage1_steps: usize,
    stage2_steps: usize,
    /// Stage 2 trains the field too (joint training): the run's final evaluation no longer
    /// shows the field stage 1 left, so stage 1's last point is measured as that stage ends.
    joint: bool,
    stage_start: Instant,
    stage1_eval: f64,
    stage2_eval: f64,
    curves: Curves,
    /// The run's log lines, as `sos train` prints them without a terminal.
    console: Console,
}

impl CurveRecorder {
    fn new(points: usize, session: &Session, stage2: bool) -> CurveRecorder {
        CurveRecorder {
            points,
            stage1_steps: session.config.train.steps,
            stage2_steps: if stage2 { session.config.segment.steps } else { 0 },
            joint: stage2 && session.config.segment.photometric_weight > 0.0,
            stage_start: Instant::now(),
            stage1_eval: 0.0,
            stage2_eval: 0.0,
            curves: Curves::default(),
            console: Console::new(false),
        }
    }

    /// Starts a stage's training clock.
    fn begin_stage(&mut self) {
        self.stage_start = Instant::now();
    }

    /// Whether `step` (1-based, of `total`) is a sampled step other than the last.
    fn sampled(&self, step: usize, total: usize) -> bool {
        self.points > 1 && step < total && (1..self.points).any(|i| (total * i).div_ceil(self.points) == step)
    }

    /// The final points, from the run's own evaluation (stage 1's only when `stage1_done` is
    /// false, as a shared stage 1's curve already ends with it, and stage 2 left the field as
    /// stage 1 did).
    fn finish(&mut self, metrics: &Metrics, stage1_seconds: f64, stage2_seconds: f64, stage1_done: bool) {
        if self.points == 0 {
            return;
        }
        if !stage1_done && !self.joint {
            self.curves.stage1.push(Stage1Point {
                step: self.stage1_steps,
                seconds: stage1_seconds,
                psnr: metrics.psnr,
            });
        }
        if self.stage2_steps > 0 {
            self.curves.stage2.push(Stage2Point {
                step: self.stage2_steps,
                seconds: stage2_seconds,
                miou: metrics.miou,
                nv_ari: metrics.nv_ari,
            });
        }
    }
}

impl TrainObserver for CurveRecorder {
    fn stage_begins(&mut self, stage: Stage, step: usize, total: usize) {
        self.console.stage_begins(stage, step, total);
    }

    fn message(&mut self, severity: Severity, text: &str) {
        self.console.message(severity, text);
    }

    fn stage_ends(&mut self, stage: Stage) {
        self.console.stage_ends(stage);
    }

    fn stage1_step(&mut self, session: &Session, stats: &StepStats) -> Result<(), RunError> {
        self.console.stage1_step(session, stats)?;
        let last_before_joint = self.joint && self.points > 0 && session.step == self.stage1_steps;
        if !(self.sampled(session.step, self.stage1_steps) || last_before_joint) {
            return Ok(());
        }
        let t = Instant::now();
        let seconds = self.stage_start.elapsed().as_secs_f64() - self.stage1_eval;
        let eval = evaluate_views(session, false)?;
        self.curves.stage1.push(Stage1Point {
            step: session.step,
            seconds,
            psnr: eval.psnr.is_finite().then_some(eval.psnr),
        });
        self.stage1_eval += t.elapsed().as_secs_f64();
        Ok(())
    }

    fn stage2_step(&mut self, session: &Session, seg: &Segmenter, stats: &SegStepStats) -> Result<(), RunError> {
        self.console.stage2_step(session, seg, stats)?;
        if !self.sampled(seg.step, self.stage2_steps) {
            return Ok(());
        }
        let t = Instant::now();
        let seconds = self.stage_start.elapsed().as_secs_f64() - self.stage2_eval;
        let inference = MaskInference::new(session, &seg.head, Some(seg.teacher.extractor()))?;
        let eval = evaluate_masks(session, &inference, false)?;
        let mut ignored = Vec::new();
        let m = mask_metrics(&eval, &mut ignored);
        self.curves.stage2.push(Stage2Point { step: seg.step, seconds, miou: m.miou, nv_ari: m.nv_ari });
        self.stage2_eval += t.elapsed().as_secs_f64();
        Ok(())
    }
}
