//! File-system helpers: every output file is written to a temporary path and renamed.

use std::io::Write;
use std::path::{Path, PathBuf};

/// An error of a file and its path, displayed as `path: cause`: the cause is in the message,
/// not chained, so `{:#}` prints it once. The typed error enums of the layers wrap it as
/// their variants for the libraries they call on a file ([`IoError`], Parquet, Arrow,
/// image).
#[derive(Debug, thiserror::Error)]
#[error("{}: {cause}", path.display())]
pub struct PathError<E> {
    /// The file or directory.
    pub path: PathBuf,
    /// The underlying error.
    pub cause: E,
}

impl<E> PathError<E> {
    /// The error of `path`, for `map_err`: `File::open(p).map_err(IoError::at(p))?`.
    pub fn at<P: AsRef<Path> + ?Sized>(path: &P) -> impl Fn(E) -> PathError<E> + Copy {
        move |cause| PathError { path: path.as_ref().to_path_buf(), cause }
    }
}

/// An I/O error naming its path: the file, or its directory when the directory or a
/// temporary file could not be created.
pub type IoError = PathError<std::io::Error>;

/// Write `bytes` to `path` through a temporary file in the same directory and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).map_err(IoError::at(&dir))?;
    let mut tmp =
        tempfile::Builder::new().prefix(".tmp-").tempfile_in(&dir).map_err(IoError::at(&dir))?;
    tmp.write_all(bytes).map_err(IoError::at(path))?;
    tmp.persist(path).map_err(|e| IoError { path: path.into(), cause: e.error })?;
    Ok(())
}

/// A staging directory beside `out`, named `<prefix>…` (same file system, so its files can
/// be renamed in); removed when dropped unless [`publish`]ed.
pub fn staging_dir(out: &Path, prefix: &str) -> Result<tempfile::TempDir, IoError> {
    let abs = std::path::absolute(out).map_err(IoError::at(out))?;
    let parent = abs.parent().unwrap_or(&abs);
    std::fs::create_dir_all(parent).map_err(IoError::at(parent))?;
    tempfile::Builder::new().prefix(prefix).tempdir_in(parent).map_err(IoError::at(parent))
}

/// Move the staged files into `out`: the whole directory when `out` does not exist yet,
/// otherwise file by file, replacing files of the same name and keeping the others.
pub fn publish(staged: &Path, out: &Path) -> Result<(), IoError> {
    if !out.exists() {
        return std::fs::rename(staged, out).map_err(IoError::at(out));
    }
    for e in std::fs::read_dir(staged).map_err(IoError::at(staged))? {
        let e = e.map_err(IoError::at(staged))?;
        let to = out.join(e.file_name());
        if e.file_type().map_err(IoError::at(&e.path()))?.is_dir() {
            std::fs::create_dir_all(&to).map_err(IoError::at(&to))?;
            publish(&e.path(), &to)?;
        } else {
            std::fs::rename(e.path(), &to).map_err(IoError::at(&to))?;
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
