//! The DINO VisionTransformer forward pass (DINO's `vision_transformer.py`), inference only.
//!
//! Patch embedding (a `p × p` stride-`p` convolution, done as one GEMM over unfolded
//! patches), a \[CLS\] token, position embeddings (interpolated for other grids), then pre-LN
//! blocks `x += proj(attn(norm1(x)))`, `x += fc2(gelu(fc1(norm2(x))))` with multi-head
//! self-attention `softmax(q·kᵀ/√d_head)·v`, exact GELU and LayerNorm ε = 1e-6.
//!
//! Outputs, as the reference uses them: the tokens of the last block BEFORE the final
//! LayerNorm (token 0 is \[CLS\], then the patches row-major) and the last block's attention of
//! the \[CLS\] query over all tokens, averaged over heads. [`Vit::final_norm`] applies the final
//! LayerNorm where the normed tokens are wanted.
//!
//! Activations are row-major `[tokens, channels]` for the whole batch, so every linear layer
//! is one large GEMM (`sos_core::nn::matmul`); attention runs one task per (image, head) on
//! the rayon pool, in blocks of queries so that large images need little memory.

use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use sos_core::nn::{matmul, MatRef, PARALLEL_MIN_MACS};

use super::fastmath::{gelu, softmax_row, sum};
use super::interpolate::interpolate_pos_grid;
use crate::checkpoint::{CheckpointError, StateDict};

/// LayerNorm epsilon of DINO's ViTs.
pub const LN_EPS: f32 = 1e-6;
/// Queries per attention block (bounds the score matrix to `QUERY_BLOCK × tokens`).
const QUERY_BLOCK: usize = 256;
/// Rows per task of the element-wise passes.
const ROWS_PER_TASK: usize = 64;

/// Dimensions of a ViT.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct VitShape {
    /// Patch side in pixels.
    pub patch: usize,
    /// Embedding width.
    pub dim: usize,
    /// Number of blocks.
    pub depth: usize,
    /// Attention heads (divides `dim`).
    pub heads: usize,
    /// Hidden width of the MLPs.
    pub mlp_hidden: usize,
    /// Side of the trained position-embedding grid (14 for 224-px inputs with 16-px patches).
    pub grid: usize,
}

impl VitShape {
    /// A DINO ViT shape: MLP ratio 4, position grid for 224-px inputs.
    pub fn dino(dim: usize, patch: usize, depth: usize, heads: usize) -> VitShape {
        VitShape { patch, dim, depth, heads, mlp_hidden: 4 * dim, grid: 224 / patch }
    }

    /// Number of weights.
    pub fn num_parameters(&self) -> usize {
        let (d, m) = (self.dim, self.mlp_hidden);
        let block = 4 * d + (3 * d * d + 3 * d) + (d * d + d) + (d * m + m) + (m * d + d);
        3 * self.patch * self.patch * d + d + d + (1 + self.grid * self.grid) * d + self.depth * block + 2 * d
    }
}

/// Why a state dict is not a (supported) DINO ViT.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// A tensor could not be read (missing, wrong type, corrupt).
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// The names or shapes are not those of a DINO ViT.
    #[error("not a DINO ViT state dict: {0}")]
    NotDino(String),
}

/// `y = x·W + b` with `W` stored `[in, out]` (PyTorch's `[out, in]`, transposed on load).
#[derive(Debug, Clone, PartialEq)]
pub struct Dense {
    /// Input width.
    pub in_dim: usize,
    /// Output width.
    pub out_dim: usize,
    /// `[in_dim, out_dim]` row-major.
    pub weight: Vec<f32>,
    /// `[out_dim]`.
    pub bias: Vec<f32>,
}

impl Dense {
    /// From PyTorch's `[out, in]` weight.
    pub fn from_torch(weight: &[f32], bias: Vec<f32>, out_dim: usize, in_dim: usize) -> Dense {
        assert_eq!(weight.len(), out_dim * in_dim);
        let mut w = vec![0.0; in_dim * out_dim];
        for o in 0..out_dim {
            for i in 0..in_dim {
                w[i * out_dim + o] = weight[o * in_dim + i];
            }
        }
        Dense { in_dim, out_dim, weight: w, bias }
    }

    /// `y = x·W + b`, or `y += x·W + b` when `accumulate`; `x` is `[rows, in_dim]`.
    pub fn apply(&self, x: &[f32], rows: usize, y: &mut [f32], accumulate: bool) {
        matmul(MatRef::new(x, rows, self.in_dim), MatRef::new(&self.weight, self.in_dim, self.out_dim), y, accumulate);
        let out = self.out_dim;
        y.par_chunks_mut(out * ROWS_PER_TASK).for_each(|chunk| {
            for row in chunk.chunks_exact_mut(out) {
                for (v, b) in row.iter_mut().zip(&self.bias) {
                    *v += b;
                }
            }
        });
    }
}

/// LayerNorm over the last dimension.
#[derive(Debug, Clone, PartialEq)]
pub struct LayerNorm {
    /// Scale.
    pub weight: Vec<f32>,
    /// Shift.
    pub bias: Vec<f32>,
}

impl LayerNorm {
    /// Normalises each row of `x` (`[rows, dim]`) into `out`.
    pub fn apply(&self, x: &[f32], out: &mut [f32]) {
        let dim = self.weight.len();
        out.par_chunks_mut(dim * ROWS_PER_TASK).zip(x.par_chunks(dim * ROWS_PER_TASK)).for_each(|(o, xs)| {
            for (orow, xrow) in o.chunks_exact_mut(dim).zip(xs.chunks_exact(dim)) {
                let mean = sum(xrow) / dim as f32;
                for (o, &v) in orow.iter_mut().zip(xrow) {
                    *o = (v - mean) * (v - mean);
                }
                let inv = 1.0 / (sum(orow) / dim as f32 + LN_EPS).sqrt();
                for (((o, &v), g), b) in orow.iter_mut().zip(xrow).zip(&self.weight).zip(&self.bias) {
                    *o = (v - mean) * inv * g + b;
                }
            }
        });
    }
}

/// One transformer block.
#[derive(Debug, Clone, PartialEq)]
pub struct Block {
    /// Pre-attention norm.
    pub norm1: LayerNorm,
    /// `dim → 3·dim` (q, k, v; heads contiguous within each).
    pub qkv: Dense,
    /// Attention output projection.
    pub proj: Dense,
    /// Pre-MLP norm.
    pub norm2: LayerNorm,
    /// MLP in.
    pub fc1: Dense,
    /// MLP out.
    pub fc2: Dense,
}

/// What [`Vit::forward`] returns for a batch.
#[derive(Debug, Clone, PartialEq)]
pub struct VitOutput {
    /// Images.
    pub batch: usize,
    /// Patch-grid rows.
    pub grid_h: usize,
    /// Patch-grid columns.
    pub grid_w: usize,
    /// Channels.
    pub dim: usize,
    /// `[batch, 1 + grid_h·grid_w, dim]`: last block's output before the final norm.
    pub tokens: Vec<f32>,
    /// `[batch, 1 + grid_h·grid_w]`: last block's \[CLS\]-query attention, mean over heads.
    pub cls_attn: Vec<f32>,
}

impl VitOutput {
    /// Tokens per image (1 + patches).
    pub fn tokens_per_image(&self) -> usize {
        1 + self.grid_h * self.grid_w
    }
}

/// A DINO VisionTransformer with its weights.
#[derive(Debug, Clone, PartialEq)]
pub struct Vit {
    /// Dimensions.
    pub shape: VitShape,
    /// Patch embedding as a dense layer over unfolded `[3, p, p]` patches.
    pub patch_embed: Dense,
    /// `[dim]`.
    pub cls_token: Vec<f32>,
    /// `[1 + grid², dim]`.
    pub pos_embed: Vec<f32>,
    /// Transformer blocks.
    pub blocks: Vec<Block>,
    /// Final norm (only for [`Vit::final_norm`]).
    pub norm: LayerNorm,
}

fn expect_shape(sd: &StateDict, name: &str, want: &[usize]) -> Result<(), LoadError> {
    match sd.shape(name) {
        None => Err(LoadError::NotDino(format!("tensor `{name}` is missing"))),
        Some(s) if s == want => Ok(()),
        Some(s) => Err(LoadError::NotDino(format!("tensor `{name}` has shape {s:?}, expected {want:?}"))),
    }
}

impl VitShape {
    /// Reads the dimensions from a state dict's shapes; `heads` defaults to `dim / 64` (every
    /// DINO ViT has 64-wide heads).
    pub fn detect(sd: &StateDict, heads: Option<usize>) -> Result<VitShape, LoadError> {
        let not_dino = |m: String| Err(LoadError::NotDino(m));
        let dim = match sd.shape("cls_token") {
            Some([1, 1, d]) if *d > 0 => *d,
            Some(s) => return not_dino(format!("`cls_token` has shape {s:?}, expected [1, 1, width]")),
            None => {
                let names: Vec<&str> = sd.names().take(5).collect();
                return not_dino(format!("it has no `cls_token` (its first tensors are {names:?})"));
            }
        };
        let patch = match sd.shape("patch_embed.proj.weight") {
            Some([d, 3, p, q]) if *d == dim && p == q && *p > 0 => *p,
            Some(s) => {
                return not_dino(format!("`patch_embed.proj.weight` has shape {s:?}, expected [{dim}, 3, p, p]"))
            }
            None => return not_dino("`patch_embed.proj.weight` is missing".into()),
        };
        let positions = match sd.shape("pos_embed") {
            Some([1, n, d]) if *d == dim && *n >= 2 => n - 1,
            Some(s) => return not_dino(format!("`pos_embed` has shape {s:?}, expected [1, 1 + grid², {dim}]")),
            None => return not_dino("`pos_embed` is missing".into()),
        };
        let grid = (positions as f64).sqrt().round() as usize;
        if grid.checked_mul(grid) != Some(positions) {
            return not_dino(format!("`pos_embed` has {positions} patch positions, not a square grid"));
        }
        let depth = (0..).take_while(|i| sd.shape(&format!("blocks.{i}.norm1.weight")).is_some()).count();
        if depth == 0 {
            return not_dino("no `blocks.0.*` tensors".into());
        }
        let mlp_hidden = match sd.shape("blocks.0.mlp.fc1.weight") {
            Some([m, d]) if *d == dim => *m,
            Some(s) => return not_dino(format!("`blocks.0.mlp.fc1.weight` has shape {s:?}, expected [hidden, {dim}]")),
            None => return not_dino("`blocks.0.mlp.fc1.weight` is missing".into()),
        };
        let heads = heads.unwrap_or((dim / 64).max(1));
        if heads == 0 || dim % heads != 0 {
            return not_dino(format!("{heads} heads do not divide the width {dim}"));
        }
        Ok(VitShape { patch, dim, depth, heads, mlp_hidden, grid })
    }
}

impl Vit {
    /// Builds the model from a DINO state dict (names as in DINO's `VisionTransformer`),
    /// checking every shape.
    pub fn from_state_dict(sd: &StateDict, shape: VitShape) -> Result<Vit, LoadError> {
        let VitShape { patch, dim: d, depth, mlp_hidden: m, grid, .. } = shape;
        let get = |name: &str, want: &[usize]| -> Result<Vec<f32>, LoadError> {
            expect_shape(sd, name, want)?;
            Ok(sd.f32(name)?)
        };
        let norm = |prefix: &str| -> Result<LayerNorm, LoadError> {
            Ok(LayerNorm {
                weight: get(&format!("{prefix}.weight"), &[d])?,
                bias: get(&format!("{prefix}.bias"), &[d])?,
            })
        };
        let dense = |prefix: &str, out: usize, inp: usize| -> Result<Dense, LoadError> {
            let w = get(&format!("{prefix}.weight"), &[out, inp])?;
            let bias_name = format!("{prefix}.bias");
            // DINO's ViTs have qkv biases; tolerate their absence (qkv_bias=False) as zeros.
            let b = if sd.shape(&bias_name).is_none() && prefix.ends_with("qkv") {
                vec![0.0; out]
            } else {
                get(&bias_name, &[out])?
            };
            Ok(Dense::from_torch(&w, b, out, inp))
        };
        let pw = get("patch_embed.proj.weight", &[d, 3, patch, patch])?;
        let patch_embed = Dense::from_torch(&pw, get("patch_embed.proj.bias", &[d])?, d, 3 * patch * patch);
        let blocks = (0..depth)
            .map(|i| {
                let p = format!("blocks.{i}");
                Ok(Block {
                    norm1: norm(&format!("{p}.norm1"))?,
                    qkv: dense(&format!("{p}.attn.qkv"), 3 * d, d)?,
                    proj: dense(&format!("{p}.attn.proj"), d, d)?,
                    norm2: norm(&format!("{p}.norm2"))?,
                    fc1: dense(&format!("{p}.mlp.fc1"), m, d)?,
                    fc2: dense(&format!("{p}.mlp.fc2"), d, m)?,
                })
            })
            .collect::<Result<Vec<_>, LoadError>>()?;
        Ok(Vit {
            shape,
            patch_embed,
            cls_token: get("cls_token", &[1, 1, d])?,
            pos_embed: get("pos_embed", &[1, 1 + grid * grid, d])?,
            blocks,
            norm: norm("norm")?,
        })
    }

    /// A model with random weights (truncated-normal-like, std ≈ 0.02, as DINO initialises;
    /// norms at identity), for timing and tests.
    pub fn random(shape: VitShape, seed: u64) -> Vit {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.gen_range(-0.035f32..0.035)).collect() };
        let VitShape { patch, dim: d, mlp_hidden: m, grid, .. } = shape;
        let ln = || LayerNorm { weight: vec![1.0; d], bias: vec![0.0; d] };
        let mut dense =
            |inp: usize, out: usize| Dense { in_dim: inp, out_dim: out, weight: draw(inp * out), bias: draw(out) };
        let patch_embed = dense(3 * patch * patch, d);
        let blocks = (0..shape.depth)
            .map(|_| Block {
                norm1: ln(),
                qkv: dense(d, 3 * d),
                proj: dense(d, d),
                norm2: ln(),
                fc1: dense(d, m),
                fc2: dense(m, d),
            })
            .collect();
        let cls_token = draw(d);
        let pos_embed = draw((1 + grid * grid) * d);
        Vit { shape, patch_embed, cls_token, pos_embed, blocks, norm: ln() }
    }

    /// Position embeddings `[1 + gh·gw, dim]` for a `height × width`-pixel input, as DINO's
    /// `interpolate_pos_encoding`: unchanged only for square inputs of the trained grid.
    pub fn pos_embed_for(&self, height: usize, width: usize) -> Vec<f32> {
        let (p, g, d) = (self.shape.patch, self.shape.grid, self.shape.dim);
        let (gh, gw) = (height / p, width / p);
        if gh * gw == g * g && height == width {
            return self.pos_embed.clone();
        }
        let mut out = self.pos_embed[..d].to_vec();
        out.extend(interpolate_pos_grid(&self.pos_embed[d..], g, d, gh, gw));
        out
    }

    /// Runs a batch of normalised images `[batch, 3, height, width]` (NCHW). Pixels beyond the
    /// last whole patch are ignored, as by the strided convolution.
    ///
    /// # Panics
    /// If `images` does not hold `batch·3·height·width` values or the image is smaller than
    /// one patch (the extractor never passes such inputs).
    pub fn forward(&self, images: &[f32], batch: usize, height: usize, width: usize) -> VitOutput {
        let VitShape { patch: p, dim: d, heads, mlp_hidden, .. } = self.shape;
        assert_eq!(images.len(), batch * 3 * height * width, "Vit::forward: input size");
        let (gh, gw) = (height / p, width / p);
        assert!(gh > 0 && gw > 0, "Vit::forward: {height}x{width} is smaller than one {p}-px patch");
        let np = gh * gw;
        let n = np + 1;
        let t = batch * n;

        // Patch embedding: unfold each patch to [3, p, p], one GEMM.
        let k = 3 * p * p;
        let mut cols = vec![0.0f32; batch * np * k];
        cols.par_chunks_mut(k).enumerate().for_each(|(row, out)| {
            let (b, i) = (row / np, row % np);
            let (py, px) = (i / gw, i % gw);
            for c in 0..3 {
                for ky in 0..p {
                    let src = ((b * 3 + c) * height + py * p + ky) * width + px * p;
                    out[(c * p + ky) * p..(c * p + ky + 1) * p].copy_from_slice(&images[src..src + p]);
                }
            }
        });
        let mut patches = vec![0.0f32; batch * np * d];
        self.patch_embed.apply(&cols, batch * np, &mut patches, false);
        drop(cols);

        let pos = self.pos_embed_for(height, width);
        let mut x = vec![0.0f32; t * d];
        x.par_chunks_mut(n * d).enumerate().for_each(|(b, img)| {
            for (j, v) in img[..d].iter_mut().enumerate() {
                *v = self.cls_token[j] + pos[j];
            }
            for i in 0..np {
                let (dst, src) = (&mut img[(1 + i) * d..(2 + i) * d], &patches[(b * np + i) * d..(b * np + i + 1) * d]);
                for ((o, s), q) in dst.iter_mut().zip(src).zip(&pos[(1 + i) * d..(2 + i) * d]) {
                    *o = s + q;
                }
            }
        });
        drop(patches);

        let mut h = vec![0.0f32; t * d];
        let mut qkv = vec![0.0f32; t * 3 * d];
        let mut att = vec![0.0f32; t * d];
        let mut hidden = vec![0.0f32; t * mlp_hidden];
        let mut cls_attn = vec![0.0f32; batch * n];
        for (i, blk) in self.blocks.iter().enumerate() {
            let last = i + 1 == self.blocks.len();
            blk.norm1.apply(&x, &mut h);
            blk.qkv.apply(&h, t, &mut qkv, false);
            attention(&qkv, batch, n, heads, d / heads, &mut att, last.then_some(&mut cls_attn[..]));
            blk.proj.apply(&att, t, &mut x, true);
            blk.norm2.apply(&x, &mut h);
            blk.fc1.apply(&h, t, &mut hidden, false);
            hidden.par_chunks_mut(mlp_hidden * ROWS_PER_TASK).for_each(|c| c.iter_mut().for_each(|v| *v = gelu(*v)));
            blk.fc2.apply(&hidden, t, &mut x, true);
        }
        VitOutput { batch, grid_h: gh, grid_w: gw, dim: d, tokens: x, cls_attn }
    }

    /// The final LayerNorm applied to tokens `[.., dim]` (DINO's `norm`).
    pub fn final_norm(&self, tokens: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0; tokens.len()];
        self.norm.apply(tokens, &mut out);
        out
    }
}

/// Multi-head self-attention of `batch` sequences of `n` tokens. `qkv` is `[batch·n, 3·dim]`
/// (q, k, v, each with the heads side by side); writes `[batch·n, dim]` into `out` and, when
/// asked, the mean over heads of the \[CLS\] query's attention `[batch, n]`.
fn attention(
    qkv: &[f32],
    batch: usize,
    n: usize,
    heads: usize,
    dh: usize,
    out: &mut [f32],
    cls_attn: Option<&mut [f32]>,
) {
    let d = heads * dh;
    let scale = 1.0 / (dh as f32).sqrt();
    // With enough (image, head) tasks to occupy the pool, query blocks small enough that
    // each product runs on its task's thread (nested splitting only adds overhead);
    // otherwise large blocks whose products use the whole pool.
    let query_block = if batch * heads >= 2 * rayon::current_num_threads() {
        ((PARALLEL_MIN_MACS - 1) / (dh * n)).clamp(8, QUERY_BLOCK)
    } else {
        QUERY_BLOCK
    };
    let mut head_out = vec![0.0f32; batch * heads * n * dh];
    let mut cls_rows = vec![0.0f32; batch * heads * n];
    head_out.par_chunks_mut(n * dh).zip(cls_rows.par_chunks_mut(n)).enumerate().for_each(|(task, (o, cls))| {
        let (b, h) = (task / heads, task % heads);
        let mut q = vec![0.0f32; n * dh];
        let mut k = vec![0.0f32; n * dh];
        let mut v = vec![0.0f32; n * dh];
        for i in 0..n {
            let row = &qkv[(b * n + i) * 3 * d..(b * n + i + 1) * 3 * d];
            for j in 0..dh {
                q[i * dh + j] = row[h * dh + j] * scale;
            }
            k[i * dh..(i + 1) * dh].copy_from_slice(&row[d + h * dh..d + (h + 1) * dh]);
            v[i * dh..(i + 1) * dh].copy_from_slice(&row[2 * d + h * dh..2 * d + (h + 1) * dh]);
        }
        let block = query_block.min(n);
        let mut scores = vec![0.0f32; block * n];
        for start in (0..n).step_by(block) {
            let rows = block.min(n - start);
            let s = &mut scores[..rows * n];
            matmul(MatRef::new(&q[start * dh..(start + rows) * dh], rows, dh), MatRef::new(&k, n, dh).t(), s, false);
            s.chunks_exact_mut(n).for_each(softmax_row);
            if start == 0 {
                cls.copy_from_slice(&s[..n]);
            }
            matmul(MatRef::new(s, rows, n), MatRef::new(&v, n, dh), &mut o[start * dh..(start + rows) * dh], false);
        }
    });
    out.par_chunks_mut(d).enumerate().for_each(|(row, orow)| {
        let (b, i) = (row / n, row % n);
        for h in 0..heads {
            let src = ((b * heads + h) * n + i) * dh;
            orow[h * dh..(h + 1) * dh].copy_from_slice(&head_out[src..src + dh]);
        }
    });
    if let Some(c) = cls_attn {
        for b in 0..batch {
            for j in 0..n {
                let sum: f32 = (0..heads).map(|h| cls_rows[(b * heads + h) * n + j]).sum();
                c[b * n + j] = sum / heads as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Attention in f64 with plain loops.
    fn naive(qkv: &[f32], batch: usize, n: usize, heads: usize, dh: usize) -> (Vec<f64>, Vec<f64>) {
        let d = heads * dh;
        let mut out = vec![0.0f64; batch * n * d];
        let mut cls = vec![0.0f64; batch * n];
        let at = |b: usize, i: usize, part: usize, h: usize, j: usize| {
            qkv[(b * n + i) * 3 * d + part * d + h * dh + j] as f64
        };
        for b in 0..batch {
            for h in 0..heads {
                for i in 0..n {
                    let s: Vec<f64> = (0..n)
                        .map(|k| {
                            (0..dh).map(|j| at(b, i, 0, h, j) * at(b, k, 1, h, j)).sum::<f64>() / (dh as f64).sqrt()
                        })
                        .collect();
                    let m = s.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    let e: Vec<f64> = s.iter().map(|v| (v - m).exp()).collect();
                    let z: f64 = e.iter().sum();
                    for j in 0..dh {
                        out[(b * n + i) * d + h * dh + j] = (0..n).map(|k| e[k] / z * at(b, k, 2, h, j)).sum();
                    }
                    if i == 0 {
                        for k in 0..n {
                            cls[b * n + k] += e[k] / z / heads as f64;
                        }
                    }
                }
            }
        }
        (out, cls)
    }

    #[test]
    fn attention_matches_plain_loops_in_both_blockings() {
        // (batch 1, 2 heads): few tasks, large query blocks (300 tokens = 2 blocks);
        // (batch 3, 4 heads): many tasks, small blocks on each task's thread.
        for (batch, heads, n) in [(1usize, 2usize, 300usize), (3, 4, 70)] {
            let dh = 16;
            let d = heads * dh;
            let qkv: Vec<f32> =
                (0..batch * n * 3 * d).map(|i| (((i * 2654435761) % 2001) as f32 / 1000.0 - 1.0) * 1.5).collect();
            let mut out = vec![0.0f32; batch * n * d];
            let mut cls = vec![0.0f32; batch * n];
            attention(&qkv, batch, n, heads, dh, &mut out, Some(&mut cls));
            let (want, want_cls) = naive(&qkv, batch, n, heads, dh);
            let err = out.iter().zip(&want).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
            let err_cls = cls.iter().zip(&want_cls).map(|(a, b)| (*a as f64 - b).abs()).fold(0.0, f64::max);
            assert!(err < 1e-5 && err_cls < 1e-6, "batch {batch} heads {heads}: {err} {err_cls}");
        }
    }

    #[test]
    fn parameter_count_of_vit_s16() {
        // DINO ViT-S/16 has 21.7 M parameters (head excluded).
        let s = VitShape::dino(384, 16, 12, 6);
        assert_eq!(s.num_parameters(), 21_665_664);
        let v = Vit::random(VitShape::dino(64, 16, 2, 2), 0);
        let stored = v.patch_embed.weight.len()
            + v.patch_embed.bias.len()
            + v.cls_token.len()
            + v.pos_embed.len()
            + v.blocks
                .iter()
                .map(|b| {
                    [&b.qkv, &b.proj, &b.fc1, &b.fc2].iter().map(|l| l.weight.len() + l.bias.len()).sum::<usize>()
                        + 2 * (b.norm1.weight.len() + b.norm2.weight.len())
                })
                .sum::<usize>()
            + 2 * v.norm.weight.len();
        assert_eq!(stored, v.shape.num_parameters());
    }
}
