//! What `torch.save` pickles for a state dict, whatever the container (zip or legacy).
//!
//! Tensors appear in the pickle as calls of `torch._utils._rebuild_tensor_v2(storage, offset,
//! size, stride, ...)`, where `storage` is a persistent id `("storage", torch.FloatStorage,
//! key, location, numel[, view_metadata])`. Parameters (`_rebuild_parameter`) and tensor
//! subclasses (`torch._tensor._rebuild_from_type_v2`) wrap such calls. The container says
//! where the storage of each key lies ([`StorageRef`] → byte range).
//!
//! Besides a plain state dict, a training checkpoint that holds one under `teacher` (DINO's
//! `*_full_checkpoint.pth`: the teacher is what DINO evaluates), `state_dict` or `model` is
//! accepted; the `module.` and `backbone.` prefixes of such checkpoints are removed.

use std::collections::{BTreeMap, HashSet};
use std::ops::Range;

use super::pickle::{self, Value};
use super::{contiguous_strides, DType, TensorEntry};

/// Keys under which training checkpoints keep the weights, in order of preference.
const NESTED_KEYS: [&str; 3] = ["teacher", "state_dict", "model"];
/// Prefixes that wrappers add to parameter names.
const PREFIXES: [&str; 2] = ["module.", "backbone."];

/// A storage as a persistent id names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StorageRef {
    /// The storage class name (`FloatStorage`, `LongStorage`, ...).
    pub type_name: String,
    /// The key the container files it under.
    pub key: String,
    /// Its number of elements, where the id gives it.
    pub numel: Option<u64>,
    /// Whether the id names a view into another storage (very old PyTorch versions).
    pub is_view: bool,
}

impl StorageRef {
    /// The element type.
    pub fn dtype(&self) -> DType {
        if self.type_name == "FloatStorage" {
            DType::F32
        } else {
            DType::Other(self.type_name.clone())
        }
    }

    /// Bytes per element of the storage class, where known.
    pub fn element_size(&self) -> Option<usize> {
        let size = match self.type_name.as_str() {
            "DoubleStorage" | "LongStorage" | "ComplexFloatStorage" => 8,
            "FloatStorage" | "IntStorage" | "QInt32Storage" => 4,
            "HalfStorage" | "BFloat16Storage" | "ShortStorage" => 2,
            "ByteStorage" | "CharStorage" | "BoolStorage" | "QInt8Storage" | "QUInt8Storage" => 1,
            "ComplexDoubleStorage" => 16,
            _ => return None,
        };
        Some(size)
    }
}

/// Tensor name → where its values are, for the object a checkpoint pickles; `storage` gives
/// the byte range of a storage in the file.
pub fn read_state_dict(
    root: &Value,
    storage: &dyn Fn(&StorageRef) -> Result<Range<usize>, String>,
) -> Result<BTreeMap<String, TensorEntry>, String> {
    let dict = state_dict_of(root)?;
    let mut entries = BTreeMap::new();
    for (key, value) in dict {
        let Some(name) = key.as_str() else { continue };
        let Some(tensor) = tensor_of(&value, storage).map_err(|e| format!("tensor `{name}`: {e}"))? else {
            continue; // not a tensor (e.g. an int entry of a training checkpoint)
        };
        let mut name = name;
        while let Some(rest) = PREFIXES.iter().find_map(|p| name.strip_prefix(p)) {
            name = rest;
        }
        entries.insert(name.to_string(), tensor);
    }
    if entries.is_empty() {
        return Err(
            "the checkpoint holds no tensors at its top level (nor under `teacher`, `state_dict` or `model`): \
                    not a saved state dict"
                .into(),
        );
    }
    Ok(entries)
}

/// Every storage the pickled object refers to, in the order first met (each key and type once).
/// The walk is iterative and visits shared values once, so a hostile pickle with deep or
/// cyclic structure cannot exhaust the stack.
pub fn storage_refs(root: &Value) -> Result<Vec<StorageRef>, String> {
    let mut out = Vec::new();
    let mut named = HashSet::new();
    let mut seen = HashSet::new();
    let mut todo = vec![root.clone()];
    while let Some(v) = todo.pop() {
        match &v {
            Value::Tuple(t) if seen.insert(std::rc::Rc::as_ptr(t) as usize) => todo.extend(t.iter().rev().cloned()),
            Value::List(l) if seen.insert(std::rc::Rc::as_ptr(l) as usize) => {
                todo.extend(l.borrow().iter().rev().cloned())
            }
            Value::Dict(d) if seen.insert(std::rc::Rc::as_ptr(d) as usize) => {
                for (k, x) in d.borrow().iter().rev() {
                    todo.push(x.clone());
                    todo.push(k.clone());
                }
            }
            Value::Call(c) if seen.insert(std::rc::Rc::as_ptr(c) as usize) => {
                let c = c.borrow();
                todo.extend(c.state.iter().cloned());
                todo.push(c.args.clone());
            }
            Value::Persistent(_) => {
                let r = storage_ref(&v)?;
                if named.insert((r.key.clone(), r.type_name.clone())) {
                    out.push(r);
                }
            }
            _ => {}
        }
    }
    Ok(out)
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
        Value::Call(c) => {
            matches!(c.borrow().callable.global(), Some(("torch._utils" | "torch._tensor", name)) if name.starts_with("_rebuild"))
        }
        _ => false,
    }
}

fn usize_list(v: &Value, what: &str) -> Result<Vec<usize>, String> {
    v.items()
        .ok_or_else(|| format!("{what} is a {}, not a tuple", v.describe()))?
        .iter()
        .map(|x| {
            x.as_int().and_then(|i| usize::try_from(i).ok()).ok_or_else(|| format!("{what} holds {}", x.describe()))
        })
        .collect()
}

/// How many parameter or subclass wrappers may enclose a tensor: torch.save writes one or
/// two, and a hostile file nesting them a million deep would overflow the stack.
const MAX_TENSOR_WRAPPERS: usize = 16;

/// The tensor a pickled value rebuilds, `None` for values that are not tensors.
fn tensor_of(
    v: &Value,
    storage: &dyn Fn(&StorageRef) -> Result<Range<usize>, String>,
) -> Result<Option<TensorEntry>, String> {
    wrapped_tensor(v, storage, 0)
}

/// [`tensor_of`] inside `wrappers` enclosing rebuild calls.
fn wrapped_tensor(
    v: &Value,
    storage: &dyn Fn(&StorageRef) -> Result<Range<usize>, String>,
    wrappers: usize,
) -> Result<Option<TensorEntry>, String> {
    if wrappers > MAX_TENSOR_WRAPPERS {
        return Err(format!("a tensor wrapped in over {MAX_TENSOR_WRAPPERS} rebuild calls"));
    }
    let Value::Call(call) = v else { return Ok(None) };
    let call = call.borrow();
    let Some(func) = call.callable.global() else { return Ok(None) };
    let args = call.args.items().unwrap_or_default();
    match func {
        ("torch._utils", "_rebuild_tensor_v2" | "_rebuild_tensor") => {
            if args.len() < 4 {
                return Err(format!("{}.{} with {} arguments", func.0, func.1, args.len()));
            }
            let sref = storage_ref(&args[0])?;
            let offset =
                args[1].as_int().and_then(|i| usize::try_from(i).ok()).ok_or("storage offset is not an integer")?;
            let shape = usize_list(&args[2], "size")?;
            let mut stride = usize_list(&args[3], "stride")?;
            if stride.is_empty() && !shape.is_empty() {
                stride = contiguous_strides(&shape);
            }
            let range = storage(&sref)?;
            Ok(Some(TensorEntry { dtype: sref.dtype(), shape, stride, offset, storage: range }))
        }
        ("torch._utils", "_rebuild_parameter" | "_rebuild_parameter_with_state") => match args.first() {
            Some(inner) => wrapped_tensor(inner, storage, wrappers + 1),
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
            wrapped_tensor(&inner, storage, wrappers + 1)
        }
        _ => Ok(None),
    }
}

/// The storage a persistent id `("storage", storage_type, key, location, numel[, view])` names.
fn storage_ref(v: &Value) -> Result<StorageRef, String> {
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
    let key = match &items[2] {
        Value::Str(s) => s.to_string(),
        Value::Int(i) => i.to_string(),
        other => return Err(format!("storage key is a {}", other.describe())),
    };
    let numel = items.get(4).and_then(Value::as_int).and_then(|n| u64::try_from(n).ok());
    let is_view = items.get(5).is_some_and(|m| !matches!(m, Value::None));
    Ok(StorageRef { type_name, key, numel, is_view })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `{"w": _rebuild_parameter(_rebuild_parameter(...(None)))}`, `depth` calls deep.
    fn nested_parameters(depth: usize) -> Vec<u8> {
        let mut p = b"\x80\x02}\x8c\x01wctorch._utils\n_rebuild_parameter\nq\x00".to_vec();
        p.extend(b"h\x00".repeat(depth - 1)); // the callable of every level, outermost first
        p.push(b'N');
        p.extend(b"\x85R".repeat(depth)); // each level: (inner,) then the call
        p.extend(b"s.");
        p
    }

    #[test]
    fn tensors_nested_beyond_any_torch_save_are_refused_not_recursed() {
        let no_storage = |_: &StorageRef| -> Result<Range<usize>, String> { Err("no storage".into()) };
        // Within the limit the innermost value is no tensor: nothing is read.
        let shallow = pickle::load(&nested_parameters(3)).unwrap();
        let err = read_state_dict(&shallow, &no_storage).unwrap_err();
        assert!(!err.contains("rebuild calls"), "{err}");
        let deep = pickle::load(&nested_parameters(200_000)).unwrap();
        let err = read_state_dict(&deep, &no_storage).unwrap_err();
        assert!(err.contains("tensor `w`") && err.contains("rebuild calls"), "{err}");
    }
}
