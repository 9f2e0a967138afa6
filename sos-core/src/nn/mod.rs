//! Dense layers on `gemm` + rayon with hand-written backward passes, activations and Adam.
