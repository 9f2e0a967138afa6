//! PyTorch's zip checkpoint (`torch.save` since 1.6): a zip whose `<prefix>/data.pkl` pickles
//! the saved object, with each tensor storage in its own entry `<prefix>/data/<key>`.
//!
//! Tensors appear in the pickle as calls of `torch._utils._rebuild_tensor_v2(storage, offset,
//! size, stride, ...)`, where `storage` is a persistent id `("storage", torch.FloatStorage,
//! key, location, numel)`. Parameters (`_rebuild_parameter`) and tensor subclasses
//! (`torch._tensor._rebuild_from_type_v2`) wrap such calls.
//!
//! Besides a plain state dict, a training checkpoint that holds one under `teacher` (DINO's
//! `*_full_checkpoint.pth`: the teacher is what DINO evaluates), `state_dict` or `model` is
//! accepted; the `module.` and `backbone.` prefixes of such checkpoints are removed.

use std::collections::BTreeMap;
use std::ops::Range;

use super::checkpoint::{contiguous_strides, DType, TensorEntry};
use super::pickle::{self, Value};
use super::zip;

/// Keys under which training checkpoints keep the weights, in order of preference.
const NESTED_KEYS: [&str; 3] = ["teacher", "state_dict", "model"];
/// Prefixes that wrappers add to parameter names.
const PREFIXES: [&str; 2] = ["module.", "backbone."];

/// Tensor name → where its values are, for a PyTorch zip checkpoint.
pub fn read_entries(bytes: &[u8]) -> Result<BTreeMap<String, TensorEntry>, String> {
    let files = zip::read_entries(bytes)?;
    let pkl_name = files
        .keys()
        .filter(|n| n.ends_with("data.pkl"))
        .min_by_key(|n| n.len())
        .ok_or("zip file without a `data.pkl` entry: not a PyTorch checkpoint")?
        .clone();
    let prefix = &pkl_name[..pkl_name.len() - "data.pkl".len()];
    if let Some(order) = files.get(&format!("{prefix}byteorder")) {
        if &bytes[order.clone()] != b"little" {
            return Err("the checkpoint was saved on a big-endian machine; save it again on a little-endian one".into());
        }
    }
    let root = pickle::load(&bytes[files[&pkl_name].clone()]).map_err(|e| format!("{pkl_name}: {e}"))?;
    let dict = state_dict_of(&root)?;
    let mut entries = BTreeMap::new();
    for (key, value) in dict {
        let Some(name) = key.as_str() else { continue };
        let Some(tensor) = tensor_of(&value, &|storage_key| files.get(&format!("{prefix}data/{storage_key}")).cloned())
            .map_err(|e| format!("tensor `{name}`: {e}"))?
        else {
            continue; // not a tensor (e.g. an int entry of a training checkpoint)
        };
        let mut name = name;
        while let Some(rest) = PREFIXES.iter().find_map(|p| name.strip_prefix(p)) {
            name = rest;
        }
        entries.insert(name.to_string(), tensor);
    }
    if entries.is_empty() {
        return Err("the checkpoint holds no tensors at its top level (nor under `teacher`, `state_dict` or `model`): \
                    not a saved state dict"
            .into());
    }
    Ok(entries)
}

fn dict_items(v: &Value) -> Option<Vec<(Value, Value)>> {
    match v {
        Value::Dict(d) => Some(d.borrow().clone()),
        _ => None,
    }
}

/// The state dict inside the pickled object.
fn state_dict_of(root: &Value) -> Result<Vec<(Value, Value)>, String> {
    let items = dict_items(root).ok_or_else(|| {
        format!("the checkpoint pickles a {} rather than a state dict (save `model.state_dict()`)", root.describe())
    })?;
    let has_tensors = items.iter().any(|(_, v)| is_tensor_call(v));
    if !has_tensors {
        for key in NESTED_KEYS {
            if let Some((_, nested)) = items.iter().find(|(k, _)| k.as_str() == Some(key)) {
                if let Some(inner) = dict_items(nested) {
                    return Ok(inner);
                }
            }
        }
    }
    Ok(items)
}

/// Whether a value is a call of one of PyTorch's tensor-rebuilding functions.
fn is_tensor_call(v: &Value) -> bool {
    match v {
        Value::Call(c) => matches!(c.borrow().callable.global(), Some(("torch._utils" | "torch._tensor", name)) if name.starts_with("_rebuild")),
        _ => false,
    }
}

fn usize_list(v: &Value, what: &str) -> Result<Vec<usize>, String> {
    v.items()
        .ok_or_else(|| format!("{what} is a {}, not a tuple", v.describe()))?
        .iter()
        .map(|x| x.as_int().and_then(|i| usize::try_from(i).ok()).ok_or_else(|| format!("{what} holds {}", x.describe())))
        .collect()
}

/// The tensor a pickled value rebuilds, `None` for values that are not tensors.
fn tensor_of(v: &Value, storage: &dyn Fn(&str) -> Option<Range<usize>>) -> Result<Option<TensorEntry>, String> {
    let Value::Call(call) = v else { return Ok(None) };
    let call = call.borrow();
    let Some(func) = call.callable.global() else { return Ok(None) };
    let args = call.args.items().unwrap_or_default();
    match func {
        ("torch._utils", "_rebuild_tensor_v2" | "_rebuild_tensor") => {
            if args.len() < 4 {
                return Err(format!("{}.{} with {} arguments", func.0, func.1, args.len()));
            }
            let (dtype, key) = storage_of(&args[0])?;
            let offset = args[1].as_int().and_then(|i| usize::try_from(i).ok()).ok_or("storage offset is not an integer")?;
            let shape = usize_list(&args[2], "size")?;
            let mut stride = usize_list(&args[3], "stride")?;
            if stride.is_empty() && !shape.is_empty() {
                stride = contiguous_strides(&shape);
            }
            let range = storage(&key).ok_or_else(|| format!("storage `data/{key}` is missing from the zip (truncated file?)"))?;
            Ok(Some(TensorEntry { dtype, shape, stride, offset, storage: range }))
        }
        ("torch._utils", "_rebuild_parameter" | "_rebuild_parameter_with_state") => match args.first() {
            Some(inner) => tensor_of(inner, storage),
            None => Err("_rebuild_parameter without arguments".into()),
        },
        ("torch._tensor", "_rebuild_from_type_v2") => {
            // (func, type, args, state): the tensor is func(*args).
            let (Some(f), Some(a)) = (args.first(), args.get(2)) else {
                return Err("_rebuild_from_type_v2 with too few arguments".into());
            };
            let inner = Value::Call(std::rc::Rc::new(std::cell::RefCell::new(pickle::Call {
                callable: f.clone(),
                args: a.clone(),
                state: None,
            })));
            tensor_of(&inner, storage)
        }
        _ => Ok(None),
    }
}

/// `(dtype, storage key)` of a persistent id `("storage", storage_type, key, location, numel)`.
fn storage_of(v: &Value) -> Result<(DType, String), String> {
    let Value::Persistent(pid) = v else {
        return Err(format!("tensor storage is a {}, not a persistent id", v.describe()));
    };
    let items = pid.items().ok_or("storage id is not a tuple")?;
    if items.len() < 3 || items[0].as_str() != Some("storage") {
        return Err("storage id is not (\"storage\", type, key, ...)".into());
    }
    let type_name = match &items[1] {
        Value::Global(g) => g.1.clone(),
        other => other.describe(),
    };
    let dtype = if type_name == "FloatStorage" { DType::F32 } else { DType::Other(type_name) };
    let key = match &items[2] {
        Value::Str(s) => s.clone(),
        Value::Int(i) => i.to_string(),
        other => return Err(format!("storage key is a {}", other.describe())),
    };
    Ok((dtype, key))
}
