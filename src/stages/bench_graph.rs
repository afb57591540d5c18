//! (being written)

/// Parameters.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BenchGraphParams {}

/// Run the stage.
pub fn run(_p: &BenchGraphParams, _ctx: &crate::context::Context) -> anyhow::Result<()> {
    anyhow::bail!("not available yet")
}
