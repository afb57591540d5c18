//! The colour part of L_rgb (paper Appendix A.3, inherited from the base models): L1 and
//! SSIM of the rendered colour against the ground truth, combined in the form of either base
//! model ([`RgbForm`]), with its gradient w.r.t. the rendered colour.
//!
//! A `valid` weight map `m` `[H, W]` (None = all ones) restricts supervision: the L1 is
//! `Σ_p m_p Σ_c |x − y| / (3 Σ_p m_p)` (the per-value mean over valid pixels) and SSIM is of
//! the premultiplied images `m·x` and `m·y`, as MoSca's `compute_rgb_loss` does. (Shape of
//! Motion composites both images over the background instead; the two agree where m = 1.)
//! At |x − y| = 0 the L1 subgradient used is 0.

use crate::metrics::ssim_grad::{SsimPadding, ssim_with_grad};

/// How L1 and SSIM combine into L_rgb.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RgbForm {
    /// `(1 − λ)·L1 + λ·(1 − SSIM)` with L1 the mean over values (3DGS, Shape of Motion:
    /// λ = 0.2).
    Blend,
    /// `L1 + λ·(1 − SSIM)` with L1 summed over the three channels and averaged over valid
    /// pixels, i.e. 3× the per-value mean (MoSca's `compute_rgb_loss`, the release: λ = 0.1).
    Additive,
}

/// The parts of one frame's colour loss.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RgbLoss {
    /// Per-value mean L1 over valid pixels.
    pub l1: f64,
    /// Mean SSIM of the (premultiplied) images.
    pub ssim: f64,
    /// L_rgb in the chosen form.
    pub value: f64,
}

/// Per-value mean L1 `Σ m|x − y| / (3 Σ m)` of `x` against `y` (`[H, W, 3]`) with valid
/// weights `valid` `[H, W]` (None = all ones); with `grad = Some((g, scale))` adds
/// `scale · dL1/dx` to `g` (`[H, W, 3]`). Zero (and no gradient) when no pixel is valid.
pub fn l1_with_grad(
    x: &[f32],
    y: &[f32],
    valid: Option<&[f32]>,
    grad: Option<(&mut [f32], f64)>,
) -> f64 {
    assert_eq!(x.len(), y.len(), "images differ in size");
    let n = x.len() / 3;
    let weight = |p: usize| valid.map_or(1.0, |m| m[p] as f64);
    let (mut sum, mut total_w) = (0.0f64, 0.0f64);
    for p in 0..n {
        let m = weight(p);
        total_w += m;
        for c in 0..3 {
            sum += m * (x[3 * p + c] as f64 - y[3 * p + c] as f64).abs();
        }
    }
    if total_w <= 0.0 {
        return 0.0;
    }
    let norm = 1.0 / (3.0 * total_w);
    if let Some((g, scale)) = grad {
        for p in 0..n {
            let k = scale * norm * weight(p);
            for c in 0..3 {
                let d = x[3 * p + c] - y[3 * p + c];
                if d != 0.0 {
                    g[3 * p + c] += (k * d.signum() as f64) as f32;
                }
            }
        }
    }
    sum * norm
}

/// L_rgb of the rendered colour `x` against the ground truth `y` (`[H, W, 3]`, W×H pixels)
/// in `form` with SSIM weight `lambda`; with `grad = Some((g, scale))` adds
/// `scale · dL_rgb/dx` to `g` (`[H, W, 3]`).
pub fn rgb_with_grad(
    x: &[f32],
    y: &[f32],
    (w, h): (usize, usize),
    valid: Option<&[f32]>,
    form: RgbForm,
    lambda: f64,
    padding: SsimPadding,
    mut grad: Option<(&mut [f32], f64)>,
) -> Result<RgbLoss, crate::metrics::Error> {
    let l1_factor = match form {
        RgbForm::Blend => 1.0 - lambda,
        RgbForm::Additive => 3.0,
    };
    let scale = grad.as_ref().map_or(0.0, |(_, s)| *s);
    let l1 = l1_with_grad(x, y, valid, grad.as_mut().map(|(g, _)| (&mut **g, scale * l1_factor)));
    let ssim = match valid {
        None => ssim_with_grad(x, y, w, h, 3, padding, grad.map(|(g, _)| (g, -scale * lambda)))?,
        Some(m) => {
            let pre = |img: &[f32]| -> Vec<f32> {
                img.chunks_exact(3)
                    .zip(m)
                    .flat_map(|(px, m)| px.iter().map(move |v| v * m))
                    .collect()
            };
            match grad {
                None => ssim_with_grad(&pre(x), &pre(y), w, h, 3, padding, None)?,
                Some((g, _)) => {
                    // d/dx of SSIM(m·x) = m · (dSSIM/d(m·x)).
                    let mut gs = vec![0.0f32; x.len()];
                    let s = ssim_with_grad(
                        &pre(x),
                        &pre(y),
                        w,
                        h,
                        3,
                        padding,
                        Some((&mut gs, -scale * lambda)),
                    )?;
                    for ((o, v), m) in g.chunks_exact_mut(3).zip(gs.chunks_exact(3)).zip(m) {
                        for c in 0..3 {
                            o[c] += m * v[c];
                        }
                    }
                    s
                }
            }
        }
    };
    Ok(RgbLoss { l1, ssim, value: l1_factor * l1 + lambda * (1.0 - ssim) })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::optimize::image_loss::fd::{Check, noise};

    /// Central differences of L_rgb in both forms, with and without a valid map, on a
    /// 12×11 image (1/1024 steps on a 1/4096 grid: exact in f32; no value sits at a kink
    /// of |x − y| since x and y are independent draws kept ≥ 2 steps apart).
    #[test]
    fn rgb_gradient_matches_finite_differences() {
        let (w, h) = (12, 11);
        let x = noise(w * h * 3, 21);
        let y: Vec<f32> = noise(w * h * 3, 22)
            .iter()
            .zip(&x)
            .map(|(q, p)| if (q - p).abs() < 4.0 / 1024.0 { (p + 0.25) % 1.0 } else { *q })
            .collect();
        let valid: Vec<f32> = (0..w * h).map(|i| [1.0, 0.5, 0.0, 1.0][i % 4]).collect();
        let mut check = Check::new("rgb", 1e-6, 2e-3);
        for (form, lambda, padding) in
            [(RgbForm::Blend, 0.2, SsimPadding::Valid), (RgbForm::Additive, 0.1, SsimPadding::Same)]
        {
            for mask in [None, Some(&valid[..])] {
                let loss = |v: &[f32]| {
                    rgb_with_grad(v, &y, (w, h), mask, form, lambda, padding, None).unwrap().value
                };
                let mut g = vec![0.0f32; x.len()];
                rgb_with_grad(&x, &y, (w, h), mask, form, lambda, padding, Some((&mut g, 1.0)))
                    .unwrap();
                let case = format!("{form:?} mask={}", mask.is_some());
                check.image(&case, &x, &g, 1.0 / 1024.0, loss, 5);
            }
        }
        check.finish();
    }

    #[test]
    fn forms_combine_as_documented() {
        let (w, h) = (11, 11);
        let x = noise(w * h * 3, 1);
        let y = noise(w * h * 3, 2);
        let p = SsimPadding::Same;
        let b = rgb_with_grad(&x, &y, (w, h), None, RgbForm::Blend, 0.2, p, None).unwrap();
        let a = rgb_with_grad(&x, &y, (w, h), None, RgbForm::Additive, 0.1, p, None).unwrap();
        assert_eq!((a.l1, a.ssim), (b.l1, b.ssim));
        assert!((b.value - (0.8 * b.l1 + 0.2 * (1.0 - b.ssim))).abs() < 1e-15);
        assert!((a.value - (3.0 * a.l1 + 0.1 * (1.0 - a.ssim))).abs() < 1e-15);
        let direct: f64 =
            x.iter().zip(&y).map(|(p, q)| (p - q).abs() as f64).sum::<f64>() / x.len() as f64;
        assert!((b.l1 - direct).abs() < 1e-12);
    }

    #[test]
    fn invalid_pixels_do_not_matter() {
        let (w, h) = (12, 12);
        let x = noise(w * h * 3, 3);
        let y = noise(w * h * 3, 4);
        let valid: Vec<f32> = (0..w * h).map(|i| if i % w < 6 { 1.0 } else { 0.0 }).collect();
        let mut x2 = x.clone();
        for p in 0..w * h {
            if valid[p] == 0.0 {
                x2[3 * p] = 1.0 - x2[3 * p];
            }
        }
        let run = |v: &[f32]| {
            let mut g = vec![0.0f32; v.len()];
            let l = rgb_with_grad(
                v,
                &y,
                (w, h),
                Some(&valid),
                RgbForm::Additive,
                0.1,
                SsimPadding::Same,
                Some((&mut g, 1.0)),
            )
            .unwrap();
            (l, g)
        };
        let ((l1, g1), (l2, g2)) = (run(&x), run(&x2));
        assert_eq!(l1, l2);
        assert_eq!(g1, g2);
        assert!((0..w * h).filter(|p| valid[*p] == 0.0).all(|p| g1[3 * p..3 * p + 3] == [0.0; 3]));
    }
}
