//! `usplat4d render`: render a model into every camera of a scene split, as RGBA PNGs laid
//! out like the scene's images (`OUT/<camera image_path>`), for `evaluate` to pair by path.
//!
//! Streaming: cameras are grouped by frame; each model frame is read once (`Model::frame`)
//! and rendered for all cameras of that frame. Output convention matches the synthetic
//! ground truth: RGBA with *straight* (non-premultiplied) colour and alpha = coverage.
//! The renderer's colour is composited over `--background`; it is un-composited as
//! `rgb = (colour − (1 − α)·bg) / α` (= Σ T·α·c / α) where α > 0, rgb = 0 where α = 0, so that
//! compositing the PNG over any background reproduces the render over that background.
//! With `--depth`, the expected z-depth normalised by alpha (Σ T·α·z / α) is written as
//! float32 `.npy` at the camera's `depth_path` (or `depth/<camera>/<frame:05>.npy`), 0 where
//! α < 0.5 (invalid, the DESIGN convention). Lens distortion is ignored (pinhole render).
//! Everything is written to a staging directory beside OUT and moved into OUT only once every
//! camera rendered, so a bad frame leaves no partial output.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context as _;

use crate::context::Context;
use crate::formats::npy::write_npy_f32;
use crate::formats::png::{Image, write_png};
use crate::model::{FrameState, Model};
use crate::render::{RenderCamera, RenderOutput, RenderSettings, Renderer, ShFrame};
use crate::scene::{Camera, Scene, Split};
use crate::util::fs::{publish, staging_dir, write_atomic};

/// Which cameras to render.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum SplitSel {
    /// Training cameras only.
    Train,
    /// Evaluation cameras only.
    Eval,
    /// Every camera.
    All,
}

/// Parameters of `usplat4d render`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RenderParams {
    /// Model directory (gaussians.parquet + trajectories.parquet).
    #[arg(long, help_heading = "Inputs")]
    pub model: PathBuf,
    /// Scene directory (cameras.parquet).
    #[arg(long, help_heading = "Inputs")]
    pub scene: PathBuf,
    /// Output directory; images go to OUT/<camera image_path>.
    #[arg(long, help_heading = "Outputs")]
    pub out: PathBuf,
    /// Cameras to render.
    #[arg(long, value_enum, default_value_t = SplitSel::All, help_heading = "Selection")]
    #[serde(default = "default_split")]
    pub split: SplitSel,
    /// Background the renderer composites over: `white`, `black` or `R,G,B` in [0, 1].
    #[arg(long, default_value = "white", help_heading = "Rendering")]
    #[serde(default = "default_background")]
    pub background: String,
    /// Upper clamp of a Gaussian's alpha at a pixel (3DGS 0.99, the release's fork 0.999).
    #[arg(long, default_value_t = 0.99, help_heading = "Rendering")]
    #[serde(default = "default_alpha_max")]
    pub alpha_max: f32,
    /// Also write the expected z-depth as float32 .npy.
    #[arg(long, help_heading = "Outputs")]
    #[serde(default)]
    pub depth: bool,
}

fn default_split() -> SplitSel {
    SplitSel::All
}
fn default_background() -> String {
    "white".into()
}
fn default_alpha_max() -> f32 {
    0.99
}
/// Parse `white`, `black` or `R,G,B`.
pub fn parse_background(s: &str) -> anyhow::Result<[f32; 3]> {
    match s {
        "white" => Ok([1.0; 3]),
        "black" => Ok([0.0; 3]),
        _ => {
            let v: Vec<f32> =
                s.split(',').map(|p| p.trim().parse::<f32>()).collect::<Result<_, _>>().map_err(
                    |_| anyhow::anyhow!("--background '{s}': expected white, black or R,G,B"),
                )?;
            match v[..] {
                [r, g, b] if v.iter().all(|c| (0.0..=1.0).contains(c)) => Ok([r, g, b]),
                _ => anyhow::bail!("--background '{s}': expected three values in [0, 1]"),
            }
        }
    }
}

/// The RGBA image (straight colour) of a render composited over `bg`.
pub fn straight_rgba(out: &RenderOutput, bg: [f32; 3]) -> Image {
    let n = out.width * out.height;
    let mut data = Vec::with_capacity(n * 4);
    for p in 0..n {
        let a = out.alpha[p];
        for c in 0..3 {
            let premult = out.color[p * 3 + c] - (1.0 - a) * bg[c];
            data.push(if a > 0.0 { premult / a } else { 0.0 });
        }
        data.push(a);
    }
    Image { width: out.width, height: out.height, channels: 4, data }
}

/// The depth map written by `--depth`: Σ T·α·z / α, 0 where α < 0.5.
pub fn normalized_depth(out: &RenderOutput) -> Vec<f32> {
    out.depth.iter().zip(&out.alpha).map(|(d, a)| if *a >= 0.5 { d / a } else { 0.0 }).collect()
}

fn depth_rel_path(c: &Camera) -> String {
    c.depth_path.clone().unwrap_or_else(|| format!("depth/{}/{:05}.npy", c.camera, c.frame))
}

fn render_frame(
    renderer: &dyn Renderer,
    model: &Model,
    state: &FrameState,
    cam: &Camera,
    settings: &RenderSettings,
) -> anyhow::Result<RenderOutput> {
    let cam = model.render_camera(cam);
    Ok(renderer.render(&RenderCamera::from(&cam), &model.splat_inputs(state), settings)?)
}

/// Run `usplat4d render`.
pub fn run(p: &RenderParams, ctx: &Context) -> anyhow::Result<()> {
    let _span = tracing::info_span!("stage.render").entered();
    let background = parse_background(&p.background)?;
    let settings = RenderSettings { background, alpha_max: p.alpha_max };
    let scene = Scene::load(&p.scene)?;
    let model = Model::load(&p.model)?;
    let cams: Vec<&Camera> = scene
        .cameras
        .iter()
        .filter(|c| match p.split {
            SplitSel::All => true,
            SplitSel::Train => c.split == Split::Train,
            SplitSel::Eval => c.split == Split::Eval,
        })
        .collect();
    let mut by_frame: BTreeMap<u32, Vec<&Camera>> = BTreeMap::new();
    for c in &cams {
        by_frame.entry(c.frame).or_default().push(c);
    }
    let t_max = model.num_frames();
    if let Some((&f, cs)) = by_frame.iter().next_back().filter(|(f, _)| **f as usize >= t_max) {
        anyhow::bail!(
            "{}: camera '{}' is at frame {f}, but the model {} has {t_max} frames",
            Scene::cameras_path(&p.scene).display(),
            cs[0].camera,
            p.model.display()
        );
    }
    if cams.iter().any(|c| c.distortion.is_some()) {
        ctx.warn("some cameras have lens distortion; the renderer ignores it (pinhole)");
    }
    let bar = ctx.progress(cams.len() as u64, "render");
    let renderer = super::device::renderer(ctx)?;
    let staging = staging_dir(&p.out, ".render-")?;
    let staged = staging.path();
    for (&frame, cs) in &by_frame {
        let state = model.frame(frame as usize)?;
        for cam in cs {
            let out = render_frame(&renderer, &model, &state, cam, &settings)
                .with_context(|| format!("rendering camera '{}' frame {frame}", cam.camera))?;
            write_png(&staged.join(&cam.image_path), &straight_rgba(&out, background))?;
            if p.depth {
                let path = staged.join(depth_rel_path(cam));
                write_npy_f32(&path, &[out.height, out.width], &normalized_depth(&out))?;
            }
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    write_manifest(staged, p, model.sh_frame, cams.len())?;
    publish(staged, &p.out)?;
    ctx.info(format!("rendered {} images into {}", cams.len(), p.out.display()));
    Ok(())
}

fn write_manifest(
    out: &Path,
    p: &RenderParams,
    sh_frame: ShFrame,
    count: usize,
) -> anyhow::Result<()> {
    let manifest = serde_json::json!({
        "model": p.model,
        "scene": p.scene,
        "split": p.split,
        "count": count,
        "background": p.background,
        "alpha_max": p.alpha_max.to_string().parse::<f64>().unwrap_or(f64::NAN),
        "sh_frame": sh_frame.name(),
        "depth": p.depth,
        "version": crate::VERSION,
    });
    let text = serde_json::to_string_pretty(&manifest)?;
    write_atomic(&out.join("renders.json"), text.as_bytes())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::datasets::demo::write_demo_scene;

    #[test]
    fn renders_every_camera_of_a_split_with_straight_alpha() {
        let dir = tempfile::tempdir().unwrap();
        let (scene, model) = write_demo_scene(dir.path(), 3).unwrap();
        let out = dir.path().join("out");
        let p = RenderParams {
            model,
            scene,
            out: out.clone(),
            split: SplitSel::Eval,
            background: "white".into(),
            alpha_max: 0.99,
            depth: true,
        };
        run(&p, &Context::quiet()).unwrap();
        for t in 0..3 {
            let img =
                crate::formats::png::read_png(&out.join(format!("rgb/cam01/{t:05}.png"))).unwrap();
            assert_eq!((img.width, img.height, img.channels), (80, 60, 4));
            assert!(img.at(40, 30, 3) > 0.95, "the plane covers the centre");
            assert_eq!(img.at(0, 0, 3), 0.0, "the corner is empty");
            let (shape, d) =
                crate::formats::npy::read_npy_f32(&out.join(format!("depth/cam01/{t:05}.npy")))
                    .unwrap();
            assert_eq!(shape, vec![60, 80]);
            assert!((d[30 * 80 + 40] - 4.0).abs() < 0.2, "depth at the centre {}", d[30 * 80 + 40]);
        }
        assert!(!out.join("rgb/cam00").exists());
        let manifest: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("renders.json")).unwrap()).unwrap();
        assert_eq!(manifest["count"], 3);
        assert_eq!(manifest["split"], "eval");
    }

    #[test]
    fn straight_colour_composites_back_to_the_render() {
        let out = RenderOutput {
            width: 2,
            height: 1,
            color: vec![0.55, 0.5, 0.9, 1.0, 1.0, 1.0],
            alpha: vec![0.5, 0.0],
            depth: vec![1.0, 0.0],
            ..RenderOutput::default()
        };
        let img = straight_rgba(&out, [1.0; 3]);
        let want = [0.1, 0.0, 0.8, 0.5, 0.0, 0.0, 0.0, 0.0];
        assert!(img.data.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6), "{:?}", img.data);
        let back = img.rgb_over([1.0; 3]);
        for (a, b) in back.data.iter().zip(&out.color) {
            assert!((a - b).abs() < 1e-6);
        }
        assert_eq!(normalized_depth(&out), vec![2.0, 0.0]);
    }

    #[test]
    fn bad_background_and_missing_model_frames_are_errors() {
        assert!(parse_background("0.5,0.5").is_err());
        assert_eq!(parse_background("0,0.5,1").unwrap(), [0.0, 0.5, 1.0]);
        let dir = tempfile::tempdir().unwrap();
        let (scene, _) = write_demo_scene(dir.path(), 3).unwrap();
        let (_, model) = write_demo_scene(&dir.path().join("short"), 2).unwrap();
        let p = RenderParams {
            model,
            scene,
            out: dir.path().join("out"),
            split: SplitSel::All,
            background: "white".into(),
            alpha_max: 0.99,
            depth: false,
        };
        let err = run(&p, &Context::quiet()).unwrap_err().to_string();
        assert!(
            err.contains("cameras.parquet") && err.contains("frame 2") && err.contains("2 frames"),
            "{err}"
        );
    }

    fn files_under(dir: &Path) -> Vec<String> {
        let mut out = Vec::new();
        let mut stack = vec![dir.to_path_buf()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).into_iter().flatten() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    out.push(p.strip_prefix(dir).unwrap().to_string_lossy().into_owned());
                }
            }
        }
        out.sort();
        out
    }

    /// A bad frame after good ones leaves no partial output: neither images of the good
    /// frames nor a staging directory; an existing output directory keeps its files.
    #[test]
    fn a_bad_later_frame_leaves_no_partial_output() {
        let dir = tempfile::tempdir().unwrap();
        let (scene, model) = write_demo_scene(dir.path(), 6).unwrap();
        let m = Model::load(&model).unwrap();
        let frames: Vec<_> = (0..6)
            .map(|t| {
                let mut f = m.frame(t).unwrap();
                if t == 4 {
                    f.position[7][1] = f32::NAN;
                }
                Ok(f)
            })
            .collect();
        Model::save(&model, &m.gaussians, frames, &crate::tables::Provenance::default()).unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(out.join("notes.txt"), "mine").unwrap();
        let p = RenderParams {
            model,
            scene,
            out: out.clone(),
            split: SplitSel::All,
            background: "white".into(),
            alpha_max: 0.99,
            depth: true,
        };
        let err = format!("{:#}", run(&p, &Context::quiet()).unwrap_err());
        assert!(err.contains("trajectories.parquet") && err.contains("row 2311"), "{err}");
        assert_eq!(files_under(&out), ["notes.txt"]);
        let siblings: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(siblings.iter().all(|n| !n.starts_with('.')), "staging left: {siblings:?}");
        let fresh = RenderParams { out: dir.path().join("fresh"), ..p };
        assert!(run(&fresh, &Context::quiet()).is_err());
        assert!(!fresh.out.exists(), "a failed render creates no output directory");
    }
}
