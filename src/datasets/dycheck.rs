//! (being written)

/// Parameters.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ImportDycheckParams {}

/// Run the stage.
pub fn run_import(_p: &ImportDycheckParams, _ctx: &crate::context::Context) -> anyhow::Result<()> {
    anyhow::bail!("not available yet")
}
