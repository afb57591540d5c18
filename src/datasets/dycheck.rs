//! (being written)

/// Parameters.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ImportDycheckParams {}

/// Run the stage.
pub fn run_import(_p: &ImportDycheckParams, _ctx: &crate::context::Context) -> anyhow::Result<()> {
    anyhow::bail!("not available yet")
}

/// Errors of reading or writing DyCheck sequences.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file is missing or malformed.
    #[error("{}: {msg}", path.display())]
    File {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        msg: String,
    },
}

/// The cameras of DyCheck sequence `dir` at downscale `factor`: training camera (split
/// train) and validation cameras (split eval), image paths in the scene layout.
pub fn read_camera_path(
    dir: &std::path::Path,
    _factor: u32,
) -> Result<Vec<crate::scene::Camera>, Error> {
    Err(Error::File { path: dir.into(), msg: "being written".into() })
}

/// Write `scene` (rendered along a DyCheck camera path, eval masks = covisibility) in the
/// DyCheck iPhone folder layout under `out`.
pub fn write_layout(
    scene: &crate::scene::Scene,
    out: &std::path::Path,
    _ctx: &crate::context::Context,
) -> Result<(), Error> {
    Err(Error::File { path: out.join(&scene.dir), msg: "being written".into() })
}
