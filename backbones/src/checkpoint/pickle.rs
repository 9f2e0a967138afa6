//! A small pickle virtual machine: enough of Python's pickle protocols 0–4 to read what
//! `torch.save` writes for a state dict (in the zip and the legacy container), without running
//! any code.
//!
//! Every [`Value`] is cheap to clone (strings and bytes are shared), so a hostile pickle that
//! repeats a memoised value many times costs a few bytes per repeat, not a copy each; the few
//! builtins that do copy a container's items share a budget proportional to the pickle's
//! length.
//!
//! Calls (`REDUCE`, `NEWOBJ`) are not executed: they become [`Value::Call`] records of the
//! callable and its arguments, which the caller interprets (see `pth.rs`). A few builtins
//! that containers depend on are evaluated: `collections.OrderedDict` (an empty or
//! pair-initialised dict), `_codecs.encode` (bytes pickled by Python 3 at protocol 2) and
//! `builtins.set`/`frozenset` (kept as lists). Persistent ids become [`Value::Persistent`].

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

/// A Python value as far as a checkpoint needs one.
#[derive(Debug, Clone)]
pub enum Value {
    /// `None`.
    None,
    /// `True` / `False`.
    Bool(bool),
    /// An integer that fits in 64 bits.
    Int(i64),
    /// A wider integer, as its little-endian two's-complement bytes (e.g. `torch.save`'s
    /// legacy magic number).
    BigInt(Rc<[u8]>),
    /// A float.
    Float(f64),
    /// A `str` (also Python 2 `str` read as Latin-1).
    Str(Rc<str>),
    /// `bytes` / `bytearray`.
    Bytes(Rc<[u8]>),
    /// A tuple.
    Tuple(Rc<Vec<Value>>),
    /// A list (also sets).
    List(Rc<RefCell<Vec<Value>>>),
    /// A dict or `OrderedDict`, in insertion order.
    Dict(Rc<RefCell<Vec<(Value, Value)>>>),
    /// A reference to `module.name`.
    Global(Rc<(String, String)>),
    /// An unevaluated call `callable(*args)`, with the state a later `BUILD` gave it.
    Call(Rc<RefCell<Call>>),
    /// A persistent id (PyTorch uses them for tensor storages).
    Persistent(Rc<Value>),
}

/// A call recorded by `REDUCE` or `NEWOBJ`.
#[derive(Debug, Clone)]
pub struct Call {
    /// The callable (usually a [`Value::Global`]).
    pub callable: Value,
    /// Its positional arguments (a tuple).
    pub args: Value,
    /// State set by `BUILD`, if any.
    pub state: Option<Value>,
}

impl Value {
    /// The string, if this is one.
    pub fn as_str(&self) -> Option<&str> {
        match self {
            Value::Str(s) => Some(s),
            _ => None,
        }
    }

    /// The integer, if this is one (booleans count, as in Python).
    pub fn as_int(&self) -> Option<i64> {
        match self {
            Value::Int(i) => Some(*i),
            Value::Bool(b) => Some(*b as i64),
            _ => None,
        }
    }

    /// Elements of a tuple or list.
    pub fn items(&self) -> Option<Vec<Value>> {
        match self {
            Value::Tuple(t) => Some(t.as_ref().clone()),
            Value::List(l) => Some(l.borrow().clone()),
            _ => None,
        }
    }

    /// Number of items of a tuple, list or dict (0 for other values), without copying them.
    pub fn item_count(&self) -> usize {
        match self {
            Value::Tuple(t) => t.len(),
            Value::List(l) => l.borrow().len(),
            Value::Dict(d) => d.borrow().len(),
            _ => 0,
        }
    }

    /// `(module, name)` of a global.
    pub fn global(&self) -> Option<(&str, &str)> {
        match self {
            Value::Global(g) => Some((g.0.as_str(), g.1.as_str())),
            _ => None,
        }
    }

    /// A short description for messages.
    pub fn describe(&self) -> String {
        match self {
            Value::None => "None".into(),
            Value::Bool(b) => b.to_string(),
            Value::Int(i) => i.to_string(),
            Value::BigInt(b) => format!("{}-byte integer", b.len()),
            Value::Float(f) => f.to_string(),
            Value::Str(s) => format!("{s:?}"),
            Value::Bytes(b) => format!("bytes[{}]", b.len()),
            Value::Tuple(t) => format!("tuple[{}]", t.len()),
            Value::List(l) => format!("list[{}]", l.borrow().len()),
            Value::Dict(d) => format!("dict[{}]", d.borrow().len()),
            Value::Global(g) => format!("{}.{}", g.0, g.1),
            // Not the callable's own description: calls can nest through their callables.
            Value::Call(c) => match c.borrow().callable.global() {
                Some((module, name)) => format!("{module}.{name}(...)"),
                None => "call(...)".into(),
            },
            Value::Persistent(_) => "persistent id".into(),
        }
    }
}

/// A pickle nests values as deep as it likes (a 300 KB file can nest a tuple 300,000 deep),
/// and the compiler's drop would recurse once per level until the stack overflows. This one
/// takes the children of a container it owns alone out into a list and drops them from
/// there, so dropping any value uses the same small stack.
impl Drop for Value {
    fn drop(&mut self) {
        let mut pending = Vec::new();
        take_children(self, &mut pending);
        while let Some(mut v) = pending.pop() {
            take_children(&mut v, &mut pending);
        }
    }
}

/// Moves the children of `v` into `out` when no other value shares its container.
fn take_children(v: &mut Value, out: &mut Vec<Value>) {
    match v {
        Value::Tuple(t) => {
            if let Some(items) = Rc::get_mut(t) {
                out.append(items);
            }
        }
        Value::List(l) => {
            if let Some(items) = Rc::get_mut(l) {
                out.append(items.get_mut());
            }
        }
        Value::Dict(d) => {
            if let Some(pairs) = Rc::get_mut(d) {
                for (k, v) in pairs.get_mut().drain(..) {
                    out.extend([k, v]);
                }
            }
        }
        Value::Call(c) => {
            if let Some(call) = Rc::get_mut(c) {
                let call = call.get_mut();
                out.push(std::mem::replace(&mut call.callable, Value::None));
                out.push(std::mem::replace(&mut call.args, Value::None));
                out.extend(call.state.take());
            }
        }
        Value::Persistent(p) => {
            if let Some(inner) = Rc::get_mut(p) {
                out.push(std::mem::replace(inner, Value::None));
            }
        }
        _ => {}
    }
}

fn tuple(items: Vec<Value>) -> Value {
    Value::Tuple(Rc::new(items))
}

fn new_dict(pairs: Vec<(Value, Value)>) -> Value {
    Value::Dict(Rc::new(RefCell::new(pairs)))
}

/// Evaluates the few builtin calls that containers depend on; `None` leaves the call recorded.
fn builtin_call(callable: &Value, args: &Value) -> Option<Value> {
    let (module, name) = callable.global()?;
    let args = args.items()?;
    match (module, name) {
        ("collections", "OrderedDict") | ("builtins" | "__builtin__", "dict") => {
            let pairs = match args.first() {
                None => Vec::new(),
                Some(list) => list
                    .items()?
                    .into_iter()
                    .map(|p| p.items().filter(|kv| kv.len() == 2).map(|kv| (kv[0].clone(), kv[1].clone())))
                    .collect::<Option<Vec<_>>>()?,
            };
            Some(new_dict(pairs))
        }
        ("_codecs", "encode") => {
            // bytes pickled at protocol <= 2: _codecs.encode(text, "latin1")
            let text = args.first()?.as_str()?;
            Some(Value::Bytes(text.chars().map(|c| c as u32 as u8).collect()))
        }
        ("builtins" | "__builtin__", "set" | "frozenset" | "list") => {
            let items = args.first().map(|a| a.items()).unwrap_or(Some(Vec::new()))?;
            Some(Value::List(Rc::new(RefCell::new(items))))
        }
        ("builtins" | "__builtin__", "tuple") | ("torch", "Size") => {
            Some(tuple(args.first().map(|a| a.items()).unwrap_or(Some(Vec::new()))?))
        }
        _ => None,
    }
}

/// The pickle machine's state.
struct Machine<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: HashMap<u64, Value>,
    /// Container items the evaluated builtin calls have copied so far (see [`Machine::push_call`]).
    copied: usize,
}

/// Container items the builtin calls of a pickle may copy: a few per byte of pickle. A
/// checkpoint's calls copy each container once; a hostile pickle could otherwise call
/// `list` on one memoised million-item list a million times in a few megabytes.
fn copy_budget(pickle_len: usize) -> usize {
    16usize.saturating_mul(pickle_len).saturating_add(1 << 20)
}

impl<'a> Machine<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.data.len())
            .ok_or("pickle ends in the middle of an opcode")?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, String> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Result<u32, String> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Result<u64, String> {
        let b = self.take(8)?;
        Ok(u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
    }
    fn line(&mut self) -> Result<String, String> {
        let rest = &self.data[self.pos..];
        let end = rest.iter().position(|&b| b == b'\n').ok_or("pickle ends in the middle of a text line")?;
        self.pos += end + 1;
        Ok(String::from_utf8_lossy(&rest[..end]).trim_end_matches('\r').to_string())
    }
    fn len_prefixed(&mut self, len: u64) -> Result<&'a [u8], String> {
        let len = usize::try_from(len).map_err(|_| "pickle string too long")?;
        self.take(len)
    }
    fn pop(&mut self) -> Result<Value, String> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err("pickle pops past a mark (corrupt pickle)".into());
        }
        self.stack.pop().ok_or_else(|| "pickle stack underflow (corrupt pickle)".into())
    }
    fn top(&mut self) -> Result<&mut Value, String> {
        self.stack.last_mut().ok_or_else(|| "pickle stack underflow (corrupt pickle)".into())
    }
    fn pop_mark(&mut self) -> Result<Vec<Value>, String> {
        let mark = self.marks.pop().ok_or("pickle has no mark to pop to (corrupt pickle)")?;
        if mark > self.stack.len() {
            return Err("pickle mark above the stack (corrupt pickle)".into());
        }
        Ok(self.stack.split_off(mark))
    }
    fn memo_get(&self, key: u64) -> Result<Value, String> {
        self.memo.get(&key).cloned().ok_or_else(|| format!("pickle refers to memo entry {key} that was never stored"))
    }
    fn memo_put(&mut self, key: u64) -> Result<(), String> {
        let v = self.stack.last().cloned().ok_or("pickle memoises from an empty stack")?;
        self.memo.insert(key, v);
        Ok(())
    }
    fn push_call(&mut self, callable: Value, args: Value) -> Result<(), String> {
        // What an evaluated builtin copies: its argument tuple and that tuple's first item.
        let first = match &args {
            Value::Tuple(t) => t.first().map_or(0, Value::item_count),
            _ => 0,
        };
        self.copied = self.copied.saturating_add(args.item_count()).saturating_add(first);
        if self.copied > copy_budget(self.data.len()) {
            return Err(format!(
                "pickle calls copy over {} container items, far more than a {}-byte checkpoint holds \
                 (corrupt or hostile pickle)",
                copy_budget(self.data.len()),
                self.data.len()
            ));
        }
        let v = builtin_call(&callable, &args)
            .unwrap_or_else(|| Value::Call(Rc::new(RefCell::new(Call { callable, args, state: None }))));
        self.stack.push(v);
        Ok(())
    }
    fn set_items(&mut self, items: Vec<Value>) -> Result<(), String> {
        if !items.len().is_multiple_of(2) {
            return Err("pickle SETITEMS with an odd number of values".into());
        }
        let target = self.top()?;
        match target {
            Value::Dict(d) => {
                let mut d = d.borrow_mut();
                let mut it = items.into_iter();
                while let (Some(k), Some(v)) = (it.next(), it.next()) {
                    d.push((k, v));
                }
                Ok(())
            }
            other => Err(format!("pickle sets items on a {}, not a dict", other.describe())),
        }
    }
    fn append(&mut self, items: Vec<Value>) -> Result<(), String> {
        match self.top()? {
            Value::List(l) => {
                l.borrow_mut().extend(items);
                Ok(())
            }
            other => Err(format!("pickle appends to a {}, not a list", other.describe())),
        }
    }
}

/// A `LONG1`/`LONG4` integer: an [`Value::Int`] when it fits in 64 bits, else a [`Value::BigInt`].
fn int_from_le(bytes: &[u8]) -> Value {
    let Some(&last) = bytes.last() else { return Value::Int(0) };
    let sign = if last & 0x80 != 0 { 0xFF } else { 0 };
    if bytes.len() > 8 {
        // Bytes past the 64th bit that only extend the sign still fit (when bit 63 agrees).
        let fits = bytes[8..].iter().all(|&b| b == sign) && (bytes[7] & 0x80 != 0) == (sign == 0xFF);
        return if fits { int_from_le(&bytes[..8]) } else { Value::BigInt(bytes.into()) };
    }
    let mut buf = [sign; 8];
    buf[..bytes.len()].copy_from_slice(bytes);
    Value::Int(i64::from_le_bytes(buf))
}

fn parse_text_int(line: &str) -> Result<Value, String> {
    let t = line.trim_end_matches('L');
    match t {
        "00" => Ok(Value::Bool(false)),
        "01" => Ok(Value::Bool(true)),
        _ => t.parse::<i64>().map(Value::Int).map_err(|_| format!("pickle integer `{line}` unreadable")),
    }
}

/// Runs a pickle and returns the value it leaves (bytes after its `STOP` are ignored).
pub fn load(data: &[u8]) -> Result<Value, String> {
    load_prefix(data).map(|(v, _)| v)
}

/// Runs the pickle at the start of `data`; returns the value it leaves and the number of
/// bytes it took, up to and including its `STOP` (the legacy `torch.save` format writes
/// several pickles one after the other).
pub fn load_prefix(data: &[u8]) -> Result<(Value, usize), String> {
    let mut m = Machine { data, pos: 0, stack: Vec::new(), marks: Vec::new(), memo: HashMap::new(), copied: 0 };
    loop {
        let at = m.pos;
        let op = m.u8()?;
        match op {
            0x80 => {
                let proto = m.u8()?;
                if proto > 5 {
                    return Err(format!("pickle protocol {proto} is newer than supported (at most 5)"));
                }
            }
            0x95 => {
                m.u64()?; // FRAME: length hint only
            }
            b'.' => return m.pop().map(|v| (v, m.pos)).map_err(|_| "pickle ended with an empty stack".to_string()),
            b'(' => m.marks.push(m.stack.len()),
            b'0' => {
                m.pop()?;
            }
            b'1' => {
                m.pop_mark()?;
            }
            b'2' => {
                let v = m.top()?.clone();
                m.stack.push(v);
            }
            // Integers.
            b'J' => {
                let v = m.u32()? as i32;
                m.stack.push(Value::Int(v as i64));
            }
            b'K' => {
                let v = m.u8()?;
                m.stack.push(Value::Int(v as i64));
            }
            b'M' => {
                let v = m.u16()?;
                m.stack.push(Value::Int(v as i64));
            }
            0x8a => {
                let n = m.u8()? as u64;
                let b = m.len_prefixed(n)?;
                m.stack.push(int_from_le(b));
            }
            0x8b => {
                let n = m.u32()? as u64;
                let b = m.len_prefixed(n)?;
                m.stack.push(int_from_le(b));
            }
            b'I' | b'L' => {
                let line = m.line()?;
                m.stack.push(parse_text_int(&line)?);
            }
            // Floats.
            b'G' => {
                let b = m.take(8)?;
                m.stack.push(Value::Float(f64::from_be_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])));
            }
            b'F' => {
                let line = m.line()?;
                let v = line.trim().parse::<f64>().map_err(|_| format!("pickle float `{line}` unreadable"))?;
                m.stack.push(Value::Float(v));
            }
            // Strings and bytes.
            b'X' | 0x8c | 0x8d => {
                let n = match op {
                    b'X' => m.u32()? as u64,
                    0x8c => m.u8()? as u64,
                    _ => m.u64()?,
                };
                let b = m.len_prefixed(n)?;
                let s = std::str::from_utf8(b).map_err(|_| "pickle string is not UTF-8")?;
                m.stack.push(Value::Str(s.into()));
            }
            b'T' | b'U' => {
                let n = if op == b'T' { m.u32()? as u64 } else { m.u8()? as u64 };
                let b = m.len_prefixed(n)?;
                m.stack.push(Value::Str(b.iter().map(|&c| c as char).collect::<String>().into()));
            }
            b'B' | b'C' | 0x8e | 0x96 => {
                let n = match op {
                    b'B' => m.u32()? as u64,
                    b'C' => m.u8()? as u64,
                    _ => m.u64()?,
                };
                let b = m.len_prefixed(n)?;
                m.stack.push(Value::Bytes(b.into()));
            }
            b'V' => {
                let line = m.line()?;
                m.stack.push(Value::Str(line.into()));
            }
            b'S' => {
                let line = m.line()?;
                let t = line.trim();
                let unquoted = t
                    .strip_prefix('\'')
                    .and_then(|s| s.strip_suffix('\''))
                    .or_else(|| t.strip_prefix('"').and_then(|s| s.strip_suffix('"')))
                    .ok_or_else(|| format!("pickle string `{line}` is not quoted"))?;
                m.stack.push(Value::Str(unquoted.into()));
            }
            // Constants.
            b'N' => m.stack.push(Value::None),
            0x88 => m.stack.push(Value::Bool(true)),
            0x89 => m.stack.push(Value::Bool(false)),
            // Tuples.
            b')' => m.stack.push(tuple(Vec::new())),
            b't' => {
                let items = m.pop_mark()?;
                m.stack.push(tuple(items));
            }
            0x85..=0x87 => {
                let n = (op - 0x84) as usize;
                if m.stack.len() < n || m.marks.last().is_some_and(|&k| k > m.stack.len() - n) {
                    return Err("pickle builds a tuple from too few values (corrupt pickle)".into());
                }
                let items = m.stack.split_off(m.stack.len() - n);
                m.stack.push(tuple(items));
            }
            // Lists and sets.
            b']' | 0x8f => m.stack.push(Value::List(Rc::new(RefCell::new(Vec::new())))),
            b'l' => {
                let items = m.pop_mark()?;
                m.stack.push(Value::List(Rc::new(RefCell::new(items))));
            }
            b'a' => {
                let v = m.pop()?;
                m.append(vec![v])?;
            }
            b'e' | 0x90 => {
                let items = m.pop_mark()?;
                m.append(items)?;
            }
            0x91 => {
                let items = m.pop_mark()?;
                m.stack.push(Value::List(Rc::new(RefCell::new(items))));
            }
            // Dicts.
            b'}' => m.stack.push(new_dict(Vec::new())),
            b'd' => {
                let items = m.pop_mark()?;
                m.stack.push(new_dict(Vec::new()));
                m.set_items(items)?;
            }
            b's' => {
                let v = m.pop()?;
                let k = m.pop()?;
                m.set_items(vec![k, v])?;
            }
            b'u' => {
                let items = m.pop_mark()?;
                m.set_items(items)?;
            }
            // Globals and calls.
            b'c' => {
                let module = m.line()?;
                let name = m.line()?;
                m.stack.push(Value::Global(Rc::new((module, name))));
            }
            0x93 => {
                let name = m.pop()?;
                let module = m.pop()?;
                match (module.as_str(), name.as_str()) {
                    (Some(a), Some(b)) => m.stack.push(Value::Global(Rc::new((a.to_string(), b.to_string())))),
                    _ => return Err("pickle STACK_GLOBAL needs two strings".into()),
                }
            }
            b'R' | 0x81 => {
                let args = m.pop()?;
                let callable = m.pop()?;
                m.push_call(callable, args)?;
            }
            0x92 => {
                let _kwargs = m.pop()?;
                let args = m.pop()?;
                let callable = m.pop()?;
                m.push_call(callable, args)?;
            }
            b'b' => {
                let state = m.pop()?;
                // Other targets (e.g. an OrderedDict's `_metadata` attribute) need no state.
                if let Value::Call(c) = m.top()? {
                    c.borrow_mut().state = Some(state);
                }
            }
            // Memo.
            b'p' => {
                let line = m.line()?;
                let key = line.trim().parse().map_err(|_| format!("pickle memo key `{line}` unreadable"))?;
                m.memo_put(key)?;
            }
            b'q' => {
                let key = m.u8()? as u64;
                m.memo_put(key)?;
            }
            b'r' => {
                let key = m.u32()? as u64;
                m.memo_put(key)?;
            }
            0x94 => {
                let key = m.memo.len() as u64;
                m.memo_put(key)?;
            }
            b'g' => {
                let line = m.line()?;
                let key = line.trim().parse().map_err(|_| format!("pickle memo key `{line}` unreadable"))?;
                let v = m.memo_get(key)?;
                m.stack.push(v);
            }
            b'h' => {
                let key = m.u8()? as u64;
                let v = m.memo_get(key)?;
                m.stack.push(v);
            }
            b'j' => {
                let key = m.u32()? as u64;
                let v = m.memo_get(key)?;
                m.stack.push(v);
            }
            // Persistent ids.
            b'Q' => {
                let pid = m.pop()?;
                m.stack.push(Value::Persistent(Rc::new(pid)));
            }
            b'P' => {
                let line = m.line()?;
                m.stack.push(Value::Persistent(Rc::new(Value::Str(line.into()))));
            }
            other => {
                return Err(format!(
                    "pickle opcode 0x{other:02x} at byte {at} is not supported by this reader (not a plain state dict?)"
                ))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dict_pairs(v: &Value) -> Vec<(Value, Value)> {
        match v {
            Value::Dict(d) => d.borrow().clone(),
            other => panic!("not a dict: {}", other.describe()),
        }
    }

    #[test]
    fn builtins_copying_one_memoised_list_over_and_over_are_stopped() {
        // list(L) a thousand times over one memoised 100,000-item list: 10^8 copies from a
        // pickle of 105 kB.
        let mut p = b"\x80\x02cbuiltins\nlist\nq\x00](".to_vec();
        p.extend(b"N".repeat(100_000));
        p.extend(b"eq\x01");
        p.extend(b"h\x00h\x01\x85R0".repeat(1000));
        p.extend(b"N.");
        let err = load(&p).unwrap_err();
        assert!(err.contains("copy over") && err.contains("hostile"), "{err}");
        // Copying it a few times, as a checkpoint might, is fine.
        let mut few = p[..p.len() - 1000 * 7 - 2].to_vec();
        few.extend(b"h\x00h\x01\x85R0".repeat(3));
        few.extend(b"N.");
        assert!(matches!(load(&few), Ok(Value::None)));
    }

    #[test]
    fn protocol_2_containers_memo_and_calls() {
        // OrderedDict([("a", 1), ("b", (True, -2, 3.5))]) with the ints and globals written as
        // Python writes them, plus a memoised list referenced twice and a recorded call.
        let mut p = vec![0x80, 2];
        p.extend(b"ccollections\nOrderedDict\nq\x00)R");
        p.extend(b"q\x01(X\x01\x00\x00\x00aK\x01");
        p.extend(b"X\x01\x00\x00\x00b\x88J\xfe\xff\xff\xffG\x40\x0c\x00\x00\x00\x00\x00\x00\x87");
        p.extend(b"X\x01\x00\x00\x00l]q\x02(K\x07K\x08eX\x01\x00\x00\x00mh\x02");
        p.extend(b"X\x01\x00\x00\x00cctorch._utils\nf\n(\x8a\x02\x00\x01N\x89tR");
        p.extend(b"u.");
        let v = load(&p).unwrap();
        let pairs = dict_pairs(&v);
        let keys: Vec<&str> = pairs.iter().map(|(k, _)| k.as_str().unwrap()).collect();
        assert_eq!(keys, ["a", "b", "l", "m", "c"]);
        assert_eq!(pairs[0].1.as_int(), Some(1));
        let b = pairs[1].1.items().unwrap();
        assert!(matches!(b[0], Value::Bool(true)));
        assert_eq!(b[1].as_int(), Some(-2));
        assert!(matches!(b[2], Value::Float(f) if f == 3.5));
        // The memoised list is shared, and was filled after being memoised.
        assert_eq!(pairs[3].1.items().unwrap().len(), 2);
        match &pairs[4].1 {
            Value::Call(c) => {
                let c = c.borrow();
                assert_eq!(c.callable.global(), Some(("torch._utils", "f")));
                let args = c.args.items().unwrap();
                assert_eq!(args[0].as_int(), Some(256));
            }
            other => panic!("expected a call, got {}", other.describe()),
        }
    }

    #[test]
    fn protocol_4_frames_and_stack_globals() {
        let mut p = vec![0x80, 4, 0x95];
        p.extend(20u64.to_le_bytes());
        p.extend(b"\x8c\x0bcollections\x94\x8c\x0bOrderedDict\x94\x93\x94)R\x94");
        p.extend(b"\x8c\x01x\x94\x8a\x09\xff\xff\xff\xff\xff\xff\xff\xff\xffs.");
        let v = load(&p).unwrap();
        let pairs = dict_pairs(&v);
        assert_eq!(pairs[0].0.as_str(), Some("x"));
        assert_eq!(pairs[0].1.as_int(), Some(-1));
    }

    #[test]
    fn corrupt_pickles_are_errors_not_panics() {
        for bad in [
            &b""[..],
            b"\x80\x02",
            b"\x80\x02}q\x00(X\x05\x00\x00\x00abc",
            b"\x80\x02h\x05.",
            b"\x80\x02K\x01u.",
            b"\x80\x02t.",
            b"\x80\x02\xff.",
            b"\x80\x09.",
            b"\x80\x02(\x85.",
            b"\x80\x02\x8a\x0a\x01\x01\x01.",
            b"\x80\x02\x8b\xff\xff\xff\xff\x01.",
        ] {
            assert!(load(bad).is_err(), "{bad:?} should fail");
        }
    }

    #[test]
    fn values_nested_300000_deep_load_and_drop_on_a_small_stack() {
        const DEPTH: usize = 300_000;
        // `prefix` DEPTH times, the innermost value, `suffix` DEPTH times.
        let run = |prefix: &[u8], inner: &[u8], suffix: &[u8]| {
            let mut bytes = b"\x80\x02".to_vec();
            bytes.extend(prefix.repeat(DEPTH));
            bytes.extend_from_slice(inner);
            bytes.extend(suffix.repeat(DEPTH));
            bytes.push(b'.');
            // 256 KiB of stack: the compiler's recursive drop needs megabytes for this depth.
            std::thread::Builder::new()
                .stack_size(256 * 1024)
                .spawn(move || load(&bytes).map(|v| v.describe()))
                .unwrap()
                .join()
                .expect("the nested value dropped without overflowing the stack")
                .unwrap()
        };
        assert_eq!(run(b"", b")", b"\x85"), "tuple[1]"); // TUPLE1 of TUPLE1 of ...
        assert_eq!(run(b"", b")", b"Q"), "persistent id"); // BINPERSID of ...
        assert_eq!(run(b"(", b"]", b"l"), "list[1]"); // MARK ... LIST
        assert_eq!(run(b"(N", b"}", b"d"), "dict[1]"); // MARK None ... DICT
        assert_eq!(run(b"cx\ny\n(", b")", b"tR"), "x.y(...)"); // GLOBAL MARK ... TUPLE REDUCE
        assert_eq!(run(b"", b"cx\ny\n", b")R"), "call(...)"); // calls of calls of ... x.y
    }

    #[test]
    fn wide_integers_are_kept_as_bytes_and_concatenated_pickles_are_split() {
        // torch.save's legacy magic number 0x1950a86a20f9469cfc6c, then a second pickle.
        let magic = [0x6c, 0xfc, 0x9c, 0x46, 0xf9, 0x20, 0x6a, 0xa8, 0x50, 0x19];
        let mut p = vec![0x80, 2, 0x8a, 10];
        p.extend(magic);
        p.push(b'.');
        let first_len = p.len();
        p.extend(b"\x80\x02M\xe9\x03.");
        let (v, used) = load_prefix(&p).unwrap();
        assert_eq!(used, first_len);
        assert!(matches!(&v, Value::BigInt(b) if b[..] == magic));
        assert_eq!(load(&p[used..]).unwrap().as_int(), Some(1001));
        // 9 bytes that only extend the sign are still 64-bit integers; 2^63 is not.
        let int = |bytes: &[u8]| int_from_le(bytes).as_int();
        assert_eq!(int(&[0xfe, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff]), Some(-2));
        assert_eq!(int(&[0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f, 0x00]), Some(i64::MAX));
        assert_eq!(int(&[0, 0, 0, 0, 0, 0, 0, 0x80, 0x00]), None);
        assert_eq!(int(&[0x80]), Some(-128));
        assert_eq!(int(&[]), Some(0));
    }

    #[test]
    fn text_protocol_values() {
        let p = b"(lp0\nI01\naI42\naF0.25\naS'hi'\na.";
        let v = load(p).unwrap();
        let items = v.items().unwrap();
        assert!(matches!(items[0], Value::Bool(true)));
        assert_eq!(items[1].as_int(), Some(42));
        assert!(matches!(items[2], Value::Float(f) if f == 0.25));
        assert_eq!(items[3].as_str(), Some("hi"));
    }
}
