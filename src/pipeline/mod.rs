//! Declarative cached pipelines (being written).

/// `usplat4d pipeline ...`
#[derive(Debug, clap::Subcommand)]
pub enum PipelineCommand {
    /// Run a pipeline.
    Run,
}

/// Run a pipeline subcommand.
pub fn run_command(_c: &PipelineCommand, _ctx: &crate::context::Context) -> anyhow::Result<()> {
    anyhow::bail!("not available yet")
}
