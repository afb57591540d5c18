//! PyTorch checkpoints (`torch.save`, the zip format of torch ≥ 1.6) read without Python.
//!
//! The archive holds `<root>/data.pkl` (a protocol-2 pickle of the saved object) and one
//! entry `<root>/data/<key>` per storage, little-endian; `<root>` is any folder name (torch
//! uses the file stem) and the other records (`version`, `byteorder`, `.format_version`, ...)
//! are optional. The pickle is decoded with [`pickle::load_restricted`] (only the globals in
//! [`ALLOWED_GLOBALS`]) and turned into a [`Value`] tree: `collections.OrderedDict` becomes a
//! dict, `torch._utils._rebuild_tensor_v2` a dense C-order [`Array`] gathered from its storage
//! by shape, strides and offset, numpy scalars (`numpy.core.multiarray.scalar` of a
//! `numpy.dtype` and `_codecs.encode` bytes, as in optimiser and scheduler state) plain
//! numbers. Errors name the file and, below the pickle, the key path (`model/fg.params.means`).
//! Typed accessors ([`Checkpoint::floats`], ...) check dtype and shape, binding named
//! dimensions ([`Dims`]) so that `G` means the same count in every key.

use std::collections::HashMap;
use std::io::{Cursor, Read};
use std::path::{Path, PathBuf};

use super::array::{Array, DType};
use super::pickle::{self, PickleError, Value as Pv};
use crate::util::fs::IoError;

/// The globals a checkpoint's pickle may name; anything else is refused.
pub const ALLOWED_GLOBALS: &[(&str, &str)] = &[
    ("collections", "OrderedDict"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"),
    ("torch", "FloatStorage"),
    ("torch", "DoubleStorage"),
    ("torch", "HalfStorage"),
    ("torch", "BFloat16Storage"),
    ("torch", "LongStorage"),
    ("torch", "IntStorage"),
    ("torch", "ShortStorage"),
    ("torch", "CharStorage"),
    ("torch", "ByteStorage"),
    ("torch", "BoolStorage"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "dtype"),
    ("_codecs", "encode"),
];

/// Errors of reading a checkpoint; each names the file.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be read.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The file is not a zip-format PyTorch checkpoint.
    #[error("{}: not a PyTorch checkpoint: {msg}", path.display())]
    NotCheckpoint {
        /// The file.
        path: PathBuf,
        /// Why.
        msg: String,
    },
    /// The zip container is truncated or corrupt.
    #[error("{}: truncated or corrupt checkpoint archive: {msg}", path.display())]
    Archive {
        /// The file.
        path: PathBuf,
        /// The zip error.
        msg: String,
    },
    /// `data.pkl` could not be decoded.
    #[error("{}: {entry}: {cause}", path.display())]
    Pickle {
        /// The file.
        path: PathBuf,
        /// The pickle entry.
        entry: String,
        /// The decoding error.
        cause: PickleError,
    },
    /// A value below the pickle is wrong: missing, bad type or shape, broken storage.
    #[error("{}: key '{key}': {msg}", path.display())]
    Key {
        /// The file.
        path: PathBuf,
        /// The key path, `/`-separated.
        key: String,
        /// What is wrong.
        msg: String,
    },
}

/// Result alias of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// A decoded value of a checkpoint.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// A bool.
    Bool(bool),
    /// An int (also numpy integer scalars).
    Int(i64),
    /// A float (also numpy float scalars).
    Float(f64),
    /// A str.
    Str(String),
    /// A bytes object.
    Bytes(Vec<u8>),
    /// A list or tuple.
    List(Vec<Value>),
    /// A dict or OrderedDict, in insertion order.
    Dict(Vec<(Value, Value)>),
    /// A tensor, materialised in C order.
    Tensor(Array),
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

    /// The str keys of a dict (empty for other values).
    pub fn keys(&self) -> Vec<&str> {
        match self {
            Value::Dict(items) => items
                .iter()
                .filter_map(|(k, _)| if let Value::Str(s) = k { Some(s.as_str()) } else { None })
                .collect(),
            _ => Vec::new(),
        }
    }

    fn kind(&self) -> String {
        match self {
            Value::None => "None".into(),
            Value::Bool(_) => "a bool".into(),
            Value::Int(_) => "an int".into(),
            Value::Float(_) => "a float".into(),
            Value::Str(_) => "a str".into(),
            Value::Bytes(_) => "bytes".into(),
            Value::List(_) => "a list".into(),
            Value::Dict(_) => "a dict".into(),
            Value::Tensor(t) => format!("a {} tensor of shape {:?}", t.dtype.name(), t.shape),
        }
    }
}

/// A dimension of an expected shape: a fixed size or a named count bound on first use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dim {
    /// Exactly this size.
    Is(usize),
    /// A named count (`G`, `T`, ...), the same in every key of one [`Dims`].
    Named(&'static str),
}

impl std::fmt::Display for Dim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Dim::Is(n) => write!(f, "{n}"),
            Dim::Named(s) => write!(f, "{s}"),
        }
    }
}

/// Named dimensions bound while reading a checkpoint: `(name, size, key that bound it)`.
#[derive(Debug, Clone, Default)]
pub struct Dims {
    bound: Vec<(&'static str, usize, String)>,
}

impl Dims {
    /// The size bound to `name`, if any.
    pub fn get(&self, name: &str) -> Option<usize> {
        self.bound.iter().find(|(n, _, _)| *n == name).map(|(_, s, _)| *s)
    }

    /// Bind `name` to `size` (as if read from `key`), unless already bound.
    pub fn bind(&mut self, name: &'static str, size: usize, key: &str) {
        if self.get(name).is_none() {
            self.bound.push((name, size, key.to_string()));
        }
    }

    /// Check `shape` against `want`, binding unbound names; the error text on mismatch.
    fn check(
        &mut self,
        want: &[Dim],
        shape: &[usize],
        key: &str,
    ) -> std::result::Result<(), String> {
        let spec = want.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ");
        let mut fresh = Vec::new();
        let mut ok = want.len() == shape.len();
        let mut why = String::new();
        if ok {
            for (d, s) in want.iter().zip(shape) {
                match d {
                    Dim::Is(n) if n != s => ok = false,
                    Dim::Named(name) => {
                        let bound = self
                            .bound
                            .iter()
                            .find(|(n, _, _)| n == name)
                            .map(|(_, v, k)| (*v, k.clone()))
                            .or_else(|| {
                                fresh
                                    .iter()
                                    .find(|(n, _)| n == name)
                                    .map(|(_, v)| (*v, key.to_string()))
                            });
                        match bound {
                            Some((v, from)) if v != *s => {
                                ok = false;
                                why = format!(" with {name} = {v} (from '{from}')");
                            }
                            Some(_) => {}
                            None => fresh.push((*name, *s)),
                        }
                    }
                    Dim::Is(_) => {}
                }
            }
        }
        if !ok {
            return Err(format!("expected shape [{spec}]{why}, found {shape:?}"));
        }
        for (n, s) in fresh {
            self.bind(n, s, key);
        }
        Ok(())
    }
}

/// A decoded checkpoint: the file name (for errors) and the value tree.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    /// The file (named in errors).
    pub path: PathBuf,
    /// The saved object.
    pub root: Value,
}

/// Storage type name → dtype.
fn storage_dtype(name: &str) -> Option<DType> {
    Some(match name {
        "FloatStorage" => DType::F32,
        "DoubleStorage" => DType::F64,
        "HalfStorage" => DType::F16,
        "BFloat16Storage" => DType::BF16,
        "LongStorage" => DType::I64,
        "IntStorage" => DType::I32,
        "ShortStorage" => DType::I16,
        "CharStorage" => DType::I8,
        "ByteStorage" => DType::U8,
        "BoolStorage" => DType::Bool,
        _ => return None,
    })
}

/// Decoding state: the archive, the storage folder and a cache of storages read.
struct Decoder<'a> {
    path: &'a Path,
    zip: zip::ZipArchive<Cursor<&'a [u8]>>,
    root: String,
    storages: HashMap<String, Vec<u8>>,
}

impl Checkpoint {
    /// Read and decode the checkpoint file `path`.
    pub fn open(path: &Path) -> Result<Checkpoint> {
        let bytes = std::fs::read(path).map_err(IoError::at(path))?;
        Self::from_bytes(path, &bytes)
    }

    /// Decode checkpoint bytes; `path` names them in errors.
    pub fn from_bytes(path: &Path, bytes: &[u8]) -> Result<Checkpoint> {
        let not = |msg: &str| Error::NotCheckpoint { path: path.to_path_buf(), msg: msg.into() };
        if bytes.first() == Some(&0x80) {
            return Err(not(
                "a bare pickle (the legacy format of torch < 1.6); re-save it with a recent torch",
            ));
        }
        if !bytes.starts_with(b"PK") {
            return Err(not("not a zip archive"));
        }
        let zip = zip::ZipArchive::new(Cursor::new(bytes))
            .map_err(|e| Error::Archive { path: path.to_path_buf(), msg: e.to_string() })?;
        let pkl = zip
            .file_names()
            .filter_map(|n| n.ok().map(|n| n.into_owned()))
            .filter(|n| n.ends_with("/data.pkl") && n.matches('/').count() == 1)
            .min()
            .ok_or_else(|| not("the zip archive has no <root>/data.pkl entry"))?;
        let root = pkl.trim_end_matches("data.pkl").to_string();
        let mut d = Decoder { path, zip, root, storages: HashMap::new() };
        if let Some(order) = d.entry_if_present(&format!("{}byteorder", d.root))?
            && order != b"little"
        {
            return Err(not(&format!(
                "byteorder '{}' (only little-endian checkpoints are supported)",
                String::from_utf8_lossy(&order)
            )));
        }
        let data = d.entry(&pkl)?;
        let tree = pickle::load_restricted(&data, ALLOWED_GLOBALS).map_err(|cause| {
            Error::Pickle { path: path.to_path_buf(), entry: pkl.clone(), cause }
        })?;
        let root = d.convert(tree, &mut Vec::new())?;
        Ok(Checkpoint { path: path.to_path_buf(), root })
    }

    fn key_err(&self, key: &[&str], msg: impl Into<String>) -> Error {
        Error::Key { path: self.path.clone(), key: key.join("/"), msg: msg.into() }
    }

    /// The value at `key` (a path of dict keys from the root), if present.
    pub fn find(&self, key: &[&str]) -> Option<&Value> {
        key.iter().try_fold(&self.root, |v, k| v.get(k))
    }

    /// Whether `key` is present.
    pub fn has(&self, key: &[&str]) -> bool {
        self.find(key).is_some()
    }

    /// The value at `key`; an error naming the key when it is missing.
    pub fn get(&self, key: &[&str]) -> Result<&Value> {
        let mut v = &self.root;
        for (i, k) in key.iter().enumerate() {
            v = match v {
                Value::Dict(_) => v.get(k).ok_or_else(|| self.key_err(&key[..=i], "missing"))?,
                other => {
                    return Err(
                        self.key_err(&key[..i], format!("expected a dict, found {}", other.kind()))
                    );
                }
            };
        }
        Ok(v)
    }

    /// The tensor at `key` with a shape matching `shape` (binding names in `dims`).
    pub fn tensor(&self, key: &[&str], shape: &[Dim], dims: &mut Dims) -> Result<&Array> {
        match self.get(key)? {
            Value::Tensor(t) => {
                dims.check(shape, &t.shape, &key.join("/")).map_err(|m| self.key_err(key, m))?;
                Ok(t)
            }
            other => Err(self.key_err(key, format!("expected a tensor, found {}", other.kind()))),
        }
    }

    /// A float tensor's values as f64, C order.
    pub fn floats(&self, key: &[&str], shape: &[Dim], dims: &mut Dims) -> Result<Vec<f64>> {
        let t = self.tensor(key, shape, dims)?;
        t.floats().ok_or_else(|| {
            self.key_err(key, format!("expected a float tensor, found {}", t.dtype.name()))
        })
    }

    /// An integer tensor's values as i64, C order.
    pub fn ints(&self, key: &[&str], shape: &[Dim], dims: &mut Dims) -> Result<Vec<i64>> {
        let t = self.tensor(key, shape, dims)?;
        t.ints().ok_or_else(|| {
            self.key_err(key, format!("expected an integer tensor, found {}", t.dtype.name()))
        })
    }

    /// A bool tensor's values, C order.
    pub fn bools(&self, key: &[&str], shape: &[Dim], dims: &mut Dims) -> Result<Vec<bool>> {
        let t = self.tensor(key, shape, dims)?;
        t.bools().ok_or_else(|| {
            self.key_err(key, format!("expected a bool tensor, found {}", t.dtype.name()))
        })
    }

    /// A one-element numeric value (tensor of shape `[]` or `[1]`, int, float or bool) as f64.
    pub fn scalar(&self, key: &[&str]) -> Result<f64> {
        match self.get(key)? {
            Value::Int(i) => Ok(*i as f64),
            Value::Float(f) => Ok(*f),
            Value::Bool(b) => Ok(f64::from(u8::from(*b))),
            Value::Tensor(t) if t.numel() == 1 && t.shape.len() <= 1 => Ok(match &t.data {
                super::array::Data::F32(v) => v[0] as f64,
                super::array::Data::F64(v) => v[0],
                super::array::Data::I64(v) => v[0] as f64,
                super::array::Data::I32(v) => v[0] as f64,
                super::array::Data::Bool(v) => f64::from(u8::from(v[0])),
            }),
            other => Err(self.key_err(key, format!("expected a number, found {}", other.kind()))),
        }
    }
}

impl Decoder<'_> {
    fn archive_err(&self, e: impl std::fmt::Display) -> Error {
        Error::Archive { path: self.path.to_path_buf(), msg: e.to_string() }
    }

    fn entry_if_present(&mut self, name: &str) -> Result<Option<Vec<u8>>> {
        let mut f = match self.zip.by_name(name) {
            Ok(f) => f,
            Err(zip::result::ZipError::FileNotFound) => return Ok(None),
            Err(e) => {
                return Err(Error::Archive { path: self.path.to_path_buf(), msg: e.to_string() });
            }
        };
        // The declared size only sizes the buffer up to a bound; reading checks the data.
        let mut buf = Vec::with_capacity((f.size() as usize).min(1 << 26));
        let res = f.read_to_end(&mut buf);
        drop(f);
        res.map_err(|e| self.archive_err(format!("{name}: {e}")))?;
        Ok(Some(buf))
    }

    fn entry(&mut self, name: &str) -> Result<Vec<u8>> {
        self.entry_if_present(name)?
            .ok_or_else(|| self.archive_err(format!("entry {name} is missing")))
    }

    fn key_err(&self, key: &[String], msg: impl Into<String>) -> Error {
        let key = if key.is_empty() { "(root)".to_string() } else { key.join("/") };
        Error::Key { path: self.path.to_path_buf(), key, msg: msg.into() }
    }

    /// Convert a pickle value; `key` is the dict-key path for error messages.
    fn convert(&mut self, v: Pv, key: &mut Vec<String>) -> Result<Value> {
        Ok(match v {
            Pv::None => Value::None,
            Pv::Bool(b) => Value::Bool(b),
            Pv::Int(i) => Value::Int(i),
            Pv::Float(f) => Value::Float(f),
            Pv::Str(s) => Value::Str(s),
            Pv::Bytes(b) => Value::Bytes(b),
            Pv::Tuple(items) | Pv::List(items) => {
                Value::List(items.into_iter().map(|x| self.convert(x, key)).collect::<Result<_>>()?)
            }
            Pv::Dict(items) => self.dict(items, key)?,
            Pv::Object { callable, args, .. } => self.object(*callable, *args, key)?,
            Pv::Global { module, name } => {
                return Err(self.key_err(key, format!("unexpected bare global '{module}.{name}'")));
            }
            Pv::PersistentId(_) => {
                return Err(self.key_err(key, "unexpected persistent id outside a tensor"));
            }
        })
    }

    fn dict(&mut self, items: Vec<(Pv, Pv)>, key: &mut Vec<String>) -> Result<Value> {
        let mut out = Vec::with_capacity(items.len());
        for (k, v) in items {
            let name = match &k {
                Pv::Str(s) => s.clone(),
                Pv::Int(i) => i.to_string(),
                _ => "?".into(),
            };
            let k = self.convert(k, key)?;
            key.push(name);
            let v = self.convert(v, key);
            key.pop();
            out.push((k, v?));
        }
        Ok(Value::Dict(out))
    }

    fn object(&mut self, callable: Pv, args: Pv, key: &mut Vec<String>) -> Result<Value> {
        let (module, name) = match callable {
            Pv::Global { module, name } => (module, name),
            other => return Err(self.key_err(key, format!("cannot call {other:?}"))),
        };
        let args = match args {
            Pv::Tuple(a) => a,
            _ => {
                return Err(
                    self.key_err(key, format!("{module}.{name}: arguments are not a tuple"))
                );
            }
        };
        match (module.as_str(), name.as_str()) {
            ("collections", "OrderedDict") => {
                // `OrderedDict([(k, v), ...])`; the usual empty call followed by SETITEMS is
                // already a dict in the pickle VM.
                let mut items = Vec::new();
                if let Some(Pv::List(pairs)) = args.into_iter().next() {
                    for p in pairs {
                        if let Pv::Tuple(mut kv) = p
                            && kv.len() == 2
                        {
                            let v = kv.pop().unwrap_or(Pv::None);
                            let k = kv.pop().unwrap_or(Pv::None);
                            items.push((k, v));
                        }
                    }
                }
                self.dict(items, key)
            }
            ("torch._utils", "_rebuild_tensor_v2") => self.tensor(args, key),
            ("torch._utils", "_rebuild_parameter") => match args.into_iter().next() {
                Some(t) => self.convert(t, key),
                None => Err(self.key_err(key, "_rebuild_parameter without a tensor")),
            },
            ("_codecs", "encode") => match args.as_slice() {
                [Pv::Str(s), Pv::Str(enc)] if enc == "latin1" || enc == "latin-1" => {
                    let b: Option<Vec<u8>> =
                        s.chars().map(|c| u8::try_from(c as u32).ok()).collect();
                    b.map(Value::Bytes).ok_or_else(|| {
                        self.key_err(key, "_codecs.encode: character outside latin-1")
                    })
                }
                _ => Err(self.key_err(key, "_codecs.encode: expected (str, 'latin1')")),
            },
            ("numpy", "dtype") => match args.first() {
                Some(Pv::Str(s)) => Ok(Value::Str(s.clone())),
                _ => Err(self.key_err(key, "numpy.dtype without a type string")),
            },
            (_, "scalar") => self.numpy_scalar(args, key),
            _ => Err(self.key_err(key, format!("unsupported object {module}.{name}"))),
        }
    }

    /// `numpy.core.multiarray.scalar(dtype, bytes)`: a numpy number in optimiser state.
    fn numpy_scalar(&mut self, args: Vec<Pv>, key: &mut Vec<String>) -> Result<Value> {
        let mut it = args.into_iter();
        let (dtype, data) = (it.next(), it.next());
        let (descr, order) = match dtype {
            Some(Pv::Object { args, state, .. }) => {
                let descr = match *args {
                    Pv::Tuple(a) => match a.into_iter().next() {
                        Some(Pv::Str(s)) => s,
                        _ => String::new(),
                    },
                    _ => String::new(),
                };
                let order = match state.map(|s| *s) {
                    Some(Pv::Tuple(st)) => match st.get(1) {
                        Some(Pv::Str(o)) => o.clone(),
                        _ => "<".into(),
                    },
                    _ => "<".into(),
                };
                (descr, order)
            }
            _ => return Err(self.key_err(key, "numpy scalar without a dtype")),
        };
        let bytes = match data.map(|d| self.convert(d, key)).transpose()? {
            Some(Value::Bytes(b)) => b,
            _ => return Err(self.key_err(key, "numpy scalar without its bytes")),
        };
        if order == ">" {
            return Err(self.key_err(key, "big-endian numpy scalar"));
        }
        let dt = DType::from_numpy(&descr)
            .ok_or_else(|| self.key_err(key, format!("unsupported numpy scalar type '{descr}'")))?;
        if bytes.len() != dt.size() {
            return Err(self.key_err(
                key,
                format!("numpy scalar '{descr}' has {} bytes, expected {}", bytes.len(), dt.size()),
            ));
        }
        let a = Array { dtype: dt, shape: vec![], data: dt.decode(&bytes, 0..1) };
        Ok(match (a.floats(), a.ints(), a.bools()) {
            (Some(f), _, _) => Value::Float(f[0]),
            (_, Some(i), _) => Value::Int(i[0]),
            (_, _, Some(b)) => Value::Bool(b[0]),
            _ => Value::None,
        })
    }

    /// `_rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[, meta])`.
    fn tensor(&mut self, args: Vec<Pv>, key: &[String]) -> Result<Value> {
        let err = |d: &Self, m: String| d.key_err(key, m);
        let mut it = args.into_iter();
        let pid = match it.next() {
            Some(Pv::PersistentId(p)) => *p,
            _ => return Err(err(self, "tensor without a storage reference".into())),
        };
        let ints = |v: Option<Pv>| -> Option<Vec<i64>> {
            match v? {
                Pv::Tuple(t) | Pv::List(t) => {
                    t.into_iter().map(|x| if let Pv::Int(i) = x { Some(i) } else { None }).collect()
                }
                _ => None,
            }
        };
        let offset = match it.next() {
            Some(Pv::Int(o)) if o >= 0 => o as usize,
            _ => return Err(err(self, "tensor storage offset is not a non-negative int".into())),
        };
        let shape = ints(it.next())
            .ok_or_else(|| err(self, "tensor size is not a tuple of ints".into()))?;
        let stride = ints(it.next())
            .ok_or_else(|| err(self, "tensor stride is not a tuple of ints".into()))?;
        let (dtype, skey, numel) = match pid {
            Pv::Tuple(t) => match t.as_slice() {
                [Pv::Str(tag), Pv::Global { name, .. }, Pv::Str(k), _, Pv::Int(n)]
                    if tag == "storage" && *n >= 0 =>
                {
                    let dt = storage_dtype(name)
                        .ok_or_else(|| err(self, format!("unsupported storage type {name}")))?;
                    (dt, k.clone(), *n as usize)
                }
                _ => return Err(err(self, "malformed storage reference".into())),
            },
            _ => return Err(err(self, "malformed storage reference".into())),
        };
        if shape.len() != stride.len() || shape.iter().chain(&stride).any(|x| *x < 0) {
            return Err(err(
                self,
                format!("tensor size {shape:?} and stride {stride:?} do not match"),
            ));
        }
        let shape: Vec<usize> = shape.iter().map(|x| *x as usize).collect();
        let stride: Vec<usize> = stride.iter().map(|x| *x as usize).collect();
        let count = shape.iter().try_fold(1usize, |a, b| a.checked_mul(*b));
        let count = count.filter(|c| *c <= numel.max(1).saturating_mul(16));
        let count = count.ok_or_else(|| {
            err(self, format!("tensor of shape {shape:?} is larger than its storage of {numel}"))
        })?;
        if count > 0 {
            let last = shape
                .iter()
                .zip(&stride)
                .try_fold(offset, |a, (s, st)| a.checked_add((s - 1).checked_mul(*st)?));
            if last.is_none_or(|l| l >= numel) {
                return Err(err(
                    self,
                    format!(
                        "tensor (offset {offset}, shape {shape:?}, stride {stride:?}) reaches past \
                         its storage of {numel} elements"
                    ),
                ));
            }
        }
        let bytes = self.storage(&skey, dtype, numel, key)?;
        // Storage element index of each C-order position.
        let mut idx = vec![0usize; shape.len()];
        let index = (0..count).map(|_| {
            let at = offset + idx.iter().zip(&stride).map(|(i, s)| i * s).sum::<usize>();
            for d in (0..shape.len()).rev() {
                idx[d] += 1;
                if idx[d] < shape[d] {
                    break;
                }
                idx[d] = 0;
            }
            at
        });
        let data = dtype.decode(bytes, index);
        Ok(Value::Tensor(Array { dtype, shape, data }))
    }

    /// The bytes of storage `skey` (read once), checked to hold `numel` elements.
    fn storage(&mut self, skey: &str, dtype: DType, numel: usize, key: &[String]) -> Result<&[u8]> {
        if !self.storages.contains_key(skey) {
            let name = format!("{}data/{skey}", self.root);
            let b = self.entry_if_present(&name)?.ok_or_else(|| {
                self.key_err(key, format!("storage entry {name} is missing from the archive"))
            })?;
            self.storages.insert(skey.to_string(), b);
        }
        let b = &self.storages[skey];
        let need = numel.checked_mul(dtype.size());
        if need.is_none_or(|n| b.len() < n) {
            return Err(Error::Key {
                path: self.path.to_path_buf(),
                key: key.join("/"),
                msg: format!(
                    "storage data/{skey} has {} bytes, {numel} {} elements need {}",
                    b.len(),
                    dtype.name(),
                    numel.saturating_mul(dtype.size())
                ),
            });
        }
        Ok(b)
    }
}
