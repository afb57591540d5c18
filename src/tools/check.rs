//! `usplat4d check PATH`: validate a model directory, a scene directory or both inside one
//! folder, reading every table completely (every frame of the trajectories, every camera's
//! files), and report the first violation with its file, column and row.

use std::path::PathBuf;

use crate::context::Context;
use crate::model::Model;
use crate::scene::Scene;

/// Parameters of `usplat4d check`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct CheckParams {
    /// A model directory (gaussians + trajectories) or a scene directory (cameras).
    pub path: PathBuf,
}

/// What `check` found valid.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CheckReport {
    /// Gaussians N and frames T of a model, if one was found.
    pub model: Option<(usize, usize)>,
    /// Images of a scene and its training frames T, if one was found.
    pub scene: Option<(usize, usize)>,
}

/// Validate everything under `path`; errors name file, column and row.
pub fn check(path: &std::path::Path, ctx: &Context) -> anyhow::Result<CheckReport> {
    let mut report = CheckReport::default();
    if Model::gaussians_path(path).exists() || Model::trajectories_path(path).exists() {
        let model = Model::load(path)?;
        let bar = ctx.progress(model.num_frames() as u64, "check frames");
        for t in 0..model.num_frames() {
            model.frame(t)?;
            bar.inc(1);
        }
        bar.finish_and_clear();
        report.model = Some((model.gaussians.len(), model.num_frames()));
    }
    if Scene::cameras_path(path).exists() {
        let scene = Scene::load(path)?;
        for (row, cam) in scene.cameras.iter().enumerate() {
            for (column, rel) in [
                ("image_path", Some(&cam.image_path)),
                ("depth_path", cam.depth_path.as_ref()),
                ("mask_path", cam.mask_path.as_ref()),
            ] {
                if let Some(rel) = rel
                    && !scene.resolve(rel).exists()
                {
                    anyhow::bail!(
                        "{}: column '{column}', row {row}: file {} does not exist",
                        Scene::cameras_path(path).display(),
                        scene.resolve(rel).display()
                    );
                }
            }
        }
        report.scene = Some((scene.cameras.len(), scene.num_frames()));
    }
    if report == CheckReport::default() {
        anyhow::bail!(
            "{}: neither a model directory (gaussians.parquet, trajectories.parquet) nor a scene directory (cameras.parquet)",
            path.display()
        );
    }
    Ok(report)
}

/// Run `usplat4d check`, printing what was validated.
pub fn run(p: &CheckParams, ctx: &Context) -> anyhow::Result<()> {
    let r = check(&p.path, ctx)?;
    if let Some((n, t)) = r.model {
        println!("model ok: {n} Gaussians, {t} frames");
    }
    if let Some((images, t)) = r.scene {
        println!("scene ok: {images} images, {t} training frames");
    }
    Ok(())
}
