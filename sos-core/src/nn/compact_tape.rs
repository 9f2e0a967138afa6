//! Tapes kept in half the memory: hidden activations rounded to bfloat16.
//!
//! A stage-2 step keeps the head's tapes for about a million samples between its forward and
//! backward passes, and the hidden activations are most of them. bfloat16 keeps f32's exponent
//! range and 8 significant bits, so a restored
//! activation is within a relative 2⁻⁸ of the one recorded and has its sign: a ReLU's
//! derivative (from the sign) is exact, and only the gradients of the weights that read the
//! activations move, each by at most 2⁻⁸ of `Σ |h| |∂L/∂y|` over the batch.

use rayon::prelude::*;

use super::mlp::MlpTape;

/// Values per parallel task of a conversion.
const CHUNK: usize = 1 << 16;

/// The bfloat16 nearest `x` (ties to even); NaN stays NaN.
pub fn to_bf16(x: f32) -> u16 {
    let bits = x.to_bits();
    if x.is_nan() {
        return ((bits >> 16) as u16) | 0x0040;
    }
    let round = 0x7FFF + ((bits >> 16) & 1);
    (bits.wrapping_add(round) >> 16) as u16
}

/// The f32 a bfloat16 stands for (exact).
pub fn from_bf16(h: u16) -> f32 {
    f32::from_bits(u32::from(h) << 16)
}

/// An [`MlpTape`] with its hidden activations in bfloat16 (input and output as recorded).
#[derive(Clone, Debug, Default)]
pub struct CompactTape {
    n: usize,
    input: Vec<f32>,
    hidden: Vec<Vec<u16>>,
    output: Vec<f32>,
}

impl CompactTape {
    /// Bytes held per sample by a tape of hidden widths `hidden` (and `input` floats per sample
    /// when the input is kept in it).
    pub fn bytes_per_sample(hidden: usize, input: usize) -> usize {
        hidden * std::mem::size_of::<u16>() + input * std::mem::size_of::<f32>()
    }

    /// Overwrites this tape with `tape`, reusing its buffers.
    pub fn store(&mut self, tape: &MlpTape) {
        let (n, input, hidden, output) = tape.parts();
        self.n = n;
        self.input.clear();
        self.input.extend_from_slice(input);
        self.output.clear();
        self.output.extend_from_slice(output);
        self.hidden.resize_with(hidden.len(), Vec::new);
        for (packed, h) in self.hidden.iter_mut().zip(hidden) {
            packed.resize(h.len(), 0);
            packed.par_chunks_mut(CHUNK).zip(h.par_chunks(CHUNK)).for_each(|(p, h)| {
                p.iter_mut().zip(h).for_each(|(p, &v)| *p = to_bf16(v));
            });
        }
    }

    /// Overwrites `tape` with this one's contents, for [`super::Mlp::backward`].
    pub fn restore(&self, tape: &mut MlpTape) {
        let (n, input, hidden, output) = tape.parts_mut();
        *n = self.n;
        input.clear();
        input.extend_from_slice(&self.input);
        output.clear();
        output.extend_from_slice(&self.output);
        hidden.resize_with(self.hidden.len(), Vec::new);
        for (h, packed) in hidden.iter_mut().zip(&self.hidden) {
            h.resize(packed.len(), 0.0);
            h.par_chunks_mut(CHUNK).zip(packed.par_chunks(CHUNK)).for_each(|(h, p)| {
                h.iter_mut().zip(p).for_each(|(h, &p)| *h = from_bf16(p));
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_is_to_nearest_within_two_to_the_minus_eight() {
        for &x in &[0.0f32, -0.0, 1.0, -1.0, 2.71, 1e-30, -7.5e20, 65504.0, 1e38, f32::MIN_POSITIVE] {
            let back = from_bf16(to_bf16(x));
            assert!((back - x).abs() <= x.abs() * 2f32.powi(-8), "{x} -> {back}");
            assert_eq!(back.is_sign_negative(), x.is_sign_negative(), "{x}");
        }
        assert!(from_bf16(to_bf16(f32::NAN)).is_nan());
        assert_eq!(from_bf16(to_bf16(f32::INFINITY)), f32::INFINITY);
        // Ties go to the even neighbour: 1 + 2^-8 lies halfway between 1 and 1 + 2^-7.
        assert_eq!(from_bf16(to_bf16(1.0 + 2f32.powi(-8))), 1.0);
        assert_eq!(from_bf16(to_bf16(1.0 + 3.0 * 2f32.powi(-8))), 1.0 + 2f32.powi(-6));
    }
}
