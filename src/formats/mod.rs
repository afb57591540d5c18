//! File formats shared by the stages: 8-bit PNG images ([`png`]) and float32 `.npy` arrays
//! ([`npy`]). All writes are atomic (temporary file, then rename; [`crate::util::fs`]).

pub mod npy;
pub mod png;

use std::path::PathBuf;

/// Errors of reading or writing image and array files; each names the file.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// File system error.
    #[error("{}: {cause}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        cause: std::io::Error,
    },
    /// The image could not be decoded or encoded.
    #[error("{}: {cause}", path.display())]
    Image {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        cause: image::ImageError,
    },
    /// A malformed `.npy` file or an unsupported dtype or shape.
    #[error("{}: {msg}", path.display())]
    Npy {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
}

/// Result alias of this module.
pub type Result<T> = std::result::Result<T, Error>;

impl From<crate::util::fs::WriteError> for Error {
    fn from(e: crate::util::fs::WriteError) -> Self {
        Error::Io { path: e.path, cause: e.source }
    }
}
