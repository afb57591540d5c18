//! The run cache under `.usplat4d/cache/` next to the pipeline file: outputs of past stage
//! runs, addressed by stage key, so that setting a parameter back to an earlier value restores
//! the outputs instead of recomputing them.
//!
//! Layout: `objects/<2 hex>/<blake3>` holds file contents by content hash (shared between
//! runs); `runs/<stage key>.json` lists, per output path, its [`Tree`] (the files and their
//! hashes) and when the entry was last used. The cache is capped in bytes of objects; past the
//! cap, the least recently used run entries are dropped with the objects only they referenced.
//! Restores go through a temporary sibling (`.restore-XXXXXX/`) that is renamed into place,
//! and the restored output is re-hashed and must match, so a damaged cache falls back to
//! running the stage. A run killed mid-restore leaves that sibling behind; every run first
//! removes such leftovers beside its outputs ([`sweep_restores`]).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::Error;
use super::hash::{Hasher, Tree};

/// A stored run: the outputs of one stage key.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    outs: BTreeMap<String, Tree>,
    last_used_ns: u128,
}

/// The run cache of one pipeline directory.
#[derive(Debug, Clone)]
pub struct RunCache {
    root: PathBuf,
    max_bytes: u64,
}

fn now_ns() -> u128 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0)
}

/// Remove a file or directory if present.
pub fn remove_path(p: &Path) -> Result<(), Error> {
    match std::fs::symlink_metadata(p) {
        Ok(m) if m.is_dir() => std::fs::remove_dir_all(p).map_err(Error::io(p)),
        Ok(_) => std::fs::remove_file(p).map_err(Error::io(p)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(Error::io(p)(e)),
    }
}

/// Prefix of the staging directory of a restore, beside the output it restores.
const RESTORE_PREFIX: &str = ".restore-";

/// Remove the staging directories that a killed restore left in `dir` (directories named
/// `.restore-` and six characters, as [`RunCache::restore`] creates them).
pub fn sweep_restores(dir: &Path) -> Result<(), Error> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(Error::io(dir)(e)),
    };
    for e in entries {
        let e = e.map_err(Error::io(dir))?;
        let name = e.file_name();
        let staged = name
            .to_str()
            .and_then(|n| n.strip_prefix(RESTORE_PREFIX))
            .is_some_and(|r| r.len() == 6 && r.bytes().all(|b| b.is_ascii_alphanumeric()));
        if staged && e.file_type().map_err(Error::io(&e.path()))?.is_dir() {
            remove_path(&e.path())?;
        }
    }
    Ok(())
}

impl RunCache {
    /// The cache rooted at `root`, holding at most `max_bytes` of objects (0 disables it).
    pub fn new(root: PathBuf, max_bytes: u64) -> RunCache {
        RunCache { root, max_bytes }
    }

    /// The cap in bytes (0: disabled).
    pub fn max_bytes(&self) -> u64 {
        self.max_bytes
    }

    fn manifest_path(&self, key: &str) -> PathBuf {
        self.root.join("runs").join(format!("{key}.json"))
    }

    fn object_path(&self, hash: &str) -> PathBuf {
        self.root.join("objects").join(&hash[..2.min(hash.len())]).join(hash)
    }

    fn read_manifest(&self, path: &Path) -> Option<Manifest> {
        serde_json::from_slice(&std::fs::read(path).ok()?).ok()
    }

    fn write_manifest(&self, key: &str, m: &Manifest) -> Result<(), Error> {
        let path = self.manifest_path(key);
        let bytes = serde_json::to_vec(m)
            .map_err(|e| Error::BadState { path: path.clone(), message: e.to_string() })?;
        Ok(crate::util::fs::write_atomic(&path, &bytes)?)
    }

    /// The output hashes stored under `key` (path → hash), if any.
    pub fn out_hashes(&self, key: &str) -> Option<BTreeMap<String, String>> {
        let m = self.read_manifest(&self.manifest_path(key))?;
        Some(m.outs.into_iter().map(|(k, t)| (k, t.hash)).collect())
    }

    /// Whether a complete entry for `key` exists.
    pub fn contains(&self, key: &str) -> bool {
        self.max_bytes > 0
            && self.read_manifest(&self.manifest_path(key)).is_some_and(|m| {
                m.outs.values().flat_map(|t| &t.files).all(|f| self.object_path(&f.hash).is_file())
            })
    }

    /// Store the outputs `outs` (path → tree, relative to `base`) under `key`, then evict.
    /// Returns false when the outputs alone exceed the cap (nothing stored).
    pub fn store(
        &self,
        key: &str,
        base: &Path,
        outs: &BTreeMap<String, Tree>,
    ) -> Result<bool, Error> {
        if outs.values().map(Tree::size).sum::<u64>() > self.max_bytes {
            return Ok(false);
        }
        for (out, tree) in outs {
            for f in &tree.files {
                let obj = self.object_path(&f.hash);
                if obj.is_file() {
                    continue;
                }
                let src =
                    if f.path.is_empty() { base.join(out) } else { base.join(out).join(&f.path) };
                let dir = obj.parent().unwrap_or(&self.root).to_path_buf();
                std::fs::create_dir_all(&dir).map_err(Error::io(&dir))?;
                let tmp = tempfile::Builder::new()
                    .prefix(".tmp-")
                    .tempfile_in(&dir)
                    .map_err(Error::io(&dir))?;
                std::fs::copy(&src, tmp.path()).map_err(Error::io(&src))?;
                tmp.persist(&obj).map_err(|e| Error::io(&obj)(e.error))?;
            }
        }
        self.write_manifest(key, &Manifest { outs: outs.clone(), last_used_ns: now_ns() })?;
        self.evict()?;
        Ok(true)
    }

    /// Restore the outputs stored under `key` into `base`. Returns the restored trees, or
    /// `None` when there is no usable entry (missing, incomplete or corrupt: then dropped).
    pub fn restore(&self, key: &str, base: &Path) -> Result<Option<BTreeMap<String, Tree>>, Error> {
        // Verification reads the staged copies: no stat cache (their paths are temporary).
        let mut hasher = Hasher::default();
        if !self.contains(key) {
            return Ok(None);
        }
        let Some(mut m) = self.read_manifest(&self.manifest_path(key)) else { return Ok(None) };
        let mut restored = BTreeMap::new();
        for (out, tree) in &m.outs {
            let dest = base.join(out);
            let parent = dest.parent().unwrap_or(base).to_path_buf();
            std::fs::create_dir_all(&parent).map_err(Error::io(&parent))?;
            let tmp = tempfile::Builder::new()
                .prefix(RESTORE_PREFIX)
                .rand_bytes(6)
                .tempdir_in(&parent)
                .map_err(Error::io(&parent))?;
            let staged = tmp.path().join("out");
            if tree.is_dir {
                std::fs::create_dir(&staged).map_err(Error::io(&staged))?;
                for d in &tree.dirs {
                    std::fs::create_dir_all(staged.join(d)).map_err(Error::io(&staged.join(d)))?;
                }
            }
            for f in &tree.files {
                let to = if f.path.is_empty() { staged.clone() } else { staged.join(&f.path) };
                std::fs::copy(self.object_path(&f.hash), &to).map_err(Error::io(&to))?;
            }
            let got = hasher.hash(&staged)?;
            if got.as_ref().map(|t| &t.hash) != Some(&tree.hash) {
                remove_path(&self.manifest_path(key))?;
                return Ok(None);
            }
            remove_path(&dest)?;
            std::fs::rename(&staged, &dest).map_err(Error::io(&dest))?;
            restored.insert(out.clone(), tree.clone());
        }
        m.last_used_ns = now_ns();
        self.write_manifest(key, &m)?;
        Ok(Some(restored))
    }

    /// Drop least recently used entries until the objects they reference fit the cap, then
    /// delete unreferenced objects.
    fn evict(&self) -> Result<(), Error> {
        let runs = self.root.join("runs");
        let mut manifests: Vec<(u128, PathBuf, Manifest)> = Vec::new();
        for e in std::fs::read_dir(&runs).map_err(Error::io(&runs))? {
            let path = e.map_err(Error::io(&runs))?.path();
            match self.read_manifest(&path) {
                Some(m) => manifests.push((m.last_used_ns, path, m)),
                None => remove_path(&path)?,
            }
        }
        manifests.sort_by(|a, b| b.0.cmp(&a.0).then_with(|| a.1.cmp(&b.1)));
        let mut keep: BTreeMap<String, u64> = BTreeMap::new();
        let mut total = 0u64;
        let mut full = false;
        for (_, path, m) in &manifests {
            let new: BTreeMap<String, u64> = m
                .outs
                .values()
                .flat_map(|t| &t.files)
                .filter(|f| !keep.contains_key(&f.hash))
                .map(|f| (f.hash.clone(), f.size))
                .collect();
            let add: u64 = new.values().sum();
            if full || total + add > self.max_bytes {
                full = true;
                remove_path(path)?;
                continue;
            }
            total += add;
            keep.extend(new);
        }
        let objects = self.root.join("objects");
        let referenced: BTreeSet<&String> = keep.keys().collect();
        for shard in std::fs::read_dir(&objects).map_err(Error::io(&objects))? {
            let shard = shard.map_err(Error::io(&objects))?.path();
            for obj in std::fs::read_dir(&shard).map_err(Error::io(&shard))? {
                let obj = obj.map_err(Error::io(&shard))?.path();
                let name =
                    obj.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                if !referenced.contains(&name) {
                    remove_path(&obj)?;
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tree_of(h: &mut Hasher, base: &Path, out: &str) -> BTreeMap<String, Tree> {
        [(out.to_string(), h.hash(&base.join(out)).unwrap().unwrap())].into()
    }

    #[test]
    fn stores_restores_and_evicts_least_recently_used() {
        let t = tempfile::tempdir().unwrap();
        let base = t.path();
        let cache = RunCache::new(base.join(".usplat4d/cache"), 10);
        let mut h = Hasher::default();
        std::fs::create_dir_all(base.join("d/e")).unwrap();
        std::fs::write(base.join("d/e/x"), "four").unwrap();
        let a = tree_of(&mut h, base, "d");
        assert!(cache.store("ka", base, &a).unwrap());
        std::fs::write(base.join("d/e/x"), "five!").unwrap();
        let b = tree_of(&mut h, base, "d");
        assert!(cache.store("kb", base, &b).unwrap());
        assert!(cache.contains("ka") && cache.contains("kb"));
        assert_eq!(cache.restore("ka", base).unwrap().unwrap(), a);
        assert_eq!(std::fs::read_to_string(base.join("d/e/x")).unwrap(), "four");
        // 4 + 5 + 3 bytes > 10: the least recently used entry (kb) goes, ka was just used.
        std::fs::write(base.join("f"), "six").unwrap();
        assert!(cache.store("kc", base, &tree_of(&mut h, base, "f")).unwrap());
        assert!(cache.contains("ka") && !cache.contains("kb") && cache.contains("kc"));
        let objects: usize = std::fs::read_dir(base.join(".usplat4d/cache/objects"))
            .unwrap()
            .map(|s| std::fs::read_dir(s.unwrap().path()).unwrap().count())
            .sum();
        assert_eq!(objects, 2);
        // Too big to cache at all.
        std::fs::write(base.join("g"), "eleven bytes").unwrap();
        assert!(!cache.store("kg", base, &tree_of(&mut h, base, "g")).unwrap());
    }

    #[test]
    fn a_corrupt_object_is_not_restored() {
        let t = tempfile::tempdir().unwrap();
        let base = t.path();
        let cache = RunCache::new(base.join("c"), 100);
        let mut h = Hasher::default();
        std::fs::write(base.join("f"), "data").unwrap();
        let tree = tree_of(&mut h, base, "f");
        cache.store("k", base, &tree).unwrap();
        std::fs::write(cache.object_path(&tree["f"].files[0].hash), "evil").unwrap();
        std::fs::write(base.join("f"), "other").unwrap();
        assert!(cache.restore("k", base).unwrap().is_none());
        assert_eq!(std::fs::read_to_string(base.join("f")).unwrap(), "other");
        assert!(!cache.contains("k"));
    }
}
