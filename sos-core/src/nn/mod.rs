//! Dense layers on `gemm` + rayon with hand-written backward passes, activations and Adam.
//!
//! All matrices are row-major `f32` slices with explicit batch sizes; a batch of `n` vectors of
//! width `d` is `[n, d]`. Backward passes accumulate parameter gradients ([`Param::grad`]) and
//! [`Adam::step`] consumes and zeros them.

pub mod activation;
pub mod adam;
pub mod compact_tape;
pub mod linear;
pub mod matmul;
pub mod mlp;
pub mod param;
pub mod vector_math;

pub use activation::{add_column_sums, Activation};
pub use adam::Adam;
pub use compact_tape::CompactTape;
pub use linear::Linear;
pub use matmul::{matmul, MatRef, PARALLEL_MIN_MACS};
pub use mlp::{Mlp, MlpTape};
pub use param::Param;
