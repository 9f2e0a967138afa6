//! Speed of one training step of the core's dense layers against the bare GEMMs they contain.
//!
//! Builds the 63→256→256→256→256→4 ReLU MLP, batch 16384, MSE loss, and times in the same run
//! (after warm-up, median of several interleaved repeats):
//! (a) one full training step through `sos_core::nn` (forward, backward, Adam), and
//! (b) the same forward and backward products called directly through `gemm`.
//! Prints ms per step, GFLOP/s of each (counting the GEMM flops `2·m·n·k` only) and their ratio.
//! Threads: `RAYON_NUM_THREADS` (default 2).

use std::time::Instant;

use gemm::Parallelism;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use sos_core::nn::{Activation, Adam, Mlp};

const DIMS: [usize; 6] = [63, 256, 256, 256, 256, 4];
const BATCH: usize = 16384;
const WARMUP: usize = 2;
const REPEATS: usize = 7;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// `dst (+)= lhs·rhs` straight through `gemm`, with the operands given by (column, row) strides
/// exactly as the nn module passes them.
#[allow(unsafe_code, clippy::too_many_arguments)]
fn bare_gemm(
    (m, n, k): (usize, usize, usize),
    dst: &mut [f32],
    accumulate: bool,
    lhs: &[f32],
    (lhs_cs, lhs_rs): (usize, usize),
    rhs: &[f32],
    (rhs_cs, rhs_rs): (usize, usize),
) {
    assert!(m > 0 && n > 0 && k > 0);
    assert!(dst.len() >= m * n);
    assert!((m - 1) * lhs_rs + (k - 1) * lhs_cs < lhs.len());
    assert!((k - 1) * rhs_rs + (n - 1) * rhs_cs < rhs.len());
    // SAFETY: the asserts bound every element gemm touches inside its slice; dst is a distinct
    // `&mut` slice written densely row-major (strides 1, n), so writes never alias the inputs.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            Parallelism::Rayon(0),
        );
    }
}

fn main() {
    sos_benchmarks::allocate_like_sos();
    let threads = std::env::var("RAYON_NUM_THREADS").ok().and_then(|s| s.parse().ok()).unwrap_or(2);
    rayon::ThreadPoolBuilder::new().num_threads(threads).build_global().expect("rayon pool");
    let n = BATCH;
    let (in_dim, out_dim) = (DIMS[0], DIMS[DIMS.len() - 1]);
    let mut rng = StdRng::seed_from_u64(0);
    let mut mlp = Mlp::new(&DIMS, Activation::Relu, Activation::Identity, &mut rng);
    let mut adam = Adam::new(1e-3);
    let x: Vec<f32> = (0..n * in_dim).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let target: Vec<f32> = (0..n * out_dim).map(|_| rng.gen_range(-1.0..1.0)).collect();

    // GEMM flops of one step: forward x·W and ∂W = xᵀ·g for every layer, ∂x = g·Wᵀ for all but
    // the first (the input needs no gradient).
    let flops: f64 =
        DIMS.windows(2).enumerate().map(|(l, d)| 2.0 * (n * d[0] * d[1]) as f64 * if l == 0 { 2.0 } else { 3.0 }).sum();

    let nn_step = |mlp: &mut Mlp, adam: &mut Adam| -> f64 {
        let (y, tape) = mlp.forward(&x, n);
        let scale = 2.0 / (n * out_dim) as f32;
        let mut loss = 0.0f64;
        let dy: Vec<f32> = y
            .iter()
            .zip(&target)
            .map(|(y, t)| {
                loss += ((y - t) * (y - t)) as f64;
                scale * (y - t)
            })
            .collect();
        mlp.backward(&tape, &dy, false);
        adam.step(&mut mlp.params_mut(), 1.0);
        loss / (n * out_dim) as f64
    };

    // Buffers for the bare GEMMs: activations per layer, gradients, weights and their grads.
    let acts: Vec<Vec<f32>> = DIMS.iter().map(|&d| vec![0.5f32; n * d]).collect();
    let mut outs: Vec<Vec<f32>> = DIMS.iter().map(|&d| vec![0.0f32; n * d]).collect();
    let grads: Vec<Vec<f32>> = DIMS.iter().map(|&d| vec![0.1f32; n * d]).collect();
    let mut dxs: Vec<Vec<f32>> = DIMS.iter().map(|&d| vec![0.0f32; n * d]).collect();
    let weights: Vec<Vec<f32>> = DIMS.windows(2).map(|d| vec![0.01f32; d[0] * d[1]]).collect();
    let mut wgrads: Vec<Vec<f32>> = DIMS.windows(2).map(|d| vec![0.0f32; d[0] * d[1]]).collect();
    let mut bare = || {
        for (l, d) in DIMS.windows(2).enumerate() {
            let (i, o) = (d[0], d[1]);
            // y[n,o] = x[n,i]·W[i,o]
            bare_gemm((n, o, i), &mut outs[l + 1], false, &acts[l], (1, i), &weights[l], (1, o));
        }
        for (l, d) in DIMS.windows(2).enumerate().rev() {
            let (i, o) = (d[0], d[1]);
            // ∂W[i,o] += xᵀ·g  (x viewed transposed: column stride i, row stride 1)
            bare_gemm((i, o, n), &mut wgrads[l], true, &acts[l], (i, 1), &grads[l + 1], (1, o));
            if l > 0 {
                // ∂x[n,i] = g[n,o]·Wᵀ  (W viewed transposed: column stride o, row stride 1)
                bare_gemm((n, i, o), &mut dxs[l], false, &grads[l + 1], (1, o), &weights[l], (o, 1));
            }
        }
    };

    let mut first_loss = f64::NAN;
    for _ in 0..WARMUP {
        let loss = nn_step(&mut mlp, &mut adam);
        if first_loss.is_nan() {
            first_loss = loss;
        }
        bare();
    }
    let (mut t_nn, mut t_bare, mut last_loss) = (Vec::new(), Vec::new(), f64::NAN);
    // Interleaved so that load from other processes affects both alike.
    for _ in 0..REPEATS {
        let t0 = Instant::now();
        last_loss = nn_step(&mut mlp, &mut adam);
        t_nn.push(t0.elapsed().as_secs_f64());
        let t0 = Instant::now();
        bare();
        t_bare.push(t0.elapsed().as_secs_f64());
    }
    let (nn_s, bare_s) = (median(t_nn), median(t_bare));
    let (nn_gf, bare_gf) = (flops / nn_s / 1e9, flops / bare_s / 1e9);
    println!(
        "mlp_step: MLP {DIMS:?} ReLU, batch {n}, MSE + Adam, {threads} rayon threads, median of {REPEATS} after {WARMUP} warm-up"
    );
    println!("GEMM work per step: {:.2} GFLOP", flops / 1e9);
    println!("nn training step : {:8.1} ms/step  {:6.1} GFLOP/s", nn_s * 1e3, nn_gf);
    println!("bare GEMMs       : {:8.1} ms/step  {:6.1} GFLOP/s", bare_s * 1e3, bare_gf);
    println!("ratio nn / bare throughput: {:.1}%", 100.0 * nn_gf / bare_gf);
    println!("(MSE loss {first_loss:.4} at the first step, {last_loss:.4} at the last)");
}
