//! Element-wise activations with in-place forward and backward passes.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Slices with at least this many elements are processed on the rayon pool.
const PAR_MIN_LEN: usize = 1 << 15;
/// Target number of elements per rayon task (about 64 KiB of `f32`, L2-friendly).
const PAR_CHUNK_LEN: usize = 1 << 14;

/// An element-wise non-linearity.
///
/// All backward passes take the forward **output** `y = f(x)` (not the input), because every
/// supported derivative can be written in terms of it; a layer therefore only has to keep its
/// activated output for backprop:
/// - `Identity`: 1
/// - `Relu`: `y > 0`
/// - `Sigmoid`: `y·(1−y)`
/// - `Softplus`: `σ(x) = 1 − e^{−y}` (computed as `−expm1(−y)` for accuracy near 0)
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[serde(rename_all = "kebab-case")]
pub enum Activation {
    /// `f(x) = x`.
    Identity,
    /// `f(x) = max(x, 0)`.
    Relu,
    /// `f(x) = 1 / (1 + e^{−x})`.
    Sigmoid,
    /// `f(x) = ln(1 + e^x)`, equal to `x` above 20 like PyTorch's default threshold.
    Softplus,
}

/// The logistic function `1 / (1 + e^{−x})` ([`Activation::Sigmoid`]).
#[inline(always)]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `ln(1 + e^x)`, and `x` itself above 20 like PyTorch's default threshold
/// ([`Activation::Softplus`]).
#[inline(always)]
pub fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

/// Rows per rayon task for a row-major matrix with `cols` columns.
fn rows_per_task(cols: usize) -> usize {
    (PAR_CHUNK_LEN / cols.max(1)).max(1)
}

/// Most tasks a parallel column sum is split into.
const MAX_SUM_TASKS: usize = 64;

/// Rows per task of a parallel column sum over `len` values in rows of `cols`. The split
/// depends on the shape alone (not on threads or scheduling), and the partial sums are added
/// in task order, so a run's gradients are the same every time, bit for bit.
fn sum_task_rows(len: usize, cols: usize) -> usize {
    let rows = len / cols.max(1);
    rows_per_task(cols).max(rows.div_ceil(MAX_SUM_TASKS))
}

/// `total += Σ partials`, the partials added together first, in order.
fn add_in_order(partials: &[Vec<f32>], total: &mut [f32]) {
    let mut sum = vec![0.0f32; total.len()];
    for p in partials {
        sum.iter_mut().zip(p).for_each(|(s, v)| *s += v);
    }
    total.iter_mut().zip(&sum).for_each(|(t, s)| *t += s);
}

/// `y[r][j] = f(y[r][j] + bias[j])` over a row-major matrix (bias may be empty: no add).
fn forward_rows<F: Fn(f32) -> f32 + Sync>(y: &mut [f32], bias: &[f32], f: F) {
    let body = |chunk: &mut [f32]| {
        if bias.is_empty() {
            chunk.iter_mut().for_each(|v| *v = f(*v));
        } else {
            for row in chunk.chunks_exact_mut(bias.len()) {
                row.iter_mut().zip(bias).for_each(|(v, &b)| *v = f(*v + b));
            }
        }
    };
    if y.len() >= PAR_MIN_LEN {
        let chunk = rows_per_task(bias.len()) * bias.len().max(1);
        y.par_chunks_mut(chunk).for_each(body);
    } else {
        body(y);
    }
}

/// `grad *= df(out)` element-wise, and (when `col_sum` is non-empty) `col_sum += Σ_rows grad`.
fn backward_rows<D: Fn(f32) -> f32 + Sync>(out: &[f32], grad: &mut [f32], col_sum: &mut [f32], df: D) {
    let cols = col_sum.len();
    let body = |o: &[f32], g: &mut [f32], acc: &mut [f32]| {
        if cols == 0 {
            g.iter_mut().zip(o).for_each(|(g, &y)| *g *= df(y));
        } else {
            for (g_row, o_row) in g.chunks_exact_mut(cols).zip(o.chunks_exact(cols)) {
                for ((g, &y), a) in g_row.iter_mut().zip(o_row).zip(acc.iter_mut()) {
                    *g *= df(y);
                    *a += *g;
                }
            }
        }
    };
    if grad.len() >= PAR_MIN_LEN {
        let chunk = sum_task_rows(grad.len(), cols) * cols.max(1);
        // Per-task partial column sums, added in task order: one pass over `grad`.
        let partials: Vec<Vec<f32>> = grad
            .par_chunks_mut(chunk)
            .zip(out.par_chunks(chunk))
            .map(|(g, o)| {
                let mut acc = vec![0.0f32; cols];
                body(o, g, &mut acc);
                acc
            })
            .collect();
        add_in_order(&partials, col_sum);
    } else {
        body(out, grad, col_sum);
    }
}

/// `col_sum[j] += Σ_r g[r][j]` for a row-major matrix with `col_sum.len()` columns (the bias
/// gradient of a linear layer whose output gradient is `g`).
///
/// # Shapes
/// `g`: `[rows, cols]` with `cols = col_sum.len()`.
pub fn add_column_sums(g: &[f32], col_sum: &mut [f32]) {
    let cols = col_sum.len();
    assert!(
        cols > 0 && g.chunks_exact(cols).remainder().is_empty(),
        "add_column_sums: {} values do not form rows of {cols}",
        g.len()
    );
    let body = |g: &[f32], acc: &mut [f32]| {
        for row in g.chunks_exact(cols) {
            acc.iter_mut().zip(row).for_each(|(a, &v)| *a += v);
        }
    };
    if g.len() >= PAR_MIN_LEN {
        let partials: Vec<Vec<f32>> = g
            .par_chunks(sum_task_rows(g.len(), cols) * cols)
            .map(|g| {
                let mut acc = vec![0.0f32; cols];
                body(g, &mut acc);
                acc
            })
            .collect();
        add_in_order(&partials, col_sum);
    } else {
        body(g, col_sum);
    }
}

impl Activation {
    /// Scalar `f(x)`.
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Identity => x,
            Activation::Relu => x.max(0.0),
            Activation::Sigmoid => sigmoid(x),
            Activation::Softplus => softplus(x),
        }
    }

    /// Scalar `f'(x)` expressed through the output `y = f(x)`.
    #[inline]
    pub fn derivative_from_output(self, y: f32) -> f32 {
        match self {
            Activation::Identity => 1.0,
            Activation::Relu => {
                if y > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            Activation::Sigmoid => y * (1.0 - y),
            Activation::Softplus => -(-y).exp_m1(),
        }
    }

    /// In place: `x ← f(x)`.
    pub fn forward(self, x: &mut [f32]) {
        self.forward_bias(x, &[]);
    }

    /// In place: `grad ← grad ⊙ f'(x)`, where `out = f(x)` is the **forward output**.
    ///
    /// # Shapes
    /// `out.len() == grad.len()`.
    pub fn backward(self, out: &[f32], grad: &mut [f32]) {
        self.backward_bias(out, grad, &mut []);
    }

    /// Fused bias add and activation over a row-major matrix: `y[r][j] ← f(y[r][j] + bias[j])`.
    /// An empty `bias` means no add.
    ///
    /// # Shapes
    /// `y`: `[rows, bias.len()]`.
    pub fn forward_bias(self, y: &mut [f32], bias: &[f32]) {
        assert!(bias.is_empty() || y.chunks_exact(bias.len()).remainder().is_empty(), "forward_bias: ragged rows");
        match self {
            Activation::Identity if bias.is_empty() => {}
            Activation::Identity => forward_rows(y, bias, |v| v),
            Activation::Relu => forward_rows(y, bias, |v| v.max(0.0)),
            Activation::Sigmoid => forward_rows(y, bias, sigmoid),
            Activation::Softplus => forward_rows(y, bias, softplus),
        }
    }

    /// Fused activation backward and bias gradient over a row-major matrix:
    /// `grad ← grad ⊙ f'(·)` from the forward output `out`, then `bias_grad[j] += Σ_r grad[r][j]`.
    /// An empty `bias_grad` skips the sum.
    ///
    /// # Shapes
    /// `out`, `grad`: `[rows, bias_grad.len()]`.
    pub fn backward_bias(self, out: &[f32], grad: &mut [f32], bias_grad: &mut [f32]) {
        assert_eq!(out.len(), grad.len(), "backward: output and gradient lengths differ");
        assert!(
            bias_grad.is_empty() || grad.chunks_exact(bias_grad.len()).remainder().is_empty(),
            "backward_bias: ragged rows"
        );
        match self {
            Activation::Identity if bias_grad.is_empty() => {}
            Activation::Identity => add_column_sums(grad, bias_grad),
            Activation::Relu => backward_rows(out, grad, bias_grad, |y| if y > 0.0 { 1.0 } else { 0.0 }),
            Activation::Sigmoid => backward_rows(out, grad, bias_grad, |y| y * (1.0 - y)),
            Activation::Softplus => backward_rows(out, grad, bias_grad, |y| -(-y).exp_m1()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Bias gradients (parallel column sums) do not depend on the thread count or on
    /// scheduling, bit for bit.
    #[test]
    fn column_sums_have_the_same_bits_on_any_thread_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let cols = 48;
        let rows = 3 * PAR_MIN_LEN / cols + 7;
        let g: Vec<f32> = (0..rows * cols).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let out: Vec<f32> = (0..rows * cols).map(|_| rng.gen_range(0.01..0.99)).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let mut sums = vec![0.0f32; cols];
                add_column_sums(&g, &mut sums);
                let mut grad = g.clone();
                let mut bias = vec![0.0f32; cols];
                Activation::Sigmoid.backward_bias(&out, &mut grad, &mut bias);
                sums.iter().chain(&bias).map(|v| v.to_bits()).collect::<Vec<_>>()
            })
        };
        let one = run(1);
        for threads in [2, 3, 7] {
            assert!(run(threads) == one, "{threads} threads give other bits than one");
        }
    }

    const ALL: [Activation; 4] = [Activation::Identity, Activation::Relu, Activation::Sigmoid, Activation::Softplus];

    /// Central differences in f64 of the f32 forward, vs. the backward from the output.
    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        // Keep away from ReLU's kink so the difference quotient is valid; cover softplus' tails.
        let mut xs: Vec<f32> = (0..200).map(|_| rng.gen_range(-6.0f32..6.0)).filter(|x| x.abs() > 0.05).collect();
        xs.extend([-30.0, -15.0, 25.0, 0.3, -0.3]);
        for act in ALL {
            let mut y = xs.clone();
            act.forward(&mut y);
            let mut g = vec![1.0f32; xs.len()];
            act.backward(&y, &mut g);
            for (i, &x) in xs.iter().enumerate() {
                let h = 1e-2f32;
                let fd = (act.apply(x + h) as f64 - act.apply(x - h) as f64) / (2.0 * h as f64);
                let an = g[i] as f64;
                assert!(
                    (fd - an).abs() <= 2e-3 + 1e-2 * fd.abs(),
                    "{act:?} at x={x}: analytic {an} vs finite difference {fd}"
                );
            }
        }
    }

    #[test]
    fn softplus_derivative_is_accurate_in_the_tail() {
        let x = -30.0f32;
        let y = Activation::Softplus.apply(x);
        let d = Activation::Softplus.derivative_from_output(y);
        let want = sigmoid(x);
        assert!((d - want).abs() <= 1e-3 * want, "{d} vs {want}");
    }

    /// The fused paths (serial and rayon-sized) must equal the plain element-wise definition.
    #[test]
    fn fused_bias_paths_match_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for &(rows, cols) in &[(3usize, 5usize), (1000, 67)] {
            let x: Vec<f32> = (0..rows * cols).map(|_| rng.gen_range(-3.0..3.0)).collect();
            let b: Vec<f32> = (0..cols).map(|_| rng.gen_range(-1.0..1.0)).collect();
            let dy: Vec<f32> = (0..rows * cols).map(|_| rng.gen_range(-1.0..1.0)).collect();
            for act in ALL {
                let mut y = x.clone();
                act.forward_bias(&mut y, &b);
                let mut g = dy.clone();
                let mut db = vec![0.5f32; cols];
                act.backward_bias(&y, &mut g, &mut db);
                let mut db_ref = vec![0.5f64; cols];
                for r in 0..rows {
                    for j in 0..cols {
                        let i = r * cols + j;
                        let want_y = act.apply(x[i] + b[j]);
                        assert!((y[i] - want_y).abs() <= 1e-6 * (1.0 + want_y.abs()), "{act:?} forward");
                        let want_g = dy[i] * act.derivative_from_output(want_y);
                        assert!((g[i] - want_g).abs() <= 1e-6, "{act:?} backward");
                        db_ref[j] += want_g as f64;
                    }
                }
                for j in 0..cols {
                    assert!((db[j] as f64 - db_ref[j]).abs() <= 1e-3, "{act:?} bias grad {j}");
                }
            }
        }
    }

    #[test]
    fn serde_names_are_kebab_case() {
        assert_eq!(serde_json::to_string(&Activation::Softplus).unwrap(), "\"softplus\"");
        let a: Activation = serde_json::from_str("\"relu\"").unwrap();
        assert_eq!(a, Activation::Relu);
    }
}
