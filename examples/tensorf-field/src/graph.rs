//! The field as a dfdx computation, generic over the tape: with `NoneTape` it is the plain
//! forward pass, with `OwnedTape` dfdx records it and `backward()` yields the gradient of every
//! parameter tensor. Nothing here is differentiated by hand.

use dfdx::shapes::{Axis, HasShape, Rank0};
use dfdx::tensor::{Cpu, Gradients, OwnedTape, Tape, Trace, WithEmptyTape};
use dfdx::tensor_ops::{BroadcastTo, GatherTo, ReshapeTo, SumTo, TryConcatAlong, TryMatMul};

use crate::layout::COUNT;
use crate::samples::{Corners, Indices, Matrix, Vector};

/// The parameter tensors, by role, each carrying tape `T`.
pub struct Net<T> {
    density_planes: [Matrix<T>; 3],
    density_lines: [Matrix<T>; 3],
    appearance_planes: [Matrix<T>; 3],
    appearance_lines: [Matrix<T>; 3],
    basis: [Matrix<T>; 3],
    w1: Matrix<T>,
    b1: Matrix<T>,
    w2: Matrix<T>,
    b2: Matrix<T>,
}

/// Constants of the density activation.
#[derive(Debug, Clone, Copy)]
pub struct Activation {
    /// Added before the softplus (sets the initial opacity).
    pub shift: f32,
    /// `1 / cell length`: converts optical depth per cell to density per world unit.
    pub inv_cell: f32,
}

fn three<T>(v: &mut std::vec::IntoIter<Matrix<T>>) -> [Matrix<T>; 3] {
    std::array::from_fn(|_| v.next().expect("layout order"))
}

impl<T: Tape<f32, Cpu>> Net<T> {
    /// The tensors in layout order (see [`crate::layout`]).
    pub fn new(tensors: Vec<Matrix<T>>) -> Self {
        assert_eq!(tensors.len(), COUNT);
        let mut it = tensors.into_iter();
        let net = Net {
            density_planes: three(&mut it),
            density_lines: three(&mut it),
            appearance_planes: three(&mut it),
            appearance_lines: three(&mut it),
            basis: three(&mut it),
            w1: it.next().expect("w1"),
            b1: it.next().expect("b1"),
            w2: it.next().expect("w2"),
            b2: it.next().expect("b2"),
        };
        debug_assert!(it.next().is_none());
        net
    }

    /// Density per world unit, `[rows]`.
    pub fn density(self, corners: &Corners, act: Activation) -> Vector<T> {
        density(self.density_planes, self.density_lines, corners, act)
    }

    /// Density `[rows]` and appearance features `[rows, features]` (the segmentation input).
    pub fn appearance(self, corners: &Corners, act: Activation) -> (Vector<T>, Matrix<T>) {
        let sigma = density(self.density_planes, self.density_lines, corners, act);
        (sigma, features(self.appearance_planes, self.appearance_lines, self.basis, corners))
    }

    /// Density `[rows]`, appearance features `[rows, features]` and colour `[rows, 3]`.
    pub fn forward(self, corners: &Corners, view: &Matrix, act: Activation) -> (Vector<T>, Matrix<T>, Matrix<T>) {
        let sigma = density(self.density_planes, self.density_lines, corners, act);
        let features = features(self.appearance_planes, self.appearance_lines, self.basis, corners);
        // The copy leaves the features' history on the tape that reaches the colour (and the
        // loss); the returned copy carries none.
        let copy = features.with_empty_tape();
        let rgb = colour(features, view, self.w1, self.b1, self.w2, self.b2, &corners.mask);
        (sigma, copy, rgb)
    }
}

/// The network over traced copies of the parameter tensors: each gets its own tape, and the
/// tapes merge where the tensors meet in the graph. A copy shares its original's id, under
/// which dfdx files the gradient.
pub fn traced(tensors: &[Matrix]) -> Net<OwnedTape<f32, Cpu>> {
    Net::new(tensors.iter().map(|t| t.leaky_trace()).collect())
}

/// The plain (untaped) network over shared parameter tensors; cloning a dfdx tensor only
/// bumps the reference count of its data.
pub fn plain(tensors: &[Matrix]) -> Net<dfdx::tensor::NoneTape> {
    Net::new(tensors.to_vec())
}

/// Interpolates a table of vertex rows `[vertices, components]` (a plane: four bilinear
/// corners; a line: two linear ones): gather each corner's vertex rows, scale them by the
/// corner's weights, add the corners up. dfdx's gather backward scatters the gradient back
/// onto the vertices.
fn interpolate<T: Tape<f32, Cpu>, const C: usize>(
    table: Matrix<T>,
    index: &[Indices; C],
    weight: &[Matrix; C],
) -> Matrix<T> {
    // One tape per use of the table (the last use keeps the original); they merge in the sum.
    let mut copies: Vec<Matrix<T>> = (1..C).map(|_| table.with_empty_tape()).collect();
    copies.push(table);
    let mut terms = copies.into_iter().zip(index).zip(weight).map(|((t, i), w)| {
        let rows: Matrix<T> = t.gather(i.clone());
        rows * w.clone()
    });
    let first = terms.next().expect("at least one corner");
    terms.fold(first, |acc, t| acc + t)
}

/// Which table set a product reads: its weights are repeated to that width.
#[derive(Clone, Copy)]
enum Set {
    Density = 0,
    Appearance = 1,
}

/// The `[rows, components]` products plane × line of pair `k`.
fn products<T: Tape<f32, Cpu>>(plane: Matrix<T>, line: Matrix<T>, corners: &Corners, set: Set, k: usize) -> Matrix<T> {
    let s = set as usize;
    interpolate(plane, &corners.plane_index[k], &corners.plane_weight[s][k])
        * interpolate(line, &corners.line_index[k], &corners.line_weight[s][k])
}

/// `softplus(x) = max(x, 0) + ln(1 + e^−|x|)`, exact and overflow-free. dfdx 0.13 has no
/// softplus op; `with_empty_tape` lets `x` feed two branches whose tapes merge again.
fn softplus<T: Tape<f32, Cpu>>(x: Vector<T>) -> Vector<T> {
    let positive = x.with_empty_tape().relu();
    let tail = (x.abs().negate().exp() + 1.0).ln();
    tail + positive
}

fn density<T: Tape<f32, Cpu>>(
    planes: [Matrix<T>; 3],
    lines: [Matrix<T>; 3],
    corners: &Corners,
    act: Activation,
) -> Vector<T> {
    let [p0, p1, p2] = planes;
    let [l0, l1, l2] = lines;
    let sum = |m: Matrix<T>| -> Vector<T> { m.sum::<(usize,), Axis<1>>() };
    let d = Set::Density;
    let raw = sum(products(p0, l0, corners, d, 0))
        + sum(products(p1, l1, corners, d, 1))
        + sum(products(p2, l2, corners, d, 2));
    softplus(raw + act.shift) * act.inv_cell * corners.mask.clone()
}

fn features<T: Tape<f32, Cpu>>(
    planes: [Matrix<T>; 3],
    lines: [Matrix<T>; 3],
    basis: [Matrix<T>; 3],
    corners: &Corners,
) -> Matrix<T> {
    let [p0, p1, p2] = planes;
    let [l0, l1, l2] = lines;
    let [b0, b1, b2] = basis;
    // TensoRF concatenates the three pairs' components and applies one basis matrix; three
    // blocks of it summed are the same map without the concatenation.
    let a = Set::Appearance;
    products(p0, l0, corners, a, 0).matmul(b0)
        + products(p1, l1, corners, a, 1).matmul(b1)
        + products(p2, l2, corners, a, 2).matmul(b2)
}

/// `[rows, cols]` plus a `[1, cols]` bias row.
fn add_bias<T: Tape<f32, Cpu>>(x: Matrix<T>, bias: Matrix<T>) -> Matrix<T> {
    let shape = *x.shape();
    let row = bias.reshape_like(&(shape.1,));
    x + row.broadcast_like::<_, Axis<0>>(&shape)
}

fn colour<T: Tape<f32, Cpu>>(
    features: Matrix<T>,
    view: &Matrix,
    w1: Matrix<T>,
    b1: Matrix<T>,
    w2: Matrix<T>,
    b2: Matrix<T>,
    mask: &Vector,
) -> Matrix<T> {
    let input: Matrix<T> = (features, view.clone()).concat_along(Axis::<1>);
    let hidden = add_bias(input.matmul(w1), b1).relu();
    let rgb = add_bias(hidden.matmul(w2), b2).sigmoid();
    let shape = *rgb.shape();
    rgb * mask.clone().broadcast_like::<_, Axis<1>>(&shape)
}

/// The surrogate loss whose parameter gradients are the vector-Jacobian product the trait's
/// `backward` asks for: `Σ σ·∂L/∂σ + Σ c·∂L/∂c`, then dfdx's reverse pass.
pub fn vector_jacobian(
    net: Net<OwnedTape<f32, Cpu>>,
    corners: &Corners,
    view: &Matrix,
    act: Activation,
    grad_density: Vector,
    grad_rgb: Matrix,
) -> Gradients<f32, Cpu> {
    let (sigma, _features, rgb) = net.forward(corners, view, act);
    let loss = (sigma * grad_density).sum::<Rank0, _>() + (rgb * grad_rgb).sum::<Rank0, _>();
    dfdx::tensor_ops::Backward::backward(loss)
}
