//! The typed error of the pipeline runner: every variant names the pipeline file and the
//! stage, key or path it is about. `run_command` converts it to `anyhow` at the top.

use std::path::{Path, PathBuf};

use crate::util::fs::IoError;

/// Everything that can go wrong loading, planning or running a pipeline.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The file could not be read or written.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The YAML is malformed or does not match the schema (unknown key, wrong type); the
    /// message comes from serde-saphyr and carries the line and column.
    #[error("{}: {message}", file.display())]
    Yaml {
        /// The pipeline file.
        file: PathBuf,
        /// Parser message with its location.
        message: String,
    },
    /// A well-formed file whose content is invalid (bad stage definition, bad quoting, ...).
    #[error("{}: {message}", file.display())]
    Invalid {
        /// The pipeline file.
        file: PathBuf,
        /// What is wrong, naming the stage and key.
        message: String,
    },
    /// `${name}` names neither a parameter nor the foreach item.
    #[error("{}: stage `{stage}`: unknown parameter `${{{name}}}`", file.display())]
    UnknownParam {
        /// The pipeline file.
        file: PathBuf,
        /// The stage whose cmd, deps or outs use it.
        stage: String,
        /// The unknown name.
        name: String,
    },
    /// The stages depend on each other in a loop.
    #[error("{}: dependency cycle: {}", file.display(), cycle.join(" -> "))]
    Cycle {
        /// The pipeline file.
        file: PathBuf,
        /// The stages of the cycle, the first repeated at the end.
        cycle: Vec<String>,
    },
    /// A dep is neither an existing path nor an output of any stage.
    #[error(
        "{}: stage `{stage}`: dependency `{path}` does not exist and no stage outputs it",
        file.display()
    )]
    MissingDep {
        /// The pipeline file.
        file: PathBuf,
        /// The stage.
        stage: String,
        /// The dep as written (after interpolation).
        path: String,
    },
    /// Two stages declare overlapping outputs.
    #[error("{}: stages `{a}` and `{b}` both output `{path}`", file.display())]
    OverlappingOuts {
        /// The pipeline file.
        file: PathBuf,
        /// First stage.
        a: String,
        /// Second stage.
        b: String,
        /// The overlapping path.
        path: String,
    },
    /// The stage command returned an error (or panicked).
    #[error("stage `{stage}` failed: {message}")]
    StageFailed {
        /// The stage.
        stage: String,
        /// The stage's own error, with its causes.
        message: String,
    },
    /// The stage finished but one of its declared outputs does not exist.
    #[error("stage `{stage}` did not produce its output `{path}`")]
    OutputNotProduced {
        /// The stage.
        stage: String,
        /// The missing output.
        path: String,
    },
    /// A `--set`, `--force` or `--only` argument is invalid.
    #[error("{}: {message}", file.display())]
    BadArgument {
        /// The pipeline file.
        file: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The lock file or a run-cache manifest is not valid JSON of the expected shape.
    #[error("{}: {message}", path.display())]
    BadState {
        /// The lock file or manifest.
        path: PathBuf,
        /// The parse error.
        message: String,
    },
}

impl Error {
    /// An I/O error on `path`.
    pub fn io<P: AsRef<Path> + ?Sized>(path: &P) -> impl Fn(std::io::Error) -> Error + Copy {
        move |cause| Error::Io(IoError::at(path)(cause))
    }
}
