//! Stage-2 steps of the `nerf` field (reference sizes) with and without skipping, from a
//! stage-1 checkpoint of `configs/nerf_synthetic_small.toml` (the default) or one that
//! `nerf_distill` (`sos-tools`) made for the same scene.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin nerf_stage2 -- speed [checkpoint] [steps]`
//! times real stage-2 steps (`train_segmentation`: render, head, teacher, losses, backward)
//! of 8 patches of 64x64 rays in these modes:
//! - `all-skips`: occupancy grid baked from the frozen density (128³, one cell of margin),
//!   early ray termination (transmittance 1e-4), weight threshold 1e-3, fine network alone on
//!   the occupancy-skipped candidates (`hierarchical = false`, 192 candidates per ray);
//! - `no-weight-threshold`, `no-early-termination`, `no-occupancy`: the same with one skip
//!   switched off;
//! - `all-skips-hierarchical`: every skip, but with the coarse network and 128 importance
//!   samples kept;
//! - `no-skipping`: the reference pipeline (coarse + fine, no occupancy, no termination, no
//!   threshold) with ONE patch, as the reference's 41 s figure is for one patch (eight would
//!   need about 9 GB for the head's inputs alone);
//! - `weight-threshold-only`, `uniform-no-skipping`, `uniform-weight-threshold-only` (one
//!   patch): the reference pipeline with weight thresholding alone, and the fine network alone
//!   on 192 uniform candidates without skipping and with weight thresholding alone.
//!
//! `NERF_STAGE2_MODES=a,b` picks modes by name.
//!
//! `... nerf_stage2 -- quality [checkpoint] [steps]` trains stage 2 on the small scene (4
//! patches of 24x24 rays) in each mode (`NERF_STAGE2_MODES`, default every skip and none) for
//! each seed (`NERF_STAGE2_SEEDS`, default `0,1`), evaluates the masks of the held-out views
//! under the training run's settings, and prints each mode's mIoU minus the first mode's.
//!
//! `... nerf_stage2 -- head [checkpoint] [repeats]` times the render and the head phase (head
//! forward and backward) of one 64x64 patch apart in each mode; `... -- weights [checkpoint]`
//! shows how the compositing weight is spread over each ray's samples;
//! `... -- density [checkpoint]` prints quantiles of the frozen density.
//!
//! Wall time depends on what else runs on the machine; each line also gives the process's CPU
//! seconds per step and the load average.

use std::path::{Path, PathBuf};
use std::time::Instant;

use sos_core::config::RunConfig;
use sos_core::segment::evaluate::evaluate_masks;
use sos_core::segment::infer::MaskInference;
use sos_core::segment::train::{train_segmentation, Segmenter};
use sos_core::train::Session;

use sos_plugins as _;

/// Settings of one mode.
#[derive(Clone, Copy)]
struct Mode {
    name: &'static str,
    hierarchical: bool,
    occupancy: bool,
    early_stop: f32,
    weight_threshold: f32,
    patches: usize,
    patch_size: u32,
}

const ALL_SKIPS: Mode = Mode {
    name: "all-skips",
    hierarchical: false,
    occupancy: true,
    early_stop: 1e-4,
    weight_threshold: 1e-3,
    patches: 8,
    patch_size: 64,
};

fn config_text(mode: &Mode, steps: usize) -> String {
    format!(
        r#"
name = "nerf-stage2-{name}"
output_dir = "runs"
seed = 0
[scene]
kind = "synthetic"
rig = "object-centric"
width = 160
height = 120
views = 40
hold_out_every = 8
[field]
kind = "nerf"
hierarchical = {hierarchical}
[train]
steps = 800
samples_per_ray = 192
early_stop = {early_stop}
weight_threshold = 0.0
occupancy = {occupancy}
occupancy_resolution = 128
occupancy_warmup = 0
checkpoint_every = 0
[render]
chunk = 2048
[segment]
# The mode's skips hold for the frozen renders too (the segment defaults would drop the
# proposal network and terminate rays whatever the mode says).
proposal = {hierarchical}
early_stop = {early_stop}
steps = {steps}
patches = {patches}
patch_size = {patch_size}
weight_threshold = {weight_threshold}
[masks]
foreground = "focus"
"#,
        name = mode.name,
        hierarchical = mode.hierarchical,
        early_stop = mode.early_stop,
        occupancy = mode.occupancy,
        patches = mode.patches,
        patch_size = mode.patch_size,
        weight_threshold = mode.weight_threshold,
    )
}

/// Process CPU seconds (user + system); 0 where unavailable.
fn cpu_seconds() -> f64 {
    sos_benchmarks::process_cpu_seconds().unwrap_or(0.0)
}

fn load_average() -> String {
    sos_benchmarks::load_average().map_or_else(|| "?".to_string(), |l| l.to_string())
}

fn open(mode: &Mode, steps: usize, checkpoint: &Path) -> Session {
    let config = RunConfig::parse(&config_text(mode, steps), Path::new("nerf_stage2.toml")).expect("config parses");
    let dir = std::env::temp_dir().join("sos-nerf-stage2");
    let mut session = Session::from_config(config, &dir).expect("scene builds");
    let t = Instant::now();
    session.load_checkpoint(Some(checkpoint)).expect("stage-1 checkpoint of configs/nerf_synthetic_small.toml");
    if let Some(occ) = &session.occupancy {
        eprintln!(
            "{}: occupancy grid baked in {:.1} s: {:.1}% of {}³ cells occupied",
            mode.name,
            t.elapsed().as_secs_f64(),
            100.0 * occ.occupancy(),
            occ.resolution()
        );
    }
    session
}

fn speed(checkpoint: &Path, steps: usize) {
    // The reference pipeline without skipping runs ONE patch, as the reference's 41 s figure
    // is for one patch (eight would need about 9 GB for the head's inputs alone); so does
    // uniform sampling without skipping, for the same reason.
    let one_patch = ["no-skipping", "weight-threshold-only", "uniform-no-skipping", "uniform-weight-threshold-only"];
    let modes: Vec<Mode> = selected_modes(&[
        "all-skips",
        "no-weight-threshold",
        "no-early-termination",
        "no-occupancy",
        "all-skips-hierarchical",
        "no-skipping",
    ])
    .into_iter()
    .map(|m| if one_patch.contains(&m.name) { Mode { patches: 1, ..m } } else { m })
    .collect();
    println!("nerf_stage2 speed: checkpoint {}, {steps} timed step(s) per mode after 1 warm-up", checkpoint.display());
    println!("| mode | patches | rays | s/step (wall) | CPU s/step | head samples/ray | load avg |");
    println!("|---|---|---|---|---|---|---|");
    for mode in &modes {
        let mut session = open(mode, 1, checkpoint);
        let mut seg = Segmenter::build(&session).expect("stage 2 builds");
        session.config.segment.steps = 1;
        train_segmentation(&mut session, &mut seg).expect("warm-up step");
        let (mut wall, mut cpu, mut per_ray) = (Vec::new(), Vec::new(), 0.0);
        for _ in 0..steps {
            session.config.segment.steps = seg.step + 1;
            let (t, c) = (Instant::now(), cpu_seconds());
            let stats = train_segmentation(&mut session, &mut seg).expect("stage-2 step");
            wall.push(t.elapsed().as_secs_f64());
            cpu.push(cpu_seconds() - c);
            per_ray = stats.samples_per_ray;
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let rays = mode.patches * (mode.patch_size * mode.patch_size) as usize;
        println!(
            "| {} | {} | {} | {:.2} | {:.2} | {:.1} | {} |",
            mode.name,
            mode.patches,
            rays,
            mean(&wall),
            mean(&cpu),
            per_ray,
            load_average()
        );
    }
}

/// Every named mode (8 patches of 64x64; `quality` shrinks the batch).
fn catalogue() -> Vec<Mode> {
    let no_skip = Mode {
        name: "no-skipping",
        hierarchical: true,
        occupancy: false,
        early_stop: 0.0,
        weight_threshold: 0.0,
        ..ALL_SKIPS
    };
    vec![
        ALL_SKIPS,
        Mode { name: "no-weight-threshold", weight_threshold: 0.0, ..ALL_SKIPS },
        Mode { name: "no-early-termination", early_stop: 0.0, ..ALL_SKIPS },
        Mode { name: "no-occupancy", occupancy: false, ..ALL_SKIPS },
        Mode { name: "all-skips-hierarchical", hierarchical: true, ..ALL_SKIPS },
        no_skip,
        Mode { name: "weight-threshold-only", weight_threshold: 1e-3, ..no_skip },
        Mode { name: "uniform-no-skipping", hierarchical: false, ..no_skip },
        Mode { name: "uniform-weight-threshold-only", hierarchical: false, weight_threshold: 1e-3, ..no_skip },
    ]
}

/// The modes named in `NERF_STAGE2_MODES` (comma-separated), in that order, or `default`.
fn selected_modes(default: &[&str]) -> Vec<Mode> {
    let names: Vec<String> = match std::env::var("NERF_STAGE2_MODES") {
        Ok(v) => v.split(',').map(str::to_owned).collect(),
        Err(_) => default.iter().map(|s| s.to_string()).collect(),
    };
    names.iter().map(|n| mode_named(n)).collect()
}

/// The catalogue's mode called `name`; an unknown name stops the run (exit code 2).
fn mode_named(name: &str) -> Mode {
    let all = catalogue();
    *all.iter().find(|m| m.name == name).unwrap_or_else(|| {
        let known: Vec<&str> = all.iter().map(|m| m.name).collect();
        eprintln!("unknown mode `{name}` in NERF_STAGE2_MODES; known: {}", known.join(", "));
        std::process::exit(2);
    })
}

/// The 64x64 patch of rays the `head` and `weights` probes render: training view 0, from
/// pixel (40, 28).
fn probe_patch(session: &Session) -> sos_core::render::rays::RayBatch {
    use sos_core::render::rays::PatchGrid;
    use sos_core::segment::patches::{patch_rays, Patch};
    let grid = PatchGrid { col0: 40, row0: 28, size: 64, stride: 1 };
    patch_rays(&session.scene, &[Patch { view: session.scene.train[0], grid }])
}

/// Trains stage 2 on the small scene (4 patches of 24x24) in each mode for each seed and
/// evaluates the held-out masks under the training mode's settings. The modes come from
/// `NERF_STAGE2_MODES` (default: `all-skips,no-skipping`), the seeds from `NERF_STAGE2_SEEDS`
/// (default `0,1`); the last table gives each mode's mIoU minus the first mode's, seed by seed.
fn quality(checkpoint: &Path, steps: usize) {
    let modes: Vec<Mode> = selected_modes(&["all-skips", "no-skipping"])
        .into_iter()
        .map(|m| Mode { patches: 4, patch_size: 24, ..m })
        .collect();
    let seeds: Vec<u64> = std::env::var("NERF_STAGE2_SEEDS")
        .ok()
        .map(|v| v.split(',').filter_map(|s| s.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![0, 1]);
    println!(
        "nerf_stage2 quality: checkpoint {}, {steps} stage-2 steps of 4 patches of 24x24 rays per run",
        checkpoint.display()
    );
    println!("| seed | mode | train s | masks s | ARI | IoU BG | IoU FG | mIoU | PSNR |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.4}"));
    let mut miou = vec![vec![f64::NAN; modes.len()]; seeds.len()];
    for (si, &seed) in seeds.iter().enumerate() {
        for (mi, mode) in modes.iter().enumerate() {
            let mut session = open(mode, steps, checkpoint);
            session.config.seed = seed;
            let mut seg = Segmenter::build(&session).expect("stage 2 builds");
            let t = Instant::now();
            train_segmentation(&mut session, &mut seg).expect("stage 2 trains");
            let train_s = t.elapsed().as_secs_f64();
            let inference = MaskInference::new(&session, &seg.head, Some(seg.teacher.extractor())).expect("inference");
            let eval = evaluate_masks(&session, &inference, false).expect("masks");
            let iou = eval.segmentation.iou();
            miou[si][mi] = iou.miou.unwrap_or(f64::NAN);
            println!(
                "| {seed} | {} | {:.0} | {:.0} | {} | {} | {} | {} | {} |",
                mode.name,
                train_s,
                eval.seconds,
                f(eval.segmentation.mean_ari()),
                f(iou.iou_bg),
                f(iou.iou_fg),
                f(iou.miou),
                eval.image.mean_psnr().map_or("-".into(), |p| format!("{p:.2}"))
            );
        }
    }
    println!("\nmIoU minus `{}`'s, seed by seed, then the mean:", modes[0].name);
    for (mi, mode) in modes.iter().enumerate().skip(1) {
        let diffs: Vec<f64> = miou.iter().map(|row| row[mi] - row[0]).collect();
        let mean = diffs.iter().sum::<f64>() / diffs.len().max(1) as f64;
        let listed: Vec<String> = diffs.iter().map(|d| format!("{d:+.4}")).collect();
        println!("  {}: {} | mean {mean:+.4}", mode.name, listed.join(" "));
    }
}

/// One head trained with every skip (seed 0), its masks rendered under each skip setting:
/// which skip moves the masks.
fn inference_skips(checkpoint: &Path, steps: usize) {
    let small = |m: Mode| Mode { patches: 4, patch_size: 24, ..m };
    let skips = small(ALL_SKIPS);
    let none = Mode {
        name: "no-skipping",
        hierarchical: true,
        occupancy: false,
        early_stop: 0.0,
        weight_threshold: 0.0,
        ..skips
    };
    let renders = [
        skips,
        Mode { name: "all-skips-hierarchical", hierarchical: true, ..skips },
        Mode {
            name: "occupancy-only-hierarchical",
            early_stop: 0.0,
            weight_threshold: 0.0,
            ..Mode { hierarchical: true, ..skips }
        },
        Mode {
            name: "early-termination-only-hierarchical",
            occupancy: false,
            weight_threshold: 0.0,
            ..Mode { hierarchical: true, ..skips }
        },
        Mode {
            name: "weight-threshold-only-hierarchical",
            occupancy: false,
            early_stop: 0.0,
            ..Mode { hierarchical: true, ..skips }
        },
        none,
    ];
    let mut session = open(&skips, steps, checkpoint);
    let mut seg = Segmenter::build(&session).expect("stage 2 builds");
    train_segmentation(&mut session, &mut seg).expect("stage 2 trains");
    println!(
        "nerf_stage2 inference: one head ({steps} steps with every skip, seed 0), masks rendered under each setting"
    );
    println!("| masks rendered with | masks s | ARI | mIoU | PSNR |");
    println!("|---|---|---|---|---|");
    for mode in renders {
        let s = open(&mode, steps, checkpoint);
        let inference = MaskInference::new(&s, &seg.head, Some(seg.teacher.extractor())).expect("inference");
        let eval = evaluate_masks(&s, &inference, false).expect("masks");
        let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.4}"));
        println!(
            "| {} | {:.0} | {} | {} | {} |",
            mode.name,
            eval.seconds,
            f(eval.segmentation.mean_ari()),
            f(eval.segmentation.iou().miou),
            eval.image.mean_psnr().map_or("-".into(), |p| format!("{p:.2}"))
        );
    }
}

/// The render and head phase of a stage-2 step on one 64x64 patch in each mode, timed apart:
/// the frozen render (which keeps the segmentation input at its samples), the head's forward
/// and backward on them (what weight thresholding decides the size of), and, for comparison,
/// the segmentation input computed again (what the head phase cost before the render kept it).
fn head_phase(checkpoint: &Path, repeats: usize) {
    use rand::{Rng, SeedableRng};
    use sos_core::config::HeadConfig;
    use sos_core::render::renderer::{render_with_seg_input, FrozenBuffers};
    use sos_core::segment::head::SegHead;
    let modes = selected_modes(&[
        "no-skipping",
        "weight-threshold-only",
        "uniform-no-skipping",
        "uniform-weight-threshold-only",
        "no-weight-threshold",
        "all-skips",
    ]);
    println!("nerf_stage2 head phase: one 64x64 patch (4096 rays), median of {repeats}");
    println!(
        "| mode | head samples/ray | render s | head forward + backward s | segmentation input again s | load avg |"
    );
    println!("|---|---|---|---|---|---|");
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    for mode in &modes {
        let session = open(mode, 1, checkpoint);
        let rays = probe_patch(&session);
        let mut options = session.render_options(false);
        options.min_weight = mode.weight_threshold;
        let dim = session.field.seg_input_dim();
        let mut head = SegHead::new(&HeadConfig::default(), dim, 1e-3, 0);
        let (mut render_s, mut head_s, mut again_s) = (Vec::new(), Vec::new(), Vec::new());
        let mut per_ray = 0.0;
        let mut buffers = FrozenBuffers::default();
        for _ in 0..repeats {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
            let t = Instant::now();
            let mut r = render_with_seg_input(
                session.field.as_ref(),
                session.render_context(),
                &rays,
                options,
                usize::MAX,
                &mut buffers,
                &mut rng,
            );
            r.composite();
            render_s.push(t.elapsed().as_secs_f64());
            let n = r.samples.len();
            per_ray = n as f64 / rays.len() as f64;
            let grads: Vec<f32> = (0..n * head.outputs()).map(|_| rng.gen_range(-1e-3..1e-3)).collect();
            let t = Instant::now();
            let (_, tape) = head.forward(&r.seg_input, n);
            head.backward(&tape, &grads);
            head_s.push(t.elapsed().as_secs_f64());
            let t = Instant::now();
            let mut input = vec![0.0; n * dim];
            session.field.seg_input(&r.samples.positions, &mut input);
            again_s.push(t.elapsed().as_secs_f64());
            buffers.recycle(&mut r);
        }
        println!(
            "| {} | {:.1} | {:.3} | {:.3} | {:.3} | {} |",
            mode.name,
            per_ray,
            median(render_s),
            median(head_s),
            median(again_s),
            load_average()
        );
    }
}

/// Quantiles of the frozen density at one jittered probe per cell of a 64³ grid over the scene
/// (what the occupancy threshold is up against).
fn density_stats(checkpoint: &Path) {
    use rand::{Rng, SeedableRng};
    let mode = Mode { name: "density", occupancy: false, ..ALL_SKIPS };
    let session = open(&mode, 1, checkpoint);
    let res = 64;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let positions: Vec<[f32; 3]> = (0..res * res * res)
        .map(|i| {
            let (x, y, z) = (i % res, (i / res) % res, i / (res * res));
            let u = [x, y, z].map(|c| (c as f32 + rng.gen::<f32>()) / res as f32);
            session.contraction.from_unit(u)
        })
        .collect();
    let mut sigma = vec![0.0; positions.len()];
    session.field.density(&positions, &mut sigma);
    let mut sorted = sigma.clone();
    sorted.sort_by(f32::total_cmp);
    let q = |f: f64| sorted[((sorted.len() - 1) as f64 * f) as usize];
    println!(
        "density quantiles over {} probes: 10% {:.3} 50% {:.3} 90% {:.3} 99% {:.3} max {:.3}",
        sorted.len(),
        q(0.1),
        q(0.5),
        q(0.9),
        q(0.99),
        q(1.0)
    );
    for t in [0.01f32, 0.027, 0.1, 0.3, 1.0, 3.0, 10.0] {
        let above = sigma.iter().filter(|&&s| s > t).count() as f64 / sigma.len() as f64;
        println!("  above {t:>6}: {:.1}%", 100.0 * above);
    }
}

/// How the compositing weight of one 64x64 patch's rays is spread over their samples, in the
/// reference pipeline (coarse + fine, no other skip): samples per ray above absolute and
/// relative thresholds, and the fewest samples that carry a given share of each ray's weight.
fn weight_spread(checkpoint: &Path) {
    use rand::SeedableRng;
    use sos_core::render::renderer::render;
    let session = open(&mode_named("no-skipping"), 1, checkpoint);
    let rays = probe_patch(&session);
    let options = session.render_options(false);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut r = render(session.field.as_ref(), session.render_context(), &rays, options, false, &mut rng);
    r.composite();
    let n_rays = rays.len() as f64;
    let mut counts = [0.0f64; 9];
    let mut opaque = 0.0;
    for ray in 0..rays.len() {
        let mut w: Vec<f32> = r.samples.range(ray).map(|k| r.weights[k]).collect();
        w.sort_by(|a, b| b.total_cmp(a));
        let total: f32 = w.iter().sum();
        opaque += total as f64;
        let peak = w.first().copied().unwrap_or(0.0);
        let above = |t: f32| w.iter().filter(|&&x| x > t).count() as f64;
        let share = |f: f32| {
            let mut acc = 0.0;
            w.iter()
                .take_while(|&&x| {
                    let before = acc;
                    acc += x;
                    before < f * total
                })
                .count() as f64
        };
        let row = [
            w.len() as f64,
            above(1e-3),
            above(1e-2),
            above(1e-2 * peak),
            above(1e-1 * peak),
            share(0.9),
            share(0.99),
            share(0.999),
            share(0.9999),
        ];
        for (c, v) in counts.iter_mut().zip(row) {
            *c += v;
        }
    }
    println!(
        "nerf_stage2 weights: one 64x64 patch, coarse + fine, no skipping; mean per ray (opacity {:.3})",
        opaque / n_rays
    );
    let names = [
        "samples",
        "w > 1e-3",
        "w > 1e-2",
        "w > 1% of peak",
        "w > 10% of peak",
        "90% of weight",
        "99%",
        "99.9%",
        "99.99%",
    ];
    for (name, c) in names.iter().zip(counts) {
        println!("  {name:>16}: {:.1}", c / n_rays);
    }
}

fn main() {
    sos_benchmarks::setup();
    let args: Vec<String> = std::env::args().collect();
    let what = args.get(1).map(String::as_str).unwrap_or("speed");
    let checkpoint =
        args.get(2).map(PathBuf::from).unwrap_or_else(|| PathBuf::from("runs/nerf-synthetic-small/checkpoint.bin"));
    let steps: Option<usize> = args.get(3).and_then(|s| s.parse().ok());
    match what {
        "speed" => speed(&checkpoint, steps.unwrap_or(2)),
        "quality" => quality(&checkpoint, steps.unwrap_or(100)),
        "density" => density_stats(&checkpoint),
        "head" => head_phase(&checkpoint, steps.unwrap_or(3)),
        "inference" => inference_skips(&checkpoint, steps.unwrap_or(60)),
        "weights" => weight_spread(&checkpoint),
        other => {
            eprintln!("unknown mode `{other}`: use `speed`, `quality`, `head`, `weights`, `density` or `inference`");
            std::process::exit(2);
        }
    }
}
