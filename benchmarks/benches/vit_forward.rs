//! ViT-S/16 forward on 8 images of 224x224 (random weights): the native `dino-vit` forward
//! against ONNX Runtime running the same network (exported by `onnx_export`), in one run.
//!
//! `ORT_DYLIB_PATH=.../libonnxruntime.so.* cargo run --release -p sos-benchmarks --features onnx --bin vit_forward`
//!
//! Threads: `RAYON_NUM_THREADS` (default 2) for both (ONNX Runtime's intra-op pool gets the
//! same count). After a warm-up, blocks of runs of each alternate (a pause between blocks so
//! that neither pool's spinning threads overlap the other's runs); the medians of wall-clock
//! and process CPU time are printed with their ratios (CPU time does not count time taken by
//! other processes, but counts idle spinning of the thread pools). Without the `onnx` feature only the native time is measured.

use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use sos_backbones::dino_vit::{Vit, VitShape};
use sos_benchmarks::{load_average, process_cpu_seconds};

const BATCH: usize = 8;
const SIZE: usize = 224;
const WARMUP: usize = 2;
const BLOCKS: usize = 3;
const RUNS_PER_BLOCK: usize = 3;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Multiply–adds ×2 of one image's forward.
fn flops_per_image(s: &VitShape, size: usize) -> f64 {
    let np = (size / s.patch).pow(2) as f64;
    let n = np + 1.0;
    let (d, m) = (s.dim as f64, s.mlp_hidden as f64);
    let patch = np * 3.0 * (s.patch * s.patch) as f64 * d;
    let block = n * d * 3.0 * d + 2.0 * n * n * d + n * d * d + 2.0 * n * d * m;
    2.0 * (patch + s.depth as f64 * block)
}

fn main() {
    sos_benchmarks::allocate_like_sos();
    let threads: usize = std::env::var("RAYON_NUM_THREADS").ok().and_then(|s| s.parse().ok()).unwrap_or(2);
    rayon::ThreadPoolBuilder::new().num_threads(threads).build_global().expect("rayon pool");
    let shape = VitShape::dino(384, 16, 12, 6);
    let model = Vit::random(shape, 7);
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let input: Vec<f32> = (0..BATCH * 3 * SIZE * SIZE).map(|_| rng.gen_range(-2.0f32..2.0)).collect();
    let gflop = flops_per_image(&shape, SIZE) * BATCH as f64 / 1e9;
    println!(
        "ViT-S/16 (random weights), {BATCH} images of {SIZE}x{SIZE}, {threads} threads, {gflop:.1} GFLOP per forward"
    );

    let cpu = || process_cpu_seconds().unwrap_or(f64::NAN);
    let native = || {
        let (t, c) = (Instant::now(), cpu());
        let out = model.forward(&input, BATCH, SIZE, SIZE);
        ((t.elapsed().as_secs_f64(), cpu() - c), out)
    };
    for _ in 0..WARMUP {
        native();
    }
    let ort = ort_runner(&model, threads);
    let mut native_times = Vec::new();
    let mut ort_times = Vec::new();
    let mut max_diff = 0.0f32;
    for _ in 0..BLOCKS {
        for _ in 0..RUNS_PER_BLOCK {
            let (t, out) = native();
            native_times.push(t);
            if let Some(run) = &ort {
                // Same network: the outputs agree (checked once per block, outside the timing).
                if ort_times.len() % RUNS_PER_BLOCK == 0 {
                    let (_, tokens) = run(&input);
                    max_diff =
                        max_diff.max(tokens.iter().zip(&out.tokens).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max));
                }
            }
        }
        std::thread::sleep(Duration::from_millis(300));
        if let Some(run) = &ort {
            for _ in 0..RUNS_PER_BLOCK {
                ort_times.push(run(&input).0);
            }
            std::thread::sleep(Duration::from_millis(300));
        }
    }
    let wall = |v: &[(f64, f64)]| median(v.iter().map(|t| t.0).collect());
    let cpu_s = |v: &[(f64, f64)]| median(v.iter().map(|t| t.1).collect());
    println!("load average {:.1} after the runs", load_average().unwrap_or(f64::NAN));
    let tn = wall(&native_times);
    println!("native forward: {:8.1} ms wall ({:.0} GFLOP/s), {:.2} CPU s", tn * 1e3, gflop / tn, cpu_s(&native_times));
    if ort.is_some() {
        let to = wall(&ort_times);
        println!(
            "ONNX Runtime:   {:8.1} ms wall ({:.0} GFLOP/s), {:.2} CPU s",
            to * 1e3,
            gflop / to,
            cpu_s(&ort_times)
        );
        println!(
            "native / ONNX Runtime = {:.2}x wall, {:.2}x CPU (target <= 1.5x); max |tokens difference| {max_diff:.2e}",
            tn / to,
            cpu_s(&native_times) / cpu_s(&ort_times)
        );
    }
}

/// One ONNX Runtime run: ((wall s, CPU s), tokens).
type OrtRun = Box<dyn Fn(&[f32]) -> ((f64, f64), Vec<f32>)>;

#[cfg(feature = "onnx")]
fn ort_runner(model: &Vit, threads: usize) -> Option<OrtRun> {
    use sos_backbones::dino_vit::onnx_export::write_vit;
    use sos_backbones::onnx::OnnxModel;
    let dir = std::env::temp_dir().join(format!("sos-vit-forward-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("vits16_b8.onnx");
    write_vit(model, SIZE, Some(BATCH), &path).expect("write the ONNX model");
    let session = match OnnxModel::load(&path, None, "image", threads) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("ONNX Runtime unavailable: {e}");
            std::process::exit(1);
        }
    };
    std::fs::remove_dir_all(&dir).ok();
    for _ in 0..WARMUP {
        session.run(vec![0.0; BATCH * 3 * SIZE * SIZE], &[BATCH, 3, SIZE, SIZE], &["tokens"]).expect("ORT run");
    }
    Some(Box::new(move |input: &[f32]| {
        let data = input.to_vec();
        let (t, c) = (Instant::now(), process_cpu_seconds().unwrap_or(f64::NAN));
        let out = session.run(data, &[BATCH, 3, SIZE, SIZE], &["tokens"]).expect("ORT run");
        let secs = (t.elapsed().as_secs_f64(), process_cpu_seconds().unwrap_or(f64::NAN) - c);
        (secs, out.into_iter().next().map(|o| o.data).unwrap_or_default())
    }))
}

#[cfg(not(feature = "onnx"))]
fn ort_runner(_: &Vit, _: usize) -> Option<OrtRun> {
    println!("ONNX Runtime comparison skipped: build with `--features onnx` and set ORT_DYLIB_PATH");
    None
}
