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
    /// Number of worker threads: 0 means all cores (the default); at most 4 per core.
    /// Results do not depend on it.
    #[arg(long, global = true, value_name = "N", value_parser = parse_threads)]
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

/// Threads per core that `--threads` allows: more only adds scheduling overhead (100,000
/// threads ran for minutes at a load of 1,300).
pub const MAX_THREADS_PER_CORE: usize = 4;

fn parse_threads(s: &str) -> Result<usize, String> {
    let n: usize = s.parse().map_err(|e| format!("{e}"))?;
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let max = MAX_THREADS_PER_CORE * cores;
    if n > max {
        return Err(format!(
            "at most {max} threads ({MAX_THREADS_PER_CORE} per core, {cores} cores); 0 means all cores"
        ));
    }
    Ok(n)
}

impl Cli {
    /// Parse a command line (`args[0]` is the program name). A value that looks like a
    /// negative number (`--k -1`) is taken as the option's value, so the option's own parser
    /// rejects it by name instead of clap reporting an unexpected argument `-1`.
    pub fn try_parse_args<I, T>(args: I) -> Result<Cli, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        use clap::{CommandFactory, FromArgMatches};
        fn negative_values(cmd: clap::Command) -> clap::Command {
            cmd.mut_args(|a| {
                if a.get_action().takes_values() { a.allow_negative_numbers(true) } else { a }
            })
            .mut_subcommands(negative_values)
        }
        let matches = negative_values(Cli::command()).try_get_matches_from(args)?;
        Cli::from_arg_matches(&matches)
    }
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
    /// Uncertainty-aware optimisation: the vanilla and USplat4D recipes (paper Sec. 4.3).
    Optimize(Box<crate::stages::optimize::OptimizeParams>),
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
    /// A model's frames as files Gaussian-splat viewers open (3DGS PLY, glTF).
    #[command(subcommand)]
    Export(crate::tools::export::ExportCommand),
}

/// `usplat4d import ...`
#[derive(Debug, Subcommand)]
pub enum ImportCommand {
    /// A DyCheck iPhone sequence (camera JSONs, rgb, depth, splits).
    Dycheck(crate::datasets::dycheck::ImportDycheckParams),
    /// A Shape of Motion checkpoint (`checkpoints/last.ckpt`) as a model directory.
    Som(crate::import::som::ImportSomParams),
    /// A MoSca log directory (`photometric_*.pth`) as a model directory.
    Mosca(crate::import::mosca::ImportMoscaParams),
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
    /// Milliseconds per optimisation step and peak memory of `optimize`.
    Optimize(crate::tools::bench::optimize::BenchOptimizeParams),
}

impl Command {
    /// The stage name used in logs and provenance.
    pub fn name(&self) -> &'static str {
        match self {
            Command::Synth(_) => "synth",
            Command::Import(ImportCommand::Dycheck(_)) => "import dycheck",
            Command::Import(ImportCommand::Som(_)) => "import som",
            Command::Import(ImportCommand::Mosca(_)) => "import mosca",
            Command::Init(_) => "init",
            Command::Render(_) => "render",
            Command::Uncertainty(_) => "uncertainty",
            Command::Keynodes(_) => "keynodes",
            Command::Edges(_) => "edges",
            Command::Optimize(_) => "optimize",
            Command::Segment(_) => "segment",
            Command::Evaluate(_) => "evaluate",
            Command::Report(_) => "report",
            Command::Benchmark(_) => "benchmark",
            Command::Lpips(_) => "lpips",
            Command::Bench(_) => "bench",
            Command::Pipeline(_) => "pipeline",
            Command::Inspect(_) => "inspect",
            Command::Check(_) => "check",
            Command::Export(crate::tools::export::ExportCommand::Ply(_)) => "export ply",
            Command::Export(crate::tools::export::ExportCommand::Gltf(_)) => "export gltf",
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
        Command::Import(ImportCommand::Som(p)) => crate::import::som::run(&p, ctx),
        Command::Import(ImportCommand::Mosca(p)) => crate::import::mosca::run(&p, ctx),
        Command::Init(p) => stages::init::run(&p, ctx),
        Command::Render(p) => stages::render::run(&p, ctx),
        Command::Uncertainty(p) => stages::uncertainty::run(&p, ctx),
        Command::Keynodes(p) => stages::keynodes::run(&p, ctx),
        Command::Edges(p) => stages::edges::run(&p, ctx),
        Command::Optimize(p) => stages::optimize::run(&p, ctx),
        Command::Segment(p) => stages::segment::run(&p, ctx),
        Command::Evaluate(p) => stages::evaluate::run(&p, ctx),
        Command::Report(p) => stages::report::run(&p, ctx),
        Command::Benchmark(p) => stages::benchmark::run(&p, ctx),
        Command::Lpips(c) => metrics::lpips::run_command(&c, ctx),
        Command::Bench(BenchCommand::Render(p)) => tools::bench::render::run(&p, ctx),
        Command::Bench(BenchCommand::Graph(p)) => tools::bench::graph::run(&p, ctx),
        Command::Bench(BenchCommand::Metrics(p)) => tools::bench::metrics::run(&p, ctx),
        Command::Bench(BenchCommand::Uncertainty(p)) => tools::bench::uncertainty::run(&p, ctx),
        Command::Bench(BenchCommand::Optimize(p)) => tools::bench::optimize::run(&p, ctx),
        Command::Pipeline(c) => pipeline::run_command(&c, &mut InProcess { ctx: ctx.clone() }, ctx),
        Command::Inspect(p) => tools::inspect::run(&p, ctx),
        Command::Check(p) => tools::check::run(&p, ctx),
        Command::Export(c) => tools::export::run_command(&c, ctx),
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
        let cli =
            Cli::try_parse_args(std::iter::once("usplat4d".to_string()).chain(stage.argv.clone()))
                .map_err(|e| {
                    // clap echoes the offending value, which a parameter may make megabytes long
                    let text = e.to_string();
                    let words: Vec<_> =
                        text.trim_end().split(' ').map(crate::pipeline::spec::shown).collect();
                    anyhow::anyhow!("{}", words.join(" "))
                })?;
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

    /// A stage whose command line holds a huge value fails with a short message: the value
    /// clap echoes is cut.
    #[test]
    fn a_huge_value_in_a_stage_command_is_cut_in_its_error() {
        let huge = "7".repeat(2_000_000);
        let text = format!(
            "params: {{n: '{huge}'}}\nstages:\n  a: {{cmd: 'segment --edges e --out o --k ${{n}}'}}\n"
        );
        let p = Pipeline::parse(Path::new("p.yaml"), &text, &[]).unwrap();
        let err = InProcess { ctx: Context::quiet() }
            .execute(&p.stages[0], Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(err.len() < 300, "{} characters", err.len());
        assert!(
            err.contains("'7777777777")
                && err.contains("(2000002 characters)")
                && err.contains("--k <K>"),
            "{err}"
        );
    }

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

#[cfg(test)]
mod parse_tests {
    use clap::CommandFactory;

    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, String> {
        Cli::try_parse_args(std::iter::once("usplat4d").chain(args.iter().copied()))
            .map_err(|e| e.to_string().lines().next().unwrap_or_default().to_string())
    }

    #[test]
    fn threads_are_capped_at_four_per_core_and_zero_means_all_cores() {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let max = 4 * cores;
        assert_eq!(
            parse(&["--threads", "100000", "check", "x"]).err().unwrap(),
            format!(
                "error: invalid value '100000' for '--threads <N>': at most {max} threads (4 per core, {cores} cores); 0 means all cores"
            )
        );
        let ok = |n: usize| parse(&["--threads", &n.to_string(), "check", "x"]).unwrap().threads;
        assert_eq!(ok(max), Some(max));
        assert_eq!(ok(0), Some(0));
        let help = Cli::command().render_long_help().to_string();
        assert!(help.contains("0 means all cores"), "{help}");
        assert!(help.contains("at most 4 per core"), "{help}");
    }

    /// `--opt -1` is the value -1, which the option's parser then accepts or rejects by name,
    /// never "unexpected argument '-1'"; checked on every option of every subcommand.
    #[test]
    fn negative_numbers_are_values_of_their_option() {
        assert_eq!(
            parse(&["segment", "--k", "-1"]).err().unwrap(),
            "error: invalid value '-1' for '--k <K>': '-1' is not a count"
        );
        fn walk(cmd: &clap::Command, path: &mut Vec<String>, bad: &mut Vec<String>) {
            for arg in cmd.get_arguments() {
                let Some(long) = arg.get_long() else { continue };
                if !arg.get_action().takes_values() || arg.is_global_set() && !path.is_empty() {
                    continue;
                }
                let opt = format!("--{long}");
                let args: Vec<&str> =
                    path.iter().map(String::as_str).chain([opt.as_str(), "-1"]).collect();
                if let Err(e) = parse(&args)
                    && (e.contains("unexpected argument") || e.contains("value is required"))
                {
                    bad.push(format!("{}: {e}", args.join(" ")));
                }
            }
            for sub in cmd.get_subcommands() {
                path.push(sub.get_name().to_string());
                walk(sub, path, bad);
                path.pop();
            }
        }
        let mut bad = Vec::new();
        walk(&Cli::command(), &mut Vec::new(), &mut bad);
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }

    /// The same stage written to two output directories gives the same table bytes: the
    /// output path is not part of the provenance.
    #[test]
    fn table_bytes_do_not_depend_on_the_output_path() {
        use crate::tables::uncertainty::{UncertaintyFrame, UncertaintyWriter};
        let dir = tempfile::tempdir().unwrap();
        let (_, model) = crate::datasets::demo::write_demo_scene(dir.path(), 3).unwrap();
        let ids = crate::model::Model::load(&model).unwrap().gaussians.id;
        let n = ids.len();
        let unc = dir.path().join("unc");
        let mut w =
            UncertaintyWriter::create(&unc.join("uncertainty.parquet"), &ids, &Default::default())
                .unwrap();
        for t in 0..3 {
            w.write(&UncertaintyFrame {
                frame: t,
                sum_w2: vec![1.0; n],
                sum_w: vec![1.0; n],
                n_pixels: vec![4; n],
                converged: (0..n).map(|i| !(i + t as usize).is_multiple_of(3)).collect(),
                u: (0..n).map(|i| 0.5 + (i % 7) as f32).collect(),
            })
            .unwrap();
        }
        w.finish().unwrap();
        let run = |out: &str| {
            let out = dir.path().join(out);
            let args = ["keynodes", "--model", model.to_str().unwrap(), "--uncertainty"];
            let cli = parse(
                &[&args[..], &[unc.to_str().unwrap(), "--out", out.to_str().unwrap()]].concat(),
            )
            .unwrap();
            dispatch(cli.command, &Context::quiet()).unwrap();
            std::fs::read(out.join("key_nodes.parquet")).unwrap()
        };
        let a = run("a");
        assert!(a == run("elsewhere/b"), "key_nodes.parquet differs between output directories");
    }
}
