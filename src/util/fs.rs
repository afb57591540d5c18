//! File-system helpers: every output file is written to a temporary path and renamed.

use std::io::Write;
use std::path::{Path, PathBuf};

/// A failed atomic write: the path that failed (the file, or its directory when the
/// directory or the temporary file could not be created) and the cause.
#[derive(Debug, thiserror::Error)]
#[error("{}: {source}", path.display())]
pub struct WriteError {
    /// The file or directory.
    pub path: PathBuf,
    /// The underlying error.
    pub source: std::io::Error,
}

/// Write `bytes` to `path` through a temporary file in the same directory and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), WriteError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let at = |p: &Path, source| WriteError { path: p.to_path_buf(), source };
    std::fs::create_dir_all(&dir).map_err(|e| at(&dir, e))?;
    let mut tmp =
        tempfile::Builder::new().prefix(".tmp-").tempfile_in(&dir).map_err(|e| at(&dir, e))?;
    tmp.write_all(bytes).map_err(|e| at(path, e))?;
    tmp.persist(path).map_err(|e| WriteError { path: path.into(), source: e.error })?;
    Ok(())
}

/// A staging directory beside `out`, named `<prefix>…` (same file system, so its files can
/// be renamed in); removed when dropped unless [`publish`]ed.
pub fn staging_dir(out: &Path, prefix: &str) -> Result<tempfile::TempDir, WriteError> {
    let abs = std::path::absolute(out).map_err(|e| WriteError { path: out.into(), source: e })?;
    let parent = abs.parent().unwrap_or(&abs);
    let at = |source| WriteError { path: parent.to_path_buf(), source };
    std::fs::create_dir_all(parent).map_err(at)?;
    tempfile::Builder::new().prefix(prefix).tempdir_in(parent).map_err(at)
}

/// Move the staged files into `out`: the whole directory when `out` does not exist yet,
/// otherwise file by file, replacing files of the same name and keeping the others.
pub fn publish(staged: &Path, out: &Path) -> Result<(), WriteError> {
    fn at(p: &Path) -> impl Fn(std::io::Error) -> WriteError + '_ {
        move |source| WriteError { path: p.to_path_buf(), source }
    }
    if !out.exists() {
        return std::fs::rename(staged, out).map_err(at(out));
    }
    for e in std::fs::read_dir(staged).map_err(at(staged))? {
        let e = e.map_err(at(staged))?;
        let to = out.join(e.file_name());
        if e.file_type().map_err(at(&e.path()))?.is_dir() {
            std::fs::create_dir_all(&to).map_err(at(&to))?;
            publish(&e.path(), &to)?;
        } else {
            std::fs::rename(e.path(), &to).map_err(at(&to))?;
        }
    }
    Ok(())
}

/// The last component of `dir` (resolved) as a label, e.g. a method or scene name.
pub fn dir_label(dir: &Path) -> String {
    dir.canonicalize()
        .ok()
        .and_then(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| dir.display().to_string())
}
