//! LPIPS (being written).

/// `usplat4d lpips ...`
#[derive(Debug, clap::Subcommand)]
pub enum LpipsCommand {
    /// Download and convert the weights.
    Install,
}

/// Run an lpips subcommand.
pub fn run_command(_c: &LpipsCommand, _ctx: &crate::context::Context) -> anyhow::Result<()> {
    anyhow::bail!("not available yet")
}
