//! usplat4d: uncertainty-aware refinement of dynamic (4D) Gaussian splatting reconstructions
//! made from one moving camera (USplat4D, ICLR 2026).
//!
//! The crate is a dataflow pipeline with on-disk stages. Every stage is a pure function of
//! its input tables and parameters; [`cli`] turns command lines into calls of those functions
//! and [`pipeline`] runs declarative YAML pipelines of them with a content-addressed cache.
//!
//! Layout: [`tables`] (Parquet schemas, readers and writers), [`scene`] (cameras and images
//! of a dataset), [`model`] (the 4D Gaussian model), [`render`] (the differentiable
//! rasterizer), [`datasets`] (synthetic benchmark, DyCheck loader), [`stages`] (uncertainty,
//! key nodes, edges, segments, evaluation), [`metrics`] (PSNR, SSIM, LPIPS, tracking).
#![warn(missing_docs)]

pub mod cli;
pub mod context;
pub mod datasets;
pub mod formats;
pub mod image_io;
pub mod import;
pub mod math;
pub mod metrics;
pub mod model;
pub mod pipeline;
pub mod render;
pub mod scene;
pub mod stages;
pub mod tables;

/// The tool version recorded in every table's metadata and in pipeline cache keys.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
