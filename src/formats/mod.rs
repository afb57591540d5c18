//! File formats: 8-bit PNG images ([`png`]) and float32 `.npy` arrays ([`npy`]) written by
//! the stages (atomically: temporary file, then rename; [`crate::util::fs`]), and what the
//! importers read: pickle streams ([`pickle`]), PyTorch checkpoints ([`torch`]), numpy
//! `.npy`/`.npz` arrays of any dtype ([`npz`]) and the dense arrays they decode to ([`array`]).

pub mod array;
pub mod npy;
pub mod npz;
pub mod pickle;
pub mod png;
pub mod torch;

use std::path::PathBuf;

use crate::util::fs::{IoError, PathError};

/// Errors of reading or writing image and array files; each names the file.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// File system error.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The image could not be decoded or encoded.
    #[error(transparent)]
    Image(#[from] PathError<image::ImageError>),
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
