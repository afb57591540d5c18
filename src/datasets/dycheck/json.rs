//! Typed access to the keys of a DyCheck JSON object, with errors that name the file and
//! the key (`<file>: key 'position': expected 3 numbers, got 2`).

use std::path::Path;

use serde_json::{Map, Value};

use super::{Error, Result};

/// A JSON object of file `path`.
pub(super) struct Obj<'a> {
    path: &'a Path,
    map: &'a Map<String, Value>,
}

/// A short rendering of a JSON value for error messages.
fn show(v: &Value) -> String {
    let s = v.to_string();
    if s.chars().count() > 40 {
        format!("{}...", s.chars().take(40).collect::<String>())
    } else {
        s
    }
}

impl<'a> Obj<'a> {
    /// The top-level object of `value` read from `path`.
    pub(super) fn new(path: &'a Path, value: &'a Value) -> Result<Self> {
        match value {
            Value::Object(map) => Ok(Obj { path, map }),
            other => Err(Error::File {
                path: path.into(),
                msg: format!("expected a JSON object, got {}", show(other)),
            }),
        }
    }

    /// An error about `key`.
    pub(super) fn err(&self, key: &str, msg: impl Into<String>) -> Error {
        Error::Key { path: self.path.into(), key: key.into(), msg: msg.into() }
    }

    /// The value of `key`, if present and not null.
    pub(super) fn opt(&self, key: &str) -> Option<&'a Value> {
        self.map.get(key).filter(|v| !v.is_null())
    }

    /// The value of a required `key`.
    pub(super) fn get(&self, key: &str) -> Result<&'a Value> {
        self.opt(key).ok_or_else(|| self.err(key, "missing"))
    }

    /// `v` (the value of `key`) as a finite number.
    pub(super) fn as_f64(&self, key: &str, v: &Value) -> Result<f64> {
        v.as_f64()
            .filter(|x| x.is_finite())
            .ok_or_else(|| self.err(key, format!("expected a finite number, got {}", show(v))))
    }

    /// A required finite number.
    pub(super) fn f64(&self, key: &str) -> Result<f64> {
        self.as_f64(key, self.get(key)?)
    }

    /// `v` (the value of `key`) as a list of exactly `n` finite numbers.
    pub(super) fn as_vec(&self, key: &str, v: &Value, n: usize) -> Result<Vec<f64>> {
        let list = v.as_array().ok_or_else(|| {
            self.err(key, format!("expected a list of {n} numbers, got {}", show(v)))
        })?;
        if list.len() != n {
            return Err(self.err(key, format!("expected {n} numbers, got {}", list.len())));
        }
        list.iter().enumerate().map(|(i, x)| self.as_f64(&format!("{key}[{i}]"), x)).collect()
    }

    /// A required list of exactly `n` finite numbers.
    pub(super) fn vec(&self, key: &str, n: usize) -> Result<Vec<f64>> {
        self.as_vec(key, self.get(key)?, n)
    }

    /// A required 3x3 matrix given as 3 rows of 3 numbers.
    pub(super) fn mat3(&self, key: &str) -> Result<[[f64; 3]; 3]> {
        let v = self.get(key)?;
        let rows = v.as_array().ok_or_else(|| {
            self.err(key, format!("expected 3 rows of 3 numbers, got {}", show(v)))
        })?;
        if rows.len() != 3 {
            return Err(
                self.err(key, format!("expected 3 rows of 3 numbers, got {} rows", rows.len()))
            );
        }
        let mut m = [[0.0; 3]; 3];
        for (i, row) in rows.iter().enumerate() {
            let r = self.as_vec(&format!("{key}[{i}]"), row, 3)?;
            m[i].copy_from_slice(&r);
        }
        Ok(m)
    }

    /// A required list of strings.
    pub(super) fn strings(&self, key: &str) -> Result<Vec<String>> {
        let v = self.get(key)?;
        let list = v
            .as_array()
            .ok_or_else(|| self.err(key, format!("expected a list of strings, got {}", show(v))))?;
        list.iter()
            .enumerate()
            .map(|(i, x)| {
                x.as_str().map(String::from).ok_or_else(|| {
                    self.err(&format!("{key}[{i}]"), format!("expected a string, got {}", show(x)))
                })
            })
            .collect()
    }

    /// A required list of non-negative integers.
    pub(super) fn u32s(&self, key: &str) -> Result<Vec<u32>> {
        let v = self.get(key)?;
        let list = v.as_array().ok_or_else(|| {
            self.err(key, format!("expected a list of non-negative integers, got {}", show(v)))
        })?;
        list.iter()
            .enumerate()
            .map(|(i, x)| {
                x.as_u64().and_then(|u| u32::try_from(u).ok()).ok_or_else(|| {
                    self.err(
                        &format!("{key}[{i}]"),
                        format!("expected a non-negative integer, got {}", show(x)),
                    )
                })
            })
            .collect()
    }
}
