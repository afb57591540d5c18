//! Content hashes of files and directories (blake3), with a stat cache that avoids re-reading
//! unchanged files.
//!
//! A file hashes to blake3 of its bytes. A directory hashes to blake3 of its sorted listing:
//! one record `f <relative path>\0<file hash>\n` per file and `d <relative path>\n` per
//! subdirectory (so empty directories count), paths `/`-separated, symlinks followed. Files of
//! a directory are hashed in parallel and merged in sorted order, so the hash does not depend
//! on the thread count.
//!
//! The stat cache (`.usplat4d/stat-cache.json`) maps each hashed file to (size, mtime in ns,
//! time it was hashed, hash). A cached hash is reused only when size and mtime are unchanged
//! *and* the file was hashed more than [`RACY_NS`] after its mtime; otherwise (including a
//! "racily clean" file modified within the mtime granularity of its hashing) the content is
//! read again. Content is the truth: the cache only ever skips reading a file whose metadata
//! says it was not touched since it was hashed.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::Error;

/// A cached hash is trusted only if the file was hashed this long after its mtime (2 s
/// covers filesystems with coarse timestamps).
pub const RACY_NS: u128 = 2_000_000_000;

/// One file inside a hashed tree.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Path relative to the tree root (`""` when the tree is a single file).
    pub path: String,
    /// blake3 of the content, hex.
    pub hash: String,
    /// Size in bytes.
    pub size: u64,
}

/// The hash of a file or directory and what it is made of.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Tree {
    /// The file or directory hash, hex.
    pub hash: String,
    /// Whether the root is a directory.
    pub is_dir: bool,
    /// Files, sorted by path.
    pub files: Vec<FileEntry>,
    /// Subdirectories, sorted (relative paths).
    pub dirs: Vec<String>,
}

impl Tree {
    /// Total size of the files in bytes.
    pub fn size(&self) -> u64 {
        self.files.iter().map(|f| f.size).sum()
    }
}

/// One stat-cache record.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Stamp {
    size: u64,
    mtime_ns: u128,
    hashed_ns: u128,
    hash: String,
}

/// Hashes paths, reusing and refreshing the stat cache.
#[derive(Debug, Default)]
pub struct Hasher {
    cache_file: Option<PathBuf>,
    stamps: BTreeMap<String, Stamp>,
    dirty: bool,
    tool: Option<String>,
    device: String,
}

fn now_ns() -> u128 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0)
}

/// blake3 of a file's content, hex.
pub fn hash_file(path: &Path) -> Result<String, Error> {
    let mut f = std::fs::File::open(path).map_err(Error::io(path))?;
    let mut h = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf).map_err(Error::io(path))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(h.finalize().to_hex().to_string())
}

impl Hasher {
    /// A hasher whose stat cache lives in `cache_file` (a missing or unreadable cache is
    /// simply empty: it only saves time).
    pub fn with_cache(cache_file: PathBuf) -> Hasher {
        let stamps = std::fs::read(&cache_file)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok())
            .unwrap_or_default();
        Hasher {
            cache_file: Some(cache_file),
            stamps,
            dirty: false,
            tool: None,
            device: String::new(),
        }
    }

    /// Write the stat cache back if it changed, forgetting files that no longer exist.
    pub fn save(&mut self) -> Result<(), Error> {
        if let (Some(file), true) = (&self.cache_file, self.dirty) {
            self.stamps.retain(|path, _| Path::new(path).exists());
            let bytes = serde_json::to_vec(&self.stamps)
                .map_err(|e| Error::BadState { path: file.clone(), message: e.to_string() })?;
            crate::util::fs::write_atomic(file, &bytes)?;
            self.dirty = false;
        }
        Ok(())
    }

    /// Append the renderer's tag (`cpu`, `gpu:<adapter>`) to [`Hasher::tool_id`].
    pub fn set_device(&mut self, tag: &str) {
        self.device = tag.to_string();
        self.tool = None;
    }

    /// Identity of the running tool: its version and the content hash of its executable
    /// (`0.1.0+1a2b3c4d5e6f7a8b`), so that a rebuilt binary re-runs stages even when the
    /// version number did not change, then the renderer's tag when set (`+cpu`). The
    /// executable's hash goes through the stat cache.
    pub fn tool_id(&mut self) -> Result<String, Error> {
        if let Some(t) = &self.tool {
            return Ok(t.clone());
        }
        let exe = std::env::current_exe().map_err(Error::io("(the running executable)"))?;
        let hash = self.hash(&exe)?.map(|t| t.hash).unwrap_or_default();
        let mut id = format!("{}+{}", crate::VERSION, &hash[..hash.len().min(16)]);
        if !self.device.is_empty() {
            id = format!("{id}+{}", self.device);
        }
        self.tool = Some(id.clone());
        Ok(id)
    }

    /// Hash `path` (file or directory); `None` when it does not exist.
    pub fn hash(&mut self, path: &Path) -> Result<Option<Tree>, Error> {
        let meta = match std::fs::metadata(path) {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::io(path)(e)),
        };
        let (mut files, mut dirs) = (Vec::new(), Vec::new());
        if meta.is_dir() {
            walk(path, "", &mut files, &mut dirs)?;
        } else {
            files.push(String::new());
        }
        let stamps = &self.stamps;
        let now = now_ns();
        let hashed: Vec<(FileEntry, Option<(String, Stamp)>)> = files
            .par_iter()
            .map(|rel| {
                let full = if rel.is_empty() { path.to_path_buf() } else { path.join(rel) };
                let m = std::fs::metadata(&full).map_err(Error::io(&full))?;
                let size = m.len();
                let mtime_ns = m
                    .modified()
                    .ok()
                    .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
                    .map(|d| d.as_nanos())
                    .unwrap_or(0);
                let key = full.to_string_lossy().into_owned();
                if let Some(s) = stamps.get(&key)
                    && s.size == size
                    && s.mtime_ns == mtime_ns
                    && s.hashed_ns > mtime_ns + RACY_NS
                {
                    return Ok((FileEntry { path: rel.clone(), hash: s.hash.clone(), size }, None));
                }
                let hash = hash_file(&full)?;
                let stamp = Stamp { size, mtime_ns, hashed_ns: now, hash: hash.clone() };
                Ok((FileEntry { path: rel.clone(), hash, size }, Some((key, stamp))))
            })
            .collect::<Result<_, Error>>()?;
        let mut entries = Vec::with_capacity(hashed.len());
        for (entry, stamp) in hashed {
            if let Some((key, stamp)) = stamp {
                self.stamps.insert(key, stamp);
                self.dirty = true;
            }
            entries.push(entry);
        }
        let hash = if meta.is_dir() {
            let mut h = blake3::Hasher::new();
            let mut records: Vec<(String, String)> = entries
                .iter()
                .map(|e| (e.path.clone(), format!("f {}\0{}\n", e.path, e.hash)))
                .chain(dirs.iter().map(|d| (d.clone(), format!("d {d}\n"))))
                .collect();
            records.sort();
            for (_, r) in &records {
                h.update(r.as_bytes());
            }
            h.finalize().to_hex().to_string()
        } else {
            entries[0].hash.clone()
        };
        Ok(Some(Tree { hash, is_dir: meta.is_dir(), files: entries, dirs }))
    }
}

/// Sorted recursive listing of `root/rel`: files and directories relative to `root`.
fn walk(
    root: &Path,
    rel: &str,
    files: &mut Vec<String>,
    dirs: &mut Vec<String>,
) -> Result<(), Error> {
    let dir = if rel.is_empty() { root.to_path_buf() } else { root.join(rel) };
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .map_err(Error::io(&dir))?
        .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
        .collect::<Result<_, _>>()
        .map_err(Error::io(&dir))?;
    names.sort();
    for name in names {
        let child = if rel.is_empty() { name } else { format!("{rel}/{name}") };
        let full = root.join(&child);
        let meta = std::fs::metadata(&full).map_err(Error::io(&full))?;
        if meta.is_dir() {
            dirs.push(child.clone());
            walk(root, &child, files, dirs)?;
        } else {
            files.push(child);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directory_hash_depends_on_names_contents_and_empty_dirs() {
        let t = tempfile::tempdir().unwrap();
        let d = t.path().join("d");
        std::fs::create_dir_all(d.join("sub")).unwrap();
        std::fs::write(d.join("a"), "1").unwrap();
        std::fs::write(d.join("sub/b"), "2").unwrap();
        let mut h = Hasher::default();
        let t1 = h.hash(&d).unwrap().unwrap();
        assert_eq!(t1.files.iter().map(|f| f.path.as_str()).collect::<Vec<_>>(), ["a", "sub/b"]);
        assert_eq!(t1.dirs, ["sub"]);
        assert_eq!(t1.size(), 2);
        std::fs::create_dir(d.join("empty")).unwrap();
        let t2 = h.hash(&d).unwrap().unwrap();
        assert_ne!(t1.hash, t2.hash);
        std::fs::write(d.join("sub/b"), "3").unwrap();
        let t3 = h.hash(&d).unwrap().unwrap();
        assert_ne!(t2.hash, t3.hash);
        let f = h.hash(&d.join("a")).unwrap().unwrap();
        assert_eq!(f.hash, blake3::hash(b"1").to_hex().to_string());
        assert!(!f.is_dir);
        assert!(h.hash(&d.join("missing")).unwrap().is_none());
    }

    #[test]
    fn stat_cache_reuses_only_old_untouched_files() {
        let t = tempfile::tempdir().unwrap();
        let f = t.path().join("f");
        std::fs::write(&f, "abc").unwrap();
        let cache = t.path().join("cache.json");
        let mut h = Hasher::with_cache(cache.clone());
        let real = h.hash(&f).unwrap().unwrap().hash;
        let key = f.to_string_lossy().into_owned();
        // Pretend the file was hashed long after its mtime with a different (fake) hash:
        // the cache is trusted, which proves it avoids reading the file.
        let stamp = h.stamps.get_mut(&key).unwrap();
        stamp.hashed_ns += 10 * RACY_NS;
        stamp.hash = "fake".into();
        h.dirty = true;
        h.save().unwrap();
        let mut h = Hasher::with_cache(cache.clone());
        assert_eq!(h.hash(&f).unwrap().unwrap().hash, "fake");
        // A size change invalidates it.
        std::fs::write(&f, "abcd").unwrap();
        assert_eq!(h.hash(&f).unwrap().unwrap().hash, blake3::hash(b"abcd").to_hex().to_string());
        // A freshly hashed file is racy: re-read even with equal size and mtime.
        std::fs::write(&f, "abc").unwrap();
        let mut h = Hasher::with_cache(cache);
        assert_eq!(h.hash(&f).unwrap().unwrap().hash, real);
        h.stamps.get_mut(&key).unwrap().hash = "stale".into();
        assert_eq!(h.hash(&f).unwrap().unwrap().hash, real);
    }
}
