//! Declarative cached pipelines: `usplat4d pipeline {run,status,dag} FILE.yaml`.
//!
//! A DVC-like YAML file declares parameters and stages (`cmd`, `deps`, `outs`, `foreach`);
//! see `pipelines/README.md` for the format. [`spec`] parses and expands it, [`dag`] orders
//! the stages, [`hash`] fingerprints files, [`lock`] remembers what each stage last used and
//! produced, [`cache`] keeps past outputs by stage key, [`status`] explains why a stage is out
//! of date and [`run`] executes stages in-process through an [`Executor`]. Everything below
//! this module returns the typed [`Error`]; `anyhow` appears only in [`run_command`].

pub mod cache;
pub mod dag;
mod error;
pub mod hash;
pub mod lock;
pub mod run;
pub mod spec;
pub mod status;

#[cfg(test)]
mod tests;

use std::io::Write;
use std::path::PathBuf;

pub use error::Error;
pub use run::{Executor, Outcome, RunOptions, Runner};
pub use spec::{Pipeline, Stage};

/// `usplat4d pipeline ...`
#[derive(Debug, clap::Subcommand)]
pub enum PipelineCommand {
    /// Run the out-of-date stages of a pipeline (skip, restore from the run cache, or run).
    Run(RunArgs),
    /// Say for each stage whether it is up to date and, if not, why.
    Status(FileArgs),
    /// Print the stages in execution order with their upstream edges.
    Dag(DagArgs),
}

/// `pipeline run` arguments.
#[derive(Debug, clap::Args)]
pub struct RunArgs {
    /// The pipeline file (YAML).
    pub file: PathBuf,
    /// Override a parameter for this run.
    #[arg(long = "set", value_name = "NAME=VALUE")]
    pub set: Vec<String>,
    /// Run this stage even if it is up to date (a foreach name forces all its items).
    #[arg(long, value_name = "STAGE")]
    pub force: Vec<String>,
    /// Consider only this stage (repeatable); its deps must already exist, upstream stages
    /// are neither checked nor run.
    #[arg(long, value_name = "STAGE")]
    pub only: Vec<String>,
    /// Print what would run and why, without running anything.
    #[arg(long)]
    pub dry_run: bool,
    /// Size cap of the run cache in GB of 10^9 bytes (LRU eviction; 0 disables it).
    #[arg(long, value_name = "GB", default_value_t = 10.0)]
    pub cache_max_gb: f64,
}

/// Arguments naming only the pipeline file.
#[derive(Debug, clap::Args)]
pub struct FileArgs {
    /// The pipeline file (YAML).
    pub file: PathBuf,
    /// Override a parameter.
    #[arg(long = "set", value_name = "NAME=VALUE")]
    pub set: Vec<String>,
}

/// `pipeline dag` arguments.
#[derive(Debug, clap::Args)]
pub struct DagArgs {
    /// The pipeline file (YAML).
    pub file: PathBuf,
    /// Print Graphviz dot instead of text.
    #[arg(long)]
    pub dot: bool,
}

/// Run a pipeline subcommand; `pipeline run` runs its stages through `exec`.
pub fn run_command(
    c: &PipelineCommand,
    exec: &mut dyn Executor,
    ctx: &crate::context::Context,
) -> anyhow::Result<()> {
    let stdout = std::io::stdout();
    let mut lock = stdout.lock();
    let mut sink = std::io::sink();
    let out: &mut dyn Write = if ctx.quiet { &mut sink } else { &mut lock };
    match c {
        PipelineCommand::Run(a) => {
            if !(a.cache_max_gb.is_finite() && a.cache_max_gb >= 0.0) {
                anyhow::bail!("--cache-max-gb must be a number >= 0, got {}", a.cache_max_gb);
            }
            let p = Pipeline::load(&a.file, &a.set)?;
            let opts =
                RunOptions { force: a.force.clone(), only: a.only.clone(), dry_run: a.dry_run };
            let mut runner = Runner::open(&p, (a.cache_max_gb * 1e9) as u64, a.only.is_empty())?;
            runner.set_device(&exec.device()?);
            runner.run(&opts, exec, ctx, out)?;
        }
        PipelineCommand::Status(a) => {
            let p = Pipeline::load(&a.file, &a.set)?;
            let mut runner = Runner::open(&p, u64::MAX, true)?;
            runner.set_device(&exec.device()?);
            runner.status(out)?;
        }
        PipelineCommand::Dag(a) => {
            let p = Pipeline::load(&a.file, &[])?;
            Runner::open(&p, 0, true)?.dag(a.dot, out)?;
        }
    }
    Ok(())
}
