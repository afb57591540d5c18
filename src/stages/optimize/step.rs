//! One optimisation step's image part: for each batch frame, render the training view with
//! the CPU [`DifferentiableRenderer`], take L_rgb against that frame's ground truth (paper
//! App. A.3), run the backward pass and chain the Gaussians' gradients to the trained
//! parameters (per-frame pose, log-scale, opacity logit, colour/SH). The batch's loss is the
//! mean over its frames. Frames are processed one after the other (the renderer is parallel
//! inside), so gradients are summed in batch order whatever the thread count.
//!
//! It also accumulates, per Gaussian, the norm of the screen-space position gradient in NDC
//! units (pixels · W/2, H/2, per view, as 3DGS and gsplat do) that density control uses.

use std::path::Path;

use super::image_loss::{RgbWeights, Truth, rgb_loss};
use super::state::{StateGrads, TrainState, sigmoid};
use crate::render::{
    ColorSource, CpuRenderer, DifferentiableRenderer, RasterPass, RenderCamera, RenderSettings,
    ShFrame, SplatInputs,
};
use crate::scene::{Camera, Scene};

/// The training view of each frame and where its ground truth lives.
pub struct TrainingViews {
    /// `[T]` the scene's training cameras, index t is frame t.
    cameras: Vec<Camera>,
    /// The scene directory the cameras' paths are relative to.
    scene: Scene,
}

impl TrainingViews {
    /// The training views of `scene` (T must equal the model's frame count).
    pub fn new(scene: &Scene) -> Self {
        TrainingViews {
            cameras: scene.train_by_frame().into_iter().cloned().collect(),
            scene: scene.clone(),
        }
    }

    /// Number of frames T.
    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// The camera that renders training frame `t`: the scene's training camera of that frame.
    /// (A model that carries its own cameras would supply them here.)
    pub fn training_camera(&self, t: usize) -> RenderCamera {
        RenderCamera::from(&self.cameras[t])
    }

    /// Ground truth of frame `t`, `[H, W, 3]` over `background`; errors name the file.
    pub fn truth(&self, t: usize, background: [f32; 3]) -> anyhow::Result<Vec<f32>> {
        let cam = &self.cameras[t];
        let path = self.scene.resolve(&cam.image_path);
        load_rgb(&path, cam, background)
    }
}

fn load_rgb(path: &Path, cam: &Camera, background: [f32; 3]) -> anyhow::Result<Vec<f32>> {
    let img = crate::image_io::read_png(path)?.rgb_over(background);
    if img.width != cam.width as usize || img.height != cam.height as usize {
        anyhow::bail!(
            "{}: image is {}x{}, the camera of frame {} says {}x{}",
            path.display(),
            img.width,
            img.height,
            cam.frame,
            cam.width,
            cam.height
        );
    }
    Ok(img.data)
}

/// Result of the image part of one step.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageStep {
    /// Named loss terms, means over the batch frames (`rgb` is their weighted sum).
    pub terms: Vec<(&'static str, f64)>,
    /// Gradients of the batch-mean L_rgb.
    pub grads: StateGrads,
    /// `[N]` Σ over batch views of |∂L_view/∂mean2d| in NDC units (visible Gaussians only).
    pub screen_grad: Vec<f32>,
    /// `[N]` number of batch views in which the Gaussian was visible.
    pub screen_count: Vec<u32>,
}

/// L_rgb and its gradients over the batch frames `batch` (frame indices, in order).
pub fn image_step(
    state: &TrainState,
    views: &TrainingViews,
    batch: &[usize],
    weights: &RgbWeights,
    settings: &RenderSettings,
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
            frame: ShFrame::World,
        }
    };
    let mut grads = StateGrads::zeros(state);
    let mut screen_grad = vec![0.0f32; n];
    let mut screen_count = vec![0u32; n];
    let mut terms: Vec<(&'static str, f64)> = Vec::new();
    let inv_b = 1.0 / batch.len().max(1) as f32;
    for &t in batch {
        let cam = views.training_camera(t);
        let inputs = SplatInputs {
            means: state.positions(t),
            quats: state.rotations(t),
            scales: &scales,
            opacities: &opacities,
            colors,
            features: &[],
            num_features: 0,
        };
        let (out, saved) = CpuRenderer
            .render_with_saved(&cam, &inputs, settings, RasterPass::Backward)
            .map_err(|e| anyhow::anyhow!("frame {t}: render: {e}"))?;
        let rgb = views.truth(t, settings.background)?;
        let (frame_terms, v) = rgb_loss(&out, &Truth { rgb: &rgb }, weights);
        for (name, value) in frame_terms {
            match terms.iter_mut().find(|(k, _)| *k == name) {
                Some((_, s)) => *s += value / batch.len() as f64,
                None => terms.push((name, value / batch.len() as f64)),
            }
        }
        let g = CpuRenderer
            .backward(&cam, &inputs, settings, &saved, &v)
            .map_err(|e| anyhow::anyhow!("frame {t}: backward: {e}"))?;
        let (half_w, half_h) = (0.5 * cam.width as f32, 0.5 * cam.height as f32);
        let k3 = state.sh_rest.len() / n.max(1);
        for i in 0..n {
            let p = &mut grads.poses.position[t * n + i];
            for k in 0..3 {
                p[k] += inv_b * g.means[i][k];
            }
            let q = &mut grads.poses.rotation[t * n + i];
            for k in 0..4 {
                q[k] += inv_b * g.quats[i][k];
            }
            for k in 0..3 {
                grads.log_scale[i][k] += inv_b * g.scales[i][k] * scales[i][k];
                grads.color[i][k] += inv_b * g.colors[i][k];
            }
            let o = sigmoid(state.logit_opacity[i]);
            grads.logit_opacity[i] += inv_b * g.opacities[i] * o * (1.0 - o);
            if out.aux.visible[i] {
                let [gx, gy] = g.means2d[i];
                screen_grad[i] += ((gx * half_w).powi(2) + (gy * half_h).powi(2)).sqrt();
                screen_count[i] += 1;
            }
        }
        for (d, s) in grads.sh_rest.iter_mut().zip(&g.sh_rest) {
            *d += inv_b * s;
        }
        debug_assert_eq!(grads.sh_rest.len(), n * k3);
    }
    Ok(ImageStep { terms, grads, screen_grad, screen_count })
}
