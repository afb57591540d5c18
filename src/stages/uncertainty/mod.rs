//! Dynamic uncertainty estimation (paper Sec. 4.1, Eqs. 3-5; official-release.md Sec. 2).
//!
//! For every training frame t the whole model (static and dynamic Gaussians, so occlusion
//! counts) is rendered from the training camera of frame t (the model's own camera when it
//! carries cameras) over a white background, and compared with the ground truth read as the
//! scene's alpha mode says (coverage: over white; DyCheck: plain RGB). Then:
//! - Eq. 3: σ²_{i,t} = 1 / Σ_{h ∈ Ω_{i,t}} (T^h_{i,t} α_i)², from the renderer's per-Gaussian
//!   `sum_w2`;
//! - Eq. 4: the per-pixel indicator 𝟙_t(h) = [‖C̄^h − C^h‖₁ < η_c] against the ground truth
//!   composited over white (channels summed, paper; or averaged, release);
//! - Eq. 5: u_{i,t} = σ²_{i,t} when the Gaussian's indicator holds, φ otherwise (and for
//!   Gaussians that touch no pixel). The paper's indicator is the product over the covered
//!   pixels, here those where the Gaussian's blending weight T·α is at least
//!   `cover-min-weight` (0: every pixel it touches, the literal reading; the paper profile's
//!   default is a measured choice, see README "Deliberate readings"); the release tests only
//!   the pixel under the projected centre, ANDed with its
//!   extra gates at that pixel: SSIM > 0.01 in all channels (11×11 Gaussian window,
//!   σ 1.5), Sobel magnitude of the prior depth below its 90th percentile over the
//!   foreground mask, and the foreground mask itself. The depth gate needs the scene's
//!   depth maps and is skipped with a warning when a frame has none; without masks the
//!   mask is all ones, as in the release.
//! - Release normalisation: with c = 1/u the contribution, c80 and c99 the global quantiles
//!   over all (t, i), ref = mean(c ∈ (c80, c99)); if ref < 0.5 every reliable c is scaled
//!   by 0.5/ref and clipped at 10 (u = 1/c). Unreliable entries keep u = φ.
//!
//! Memory: all frames' statistics stay in memory until the normalisation, `N·T·17` bytes
//! (1.6 GB for N = 200,000 and T = 475), plus one frame's images and render.
//!
//! The anisotropic U_{i,t} of Eq. 6 is derived from u and the camera where needed
//! ([`super::graph::metric::uncertainty_matrix`]), not stored.

use std::path::PathBuf;

use super::params::check;
use crate::context::Context;
use crate::render::{
    ConvergenceTest, Cutoff, DifferentiableRenderer, RenderAux, RenderCamera, RenderSettings,
    SplatInputs,
};
use crate::tables::uncertainty::UncertaintyFrame;
use crate::util::{filter, stats};

/// Which pixels a Gaussian's convergence indicator tests (profile row 4).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Gate {
    /// Product over all covered pixels (paper).
    AllCoveredPixels,
    /// The pixel under the projected centre (release).
    CentrePixel,
}

/// How the L1 colour error combines channels (profile row 6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ChannelReduce {
    /// ‖C̄ − C‖₁ summed over RGB (paper).
    Sum,
    /// Mean absolute error over RGB (release).
    Mean,
}

/// Which Gaussians get an uncertainty (profile row 3).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scope {
    /// Every Gaussian (paper).
    All,
    /// Dynamic Gaussians only (release); static ones are rendered but not listed.
    DynamicOnly,
}

crate::stage_params! {
    /// Parameters of `usplat4d uncertainty`; unset values take the profile's defaults.
    pub struct UncertaintyParams;
    /// Concrete settings (recorded in the table's provenance).
    pub struct UncertaintySettings;
    inputs {
        /// Model directory (gaussians.parquet + trajectories.parquet).
        #[arg(long, value_name = "MODEL_DIR")]
        model: PathBuf,
        /// Scene directory (cameras.parquet and the training images).
        #[arg(long, value_name = "SCENE_DIR")]
        scene: PathBuf,
        /// Output directory (uncertainty.parquet).
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
    }
    params {
        heading "Method" {
            /// Colour-error threshold η_c, in (0, 1].
            eta_c: f32 => f32 [check::unit] { paper "0.5", release "0.3", row "5" },
            /// Pixels tested (all-covered-pixels, centre-pixel).
            gate: Gate => Gate [check::choice]
                { paper "all-covered-pixels", release "centre-pixel", row "4" },
            /// Covered pixels of the all-covered-pixels test: those where the Gaussian's
            /// blending weight T·α is at least this, in [0, 1]; 0 for every pixel it touches.
            cover_min_weight: f32 => Option<f32> [check::fraction]
                { paper "0.5", release "0", row "4" },
            /// Channel reduction of the L1 error (sum, mean).
            channel_reduce: ChannelReduce => ChannelReduce [check::choice]
                { paper "sum", release "mean", row "6" },
            /// SSIM gate threshold, 0 for off (`None`).
            ssim_gate: f32 => Option<f32> [check::finite32] { paper "0", release "0.01", row "7" },
            /// Depth-edge gate percentile, 0 for off (`None`).
            depth_edge_percentile: f32 => Option<f32> [check::percentile]
                { paper "0", release "90", row "8" },
            /// Foreground-mask gate.
            fg_mask_gate: bool => bool [check::parsed] { paper "false", release "true", row "9" },
            /// φ, the uncertainty of unconverged or unseen Gaussians.
            phi: f32 => f32 [check::positive] { paper "1e8", release "1e8", row "10" },
            /// Gaussians listed (all, dynamic-only).
            scope: Scope => Scope [check::choice] { paper "all", release "dynamic-only", row "3" },
            /// Contribution normalisation target, 0 for off (`None`).
            contrib_norm_target: f32 => Option<f32> [check::finite32]
                { paper "0", release "0.5", row "11" },
            /// Clip of the normalised contribution.
            contrib_clip_max: f32 => f32 [check::positive] { paper "10", release "10", row "12" },
        }
    }
    copied {}
}

/// Eq. 4: the per-pixel pass map `[H, W]` of ‖C̄ − C‖₁ < η_c for two `[H, W, 3]` images.
pub fn pixel_pass(rendered: &[f32], truth: &[f32], eta_c: f32, reduce: ChannelReduce) -> Vec<bool> {
    rendered
        .chunks_exact(3)
        .zip(truth.chunks_exact(3))
        .map(|(a, b)| {
            let l1: f32 = (0..3).map(|c| (a[c] - b[c]).abs()).sum();
            let e = match reduce {
                ChannelReduce::Sum => l1,
                ChannelReduce::Mean => l1 / 3.0,
            };
            e < eta_c
        })
        .collect()
}

/// Eqs. 3 and 5 for one frame: u = 1/Σ(Tα)² (clamped to φ) where the Gaussian touched a
/// pixel and its indicator holds, φ otherwise. `indicator` `[N]` is 𝟙_{i,t}; `rows` picks
/// the listed Gaussians (canonical indices).
pub fn frame_uncertainty(
    t: u32,
    aux: &RenderAux,
    indicator: &[bool],
    rows: &[usize],
    phi: f32,
) -> UncertaintyFrame {
    let mut f = UncertaintyFrame { frame: t, ..Default::default() };
    for &i in rows {
        let s = aux.sum_w2[i];
        let seen = aux.n_pixels[i] > 0 && s > 0.0;
        let converged = seen && indicator[i];
        f.sum_w2.push(s);
        f.sum_w.push(aux.sum_w[i]);
        f.n_pixels.push(aux.n_pixels[i]);
        f.converged.push(converged);
        f.u.push(if converged { (1.0 / s).min(phi) } else { phi });
    }
    f
}

/// Release normalisation (official-release.md Sec. 2.3) of all frames in place; returns the
/// scale applied to the contributions (1 when none).
pub fn normalise(frames: &mut [UncertaintyFrame], target: f32, clip: f32, phi: f32) -> f32 {
    let mut c: Vec<f32> = frames
        .iter()
        .flat_map(|f| {
            f.u.iter().zip(&f.converged).map(|(u, ok)| if *ok { 1.0 / u } else { 1.0 / phi })
        })
        .collect();
    let c80 = stats::quantile(&mut c, 0.80);
    let c99 = stats::quantile(&mut c, 0.99);
    let band: Vec<f64> = c.iter().filter(|v| **v > c80 && **v < c99).map(|v| *v as f64).collect();
    if band.is_empty() {
        return 1.0;
    }
    let reference = band.iter().sum::<f64>() / band.len() as f64;
    if reference >= target as f64 {
        return 1.0;
    }
    let scale = (target as f64 / reference) as f32;
    for f in frames.iter_mut() {
        for (u, ok) in f.u.iter_mut().zip(&f.converged) {
            if *ok {
                *u = 1.0 / (scale / *u).min(clip);
            }
        }
    }
    scale
}

/// The release's extra gates ANDed into `pass` `[H, W]`: SSIM of every channel above
/// `ssim`, depth gradient below its `percentile` over the mask's valid depth, mask ≥ 0.5.
pub fn apply_gates(
    pass: &mut [bool],
    rendered: &[f32],
    truth: &[f32],
    depth: Option<&[f32]>,
    mask: &[bool],
    (w, h): (usize, usize),
    s: &UncertaintySettings,
) {
    if let Some(thr) = s.ssim_gate {
        let m = crate::metrics::ssim::ssim_map(rendered, truth, w, h);
        for (i, p) in pass.iter_mut().enumerate() {
            *p &= (0..3).all(|c| m[i * 3 + c] > thr);
        }
    }
    if let (Some(pct), Some(d)) = (s.depth_edge_percentile, depth) {
        let g = filter::sobel_magnitude(d, w, h);
        // over the mask where the depth is valid: DyCheck's depth is 0 where the LiDAR has
        // none, and a frame without a mask would otherwise take its quantile over an empty
        // background, a limit of 0 that fails every pixel
        let mut inside: Vec<f32> = g
            .iter()
            .zip(mask)
            .zip(d)
            .filter(|((_, m), z)| **m && **z > 0.0 && z.is_finite())
            .map(|((v, _), _)| *v)
            .collect();
        if !inside.is_empty() {
            let limit = stats::quantile(&mut inside, pct as f64 / 100.0);
            for (p, v) in pass.iter_mut().zip(&g) {
                *p &= *v < limit;
            }
        }
    }
    if s.fg_mask_gate {
        for (p, m) in pass.iter_mut().zip(mask) {
            *p &= *m;
        }
    }
}

/// One frame's references for Eq. 4 and the release gates.
#[derive(Debug, Clone, Copy)]
pub struct FrameTruth<'a> {
    /// `[H, W, 3]` ground-truth colour composited over the render background.
    pub rgb: &'a [f32],
    /// `[H, W]` foreground mask (all true without masks).
    pub mask: &'a [bool],
    /// `[H, W]` prior depth for the depth-edge gate, when the frame has one.
    pub depth: Option<&'a [f32]>,
}

/// The stage's work on one frame once its inputs are loaded: one render of the whole model
/// from the training camera, Eq. 4's pass map with the release gates, the convergence
/// indicator from that same render (no second render), then Eqs. 3 and 5.
pub fn frame_work<R: DifferentiableRenderer>(
    renderer: &R,
    t: u32,
    camera: &RenderCamera,
    inputs: &SplatInputs,
    settings: &RenderSettings,
    truth: &FrameTruth,
    rows: &[usize],
    s: &UncertaintySettings,
) -> Result<UncertaintyFrame, crate::render::Error> {
    let (out, saved) = renderer.render_with_saved(camera, inputs, settings, Cutoff::Hard)?;
    let (w, h) = (out.width, out.height);
    let mut pass = pixel_pass(&out.color, truth.rgb, s.eta_c, s.channel_reduce);
    apply_gates(&mut pass, &out.color, truth.rgb, truth.depth, truth.mask, (w, h), s);
    let test = match (s.gate, s.cover_min_weight) {
        (Gate::AllCoveredPixels, None) => ConvergenceTest::AllCoveredPixels,
        (Gate::AllCoveredPixels, Some(m)) => ConvergenceTest::WeightedPixels(m),
        (Gate::CentrePixel, _) => ConvergenceTest::CentrePixel,
    };
    let indicator = renderer.convergence_saved(camera, settings, &saved, &pass, test)?;
    Ok(frame_uncertainty(t, &out.aux, &indicator, rows, s.phi))
}

/// A frame's references read from the scene directory (owned [`FrameTruth`]).
#[derive(Debug, Clone)]
pub struct LoadedTruth {
    /// `[H, W, 3]` ground truth over the background.
    pub rgb: Vec<f32>,
    /// `[H, W]` mask (all true when the camera has none).
    pub mask: Vec<bool>,
    /// `[H, W]` prior depth, read only when the depth-edge gate is on.
    pub depth: Option<Vec<f32>>,
    /// The depth-edge gate is on but the camera has no depth map.
    pub missing_depth: bool,
}

impl LoadedTruth {
    /// Read the image (and mask, and depth when the gate needs it) of training camera
    /// `cam`; errors name the file.
    pub fn load(
        scene: &crate::scene::Scene,
        cam: &crate::scene::Camera,
        background: [f32; 3],
        s: &UncertaintySettings,
    ) -> anyhow::Result<Self> {
        let (w, h) = cam.pinhole.size();
        let gate = s.depth_edge_percentile.is_some();
        let truth = scene.ground_truth(cam, background, true, gate)?;
        if truth.rgb.width != w || truth.rgb.height != h {
            anyhow::bail!(
                "{}: image is {}x{}, the camera says {w}x{h}",
                scene.resolve(&cam.image_path).display(),
                truth.rgb.width,
                truth.rgb.height
            );
        }
        let mask: Vec<bool> = match &truth.mask {
            Some(m) => m.data.iter().map(|v| *v >= 0.5).collect(),
            None => vec![true; w * h],
        };
        let missing_depth = gate && cam.depth_path.is_none();
        Ok(LoadedTruth { rgb: truth.rgb.data, mask, depth: truth.depth, missing_depth })
    }

    /// Borrowed view for [`frame_work`].
    pub fn view(&self) -> FrameTruth<'_> {
        FrameTruth { rgb: &self.rgb, mask: &self.mask, depth: self.depth.as_deref() }
    }
}

/// `usplat4d uncertainty`: render every training frame, write `OUT/uncertainty.parquet`.
pub fn run(p: &UncertaintyParams, ctx: &Context) -> anyhow::Result<()> {
    use crate::tables::Table;
    let _span = tracing::info_span!("uncertainty").entered();
    let s = p.resolve()?;
    let model = crate::model::Model::load(&p.model)?;
    let scene = crate::scene::Scene::load(&p.scene)?;
    let cams = scene.train_by_frame();
    if cams.len() != model.num_frames() {
        anyhow::bail!(
            "{}: {} training frames, but the model {} has {}",
            p.scene.display(),
            cams.len(),
            p.model.display(),
            model.num_frames()
        );
    }
    let g = &model.gaussians;
    let rows: Vec<usize> =
        (0..g.len()).filter(|&i| s.scope == Scope::All || g.dynamic[i]).collect();
    let ids: Vec<u32> = rows.iter().map(|&i| g.id[i]).collect();
    let settings = RenderSettings::default();
    let mut frames = Vec::with_capacity(cams.len());
    let mut warned_depth = false;
    let renderer = super::device::renderer(ctx)?;
    let bar = ctx.progress(cams.len() as u64, "uncertainty");
    for (t, cam) in cams.iter().enumerate() {
        let state = model.frame(t)?;
        let inputs = model.splat_inputs(&state);
        let loaded = LoadedTruth::load(&scene, cam, settings.background, &s)?;
        if loaded.missing_depth && !warned_depth {
            warned_depth = true;
            ctx.warn(format!(
                "uncertainty: frame {t} has no depth map; the depth-edge gate is not applied"
            ));
        }
        let truth = loaded.view();
        let camera = RenderCamera::from(&model.training_camera(cam));
        let frame = frame_work(&renderer, t as u32, &camera, &inputs, &settings, &truth, &rows, &s)
            .map_err(|e| anyhow::anyhow!("frame {t}: render: {e}"))?;
        frames.push(frame);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let scale = match s.contrib_norm_target {
        Some(target) => normalise(&mut frames, target, s.contrib_clip_max, s.phi),
        None => 1.0,
    };
    let converged: usize = frames.iter().map(|f| f.converged.iter().filter(|c| **c).count()).sum();
    ctx.info(format!(
        "uncertainty: {} Gaussians x {} frames, {:.1}% converged, contribution scale {scale}",
        ids.len(),
        frames.len(),
        100.0 * converged as f64 / (ids.len() * frames.len()).max(1) as f64
    ));
    let prov = crate::tables::Provenance::new(
        "uncertainty",
        &serde_json::json!({ "params": p, "resolved": s, "scale": scale }),
    );
    let path = p.out.join(crate::tables::uncertainty::UncertaintyTable::file_name());
    let mut w = crate::tables::uncertainty::UncertaintyWriter::create(&path, &ids, &prov)?;
    for f in &frames {
        w.write(f)?;
    }
    w.finish()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::params::Profile;

    fn aux(sum_w2: Vec<f32>, n_pixels: Vec<u32>) -> RenderAux {
        let n = sum_w2.len();
        RenderAux {
            visible: vec![true; n],
            radius_px: vec![1.0; n],
            sum_w: vec![1.0; n],
            sum_w2,
            n_pixels,
        }
    }

    #[test]
    fn eq3_and_eq5_on_hand_made_numbers() {
        // Gaussian 0: Σ(Tα)² = 4 → σ² = 0.25; 1: unconverged → φ; 2: unseen → φ;
        // 3: Σ(Tα)² tiny, 1/x above φ → clamped to φ; 4 is not listed.
        let a = aux(vec![4.0, 2.0, 0.0, 1e-12, 1.0], vec![10, 5, 0, 1, 3]);
        let f = frame_uncertainty(3, &a, &[true, false, true, true, true], &[0, 1, 2, 3], 1e8);
        assert_eq!(f.frame, 3);
        assert_eq!(f.u, vec![0.25, 1e8, 1e8, 1e8]);
        assert_eq!(f.converged, vec![true, false, false, true]);
        assert_eq!(f.n_pixels, vec![10, 5, 0, 1]);
    }

    #[test]
    fn pixel_indicator_sums_or_averages_channels() {
        let r = [0.5, 0.5, 0.5, 0.0, 0.0, 0.0];
        let t = [0.7, 0.7, 0.7, 0.1, 0.1, 0.1];
        // errors: 0.6 (sum) / 0.2 (mean); 0.3 / 0.1
        assert_eq!(pixel_pass(&r, &t, 0.5, ChannelReduce::Sum), vec![false, true]);
        assert_eq!(pixel_pass(&r, &t, 0.3, ChannelReduce::Mean), vec![true, true]);
        assert_eq!(pixel_pass(&r, &t, 0.15, ChannelReduce::Mean), vec![false, true]);
    }

    #[test]
    fn release_normalisation_scales_up_and_clips() {
        // contributions 0.1..=1.0 step 0.1 (u = 1/c) over 2 frames plus unreliable entries.
        let mk = |t: u32| {
            let c: Vec<f32> = (1..=10).map(|k| k as f32 / 10.0).collect();
            UncertaintyFrame {
                frame: t,
                sum_w2: c.clone(),
                sum_w: vec![1.0; 11],
                n_pixels: vec![1; 11],
                converged: (0..11).map(|k| k < 10).collect(),
                u: c.iter().map(|c| 1.0 / c).chain([1e8]).collect(),
            }
        };
        let mut frames = vec![mk(0), mk(1)];
        let scale = normalise(&mut frames, 18.0, 10.0, 1e8);
        // c80 = 0.8 and c99 = 1.0 over the 22 values; the band (c80, c99) holds the 0.9s:
        // ref 0.9 → scale 18/0.9 = 20
        assert!((scale - 20.0).abs() < 1e-4, "{scale}");
        assert!((frames[0].u[0] - 0.5).abs() < 1e-5);
        assert_eq!(frames[0].u[9], 0.1, "1.0 * scale clipped to 10");
        assert_eq!(frames[1].u[10], 1e8, "unreliable entries keep φ");
        let mut again = frames.clone();
        assert_eq!(normalise(&mut again, 0.5, 10.0, 1e8), 1.0, "only ever scales up");
    }

    #[test]
    fn gates_and_profiles() {
        let p = UncertaintySettings::defaults(Profile::Paper);
        let r = UncertaintySettings::defaults(Profile::Release);
        assert_eq!((p.eta_c, r.eta_c), (0.5, 0.3));
        assert_eq!((p.gate, r.gate), (Gate::AllCoveredPixels, Gate::CentrePixel));
        assert_eq!((p.ssim_gate, r.ssim_gate), (None, Some(0.01)));
        // identical images: SSIM 1 everywhere, so the SSIM gate passes; the mask gate
        // removes masked-out pixels; a depth step fails the depth-edge gate on the step.
        let (w, h) = (16, 8);
        let img: Vec<f32> = (0..w * h * 3).map(|i| (i % 7) as f32 / 7.0).collect();
        let depth: Vec<f32> = (0..w * h).map(|i| if i % w < 8 { 1.0 } else { 3.0 }).collect();
        let mask: Vec<bool> = (0..w * h).map(|i| i / w != 0).collect();
        let mut pass = vec![true; w * h];
        apply_gates(&mut pass, &img, &img, Some(&depth), &mask, (w, h), &r);
        assert!(!pass[3], "masked out");
        assert!(!pass[w + 8] && !pass[w + 7], "depth edge");
        assert!(pass[w + 2] && pass[w + 13]);
    }

    /// A DyCheck frame: no mask, and depth only on the object (0 = no LiDAR). The depth-edge
    /// quantile is taken over the valid depth, so the object's interior passes; over the
    /// whole frame it would be 0 and fail every pixel.
    #[test]
    fn depth_edge_gate_ignores_missing_depth() {
        let r = UncertaintySettings::defaults(Profile::Release);
        let (w, h) = (32, 32);
        let img = vec![0.5; w * h * 3];
        let object = |i: usize| (12..20).contains(&(i % w)) && (12..20).contains(&(i / w));
        let depth: Vec<f32> =
            (0..w * h).map(|i| if object(i) { 2.0 + (i % w) as f32 * 1e-3 } else { 0.0 }).collect();
        let mut pass = vec![true; w * h];
        apply_gates(&mut pass, &img, &img, Some(&depth), &vec![true; w * h], (w, h), &r);
        assert!(pass[15 * w + 15], "object interior passes");
        assert!(!pass[12 * w + 12], "silhouette fails");
    }
}
