//! The CPU reference renderer: runs the stages `project` → colours (SH) → `isect_tiles` →
//! `tile_ranges` → `rasterize_fwd` (→ `rasterize_bwd` → projection and SH VJPs) and turns
//! their per-pair results into images and per-Gaussian statistics.
//!
//! Every reduction over pairs or Gaussians is sequential in a fixed order (or rayon over
//! independent Gaussians), so outputs and gradients are bit-identical whatever the thread
//! count. Channel layout per Gaussian, C = 4 + F: `[r, g, b, z, f_0 .. f_{F-1}]`.

pub mod backward;
pub mod blend;
pub mod forward;
pub mod isect;
pub mod project;

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use crate::math::quat;
use crate::render::constants::ALPHA_THRESHOLD;
use crate::render::{
    ColorSource, ConvergenceTest, CpuRenderer, Cutoff, DifferentiableRenderer, Error, ImageGrads,
    RenderAux, RenderCamera, RenderOutput, RenderSettings, ShFrame, SplatGrads, SplatInputs,
    check_saved, sh,
};
use backward::rasterize_bwd;
use forward::{FwdImages, RasterInputs, failing_pairs, failing_pairs_weighted, rasterize_fwd};
use isect::{Intersections, TileGrid, isect_tiles, tile_ranges};
use project::{CameraConsts, Splat2d, Splat2dGrad, project, project_vjp};

/// Forward state the CPU backward pass needs (one render's worth).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SavedForBackward {
    /// `[N]` projected Gaussians.
    pub splats: Vec<Splat2d>,
    /// `[N, C]` channel values, C = 4 + F.
    pub channels: Vec<f32>,
    /// The sorted intersections `[M]`.
    pub isect: Intersections,
    /// `[TX·TY + 1]` tile offsets.
    pub offsets: Vec<usize>,
    /// `[H, W]` final transmittance.
    pub final_t: Vec<f32>,
    /// `[H, W]` last contributor (see [`FwdImages::last_contributor`]).
    pub last_contributor: Vec<u32>,
    /// The cutoff the forward pass used.
    pub cutoff: Cutoff,
}

/// Checks array lengths against N (and F) at stage entry.
pub(crate) fn check_inputs(
    cam: &RenderCamera,
    inputs: &SplatInputs,
    settings: &RenderSettings,
) -> Result<(), Error> {
    let n = inputs.means.len();
    let dim = |name: &'static str, got: usize, expected: usize| {
        if got == expected { Ok(()) } else { Err(Error::Shape { name, got, expected }) }
    };
    dim("quats", inputs.quats.len(), n)?;
    dim("scales", inputs.scales.len(), n)?;
    dim("opacities", inputs.opacities.len(), n)?;
    dim("features", inputs.features.len(), n * inputs.num_features)?;
    match inputs.colors {
        ColorSource::Rgb(c) => dim("colors", c.len(), n)?,
        ColorSource::Sh { degree, dc, rest, .. } => {
            if degree > 3 {
                return Err(Error::Settings(format!(
                    "SH degree {degree} is not supported (0..=3)"
                )));
            }
            dim("sh dc", dc.len(), n)?;
            dim("sh rest", rest.len(), n * 3 * (sh::num_basis(degree) - 1))?;
        }
    }
    if n > u32::MAX as usize {
        return Err(Error::Settings(format!("{n} Gaussians exceed the u32 index space")));
    }
    let cam_ok = [cam.fx, cam.fy, cam.cx, cam.cy, cam.near].iter().all(|v| v.is_finite())
        && cam.fx > 0.0
        && cam.fy > 0.0
        && cam.near > 0.0
        && cam.far > cam.near
        && cam.width > 0
        && cam.height > 0
        && cam.w2c.is_finite();
    if !cam_ok {
        return Err(Error::Settings(format!("unusable camera {cam:?}")));
    }
    let a = settings.alpha_max;
    if !(a > ALPHA_THRESHOLD && a < 1.0) {
        return Err(Error::Settings(format!("alpha_max {a} must be in (1/255, 1)")));
    }
    if !settings.background.iter().all(|v| v.is_finite()) {
        return Err(Error::Settings(format!("background {:?} is not finite", settings.background)));
    }
    Ok(())
}

/// Unit view direction of Gaussian `i` for SH (world or local frame); zero when undefined.
fn view_dir(c: &CameraConsts, mean: [f32; 3], quat: [f32; 4], frame: ShFrame) -> (Vec3, f32) {
    let d = Vec3::from(mean) - c.center;
    let len = d.length();
    if !(len > 0.0 && len.is_finite()) {
        return (Vec3::ZERO, 0.0);
    }
    let dir = d / len;
    match frame {
        ShFrame::World => (dir, len),
        ShFrame::Local => match quat::normalize(quat) {
            Some((q, _)) => (quat::to_rotmat(q).transpose() * dir, len),
            None => (Vec3::ZERO, 0.0),
        },
    }
}

/// `[N, C]` channel values of the visible Gaussians (zeros for culled ones).
fn channels(c: &CameraConsts, inputs: &SplatInputs, splats: &[Splat2d]) -> Vec<f32> {
    let nf = inputs.num_features;
    let nc = 4 + nf;
    let mut out = vec![0.0f32; splats.len() * nc];
    out.par_chunks_mut(nc).enumerate().for_each(|(i, ch)| {
        if !splats[i].valid {
            return;
        }
        let rgb = match inputs.colors {
            ColorSource::Rgb(rgb) => rgb[i],
            ColorSource::Sh { degree, dc, rest, frame } => {
                let k3 = 3 * (sh::num_basis(degree) - 1);
                let (dir, _) = view_dir(c, inputs.means[i], inputs.quats[i], frame);
                sh::eval(degree, dc[i], &rest[i * k3..(i + 1) * k3], dir.into())
            }
        };
        ch[..3].copy_from_slice(&rgb);
        ch[3] = splats[i].depth;
        ch[4..].copy_from_slice(&inputs.features[i * nf..(i + 1) * nf]);
        // Poisoned colours or features must not poison the image: the Gaussian stays
        // geometrically visible with those channels zeroed.
        for v in ch.iter_mut() {
            if !v.is_finite() {
                *v = 0.0;
            }
        }
    });
    out
}

/// Forward through all stages.
fn run_forward(
    cam: &RenderCamera,
    inputs: &SplatInputs,
    settings: &RenderSettings,
    cutoff: Cutoff,
) -> Result<(SavedForBackward, FwdImages), Error> {
    check_inputs(cam, inputs, settings)?;
    let _span = tracing::debug_span!("render.cpu.forward", n = inputs.means.len()).entered();
    let consts = CameraConsts::new(cam);
    let grid = TileGrid::new(cam.width, cam.height);
    let splats = project(&consts, inputs);
    let channels = channels(&consts, inputs, &splats);
    let isect = isect_tiles(&grid, &splats);
    let offsets = tile_ranges(&isect.keys, grid.num_tiles());
    let inp = RasterInputs {
        grid,
        splats: &splats,
        channels: &channels,
        num_channels: 4 + inputs.num_features,
        isect: &isect,
        offsets: &offsets,
        alpha_max: settings.alpha_max,
        cutoff,
    };
    let mut fwd = rasterize_fwd(&inp);
    let saved = SavedForBackward {
        final_t: std::mem::take(&mut fwd.final_t),
        last_contributor: std::mem::take(&mut fwd.last_contributor),
        splats,
        channels,
        isect,
        offsets,
        cutoff,
    };
    Ok((saved, fwd))
}

/// Per-Gaussian sums of the per-pair statistics, in list order.
fn reduce_stats(saved: &SavedForBackward, fwd: &FwdImages) -> RenderAux {
    let mut aux = RenderAux::culled(saved.splats.len());
    for (&g, s) in saved.isect.gaussian.iter().zip(&fwd.stats) {
        let g = g as usize;
        aux.visible[g] = true;
        aux.radius_px[g] = saved.splats[g].radius;
        aux.sum_w2[g] += s.sum_w2;
        aux.sum_w[g] += s.sum_w;
        aux.n_pixels[g] += s.n_pixels;
    }
    aux
}

/// `[N]` release convergence: the pixel under the projected centre passes.
fn centre_pass(splats: &[Splat2d], pixel_pass: &[bool], w: usize, h: usize) -> Vec<bool> {
    splats
        .iter()
        .map(|s| {
            let (x, y) = (s.mean2d[0].floor(), s.mean2d[1].floor());
            s.valid
                && x >= 0.0
                && y >= 0.0
                && (x as usize) < w
                && (y as usize) < h
                && pixel_pass[y as usize * w + x as usize]
        })
        .collect()
}

fn assemble(
    cam: &RenderCamera,
    settings: &RenderSettings,
    nf: usize,
    saved: &SavedForBackward,
    fwd: &FwdImages,
    aux: RenderAux,
) -> RenderOutput {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let nc = 4 + nf;
    let ch = |p: usize, c: usize| fwd.channels[p * nc + c];
    RenderOutput::compose((w, h, nf), aux, ch, |p| saved.final_t[p], settings.background)
}

super::render_is_forward!(CpuRenderer);

impl DifferentiableRenderer for CpuRenderer {
    type Saved = SavedForBackward;

    fn render_with_saved(
        &self,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        cutoff: Cutoff,
    ) -> Result<(RenderOutput, SavedForBackward), Error> {
        let (saved, fwd) = run_forward(cam, inputs, settings, cutoff)?;
        let aux = reduce_stats(&saved, &fwd);
        let out = assemble(cam, settings, inputs.num_features, &saved, &fwd, aux);
        Ok((out, saved))
    }

    fn backward(
        &self,
        cam: &RenderCamera,
        inputs: &SplatInputs,
        settings: &RenderSettings,
        saved: &SavedForBackward,
        v: &ImageGrads,
    ) -> Result<SplatGrads, Error> {
        check_inputs(cam, inputs, settings)?;
        let _span = tracing::debug_span!("render.cpu.backward", n = inputs.means.len()).entered();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n = inputs.means.len();
        let nf = inputs.num_features;
        let nc = 4 + nf;
        check_saved(cam, None, saved.splats.len() == n && saved.final_t.len() == w * h)?;
        v.check_shapes(w, h, nf)?;
        // Per-pixel cotangents of the blended channels and of alpha.
        let mut v_ch = vec![0.0f32; w * h * nc];
        let mut v_alpha = vec![0.0f32; w * h];
        for p in 0..w * h {
            v_alpha[p] = v.pixel(p, settings.background, &mut v_ch[p * nc..(p + 1) * nc]);
        }
        let inp = RasterInputs {
            grid: TileGrid::new(cam.width, cam.height),
            splats: &saved.splats,
            channels: &saved.channels,
            num_channels: nc,
            isect: &saved.isect,
            offsets: &saved.offsets,
            alpha_max: settings.alpha_max,
            cutoff: saved.cutoff,
        };
        let g2 = rasterize_bwd(&inp, &saved.final_t, &saved.last_contributor, &v_ch, &v_alpha);
        let consts = CameraConsts::new(cam);
        Ok(project_backward(&consts, inputs, saved, &g2.splats, &g2.channels))
    }

    fn convergence_saved(
        &self,
        cam: &RenderCamera,
        settings: &RenderSettings,
        saved: &SavedForBackward,
        pixel_pass: &[bool],
        test: ConvergenceTest,
    ) -> Result<Vec<bool>, Error> {
        let (w, h) = (cam.width as usize, cam.height as usize);
        check_saved(cam, Some(pixel_pass), saved.final_t.len() == w * h)?;
        if test == ConvergenceTest::CentrePixel {
            return Ok(centre_pass(&saved.splats, pixel_pass, w, h));
        }
        let inp = RasterInputs {
            grid: TileGrid::new(cam.width, cam.height),
            splats: &saved.splats,
            channels: &saved.channels,
            num_channels: saved.channels.len() / saved.splats.len().max(1),
            isect: &saved.isect,
            offsets: &saved.offsets,
            alpha_max: settings.alpha_max,
            cutoff: saved.cutoff,
        };
        let fail = match test {
            ConvergenceTest::WeightedPixels(min_weight) => {
                failing_pairs_weighted(&inp, &saved.last_contributor, pixel_pass, min_weight)
            }
            _ => failing_pairs(&inp, &saved.last_contributor, pixel_pass),
        };
        let mut ok = vec![true; saved.splats.len()];
        for (&g, f) in saved.isect.gaussian.iter().zip(&fail) {
            ok[g as usize] &= !f;
        }
        Ok(ok)
    }
}

/// Per-Gaussian VJPs of the channel construction (SH, depth, features) and of `project`
/// (rayon over Gaussians, each independent).
fn project_backward(
    c: &CameraConsts,
    inputs: &SplatInputs,
    saved: &SavedForBackward,
    v2d: &[Splat2dGrad],
    v_ch: &[f32],
) -> SplatGrads {
    let n = inputs.means.len();
    let nf = inputs.num_features;
    let nc = 4 + nf;
    let k3 = match inputs.colors {
        ColorSource::Rgb(_) => 0,
        ColorSource::Sh { degree, .. } => 3 * (sh::num_basis(degree) - 1),
    };
    struct One {
        mean: [f32; 3],
        quat: [f32; 4],
        scale: [f32; 3],
        opacity: f32,
        color: [f32; 3],
        rest: Vec<f32>,
    }
    let per: Vec<One> = (0..n)
        .into_par_iter()
        .map(|i| {
            let s = &saved.splats[i];
            let vc = &v_ch[i * nc..(i + 1) * nc];
            let mut rest = vec![0.0f32; k3];
            if !s.valid {
                return One {
                    mean: [0.0; 3],
                    quat: [0.0; 4],
                    scale: [0.0; 3],
                    opacity: 0.0,
                    color: [0.0; 3],
                    rest,
                };
            }
            let mut v_mean = Vec3::ZERO;
            let mut v_rot = Mat3::ZERO;
            let v_rgb = [vc[0], vc[1], vc[2]];
            let color = match inputs.colors {
                ColorSource::Rgb(_) => v_rgb,
                ColorSource::Sh { degree, dc, rest: coeffs, frame } => {
                    let (dir, len) = view_dir(c, inputs.means[i], inputs.quats[i], frame);
                    let (v_dc, v_dir) = sh::eval_vjp(
                        degree,
                        dc[i],
                        &coeffs[i * k3..(i + 1) * k3],
                        dir.into(),
                        v_rgb,
                        &mut rest,
                    );
                    if len > 0.0 {
                        let v_dir = Vec3::from(v_dir);
                        // World direction d = (p − c)/|p − c|; local direction Rᵀ d.
                        let (v_dw, d_world) = match frame {
                            ShFrame::World => (v_dir, dir),
                            ShFrame::Local => {
                                let (q, _) = quat::normalize(inputs.quats[i])
                                    .unwrap_or(([1.0, 0.0, 0.0, 0.0], 1.0));
                                let r = quat::to_rotmat(q);
                                let dw = r * dir;
                                // dir_l[j] = Σ_i R[i][j] dw[i] → dL/dR[i][j] = dw[i] v_dir[j].
                                v_rot = Mat3::from_cols(dw * v_dir.x, dw * v_dir.y, dw * v_dir.z);
                                (r * v_dir, dw)
                            }
                        };
                        v_mean += (v_dw - d_world * d_world.dot(v_dw)) / len;
                    }
                    v_dc
                }
            };
            let g2 = Splat2dGrad { depth: vc[3], ..v2d[i] };
            let g3 =
                project_vjp(c, inputs.means[i], inputs.quats[i], inputs.scales[i], s, &g2, v_rot);
            let mean = (Vec3::from(g3.mean) + v_mean).into();
            One { mean, quat: g3.quat, scale: g3.scale, opacity: g3.opacity, color, rest }
        })
        .collect();
    let mut out = SplatGrads {
        means: Vec::with_capacity(n),
        quats: Vec::with_capacity(n),
        scales: Vec::with_capacity(n),
        opacities: Vec::with_capacity(n),
        colors: Vec::with_capacity(n),
        sh_rest: Vec::with_capacity(n * k3),
        features: Vec::with_capacity(n * nf),
        means2d: Vec::with_capacity(n),
    };
    for (i, o) in per.into_iter().enumerate() {
        out.means.push(o.mean);
        out.quats.push(o.quat);
        out.scales.push(o.scale);
        out.opacities.push(o.opacity);
        out.colors.push(o.color);
        out.sh_rest.extend_from_slice(&o.rest);
        out.features.extend_from_slice(&v_ch[i * nc + 4..(i + 1) * nc]);
        out.means2d.push(if saved.splats[i].valid { v2d[i].mean2d } else { [0.0; 2] });
    }
    out
}
