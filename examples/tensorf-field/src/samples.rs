//! A block of samples as the dfdx graph reads it: for every plane the rows of its four
//! bilinear corners and their weights, for every line its two linear corners, the mask of
//! samples inside the unit cube, and the encoded view directions. All of it is constant (no
//! gradient flows into positions or directions), so it is computed here in plain Rust and
//! handed to dfdx as index and weight tensors.

use dfdx::tensor::{Cpu, Tensor, TensorFromVec};
use sos_core::camera::Vec3;
use sos_core::encoding::{positional_encoding, positional_encoding_dim};
use sos_core::render::contraction::Contraction;

/// The axis pairs of the three planes and, at the same index, the axis of the line each is
/// multiplied with (TensoRF's `matMode` and `vecMode`).
pub const PLANES: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];
/// See [`PLANES`].
pub const LINES: [usize; 3] = [2, 1, 0];

/// A dfdx `f32` matrix on the CPU (row-major `[rows, cols]`), with tape `T`.
pub type Matrix<T = dfdx::tensor::NoneTape> = Tensor<(usize, usize), f32, Cpu, T>;
/// A dfdx `f32` vector on the CPU, with tape `T`.
pub type Vector<T = dfdx::tensor::NoneTape> = Tensor<(usize,), f32, Cpu, T>;
/// Row indices for `gather`.
pub type Indices = Tensor<(usize,), usize, Cpu>;

/// Corner rows and interpolation weights of a block of samples, padded with empty rows to a
/// fixed count when the caller asks for it.
pub struct Corners {
    /// Per plane and corner `(0,0), (0,1), (1,0), (1,1)`, the vertex row of every sample.
    pub plane_index: [[Indices; 4]; 3],
    /// Bilinear weights matching `plane_index`, repeated across the components of each
    /// table set (density, then appearance when asked for): `[rows, width]`.
    pub plane_weight: Vec<[[Matrix; 4]; 3]>,
    /// Per line and corner (lower, upper), the vertex row of every sample.
    pub line_index: [[Indices; 2]; 3],
    /// Linear weights matching `line_index`, repeated as `plane_weight`.
    pub line_weight: Vec<[[Matrix; 2]; 3]>,
    /// 1 for samples inside the unit cube, 0 outside and for padding.
    pub mask: Vector,
}

/// Lower vertex and the fraction towards the next one, for a unit coordinate on `res`
/// vertices (vertices at `0, 1/(res−1), …, 1`, as `grid_sample` with `align_corners`).
fn cell(u: f32, res: usize) -> (usize, f32) {
    let t = u * (res - 1) as f32;
    let i = (t.floor() as usize).min(res - 2);
    (i, t - i as f32)
}

impl Corners {
    /// The corners of `positions` for planes and lines of `res` vertices per axis, padded
    /// to `rows` rows (`rows >= positions.len()`), with weights for tables of `widths`
    /// components (the density's, and the appearance's when the caller needs it).
    pub fn new(
        dev: &Cpu,
        contraction: &Contraction,
        res: [usize; 3],
        widths: &[usize],
        positions: &[Vec3],
        rows: usize,
    ) -> Self {
        assert!(rows >= positions.len());
        let mut plane_index: [[Vec<usize>; 4]; 3] = std::array::from_fn(|_| std::array::from_fn(|_| vec![0; rows]));
        let mut plane_weight: [[Vec<f32>; 4]; 3] = std::array::from_fn(|_| std::array::from_fn(|_| vec![0.0; rows]));
        let mut line_index: [[Vec<usize>; 2]; 3] = std::array::from_fn(|_| std::array::from_fn(|_| vec![0; rows]));
        let mut line_weight: [[Vec<f32>; 2]; 3] = std::array::from_fn(|_| std::array::from_fn(|_| vec![0.0; rows]));
        let mut mask = vec![0.0; rows];
        for (s, p) in positions.iter().enumerate() {
            let u = contraction.to_unit(*p);
            // Outside the cube (or NaN): all weights stay 0, so every component reads 0, and
            // the mask zeroes the density and colour.
            if !Contraction::inside(u) {
                continue;
            }
            mask[s] = 1.0;
            let cells: [(usize, f32); 3] = std::array::from_fn(|a| cell(u[a], res[a]));
            for (k, &(a, b)) in PLANES.iter().enumerate() {
                let ((ia, fa), (ib, fb)) = (cells[a], cells[b]);
                let corners = [
                    (0, 0, (1.0 - fa) * (1.0 - fb)),
                    (0, 1, (1.0 - fa) * fb),
                    (1, 0, fa * (1.0 - fb)),
                    (1, 1, fa * fb),
                ];
                for (c, (da, db, w)) in corners.into_iter().enumerate() {
                    plane_index[k][c][s] = (ia + da) * res[b] + ib + db;
                    plane_weight[k][c][s] = w;
                }
            }
            for (k, &c) in LINES.iter().enumerate() {
                let (ic, fc) = cells[c];
                (line_index[k][0][s], line_index[k][1][s]) = (ic, ic + 1);
                (line_weight[k][0][s], line_weight[k][1][s]) = (1.0 - fc, fc);
            }
        }
        let index = |v: Vec<usize>| dev.tensor_from_vec(v, (rows,));
        // Weights are written out per component rather than broadcast: dfdx's CPU kernels take
        // a fast path when both operands are contiguous.
        let repeat = |v: &Vec<f32>, width: usize| {
            let mut data = vec![0.0; rows * width];
            for (row, &w) in data.chunks_exact_mut(width).zip(v) {
                row.fill(w);
            }
            dev.tensor_from_vec(data, (rows, width))
        };
        Corners {
            plane_index: plane_index.map(|corners| corners.map(index)),
            plane_weight: widths
                .iter()
                .map(|&w| std::array::from_fn(|k| std::array::from_fn(|c| repeat(&plane_weight[k][c], w))))
                .collect(),
            line_index: line_index.map(|corners| corners.map(index)),
            line_weight: widths
                .iter()
                .map(|&w| std::array::from_fn(|k| std::array::from_fn(|c| repeat(&line_weight[k][c], w))))
                .collect(),
            mask: dev.tensor_from_vec(mask, (rows,)),
        }
    }
}

/// The colour MLP's view input, `[rows, 3·(1 + 2·frequencies)]`: the direction and its
/// positional encoding; padding rows are zero.
pub fn view_encoding(dev: &Cpu, directions: &[Vec3], rows: usize, frequencies: usize) -> Matrix {
    let dim = positional_encoding_dim(3, frequencies);
    let mut data = vec![0.0; rows * dim];
    for (d, row) in directions.iter().zip(data.chunks_exact_mut(dim)) {
        positional_encoding(d, frequencies, row);
    }
    dev.tensor_from_vec(data, (rows, dim))
}
