//! One training step of the core's dense layers against the bare GEMMs it contains.
//!
//! The 63→256→256→256→256→4 ReLU MLP, batch 16384, MSE loss. Group `mlp_step`, one run:
//! - `nn_step`: one full training step through `sos_core::nn` (forward, backward, Adam);
//! - `bare_gemms`: the same forward and backward products called directly through
//!   [`sos_core::nn::matmul`], the one GEMM entry point the layers use.
//!
//! Criterion's throughput is GEMM flops (`2·m·n·k`, as elements per second); after the group a
//! summary prints ms per step, GFLOP/s of each and the ratio nn / bare throughput.
//!
//! `cargo bench -p sos-benchmarks --bench mlp_step`; threads: `RAYON_NUM_THREADS` (default 2).

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode, Throughput};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use sos_benchmarks::GroupResults;
use sos_core::nn::{matmul, Activation, Adam, MatRef, Mlp};

const DIMS: [usize; 6] = [63, 256, 256, 256, 256, 4];
const BATCH: usize = 16384;

/// MSE of `y` against `target` and its gradient.
fn mse(y: &[f32], target: &[f32]) -> (f64, Vec<f32>) {
    let scale = 2.0 / y.len() as f32;
    let mut loss = 0.0f64;
    let dy = y
        .iter()
        .zip(target)
        .map(|(y, t)| {
            loss += ((y - t) * (y - t)) as f64;
            scale * (y - t)
        })
        .collect();
    (loss / y.len() as f64, dy)
}

/// The operands of every GEMM of one step, filled with constants.
struct Bare {
    acts: Vec<Vec<f32>>,
    outs: Vec<Vec<f32>>,
    grads: Vec<Vec<f32>>,
    dxs: Vec<Vec<f32>>,
    weights: Vec<Vec<f32>>,
    wgrads: Vec<Vec<f32>>,
}

impl Bare {
    fn new(n: usize) -> Self {
        let per_layer = |v: f32| DIMS.iter().map(|&d| vec![v; n * d]).collect();
        let per_weight = |v: f32| DIMS.windows(2).map(|d| vec![v; d[0] * d[1]]).collect();
        Self {
            acts: per_layer(0.5),
            outs: per_layer(0.0),
            grads: per_layer(0.1),
            dxs: per_layer(0.0),
            weights: per_weight(0.01),
            wgrads: per_weight(0.0),
        }
    }

    /// The products of one forward and backward pass, in the order the layers run them.
    fn step(&mut self, n: usize) {
        for (l, d) in DIMS.windows(2).enumerate() {
            let (i, o) = (d[0], d[1]);
            // y[n,o] = x[n,i]·W[i,o]
            matmul(MatRef::new(&self.acts[l], n, i), MatRef::new(&self.weights[l], i, o), &mut self.outs[l + 1], false);
        }
        for (l, d) in DIMS.windows(2).enumerate().rev() {
            let (i, o) = (d[0], d[1]);
            let (x, g, w) = (MatRef::new(&self.acts[l], n, i), MatRef::new(&self.grads[l + 1], n, o), &self.weights[l]);
            // ∂W[i,o] += xᵀ·g
            matmul(x.t(), g, &mut self.wgrads[l], true);
            if l > 0 {
                // ∂x[n,i] = g·Wᵀ
                matmul(g, MatRef::new(w, i, o).t(), &mut self.dxs[l], false);
            }
        }
    }
}

fn bench(c: &mut Criterion) {
    let threads = sos_benchmarks::setup();
    let n = BATCH;
    let (in_dim, out_dim) = (DIMS[0], DIMS[DIMS.len() - 1]);
    let mut rng = StdRng::seed_from_u64(0);
    let mut mlp = Mlp::new(&DIMS, Activation::Relu, Activation::Identity, &mut rng);
    let mut adam = Adam::new(1e-3);
    let x: Vec<f32> = (0..n * in_dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let target: Vec<f32> = (0..n * out_dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let mut bare = Bare::new(n);

    // GEMM flops of one step: forward x·W and ∂W = xᵀ·g for every layer, ∂x = g·Wᵀ for all but
    // the first (the input needs no gradient).
    let flops: f64 =
        DIMS.windows(2).enumerate().map(|(l, d)| 2.0 * (n * d[0] * d[1]) as f64 * if l == 0 { 2.0 } else { 3.0 }).sum();
    let mut losses = Vec::new();

    let results = GroupResults::new("mlp_step");
    let mut group = c.benchmark_group("mlp_step");
    group.sampling_mode(SamplingMode::Flat).throughput(Throughput::Elements(flops as u64));
    group.bench_function("nn_step", |b| {
        b.iter(|| {
            let (y, tape) = mlp.forward(&x, n);
            let (loss, dy) = mse(&y, &target);
            mlp.backward(&tape, &dy, false);
            adam.step(&mut mlp.params_mut(), 1.0);
            losses.push(loss);
        })
    });
    group.bench_function("bare_gemms", |b| b.iter(|| bare.step(n)));
    group.finish();

    println!(
        "mlp_step: MLP {DIMS:?} ReLU, batch {n}, MSE + Adam, {threads} rayon threads; GEMM work per step {:.2} GFLOP",
        flops / 1e9
    );
    if let (Some(nn_s), Some(bare_s)) = (results.median("nn_step"), results.median("bare_gemms")) {
        let (nn_gf, bare_gf) = (flops / nn_s / 1e9, flops / bare_s / 1e9);
        println!("nn training step : {:8.1} ms/step  {nn_gf:6.1} GFLOP/s", nn_s * 1e3);
        println!("bare GEMMs       : {:8.1} ms/step  {bare_gf:6.1} GFLOP/s", bare_s * 1e3);
        println!("ratio nn / bare throughput: {:.1}% (criterion medians)", 100.0 * nn_gf / bare_gf);
    }
    if let (Some(first), Some(last)) = (losses.first(), losses.last()) {
        println!("(MSE loss {first:.4} at the first step, {last:.4} at the last of {})", losses.len());
    }
}

criterion_group! {
    name = benches;
    config = sos_benchmarks::criterion(10, 2.0, 5.0);
    targets = bench
}
criterion_main!(benches);
