//! L_rgb, the image-space loss of one training frame (paper Appendix A.3: "a standard
//! combination of RGB ℓ1 and SSIM ... mask loss, depth loss ... and tracking loss, inherited
//! from the base models"), as pure functions of the rendered images that return the loss
//! terms and their cotangent [`ImageGrads`] for the renderer's backward pass.
//!
//! Terms, each used when the frame has that prior and its weight is > 0:
//! - colour ([`photometric`]): L1 and SSIM (own backward in [`crate::metrics::ssim_grad`]),
//!   combined as Shape of Motion or MoSca do;
//! - mask ([`mask`]): mean (α − mask)²;
//! - depth ([`depth`]): scale- and shift-invariant L1 of the alpha-normalised expected depth
//!   against the depth prior;
//! - tracks ([`track`]): target-frame positions rendered as features, projected at the
//!   tracked source pixels and compared with the tracked target pixels.
//!
//! [`rgb_loss`] evaluates them for one rendered frame; [`ImageLossWeights::defaults`] gives
//! each profile's weights with where every value comes from.

pub mod depth;
#[cfg(test)]
mod fd;
pub mod mask;
pub mod photometric;
pub mod track;

pub use depth::DepthRegion;
pub use photometric::RgbForm;
pub use track::{Track, TrackForm, TrackSet};

use super::graph_loss::Reduction;
use crate::metrics::ssim_grad::SsimPadding;
use crate::render::{ImageGrads, RenderOutput};
use crate::stages::params::Profile;

/// Errors of the image loss: the ground truth does not match the render.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An input image has the wrong number of values.
    #[error("image loss: '{name}' has {got} values, expected {expected} (render is {w}x{h})")]
    Shape {
        /// The input.
        name: &'static str,
        /// Its length.
        got: usize,
        /// The expected length.
        expected: usize,
        /// Render width.
        w: usize,
        /// Render height.
        h: usize,
    },
    /// A track set names a feature block the render does not have.
    #[error("image loss: track feature block {block} needs {need} channels, render has {have}")]
    FeatureBlock {
        /// The block.
        block: usize,
        /// Channels it needs.
        need: usize,
        /// Channels rendered.
        have: usize,
    },
    /// SSIM could not be computed (a `valid` SSIM on an image under 11×11).
    #[error(transparent)]
    Ssim(#[from] crate::metrics::Error),
}

/// The weights and forms of L_rgb's terms. `paper` values are Shape of Motion's defaults
/// (formats-and-protocols.md §1.3) where the paper is silent, since the paper inherits these
/// terms from its base models; `release` values are MoSca's as the release's fine-tuning
/// stage uses them (official-release.md §5.3, MoSca's `photometric_fit`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImageLossWeights {
    /// Weight of the colour term [paper 1: SoM `w_rgb`; release 1: `1·L_rgb`].
    pub rgb: f64,
    /// Combination of L1 and SSIM [paper `Blend`: SoM's `0.8·L1 + 0.2·(1 − SSIM)`; release
    /// `Additive`: MoSca's `L1 + 0.1·(1 − SSIM)`].
    pub rgb_form: RgbForm,
    /// λ of the SSIM term [paper 0.2 (SoM); release 0.1 (MoSca)].
    pub ssim_lambda: f64,
    /// SSIM borders [paper `Valid`: SoM's `pytorch_msssim.SSIM`; release `Same`: MoSca's
    /// 3DGS-style `ssim`].
    pub ssim_padding: SsimPadding,
    /// Weight of the mask term [paper 1: SoM `w_mask`; release 0: `λ_mask` 0].
    pub mask: f64,
    /// Weight of the depth term [paper 0.5: SoM `w_depth_reg` (SoM's own term is an L1 on
    /// disparity; the form here is the release's); release 0.1: `0.1·L_dep`].
    pub depth: f64,
    /// Pixels the depth term supervises [paper `Foreground` (SoM's foreground-only model);
    /// release `ValidPrior` (MoSca's "all" mask × depth mask)].
    pub depth_region: DepthRegion,
    /// Weight of the track term [paper 2: SoM `w_track`; release 0.1: `0.1·L_track`, iPhone
    /// config].
    pub track: f64,
    /// Per-track error and reduction [paper `Som { trim 0.98 }`; release `Mosca { clamp 100
    /// px }`].
    pub track_form: TrackForm,
    /// How a step combines its batch frames' terms [paper `Mean`: one view's scale, as the
    /// base models weigh L_rgb against their other terms (MoSca fits one view a step);
    /// release `Sum`: its `photometric_fit` adds the 8 views' losses].
    pub batch: Reduction,
}

impl ImageLossWeights {
    /// The weights of `profile` (field docs say where each value comes from).
    pub fn defaults(profile: Profile) -> ImageLossWeights {
        match profile {
            Profile::Paper => ImageLossWeights {
                rgb: 1.0,
                rgb_form: RgbForm::Blend,
                ssim_lambda: 0.2,
                ssim_padding: SsimPadding::Valid,
                mask: 1.0,
                depth: 0.5,
                depth_region: DepthRegion::Foreground,
                track: 2.0,
                track_form: TrackForm::Som { trim_quantile: 0.98 },
                batch: Reduction::Mean,
            },
            Profile::Release => ImageLossWeights {
                rgb: 1.0,
                rgb_form: RgbForm::Additive,
                ssim_lambda: 0.1,
                ssim_padding: SsimPadding::Same,
                mask: 0.0,
                depth: 0.1,
                depth_region: DepthRegion::ValidPrior,
                track: 0.1,
                track_form: TrackForm::Mosca { clamp_px: 100.0 },
                batch: Reduction::Sum,
            },
        }
    }
}

/// One training frame's references, `[H, W]` images at the render's size.
#[derive(Debug, Clone, Copy)]
pub struct FrameTargets<'a> {
    /// `[H, W, 3]` ground-truth colour composited over the render background.
    pub rgb: &'a [f32],
    /// `[H, W]` colour supervision weights in [0, 1]; None: every pixel.
    pub valid: Option<&'a [f32]>,
    /// `[H, W]` foreground mask in [0, 1]; None: the scene has no masks (no mask term).
    pub mask: Option<&'a [f32]>,
    /// `[H, W]` prior z-depth, 0 = invalid; None: no depth prior (no depth term).
    pub depth: Option<&'a [f32]>,
    /// Tracks from this frame, one set per rendered feature block; empty: no track term.
    pub tracks: &'a [TrackSet<'a>],
}

/// Names of the terms [`rgb_loss`] may return, in order.
pub const TERMS: [&str; 4] = ["rgb", "mask", "depth", "track"];

/// Named loss terms, each already multiplied by its weight.
pub type Terms = Vec<(&'static str, f64)>;

/// L_rgb of one rendered frame `out` against `truth`: the terms used (each already
/// multiplied by its weight, so that they sum to the loss; names from [`TERMS`]) and the
/// cotangent of that sum w.r.t. the render's images. Unused images get empty cotangents.
/// The track term reads `out.features` (`[H, W, F]`, F = its length / (H·W)).
pub fn rgb_loss(
    out: &RenderOutput,
    truth: &FrameTargets,
    weights: &ImageLossWeights,
) -> Result<(Terms, ImageGrads), Error> {
    let (w, h) = (out.width, out.height);
    let n = w * h;
    let check = |name: &'static str, got: usize, expected: usize| {
        if got == expected { Ok(()) } else { Err(Error::Shape { name, got, expected, w, h }) }
    };
    check("rendered color", out.color.len(), 3 * n)?;
    check("rendered alpha", out.alpha.len(), n)?;
    check("ground-truth rgb", truth.rgb.len(), 3 * n)?;
    for (name, img) in [("valid", truth.valid), ("mask", truth.mask), ("depth prior", truth.depth)]
    {
        if let Some(img) = img {
            check(name, img.len(), n)?;
        }
    }
    let mut terms = Vec::new();
    let mut grads = ImageGrads::default();
    if weights.rgb > 0.0 {
        grads.color = vec![0.0; 3 * n];
        let l = photometric::rgb_with_grad(
            &out.color,
            truth.rgb,
            (w, h),
            truth.valid,
            weights.rgb_form,
            weights.ssim_lambda,
            weights.ssim_padding,
            Some((&mut grads.color, weights.rgb)),
        )?;
        terms.push(("rgb", weights.rgb * l.value));
    }
    if let (Some(m), true) = (truth.mask, weights.mask > 0.0) {
        grads.alpha = vec![0.0; n];
        let l = mask::alpha_mask_with_grad(&out.alpha, m, Some((&mut grads.alpha, weights.mask)));
        terms.push(("mask", weights.mask * l));
    }
    if let (Some(prior), true) = (truth.depth, weights.depth > 0.0) {
        check("rendered depth", out.depth.len(), n)?;
        let region = match weights.depth_region {
            DepthRegion::ValidPrior => None,
            DepthRegion::Foreground => truth.mask,
        };
        grads.depth = vec![0.0; n];
        if grads.alpha.is_empty() {
            grads.alpha = vec![0.0; n];
        }
        let g = depth::DepthGrads {
            depth: &mut grads.depth,
            alpha: &mut grads.alpha,
            scale: weights.depth,
        };
        let l = depth::ssi_depth_with_grad(&out.depth, &out.alpha, prior, region, Some(g));
        terms.push(("depth", weights.depth * l));
    }
    if !truth.tracks.is_empty() && weights.track > 0.0 {
        let f = out.features.len().checked_div(n).unwrap_or(0);
        check("rendered features", out.features.len(), n * f)?;
        if let Some(s) = truth.tracks.iter().find(|s| 3 * s.block + 3 > f) {
            return Err(Error::FeatureBlock { block: s.block, need: 3 * s.block + 3, have: f });
        }
        grads.features = vec![0.0; n * f];
        let l = track::track_with_grad(
            &out.features,
            (w, h),
            f,
            truth.tracks,
            weights.track_form,
            Some((&mut grads.features, weights.track)),
        );
        terms.push(("track", weights.track * l));
    }
    Ok((terms, grads))
}

#[cfg(test)]
mod tests;
