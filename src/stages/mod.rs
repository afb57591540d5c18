//! The USplat4D stages, each a pure function of its input tables and parameters.

pub mod benchmark;
pub mod device;
pub mod edges;
pub mod evaluate;
pub mod graph;
pub mod init;
pub mod keynodes;
pub mod optimize;
pub mod params;
pub mod render;
pub mod report;
pub mod segment;
pub mod uncertainty;

/// A stage ran but a check it was asked to make failed (exit code 1, e.g.
/// `evaluate --fail-below`).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct CheckFailed(pub String);
