//! Cost of a stage-2 step with a ViT-S/16 teacher (random weights) against the weight-free
//! `cell-stats` teacher, with the teacher-feature cache, and `teacher_source = "rendered"`
//! against `"captured"`.
//!
//! `cargo run --release -p sos-benchmarks --bin vit_stage2 [STAGE1_STEPS] [TIMED_STEPS] [--miou STEPS]`
//! (defaults 600 and 10). A short stage 1 on the built-in synthetic scene (400x300, 35
//! training views), then for each (teacher, source), from the same frozen field:
//! - cold: `TIMED_STEPS` stage-2 steps (8 patches of 64x64 rays); patch offsets are drawn per
//!   step, so these are cache misses;
//! - warm: the same steps again (the sampler and step counter rewound, so the same patches
//!   come back): every teacher lookup hits the cache, as in a long run whose placements
//!   repeat.
//!
//! Prints wall-clock and process CPU seconds per step and the ratios to `cell-stats` (CPU
//! time does not count time taken by other processes, but it counts the thread pools' idle
//! spinning, which grows when the machine is shared). With `SOS_PROFILE=1` each step also
//! prints its phases, the teacher's among them. With `--miou STEPS` it also
//! trains the head for STEPS steps with `cell-stats` from rendered and from captured
//! patches and reports the held-out mIoU of each (`focus` foreground rule).
//! Threads: `RAYON_NUM_THREADS` (default 2).

use std::path::Path;
use std::time::Instant;

use sos_backbones::dino_vit::{DinoVit, Preprocess, Vit, VitShape};
use sos_benchmarks::{load_average, process_cpu_seconds};
use sos_core::config::{RunConfig, TeacherSource};
use sos_core::plugin::FeatureExtractor;
use sos_core::segment::evaluate::evaluate_masks;
use sos_core::segment::infer::MaskInference;
use sos_core::segment::teacher::Teacher;
use sos_core::segment::train::{train_segmentation, Segmenter};
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

fn extractor(kind: Kind) -> Box<dyn FeatureExtractor> {
    match kind {
        Kind::CellStats => Box::new(sos_backbones::CellStats::new(Default::default()).expect("defaults are valid")),
        Kind::VitS16 => Box::new(DinoVit::new(
            Vit::random(VitShape::dino(384, 16, 12, 6), 11),
            Preprocess::reference(16),
            "random-vits16".into(),
            8,
        )),
    }
}

/// Wall and CPU seconds of one timed section.
#[derive(Clone, Copy)]
struct Timing {
    wall: f64,
    cpu: f64,
}

fn timed(f: impl FnOnce()) -> Timing {
    let (t, c) = (Instant::now(), process_cpu_seconds().unwrap_or(f64::NAN));
    f();
    Timing { wall: t.elapsed().as_secs_f64(), cpu: process_cpu_seconds().unwrap_or(f64::NAN) - c }
}

/// Seconds per step of `steps` steps (wall, CPU), then of the same steps again (all cache hits).
fn time_steps(session: &mut Session, kind: Kind, source: TeacherSource, steps: usize) -> (Timing, Timing, usize, usize) {
    session.config.segment.teacher_source = source;
    session.config.segment.steps = steps;
    let mut seg = Segmenter::build(session).expect("stage 2 builds");
    seg.teacher = Teacher::new(extractor(kind), source, true);
    let sampler = seg.sampler.clone();
    let per_step = |t: Timing| Timing { wall: t.wall / steps as f64, cpu: t.cpu / steps as f64 };
    let cold = per_step(timed(|| {
        train_segmentation(session, &mut seg, false).expect("stage 2 runs");
    }));
    let misses = seg.teacher.misses;
    seg.step = 0;
    seg.sampler = sampler;
    let warm = per_step(timed(|| {
        train_segmentation(session, &mut seg, false).expect("stage 2 runs");
    }));
    (cold, warm, misses, seg.teacher.hits)
}

fn miou(session: &mut Session, source: TeacherSource, steps: usize) -> (f64, f64, f64) {
    session.config.segment.teacher_source = source;
    session.config.segment.steps = steps;
    let mut seg = Segmenter::build(session).expect("stage 2 builds");
    let t = Instant::now();
    train_segmentation(session, &mut seg, false).expect("stage 2 runs");
    let seconds = t.elapsed().as_secs_f64();
    let inference = MaskInference::new(session, &seg.head, None).expect("mask inference");
    let eval = evaluate_masks(session, &inference, false).expect("evaluation");
    let report = serde_json::to_value(&eval.segmentation).expect("report serialises");
    let get = |k: &str| report.get(k).and_then(|v| v.as_f64()).unwrap_or(f64::NAN);
    (seconds, get("miou"), get("mean_ari"))
}

fn main() {
    let threads: usize = std::env::var("RAYON_NUM_THREADS").ok().and_then(|s| s.parse().ok()).unwrap_or(2);
    rayon::ThreadPoolBuilder::new().num_threads(threads).build_global().expect("rayon pool");
    let args: Vec<String> = std::env::args().skip(1).collect();
    let miou_steps = args.iter().position(|a| a == "--miou").and_then(|i| args.get(i + 1)).and_then(|s| s.parse().ok());
    let positional: Vec<usize> = args.iter().take_while(|a| *a != "--miou").filter_map(|s| s.parse().ok()).collect();
    let stage1 = positional.first().copied().unwrap_or(600);
    let timed = positional.get(1).copied().unwrap_or(10).max(1);

    let mut config = RunConfig::parse(CONFIG, Path::new("vit_stage2.toml")).expect("built-in config parses");
    config.train.steps = stage1;
    let dir = std::env::temp_dir().join(format!("sos-vit-stage2-{}", std::process::id()));
    let mut session = Session::from_config(config, &dir).expect("synthetic scene builds");
    let t = Instant::now();
    let stats = train_photometric(&mut session, false).expect("stage 1 runs");
    println!("stage 1: {stage1} steps in {:.1} s (last batch PSNR {:.2} dB)", t.elapsed().as_secs_f64(), stats.psnr);
    println!(
        "stage 2: 8 patches of 64x64 rays per step, {timed} timed steps per row, {threads} threads (load average {:.1})",
        load_average().unwrap_or(f64::NAN)
    );
    println!(
        "{:<20} {:<9} {:>15} {:>15} {:>15} {:>15} {:>10}",
        "teacher", "source", "cold wall s/st", "warm wall s/st", "cold CPU s/st", "warm CPU s/st", "miss/hit"
    );
    let mut base: Option<(Timing, Timing)> = None;
    let mut rows = Vec::new();
    for (kind, name) in [(Kind::CellStats, "cell-stats"), (Kind::VitS16, "ViT-S/16 (random)")] {
        for source in [TeacherSource::Rendered, TeacherSource::Captured] {
            let (cold, warm, misses, hits) = time_steps(&mut session, kind, source, timed);
            let src = if source == TeacherSource::Rendered { "rendered" } else { "captured" };
            println!(
                "{name:<20} {src:<9} {:>15.3} {:>15.3} {:>15.3} {:>15.3} {:>10}",
                cold.wall,
                warm.wall,
                cold.cpu,
                warm.cpu,
                format!("{misses}/{hits}")
            );
            if kind == Kind::CellStats && source == TeacherSource::Rendered {
                base = Some((cold, warm));
            }
            rows.push((name, src, cold, warm));
        }
    }
    let (bc, bw) = base.expect("cell-stats row");
    for (name, src, cold, warm) in &rows {
        if name.starts_with("ViT") {
            println!(
                "{name} {src} vs cell-stats rendered: cold {:.2}x wall / {:.2}x CPU, warm (all cached) {:.2}x wall / {:.2}x CPU \
                 (target <= 1.3x with the cache)",
                cold.wall / bc.wall,
                cold.cpu / bc.cpu,
                warm.wall / bw.wall,
                warm.cpu / bw.cpu
            );
        }
    }
    if let Some(steps) = miou_steps {
        println!("mIoU after {steps} stage-2 steps with cell-stats (held-out views, `focus` rule):");
        for source in [TeacherSource::Rendered, TeacherSource::Captured] {
            let (seconds, miou, ari) = miou(&mut session, source, steps);
            let src = if source == TeacherSource::Rendered { "rendered" } else { "captured" };
            println!("  {src:<9} {seconds:>7.1} s  mIoU {miou:.3}  ARI {ari:.3}");
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}
