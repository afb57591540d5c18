//! The lock file `FILE.lock` next to `FILE.yaml`: per stage, what its last successful run
//! used and produced.
//!
//! An entry is written only after its stage finished and its outputs were hashed, and the
//! whole file is replaced atomically (temp + rename). So a run killed in the middle of a stage
//! leaves the previous entry (whose output hashes no longer match) or none: the next run
//! redoes that stage and trusts everything else. The format is pretty JSON (a YAML subset),
//! keys sorted, so it diffs well under version control.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::Error;

/// Format version of the lock file.
pub const LOCK_VERSION: u32 = 1;

/// What one stage's last successful run used and produced.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LockEntry {
    /// The stage key: blake3 of cmd, tool version, params, outs and dep hashes.
    pub key: String,
    /// The command after interpolation.
    pub cmd: String,
    /// `crate::VERSION` of the tool that ran it.
    pub tool_version: String,
    /// Parameters the stage used, name → value.
    pub params: BTreeMap<String, String>,
    /// Dep path → content hash.
    pub deps: BTreeMap<String, String>,
    /// Out path → content hash.
    pub outs: BTreeMap<String, String>,
}

/// The lock file content.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Lock {
    /// [`LOCK_VERSION`].
    pub version: u32,
    /// Stage name → entry.
    pub stages: BTreeMap<String, LockEntry>,
    #[serde(skip)]
    path: PathBuf,
}

impl Lock {
    /// Read `path`; a missing file is an empty lock.
    pub fn load(path: &Path) -> Result<Lock, Error> {
        let bytes = match std::fs::read(path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Lock {
                    version: LOCK_VERSION,
                    stages: BTreeMap::new(),
                    path: path.into(),
                });
            }
            Err(e) => return Err(Error::io(path)(e)),
        };
        let mut lock: Lock = serde_json::from_slice(&bytes).map_err(|e| Error::BadState {
            path: path.into(),
            message: format!("invalid lock file: {e}"),
        })?;
        if lock.version != LOCK_VERSION {
            return Err(Error::BadState {
                path: path.into(),
                message: format!(
                    "lock file version {} (this tool writes {LOCK_VERSION})",
                    lock.version
                ),
            });
        }
        lock.path = path.into();
        Ok(lock)
    }

    /// Record `entry` for `stage` and rewrite the file atomically.
    pub fn record(&mut self, stage: &str, entry: LockEntry) -> Result<(), Error> {
        self.stages.insert(stage.to_string(), entry);
        self.save()
    }

    /// Drop entries of stages no longer in the pipeline (on the next save).
    pub fn retain(&mut self, names: &[&str]) {
        self.stages.retain(|k, _| names.contains(&k.as_str()));
    }

    /// Rewrite the file atomically.
    pub fn save(&self) -> Result<(), Error> {
        let mut text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::BadState { path: self.path.clone(), message: e.to_string() })?;
        text.push('\n');
        Ok(crate::util::fs::write_atomic(&self.path, text.as_bytes())?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects_garbage() {
        let t = tempfile::tempdir().unwrap();
        let path = t.path().join("p.lock");
        let mut lock = Lock::load(&path).unwrap();
        assert!(lock.stages.is_empty());
        let entry = LockEntry {
            key: "k".into(),
            cmd: "c".into(),
            tool_version: crate::VERSION.into(),
            params: [("n".to_string(), "3".to_string())].into(),
            deps: BTreeMap::new(),
            outs: [("o".to_string(), "h".to_string())].into(),
        };
        lock.record("s", entry.clone()).unwrap();
        assert_eq!(Lock::load(&path).unwrap().stages["s"], entry);
        std::fs::write(&path, "{\"version\": 1}").unwrap();
        let e = Lock::load(&path).unwrap_err().to_string();
        assert!(
            e.starts_with(&format!(
                "{}: invalid lock file: missing field `stages`",
                path.display()
            )),
            "{e}"
        );
    }
}
