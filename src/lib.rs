//! usplat4d: uncertainty-aware refinement of dynamic (4D) Gaussian splatting reconstructions
//! made from one moving camera (USplat4D, ICLR 2026).
//!
//! The crate is a dataflow pipeline with on-disk stages. Every stage is a pure function of
//! its input tables and parameters; [`cli`] turns command lines into calls of those functions
//! and [`pipeline`] runs declarative YAML pipelines of them with a content-addressed cache.
//!
//! Layout, lowest layer first: [`util`] (seeded generator, atomic writes, statistics),
//! [`math`] (quaternions and their VJPs), [`formats`] (PNG, `.npy`), [`render`] (the
//! differentiable rasterizer), [`tables`] (Parquet schemas, readers, writers and the
//! in-memory types they store), [`scene`] and [`model`] (dataset and 4D model directories),
//! [`metrics`] (PSNR, SSIM, LPIPS, tracking), [`datasets`] (synthetic benchmark, DyCheck),
//! [`stages`] (uncertainty, key nodes, edges, segments, render, evaluation), [`tools`]
//! (inspect, check, benchmarks), [`pipeline`] and [`cli`].
//!
//! Dependency rule (checked by `tests/layout.rs` on the source): `render` imports only
//! `math` and `util`; `tables` only `util`, `math` and `formats`; `model` and `scene` import
//! `tables` (and the layers below); `metrics`, `stages` and `datasets` anything below them;
//! `tools` may call `stages`; `pipeline` imports only `util` and `context` (it runs stages
//! through its `Executor` trait); only `cli` imports `pipeline`; nothing imports `cli`; and
//! no two files import each other (a folder's `mod.rs` may share items with its own files).
#![warn(missing_docs)]

pub mod cli;
pub mod context;
pub mod datasets;
pub mod formats;
pub mod import;
pub mod math;
pub mod metrics;
pub mod model;
pub mod pipeline;
pub mod render;
pub mod scene;
pub mod stages;
#[cfg(test)]
mod table_tests;
pub mod tables;
pub mod tools;
pub mod util;

/// The tool version recorded in every table's metadata and in pipeline cache keys.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
