//! `usplat4d synth`: the synthetic extreme-view benchmark rendered from an animated glTF
//! model with our own CPU rasterizer, with exact ground truth.
//!
//! Pipeline: [`asset::load`] reads the glTF (nodes, skins, animations, morph targets,
//! materials, textures); each benchmark frame t maps to an animation time
//! ([`anim::frame_time`], zig-zag when the clip is short), is posed ([`anim::pose`],
//! [`skin::pose_vertices`]) and normalised (centre of the bounding box over all frames at
//! the origin, box diagonal 2, then [`cameras::Placement`] into the camera world). Pass 1
//! finds that box; pass 2 writes the oracle model (`oracle/`, N area-uniform surface
//! Gaussians) and `tracks_3d`; pass 3 renders every training frame (and `tracks_2d` by depth
//! test), then every eval view: RGBA, z-depth `.npy` and mask per image, written and
//! dropped one frame at a time ([`raster`], [`shade`]). The camera protocol is in
//! [`cameras`]; `--layout dycheck` adds covisibility masks ([`covis`]) and the DyCheck
//! folder layout.

mod anim;
mod asset;
mod cameras;
mod covis;
pub mod priors;
mod raster;
mod shade;
mod shader;
mod skin;
pub(crate) mod surface;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};
use rayon::prelude::*;

pub use priors::PriorKind;
pub use shade::TextureMode;

use crate::context::Context;
use crate::datasets::dycheck;
use crate::formats::{self, npy::write_npy_f32, png::write_png};
use crate::model::{FrameState, Gaussians, Model};
use crate::scene::{Camera, Scene, Split};
use crate::tables::tracks_2d::{Tracks2dFrame, Tracks2dWriter};
use crate::tables::tracks_3d::Tracks3dWriter;
use crate::tables::{self, Provenance};
use crate::util::fs::IoError;
use crate::util::rng::{Rng, mix};

/// Output layouts of `synth`.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Layout {
    /// The scene directory only.
    Scene,
    /// The scene directory plus the DyCheck iPhone layout in `SCENE_DIR/dycheck/`, with
    /// covisibility masks as the eval cameras' masks.
    Dycheck,
}

/// Parameters of `usplat4d synth`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct SynthParams {
    /// The animated glTF model (`.glb`, or `.gltf` with embedded or external buffers).
    #[arg(long, help_heading = "Input")]
    pub gltf: PathBuf,
    /// Animation to play (default: the first one).
    #[arg(long, help_heading = "Input")]
    #[serde(default)]
    pub animation: Option<String>,
    /// Output scene directory.
    #[arg(long, help_heading = "Output")]
    pub out: PathBuf,
    /// Number of frames T of the training video (orbit protocol).
    #[arg(long, default_value_t = 121, help_heading = "Protocol")]
    #[serde(default = "defaults::frames")]
    pub frames: u32,
    /// Number of cameras C on the circle (camera 0 trains, the others evaluate).
    #[arg(long, default_value_t = 12, help_heading = "Protocol")]
    #[serde(default = "defaults::cameras")]
    pub cameras: u32,
    /// Counter-clockwise rotation of all cameras per frame, degrees.
    #[arg(long, default_value_t = 3.0, help_heading = "Protocol")]
    #[serde(default = "defaults::deg_per_frame")]
    pub deg_per_frame: f64,
    /// Camera elevation above the horizontal, degrees.
    #[arg(long, default_value_t = 35.0, help_heading = "Protocol")]
    #[serde(default = "defaults::elevation_deg")]
    pub elevation_deg: f64,
    /// Image width, pixels.
    #[arg(long, default_value_t = 512, help_heading = "Protocol")]
    #[serde(default = "defaults::size")]
    pub width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 512, help_heading = "Protocol")]
    #[serde(default = "defaults::size")]
    pub height: u32,
    /// Rate at which the animation is sampled, frames per second.
    #[arg(long, default_value_t = 30.0, help_heading = "Protocol")]
    #[serde(default = "defaults::fps")]
    pub fps: f64,
    /// Supersampling per pixel side (2 → 2x2 samples).
    #[arg(long, default_value_t = 2, help_heading = "Rendering")]
    #[serde(default = "defaults::supersample")]
    pub supersample: u32,
    /// Procedural texture: on untextured materials (auto), everywhere, or never.
    #[arg(long, value_enum, default_value_t = TextureMode::Auto, help_heading = "Rendering")]
    #[serde(default = "defaults::texture")]
    pub texture: TextureMode,
    /// Number of oracle Gaussians N.
    #[arg(long, default_value_t = 20000, help_heading = "Ground truth")]
    #[serde(default = "defaults::gaussians")]
    pub gaussians: u32,
    /// Number of ground-truth tracks M.
    #[arg(long, default_value_t = 1024, help_heading = "Ground truth")]
    #[serde(default = "defaults::tracks")]
    pub tracks: u32,
    /// Static ground plane under the model with this many static oracle Gaussians on it
    /// (`dynamic = false`), 0 for none: a well-observed static background as real base
    /// models have. It is in the colour, alpha and depth, not in the foreground mask.
    #[arg(long, default_value_t = 0, help_heading = "Ground truth")]
    #[serde(default)]
    pub ground_plane: u32,
    /// Seed of the surface sampling.
    #[arg(long, default_value_t = 0, help_heading = "Ground truth")]
    #[serde(default)]
    pub seed: u64,
    /// Render along a real camera path instead of the orbit: `dycheck:DIR`.
    #[arg(long, help_heading = "Protocol")]
    #[serde(default)]
    pub trajectory: Option<String>,
    /// Downscale factor of the DyCheck cameras of `--trajectory`.
    #[arg(long, default_value_t = 2, help_heading = "Protocol")]
    #[serde(default = "defaults::trajectory_factor")]
    pub trajectory_factor: u32,
    /// Keep every S-th frame of the `--trajectory` path (training and validation cameras
    /// alike), renumbered 0, 1, 2, ...; the animation advances one sample per kept frame.
    #[arg(long, default_value_t = 1, help_heading = "Protocol")]
    #[serde(default = "defaults::trajectory_stride")]
    pub trajectory_stride: u32,
    /// Output layout.
    #[arg(long, value_enum, default_value_t = Layout::Scene, help_heading = "Output")]
    #[serde(default = "defaults::layout")]
    pub layout: Layout,
    /// Monocular priors written beside the exact data (`priors/`, named in `priors.json`).
    #[arg(long, value_enum, default_value_t = PriorKind::Realistic, help_heading = "Priors")]
    #[serde(default = "defaults::priors")]
    pub priors: PriorKind,
    /// σ of the log of the per-frame depth scale error.
    #[arg(long, default_value_t = 0.02, help_heading = "Priors")]
    #[serde(default = "defaults::depth_scale_error")]
    pub depth_scale_error: f64,
    /// σ of the per-frame depth shift error, in units of the frame's median depth.
    #[arg(long, default_value_t = 0.01, help_heading = "Priors")]
    #[serde(default = "defaults::depth_shift_error")]
    pub depth_shift_error: f64,
    /// σ of the relative depth noise (mostly smooth, partly per pixel).
    #[arg(long, default_value_t = 0.03, help_heading = "Priors")]
    #[serde(default = "defaults::depth_noise")]
    pub depth_noise: f64,
    /// σ of the depth edge-bleeding blur, pixels.
    #[arg(long, default_value_t = 1.0, help_heading = "Priors")]
    #[serde(default = "defaults::depth_edge_px")]
    pub depth_edge_px: f64,
    /// σ of the track position noise per axis, pixels.
    #[arg(long, default_value_t = 1.0, help_heading = "Priors")]
    #[serde(default = "defaults::track_noise_px")]
    pub track_noise_px: f64,
    /// Fraction of tracks that keep their drift after an occlusion.
    #[arg(long, default_value_t = 0.15, help_heading = "Priors")]
    #[serde(default = "defaults::track_drift_fraction")]
    pub track_drift_fraction: f64,
    /// σ per axis and occluded frame of the track drift random walk, pixels.
    #[arg(long, default_value_t = 1.0, help_heading = "Priors")]
    #[serde(default = "defaults::track_drift_px")]
    pub track_drift_px: f64,
    /// Largest shift of a visibility change, frames.
    #[arg(long, default_value_t = 2, help_heading = "Priors")]
    #[serde(default = "defaults::visibility_lag")]
    pub visibility_lag: u32,
    /// Probability that a visibility label flips.
    #[arg(long, default_value_t = 0.03, help_heading = "Priors")]
    #[serde(default = "defaults::visibility_flip")]
    pub visibility_flip: f64,
}

impl SynthParams {
    /// The error levels of the realistic priors.
    pub fn levels(&self) -> priors::Levels {
        priors::Levels {
            depth_scale_error: self.depth_scale_error,
            depth_shift_error: self.depth_shift_error,
            depth_noise: self.depth_noise,
            depth_edge_px: self.depth_edge_px,
            track_noise_px: self.track_noise_px,
            track_drift_fraction: self.track_drift_fraction,
            track_drift_px: self.track_drift_px,
            visibility_lag: self.visibility_lag,
            visibility_flip: self.visibility_flip,
        }
    }
}

mod defaults {
    pub fn frames() -> u32 {
        121
    }
    pub fn cameras() -> u32 {
        12
    }
    pub fn deg_per_frame() -> f64 {
        3.0
    }
    pub fn elevation_deg() -> f64 {
        35.0
    }
    pub fn size() -> u32 {
        512
    }
    pub fn fps() -> f64 {
        30.0
    }
    pub fn supersample() -> u32 {
        2
    }
    pub fn texture() -> super::TextureMode {
        super::TextureMode::Auto
    }
    pub fn gaussians() -> u32 {
        20000
    }
    pub fn tracks() -> u32 {
        1024
    }
    pub fn trajectory_stride() -> u32 {
        1
    }
    pub fn trajectory_factor() -> u32 {
        2
    }
    pub fn layout() -> super::Layout {
        super::Layout::Scene
    }
    pub fn priors() -> super::PriorKind {
        super::PriorKind::Realistic
    }
    pub fn depth_scale_error() -> f64 {
        0.02
    }
    pub fn depth_shift_error() -> f64 {
        0.01
    }
    pub fn depth_noise() -> f64 {
        0.03
    }
    pub fn depth_edge_px() -> f64 {
        1.0
    }
    pub fn track_noise_px() -> f64 {
        1.0
    }
    pub fn track_drift_fraction() -> f64 {
        0.15
    }
    pub fn track_drift_px() -> f64 {
        1.0
    }
    pub fn visibility_lag() -> u32 {
        2
    }
    pub fn visibility_flip() -> f64 {
        0.03
    }
}

/// Errors of the synthetic benchmark generator; each names the file it concerns.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The model file cannot be read.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The glTF is truncated, malformed or unsupported.
    #[error("{}: not a usable glTF file: {msg}", path.display())]
    Malformed {
        /// The glTF file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// A buffer or texture image the glTF references is missing.
    #[error("{}: {what} refers to the missing file {}", path.display(), file.display())]
    MissingFile {
        /// The glTF file.
        path: PathBuf,
        /// Which object refers to it.
        what: String,
        /// The missing file.
        file: PathBuf,
    },
    /// `--animation` names no animation of the file.
    #[error("{}: no animation named '{name}' (available: {available})", path.display())]
    UnknownAnimation {
        /// The glTF file.
        path: PathBuf,
        /// The requested name.
        name: String,
        /// The available names.
        available: String,
    },
    /// The posed model has no extent or no area.
    #[error("{}: the model is degenerate: {msg}", path.display())]
    Degenerate {
        /// The glTF file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// A parameter is out of range.
    #[error("--{flag}: {msg}")]
    Param {
        /// The flag.
        flag: &'static str,
        /// What is wrong.
        msg: String,
    },
    /// Writing a table failed.
    #[error(transparent)]
    Table(#[from] tables::Error),
    /// Writing an image failed.
    #[error(transparent)]
    Image(#[from] formats::Error),
    /// Reading a DyCheck camera path or writing the DyCheck layout failed.
    #[error(transparent)]
    Dycheck(#[from] dycheck::Error),
}

/// What [`generate`] produced.
#[derive(Debug, Clone)]
pub struct Summary {
    /// Training frames T.
    pub frames: usize,
    /// Images rendered (train and eval).
    pub images: usize,
    /// Triangles of the model.
    pub triangles: usize,
}

/// Run the stage.
pub fn run(p: &SynthParams, ctx: &Context) -> anyhow::Result<()> {
    let t0 = std::time::Instant::now();
    let s = generate(p, ctx)?;
    ctx.info(format!(
        "synth: {} images ({} frames, {} triangles) in {}, {:.1} s",
        s.images,
        s.frames,
        s.triangles,
        p.out.display(),
        t0.elapsed().as_secs_f64()
    ));
    Ok(())
}

fn check(p: &SynthParams) -> Result<(), Error> {
    let param = |flag, msg: &str| Err(Error::Param { flag, msg: msg.to_string() });
    if p.frames == 0 {
        return param("frames", "must be at least 1");
    }
    if p.cameras == 0 {
        return param("cameras", "must be at least 1");
    }
    if p.width == 0 || p.height == 0 || p.width > 16384 || p.height > 16384 {
        return param("width", "width and height must be in 1..=16384");
    }
    if p.trajectory_stride == 0 {
        return param("trajectory-stride", "must be at least 1");
    }
    if !(1..=8).contains(&p.supersample) {
        return param("supersample", "must be in 1..=8");
    }
    if !(p.fps > 0.0 && p.fps.is_finite()) {
        return param("fps", "must be positive");
    }
    if p.elevation_deg.is_nan() || p.elevation_deg.abs() >= 90.0 || !p.deg_per_frame.is_finite() {
        return param(
            "elevation-deg",
            "elevation must be inside (-90, 90) and the rotation finite",
        );
    }
    if p.gaussians == 0 {
        return param("gaussians", "must be at least 1");
    }
    let lv = p.levels();
    for (flag, v) in [
        ("depth-scale-error", lv.depth_scale_error),
        ("depth-shift-error", lv.depth_shift_error),
        ("depth-noise", lv.depth_noise),
        ("depth-edge-px", lv.depth_edge_px),
        ("track-noise-px", lv.track_noise_px),
        ("track-drift-px", lv.track_drift_px),
    ] {
        if !(v >= 0.0 && v.is_finite()) {
            return param(flag, "must be finite and non-negative");
        }
    }
    for (flag, v) in
        [("track-drift-fraction", lv.track_drift_fraction), ("visibility-flip", lv.visibility_flip)]
    {
        if !(0.0..=1.0).contains(&v) {
            return param(flag, "must be in [0, 1]");
        }
    }
    Ok(())
}

/// The scene's cameras: the orbit protocol, or a DyCheck path with scene-layout paths.
fn protocol_cameras(p: &SynthParams) -> Result<(Vec<Camera>, bool), Error> {
    match &p.trajectory {
        None => Ok((
            cameras::orbit(
                p.frames,
                p.cameras,
                p.deg_per_frame,
                p.elevation_deg,
                p.width,
                p.height,
            ),
            false,
        )),
        Some(t) => {
            let dir = t.strip_prefix("dycheck:").ok_or_else(|| Error::Param {
                flag: "trajectory",
                msg: format!("'{t}' is not of the form dycheck:DIR"),
            })?;
            let stride = p.trajectory_stride;
            let mut cams = dycheck::read_camera_path(Path::new(dir), p.trajectory_factor)?;
            cams.retain(|c| c.frame % stride == 0);
            for c in &mut cams {
                c.frame /= stride;
                let (rgb, depth, mask) = cameras::paths(&c.camera, c.frame);
                (c.image_path, c.depth_path, c.mask_path) = (rgb, Some(depth), Some(mask));
                c.distortion = None;
            }
            Ok((cams, true))
        }
    }
}

/// Generate the benchmark scene of `p` (see the module doc).
pub fn generate(p: &SynthParams, ctx: &Context) -> Result<Summary, Error> {
    check(p)?;
    let asset = asset::load(&p.gltf)?;
    let anim = asset.animation(p.animation.as_deref())?;
    if anim.is_none() {
        ctx.warn(format!(
            "{}: the file has no animation; rendering a static scene",
            p.gltf.display()
        ));
    }
    if asset.parts.iter().all(|x| x.skin.is_none()) {
        ctx.warn(format!(
            "{}: no skinned mesh; only node and morph animation moves the model",
            p.gltf.display()
        ));
    }
    let shader = shader::Shader::new(&asset, p.texture);
    let (mut cams, on_path) = protocol_cameras(p)?;
    let num_train = cams
        .iter()
        .filter(|c| c.split == Split::Train)
        .map(|c| c.frame as usize + 1)
        .max()
        .unwrap_or(0);
    if num_train == 0 {
        return Err(Error::Param {
            flag: "trajectory",
            msg: "the camera path has no training camera".into(),
        });
    }
    let last_frame = cams.iter().map(|c| c.frame).max().unwrap_or(0);
    let times: Vec<f32> = (0..=last_frame)
        .map(|t| anim.map(|a| anim::frame_time(t, p.fps, a.start, a.end)).unwrap_or(0.0))
        .collect();

    // Pass 1: bounding box over all frames, glTF world space.
    let bar = ctx.progress(times.len() as u64, "bounds");
    let (lo, hi) = times
        .par_iter()
        .map(|&t| {
            let v = skin::pose_vertices(&asset, &anim::pose(&asset.nodes, &asset.parent, anim, t));
            bar.inc(1);
            v.iter().fold((Vec3::MAX, Vec3::MIN), |(lo, hi), p| (lo.min(*p), hi.max(*p)))
        })
        .reduce(|| (Vec3::MAX, Vec3::MIN), |a, b| (a.0.min(b.0), a.1.max(b.1)));
    bar.finish_and_clear();
    let diag = (hi - lo).length();
    if !(diag > 0.0 && diag.is_finite()) {
        return Err(Error::Degenerate {
            path: p.gltf.clone(),
            msg: format!("bounding box diagonal {diag}"),
        });
    }
    let centre = (lo + hi) / 2.0;
    let norm_scale = 2.0 / diag;
    let placement =
        if on_path { cameras::place_on_path(&cams) } else { cameras::Placement::IDENTITY };
    let to_world = placement.matrix().as_mat4()
        * Mat4::from_scale(Vec3::splat(norm_scale))
        * Mat4::from_translation(-centre);
    // The model's triangles, then those of the ground plane (static vertices appended).
    let num_model_tris = asset.mesh.tris.len();
    let num_model_verts =
        skin::pose_vertices(&asset, &anim::pose(&asset.nodes, &asset.parent, anim, times[0])).len();
    let (plane_verts, plane_tris) = if p.ground_plane > 0 {
        let floor = (lo.y - centre.y) * norm_scale;
        ground_plane(floor, placement.matrix().as_mat4(), num_model_verts as u32)
    } else {
        (Vec::new(), Vec::new())
    };
    let all_tris: Vec<[u32; 3]> = asset.mesh.tris.iter().chain(&plane_tris).copied().collect();
    let posed = |t: usize| -> Vec<Vec3> {
        let v =
            skin::pose_vertices(&asset, &anim::pose(&asset.nodes, &asset.parent, anim, times[t]));
        v.into_iter()
            .map(|p| to_world.transform_point3(p))
            .chain(plane_verts.iter().copied())
            .collect()
    };
    let tris = &all_tris;
    let model_tris = &all_tris[..num_model_tris];

    // Surface samples on frame 0.
    let pos0 = posed(0);
    let mut gauss_pts = surface::sample_surface(
        &pos0,
        model_tris,
        p.gaussians as usize,
        &mut Rng::from_state(p.seed).after(1),
    );
    let num_dynamic = gauss_pts.len();
    let plane_pts = surface::sample_surface(
        &pos0,
        &all_tris[num_model_tris..],
        p.ground_plane as usize,
        &mut Rng::from_state(mix(p.seed ^ 0x9d0u64)).after(1),
    );
    gauss_pts.extend(
        plane_pts
            .into_iter()
            .map(|s| surface::SurfacePoint { tri: s.tri + num_model_tris as u32, ..s }),
    );
    let track_pts = surface::sample_surface(
        &pos0,
        model_tris,
        p.tracks as usize,
        &mut Rng::from_state(mix(!p.seed)).after(1),
    );
    if gauss_pts.is_empty() {
        return Err(Error::Degenerate {
            path: p.gltf.clone(),
            msg: "the surface has zero area at frame 0".into(),
        });
    }
    let spacing = (surface::total_area(&pos0, model_tris) / p.gaussians as f64).sqrt() as f32;
    let plane_spacing = (surface::total_area(&pos0, &all_tris[num_model_tris..])
        / p.ground_plane.max(1) as f64)
        .sqrt() as f32;
    let to_plane = placement.matrix().as_mat4().inverse();
    let shade_fn = |tri: u32, b: [f32; 3]| -> Vec3 {
        if (tri as usize) < num_model_tris {
            shader.color(tri, b)
        } else {
            let q = surface::position(&pos0, tris, &surface::SurfacePoint { tri, b });
            plane_color(to_plane.transform_point3(q))
        }
    };
    let n = gauss_pts.len();
    let gaussians = Gaussians {
        id: (0..n as u32).collect(),
        dynamic: (0..n).map(|i| i < num_dynamic).collect(),
        scale: (0..n)
            .map(|i| {
                let s = if i < num_dynamic { spacing } else { plane_spacing };
                [0.5 * s, 0.5 * s, 0.05 * s]
            })
            .collect(),
        opacity: vec![0.95; n],
        color: gauss_pts
            .iter()
            .map(|s| shade_fn(s.tri, s.b).to_array().map(shade::linear_to_srgb))
            .collect(),
        sh_degree: 0,
        sh_rest: Vec::new(),
    };

    // Pass 2: oracle model and tracks_3d.
    let prov = Provenance::new("synth", p);
    std::fs::create_dir_all(&p.out).map_err(IoError::at(&p.out)).map_err(formats::Error::from)?;
    let mut t3 = Tracks3dWriter::create(&p.out.join("tracks_3d.parquet"), track_pts.len(), &prov)?;
    let bar = ctx.progress(num_train as u64, "oracle");
    let frames = (0..num_train).map(|t| -> tables::Result<FrameState> {
        let pos = posed(t);
        let tp: Vec<[f32; 3]> =
            track_pts.iter().map(|s| surface::position(&pos, tris, s).to_array()).collect();
        t3.write(&tp)?;
        bar.inc(1);
        Ok(FrameState {
            frame: t as u32,
            position: gauss_pts
                .iter()
                .map(|s| surface::position(&pos, tris, s).to_array())
                .collect(),
            rotation: gauss_pts
                .iter()
                .map(|s| surface::frame(&pos, tris, s).to_array())
                .map(|[x, y, z, w]| [w, x, y, z])
                .collect(),
        })
    });
    Model::save(&p.out.join("oracle"), &gaussians, frames, &prov)?;
    t3.finish()?;
    bar.finish_and_clear();

    // Pass 3: render. Training frames first (tracks_2d, covisibility buffers), then eval views.
    let mut by_frame: BTreeMap<(bool, u32), Vec<usize>> = BTreeMap::new();
    for (i, c) in cams.iter().enumerate() {
        by_frame.entry((c.split == Split::Eval, c.frame)).or_default().push(i);
    }
    let mut covis = (p.layout == Layout::Dycheck).then(|| covis::Covis::new(num_train));
    if covis.is_some() {
        for c in cams.iter_mut().filter(|c| c.split == Split::Eval) {
            c.mask_path = Some(format!("covisible/{}/{:05}.png", c.camera, c.frame));
        }
    }
    let mut t2 = Tracks2dWriter::create(&p.out.join("tracks_2d.parquet"), track_pts.len(), &prov)?;
    let realistic = p.priors == PriorKind::Realistic;
    let levels = p.levels();
    let mut exact_tracks: Vec<Tracks2dFrame> = Vec::new();
    let (mut depth_err, mut depth_px) = (0.0f64, 0usize);
    let ss = p.supersample as usize;
    let bar = ctx.progress(cams.len() as u64, "render");
    let mut next_train = 0u32;
    for (&(eval, frame), idx) in &by_frame {
        let pos = posed(frame as usize);
        type TrainOut = (raster::View, raster::Samples, Tracks2dFrame, (f64, usize));
        let out: Vec<Option<TrainOut>> = idx
            .par_iter()
            .map(|&i| -> Result<_, Error> {
                let cam = &cams[i];
                let view = raster::View::of(cam);
                let samples = raster::rasterize(&view, ss, &pos, tris);
                let r = raster::resolve(&samples, &shade_fn, num_model_tris as u32);
                write_png(&p.out.join(&cam.image_path), &r.rgba)?;
                write_npy_f32(&p.out.join(depth_rel(cam)), &[view.height, view.width], &r.depth)?;
                write_png(
                    &p.out.join(format!("mask/{}/{:05}.png", cam.camera, cam.frame)),
                    &r.mask,
                )?;
                if let Some(c) = &covis
                    && eval
                {
                    write_png(
                        &p.out.join(cam.mask_path.as_deref().unwrap_or_default()),
                        &c.mask(&samples, tris),
                    )?;
                }
                bar.inc(1);
                if eval {
                    return Ok(None);
                }
                let mut err = (0.0, 0);
                if realistic {
                    let prior = priors::depth_prior(
                        &r.depth,
                        view.width,
                        view.height,
                        cam.frame,
                        p.seed,
                        &levels,
                    );
                    for (a, b) in prior.iter().zip(&r.depth) {
                        if *b > 0.0 {
                            err.0 += ((a - b) / b).abs() as f64;
                            err.1 += 1;
                        }
                    }
                    write_npy_f32(
                        &p.out.join(PRIORS_DIR).join(depth_rel(cam)),
                        &[view.height, view.width],
                        &prior,
                    )?;
                }
                let mut f = Tracks2dFrame::default();
                for s in &track_pts {
                    let (q, vis) = raster::visibility(
                        &view,
                        &samples,
                        surface::position(&pos, tris, s),
                        s.tri,
                    )
                    .map(|(q, v)| ([q.x, q.y], v))
                    .unwrap_or(([-1.0, -1.0], false));
                    f.xy.push(q);
                    f.visible.push(vis);
                }
                Ok(Some((view, samples, f, err)))
            })
            .collect::<Result<_, Error>>()?;
        for (view, samples, f, err) in out.into_iter().flatten() {
            if frame != next_train {
                return Err(Error::Param {
                    flag: "trajectory",
                    msg: format!(
                        "training frame {frame} is not the next frame ({next_train}): one training camera per frame"
                    ),
                });
            }
            t2.write(&f)?;
            depth_err += err.0;
            depth_px += err.1;
            if realistic {
                exact_tracks.push(f);
            }
            next_train += 1;
            if let Some(c) = &mut covis
                && c.wants(frame)
            {
                c.keep(view, pos.clone(), &samples);
            }
        }
    }
    t2.finish()?;
    bar.finish_and_clear();
    let (w0, h0) =
        cams.iter().find(|c| c.split == Split::Train).map_or((1, 1), |c| c.pinhole.size());
    let measured = realistic
        .then(|| -> Result<priors::Measured, Error> {
            let (prior, drifting) = priors::track_priors(&exact_tracks, w0, h0, p.seed, &levels);
            let mut w = Tracks2dWriter::create(
                &p.out.join(PRIORS_DIR).join("tracks_2d.parquet"),
                track_pts.len(),
                &prov,
            )?;
            for f in &prior {
                w.write(f)?;
            }
            w.finish()?;
            let (delta, oa) = priors::track_errors(&exact_tracks, &prior, w0, h0);
            Ok(priors::Measured {
                depth_abs_rel: depth_err / depth_px.max(1) as f64,
                track_delta_avg: delta,
                occlusion_accuracy: oa,
                drifting_tracks: drifting,
            })
        })
        .transpose()?;
    write_manifest(p, measured)?;

    let scene = Scene { dir: p.out.clone(), cameras: cams };
    scene.save(&prov)?;
    let info = serde_json::json!({
        "source": p.gltf.file_name().map(|f| f.to_string_lossy().to_string()),
        "animation": anim.map(|a| a.name.clone()),
        "animation_start_s": anim.map(|a| a.start),
        "animation_end_s": anim.map(|a| a.end),
        "fps": p.fps,
        "frames": num_train,
        "object_centre_gltf": centre.to_array(),
        "bbox_diagonal_gltf": diag,
        "normalise_scale": norm_scale,
        "bbox_diagonal": 2.0,
        "placement": placement,
        "orbit_distance": if on_path { None } else { Some(cameras::ORBIT_DISTANCE) },
        "procedural_texture": shader.any_procedural(),
        "oracle_spacing": spacing,
        "ground_plane_gaussians": p.ground_plane,
        "trajectory": p.trajectory,
    });
    let text = serde_json::to_string_pretty(&info).unwrap_or_default();
    crate::util::fs::write_atomic(&p.out.join("scene.json"), text.as_bytes())
        .map_err(crate::formats::Error::from)?;
    if p.layout == Layout::Dycheck {
        dycheck::write_layout(&scene, &p.out.join("dycheck"), ctx)?;
    }
    Ok(Summary { frames: num_train, images: scene.cameras.len(), triangles: tris.len() })
}

/// Half the side of the ground plane, in normalised model units (the model's box diagonal
/// is 2).
const PLANE_HALF_SIDE: f32 = 1.5;

/// Quads per side of the ground plane's triangle grid.
const PLANE_GRID: u32 = 8;

/// The ground plane at height `floor` (normalised model space, +Y up) mapped by `placement`
/// into the world: its vertices and its triangles, numbered from `first_vertex`.
fn ground_plane(floor: f32, placement: Mat4, first_vertex: u32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let g = PLANE_GRID;
    let mut verts = Vec::new();
    for j in 0..=g {
        for i in 0..=g {
            let (x, z) = [i, j].map(|k| (2.0 * k as f32 / g as f32 - 1.0) * PLANE_HALF_SIDE).into();
            verts.push(placement.transform_point3(Vec3::new(x, floor, z)));
        }
    }
    let mut tris = Vec::new();
    for j in 0..g {
        for i in 0..g {
            let a = first_vertex + j * (g + 1) + i;
            let (b, c, d) = (a + 1, a + g + 1, a + g + 2);
            // counter-clockwise seen from above (+Y)
            tris.push([a, c, b]);
            tris.push([b, c, d]);
        }
    }
    (verts, tris)
}

/// Linear colour of the ground plane at `local` (normalised model space): a grey
/// checkerboard of squares 0.25 units wide, with a smooth tint so that no two squares look
/// alike.
fn plane_color(local: Vec3) -> Vec3 {
    let (u, v) = (local.x / 0.25, local.z / 0.25);
    let check = if (u.floor() as i64 + v.floor() as i64).rem_euclid(2) == 0 { 0.6 } else { 0.25 };
    let tint = 0.5 + 0.5 * (0.7 * local.x).sin() * (0.9 * local.z).cos();
    Vec3::new(check * (0.8 + 0.2 * tint), check * 0.85, check * (1.0 - 0.2 * tint))
}

/// Directory of the realistic priors inside the scene.
const PRIORS_DIR: &str = "priors";

/// `priors.json`: which files a monocular pipeline sees and which are ground truth.
fn write_manifest(p: &SynthParams, measured: Option<priors::Measured>) -> Result<(), Error> {
    let realistic = p.priors == PriorKind::Realistic;
    let (depth_prefix, tracks) = if realistic {
        (format!("{PRIORS_DIR}/"), format!("{PRIORS_DIR}/tracks_2d.parquet"))
    } else {
        (String::new(), "tracks_2d.parquet".to_string())
    };
    let json = serde_json::json!({
        "priors": p.priors,
        "monocular_inputs": {
            "cameras": "cameras.parquet, rows of split 'train'",
            "rgb": "image_path of the training cameras",
            "mask": "mask_path of the training cameras (foreground segmentation, exact)",
            "depth_prefix": depth_prefix,
            "depth": format!("{depth_prefix}<depth_path of the training cameras>"),
            "tracks_2d": tracks,
        },
        "ground_truth": [
            "depth_path of every camera (exact z-depth)",
            "tracks_2d.parquet (exact projections and visibility)",
            "tracks_3d.parquet",
            "oracle/ (the oracle 4D Gaussian model)",
            "image_path and mask_path of the eval cameras",
            "dycheck/ (the DyCheck layout, when written)",
        ],
        "levels": realistic.then(|| p.levels()),
        "measured": measured,
    });
    let text = serde_json::to_string_pretty(&json).unwrap_or_default();
    crate::util::fs::write_atomic(&Scene::priors_path(&p.out), text.as_bytes())
        .map_err(crate::formats::Error::from)?;
    Ok(())
}

fn depth_rel(c: &Camera) -> String {
    c.depth_path.clone().unwrap_or_else(|| format!("depth/{}/{:05}.npy", c.camera, c.frame))
}
