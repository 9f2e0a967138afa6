//! One stage-1 step of the `nerf` field at the reference's sizes (1024 rays, 64 coarse + 128
//! importance samples, 8 x 256 trunks, separate coarse and fine networks, no skipping), and
//! the dense-layer throughput of that step against bare GEMMs on the same shapes, in one run.
//!
//! The step is the real one: the renderer's hierarchical pass, compositing, MSE on coarse and
//! fine colours, compositing backward, both networks' backward passes and Adam. Each network's
//! forward, backward and Adam step are timed by a wrapper; their GEMM work is counted from the
//! actual sample counts (fixed by one step before the group). Group `nerf_step`:
//! - `networks`: real stage-1 steps, of which criterion is given the time spent in the two
//!   networks (forward, backward, Adam);
//! - `bare_full_batch`, `bare_row_blocks`: every GEMM of those passes (same m, n, k, same
//!   transposes) replayed through [`sos_core::nn::matmul`] alone, once with the full batch as
//!   rows and once in the networks' row blocks; the faster of the two is the reference rate.
//!
//! Criterion's throughput is the networks' GEMM flops per step (elements per second). After the
//! group a summary prints the samples per ray, the whole step's time and its parts (medians and
//! means over the steps the `networks` benchmark ran), GFLOP/s of each benchmark and the ratio
//! networks / best bare throughput.
//!
//! `cargo bench -p sos-benchmarks --bench nerf_step`; threads: `RAYON_NUM_THREADS` (default 2).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode, Throughput};
use rand::{Rng, SeedableRng};
use sos_benchmarks::{median, GroupResults};
use sos_core::camera::Vec3;
use sos_core::config::RunConfig;
use sos_core::nn::{matmul, Linear, MatRef};
use sos_core::plugin::field::{Hierarchical, HierarchicalSampling};
use sos_core::plugin::{FieldTape, RadianceField};
use sos_core::render::composite::{RayColour, RayGrad};
use sos_core::render::contraction::Contraction;
use sos_core::render::rays::RayBatch;
use sos_core::render::renderer::render;
use sos_core::train::Session;
use sos_plugins::nerf::{network::CHUNK, NerfConfig, NerfMlp, NerfNet};

const CONFIG: &str = r#"
name = "nerf-step"
output_dir = "runs"
[scene]
kind = "synthetic"
rig = "object-centric"
width = 200
height = 150
views = 24
[field]
kind = "nerf"
[train]
rays_per_step = 1024
occupancy = false
early_stop = 0.0
weight_threshold = 0.0
sample_colour_weight = 0.0
[segment]
steps = 0
"#;

/// Time spent in one network's passes since the last [`Stats::take`].
#[derive(Default)]
struct Stats {
    forward_ns: AtomicU64,
    backward_ns: AtomicU64,
    step_ns: AtomicU64,
    /// Points of the last recorded forward pass.
    last_n: AtomicU64,
}

impl Stats {
    /// (forward, backward, step) seconds, reset to zero.
    fn take(&self) -> [f64; 3] {
        [&self.forward_ns, &self.backward_ns, &self.step_ns].map(|a| a.swap(0, Ordering::Relaxed) as f64 * 1e-9)
    }
}

/// A network whose forward, backward and step are timed.
struct Timed {
    net: NerfNet,
    stats: Arc<Stats>,
}

fn timed<T>(acc: &AtomicU64, f: impl FnOnce() -> T) -> T {
    let t = Instant::now();
    let out = f();
    acc.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    out
}

impl RadianceField for Timed {
    fn density(&self, p: &[Vec3], d: &mut [f32]) {
        self.net.density(p, d)
    }
    fn forward(&self, p: &[Vec3], dirs: &[Vec3], d: &mut [f32], c: &mut [[f32; 3]], record: bool) -> FieldTape {
        if record {
            self.stats.last_n.store(p.len() as u64, Ordering::Relaxed);
        }
        timed(&self.stats.forward_ns, || self.net.forward(p, dirs, d, c, record))
    }
    fn backward(&mut self, p: &[Vec3], dirs: &[Vec3], tape: FieldTape, gd: &[f32], gc: &[[f32; 3]]) {
        let t = Instant::now();
        self.net.backward(p, dirs, tape, gd, gc);
        self.stats.backward_ns.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }
    fn step(&mut self, lr_factor: f32) {
        let t = Instant::now();
        self.net.step(lr_factor);
        self.stats.step_ns.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }
    fn gradients_finite(&self) -> bool {
        self.net.gradients_finite()
    }
    fn discard_gradients(&mut self) {
        self.net.discard_gradients()
    }
    fn seg_input_dim(&self) -> usize {
        self.net.seg_input_dim()
    }
    fn seg_input(&self, p: &[Vec3], out: &mut [f32]) {
        self.net.seg_input(p, out)
    }
    fn save_state(&self) -> Vec<u8> {
        self.net.save_state()
    }
    fn load_state(&mut self, b: &[u8]) -> Result<(), sos_core::error::StateError> {
        self.net.load_state(b)
    }
    fn num_parameters(&self) -> usize {
        self.net.num_parameters()
    }
    fn parameters(&self) -> Vec<f32> {
        self.net.parameters()
    }
    fn set_parameters(&mut self, values: &[f32]) -> Result<(), sos_core::error::StateError> {
        self.net.set_parameters(values)
    }
    fn gradients(&self) -> Vec<f32> {
        self.net.gradients()
    }
}

/// Coarse + fine timed networks with the reference's hierarchical sampling.
struct Pair {
    fine: Timed,
    coarse: Timed,
    h: Hierarchical,
}

impl RadianceField for Pair {
    fn density(&self, p: &[Vec3], d: &mut [f32]) {
        self.fine.density(p, d)
    }
    fn forward(&self, p: &[Vec3], dirs: &[Vec3], d: &mut [f32], c: &mut [[f32; 3]], record: bool) -> FieldTape {
        self.fine.forward(p, dirs, d, c, record)
    }
    fn backward(&mut self, p: &[Vec3], dirs: &[Vec3], tape: FieldTape, gd: &[f32], gc: &[[f32; 3]]) {
        self.fine.backward(p, dirs, tape, gd, gc)
    }
    fn step(&mut self, lr_factor: f32) {
        self.fine.step(lr_factor);
        self.coarse.step(lr_factor);
    }
    fn gradients_finite(&self) -> bool {
        self.fine.gradients_finite() && self.coarse.gradients_finite()
    }
    fn discard_gradients(&mut self) {
        self.fine.discard_gradients();
        self.coarse.discard_gradients();
    }
    fn seg_input_dim(&self) -> usize {
        self.fine.seg_input_dim()
    }
    fn seg_input(&self, p: &[Vec3], out: &mut [f32]) {
        self.fine.seg_input(p, out)
    }
    fn save_state(&self) -> Vec<u8> {
        Vec::new()
    }
    fn load_state(&mut self, _: &[u8]) -> Result<(), sos_core::error::StateError> {
        Ok(())
    }
    fn num_parameters(&self) -> usize {
        self.fine.num_parameters() + self.coarse.num_parameters()
    }
    fn parameters(&self) -> Vec<f32> {
        [self.fine.parameters(), self.coarse.parameters()].concat()
    }
    fn set_parameters(&mut self, values: &[f32]) -> Result<(), sos_core::error::StateError> {
        let n = self.fine.num_parameters().min(values.len());
        self.fine.set_parameters(&values[..n])?;
        self.coarse.set_parameters(&values[n..])
    }
    fn gradients(&self) -> Vec<f32> {
        [self.fine.gradients(), self.coarse.gradients()].concat()
    }
    fn hierarchical(&self) -> Option<&dyn HierarchicalSampling> {
        Some(self)
    }
    fn hierarchical_mut(&mut self) -> Option<&mut dyn HierarchicalSampling> {
        Some(self)
    }
}

impl HierarchicalSampling for Pair {
    fn sampling(&self) -> Hierarchical {
        self.h
    }
    fn proposal(&self) -> Option<&dyn RadianceField> {
        Some(&self.coarse)
    }
    fn proposal_mut(&mut self) -> Option<&mut dyn RadianceField> {
        Some(&mut self.coarse)
    }
}

/// One GEMM `[m, k] · [k, n]`, each operand stored row-major and possibly used transposed,
/// and whether it accumulates into the destination.
#[derive(Clone, Copy)]
struct Gemm {
    m: usize,
    n: usize,
    k: usize,
    lhs_t: bool,
    rhs_t: bool,
    accumulate: bool,
}

impl Gemm {
    fn flops(&self) -> f64 {
        2.0 * (self.m * self.n * self.k) as f64
    }

    /// Runs the product on the leading values of scratch buffers.
    fn run(&self, dst: &mut [f32], lhs: &[f32], rhs: &[f32]) {
        let Gemm { m, n, k, .. } = *self;
        let a = if self.lhs_t { MatRef::new(&lhs[..k * m], k, m).t() } else { MatRef::new(&lhs[..m * k], m, k) };
        let b = if self.rhs_t { MatRef::new(&rhs[..n * k], n, k).t() } else { MatRef::new(&rhs[..k * n], k, n) };
        matmul(a, b, &mut dst[..m * n], self.accumulate);
    }
}

/// Every GEMM of one forward + backward of `mlp` over `rows` points, in the order the
/// network runs them (see `NerfMlp::forward`/`backward`): per input block of each layer, the
/// forward product, the weight gradient, and the input gradient where one is needed.
fn network_gemms(mlp: &NerfMlp, rows: usize) -> Vec<Gemm> {
    let mut out = Vec::new();
    // (layer, input block widths, which blocks need ∂x)
    let mut layers: Vec<(&Linear, Vec<usize>, Vec<bool>)> = Vec::new();
    let pe = mlp.pe_dim();
    for (l, layer) in mlp.trunk.layers.iter().enumerate() {
        if l == 0 {
            layers.push((layer, vec![pe], vec![false]));
        } else if mlp.trunk.skip_at == Some(l) {
            layers.push((layer, vec![pe, layer.in_dim - pe], vec![false, true]));
        } else {
            layers.push((layer, vec![layer.in_dim], vec![true]));
        }
    }
    let w = mlp.width();
    layers.push((&mlp.sigma, vec![w], vec![true]));
    layers.push((&mlp.feature, vec![w], vec![true]));
    layers.push((&mlp.view, vec![w, mlp.view.in_dim - w], vec![true, false]));
    layers.push((&mlp.rgb, vec![mlp.rgb.in_dim], vec![true]));
    for (layer, blocks, need_dx) in layers {
        let o = layer.out_dim;
        for (&i, &dx) in blocks.iter().zip(&need_dx) {
            // y[rows, o] (+)= x[rows, i] · W[i, o]
            out.push(Gemm { m: rows, n: o, k: i, lhs_t: false, rhs_t: false, accumulate: false });
            // ∂W[i, o] += xᵀ · g
            out.push(Gemm { m: i, n: o, k: rows, lhs_t: true, rhs_t: false, accumulate: true });
            if dx {
                // ∂x[rows, i] = g · Wᵀ
                out.push(Gemm { m: rows, n: i, k: o, lhs_t: false, rhs_t: true, accumulate: false });
            }
        }
    }
    out
}

/// Runs a list of GEMMs on scratch buffers.
fn run_bare(gemms: &[Gemm], scratch: &mut [Vec<f32>; 3]) {
    let [dst, lhs, rhs] = scratch;
    for g in gemms {
        g.run(dst, lhs, rhs);
    }
}

/// The same GEMMs split into the networks' row blocks.
fn blocked(mlp: &NerfMlp, rows: usize) -> Vec<Gemm> {
    let mut out = Vec::new();
    let mut left = rows;
    while left > 0 {
        let r = left.min(CHUNK);
        out.extend(network_gemms(mlp, r));
        left -= r;
    }
    out
}

/// What the steps of the `networks` benchmark measured besides the networks' time.
#[derive(Default)]
struct StepLog {
    /// Seconds of each whole step.
    seconds: Vec<f64>,
    /// Sums over the steps of (forward, backward, Adam) seconds, fine then coarse network.
    parts: [f64; 6],
    /// Fine MSE of each step.
    mse: Vec<f64>,
}

fn bench(c: &mut Criterion) {
    let threads = sos_benchmarks::setup();
    let config = RunConfig::parse(CONFIG, Path::new("nerf_step.toml")).expect("built-in config parses");
    let dir = std::env::temp_dir().join(format!("sos-nerf-step-{}", std::process::id()));
    let mut session = Session::from_config(config, &dir).expect("synthetic scene builds");
    let nerf = NerfConfig::default();
    let contraction = Contraction::new(&session.scene.extent);
    let shape = nerf.shape();
    let (fine_stats, coarse_stats) = (Arc::new(Stats::default()), Arc::new(Stats::default()));
    let fine_net = NerfNet::new(shape, nerf.density_activation, nerf.lr, contraction, 1);
    let mlp_shape = fine_net.mlp.clone();
    let pair = Pair {
        fine: Timed { net: fine_net, stats: fine_stats.clone() },
        coarse: Timed {
            net: NerfNet::new(shape, nerf.density_activation, nerf.lr, contraction, 2),
            stats: coarse_stats.clone(),
        },
        h: Hierarchical { coarse_samples: nerf.coarse_samples, fine_samples: nerf.fine_samples },
    };
    session.field = Box::new(pair);
    let n_rays = session.config.train.rays_per_step;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);

    // One real stage-1 step; returns (seconds, fine MSE).
    let mut step = move |session: &mut Session| -> (f64, f64) {
        let t0 = Instant::now();
        let mut rays = RayBatch::default();
        let mut targets = Vec::new();
        for _ in 0..n_rays {
            let v = &session.scene.views[session.scene.train[rng.gen_range(0..session.scene.train.len())]];
            let (c, r) = (rng.gen_range(0..v.camera.width), rng.gen_range(0..v.camera.height));
            rays.push_pixel(&v.camera, c, r);
            targets.push(v.image.pixel(c as usize, r as usize));
        }
        let options = session.render_options(true);
        let mut r = render(session.field.as_ref(), session.render_context(), &rays, options, true, &mut rng);
        r.composite();
        let mut coarse = r.coarse.take().expect("hierarchical pass");
        let scale = 2.0 / (n_rays * 3) as f32;
        let grads = |colours: &[RayColour], mse: &mut f64| -> Vec<RayGrad<'static>> {
            colours
                .iter()
                .zip(&targets)
                .map(|(c, t)| {
                    let mut g = RayGrad::default();
                    for k in 0..3 {
                        let e = c.rgb[k] - t[k];
                        *mse += (e * e) as f64;
                        g.rgb[k] = scale * e;
                    }
                    g
                })
                .collect()
        };
        let mut mse = 0.0;
        let gf = grads(&r.colours, &mut mse);
        let gc = grads(&coarse.colours, &mut 0.0);
        let (gs, grgb, _) = r.composite_backward(&[], 0, &gf);
        let (cgs, cgrgb, _) = coarse.composite_backward(&[], 0, &gc);
        let tape = r.tape.take();
        session.field.backward(&r.samples.positions, &r.samples.directions, tape, &gs, &grgb);
        let tape = coarse.tape.take();
        let (p, d) = (&coarse.samples.positions, &coarse.samples.directions);
        let proposal = session.field.hierarchical_mut().and_then(|h| h.proposal_mut()).expect("coarse network");
        proposal.backward(p, d, tape, &cgs, &cgrgb);
        session.field.step(1.0);
        (t0.elapsed().as_secs_f64(), mse / (n_rays * 3) as f64)
    };

    // Warm-up, which also fixes the sample counts: every ray crosses the room, so they are
    // constant.
    let (_, first_mse) = step(&mut session);
    fine_stats.take();
    coarse_stats.take();
    let n_fine = fine_stats.last_n.load(Ordering::Relaxed) as usize;
    let n_coarse = coarse_stats.last_n.load(Ordering::Relaxed) as usize;
    let full: Vec<Gemm> =
        network_gemms(&mlp_shape, n_fine).into_iter().chain(network_gemms(&mlp_shape, n_coarse)).collect();
    let blocks: Vec<Gemm> = blocked(&mlp_shape, n_fine).into_iter().chain(blocked(&mlp_shape, n_coarse)).collect();
    let flops: f64 = full.iter().map(Gemm::flops).sum();
    let biggest = n_fine.max(n_coarse) * 512;
    let mut scratch = [vec![0.01f32; biggest], vec![0.02f32; biggest], vec![0.03f32; biggest]];
    let mut log = StepLog::default();

    let results = GroupResults::new("nerf_step");
    let mut group = c.benchmark_group("nerf_step");
    group.sampling_mode(SamplingMode::Flat).throughput(Throughput::Elements(flops as u64));
    group.bench_function("networks", |b| {
        b.iter_custom(|iters| {
            let mut networks = 0.0;
            for _ in 0..iters {
                let (seconds, mse) = step(&mut session);
                let (f, c) = (fine_stats.take(), coarse_stats.take());
                for k in 0..3 {
                    log.parts[k] += f[k];
                    log.parts[3 + k] += c[k];
                }
                networks += f.iter().sum::<f64>() + c.iter().sum::<f64>();
                log.seconds.push(seconds);
                log.mse.push(mse);
            }
            Duration::from_secs_f64(networks)
        })
    });
    group.bench_function("bare_full_batch", |b| b.iter(|| run_bare(&full, &mut scratch)));
    group.bench_function("bare_row_blocks", |b| b.iter(|| run_bare(&blocks, &mut scratch)));
    group.finish();

    let (c_s, f_s) = (nerf.coarse_samples, nerf.fine_samples);
    println!(
        "nerf_step: {n_rays} rays, {c_s} coarse + {f_s} importance samples, 2 x NeRF MLP (8x256, skip 5, view 128), {threads} rayon threads"
    );
    println!(
        "samples: fine {n_fine} ({:.0}/ray), coarse {n_coarse} ({:.0}/ray)",
        n_fine as f64 / n_rays as f64,
        n_coarse as f64 / n_rays as f64
    );
    if !log.seconds.is_empty() {
        let steps = log.seconds.len();
        let p = log.parts.map(|s| s / steps as f64);
        println!("full stage-1 step: {:.2} s (median of {steps} steps)", median(&log.seconds));
        println!("  fine   forward {:.2} s  backward {:.2} s  adam {:.3} s (means)", p[0], p[1], p[2]);
        println!("  coarse forward {:.2} s  backward {:.2} s  adam {:.3} s (means)", p[3], p[4], p[5]);
    }
    println!("GEMM work of the networks per step: {:.1} GFLOP", flops / 1e9);
    let measured = ["networks", "bare_full_batch", "bare_row_blocks"].map(|f| results.median(f));
    for (label, s) in
        ["networks (fwd+bwd+adam)", "bare GEMMs, full batch ", "bare GEMMs, row blocks "].iter().zip(measured)
    {
        if let Some(s) = s {
            println!("{label}: {s:.2} s  {:.1} GFLOP/s (criterion median)", flops / s / 1e9);
        }
    }
    if let [Some(dense_s), Some(full_s), Some(blocks_s)] = measured {
        println!("ratio networks / best bare throughput: {:.1}%", 100.0 * full_s.min(blocks_s) / dense_s);
    }
    if let Some(last_mse) = log.mse.last() {
        println!("(fine MSE {first_mse:.4} at the warm-up step, {last_mse:.4} at the last)");
    }
    std::fs::remove_dir_all(&dir).ok();
}

criterion_group! {
    name = benches;
    config = sos_benchmarks::criterion(10, 1.0, 20.0);
    targets = bench
}
criterion_main!(benches);
