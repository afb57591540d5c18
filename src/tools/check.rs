//! `usplat4d check PATH`: validate a model directory, a scene directory or both inside one
//! folder, reading every table completely (every frame of the trajectories, every camera's
//! files), and report the first violation with its file, column and row. Every image, mask
//! and depth map is decoded in full and its size checked against its camera.

use std::path::PathBuf;

use rayon::prelude::*;

use crate::context::Context;
use crate::formats::npy::read_npy_f32;
use crate::formats::png::read_png;
use crate::model::Model;
use crate::scene::{Camera, Scene};

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
        let bar = ctx.progress(scene.cameras.len() as u64, "check files");
        let results: Vec<anyhow::Result<()>> = scene
            .cameras
            .par_iter()
            .enumerate()
            .map(|(row, cam)| {
                let r = check_files(&scene, row, cam);
                bar.inc(1);
                r
            })
            .collect();
        bar.finish_and_clear();
        results.into_iter().collect::<anyhow::Result<()>>()?;
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

/// Decode the image, depth map and mask of camera `row` and check their sizes.
fn check_files(scene: &Scene, row: usize, cam: &Camera) -> anyhow::Result<()> {
    let (w, h) = cam.pinhole.size();
    for (column, rel) in [
        ("image_path", Some(&cam.image_path)),
        ("depth_path", cam.depth_path.as_ref()),
        ("mask_path", cam.mask_path.as_ref()),
    ] {
        let Some(rel) = rel else { continue };
        let file = scene.resolve(rel);
        let at =
            format!("{}: column '{column}', row {row}", Scene::cameras_path(&scene.dir).display());
        if !file.exists() {
            anyhow::bail!("{at}: file {} does not exist", file.display());
        }
        if column == "depth_path" {
            let (shape, _) = read_npy_f32(&file).map_err(|e| anyhow::anyhow!("{at}: {e}"))?;
            if shape != [h, w] {
                anyhow::bail!(
                    "{at}: {} has shape {shape:?}, the camera needs [{h}, {w}] (height, width)",
                    file.display()
                );
            }
        } else {
            let img = read_png(&file).map_err(|e| anyhow::anyhow!("{at}: {e}"))?;
            if (img.width, img.height) != (w, h) {
                anyhow::bail!(
                    "{at}: {} is {}x{}, the camera is {w}x{h}",
                    file.display(),
                    img.width,
                    img.height
                );
            }
        }
    }
    Ok(())
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::npy::write_npy_f32;
    use crate::formats::png::{Image, write_png};
    use crate::tables::Provenance;
    use std::path::Path;

    /// A scene of the demo cameras with an image, a depth map and a mask per camera.
    fn scene_with_files(dir: &Path) -> Scene {
        let (scene_dir, _) = crate::datasets::demo::write_demo_scene(dir, 2).unwrap();
        let mut scene = Scene::load(&scene_dir).unwrap();
        for c in &mut scene.cameras {
            let (w, h) = c.pinhole.size();
            c.depth_path = Some(format!("depth/{}/{:05}.npy", c.camera, c.frame));
            c.mask_path = Some(format!("mask/{}/{:05}.png", c.camera, c.frame));
            write_png(&scene.dir.join(&c.image_path), &Image::filled(w, h, 4, 0.5)).unwrap();
            write_png(&scene.dir.join(c.mask_path.as_ref().unwrap()), &Image::filled(w, h, 1, 1.0))
                .unwrap();
            write_npy_f32(
                &scene.dir.join(c.depth_path.as_ref().unwrap()),
                &[h, w],
                &vec![2.0; w * h],
            )
            .unwrap();
        }
        scene.save(&Provenance::default()).unwrap();
        scene
    }

    fn check_err(scene: &Scene) -> String {
        format!("{:#}", check(&scene.dir, &Context::quiet()).unwrap_err())
    }

    #[test]
    fn every_image_depth_map_and_mask_is_decoded_and_sized() {
        let dir = tempfile::tempdir().unwrap();
        let scene = scene_with_files(dir.path());
        let report = check(&scene.dir, &Context::quiet()).unwrap();
        assert_eq!(report.scene, Some((4, 2)));
        let cams = Scene::cameras_path(&scene.dir);
        let c = &scene.cameras[3];

        let img = scene.dir.join(&c.image_path);
        let bytes = std::fs::read(&img).unwrap();
        std::fs::write(&img, &bytes[..bytes.len() - 20]).unwrap();
        let err = check_err(&scene);
        assert!(
            err.starts_with(&format!(
                "{}: column 'image_path', row 3: {}: ",
                cams.display(),
                img.display()
            )),
            "{err}"
        );
        write_png(&img, &Image::filled(80, 59, 4, 0.5)).unwrap();
        assert_eq!(
            check_err(&scene),
            format!(
                "{}: column 'image_path', row 3: {} is 80x59, the camera is 80x60",
                cams.display(),
                img.display()
            )
        );
        write_png(&img, &Image::filled(80, 60, 4, 0.5)).unwrap();

        let depth = scene.dir.join(c.depth_path.as_ref().unwrap());
        let bytes = std::fs::read(&depth).unwrap();
        std::fs::write(&depth, &bytes[..bytes.len() - 4]).unwrap();
        let err = check_err(&scene);
        assert!(
            err.starts_with(&format!(
                "{}: column 'depth_path', row 3: {}: ",
                cams.display(),
                depth.display()
            )) && err.contains("truncated"),
            "{err}"
        );
        write_npy_f32(&depth, &[80, 60], &vec![2.0; 4800]).unwrap();
        assert_eq!(
            check_err(&scene),
            format!(
                "{}: column 'depth_path', row 3: {} has shape [80, 60], the camera needs [60, 80] (height, width)",
                cams.display(),
                depth.display()
            )
        );
        write_npy_f32(&depth, &[60, 80], &vec![2.0; 4800]).unwrap();

        let mask = scene.dir.join(c.mask_path.as_ref().unwrap());
        write_png(&mask, &Image::filled(40, 30, 1, 1.0)).unwrap();
        assert_eq!(
            check_err(&scene),
            format!(
                "{}: column 'mask_path', row 3: {} is 40x30, the camera is 80x60",
                cams.display(),
                mask.display()
            )
        );
    }
}
