//! `usplat4d import dycheck`: a DyCheck iPhone sequence into a scene directory.
//!
//! Reads the splits and camera files ([`Sequence`]), then per image (rayon over images,
//! errors reported for the first failing image in camera-table order):
//! - `rgb/<factor>x/<name>.png` → `rgb/<cam>/<frame:05>.png`, RGBA (RGB gets alpha 255;
//!   DyCheck's alpha is kept: on training images it is 0 where LiDAR depth is missing);
//! - training images: `depth/<factor>x/<name>.npy` `(H, W, 1)` z-depth (0 = invalid, ×scale
//!   with `--world dycheck`) → `depth/<cam>/<frame:05>.npy` `[H, W]`;
//! - validation images: `covisible/2x/val/<name>.png` (DyCheck has it at 2x only) →
//!   `mask/<cam>/<frame:05>.png`, binarised to 0/255 (`> 0`, as MoSca reads it) and
//!   nearest-resized to the camera's size when `factor` ≠ 2.
//!
//! A missing `depth/<factor>x` or `covisible/2x/val` directory is a warning and leaves the
//! depth or mask column null; a missing file inside a present directory is an error.
//! `keypoint/2x/train/*.json` (DyCheck's PCK-T annotations: `[J, 3]` rows `[x, y, visible]`
//! in 2x integer pixel indices; see the `keypoints` module) are checked (every file parses, names
//! a training image, and has the same J) and copied unchanged with `skeleton.json` to
//! `keypoint/2x/train/`. `scene.json` records the source, factor, world frame, fps,
//! near/far, DyCheck's `scene.json` / `extra.json`, and `keypoints`: the directory and the
//! frame of each keypoint file (`{"dir", "frames": {frame_name: frame}}`).
//! `cameras.parquet` is written last.
//!
//! `--cameras-only` writes `cameras.parquet` and `scene.json` alone (for sequences shipped
//! without images, like the paper-windmill camera files): image paths are set, depth and
//! mask paths are null.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde_json::json;

use super::keypoints::{self, KEYPOINT_DIR};
use super::sequence::{SceneInfo, Sequence};
use super::{Error, Result, World};
use crate::context::Context;
use crate::formats::{self, png::Image};
use crate::scene::{Camera, Scene, Split};
use crate::tables::Provenance;
use crate::util::fs::IoError;

/// Parameters of `usplat4d import dycheck`.
#[derive(Debug, Clone, clap::Args, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct ImportDycheckParams {
    /// DyCheck sequence directory (camera/, splits/, rgb/, depth/, covisible/, ...).
    #[arg(long, value_name = "SEQ_DIR")]
    pub data: PathBuf,
    /// Scene directory to write.
    #[arg(long, value_name = "SCENE_DIR")]
    pub out: PathBuf,
    /// Downscale factor F: reads rgb/Fx and depth/Fx, divides the intrinsics by F (DyCheck's
    /// benchmark resolution is F = 2: 360x480).
    #[arg(long, default_value_t = 2)]
    pub factor: u32,
    /// World frame of cameras and depth: `source` (as stored, metres) or `dycheck`
    /// (DyCheck's parser normalisation from scene.json).
    #[arg(long, value_enum, default_value_t = World::Source)]
    pub world: World,
    /// Write only cameras.parquet and scene.json (no images, depth or masks are read).
    #[arg(long)]
    pub cameras_only: bool,
}

/// Run `usplat4d import dycheck`.
pub fn run_import(p: &ImportDycheckParams, ctx: &Context) -> anyhow::Result<()> {
    let scene = import(p, ctx)?;
    ctx.info(format!(
        "imported {} training and {} evaluation images into {}",
        scene.train().count(),
        scene.eval().count(),
        p.out.display()
    ));
    Ok(())
}

/// Import sequence `p.data` into scene directory `p.out`; returns the written scene.
pub fn import(p: &ImportDycheckParams, ctx: &Context) -> Result<Scene> {
    let _span = tracing::info_span!("import_dycheck").entered();
    if p.factor == 0 {
        return Err(Error::Factor(p.factor));
    }
    let seq = Sequence::read(&p.data)?;
    let mut cameras = seq.cameras(p.factor, p.world)?;
    let info = SceneInfo::read(&p.data.join("scene.json"))?;
    let extra_path = p.data.join("extra.json");
    let extra = if extra_path.exists() { Some(super::read_json(&extra_path, None)?) } else { None };
    let mut keypoints = None;
    if p.cameras_only {
        for c in &mut cameras {
            c.depth_path = None;
            c.mask_path = None;
        }
    } else {
        let scale = match p.world {
            World::Source => 1.0,
            World::Dycheck => info.map_or(1.0, |i| i.scale),
        };
        copy_images(p, &seq, &mut cameras, scale, ctx)?;
        keypoints = copy_keypoints(&seq, &p.out)?;
    }
    let (near, far) = match (info, p.world) {
        (Some(i), World::Dycheck) => (Some(i.near), Some(i.far)),
        (Some(i), World::Source) => (Some(i.near / i.scale), Some(i.far / i.scale)),
        (None, _) => (None, None),
    };
    let meta = json!({
        "source": "dycheck",
        "sequence": p.data.file_name().map(|n| n.to_string_lossy().into_owned()),
        "factor": p.factor,
        "world": p.world,
        "fps": extra.as_ref().and_then(|e| e.get("fps")).and_then(|f| f.as_f64()),
        "near": near,
        "far": far,
        "keypoints": keypoints,
        "dycheck_scene": info.map(|i| json!({
            "center": i.center, "scale": i.scale, "near": i.near, "far": i.far,
        })),
        "dycheck_extra": extra,
    });
    super::write_json(&p.out.join("scene.json"), &meta)?;
    let scene = Scene { dir: p.out.clone(), cameras };
    // DyCheck's alpha marks missing LiDAR depth, not coverage: compare plain RGB.
    scene.save_with(&Provenance::new("import dycheck", p), crate::scene::GtAlpha::Ignore)?;
    Ok(scene)
}

/// The split file that lists an image, for "needed by" messages.
fn split_file(split: Split) -> &'static str {
    match split {
        Split::Train => "splits/train.json",
        Split::Eval => "splits/val.json",
    }
}

/// An existing input file, or [`Error::Missing`] naming what needs it.
fn existing(path: PathBuf, name: &str, split: Split) -> Result<PathBuf> {
    if path.is_file() {
        Ok(path)
    } else {
        Err(Error::Missing { path, needed_by: Some(format!("'{name}' of {}", split_file(split))) })
    }
}

/// Convert every image, depth map and covisibility mask of `seq` into the scene layout.
fn copy_images(
    p: &ImportDycheckParams,
    seq: &Sequence,
    cameras: &mut [Camera],
    scale: f64,
    ctx: &Context,
) -> Result<()> {
    let rgb_dir = p.data.join("rgb").join(format!("{}x", p.factor));
    let depth_dir = p.data.join("depth").join(format!("{}x", p.factor));
    let cov_dir = p.data.join("covisible").join("2x").join("val");
    let has_train = cameras.iter().any(|c| c.split == Split::Train);
    if has_train && !depth_dir.is_dir() {
        ctx.warn(format!("{} not found: training images get no depth", depth_dir.display()));
        cameras.iter_mut().for_each(|c| c.depth_path = None);
    }
    let has_eval = cameras.iter().any(|c| c.split == Split::Eval);
    if has_eval && !cov_dir.is_dir() {
        ctx.warn(format!(
            "{} not found: evaluation images get no covisibility mask",
            cov_dir.display()
        ));
        cameras.iter_mut().for_each(|c| c.mask_path = None);
    }
    let bar = ctx.progress(cameras.len() as u64, "import");
    let results: Vec<Result<()>> = cameras
        .par_iter()
        .zip(seq.entries.par_iter())
        .map(|(cam, e)| {
            let (w, h) = cam.pinhole.size();
            let src = existing(rgb_dir.join(format!("{}.png", e.name)), &e.name, e.split)?;
            let img = formats::png::read_png(&src)?;
            check_size(&src, img.width, img.height, cam, p.factor)?;
            formats::png::write_png(&p.out.join(&cam.image_path), &to_rgba(img))?;
            if let Some(rel) = &cam.depth_path {
                let src = existing(depth_dir.join(format!("{}.npy", e.name)), &e.name, e.split)?;
                let (shape, mut data) = formats::npy::read_npy_f32(&src)?;
                if shape != [h, w, 1] && shape != [h, w] {
                    return Err(Error::File {
                        path: src,
                        msg: format!(
                            "depth shape {shape:?} does not match the camera's image ({h}, {w}, 1)"
                        ),
                    });
                }
                if scale != 1.0 {
                    data.iter_mut().for_each(|d| *d = (*d as f64 * scale) as f32);
                }
                formats::npy::write_npy_f32(&p.out.join(rel), &[h, w], &data)?;
            }
            if let Some(rel) = &cam.mask_path {
                let src = existing(cov_dir.join(format!("{}.png", e.name)), &e.name, e.split)?;
                let m = formats::png::read_png(&src)?.channel(0);
                let data: Vec<f32> =
                    m.data.iter().map(|v| if *v > 0.0 { 1.0 } else { 0.0 }).collect();
                let data = if (m.width, m.height) == (w, h) {
                    data
                } else {
                    super::resize_nearest(&data, m.width, m.height, 1, w, h)
                };
                formats::png::write_png(
                    &p.out.join(rel),
                    &Image { width: w, height: h, channels: 1, data },
                )?;
            }
            bar.inc(1);
            Ok(())
        })
        .collect();
    bar.finish_and_clear();
    results.into_iter().collect()
}

/// An image size mismatch names the image and the camera size.
fn check_size(path: &Path, w: usize, h: usize, cam: &Camera, factor: u32) -> Result<()> {
    if (w, h) == cam.pinhole.size() {
        return Ok(());
    }
    Err(Error::File {
        path: path.into(),
        msg: format!(
            "image is {w}x{h} but its camera at factor {factor} is {}x{} (W x H)",
            cam.pinhole.width, cam.pinhole.height
        ),
    })
}

/// `img` with 4 channels: grey is replicated, missing alpha is 1.
fn to_rgba(img: Image) -> Image {
    if img.channels == 4 {
        return img;
    }
    let n = img.width * img.height;
    let mut data = Vec::with_capacity(n * 4);
    for px in img.data.chunks_exact(img.channels) {
        match px.len() {
            1 => data.extend_from_slice(&[px[0], px[0], px[0], 1.0]),
            _ => data.extend_from_slice(&[px[0], px[1], px[2], 1.0]),
        }
    }
    Image { channels: 4, data, ..img }
}

/// Copy `keypoint/2x/train/*.json` (and `skeleton.json`) unchanged after checking each
/// file and resolving its name to a training image of `seq`; returns the `scene.json`
/// entry `{"dir", "frames": {frame_name: frame}}` when the directory exists.
fn copy_keypoints(seq: &Sequence, out: &Path) -> Result<Option<serde_json::Value>> {
    let dir = seq.dir.join(KEYPOINT_DIR);
    if !dir.is_dir() {
        return Ok(None);
    }
    let frame_of: HashMap<&str, u32> = seq
        .entries
        .iter()
        .filter(|e| e.split == Split::Train)
        .map(|e| (e.name.as_str(), e.frame))
        .collect();
    let mut frames = serde_json::Map::new();
    let mut first: Option<(PathBuf, usize)> = None;
    let files = keypoints::list_files(&dir)?;
    for f in &files {
        let stem = f.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let frame = *frame_of.get(stem.as_str()).ok_or_else(|| Error::File {
            path: f.clone(),
            msg: format!("'{stem}' is not a training image of splits/train.json"),
        })?;
        let j = keypoints::read_keypoints(f)?.len();
        match &first {
            Some((p, n)) if *n != j => {
                return Err(Error::File {
                    path: f.clone(),
                    msg: format!("has {j} keypoints but {} has {n}", p.display()),
                });
            }
            Some(_) => {}
            None => first = Some((f.clone(), j)),
        }
        frames.insert(stem, json!(frame));
    }
    let skeleton = dir.join(keypoints::SKELETON);
    for f in files.iter().chain(skeleton.is_file().then_some(&skeleton)) {
        let bytes = std::fs::read(f).map_err(IoError::at(f))?;
        let name = f.file_name().unwrap_or_default();
        crate::util::fs::write_atomic(&out.join(KEYPOINT_DIR).join(name), &bytes)?;
    }
    Ok(Some(json!({"dir": KEYPOINT_DIR, "frames": frames})))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_defaults_and_unknown_options() {
        let parse = crate::util::parse_args::<ImportDycheckParams>;
        let p = parse(&["--data", "seq", "--out", "scene"]).unwrap();
        assert_eq!((p.factor, p.world, p.cameras_only), (2, World::Source, false));
        let p = parse(&["--data", "s", "--out", "o", "--world", "dycheck", "--cameras-only"]);
        let p = p.unwrap();
        assert_eq!((p.world, p.cameras_only), (World::Dycheck, true));
        let err = parse(&["--data", "s", "--out", "o", "--factr", "2"]).unwrap_err().to_string();
        assert!(err.contains("unexpected argument '--factr'"), "{err}");
    }

    #[test]
    fn rgb_and_grey_become_rgba() {
        let rgb = Image { width: 1, height: 1, channels: 3, data: vec![0.1, 0.2, 0.3] };
        assert_eq!(to_rgba(rgb).data, [0.1, 0.2, 0.3, 1.0]);
        let grey = Image { width: 1, height: 1, channels: 1, data: vec![0.5] };
        assert_eq!(to_rgba(grey).data, [0.5, 0.5, 0.5, 1.0]);
    }
}
