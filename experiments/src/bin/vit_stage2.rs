//! Cost of a stage-2 step with a ViT-S/16 teacher (random weights) against the weight-free
//! `cell-stats` teacher, with the teacher-feature cache and patch offsets on the default
//! `segment.offset_grid`, for `teacher_source = "rendered"` and `"captured"`.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin vit_stage2 [STAGE1_STEPS] [TIMED_STEPS] [--run STEPS] [--miou STEPS]`
//! (defaults 600, 10 and a run of 300 steps). A short stage 1 on
//! the built-in synthetic scene (400x300, 35 training views), then:
//! - the cache hit rate of a stage-2 run of RUN steps (8 patches of 64x64 rays per step), over
//!   the whole run and over its second half, with the default offset grid and with any-pixel
//!   offsets. The patch sampler draws from its own seeded generator, so this is exact for the
//!   run and needs no rendering;
//! - TIMED_STEPS steps per row, from the same frozen field, of two kinds:
//!   - cold: the first steps of a run, with an empty cache (all misses);
//!   - steady: the steps from RUN/2 on, with the cache as the first RUN/2 steps left it. Before
//!     the clock starts, the cache is given the features of exactly those upcoming patches that
//!     the first half drew, so the timed steps hit and miss as in the middle of a real run.
//!
//!   Rows: `cell-stats` steady (its cold steps cost the same), ViT cold and steady with
//!   rendered patches, and both teachers steady with captured ones.
//!
//! Prints wall-clock and process CPU seconds per step, the extractor's seconds per step, the
//! hits and misses, and the ratios ViT / `cell-stats` (target: steady <= 1.3). Whole steps
//! swing with the load of a shared machine; the "teacher-phase" ratio, `cell-stats` step plus
//! the extra extractor time, is the steadier estimate. CPU time does not count other
//! processes but counts thread pools' idle spinning. With `SOS_PROFILE=1` each step prints its
//! phases. With `--miou STEPS` it also trains the head for STEPS steps with `cell-stats` from
//! rendered and from captured patches and reports the held-out mIoU of each (`focus` rule).
//! Threads: `RAYON_NUM_THREADS` (default 2).

use std::collections::HashSet;
use std::path::Path;
use std::time::Instant;

use sos_backbones::dino_vit::{DinoVit, Preprocess, Vit, VitShape};
use sos_benchmarks::{load_average, process_cpu_seconds};
use sos_core::config::{RunConfig, SegmentConfig, TeacherSource};
use sos_core::plugin::FeatureExtractor;
use sos_core::segment::evaluate::evaluate_masks;
use sos_core::segment::infer::MaskInference;
use sos_core::segment::patches::Patch;
use sos_core::segment::teacher::Teacher;
use sos_core::segment::train::{render_patches, train_segmentation, Segmenter};
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;
use sos_plugins as _;

const CONFIG: &str = r#"
name = "vit-stage2"
output_dir = "runs"
seed = 0
[scene]
kind = "synthetic"
rig = "object-centric"
width = 400
height = 300
views = 40
hold_out_every = 8
[field]
kind = "voxel-grid"
[train]
checkpoint_every = 0
[segment]
steps = 0
[masks]
foreground = "focus"
"#;

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    CellStats,
    VitS16,
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::CellStats => "cell-stats",
            Kind::VitS16 => "ViT-S/16 (random)",
        }
    }

    fn extractor(self) -> Box<dyn FeatureExtractor> {
        match self {
            Kind::CellStats => Box::new(sos_backbones::CellStats::new(Default::default()).expect("defaults are valid")),
            Kind::VitS16 => Box::new(DinoVit::new(
                Vit::random(VitShape::dino(384, 16, 12, 6), 11),
                Preprocess::reference(16),
                "random-vits16".into(),
                8,
            )),
        }
    }
}

/// Which steps of a run are timed.
#[derive(Clone, Copy, PartialEq)]
enum Phase {
    /// The first steps, empty cache.
    Cold,
    /// Steps from the middle of the run on, with the cache the first half filled.
    Steady,
}

impl Phase {
    fn name(self) -> &'static str {
        match self {
            Phase::Cold => "cold",
            Phase::Steady => "steady",
        }
    }
}

fn source_name(source: TeacherSource) -> &'static str {
    match source {
        TeacherSource::Rendered => "rendered",
        TeacherSource::Captured => "captured",
    }
}

/// Per-step costs of some timed steps.
#[derive(Clone, Copy)]
struct Timing {
    wall: f64,
    cpu: f64,
    teacher: f64,
    hits: usize,
    misses: usize,
}

/// Runs `seg` (from step 0) for `steps` steps and times them.
fn time_steps(session: &mut Session, seg: &mut Segmenter, steps: usize) -> Timing {
    session.config.segment.steps = steps;
    let (t, c) = (Instant::now(), process_cpu_seconds().unwrap_or(f64::NAN));
    train_segmentation(session, seg).expect("stage 2 runs");
    let n = steps as f64;
    Timing {
        wall: t.elapsed().as_secs_f64() / n,
        cpu: (process_cpu_seconds().unwrap_or(f64::NAN) - c) / n,
        teacher: seg.teacher.seconds / n,
        hits: seg.teacher.hits,
        misses: seg.teacher.misses,
    }
}

/// A fresh stage 2 with the given teacher and an empty cache.
fn segmenter(session: &mut Session, kind: Kind, source: TeacherSource) -> Segmenter {
    session.config.segment.teacher_source = source;
    let mut seg = Segmenter::build(session).expect("stage 2 builds");
    seg.teacher = Teacher::new(kind.extractor(), source, true);
    seg
}

/// The first `steps` steps of a run.
fn cold(session: &mut Session, kind: Kind, source: TeacherSource, steps: usize) -> Timing {
    let mut seg = segmenter(session, kind, source);
    time_steps(session, &mut seg, steps)
}

/// `steps` steps from step `from` of a run, with the cache as steps `0..from` left it.
fn steady(session: &mut Session, kind: Kind, source: TeacherSource, from: usize, steps: usize) -> Timing {
    let mut seg = segmenter(session, kind, source);
    let n = session.config.segment.patches;
    let mut earlier = HashSet::new();
    for _ in 0..from {
        earlier.extend(seg.sampler.next_batch(&session.scene, n));
    }
    seg.sampler.take_notices();
    // The upcoming patches that the first part of the run already cached.
    let mut ahead = seg.sampler.clone();
    let mut cached: Vec<Patch> = Vec::new();
    for p in (0..steps).flat_map(|_| ahead.next_batch(&session.scene, n)) {
        if earlier.contains(&p) && !cached.contains(&p) {
            cached.push(p);
        }
    }
    let rendered = match source {
        TeacherSource::Rendered => render_patches(session, &cached),
        TeacherSource::Captured => Vec::new(),
    };
    seg.teacher.features(&session.scene, &cached, &rendered, true).expect("teacher runs");
    (seg.teacher.hits, seg.teacher.misses, seg.teacher.seconds) = (0, 0, 0.0);
    time_steps(session, &mut seg, steps)
}

/// Cache hit rates of a `run`-step stage 2 with offsets on `grid` (whole run, second half)
/// and the placements per view: the run's own patch sampler, drawn ahead.
fn hit_rates(session: &mut Session, grid: u32, run: usize) -> (f64, f64, u64) {
    let configured = session.config.segment.offset_grid;
    session.config.segment.offset_grid = grid;
    let mut sampler = Segmenter::build(session).expect("stage 2 builds").sampler;
    session.config.segment.offset_grid = configured;
    let (scene, patches) = (&session.scene, session.config.segment.patches);
    let mut seen = HashSet::new();
    let (mut hits, mut late_hits) = (0usize, 0usize);
    for step in 0..run {
        for p in sampler.next_batch(scene, patches) {
            if !seen.insert(p) {
                hits += 1;
                late_hits += usize::from(step >= run / 2);
            }
        }
    }
    let cam = &scene.views[scene.train[0]].camera;
    let placements = sampler.placements(cam.width, cam.height).unwrap_or(0);
    let draws = |steps: usize| (steps * patches).max(1) as f64;
    (hits as f64 / draws(run), late_hits as f64 / draws(run - run / 2), placements)
}

fn miou(session: &mut Session, source: TeacherSource, steps: usize) -> (f64, f64, f64) {
    session.config.segment.teacher_source = source;
    session.config.segment.steps = steps;
    let mut seg = Segmenter::build(session).expect("stage 2 builds");
    let t = Instant::now();
    train_segmentation(session, &mut seg).expect("stage 2 runs");
    let seconds = t.elapsed().as_secs_f64();
    let inference = MaskInference::new(session, &seg.head, None).expect("mask inference");
    let eval = evaluate_masks(session, &inference, false).expect("evaluation");
    let report = serde_json::to_value(&eval.segmentation).expect("report serialises");
    let get = |k: &str| report.get(k).and_then(|v| v.as_f64()).unwrap_or(f64::NAN);
    (seconds, get("miou"), get("mean_ari"))
}

/// The value after `flag`, if any.
fn option(args: &[String], flag: &str) -> Option<usize> {
    args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).and_then(|s| s.parse().ok())
}

fn main() {
    let threads = sos_benchmarks::setup();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let miou_steps = option(&args, "--miou");
    let run = option(&args, "--run").unwrap_or(SegmentConfig::default().steps).max(2);
    let positional: Vec<usize> =
        args.iter().take_while(|a| !a.starts_with("--")).filter_map(|s| s.parse().ok()).collect();
    let stage1 = positional.first().copied().unwrap_or(600);
    let timed = positional.get(1).copied().unwrap_or(10).max(1);

    let mut config = RunConfig::parse(CONFIG, Path::new("vit_stage2.toml")).expect("built-in config parses");
    config.train.steps = stage1;
    let dir = std::env::temp_dir().join(format!("sos-vit-stage2-{}", std::process::id()));
    let mut session = Session::from_config(config, &dir).expect("synthetic scene builds");
    let t = Instant::now();
    let stats = train_photometric(&mut session).expect("stage 1 runs");
    println!("stage 1: {stage1} steps in {:.1} s (last batch PSNR {:.2} dB)", t.elapsed().as_secs_f64(), stats.psnr);

    println!(
        "teacher cache over a {run}-step stage 2 ({} patches per step, {} training views), from the sampler alone:",
        session.config.segment.patches,
        session.scene.train.len()
    );
    for grid in [session.config.segment.offset_grid, 1] {
        let (all, late, placements) = hit_rates(&mut session, grid, run);
        println!(
            "  offset_grid {grid:>2}: {placements:>5} placements per view, hit rate {:.0} % over the run, {:.0} % in its second half",
            100.0 * all,
            100.0 * late
        );
    }

    println!(
        "stage 2: {timed} timed steps per row (cold: from step 0, empty cache; steady: from step {} of {run}), \
         {threads} threads (load average {:.1})",
        run / 2,
        load_average().unwrap_or(f64::NAN)
    );
    println!(
        "{:<18} {:<9} {:<7} {:>10} {:>10} {:>12} {:>9}",
        "teacher", "source", "steps", "wall s/st", "CPU s/st", "teacher s/st", "hit/miss"
    );
    // `cell-stats` costs the same cold or steady (its extractor takes ~1 ms a step): it is
    // timed once per source, as is the ViT's cold phase (the same extractor work whatever
    // the source).
    let plan = [
        (TeacherSource::Rendered, Kind::CellStats, Phase::Steady),
        (TeacherSource::Rendered, Kind::VitS16, Phase::Cold),
        (TeacherSource::Rendered, Kind::VitS16, Phase::Steady),
        (TeacherSource::Captured, Kind::CellStats, Phase::Steady),
        (TeacherSource::Captured, Kind::VitS16, Phase::Steady),
    ];
    let mut rows = Vec::new();
    for (source, kind, phase) in plan {
        let t = match phase {
            Phase::Cold => cold(&mut session, kind, source, timed),
            Phase::Steady => steady(&mut session, kind, source, run / 2, timed),
        };
        println!(
            "{:<18} {:<9} {:<7} {:>10.3} {:>10.3} {:>12.3} {:>9}",
            kind.name(),
            source_name(source),
            phase.name(),
            t.wall,
            t.cpu,
            t.teacher,
            format!("{}/{}", t.hits, t.misses)
        );
        rows.push((source, kind, phase, t));
    }
    let find = |source: TeacherSource, kind: Kind, phase: Phase| {
        rows.iter().find(|r| (r.0, r.1, r.2) == (source, kind, phase)).map(|r| r.3).expect("planned row")
    };
    // The base step plus the ViT's extra extractor time: insensitive to load swings of the
    // rendering and backward phases, which dominate a step.
    let phase_ratio = |b: Timing, v: Timing| (b.wall + v.teacher - b.teacher) / b.wall;
    for (source, phase) in [
        (TeacherSource::Rendered, Phase::Steady),
        (TeacherSource::Captured, Phase::Steady),
        (TeacherSource::Rendered, Phase::Cold),
    ] {
        let (base, vit) = (find(source, Kind::CellStats, Phase::Steady), find(source, Kind::VitS16, phase));
        println!(
            "ViT-S/16 / cell-stats, {} {}: {:.2}x wall, {:.2}x CPU, {:.2}x by the teacher phase{}",
            source_name(source),
            phase.name(),
            vit.wall / base.wall,
            vit.cpu / base.cpu,
            phase_ratio(base, vit),
            if phase == Phase::Steady { " (target <= 1.3x)" } else { "" }
        );
    }
    println!("load average {:.1} at the end", load_average().unwrap_or(f64::NAN));

    if let Some(steps) = miou_steps {
        println!("mIoU after {steps} stage-2 steps with cell-stats (held-out views, `focus` rule):");
        for source in [TeacherSource::Rendered, TeacherSource::Captured] {
            let (seconds, miou, ari) = miou(&mut session, source, steps);
            println!("  {:<9} {seconds:>7.1} s  mIoU {miou:.3}  ARI {ari:.3}", source_name(source));
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}
