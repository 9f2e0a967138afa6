//! Safe wrapper over `gemm::gemm` for row-major `f32` matrices.

use gemm::Parallelism;

/// Products with at least this many multiply-adds (`m·k·n`) run on the rayon pool; smaller ones
/// stay on the calling thread, where the fork/join cost would exceed the work.
pub const PARALLEL_MIN_MACS: usize = 1 << 18;

/// A read-only view of a row-major matrix, used as an operand of [`matmul`], optionally
/// transposed (the transpose is free: it only swaps strides).
///
/// # Shapes
/// `data` holds `rows × cols` values, row-major, as stored. The operand's logical shape is
/// `rows × cols`, or `cols × rows` when [`MatRef::t`] was applied.
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a> {
    /// The stored values, `rows · cols` of them, row-major.
    pub data: &'a [f32],
    /// Stored row count.
    pub rows: usize,
    /// Stored column count.
    pub cols: usize,
    /// Whether the operand is used as its transpose.
    pub transposed: bool,
}

impl<'a> MatRef<'a> {
    /// Views `data` as a stored `rows × cols` row-major matrix, not transposed.
    ///
    /// # Panics
    /// If `data.len() != rows * cols`.
    pub fn new(data: &'a [f32], rows: usize, cols: usize) -> Self {
        assert_eq!(data.len(), rows * cols, "MatRef: {} values for a {rows}×{cols} matrix", data.len());
        Self { data, rows, cols, transposed: false }
    }

    /// The transpose of this operand (toggles; no data is moved).
    pub fn t(self) -> Self {
        Self { transposed: !self.transposed, ..self }
    }

    /// Logical row count (after the optional transpose).
    pub fn op_rows(&self) -> usize {
        if self.transposed {
            self.cols
        } else {
            self.rows
        }
    }

    /// Logical column count (after the optional transpose).
    pub fn op_cols(&self) -> usize {
        if self.transposed {
            self.rows
        } else {
            self.cols
        }
    }

    /// (column stride, row stride) of the logical operand, in elements.
    fn strides(&self) -> (isize, isize) {
        let ld = self.cols as isize;
        if self.transposed {
            (ld, 1)
        } else {
            (1, ld)
        }
    }
}

/// `c = a · b` (or `c += a · b` when `accumulate`), all row-major `f32`.
///
/// # Shapes
/// `a` is logically `m × k`, `b` is logically `k × n` (each possibly a transposed view), and `c`
/// is a row-major `m × n` slice of exactly `m · n` values.
///
/// Large products use `Parallelism::Rayon(0)` (the current rayon pool's thread count); small ones
/// run single-threaded.
///
/// # Panics
/// If the inner dimensions disagree or `c.len() != m * n`.
pub fn matmul(a: MatRef<'_>, b: MatRef<'_>, c: &mut [f32], accumulate: bool) {
    let (m, k, n) = (a.op_rows(), a.op_cols(), b.op_cols());
    assert_eq!(b.op_rows(), k, "matmul: inner dimensions differ ({m}×{k} · {}×{n})", b.op_rows());
    assert_eq!(c.len(), m * n, "matmul: destination has {} values, expected {m}×{n}", c.len());
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        // Empty sum: the product is zero.
        if !accumulate {
            c.fill(0.0);
        }
        return;
    }
    let macs = m.saturating_mul(n).saturating_mul(k);
    let parallelism = if macs >= PARALLEL_MIN_MACS && rayon::current_num_threads() > 1 {
        Parallelism::Rayon(0)
    } else {
        Parallelism::None
    };
    let (a_cs, a_rs) = a.strides();
    let (b_cs, b_rs) = b.strides();
    raw_gemm(m, n, k, c, a.data, (a_cs, a_rs), b.data, (b_cs, b_rs), accumulate, parallelism);
}

/// The single `unsafe` call into `gemm`. Every pointer/stride combination is re-checked here so
/// the function is sound for any arguments.
#[allow(unsafe_code, clippy::too_many_arguments)]
fn raw_gemm(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    lhs: &[f32],
    (lhs_cs, lhs_rs): (isize, isize),
    rhs: &[f32],
    (rhs_cs, rhs_rs): (isize, isize),
    accumulate: bool,
    parallelism: Parallelism,
) {
    // Largest element offset reached by a matrix with the given shape and non-negative strides.
    fn last_index(rows: usize, cols: usize, cs: isize, rs: isize) -> usize {
        assert!(cs >= 0 && rs >= 0, "raw_gemm: negative strides are not supported");
        (rows - 1) * rs as usize + (cols - 1) * cs as usize
    }
    assert!(m > 0 && n > 0 && k > 0, "raw_gemm: empty products are handled by the caller");
    assert!(last_index(m, k, lhs_cs, lhs_rs) < lhs.len(), "raw_gemm: lhs out of bounds");
    assert!(last_index(k, n, rhs_cs, rhs_rs) < rhs.len(), "raw_gemm: rhs out of bounds");
    // dst is written densely row-major, so every element is distinct (no aliasing writes).
    assert!(dst.len() >= m * n, "raw_gemm: dst out of bounds");
    let (dst_cs, dst_rs) = (1isize, n as isize);
    // SAFETY: the asserts above prove that every element gemm reads from `lhs` (m×k with strides
    // lhs_cs/lhs_rs) and from `rhs` (k×n with rhs_cs/rhs_rs) and every element it reads/writes in
    // `dst` (m×n, strides 1/n, all distinct) lies inside the respective slice. `dst` is a
    // `&mut` borrow, so it cannot alias `lhs` or `rhs`. gemm only reads `dst` when `read_dst`
    // is true, and the slice is fully initialised anyway. T = f32 is a supported type.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            dst_cs,
            dst_rs,
            accumulate,
            lhs.as_ptr(),
            lhs_cs,
            lhs_rs,
            rhs.as_ptr(),
            rhs_cs,
            rhs_rs,
            1.0, // alpha: weight of the old dst (only used when accumulating)
            1.0, // beta: weight of lhs·rhs
            false,
            false,
            false,
            parallelism,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random(len: usize, rng: &mut impl Rng) -> Vec<f32> {
        (0..len).map(|_| rng.gen_range(-1.0..1.0)).collect()
    }

    /// Reference: element (i, j) of a stored row-major matrix, through an optional transpose.
    fn at(x: &MatRef<'_>, i: usize, j: usize) -> f64 {
        let (r, c) = if x.transposed { (j, i) } else { (i, j) };
        x.data[r * x.cols + c] as f64
    }

    #[test]
    fn matches_naive_for_all_transposes() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // Includes sizes that do not divide the 16-lane SIMD width, non-square shapes and one
        // product large enough to take the parallel path.
        let sizes = [(1, 1, 1), (3, 5, 7), (17, 33, 9), (16, 1, 31), (64, 63, 65), (130, 70, 100)];
        for &(m, k, n) in &sizes {
            for ta in [false, true] {
                for tb in [false, true] {
                    for accumulate in [false, true] {
                        let a_data = random(m * k, &mut rng);
                        let b_data = random(k * n, &mut rng);
                        let a = if ta { MatRef::new(&a_data, k, m).t() } else { MatRef::new(&a_data, m, k) };
                        let b = if tb { MatRef::new(&b_data, n, k).t() } else { MatRef::new(&b_data, k, n) };
                        let c0 = random(m * n, &mut rng);
                        let mut c = c0.clone();
                        matmul(a, b, &mut c, accumulate);
                        for i in 0..m {
                            for j in 0..n {
                                let mut want: f64 = (0..k).map(|p| at(&a, i, p) * at(&b, p, j)).sum();
                                if accumulate {
                                    want += c0[i * n + j] as f64;
                                }
                                let got = c[i * n + j] as f64;
                                assert!(
                                    (got - want).abs() <= 1e-4 * (1.0 + want.abs()),
                                    "m={m} k={k} n={n} ta={ta} tb={tb} acc={accumulate} ({i},{j}): {got} vs {want}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn empty_inner_dimension_gives_zero() {
        let mut c = vec![5.0; 6];
        matmul(MatRef::new(&[], 2, 0), MatRef::new(&[], 0, 3), &mut c, false);
        assert_eq!(c, vec![0.0; 6]);
    }

    #[test]
    #[should_panic(expected = "inner dimensions")]
    fn rejects_mismatched_shapes() {
        let mut c = vec![0.0; 4];
        matmul(MatRef::new(&[0.0; 6], 2, 3), MatRef::new(&[0.0; 4], 2, 2), &mut c, false);
    }
}
