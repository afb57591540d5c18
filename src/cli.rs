//! The command line: clap structs (the "low args") and the dispatcher that calls one stage.
//!
//! Each stage owns its parameter struct (deriving both `clap::Args` and
//! `serde::Deserialize`), so pipeline `params:` and CLI flags cannot diverge. This module
//! only names the subcommands and routes them; it performs no I/O of its own.

use std::path::Path;

use clap::{Parser, Subcommand};

use crate::context::Context;
use crate::pipeline::{Executor, spec::Stage};

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
    /// Where to rasterize: `cpu` (default: the bit-deterministic reference), `gpu` (wgpu;
    /// software adapters such as lavapipe count) or `auto` (a hardware GPU if there is one,
    /// else the CPU). GPU results match the CPU within tolerances, not bitwise.
    #[arg(long, global = true, value_enum, value_name = "DEVICE")]
    pub device: Option<crate::context::Device>,
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
    /// One self-contained HTML report of a run: tables, charts, image grids, graph figures.
    Report(crate::stages::report::ReportParams),
    /// The paper's tables (Table 2 form per scene and averaged, tracking, ablations) from
    /// many evaluations: benchmark.md and benchmark.parquet.
    Benchmark(crate::stages::benchmark::BenchmarkParams),
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
    Inspect(crate::tools::inspect::InspectParams),
    /// Validate a model or scene directory completely (every frame, every file).
    Check(crate::tools::check::CheckParams),
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
    Render(crate::tools::bench::render::BenchRenderParams),
    /// Key-node and edge construction timings at scale.
    Graph(crate::tools::bench::graph::BenchGraphParams),
    /// LPIPS and evaluation timings.
    Metrics(crate::tools::bench::metrics::BenchMetricsParams),
    /// Per-frame timings of the uncertainty stage's render and convergence test.
    Uncertainty(crate::tools::bench::uncertainty::BenchUncertaintyParams),
}

impl Command {
    /// The stage name used in logs and provenance.
    pub fn name(&self) -> &'static str {
        match self {
            Command::Synth(_) => "synth",
            Command::Import(ImportCommand::Dycheck(_)) => "import dycheck",
            Command::Render(_) => "render",
            Command::Uncertainty(_) => "uncertainty",
            Command::Keynodes(_) => "keynodes",
            Command::Edges(_) => "edges",
            Command::Segment(_) => "segment",
            Command::Evaluate(_) => "evaluate",
            Command::Report(_) => "report",
            Command::Benchmark(_) => "benchmark",
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
    use crate::{datasets, metrics, pipeline, stages, tools};
    let _span = tracing::info_span!("stage", name = command.name()).entered();
    tracing::info!("start");
    match command {
        Command::Synth(p) => datasets::synth::run(&p, ctx),
        Command::Import(ImportCommand::Dycheck(p)) => datasets::dycheck::run_import(&p, ctx),
        Command::Render(p) => stages::render::run(&p, ctx),
        Command::Uncertainty(p) => stages::uncertainty::run(&p, ctx),
        Command::Keynodes(p) => stages::keynodes::run(&p, ctx),
        Command::Edges(p) => stages::edges::run(&p, ctx),
        Command::Segment(p) => stages::segment::run(&p, ctx),
        Command::Evaluate(p) => stages::evaluate::run(&p, ctx),
        Command::Report(p) => stages::report::run(&p, ctx),
        Command::Benchmark(p) => stages::benchmark::run(&p, ctx),
        Command::Lpips(c) => metrics::lpips::run_command(&c, ctx),
        Command::Bench(BenchCommand::Render(p)) => tools::bench::render::run(&p, ctx),
        Command::Bench(BenchCommand::Graph(p)) => tools::bench::graph::run(&p, ctx),
        Command::Bench(BenchCommand::Metrics(p)) => tools::bench::metrics::run(&p, ctx),
        Command::Bench(BenchCommand::Uncertainty(p)) => tools::bench::uncertainty::run(&p, ctx),
        Command::Pipeline(c) => pipeline::run_command(&c, &mut InProcess { ctx: ctx.clone() }, ctx),
        Command::Inspect(p) => tools::inspect::run(&p, ctx),
        Command::Check(p) => tools::check::run(&p, ctx),
    }
}

/// Runs a stage as a usplat4d subcommand in this process: parses `argv` with the CLI parser
/// and calls [`dispatch`] with the working directory set to the pipeline directory for the
/// duration of the stage (the runner is single-threaded at the stage level). Stage output is
/// quiet unless the pipeline runs with `--verbose`.
#[derive(Debug, Clone)]
pub struct InProcess {
    /// The pipeline's context.
    pub ctx: Context,
}

impl Executor for InProcess {
    fn execute(&mut self, stage: &Stage, base: &Path) -> anyhow::Result<()> {
        use clap::Parser;
        let cli =
            Cli::try_parse_from(std::iter::once("usplat4d".to_string()).chain(stage.argv.clone()))
                .map_err(|e| anyhow::anyhow!("{}", e.to_string().trim_end()))?;
        if matches!(cli.command, Command::Pipeline(_)) {
            anyhow::bail!("a stage cannot run `pipeline`");
        }
        if cli.threads.is_some() {
            self.ctx
                .warn(format!("stage `{}`: --threads is ignored inside a pipeline", stage.name));
        }
        let ctx = Context {
            quiet: cli.quiet || self.ctx.quiet || self.ctx.verbose == 0,
            verbose: cli.verbose.max(self.ctx.verbose.saturating_sub(1)),
            device: cli.device.unwrap_or(self.ctx.device),
        };
        let previous = std::env::current_dir()?;
        let base = if base.as_os_str().is_empty() { Path::new(".") } else { base };
        std::env::set_current_dir(base).map_err(|e| anyhow::anyhow!("{}: {e}", base.display()))?;
        let result =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| dispatch(cli.command, &ctx)));
        std::env::set_current_dir(&previous)
            .map_err(|e| anyhow::anyhow!("{}: {e}", previous.display()))?;
        match result {
            Ok(r) => r,
            Err(panic) => {
                let msg = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "unknown panic".into());
                anyhow::bail!("panicked: {msg}")
            }
        }
    }

    fn device(&mut self) -> anyhow::Result<String> {
        Ok(crate::stages::device::renderer(&self.ctx)?.tag())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::spec::Pipeline;

    #[test]
    fn the_in_process_executor_reports_bad_commands_without_running_them() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("p.yaml");
        let yaml = "stages:\n  a: {cmd: pipeline dag x.yaml}\n  b: {cmd: frobnicate --now}\n";
        std::fs::write(&file, yaml).unwrap();
        let p = Pipeline::load(&file, &[]).unwrap();
        let mut exec = InProcess { ctx: Context::quiet() };
        let e = exec.execute(&p.stages[0], &p.base).unwrap_err();
        assert_eq!(e.to_string(), "a stage cannot run `pipeline`");
        let e = exec.execute(&p.stages[1], &p.base).unwrap_err();
        assert!(e.to_string().starts_with("error: unrecognized subcommand 'frobnicate'"), "{e}");
    }

    /// Parse `usplat4d ARGS` and return clap's error message.
    fn rejected(args: &[&str]) -> String {
        let argv = std::iter::once("usplat4d").chain(args.iter().copied());
        match Cli::try_parse_from(argv) {
            Ok(c) => panic!("accepted: {:?}", c.command),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn out_of_range_sizes_thresholds_and_counts_name_their_option() {
        let keynodes = ["keynodes", "--model", "m", "--uncertainty", "u", "--out", "o"];
        for bad in [["--voxel-size", "0"], ["--voxel-size", "1e-300"], ["--key-budget", "200%"]] {
            let e = rejected(&[&keynodes[..], &bad[..]].concat());
            assert!(e.contains(bad[0]), "{bad:?}: {e}");
        }
        let unc = ["uncertainty", "--model", "m", "--scene", "s", "--out", "o"];
        for bad in [["--eta-c", "2"], ["--phi", "0"], ["--contrib-clip-max", "NaN"]] {
            let e = rejected(&[&unc[..], &bad[..]].concat());
            assert!(e.contains(bad[0]), "{bad:?}: {e}");
        }
        let e = rejected(&["evaluate", "--renders", "r", "--scene", "s", "--fail-below", "NaN"]);
        assert!(e.contains("--fail-below"), "{e}");
        let e = rejected(&["segment", "--edges", "e", "--out", "o", "--k", "0"]);
        assert!(e.contains("--k"), "{e}");
        let ok = ["keynodes", "--model", "m", "--uncertainty", "u", "--out", "o"];
        Cli::try_parse_from(std::iter::once("usplat4d").chain(ok).chain([
            "--voxel-size",
            "2%",
            "--key-budget",
            "2%",
        ]))
        .unwrap();
    }
}
