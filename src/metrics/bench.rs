//! (being written)

/// Parameters.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct BenchMetricsParams {}

/// Run the stage.
pub fn run(_p: &BenchMetricsParams, _ctx: &crate::context::Context) -> anyhow::Result<()> {
    anyhow::bail!("not available yet")
}
