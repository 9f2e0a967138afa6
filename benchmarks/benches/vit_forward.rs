//! ViT-S/16 forward on 8 images of 224x224 (random weights): the native `dino-vit` forward
//! against ONNX Runtime running the same network (written by `dino_vit::onnx_export`), in one
//! run.
//!
//! Group `vit_forward`: `native` and `onnx_runtime`, one forward each per iteration, with a
//! pause between them so that neither pool's spinning threads overlap the other's runs. Both get
//! `RAYON_NUM_THREADS` threads (default 2; ONNX Runtime's intra-op pool gets the same count).
//! Criterion's throughput is the forward's flops (elements per second). Before the group, the two
//! outputs are compared once; after it a summary prints each one's wall time (criterion's median)
//! and process CPU seconds per forward (median over every forward run), and the ratios native /
//! ONNX Runtime (CPU time does not count time taken by other processes, but counts idle spinning
//! of the thread pools).
//!
//! `ORT_DYLIB_PATH=.../libonnxruntime.so.* cargo bench -p sos-benchmarks --features onnx --bench vit_forward`

use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode, Throughput};
use rand::{Rng, SeedableRng};
use sos_backbones::dino_vit::onnx_export::write_vit;
use sos_backbones::dino_vit::{Vit, VitShape};
use sos_backbones::onnx::OnnxModel;
use sos_benchmarks::{load_average, median, process_cpu_seconds, GroupResults};

const BATCH: usize = 8;
const SIZE: usize = 224;

/// Multiply–adds ×2 of one image's forward.
fn flops_per_image(s: &VitShape, size: usize) -> f64 {
    let np = (size / s.patch).pow(2) as f64;
    let n = np + 1.0;
    let (d, m) = (s.dim as f64, s.mlp_hidden as f64);
    let patch = np * 3.0 * (s.patch * s.patch) as f64 * d;
    let block = n * d * 3.0 * d + 2.0 * n * n * d + n * d * d + 2.0 * n * d * m;
    2.0 * (patch + s.depth as f64 * block)
}

/// `model` as an ONNX Runtime session with `threads` intra-op threads; exits the process when
/// ONNX Runtime cannot be loaded.
fn onnx_session(model: &Vit, threads: usize) -> OnnxModel {
    let dir = std::env::temp_dir().join(format!("sos-vit-forward-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("vits16_b8.onnx");
    write_vit(model, SIZE, Some(BATCH), &path).expect("write the ONNX model");
    let session = OnnxModel::load(&path, None, "image", threads).unwrap_or_else(|e| {
        eprintln!("ONNX Runtime unavailable: {e}");
        std::process::exit(1);
    });
    std::fs::remove_dir_all(&dir).ok();
    session
}

/// Runs `forward` `iters` times on what `prepare` gives it (untimed), pushing each run's
/// process CPU seconds to `cpu`; returns the wall time of the runs.
fn timed_runs<T>(
    iters: u64,
    cpu: &mut Vec<f64>,
    mut prepare: impl FnMut() -> T,
    mut forward: impl FnMut(T),
) -> Duration {
    let mut wall = Duration::ZERO;
    for _ in 0..iters {
        let data = prepare();
        let (started, c) = (Instant::now(), process_cpu_seconds().unwrap_or(f64::NAN));
        forward(data);
        cpu.push(process_cpu_seconds().unwrap_or(f64::NAN) - c);
        wall += started.elapsed();
    }
    wall
}

fn bench(c: &mut Criterion) {
    let threads = sos_benchmarks::setup();
    let shape = VitShape::dino(384, 16, 12, 6);
    let model = Vit::random(shape, 7);
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let input: Vec<f32> = (0..BATCH * 3 * SIZE * SIZE).map(|_| rng.gen_range(-2.0f32..2.0)).collect();
    let dims = [BATCH, 3, SIZE, SIZE];
    let flops = flops_per_image(&shape, SIZE) * BATCH as f64;
    println!(
        "vit_forward: ViT-S/16 (random weights), {BATCH} images of {SIZE}x{SIZE}, {threads} threads, {:.1} GFLOP per forward",
        flops / 1e9
    );
    let ort = onnx_session(&model, threads);
    let native_tokens = model.forward(&input, BATCH, SIZE, SIZE).tokens;
    let ort_out = ort.run(input.clone(), &dims, &["tokens"]).expect("ORT run");
    let ort_tokens = ort_out.into_iter().next().map(|o| o.data).unwrap_or_default();
    assert_eq!(ort_tokens.len(), native_tokens.len(), "token counts of the two forwards");
    let max_diff = ort_tokens.iter().zip(&native_tokens).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    let (mut native_cpu, mut ort_cpu) = (Vec::new(), Vec::new());

    let results = GroupResults::new("vit_forward");
    let mut group = c.benchmark_group("vit_forward");
    group.sampling_mode(SamplingMode::Flat).throughput(Throughput::Elements(flops as u64));
    group.bench_function("native", |b| {
        b.iter_custom(|iters| {
            timed_runs(
                iters,
                &mut native_cpu,
                || (),
                |()| {
                    std::hint::black_box(model.forward(&input, BATCH, SIZE, SIZE));
                },
            )
        })
    });
    std::thread::sleep(Duration::from_millis(300));
    group.bench_function("onnx_runtime", |b| {
        b.iter_custom(|iters| {
            timed_runs(
                iters,
                &mut ort_cpu,
                || input.clone(),
                |data| {
                    std::hint::black_box(ort.run(data, &dims, &["tokens"]).expect("ORT run"));
                },
            )
        })
    });
    group.finish();

    println!("load average {:.1} after the runs", load_average().unwrap_or(f64::NAN));
    let (native_s, ort_s) = (results.median("native"), results.median("onnx_runtime"));
    for (label, wall, cpu) in [("native forward", native_s, &native_cpu), ("ONNX Runtime  ", ort_s, &ort_cpu)] {
        if let Some(wall) = wall {
            println!(
                "{label}: {:8.1} ms wall ({:.0} GFLOP/s), {:.2} CPU s",
                wall * 1e3,
                flops / 1e9 / wall,
                median(cpu)
            );
        }
    }
    if let (Some(native_s), Some(ort_s)) = (native_s, ort_s) {
        println!(
            "native / ONNX Runtime = {:.2}x wall, {:.2}x CPU; max |tokens difference| {max_diff:.2e}",
            native_s / ort_s,
            median(&native_cpu) / median(&ort_cpu)
        );
    }
}

criterion_group! {
    name = benches;
    config = sos_benchmarks::criterion(10, 2.0, 10.0);
    targets = bench
}
criterion_main!(benches);
