//! The Gaussian rasterizer: one [`Renderer`] interface, implemented on the CPU (the
//! reference, rayon over tiles) and on the GPU ([`gpu`], wgpu + WGSL), which matches it within
//! tolerances (images 1e-4 absolute, statistics 1e-4 relative, gradients 1e-3 relative; GPU
//! sums use float atomics, so GPU results are not bitwise deterministic). Stages get one
//! through `--device cpu|gpu|auto` (`stages::device`, [`gpu::AnyRenderer`]).
//!
//! Inputs are one frame's Gaussians ([`SplatInputs`], canonical order, `[N]` arrays) and a
//! pinhole [`RenderCamera`]. Outputs are images `[H, W, C]` plus per-Gaussian statistics in
//! [`RenderAux`], indexed by canonical position (0 when culled).
//!
//! The CPU rasterizer ([`cpu`]) is split into gsplat's stages, each a public function with
//! its own tests: [`cpu::project::project`] → [`cpu::isect::isect_tiles`] →
//! [`cpu::isect::tile_ranges`] → [`cpu::forward::rasterize_fwd`] →
//! [`cpu::backward::rasterize_bwd`]; [`cpu::blend`] holds the per-(Gaussian, pixel) alpha
//! math both passes share and [`constants`] its thresholds; [`cpu`] chains them. Gradients
//! come from [`DifferentiableRenderer`].
//!
//! Colour convention (3DGS): `colour = dc + Σ_k Y_k(dir)·rest_k`, clamped at 0, where `dc`
//! is the degree-0 RGB; colour images are composited over the background.

pub mod constants;
pub mod cpu;
#[cfg(test)]
mod fit_tests;
pub mod gpu;
pub mod sh;
pub mod synthetic;
#[cfg(test)]
mod test_scene;
#[cfg(test)]
mod tests;

pub use cpu::SavedForBackward;

use glam::Mat4;
use rayon::prelude::*;

/// Errors of the renderer (bad shapes or settings; poisoned values are culled, not errors).
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Input arrays disagree in length.
    #[error("input '{name}' has {got} entries, expected {expected}")]
    Shape {
        /// The input.
        name: &'static str,
        /// Its length.
        got: usize,
        /// The expected length.
        expected: usize,
    },
    /// A setting or camera value is unusable.
    #[error("{0}")]
    Settings(String),
    /// The GPU failed (device lost, out of memory, kernels rejected by the driver).
    #[error("GPU: {0}")]
    Gpu(String),
}

/// Checks of a call on a saved forward state (backward, convergence): `pixel_pass`, when
/// given, is `[H, W]` for `cam`; `same` says whether the state was saved by a render of
/// these sizes (else: "belongs to another render").
pub(crate) fn check_saved(
    cam: &RenderCamera,
    pixel_pass: Option<&[bool]>,
    same: bool,
) -> Result<(), Error> {
    let expected = cam.width as usize * cam.height as usize;
    if let Some(p) = pixel_pass.filter(|p| p.len() != expected) {
        return Err(Error::Shape { name: "pixel_pass", got: p.len(), expected });
    }
    if !same {
        return Err(Error::Settings("saved forward state belongs to another render".into()));
    }
    Ok(())
}

/// A pinhole camera for rendering (no distortion).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderCamera {
    /// Focal length x, pixels.
    pub fx: f32,
    /// Focal length y, pixels.
    pub fy: f32,
    /// Principal point x, pixels (pixel centres at +0.5).
    pub cx: f32,
    /// Principal point y, pixels.
    pub cy: f32,
    /// World-to-camera (glam, column-major), OpenCV axes.
    pub w2c: Mat4,
    /// Image width W.
    pub width: u32,
    /// Image height H.
    pub height: u32,
    /// Near plane (z in camera space); Gaussians closer are culled.
    pub near: f32,
    /// Far plane; Gaussians farther are culled.
    pub far: f32,
}

/// Which frame spherical harmonics are evaluated in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ShFrame {
    /// View direction in world coordinates (3DGS, SoM).
    #[default]
    World,
    /// View direction rotated into the Gaussian's local frame (MoSca).
    Local,
}

impl ShFrame {
    /// Its name in a model's metadata: `world` or `local`.
    pub fn name(self) -> &'static str {
        match self {
            ShFrame::World => "world",
            ShFrame::Local => "local",
        }
    }
}

/// Colour of each Gaussian.
#[derive(Debug, Clone, Copy)]
pub enum ColorSource<'a> {
    /// Plain RGB `[N]`.
    Rgb(&'a [[f32; 3]]),
    /// Spherical harmonics: `dc` `[N]` is the degree-0 colour (as in the gaussians table),
    /// `rest` `[N, K, 3]` flattened, K = (degree+1)^2 - 1.
    Sh {
        /// Degree 0..=3.
        degree: u8,
        /// Degree-0 colour `[N]`.
        dc: &'a [[f32; 3]],
        /// Higher-order coefficients `[N, K, 3]`.
        rest: &'a [f32],
        /// Frame of the view direction.
        frame: ShFrame,
    },
}

/// One frame's Gaussians, canonical order, `[N]` each.
#[derive(Debug, Clone, Copy)]
pub struct SplatInputs<'a> {
    /// World positions.
    pub means: &'a [[f32; 3]],
    /// Rotations `w, x, y, z` (normalised by the renderer; zero ones are culled).
    pub quats: &'a [[f32; 4]],
    /// Linear scales.
    pub scales: &'a [[f32; 3]],
    /// Opacities in [0, 1].
    pub opacities: &'a [f32],
    /// Colours.
    pub colors: ColorSource<'a>,
    /// Extra feature channels `[N, F]` blended like colour (F = `num_features`), or empty.
    pub features: &'a [f32],
    /// F, the number of feature channels (0 for none).
    pub num_features: usize,
}

/// Rasterization settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderSettings {
    /// Background colour composited behind the Gaussians.
    pub background: [f32; 3],
    /// Upper clamp of a Gaussian's alpha at a pixel (0.99 or 0.999).
    pub alpha_max: f32,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings { background: [1.0, 1.0, 1.0], alpha_max: 0.99 }
    }
}

/// Per-Gaussian statistics of one render, `[N]` each, canonical order, 0 when culled.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RenderAux {
    /// Whether the Gaussian survived culling and touched at least one tile.
    pub visible: Vec<bool>,
    /// Screen-space radius, pixels.
    pub radius_px: Vec<f32>,
    /// Σ over pixels of (T·α)² — 1/σ² of the paper's Eq. 3.
    pub sum_w2: Vec<f32>,
    /// Σ over pixels of T·α (the Gaussian's total blending weight).
    pub sum_w: Vec<f32>,
    /// Number of pixels where the Gaussian contributed (α ≥ 1/255 before termination).
    pub n_pixels: Vec<u32>,
}

impl RenderAux {
    /// Statistics of `n` Gaussians, all culled (zeros).
    pub fn culled(n: usize) -> RenderAux {
        RenderAux {
            visible: vec![false; n],
            radius_px: vec![0.0; n],
            sum_w2: vec![0.0; n],
            sum_w: vec![0.0; n],
            n_pixels: vec![0; n],
        }
    }
}

impl RenderOutput {
    /// The `w`×`h` output with `nf` feature channels and `aux` from each pixel's blended
    /// channels `ch(p, c)` (`c` < 4 + F: colour, depth, features) and final transmittance
    /// `t(p)`: the colour composited over `background`, alpha = 1 − T. By rows in parallel
    /// (a 1080p frame has 2M pixels); each value is written once, so the bits do not depend
    /// on the thread count.
    pub fn compose(
        (w, h, nf): (usize, usize, usize),
        aux: RenderAux,
        ch: impl Fn(usize, usize) -> f32 + Sync,
        t: impl Fn(usize) -> f32 + Sync,
        background: [f32; 3],
    ) -> RenderOutput {
        let mut out = RenderOutput {
            width: w,
            height: h,
            color: vec![0.0; w * h * 3],
            features: vec![0.0; w * h * nf],
            alpha: vec![0.0; w * h],
            depth: vec![0.0; w * h],
            aux,
        };
        out.color
            .par_chunks_mut(3 * w)
            .zip(out.depth.par_chunks_mut(w))
            .zip(out.alpha.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, ((color, depth), alpha))| {
                for x in 0..w {
                    let p = y * w + x;
                    let t = t(p);
                    for k in 0..3 {
                        color[3 * x + k] = ch(p, k) + t * background[k];
                    }
                    depth[x] = ch(p, 3);
                    alpha[x] = 1.0 - t;
                }
            });
        if nf > 0 {
            out.features.par_chunks_mut(nf).enumerate().for_each(|(p, v)| {
                for (c, v) in v.iter_mut().enumerate() {
                    *v = ch(p, 4 + c);
                }
            });
        }
        out
    }

    /// Cheap consistency check of the output sizes: `Err` names the first array whose
    /// length disagrees with W, H, F and N.
    pub fn validate_counts(&self, num_features: usize, num_gaussians: usize) -> Result<(), Error> {
        let (w, h) = (self.width, self.height);
        let a = &self.aux;
        let checks: [(&'static str, usize, usize); 9] = [
            ("color", self.color.len(), w * h * 3),
            ("features", self.features.len(), w * h * num_features),
            ("alpha", self.alpha.len(), w * h),
            ("depth", self.depth.len(), w * h),
            ("aux.visible", a.visible.len(), num_gaussians),
            ("aux.radius_px", a.radius_px.len(), num_gaussians),
            ("aux.sum_w2", a.sum_w2.len(), num_gaussians),
            ("aux.sum_w", a.sum_w.len(), num_gaussians),
            ("aux.n_pixels", a.n_pixels.len(), num_gaussians),
        ];
        for (name, got, expected) in checks {
            if got != expected {
                return Err(Error::Shape { name, got, expected });
            }
        }
        Ok(())
    }
}

/// The images of one render.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RenderOutput {
    /// Width W.
    pub width: usize,
    /// Height H.
    pub height: usize,
    /// Colour `[H, W, 3]` composited over the background.
    pub color: Vec<f32>,
    /// Features `[H, W, F]` (not composited over anything).
    pub features: Vec<f32>,
    /// Accumulated opacity `[H, W]`.
    pub alpha: Vec<f32>,
    /// Expected z-depth `[H, W]` (Σ T·α·z, not normalised by alpha).
    pub depth: Vec<f32>,
    /// Per-Gaussian statistics.
    pub aux: RenderAux,
}

/// Which per-Gaussian convergence indicator [`DifferentiableRenderer::convergence_saved`]
/// computes (paper Eq. 5's product, or the release's centre pixel).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ConvergenceTest {
    /// No pixel the Gaussian was blended into fails (vacuously true for unseen Gaussians).
    AllCoveredPixels,
    /// The pixel under the projected centre passes (false when the centre is off-screen or
    /// the Gaussian is culled).
    CentrePixel,
    /// No pixel where the Gaussian's blending weight T·α is at least the given floor
    /// (in (0, 1]) fails: the covered-pixel set restricted to the pixels the Gaussian
    /// visibly contributes to (issue 15 item 4).
    WeightedPixels(f32),
}

/// A Gaussian rasterizer.
pub trait Renderer {
    /// Render one frame.
    fn render(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
    ) -> Result<RenderOutput, Error>;
}

/// The CPU reference rasterizer (rayon over tiles), implemented in [`cpu`].
#[derive(Debug, Clone, Copy, Default)]
pub struct CpuRenderer;

/// How alphas near the 1/255 threshold ([`constants::ALPHA_THRESHOLD`]) are treated: the
/// one setting in which a render for training differs from one for finite-difference tests.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Cutoff {
    /// 3DGS: skip `α < 1/255`, keep `α` unchanged above (a step at the threshold).
    #[default]
    Hard,
    /// `α · s((α − τ)/τ)` with `s` the smoothstep, τ = 1/255: zero below τ, `α` above 2τ,
    /// continuously differentiable in between. Used by finite-difference tests only.
    Smooth,
}

/// Cotangents of a render's images (dL/d output). An empty vector means all zeros.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImageGrads {
    /// dL/d colour `[H, W, 3]` (of the composited colour).
    pub color: Vec<f32>,
    /// dL/d alpha `[H, W]`.
    pub alpha: Vec<f32>,
    /// dL/d expected depth `[H, W]`.
    pub depth: Vec<f32>,
    /// dL/d features `[H, W, F]`.
    pub features: Vec<f32>,
}

impl ImageGrads {
    /// Check that each non-empty cotangent has the size of a `w`×`h` image with `nf`
    /// features (an empty one means zero).
    pub fn check_shapes(&self, w: usize, h: usize, nf: usize) -> Result<(), Error> {
        for (name, got, expected) in [
            ("v_color", &self.color, w * h * 3),
            ("v_alpha", &self.alpha, w * h),
            ("v_depth", &self.depth, w * h),
            ("v_features", &self.features, w * h * nf),
        ] {
            if !got.is_empty() && got.len() != expected {
                return Err(Error::Shape { name, got: got.len(), expected });
            }
        }
        Ok(())
    }

    /// The cotangents of pixel `p`'s blended channels into `v_ch` (`[4 + F]`: colour,
    /// depth, features); returns dL/d alpha with the background term
    /// colour += (1 − alpha)·bg moved into it.
    pub fn pixel(&self, p: usize, background: [f32; 3], v_ch: &mut [f32]) -> f32 {
        let nf = v_ch.len() - 4;
        let mut va = self.alpha.get(p).copied().unwrap_or(0.0);
        for k in 0..3 {
            let vc = self.color.get(p * 3 + k).copied().unwrap_or(0.0);
            v_ch[k] = vc;
            va -= background[k] * vc;
        }
        v_ch[3] = self.depth.get(p).copied().unwrap_or(0.0);
        for f in 0..nf {
            v_ch[4 + f] = self.features.get(p * nf + f).copied().unwrap_or(0.0);
        }
        va
    }
}

/// Gradients w.r.t. one frame's Gaussians, canonical order, 0 for culled Gaussians.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SplatGrads {
    /// dL/d positions `[N]`.
    pub means: Vec<[f32; 3]>,
    /// dL/d rotations `[N]` (w, x, y, z), w.r.t. the unnormalised input quaternion.
    pub quats: Vec<[f32; 4]>,
    /// dL/d scales `[N]`.
    pub scales: Vec<[f32; 3]>,
    /// dL/d opacities `[N]`.
    pub opacities: Vec<f32>,
    /// dL/d colour `[N]`: the RGB of [`ColorSource::Rgb`] or the `dc` of [`ColorSource::Sh`].
    pub colors: Vec<[f32; 3]>,
    /// dL/d SH `rest` `[N, K, 3]` flattened (empty for RGB).
    pub sh_rest: Vec<f32>,
    /// dL/d features `[N, F]`.
    pub features: Vec<f32>,
    /// dL/d projected 2D means `[N]`, pixels (the screen-space position gradient that
    /// density control accumulates; part of `means`' chain, not an extra input).
    pub means2d: Vec<[f32; 2]>,
}

/// A renderer with gradients (the optimiser's interface). `Saved` is the forward state the
/// backward pass needs (CPU: [`SavedForBackward`]; GPU: device buffers).
pub trait DifferentiableRenderer: Renderer {
    /// Forward state kept for [`DifferentiableRenderer::backward`].
    type Saved;

    /// Render one frame and keep what the backward pass needs.
    fn render_with_saved(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        cutoff: Cutoff,
    ) -> Result<(RenderOutput, Self::Saved), Error>;

    /// Gradients of the loss w.r.t. the inputs of the render that produced `saved`, given the
    /// image cotangents. Exact for that render; deterministic whatever the thread count.
    fn backward(
        &self,
        camera: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        saved: &Self::Saved,
        grads: &ImageGrads,
    ) -> Result<SplatGrads, Error>;

    /// `[N]` convergence indicator of the render that produced `saved` against a per-pixel
    /// pass map `[H, W]` (computed from that render, e.g. |rendered − truth|₁ < η_c), without
    /// rendering again: the uncertainty stage renders each frame once.
    fn convergence_saved(
        &self,
        camera: &RenderCamera,
        settings: &RenderSettings,
        saved: &Self::Saved,
        pixel_pass: &[bool],
        test: ConvergenceTest,
    ) -> Result<Vec<bool>, Error>;
}

/// `impl Renderer` for a [`DifferentiableRenderer`] whose plain render is its hard-cutoff
/// [`DifferentiableRenderer::render_with_saved`], the saved state dropped (the CPU, GPU and
/// either renderer: one forward pass, written once).
macro_rules! render_is_forward {
    ($t:ty) => {
        impl $crate::render::Renderer for $t {
            fn render(
                &self,
                cam: &$crate::render::RenderCamera,
                inputs: &$crate::render::SplatInputs,
                settings: &$crate::render::RenderSettings,
            ) -> Result<$crate::render::RenderOutput, $crate::render::Error> {
                let hard = $crate::render::Cutoff::Hard;
                Ok($crate::render::DifferentiableRenderer::render_with_saved(
                    self, cam, inputs, settings, hard,
                )?
                .0)
            }
        }
    };
}
pub(crate) use render_is_forward;
