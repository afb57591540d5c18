//! The depth term of L_rgb: MoSca's scale- and shift-invariant L1 (`compute_dep_loss` with
//! `st_invariant`, the release's L_dep), with its gradient w.r.t. the rendered images.
//!
//! Over the supervised pixels R (the region mask, ≥ 0.5, where the prior is a valid depth:
//! finite and > 0), each map is normalised by its median t and its mean absolute deviation
//! s = mean_R |d − t|; the loss is `mean_R |(d − t_d)/s_d − (g − t_g)/s_g|` for the
//! prediction d against the prior g.
//!
//! Prediction: the renderer's depth is Σ T·α·z, not normalised by alpha. We normalise,
//! d = D / max(α, 1e-6) (the alpha-weighted mean z of the Gaussians at the pixel): Shape of
//! Motion renders gsplat's alpha-normalised "ED" depth, and MoSca's backend returns a
//! normalised depth (its loss code keeps the division commented out with "gof does not need
//! divide alpha"). So the gradient reaches both images: dL/dD = dL/dd / α and
//! dL/dα = −dL/dd · D / α² (0 where α ≤ 1e-6, the clamp).
//!
//! Differentiating the normalisation: the median is the element at the lower middle rank
//! (`torch.median`), and its index is held fixed (the loss is piecewise smooth and the rank
//! order is locally constant), so t_d moves with that one pixel; the mean absolute
//! deviation is differentiated exactly (sign(d − t) per pixel, through t as well). With
//! e_p = sign(n_p − ĝ_p)/|R|, n = (d − t)/s, E = Σ e_p, F = Σ e_p·n_p and σ_j = sign(d_j − t):
//! `dL/dd_j = e_j/s − (F/(s|R|))·σ_j`, plus `−E/s + (F/(s|R|))·Σσ` at the median pixel.
//! Fewer than 2 supervised pixels, or a constant map (s = 0), give 0 and no gradient.

use crate::stages::optimize::sign;

/// The lower bound on α when normalising the rendered depth.
pub const ALPHA_EPS: f32 = 1e-6;

/// Which pixels the depth term supervises (besides needing a valid prior).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum DepthRegion {
    /// Every pixel with a valid prior (MoSca's "all" supervision mask × depth mask; the
    /// release).
    ValidPrior,
    /// Foreground-mask pixels with a valid prior (Shape of Motion's `depth_masks` of its
    /// foreground-only model). Without a mask, every pixel.
    Foreground,
}

/// Cotangent buffers of the depth term: `[H, W]` each, added to.
pub struct DepthGrads<'a> {
    /// dL/d rendered depth D.
    pub depth: &'a mut [f32],
    /// dL/d rendered alpha.
    pub alpha: &'a mut [f32],
    /// Factor applied to both.
    pub scale: f64,
}

/// The scale- and shift-invariant L1 of the rendered depth (`depth` Σ T·α·z and `alpha`,
/// `[H, W]`) against `prior` (`[H, W]`, 0 = invalid) over the pixels where `region`
/// (`[H, W]`, None = all) is ≥ 0.5; with `grad` adds the scaled cotangents.
pub fn ssi_depth_with_grad(
    depth: &[f32],
    alpha: &[f32],
    prior: &[f32],
    region: Option<&[f32]>,
    grad: Option<DepthGrads>,
) -> f64 {
    let n = depth.len();
    assert!(alpha.len() == n && prior.len() == n, "depth, alpha and prior differ in size");
    let pixels: Vec<usize> = (0..n)
        .filter(|&p| region.is_none_or(|m| m[p] >= 0.5) && prior[p].is_finite() && prior[p] > 0.0)
        .collect();
    let pred: Vec<f64> =
        pixels.iter().map(|&p| depth[p] as f64 / alpha[p].max(ALPHA_EPS) as f64).collect();
    let target: Vec<f64> = pixels.iter().map(|&p| prior[p] as f64).collect();
    let Some((loss, dpred)) = ssi_l1(&pred, &target) else {
        return 0.0;
    };
    if let Some(DepthGrads { depth: gd, alpha: ga, scale }) = grad {
        for (&p, g) in pixels.iter().zip(&dpred) {
            let a = alpha[p].max(ALPHA_EPS) as f64;
            gd[p] += (scale * g / a) as f32;
            if alpha[p] > ALPHA_EPS {
                ga[p] -= (scale * g * depth[p] as f64 / (a * a)) as f32;
            }
        }
    }
    loss
}

/// Median (lower middle rank, ties broken by index) and mean absolute deviation of `v`, or
/// `None` when `v` has fewer than 2 values or no spread.
fn normalisation(v: &[f64]) -> Option<(usize, f64, f64)> {
    if v.len() < 2 {
        return None;
    }
    let mut idx: Vec<usize> = (0..v.len()).collect();
    let k = (v.len() - 1) / 2;
    idx.select_nth_unstable_by(k, |a, b| v[*a].total_cmp(&v[*b]).then(a.cmp(b)));
    let m = idx[k];
    let t = v[m];
    let s = v.iter().map(|x| (x - t).abs()).sum::<f64>() / v.len() as f64;
    (s > 0.0 && s.is_finite()).then_some((m, t, s))
}

/// The scale- and shift-invariant L1 of `pred` against `target` (same length) and its
/// gradient w.r.t. `pred` (module doc), or `None` when either cannot be normalised.
fn ssi_l1(pred: &[f64], target: &[f64]) -> Option<(f64, Vec<f64>)> {
    let (k, t, s) = normalisation(pred)?;
    let (_, tg, sg) = normalisation(target)?;
    let inv_n = 1.0 / pred.len() as f64;
    let norm: Vec<f64> = pred.iter().map(|d| (d - t) / s).collect();
    let e: Vec<f64> =
        norm.iter().zip(target).map(|(n, g)| inv_n * sign(n - (g - tg) / sg)).collect();
    let loss = norm.iter().zip(target).map(|(n, g)| (n - (g - tg) / sg).abs()).sum::<f64>() * inv_n;
    let big_e: f64 = e.iter().sum();
    let big_f: f64 = e.iter().zip(&norm).map(|(e, n)| e * n).sum();
    let sum_sigma: f64 = pred.iter().map(|d| sign(d - t)).sum();
    let c = big_f / s * inv_n;
    let mut grad: Vec<f64> = e.iter().zip(pred).map(|(e, d)| e / s - c * sign(d - t)).collect();
    grad[k] += -big_e / s + c * sum_sigma;
    Some((loss, grad))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::optimize::image_loss::fd::{Check, noise};

    /// A test scene `[H, W]`: depth-like prior in [1, 3] with invalid pixels, a rendered
    /// expected depth and alpha, and a region mask.
    fn scene(n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
        let alpha: Vec<f32> = noise(n, 41).iter().map(|v| 0.3 + 0.7 * v).collect();
        let z: Vec<f32> = noise(n, 42).iter().map(|v| 1.0 + 2.0 * v).collect();
        let depth: Vec<f32> = z.iter().zip(&alpha).map(|(z, a)| z * a).collect();
        let prior: Vec<f32> = noise(n, 43)
            .iter()
            .enumerate()
            .map(|(i, v)| if i % 11 == 3 { 0.0 } else { 1.0 + 2.0 * v })
            .collect();
        let region: Vec<f32> = (0..n).map(|i| if i % 5 == 1 { 0.0 } else { 1.0 }).collect();
        (depth, alpha, prior, region)
    }

    /// Central differences in f64 on the core: every prediction value, the median included.
    #[test]
    fn ssi_core_gradient_matches_finite_differences() {
        let n = 37;
        let pred: Vec<f64> = noise(n, 51).iter().map(|v| 1.0 + 3.0 * *v as f64).collect();
        let target: Vec<f64> = noise(n, 52).iter().map(|v| 0.5 + *v as f64).collect();
        let (_, g) = ssi_l1(&pred, &target).unwrap();
        let (k, ..) = normalisation(&pred).unwrap();
        // The step must not reorder values (their spacing is ≥ 1/4096 · 3).
        let eps = 1e-5;
        let mut check = Check::new("ssi depth core", 1e-8, 1e-5);
        for j in 0..n {
            let mut p = pred.clone();
            p[j] += eps;
            let lp = ssi_l1(&p, &target).unwrap().0;
            p[j] -= 2.0 * eps;
            let lm = ssi_l1(&p, &target).unwrap().0;
            let case = if j == k { format!("median pixel {j}") } else { format!("pixel {j}") };
            check.compare(&case, g[j], (lp - lm) / (2.0 * eps));
        }
        check.finish();
    }

    /// Through the alpha normalisation: gradients w.r.t. the rendered depth and alpha
    /// images, f64 central differences of the f32 images on 1/1024 steps would reorder
    /// nearby values, so this uses the images' own scale with a small exact step.
    #[test]
    fn depth_and_alpha_gradients_match_finite_differences() {
        let (w, h) = (9, 8);
        let (depth, alpha, prior, region) = scene(w * h);
        let mut gd = vec![0.0f32; w * h];
        let mut ga = vec![0.0f32; w * h];
        let grads = DepthGrads { depth: &mut gd, alpha: &mut ga, scale: 0.5 };
        ssi_depth_with_grad(&depth, &alpha, &prior, Some(&region), Some(grads));
        let eps = 1.0 / (1 << 16) as f32;
        let mut check = Check::new("ssi depth images", 1e-5, 2e-3);
        let ld = |d: &[f32]| 0.5 * ssi_depth_with_grad(d, &alpha, &prior, Some(&region), None);
        check.image("depth", &depth, &gd, eps, ld, 1);
        let la = |a: &[f32]| 0.5 * ssi_depth_with_grad(&depth, a, &prior, Some(&region), None);
        check.image("alpha", &alpha, &ga, eps, la, 1);
        check.finish();
        // Unsupervised pixels get nothing.
        for p in 0..w * h {
            if region[p] < 0.5 || prior[p] <= 0.0 {
                assert_eq!((gd[p], ga[p]), (0.0, 0.0), "pixel {p}");
            }
        }
    }

    #[test]
    fn invariant_to_scale_and_shift_of_either_map() {
        let (depth, alpha, prior, region) = scene(64);
        let base = ssi_depth_with_grad(&depth, &alpha, &prior, Some(&region), None);
        assert!(base > 0.1, "{base}");
        let scaled: Vec<f32> =
            prior.iter().map(|p| if *p > 0.0 { 4.0 * p + 2.0 } else { 0.0 }).collect();
        let s = ssi_depth_with_grad(&depth, &alpha, &scaled, Some(&region), None);
        assert!((s - base).abs() < 1e-5, "{s} vs {base}");
        // Rendering the prior itself (alpha 1) costs nothing, at any scale and shift.
        let ones = vec![1.0f32; 64];
        let d: Vec<f32> = prior.iter().map(|p| 0.5 * p + 1.0).collect();
        assert!(ssi_depth_with_grad(&d, &ones, &prior, Some(&region), None) < 1e-6);
    }

    #[test]
    fn degenerate_inputs_give_zero() {
        let ones = vec![1.0f32; 16];
        let zeros = vec![0.0f32; 16];
        // No valid prior, or a constant prediction.
        assert_eq!(ssi_depth_with_grad(&ones, &ones, &zeros, None, None), 0.0);
        let prior: Vec<f32> = (0..16).map(|i| 1.0 + i as f32).collect();
        assert_eq!(ssi_depth_with_grad(&ones, &ones, &prior, None, None), 0.0);
    }
}
