//! One optimisation step's image part: for each batch frame, render the training view with
//! the [`DifferentiableRenderer`] of `--device`, take L_rgb against that frame's ground truth (paper
//! App. A.3: colour, mask, depth, and the 2D tracks to the next batch frame when the scene
//! has them), run the backward pass and chain the Gaussians' gradients to the trained
//! parameters (per-frame pose, log-scale, opacity logit, colour/SH). The batch's loss is the
//! mean over its frames or their sum (`--image-batch`: the release adds its 8 views').
//! Frames are rendered one after the other (the renderer is parallel inside), their image
//! losses in parallel, and their gradients summed in batch order, so the result does not
//! depend on the thread count.
//!
//! It also accumulates, per Gaussian, the norm of the screen-space position gradient in NDC
//! units (pixels · W/2, H/2, per view, as 3DGS and gsplat do) that density control uses.

use super::graph_loss::Reduction;
use super::image_loss::track::{
    Track, add_target_position_grads, interval_weight, tracks_between, write_target_features,
};
use super::image_loss::{FrameTargets, ImageLossWeights, TrackForm, TrackSet, rgb_loss};
use super::state::{StateGrads, TrainState, sigmoid};
use super::timing::PhaseTimes;
use crate::model::Model;
use crate::render::{
    ColorSource, Cutoff, DifferentiableRenderer, RenderCamera, RenderSettings, ShFrame, SplatInputs,
};
use crate::scene::{Camera, GtAlpha, Scene};
use crate::tables::tracks_2d::{Tracks2dFrame, Tracks2dReader};
use rayon::prelude::*;
use std::borrow::Cow;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Bytes of decoded ground truth kept in memory; frames beyond it are read again each time.
const TRUTH_CACHE_BYTES: usize = 1 << 30;

/// The training view of each frame and where its ground truth lives. Decoded ground truth
/// and 2D tracks are kept after their first read (images up to [`TRUTH_CACHE_BYTES`]), since
/// every epoch reads every frame again.
pub struct TrainingViews {
    /// `[T]` the scene's training cameras, index t is frame t.
    cameras: Vec<Camera>,
    /// `[T]` the cameras that render them (the model's own when it has them).
    render_cameras: Vec<Camera>,
    /// The frame the model's SH colours are evaluated in (MoSca: local).
    sh_frame: ShFrame,
    /// The scene directory the cameras' paths are relative to.
    scene: Scene,
    /// How the scene's images' alpha is read.
    gt_alpha: GtAlpha,
    /// The scene's 2D tracks in the training camera, if it has them.
    tracks: Option<Tracks2dReader>,
    /// `[T]` decoded ground truth, with the background it was composited over.
    truths: Vec<OnceLock<([f32; 3], FrameTruth)>>,
    /// Bytes held in `truths`.
    truth_bytes: AtomicUsize,
    /// `[T]` decoded 2D tracks of each frame.
    track_frames: Vec<OnceLock<Tracks2dFrame>>,
}

/// One training frame's ground truth, `[H, W]` images.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameTruth {
    /// `[H, W, 3]` colour over the render background.
    pub rgb: Vec<f32>,
    /// `[H, W]` foreground mask in [0, 1], when the camera has one.
    pub mask: Option<Vec<f32>>,
    /// `[H, W]` prior z-depth (0 = invalid), when the camera has one.
    pub depth: Option<Vec<f32>>,
}

impl FrameTruth {
    /// Bytes of its images.
    fn bytes(&self) -> usize {
        let len = |v: &Option<Vec<f32>>| v.as_ref().map_or(0, Vec::len);
        4 * (self.rgb.len() + len(&self.mask) + len(&self.depth))
    }
}

impl TrainingViews {
    /// The training views of `scene` rendered with `model`'s cameras
    /// ([`Model::training_camera`]; T must equal the model's frame count) and its
    /// `tracks_2d.parquet` when present.
    pub fn new(scene: &Scene, model: &Model) -> anyhow::Result<Self> {
        let tracks_path = scene.dir.join("tracks_2d.parquet");
        let tracks =
            if tracks_path.exists() { Some(Tracks2dReader::open(&tracks_path)?) } else { None };
        let cameras: Vec<Camera> = scene.train_by_frame().into_iter().cloned().collect();
        if let Some(t) = &tracks
            && t.num_frames() != cameras.len()
        {
            anyhow::bail!(
                "{}: {} frames, the scene has {} training frames",
                tracks_path.display(),
                t.num_frames(),
                cameras.len()
            );
        }
        let render_cameras = cameras.iter().map(|c| model.training_camera(c)).collect();
        let frames = cameras.len();
        Ok(TrainingViews {
            cameras,
            render_cameras,
            sh_frame: model.sh_frame,
            scene: scene.clone(),
            gt_alpha: scene.gt_alpha()?,
            tracks,
            truths: (0..frames).map(|_| OnceLock::new()).collect(),
            truth_bytes: AtomicUsize::new(0),
            track_frames: (0..frames).map(|_| OnceLock::new()).collect(),
        })
    }

    /// Number of frames T.
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// The camera that renders training frame `t`: the model's own camera of that frame
    /// when it carries cameras, else the scene's training camera.
    pub fn training_camera(&self, t: usize) -> RenderCamera {
        RenderCamera::from(&self.render_cameras[t])
    }

    /// Ground truth of frame `t` (colour over `background`, mask, depth); errors name the file.
    /// Kept after the first read while the cache has room.
    pub fn truth(&self, t: usize, background: [f32; 3]) -> anyhow::Result<Cow<'_, FrameTruth>> {
        if let Some((bg, truth)) = self.truths[t].get()
            && *bg == background
        {
            return Ok(Cow::Borrowed(truth));
        }
        let truth = self.read_truth(t, background)?;
        let bytes = 4
            * (truth.rgb.len()
                + truth.mask.as_ref().map_or(0, Vec::len)
                + truth.depth.as_ref().map_or(0, Vec::len));
        let held = self.truth_bytes.load(Ordering::Relaxed);
        if self.truths[t].get().is_none() && held + bytes <= TRUTH_CACHE_BYTES {
            self.truth_bytes.store(held + bytes, Ordering::Relaxed);
            let _ = self.truths[t].set((background, truth));
            return Ok(Cow::Borrowed(&self.truths[t].get().expect("just set").1));
        }
        Ok(Cow::Owned(truth))
    }

    /// Read the ground truth of the first frames that fit the cache (over `background`, in
    /// parallel) and every frame's 2D tracks, so that steps find them decoded; errors name
    /// the file of the first failing frame.
    pub fn preload(&self, background: [f32; 3]) -> anyhow::Result<()> {
        let mut budget = TRUTH_CACHE_BYTES.saturating_sub(self.truth_bytes.load(Ordering::Relaxed));
        let mut frames = Vec::new();
        for (t, cam) in self.cameras.iter().enumerate() {
            let planes = 3 + cam.mask_path.is_some() as usize + cam.depth_path.is_some() as usize;
            let bytes = 4 * planes * cam.pinhole.width as usize * cam.pinhole.height as usize;
            if self.truths[t].get().is_some() || bytes > budget {
                continue;
            }
            budget -= bytes;
            frames.push(t);
        }
        let read: Vec<anyhow::Result<FrameTruth>> =
            frames.par_iter().map(|&t| self.read_truth(t, background)).collect();
        for (&t, truth) in frames.iter().zip(read) {
            let truth = truth?;
            self.truth_bytes.fetch_add(truth.bytes(), Ordering::Relaxed);
            let _ = self.truths[t].set((background, truth));
        }
        // one reader, one frame at a time (it reads a single open file)
        if let Some(r) = &self.tracks {
            for t in 0..self.len() {
                self.track_frame(r, t)?;
            }
        }
        Ok(())
    }

    /// [`Self::truth`] read from the files.
    fn read_truth(&self, t: usize, background: [f32; 3]) -> anyhow::Result<FrameTruth> {
        let cam = &self.cameras[t];
        let (w, h) = cam.pinhole.size();
        let rgb = load_rgb(&self.scene, cam, self.gt_alpha, background)?;
        let mask = match &cam.mask_path {
            Some(m) => {
                let path = self.scene.resolve(m);
                let img = crate::formats::png::read_png(&path)?;
                if img.width != w || img.height != h {
                    anyhow::bail!(
                        "{}: mask is {}x{}, the camera says {w}x{h}",
                        path.display(),
                        img.width,
                        img.height
                    );
                }
                Some((0..w * h).map(|i| img.data[i * img.channels]).collect())
            }
            None => None,
        };
        let depth = match &cam.depth_path {
            Some(d) => {
                let path = self.scene.resolve(d);
                let (shape, v) = crate::formats::npy::read_npy_f32(&path)?;
                if v.len() != w * h {
                    anyhow::bail!(
                        "{}: depth has shape {shape:?}, the camera says {h}x{w}",
                        path.display()
                    );
                }
                Some(v)
            }
            None => None,
        };
        Ok(FrameTruth { rgb, mask, depth })
    }

    /// The 2D tracks from frame `s` to frame `t` (both visible), weighted as `form` does.
    fn tracks(&self, s: usize, t: usize, form: TrackForm) -> anyhow::Result<Vec<Track>> {
        let Some(r) = &self.tracks else { return Ok(Vec::new()) };
        let w = match form {
            TrackForm::Som { .. } => interval_weight(s, t, self.len()),
            TrackForm::Mosca { .. } => 1.0,
        };
        Ok(tracks_between(self.track_frame(r, s)?, self.track_frame(r, t)?, w))
    }

    /// The 2D tracks of frame `t`, decoded once.
    fn track_frame(&self, r: &Tracks2dReader, t: usize) -> anyhow::Result<&Tracks2dFrame> {
        if let Some(f) = self.track_frames[t].get() {
            return Ok(f);
        }
        let _ = self.track_frames[t].set(r.frame(t)?);
        Ok(self.track_frames[t].get().expect("just set"))
    }
}

fn load_rgb(
    scene: &Scene,
    cam: &Camera,
    alpha: GtAlpha,
    background: [f32; 3],
) -> anyhow::Result<Vec<f32>> {
    let path = &scene.resolve(&cam.image_path);
    let img = alpha.rgb(&crate::formats::png::read_png(path)?, background);
    if img.width != cam.pinhole.width as usize || img.height != cam.pinhole.height as usize {
        anyhow::bail!(
            "{}: image is {}x{}, the camera of frame {} says {}x{}",
            path.display(),
            img.width,
            img.height,
            cam.frame,
            cam.pinhole.width,
            cam.pinhole.height
        );
    }
    Ok(img.data)
}

/// Result of the image part of one step.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageStep {
    /// Named, weighted loss terms ([`super::image_loss::TERMS`]), means over the batch frames.
    pub terms: Vec<(&'static str, f64)>,
    /// `[N]` Σ over batch views of |∂L_view/∂mean2d| in NDC units (visible Gaussians only).
    pub screen_grad: Vec<f32>,
    /// `[N]` number of batch views in which the Gaussian was visible.
    pub screen_count: Vec<u32>,
}

/// L_rgb and its gradients over the batch frames `batch` (frame indices, in order), rendered
/// by `renderer` (the CPU, or the GPU that `--device` names); `grads` is reset to the
/// gradients of the batch's L_rgb (the mean or sum of its frames', `weights.batch`), its
/// pose row j holding frame `batch[j]`'s. Each phase's wall time is added to `timer`.
pub fn image_step<R: DifferentiableRenderer>(
    renderer: &R,
    state: &TrainState,
    views: &TrainingViews,
    batch: &[usize],
    weights: &ImageLossWeights,
    settings: &RenderSettings,
    grads: &mut StateGrads,
    timer: &mut PhaseTimes,
) -> anyhow::Result<ImageStep> {
    let n = state.n();
    let scales = state.scales();
    let opacities = state.opacities();
    let colors = if state.sh_degree == 0 {
        ColorSource::Rgb(&state.color)
    } else {
        ColorSource::Sh {
            degree: state.sh_degree,
            dc: &state.color,
            rest: &state.sh_rest,
            frame: views.sh_frame,
        }
    };
    grads.reset(state, batch.len());
    let mut screen_grad = vec![0.0f32; n];
    let mut screen_count = vec![0u32; n];
    let mut terms: Vec<(&'static str, f64)> = Vec::new();
    // The batch's terms are the mean of its frames' or their sum (`weights.batch`).
    let (inv_b, per_frame) = match weights.batch {
        Reduction::Mean => (1.0 / batch.len().max(1) as f32, batch.len() as f64),
        Reduction::Sum => (1.0, 1.0),
    };
    // Frames go in groups: forward renders one frame after another (the renderer is parallel
    // inside), then the group's image losses in parallel, then backward and chaining in
    // batch order. One frame's loss is too small to fill many cores (on a 16-core GPU host it
    // was half the step); on few cores one frame at a time keeps its images in cache.
    let group = (rayon::current_num_threads() / 2).clamp(1, batch.len().max(1));
    for first in (0..batch.len()).step_by(group) {
        let (mut frames, mut saved_states) = (Vec::with_capacity(group), Vec::new());
        for j in first..(first + group).min(batch.len()) {
            let t = batch[j];
            // The track term's target: the next frame of the batch (its positions rendered as
            // features from this frame, Shape of Motion's scheme).
            let target_row = (j + 1) % batch.len();
            let target = batch[target_row];
            let target_cam = views.training_camera(target);
            let tracks = timer.time("load ground truth", || {
                if weights.track > 0.0 && target != t {
                    views.tracks(t, target, weights.track_form)
                } else {
                    Ok(Vec::new())
                }
            })?;
            let nf = if tracks.is_empty() { 0 } else { 3 };
            let mut features = vec![0.0f32; n * nf];
            if nf > 0 {
                write_target_features(&mut features, nf, 0, state.positions(target), &target_cam);
            }
            let cam = views.training_camera(t);
            let inputs = frame_inputs(state, t, &scales, &opacities, colors, &features, nf);
            let (out, saved) = timer
                .time("render forward", || {
                    renderer.render_with_saved(&cam, &inputs, settings, Cutoff::Hard)
                })
                .map_err(|e| anyhow::anyhow!("frame {t}: render: {e}"))?;
            let truth = timer.time("load ground truth", || views.truth(t, settings.background))?;
            frames.push(BatchFrame {
                row: j,
                t,
                cam,
                target_row,
                target_cam,
                tracks,
                features,
                out,
                truth,
            });
            saved_states.push(saved);
        }
        let losses: Vec<_> = timer.time("image loss", || {
            frames
                .par_iter()
                .map(|f| {
                    let sets = [TrackSet { block: 0, camera: &f.target_cam, tracks: &f.tracks }];
                    let targets = FrameTargets {
                        rgb: &f.truth.rgb,
                        valid: None,
                        mask: f.truth.mask.as_deref(),
                        depth: f.truth.depth.as_deref(),
                        tracks: if f.features.is_empty() { &[] } else { &sets },
                    };
                    rgb_loss(&f.out, &targets, weights)
                })
                .collect()
        });
        for ((f, saved), loss) in frames.iter().zip(saved_states).zip(losses) {
            let (j, t) = (f.row, f.t);
            let (frame_terms, v) = loss.map_err(|e| anyhow::anyhow!("frame {t}: {e}"))?;
            for (name, value) in frame_terms {
                match terms.iter_mut().find(|(k, _)| *k == name) {
                    Some((_, s)) => *s += value / per_frame,
                    None => terms.push((name, value / per_frame)),
                }
            }
            let nf = f.features.len() / n.max(1);
            let (cam, inputs) =
                (&f.cam, frame_inputs(state, t, &scales, &opacities, colors, &f.features, nf));
            let g = timer
                .time("render backward", || renderer.backward(cam, &inputs, settings, &saved, &v))
                .map_err(|e| anyhow::anyhow!("frame {t}: backward: {e}"))?;
            let chain = timer.start();
            let (half_w, half_h) = (0.5 * cam.width as f32, 0.5 * cam.height as f32);
            let k3 = state.sh_rest.len() / n.max(1);
            for i in 0..n {
                let p = &mut grads.poses.position[j * n + i];
                for k in 0..3 {
                    p[k] += inv_b * g.means[i][k];
                }
                let q = &mut grads.poses.rotation[j * n + i];
                for k in 0..4 {
                    q[k] += inv_b * g.quats[i][k];
                }
                for k in 0..3 {
                    grads.log_scale[i][k] += inv_b * g.scales[i][k] * scales[i][k];
                    grads.color[i][k] += inv_b * g.colors[i][k];
                }
                let o = sigmoid(state.logit_opacity[i]);
                grads.logit_opacity[i] += inv_b * g.opacities[i] * o * (1.0 - o);
                if f.out.aux.visible[i] {
                    let [gx, gy] = g.means2d[i];
                    screen_grad[i] += ((gx * half_w).powi(2) + (gy * half_h).powi(2)).sqrt();
                    screen_count[i] += 1;
                }
            }
            for (d, s) in grads.sh_rest.iter_mut().zip(&g.sh_rest) {
                *d += inv_b * s;
            }
            if nf > 0 {
                let scaled: Vec<f32> = g.features.iter().map(|v| inv_b * v).collect();
                let at = &mut grads.poses.position[f.target_row * n..(f.target_row + 1) * n];
                add_target_position_grads(at, &scaled, nf, 0, &f.target_cam);
            }
            debug_assert_eq!(grads.sh_rest.len(), n * k3);
            timer.stop("chain to parameters", chain);
        }
    }
    Ok(ImageStep { terms, screen_grad, screen_count })
}

/// One batch frame between its forward render and its backward pass.
struct BatchFrame<'a> {
    /// Its row in the batch, and its frame.
    row: usize,
    t: usize,
    cam: RenderCamera,
    target_row: usize,
    target_cam: RenderCamera,
    tracks: Vec<Track>,
    features: Vec<f32>,
    out: crate::render::RenderOutput,
    truth: Cow<'a, FrameTruth>,
}

/// The renderer's inputs for frame `t` of `state`.
fn frame_inputs<'a>(
    state: &'a TrainState,
    t: usize,
    scales: &'a [[f32; 3]],
    opacities: &'a [f32],
    colors: ColorSource<'a>,
    features: &'a [f32],
    num_features: usize,
) -> SplatInputs<'a> {
    SplatInputs {
        means: state.positions(t),
        quats: state.rotations(t),
        scales,
        opacities,
        colors,
        features,
        num_features,
    }
}
