//! Writes a [`Vit`] as an ONNX model (opset 17), so that the `onnx` extractor and ONNX
//! Runtime can run exactly the native network without Python.
//!
//! The graph has the input `image` `[batch, 3, size, size]` (normalised, fixed size; the
//! batch fixed or symbolic) and the outputs `tokens` `[batch, 1 + patches, dim]` (last block,
//! before the final norm) and `cls_attn` `[batch, 1 + patches]` (last block's \[CLS\]-query
//! attention, mean over heads) — the names and layout of the reference fixture's
//! `model.onnx`. The position embedding for `size` is interpolated once at export time.
//!
//! The protobuf encoding is written directly (field numbers of `onnx.proto`).

use std::path::Path;

use super::model::{Vit, LN_EPS};

const OPSET: u64 = 17;
const IR_VERSION: u64 = 8;
const FLOAT: u64 = 1;
const INT64: u64 = 7;

/// A protobuf message under construction.
#[derive(Default)]
struct Msg(Vec<u8>);

impl Msg {
    fn raw_varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.0.push((v as u8) | 0x80);
            v >>= 7;
        }
        self.0.push(v as u8);
    }
    fn varint(&mut self, field: u64, v: u64) -> &mut Self {
        self.raw_varint(field << 3);
        self.raw_varint(v);
        self
    }
    fn int(&mut self, field: u64, v: i64) -> &mut Self {
        self.varint(field, v as u64)
    }
    fn bytes(&mut self, field: u64, b: &[u8]) -> &mut Self {
        self.raw_varint(field << 3 | 2);
        self.raw_varint(b.len() as u64);
        self.0.extend_from_slice(b);
        self
    }
    fn str(&mut self, field: u64, s: &str) -> &mut Self {
        self.bytes(field, s.as_bytes())
    }
    fn msg(&mut self, field: u64, m: &Msg) -> &mut Self {
        self.bytes(field, &m.0)
    }
    fn float(&mut self, field: u64, f: f32) -> &mut Self {
        self.raw_varint(field << 3 | 5);
        self.0.extend_from_slice(&f.to_le_bytes());
        self
    }
}

/// An attribute: `(name, value)`.
enum Attr {
    Int(&'static str, i64),
    Ints(&'static str, Vec<i64>),
    Float(&'static str, f32),
}

impl Attr {
    fn encode(&self) -> Msg {
        let mut m = Msg::default();
        match self {
            Attr::Int(name, v) => {
                m.str(1, name).int(3, *v).varint(20, 2);
            }
            Attr::Ints(name, vs) => {
                m.str(1, name);
                for v in vs {
                    m.int(8, *v);
                }
                m.varint(20, 7);
            }
            Attr::Float(name, v) => {
                m.str(1, name).float(2, *v).varint(20, 1);
            }
        }
        m
    }
}

/// A graph under construction.
#[derive(Default)]
struct Graph {
    nodes: Vec<Msg>,
    initializers: Vec<Msg>,
    count: usize,
}

impl Graph {
    fn fresh(&mut self, hint: &str) -> String {
        self.count += 1;
        format!("{hint}_{}", self.count)
    }

    fn tensor(&mut self, name: &str, dims: &[usize], data_type: u64, raw: Vec<u8>) {
        let mut t = Msg::default();
        for &d in dims {
            t.int(1, d as i64);
        }
        t.varint(2, data_type).str(8, name).bytes(9, &raw);
        self.initializers.push(t);
    }

    fn f32(&mut self, hint: &str, dims: &[usize], data: &[f32]) -> String {
        assert_eq!(dims.iter().product::<usize>(), data.len(), "initializer {hint}");
        let name = self.fresh(hint);
        self.tensor(&name, dims, FLOAT, data.iter().flat_map(|v| v.to_le_bytes()).collect());
        name
    }

    fn i64s(&mut self, hint: &str, dims: &[usize], data: &[i64]) -> String {
        let name = self.fresh(hint);
        self.tensor(&name, dims, INT64, data.iter().flat_map(|v| v.to_le_bytes()).collect());
        name
    }

    /// Adds a node and returns its (first) output name.
    fn op(&mut self, op_type: &str, inputs: &[&str], attrs: &[Attr]) -> String {
        let out = self.fresh(&op_type.to_lowercase());
        self.op_to(op_type, inputs, attrs, &out);
        out
    }

    fn op_to(&mut self, op_type: &str, inputs: &[&str], attrs: &[Attr], output: &str) {
        let mut n = Msg::default();
        for i in inputs {
            n.str(1, i);
        }
        n.str(2, output).str(3, &format!("{op_type}_{}", self.nodes.len())).str(4, op_type);
        for a in attrs {
            n.msg(5, &a.encode());
        }
        self.nodes.push(n);
    }
}

/// `ValueInfoProto` of a float tensor; `None` dimensions are symbolic (`batch`).
fn value_info(name: &str, dims: &[Option<usize>]) -> Msg {
    let mut shape = Msg::default();
    for d in dims {
        let mut dim = Msg::default();
        match d {
            Some(v) => dim.int(1, *v as i64),
            None => dim.str(2, "batch"),
        };
        shape.msg(1, &dim);
    }
    let mut tensor = Msg::default();
    tensor.varint(1, FLOAT).msg(2, &shape);
    let mut ty = Msg::default();
    ty.msg(1, &tensor);
    let mut vi = Msg::default();
    vi.str(1, name).msg(2, &ty);
    vi
}

/// The ONNX model bytes of `model` for `size × size` inputs, with a fixed batch or (`None`)
/// a symbolic one.
///
/// # Panics
/// If `size` is smaller than one patch.
pub fn export_vit(model: &Vit, size: usize, batch: Option<usize>) -> Vec<u8> {
    let s = model.shape;
    let (p, d, heads) = (s.patch, s.dim, s.heads);
    assert!(size >= p, "export_vit: input {size} is smaller than a {p}-px patch");
    let dh = d / heads;
    let np = (size / p) * (size / p);
    let n = np + 1;
    let mut g = Graph::default();

    // Patch embedding: Conv with the [D, 3, p, p] kernel (the dense layer stores it transposed).
    let k = 3 * p * p;
    let mut conv_w = vec![0.0f32; d * k];
    for i in 0..k {
        for o in 0..d {
            conv_w[o * k + i] = model.patch_embed.weight[i * d + o];
        }
    }
    let w = g.f32("patch_embed_w", &[d, 3, p, p], &conv_w);
    let b = g.f32("patch_embed_b", &[d], &model.patch_embed.bias);
    let conv = g.op(
        "Conv",
        &["image", &w, &b],
        &[Attr::Ints("kernel_shape", vec![p as i64; 2]), Attr::Ints("strides", vec![p as i64; 2])],
    );
    let shape = g.i64s("shape", &[3], &[0, d as i64, -1]);
    let flat = g.op("Reshape", &[&conv, &shape], &[]);
    let patches = g.op("Transpose", &[&flat], &[Attr::Ints("perm", vec![0, 2, 1])]);

    // [CLS] broadcast to the batch: Expand to (batch, 1, D).
    let img_shape = g.op("Shape", &["image"], &[]);
    let (starts, ends, axes) = (g.i64s("starts", &[1], &[0]), g.i64s("ends", &[1], &[1]), g.i64s("axes", &[1], &[0]));
    let batch_dim = g.op("Slice", &[&img_shape, &starts, &ends, &axes], &[]);
    let rest = g.i64s("rest", &[2], &[1, d as i64]);
    let cls_shape = g.op("Concat", &[&batch_dim, &rest], &[Attr::Int("axis", 0)]);
    let cls = g.f32("cls_token", &[1, 1, d], &model.cls_token);
    let cls_b = g.op("Expand", &[&cls, &cls_shape], &[]);
    let tokens = g.op("Concat", &[&cls_b, &patches], &[Attr::Int("axis", 1)]);
    let pos = g.f32("pos_embed", &[1, n, d], &model.pos_embed_for(size, size));
    let mut x = g.op("Add", &[&tokens, &pos], &[]);

    let qkv_shape = g.i64s("qkv_shape", &[5], &[0, 0, 3, heads as i64, dh as i64]);
    let merge_shape = g.i64s("merge_shape", &[3], &[0, 0, d as i64]);
    let index: Vec<String> = (0..3).map(|i| g.i64s("index", &[], &[i])).collect();
    let scale = g.f32("scale", &[], &[1.0 / (dh as f32).sqrt()]);
    let inv_sqrt2 = g.f32("inv_sqrt2", &[], &[std::f32::consts::FRAC_1_SQRT_2]);
    let one = g.f32("one", &[], &[1.0]);
    let half = g.f32("half", &[], &[0.5]);
    let mut cls_attn = String::new();
    for (bi, blk) in model.blocks.iter().enumerate() {
        let layer_norm = |g: &mut Graph, x: &str, ln: &super::model::LayerNorm| {
            let w = g.f32("ln_w", &[d], &ln.weight);
            let b = g.f32("ln_b", &[d], &ln.bias);
            g.op("LayerNormalization", &[x, &w, &b], &[Attr::Int("axis", -1), Attr::Float("epsilon", LN_EPS)])
        };
        let dense = |g: &mut Graph, x: &str, l: &super::model::Dense| {
            let w = g.f32("w", &[l.in_dim, l.out_dim], &l.weight);
            let b = g.f32("b", &[l.out_dim], &l.bias);
            let y = g.op("MatMul", &[x, &w], &[]);
            g.op("Add", &[&y, &b], &[])
        };
        let h = layer_norm(&mut g, &x, &blk.norm1);
        let qkv = dense(&mut g, &h, &blk.qkv);
        let split = g.op("Reshape", &[&qkv, &qkv_shape], &[]);
        let heads_first = g.op("Transpose", &[&split], &[Attr::Ints("perm", vec![2, 0, 3, 1, 4])]);
        let q = g.op("Gather", &[&heads_first, &index[0]], &[Attr::Int("axis", 0)]);
        let k = g.op("Gather", &[&heads_first, &index[1]], &[Attr::Int("axis", 0)]);
        let v = g.op("Gather", &[&heads_first, &index[2]], &[Attr::Int("axis", 0)]);
        let qs = g.op("Mul", &[&q, &scale], &[]);
        let kt = g.op("Transpose", &[&k], &[Attr::Ints("perm", vec![0, 1, 3, 2])]);
        let scores = g.op("MatMul", &[&qs, &kt], &[]);
        let attn = g.op("Softmax", &[&scores], &[Attr::Int("axis", -1)]);
        if bi + 1 == model.blocks.len() {
            let (s0, s1, s2) = (g.i64s("starts", &[1], &[0]), g.i64s("ends", &[1], &[1]), g.i64s("axes", &[1], &[2]));
            let cls_row = g.op("Slice", &[&attn, &s0, &s1, &s2], &[]);
            cls_attn = g.op("ReduceMean", &[&cls_row], &[Attr::Ints("axes", vec![1, 2]), Attr::Int("keepdims", 0)]);
        }
        let o = g.op("MatMul", &[&attn, &v], &[]);
        let o = g.op("Transpose", &[&o], &[Attr::Ints("perm", vec![0, 2, 1, 3])]);
        let o = g.op("Reshape", &[&o, &merge_shape], &[]);
        let o = dense(&mut g, &o, &blk.proj);
        x = g.op("Add", &[&x, &o], &[]);
        let h = layer_norm(&mut g, &x, &blk.norm2);
        let u = dense(&mut g, &h, &blk.fc1);
        let z = g.op("Mul", &[&u, &inv_sqrt2], &[]);
        let e = g.op("Erf", &[&z], &[]);
        let e = g.op("Add", &[&e, &one], &[]);
        let y = g.op("Mul", &[&u, &e], &[]);
        let y = g.op("Mul", &[&y, &half], &[]);
        let y = dense(&mut g, &y, &blk.fc2);
        x = g.op("Add", &[&x, &y], &[]);
    }
    g.op_to("Identity", &[&x], &[], "tokens");
    g.op_to("Identity", &[&cls_attn], &[], "cls_attn");

    let mut graph = Msg::default();
    for node in &g.nodes {
        graph.msg(1, node);
    }
    graph.str(2, "dino_vit");
    for t in &g.initializers {
        graph.msg(5, t);
    }
    graph.msg(11, &value_info("image", &[batch, Some(3), Some(size), Some(size)]));
    graph.msg(12, &value_info("tokens", &[batch, Some(n), Some(d)]));
    graph.msg(12, &value_info("cls_attn", &[batch, Some(n)]));
    let mut opset = Msg::default();
    opset.str(1, "").varint(2, OPSET);
    let mut model_msg = Msg::default();
    model_msg.varint(1, IR_VERSION).str(2, "nerf-sos").str(3, env!("CARGO_PKG_VERSION")).msg(7, &graph).msg(8, &opset);
    model_msg.0
}

/// Writes [`export_vit`]'s bytes to `path`.
pub fn write_vit(model: &Vit, size: usize, batch: Option<usize>, path: &Path) -> std::io::Result<()> {
    std::fs::write(path, export_vit(model, size, batch))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dino_vit::model::VitShape;

    #[test]
    fn varints_and_structure() {
        let mut m = Msg::default();
        m.varint(1, 300);
        assert_eq!(m.0, vec![0x08, 0xAC, 0x02]);
        let mut m = Msg::default();
        m.int(3, -1);
        assert_eq!(m.0.len(), 1 + 10);
        let vit = Vit::random(VitShape::dino(64, 16, 2, 2), 1);
        let bytes = export_vit(&vit, 224, None);
        // Starts with ir_version = 8 and holds every weight once (as raw little-endian f32).
        assert_eq!(&bytes[..2], &[0x08, 0x08]);
        let needle: Vec<u8> = vit.blocks[1].fc2.weight[..4].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert!(bytes.windows(needle.len()).any(|w| w == needle.as_slice()));
        assert!(bytes.len() > vit.shape.num_parameters() * 4);
    }
}
