//! Arrow schemas and Parquet I/O of every intermediate table, one module per table.
//!
//! Each table module holds its schema (documented column by column in
//! `data_schema/<table>.md`, checked by a test), an in-memory columnar struct, a writer and
//! a reader. The shared machinery lives in [`io`] (atomic writes, one row group per frame,
//! provenance metadata, whole-schema validation) and [`validate`] (finite values,
//! normalised quaternions, unique ids, frames without gaps). Every error names the file, and
//! where it applies the column and the row or frame.

pub mod benchmark;
pub mod cameras;
pub mod edges;
pub mod gaussians;
pub mod io;
pub mod key_nodes;
pub mod metrics;
pub mod model_cameras;
pub mod pages;
pub mod segments;
pub mod tracks_2d;
pub mod tracks_3d;
pub mod training_log;
pub mod trajectories;
pub mod uncertainty;
pub mod validate;

use std::path::PathBuf;

use arrow::datatypes::SchemaRef;

use crate::util::fs::{IoError, PathError};

pub use io::{Provenance, Table, TableReader, TableWriter};

/// Errors of reading, validating or writing a table.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be opened, created, written or renamed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The Parquet layer failed (not a Parquet file, truncated, corrupt).
    #[error(transparent)]
    Parquet(#[from] PathError<parquet::errors::ParquetError>),
    /// The Arrow layer failed while assembling or decoding a batch.
    #[error(transparent)]
    Arrow(#[from] PathError<arrow::error::ArrowError>),
    /// Not a Parquet file, or one whose footer describes pages outside the file.
    #[error("{}: {msg}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// The file's schema differs from the table's; lists every mismatch.
    #[error("{}: not a valid '{table}' table: {problems}", path.display())]
    Schema {
        /// The file.
        path: PathBuf,
        /// The expected table.
        table: &'static str,
        /// All mismatches, separated by "; ".
        problems: String,
    },
    /// A value breaks an invariant of its column.
    #[error("{}: column '{column}', row {row}: {msg}", path.display())]
    Value {
        /// The file.
        path: PathBuf,
        /// The column.
        column: String,
        /// Zero-based row in the file.
        row: u64,
        /// What is wrong.
        msg: String,
    },
    /// A frame-level invariant is broken (gap, duplicate, wrong row count).
    #[error("{}: frame {frame}: {msg}", path.display())]
    Frame {
        /// The file.
        path: PathBuf,
        /// The frame index.
        frame: u64,
        /// What is wrong.
        msg: String,
    },
    /// Two tables of one dataset disagree (e.g. ids of `trajectories` and `gaussians`).
    #[error("{}: {msg}", path.display())]
    Mismatch {
        /// The file that disagrees.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
}

/// Result alias of this module.
pub type Result<T> = std::result::Result<T, Error>;

/// One table kind: name, schema version and schema.
#[derive(Debug, Clone)]
pub struct TableKind {
    /// Table name (file stem, doc name).
    pub name: &'static str,
    /// Schema version.
    pub version: u32,
    /// Arrow schema.
    pub schema: SchemaRef,
}

/// Every table kind: the documentation test and the interop tests walk it.
pub fn registry() -> Vec<TableKind> {
    fn entry<T: Table>() -> TableKind {
        TableKind { name: T::NAME, version: T::VERSION, schema: T::schema() }
    }
    vec![
        entry::<cameras::CamerasTable>(),
        entry::<gaussians::GaussiansTable>(),
        entry::<trajectories::TrajectoriesTable>(),
        entry::<model_cameras::ModelCamerasTable>(),
        entry::<tracks_2d::Tracks2dTable>(),
        entry::<tracks_3d::Tracks3dTable>(),
        entry::<metrics::MetricsTable>(),
        entry::<uncertainty::UncertaintyTable>(),
        entry::<key_nodes::KeyNodesTable>(),
        entry::<edges::EdgesTable>(),
        entry::<segments::SegmentsTable>(),
        entry::<benchmark::BenchmarkTable>(),
        entry::<training_log::TrainingLogTable>(),
    ]
}
