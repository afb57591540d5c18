//! The command line: clap structs (the "low args") and the dispatcher that calls one stage.
//!
//! Each stage owns its parameter struct (deriving both `clap::Args` and
//! `serde::Deserialize`), so pipeline `params:` and CLI flags cannot diverge. This module
//! only names the subcommands and routes them; it performs no I/O of its own.

use clap::{Parser, Subcommand};

use crate::context::Context;

/// Top-level command line of the `usplat4d` binary.
#[derive(Debug, Parser)]
#[command(name = "usplat4d", version, about = "Uncertainty-aware 4D Gaussian splatting (USplat4D)")]
pub struct Cli {
    /// Print nothing but errors and warnings (no progress bars).
    #[arg(long, short, global = true)]
    pub quiet: bool,
    /// More diagnostic output (repeat for more).
    #[arg(long, short, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    /// Number of worker threads (default: all cores). Results do not depend on it.
    #[arg(long, global = true, value_name = "N")]
    pub threads: Option<usize>,
    /// The stage to run.
    #[command(subcommand)]
    pub command: Command,
}

/// One subcommand per stage, plus the pipeline runner and table inspection.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Render the synthetic extreme-view benchmark from an animated glTF model.
    Synth(crate::datasets::synth::SynthParams),
    /// Import a dataset or a base reconstruction.
    #[command(subcommand)]
    Import(ImportCommand),
    /// Lift the monocular priors of a scene into an initial 4D model.
    Init(crate::stages::init::InitParams),
    /// Render a model into the cameras of a scene.
    Render(crate::stages::render::RenderParams),
    /// Per-Gaussian, per-frame uncertainty (paper Sec. 4.1, Eqs. 3-6).
    Uncertainty(crate::stages::uncertainty::UncertaintyParams),
    /// Key-node selection (paper Sec. 4.2).
    Keynodes(crate::stages::keynodes::KeynodeParams),
    /// Uncertainty-aware graph edges (paper Sec. 4.2, Eqs. 7-8).
    Edges(crate::stages::edges::EdgeParams),
    /// Motion segments by spectral clustering of the key graph.
    Segment(crate::stages::segment::SegmentParams),
    /// Image and tracking metrics of renders against a scene.
    Evaluate(crate::stages::evaluate::EvaluateParams),
    /// LPIPS weights management.
    #[command(subcommand)]
    Lpips(crate::metrics::lpips::LpipsCommand),
    /// Benchmarks (release builds only give meaningful numbers).
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Declarative cached pipelines.
    #[command(subcommand)]
    Pipeline(crate::pipeline::PipelineCommand),
    /// Print schema, row count, per-column statistics and first rows of a Parquet table.
    Inspect(crate::tables::inspect::InspectParams),
    /// Validate a model or scene directory completely (every frame, every file).
    Check(crate::tables::check::CheckParams),
}

/// `usplat4d import ...`
#[derive(Debug, Subcommand)]
pub enum ImportCommand {
    /// A DyCheck iPhone sequence (camera JSONs, rgb, depth, splits).
    Dycheck(crate::datasets::dycheck::ImportDycheckParams),
}

/// `usplat4d bench ...`
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Rasterizer forward and forward+backward timings.
    Render(crate::render::bench::BenchRenderParams),
    /// Key-node and edge construction timings at scale.
    Graph(crate::stages::bench_graph::BenchGraphParams),
    /// LPIPS and evaluation timings.
    Metrics(crate::metrics::bench::BenchMetricsParams),
    /// Per-frame timings of the uncertainty stage's render and convergence test.
    Uncertainty(crate::stages::bench_uncertainty::BenchUncertaintyParams),
}

impl Command {
    /// The stage name used in logs and provenance.
    pub fn name(&self) -> &'static str {
        match self {
            Command::Synth(_) => "synth",
            Command::Import(ImportCommand::Dycheck(_)) => "import dycheck",
            Command::Init(_) => "init",
            Command::Render(_) => "render",
            Command::Uncertainty(_) => "uncertainty",
            Command::Keynodes(_) => "keynodes",
            Command::Edges(_) => "edges",
            Command::Segment(_) => "segment",
            Command::Evaluate(_) => "evaluate",
            Command::Lpips(_) => "lpips",
            Command::Bench(_) => "bench",
            Command::Pipeline(_) => "pipeline",
            Command::Inspect(_) => "inspect",
            Command::Check(_) => "check",
        }
    }
}

/// Run one parsed command inside a tracing span named after it. Used by `main` and by the
/// pipeline runner (in-process).
pub fn dispatch(command: Command, ctx: &Context) -> anyhow::Result<()> {
    use crate::{datasets, metrics, pipeline, render, stages, tables};
    let _span = tracing::info_span!("stage", name = command.name()).entered();
    tracing::info!("start");
    match command {
        Command::Synth(p) => datasets::synth::run(&p, ctx),
        Command::Import(ImportCommand::Dycheck(p)) => datasets::dycheck::run_import(&p, ctx),
        Command::Init(p) => stages::init::run(&p, ctx),
        Command::Render(p) => stages::render::run(&p, ctx),
        Command::Uncertainty(p) => stages::uncertainty::run(&p, ctx),
        Command::Keynodes(p) => stages::keynodes::run(&p, ctx),
        Command::Edges(p) => stages::edges::run(&p, ctx),
        Command::Segment(p) => stages::segment::run(&p, ctx),
        Command::Evaluate(p) => stages::evaluate::run(&p, ctx),
        Command::Lpips(c) => metrics::lpips::run_command(&c, ctx),
        Command::Bench(BenchCommand::Render(p)) => render::bench::run(&p, ctx),
        Command::Bench(BenchCommand::Graph(p)) => stages::bench_graph::run(&p, ctx),
        Command::Bench(BenchCommand::Metrics(p)) => metrics::bench::run(&p, ctx),
        Command::Bench(BenchCommand::Uncertainty(p)) => stages::bench_uncertainty::run(&p, ctx),
        Command::Pipeline(c) => pipeline::run_command(&c, ctx),
        Command::Inspect(p) => tables::inspect::run(&p, ctx),
        Command::Check(p) => tables::check::run(&p, ctx),
    }
}
