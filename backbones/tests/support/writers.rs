//! Minimal writers of the two checkpoint formats, for tests only: a PyTorch zip checkpoint as
//! `torch.save` lays it out (pickle protocol 2, memoised globals, `_rebuild_tensor_v2` calls
//! with persistent storage ids, one stored zip entry per storage) and a safetensors file.

use std::path::Path;

use sos_backbones::fixture::F32Array;

/// One tensor to write into a `.pth`.
#[derive(Clone, Debug)]
pub struct PthTensor {
    /// State-dict name.
    pub name: String,
    /// PyTorch storage class (`FloatStorage`, `HalfStorage`, ...).
    pub storage_type: String,
    /// The storage's bytes.
    pub storage: Vec<u8>,
    /// Elements in the storage.
    pub storage_numel: usize,
    /// Element offset of the tensor in the storage.
    pub offset: usize,
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Strides.
    pub stride: Vec<usize>,
}

impl PthTensor {
    /// A contiguous float32 tensor.
    pub fn f32(name: &str, a: &F32Array) -> PthTensor {
        let mut stride = vec![1; a.shape.len()];
        for d in (0..a.shape.len().saturating_sub(1)).rev() {
            stride[d] = stride[d + 1] * a.shape[d + 1];
        }
        PthTensor {
            name: name.into(),
            storage_type: "FloatStorage".into(),
            storage: a.data.iter().flat_map(|v| v.to_le_bytes()).collect(),
            storage_numel: a.data.len(),
            offset: 0,
            shape: a.shape.clone(),
            stride,
        }
    }

    /// A 2-D float32 tensor stored transposed (column-major storage, strides `[1, rows]`) after
    /// `offset` padding elements, as a `.t()` view of a larger storage is saved.
    pub fn f32_transposed_view(name: &str, a: &F32Array, offset: usize) -> PthTensor {
        let (r, c) = (a.shape[0], a.shape[1]);
        let mut storage = vec![-7.0f32; offset];
        for j in 0..c {
            for i in 0..r {
                storage.push(a.data[i * c + j]);
            }
        }
        PthTensor {
            name: name.into(),
            storage_type: "FloatStorage".into(),
            storage_numel: storage.len(),
            storage: storage.iter().flat_map(|v| v.to_le_bytes()).collect(),
            offset,
            shape: vec![r, c],
            stride: vec![1, r],
        }
    }
}

/// Options of [`write_pth`].
#[derive(Clone, Debug, Default)]
pub struct PthOptions {
    /// Folder name inside the zip (`torch.save` uses the file stem, newer versions `archive`).
    pub prefix: String,
    /// Wrap the state dict as DINO's full checkpoints do: `{"teacher": ..., "epoch": 100,
    /// "args": Namespace(...)}` with `module.backbone.` before every name.
    pub as_training_checkpoint: bool,
    /// Mark the storage entries as deflated (a re-zipped checkpoint).
    pub claim_compressed: bool,
}

struct Pickle(Vec<u8>);

impl Pickle {
    fn op(&mut self, b: &[u8]) {
        self.0.extend_from_slice(b);
    }
    fn unicode(&mut self, s: &str) {
        self.0.push(b'X');
        self.0.extend_from_slice(&(s.len() as u32).to_le_bytes());
        self.0.extend_from_slice(s.as_bytes());
    }
    fn int(&mut self, v: usize) {
        self.0.push(b'J');
        self.0.extend_from_slice(&(v as i32).to_le_bytes());
    }
    fn ints(&mut self, vs: &[usize]) {
        self.op(b"(");
        for &v in vs {
            self.int(v);
        }
        self.op(b"t");
    }
}

fn state_dict_pickle(p: &mut Pickle, tensors: &[PthTensor], name_prefix: &str) {
    // OrderedDict() memoised as 0, the rebuild function as 1 (fetched with BINGET after).
    p.op(b"ccollections\nOrderedDict\nq\x00)R(");
    for (i, t) in tensors.iter().enumerate() {
        p.unicode(&format!("{name_prefix}{}", t.name));
        if i == 0 {
            p.op(b"ctorch._utils\n_rebuild_tensor_v2\nq\x01");
        } else {
            p.op(b"h\x01");
        }
        p.op(b"((");
        p.unicode("storage");
        p.op(format!("ctorch\n{}\n", t.storage_type).as_bytes());
        p.unicode(&i.to_string());
        p.unicode("cpu");
        p.int(t.storage_numel);
        p.op(b"tQ");
        p.int(t.offset);
        p.ints(&t.shape);
        p.ints(&t.stride);
        p.op(b"\x89h\x00)RtR");
    }
    p.op(b"u");
}

/// CRC-32 (IEEE) of `data`, as zip entries carry.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

/// A zip file of stored entries; `deflated` marks entries as compressed (method 8) without
/// compressing them.
pub fn zip_bytes(entries: &[(String, Vec<u8>)], deflated: impl Fn(&str) -> bool) -> Vec<u8> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    for (name, data) in entries {
        let offset = out.len() as u32;
        let method: u16 = if deflated(name) { 8 } else { 0 };
        let crc = crc32(data);
        let mut local = Vec::new();
        local.extend(0x0403_4b50u32.to_le_bytes());
        local.extend(20u16.to_le_bytes());
        local.extend(0u16.to_le_bytes());
        local.extend(method.to_le_bytes());
        local.extend([0u8; 4]);
        local.extend(crc.to_le_bytes());
        local.extend((data.len() as u32).to_le_bytes());
        local.extend((data.len() as u32).to_le_bytes());
        local.extend((name.len() as u16).to_le_bytes());
        local.extend(0u16.to_le_bytes());
        local.extend(name.as_bytes());
        out.extend(&local);
        out.extend(data);
        central.extend(0x0201_4b50u32.to_le_bytes());
        central.extend(20u16.to_le_bytes());
        central.extend(20u16.to_le_bytes());
        central.extend(0u16.to_le_bytes());
        central.extend(method.to_le_bytes());
        central.extend([0u8; 4]);
        central.extend(crc.to_le_bytes());
        central.extend((data.len() as u32).to_le_bytes());
        central.extend((data.len() as u32).to_le_bytes());
        central.extend((name.len() as u16).to_le_bytes());
        central.extend([0u8; 8]); // extra, comment, disk, internal attributes
        central.extend(0u32.to_le_bytes());
        central.extend(offset.to_le_bytes());
        central.extend(name.as_bytes());
    }
    let dir_offset = out.len() as u32;
    out.extend(&central);
    out.extend(0x0605_4b50u32.to_le_bytes());
    out.extend([0u8; 4]);
    out.extend((entries.len() as u16).to_le_bytes());
    out.extend((entries.len() as u16).to_le_bytes());
    out.extend((central.len() as u32).to_le_bytes());
    out.extend(dir_offset.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out
}

/// The bytes of a `.pth` holding `tensors`.
pub fn pth_bytes(tensors: &[PthTensor], options: &PthOptions) -> Vec<u8> {
    let prefix = if options.prefix.is_empty() { "archive" } else { options.prefix.as_str() };
    let mut p = Pickle(vec![0x80, 2]);
    if options.as_training_checkpoint {
        p.op(b"}q\x02(");
        p.unicode("teacher");
        state_dict_pickle(&mut p, tensors, "module.backbone.");
        p.unicode("epoch");
        p.int(100);
        p.unicode("args");
        p.op(b"cargparse\nNamespace\n)\x81}(");
        p.unicode("lr");
        p.op(b"G\x3f\x50\x62\x4d\xd2\xf1\xa9\xfc");
        p.op(b"ub");
        p.op(b"u");
    } else {
        state_dict_pickle(&mut p, tensors, "");
    }
    p.op(b".");
    let mut entries = vec![(format!("{prefix}/data.pkl"), p.0), (format!("{prefix}/byteorder"), b"little".to_vec())];
    for (i, t) in tensors.iter().enumerate() {
        entries.push((format!("{prefix}/data/{i}"), t.storage.clone()));
    }
    entries.push((format!("{prefix}/version"), b"3\n".to_vec()));
    zip_bytes(&entries, |name| options.claim_compressed && name.contains("/data/"))
}

/// Writes a `.pth` of float32 tensors.
pub fn write_pth(path: &Path, tensors: &[(String, F32Array)], options: &PthOptions) {
    let ts: Vec<PthTensor> = tensors.iter().map(|(n, a)| PthTensor::f32(n, a)).collect();
    std::fs::write(path, pth_bytes(&ts, options)).expect("write pth");
}

/// The bytes of a safetensors file; `dtype` overrides the type of the named tensors.
pub fn safetensors_bytes(tensors: &[(String, F32Array)], dtype_of: impl Fn(&str) -> &'static str) -> Vec<u8> {
    let mut header = serde_json::Map::new();
    header.insert("__metadata__".into(), serde_json::json!({ "format": "pt" }));
    let mut data = Vec::new();
    for (name, a) in tensors {
        let begin = data.len();
        data.extend(a.data.iter().flat_map(|v| v.to_le_bytes()));
        header.insert(
            name.clone(),
            serde_json::json!({ "dtype": dtype_of(name), "shape": a.shape, "data_offsets": [begin, data.len()] }),
        );
    }
    let mut text = serde_json::Value::Object(header).to_string();
    while !(8 + text.len()).is_multiple_of(8) {
        text.push(' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend(text.as_bytes());
    out.extend(data);
    out
}

/// Writes a float32 safetensors file.
pub fn write_safetensors(path: &Path, tensors: &[(String, F32Array)]) {
    std::fs::write(path, safetensors_bytes(tensors, |_| "F32")).expect("write safetensors");
}
